"""A scripted V4L2 device (no V4L2 device exists on CI machines): formats, size rounding, sequence gaps, unplug."""

from __future__ import annotations

import errno
import time
from dataclasses import dataclass, field

import numpy as np

from gearscan.acquisition.v4l2 import V4L2Buffer


@dataclass
class FakeV4L2Backend:
    """A scripted V4L2 device for tests: formats, size rounding, sequence gaps, unplug.

    ``frames()`` yields the images served; ``skip_sequences`` are sequence numbers the
    "driver" drops (frame-id gaps), ``error_sequences`` come flagged V4L2_BUF_FLAG_ERROR,
    ``unplug_after`` makes dequeue raise ENODEV after that many buffers.
    """

    offered: tuple[str, ...] = ("YUYV", "GREY", "Y12 ")
    max_size: tuple[int, int] = (1280, 960)
    width_step: int = 16
    padding: int = 32  # extra bytes per line, like many drivers
    skip_sequences: set[int] = field(default_factory=set)
    error_sequences: set[int] = field(default_factory=set)
    unplug_after: int | None = None
    fps: float = 500.0
    opened: int = 0
    streaming: bool = False
    _fmt: tuple[int, int, str] = (640, 480, "YUYV")
    _seq: int = 0
    _served: int = 0
    _t0: int = 0

    def open(self) -> None:
        self.opened += 1

    def close(self) -> None:
        self.streaming = False

    def info(self) -> dict[str, str]:
        return {"driver": "fakev4l2", "card": "Fake Mono Cam", "bus_info": "platform:fake"}

    def formats(self) -> list[str]:
        return list(self.offered)

    def set_format(self, width: int, height: int, fourcc: str) -> tuple[int, int, str, int]:
        w = min(width or self._fmt[0], self.max_size[0]) // self.width_step * self.width_step
        h = min(height or self._fmt[1], self.max_size[1])
        f = fourcc if fourcc in self.offered else self.offered[0]
        self._fmt = (w, h, f)
        return w, h, f, self._bpl()

    def _bpl(self) -> int:
        return self._fmt[0] * (1 if self._fmt[2] == "GREY" else 2) + self.padding

    def set_exposure_us(self, exposure_us: float) -> float:
        return round(exposure_us / 100) * 100.0

    def set_frame_rate(self, fps: float) -> float:
        self.fps = fps
        return fps

    def start(self, n_buffers: int) -> int:
        self.streaming = True
        self._t0 = time.monotonic_ns()
        return min(n_buffers, 32)

    def stop(self) -> None:
        self.streaming = False

    @staticmethod
    def image(seq: int, w: int, h: int, fourcc: str) -> np.ndarray:
        y, x = np.mgrid[0:h, 0:w]
        if fourcc == "Y12 ":
            return ((x * 7 + y * 3 + seq) % 4096).astype(np.uint16)
        return ((x + y + seq) % 256).astype(np.uint8)

    def dequeue(self, timeout: float) -> V4L2Buffer | None:
        if not self.streaming:
            time.sleep(timeout)
            return None
        if self.unplug_after is not None and self._served >= self.unplug_after:
            raise OSError(errno.ENODEV, "No such device")
        while self._seq in self.skip_sequences:
            self._seq += 1
        due = self._t0 + int(self._seq * 1e9 / self.fps)
        wait = (due - time.monotonic_ns()) / 1e9
        if wait > timeout:
            time.sleep(timeout)
            return None
        if wait > 0:
            time.sleep(wait)
        w, h, f = self._fmt
        img = self.image(self._seq, w, h, f)
        rows = np.zeros((h, self._bpl()), np.uint8)
        rows[:, : img.nbytes // h] = img.view(np.uint8).reshape(h, -1)
        buf = V4L2Buffer(rows.tobytes(), self._seq, due, w, h, self._bpl(), error=self._seq in self.error_sequences)
        self._seq += 1
        self._served += 1
        return buf
