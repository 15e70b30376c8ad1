"""Device clock -> host clock mapping (offset and drift), shared by cameras and the encoder.

Every device stamps its events in its own clock; the pipeline works in the host's
``time.monotonic_ns``. Each received message gives a pair (device time of the event,
host time of arrival). Arrival = event + transfer latency, latency >= some minimum and
jittery, so the mapping is fitted as

    host = host0 + slope * (device - device0) + offset

with ``slope`` (1 + drift) and ``offset`` from the LOWER envelope of the window's pairs: the
line below every pair that is highest at the window's middle (the linear-programming clock-skew
estimate, Moon, Skelly & Towsley 1999), i.e. the edge of the pairs' lower convex hull above the
middle. Only the fastest messages define it: a reader that falls behind for a while (a loaded
machine: every line of a quarter second arrives milliseconds late) sits above the envelope and
never tilts or lifts the mapping, and only the constant minimum latency remains as a bias.
"""

from __future__ import annotations

from collections import deque

import numpy as np


class ClockSync:
    """Sliding-window fit of host time as a linear function of device time (both ns).

    ``min_span_ns``: the drift is only estimated once the window spans this much device time
    (shorter spans give noisy slopes); before that the slope is 1.
    """

    def __init__(self, window: int = 512, min_span_ns: int = 500_000_000, refit_every: int = 16):
        if window < 2:
            raise ValueError(f"window must be >= 2 samples, got {window}")
        self._pairs: deque[tuple[int, int]] = deque(maxlen=window)
        self.min_span_ns = int(min_span_ns)
        self.refit_every = max(1, int(refit_every))
        self._since_fit = 0
        self._device0 = 0
        self._host0 = 0
        self.slope = 1.0
        self.offset_ns = 0.0
        self._fitted = False

    def __len__(self) -> int:
        return len(self._pairs)

    def reset(self) -> None:
        """Forget all pairs (after a device reconnect its clock may have restarted)."""
        self._pairs.clear()
        self._fitted = False
        self.slope = 1.0
        self.offset_ns = 0.0

    def add(self, device_ns: int, host_ns: int) -> None:
        self._pairs.append((int(device_ns), int(host_ns)))
        self._since_fit += 1
        if not self._fitted or self._since_fit >= self.refit_every or len(self._pairs) < 32:
            self.fit()

    @property
    def drift_ppm(self) -> float:
        """Host ns per device ns minus one, in ppm (negative: the device clock runs fast)."""
        return (self.slope - 1.0) * 1e6

    def fit(self) -> None:
        if not self._pairs:
            return
        arr = np.asarray(self._pairs, dtype=np.int64)
        self._device0, self._host0 = int(arr[0, 0]), int(arr[0, 1])
        x = (arr[:, 0] - self._device0).astype(np.float64)
        y = (arr[:, 1] - self._host0).astype(np.float64)
        slope = 1.0
        if x.max() - x.min() >= self.min_span_ns and len(x) >= 16:
            slope = 1.0 + _envelope_slope(x, y - x)
        self.slope = slope
        self.offset_ns = float(np.min(y - slope * x))
        self._fitted = True
        self._since_fit = 0

    def to_device(self, host_ns: int) -> int:
        """Inverse of :meth:`to_host`."""
        if not self._fitted:
            return int(host_ns)
        return self._device0 + int(round((int(host_ns) - self._host0 - self.offset_ns) / self.slope))

    def to_host(self, device_ns: int) -> int:
        """Host time (ns) of a device-clock instant; identity before the first pair."""
        if not self._fitted:
            return int(device_ns)
        return self._host0 + int(round(self.slope * (int(device_ns) - self._device0) + self.offset_ns))


def _envelope_slope(x: np.ndarray, r: np.ndarray, bins: int = 64) -> float:
    """Slope of the lower convex hull of ``(x, r)`` at the middle of ``x`` (``x`` ascending).

    A stall that covers the middle of the window (over half of it) still tilts it.

    The hull is built on the lowest pair of each of ``bins`` consecutive groups (a late pair is
    never a hull vertex, so nothing is lost but cost).
    """
    groups = np.array_split(np.arange(len(x)), min(bins, len(x)))
    pick = np.array([g[np.argmin(r[g])] for g in groups if len(g)])
    hull: list[int] = []  # Andrew's monotone chain, lower part
    for i in pick:
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            if (x[b] - x[a]) * (r[i] - r[a]) - (r[b] - r[a]) * (x[i] - x[a]) <= 0:
                hull.pop()  # b is on or above the segment a-i
            else:
                break
        hull.append(int(i))
    if len(hull) < 2:
        return 0.0
    mid = 0.5 * (x[0] + x[-1])
    for a, b in zip(hull, hull[1:], strict=False):
        if x[b] >= mid and x[b] > x[a]:
            return float((r[b] - r[a]) / (x[b] - x[a]))
    return 0.0
