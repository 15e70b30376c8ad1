"""Device clock -> host clock mapping (offset and drift), shared by cameras and the encoder.

Every device stamps its events in its own clock; the pipeline works in the host's
``time.monotonic_ns``. Each received message gives a pair (device time of the event,
host time of arrival). Arrival = event + transfer latency, latency >= some minimum and
jittery, so the mapping is fitted as

    host = host0 + slope * (device - device0) + offset

with ``slope`` (1 + drift) from a least-squares line through the fastest message of each of
8 time bins of a sliding window, and ``offset`` put on the LOWER envelope of the residuals: the fastest message of the window defines the
latency floor. That is robust to latency spikes (a delayed line never pulls the mapping
late), and only the constant minimum latency remains as a bias.
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
            # slope through the fastest message of each of 8 time bins: latency varies
            # (a reader that falls behind reads lines late), the floor does not
            r = y - x
            bins = np.array_split(np.arange(len(x)), 8)
            pick = np.array([b[np.argmin(r[b])] for b in bins])
            xs, ys = x[pick], y[pick]
            xm, ym = xs.mean(), ys.mean()
            slope = float(np.dot(xs - xm, ys - ym) / np.dot(xs - xm, xs - xm))
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
