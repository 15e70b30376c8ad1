"""Device -> host clock mapping against a known truth: drift, latency floor, a reader that falls behind."""

from __future__ import annotations

import numpy as np
import pytest

from gearscan.acquisition.clock import ClockSync

DRIFT = 80e-6  # host ns per device ns - 1
FLOOR_NS = 150_000  # minimum transfer latency


def _pairs(rng, n=2000, rate_hz=1000, stall=None):
    device = np.arange(n, dtype=np.int64) * (1_000_000_000 // rate_hz) + 7_000_000_000
    true_host = 3_000_000_000 + (device - device[0]) * (1 + DRIFT)
    latency = FLOOR_NS + rng.exponential(60_000, n)
    if stall is not None:  # every line in [a, b) read late: the reader was starved
        a, b, late_ns = stall
        latency[a:b] += late_ns + rng.uniform(0, late_ns, b - a)
    return device, true_host, true_host + latency


@pytest.mark.parametrize("stall", [None, (1500, 1750, 5_000_000), (0, 250, 8_000_000), (1000, 1300, 20_000_000)])
def test_mapping_stays_on_the_latency_floor(stall):
    rng = np.random.default_rng(3)
    device, true_host, arrival = _pairs(rng, stall=stall)
    clock = ClockSync(window=4096, refit_every=16)
    mapped = np.empty(len(device))
    for i, (d, h) in enumerate(zip(device, arrival, strict=True)):
        clock.add(int(d), int(h))
        mapped[i] = clock.to_host(int(d))
    err = mapped - true_host
    span_ok = device - device[0] >= 600_000_000  # the drift is estimated from 0.5 s of pairs on
    # what remains is the minimum latency (a constant bias) plus a fraction of the jitter, never the stall
    assert np.all(err[span_ok] >= FLOOR_NS - 20_000)
    assert np.percentile(np.abs(err[span_ok] - FLOOR_NS), 99) < 100_000, np.percentile(np.abs(err[span_ok]), 99)
    assert abs(clock.drift_ppm - DRIFT * 1e6) < 30


def test_window_and_reset():
    with pytest.raises(ValueError, match="window"):
        ClockSync(window=1)
    clock = ClockSync()
    assert clock.to_host(123) == 123  # identity before the first pair
    clock.add(1_000, 5_000)
    assert clock.to_host(2_000) == 6_000
    clock.reset()
    assert clock.to_host(2_000) == 2_000
