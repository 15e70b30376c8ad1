"""V4L2 cameras (USB UVC, MIPI, frame grabbers) with the same semantics as the Aravis driver.

Two layers, as in linuxpy: a raw backend (:class:`V4L2Backend`: open, formats, set_format,
buffers, dequeue with timeout) and the friendly :class:`V4L2Camera` that negotiates the
format, checks what the driver granted, tracks sequence numbers and raises the common
errors (:class:`GrabTimeout`, :class:`CameraDisconnected`, :class:`CameraConfigError`).

:class:`LinuxpyBackend` talks to ``/dev/videoN`` through linuxpy (imported lazily). The
machines this was built on have no V4L2 device at all (no /dev/video*, no vivid or
v4l2loopback), so the camera logic is tested against :class:`gearscan.mocks.v4l2_backend.FakeV4L2Backend`, and the
linuxpy path is for real machines.

V4L2 buffer timestamps are CLOCK_MONOTONIC (``V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC``), the
host clock itself, so no clock mapping is fitted. Sequence numbers are 32-bit.
"""

from __future__ import annotations

import errno
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from gearscan.acquisition.camera import (
    PIXEL_FORMATS,
    BaseCamera,
    CameraConfigError,
    CameraDisconnected,
    CameraError,
    CameraInfo,
    CameraNotFound,
    CameraSettings,
    RawFrame,
)

#: GenICam pixel format -> V4L2 fourcc (grey formats, 16-bit little-endian containers).
FOURCC = {"Mono8": "GREY", "Mono10": "Y10 ", "Mono12": "Y12 ", "Mono14": "Y14 ", "Mono16": "Y16 "}


@dataclass(frozen=True, slots=True)
class V4L2Buffer:
    data: bytes | memoryview
    sequence: int
    timestamp_ns: int  # CLOCK_MONOTONIC
    width: int
    height: int
    bytes_per_line: int
    error: bool = False  # V4L2_BUF_FLAG_ERROR: data may be corrupt


class V4L2Backend(Protocol):
    """Raw device layer (one per /dev/videoN)."""

    def open(self) -> None: ...
    def close(self) -> None: ...
    def info(self) -> dict[str, str]: ...  # driver, card, bus_info
    def formats(self) -> list[str]: ...  # fourccs
    def set_format(self, width: int, height: int, fourcc: str) -> tuple[int, int, str, int]: ...
    def set_exposure_us(self, exposure_us: float) -> float: ...  # returns value granted
    def set_frame_rate(self, fps: float) -> float: ...
    def start(self, n_buffers: int) -> int: ...  # returns buffers granted
    def stop(self) -> None: ...
    def dequeue(self, timeout: float) -> V4L2Buffer | None: ...  # None on timeout; OSError(ENODEV) if gone


class V4L2Camera(BaseCamera):
    driver = "v4l2"
    frame_id_modulus = 1 << 32
    timestamps_are_host = True

    def __init__(self, path: str = "/dev/video0", backend: V4L2Backend | None = None):
        super().__init__()
        self.path = path
        self._backend = backend
        self.info = CameraInfo(id=path, vendor="", model="", serial="", address=path, driver="v4l2")
        self.granted: dict[str, object] = {}
        self._bits = 8
        self._dtype: type = np.uint8
        self._size = (0, 0)

    def open(self) -> None:
        if self._backend is None:
            if not Path(self.path).exists():
                found = [c.id for c in list_v4l2_devices()]
                raise CameraNotFound(f"camera.id: {self.path!r} not found; V4L2 devices: {found or 'none'}")
            self._backend = LinuxpyBackend(self.path)
        try:
            self._backend.open()
        except OSError as exc:
            raise CameraError(f"camera {self.path}: cannot open ({exc.strerror or exc})") from exc
        i = self._backend.info()
        self.info = CameraInfo(id=self.path, vendor=i.get("driver", ""), model=i.get("card", ""), serial="", address=i.get("bus_info", ""), driver="v4l2")

    def close(self) -> None:
        if self._backend is not None:
            self.stop()
            self._backend.close()

    def _apply(self, s: CameraSettings) -> None:
        b = self._require()
        fourcc = FOURCC[s.pixel_format]
        offered = b.formats()
        if fourcc not in offered:
            mono = [k for k, v in FOURCC.items() if v in offered]
            raise CameraConfigError(
                f"camera.pixel_format: {s.pixel_format!r} (V4L2 {fourcc.strip()!r}) not offered by {self.path} "
                f"({self.info.model}); it offers {mono} (all fourccs: {offered})"
            )
        if s.roi is not None and (s.roi[0] or s.roi[1]):
            raise CameraConfigError(f"camera.roi: offsets need V4L2 crop support, which this driver does not use; got {s.roi}")
        w, h = (s.roi[2], s.roi[3]) if s.roi is not None else (0, 0)
        gw, gh, gfour, bpl = b.set_format(w, h, fourcc)
        if gfour != fourcc:
            raise CameraConfigError(f"camera.pixel_format: asked {fourcc!r}, driver set {gfour!r}")
        if s.roi is not None and (gw, gh) != (w, h):
            raise CameraConfigError(f"camera.roi: driver adjusted {w}x{h} to {gw}x{gh}; use a size it supports")
        self._dtype, self._bits = PIXEL_FORMATS[s.pixel_format]
        if bpl < gw * np.dtype(self._dtype).itemsize:
            raise CameraError(f"camera {self.path}: bytes per line {bpl} < width {gw} x {np.dtype(self._dtype).itemsize}")
        self._size = (gw, gh)
        self.granted = {"width": gw, "height": gh, "fourcc": gfour, "bytes_per_line": bpl}
        try:
            self.granted["exposure_us"] = b.set_exposure_us(s.exposure_us)
            if s.frame_rate_hz is not None:
                self.granted["frame_rate_hz"] = b.set_frame_rate(s.frame_rate_hz)
        except OSError as exc:
            raise CameraConfigError(f"camera.exposure_us / frame_rate_hz: rejected by {self.path} ({exc})") from exc
        if s.trigger != "free-run":
            raise CameraConfigError(f"camera.trigger: V4L2 has no standard trigger control; only 'free-run', got {s.trigger!r}")

    def _require(self) -> V4L2Backend:
        if self._backend is None:
            raise CameraError(f"v4l2 camera {self.path} is not open (use it as a context manager)")
        return self._backend

    def _start(self) -> None:
        granted = self._require().start(self.settings.buffer_count)
        self.granted["buffers"] = granted

    def _stop(self) -> None:
        self._require().stop()

    def _pop(self, timeout: float) -> RawFrame | None:
        deadline = time.monotonic() + timeout
        while True:
            try:
                buf = self._require().dequeue(max(0.0, deadline - time.monotonic()))
            except OSError as exc:
                if exc.errno in (errno.ENODEV, errno.EIO, errno.ENXIO):
                    raise CameraDisconnected(f"camera {self.path} disappeared ({exc.strerror}); call reconnect()") from exc
                raise CameraError(f"camera {self.path}: dequeue failed ({exc})") from exc
            if buf is None:
                return None
            if buf.error:
                self.stats.incomplete += 1
                continue
            w, h = buf.width, buf.height
            item = np.dtype(self._dtype).itemsize
            rows = np.frombuffer(buf.data, dtype=np.uint8, count=buf.bytes_per_line * h).reshape(h, buf.bytes_per_line)
            image = rows[:, : w * item].copy().view(self._dtype).reshape(h, w)
            return RawFrame(image, buf.sequence, buf.timestamp_ns, time.monotonic_ns(), self._bits)

    def reconnect(self, timeout: float = 10.0, poll: float = 0.2) -> None:
        deadline = time.monotonic() + timeout
        was = self._streaming
        self._streaming = False
        last: Exception | None = None
        while time.monotonic() < deadline:
            try:
                self._require().close()
                self.open()
                self._apply(self.settings)
                if was:
                    self.start()
                return
            except (CameraError, OSError) as exc:
                last = exc
                time.sleep(poll)
        raise CameraDisconnected(f"camera {self.path} did not come back within {timeout:g} s ({last})")


def list_v4l2_devices() -> list[CameraInfo]:
    """Capture devices under /dev/video* (names from sysfs; no linuxpy needed)."""
    out = []
    for dev in sorted(Path("/dev").glob("video*")):
        name = Path(f"/sys/class/video4linux/{dev.name}/name")
        model = name.read_text().strip() if name.exists() else ""
        out.append(CameraInfo(id=str(dev), vendor="", model=model, serial="", address=str(dev), driver="v4l2"))
    return out


class LinuxpyBackend:
    """Real /dev/videoN through linuxpy (MMAP buffers, select-based dequeue)."""

    def __init__(self, path: str):
        self.path = path
        self._dev = None
        self._capture = None
        self._frames: queue.Queue = queue.Queue(maxsize=1)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._error: OSError | None = None

    def open(self) -> None:
        from linuxpy.video.device import Device

        self._dev = Device(self.path)
        self._dev.open()

    def close(self) -> None:
        if self._dev is not None:
            self._dev.close()
            self._dev = None

    def info(self) -> dict[str, str]:
        i = self._dev.info
        return {"driver": i.driver, "card": i.card, "bus_info": i.bus_info}

    def formats(self) -> list[str]:
        from linuxpy.video.device import BufferType

        out = []
        for f in self._dev.info.formats:
            if f.type == BufferType.VIDEO_CAPTURE:
                code = int(f.pixel_format)
                out.append("".join(chr((code >> (8 * k)) & 0xFF) for k in range(4)))
        return out

    def set_format(self, width: int, height: int, fourcc: str) -> tuple[int, int, str, int]:
        from linuxpy.video.device import BufferType

        cur = self._dev.get_format(BufferType.VIDEO_CAPTURE)
        self._dev.set_format(BufferType.VIDEO_CAPTURE, width or cur.width, height or cur.height, fourcc)
        f = self._dev.get_format(BufferType.VIDEO_CAPTURE)
        code = int(f.pixel_format)
        return f.width, f.height, "".join(chr((code >> (8 * k)) & 0xFF) for k in range(4)), f.bytes_per_line

    def set_exposure_us(self, exposure_us: float) -> float:
        ctrls = self._dev.controls
        if "exposure_time_absolute" in ctrls:  # 100 us units (V4L2_CID_EXPOSURE_ABSOLUTE)
            if "auto_exposure" in ctrls:
                ctrls["auto_exposure"].value = 1  # manual mode
            ctrls["exposure_time_absolute"].value = int(round(exposure_us / 100))
            return ctrls["exposure_time_absolute"].value * 100.0
        return float("nan")

    def set_frame_rate(self, fps: float) -> float:
        from linuxpy.video.device import BufferType

        self._dev.set_fps(BufferType.VIDEO_CAPTURE, fps)
        return float(self._dev.get_fps(BufferType.VIDEO_CAPTURE))

    def start(self, n_buffers: int) -> int:
        from linuxpy.video.device import VideoCapture

        self._frames = queue.Queue(maxsize=n_buffers)
        self._capture = VideoCapture(self._dev, size=n_buffers)
        self._stop.clear()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()
        return n_buffers

    def _read(self) -> None:
        try:
            with self._capture as stream:
                for frame in stream:
                    if self._stop.is_set():
                        return
                    f = self._capture.get_format()
                    buf = V4L2Buffer(
                        bytes(frame.data), int(frame.frame_nb), int(frame.timestamp * 1e9), frame.width, frame.height,
                        f.bytes_per_line, error=bool(int(frame.flags) & 0x40),
                    )
                    try:
                        self._frames.put_nowait(buf)
                    except queue.Full:  # consumer behind: drop the oldest, like the hardware does
                        self._frames.get_nowait()
                        self._frames.put_nowait(buf)
        except OSError as exc:
            self._error = exc

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._thread = None

    def dequeue(self, timeout: float) -> V4L2Buffer | None:
        if self._error is not None:
            raise self._error
        try:
            return self._frames.get(timeout=timeout) if timeout > 0 else self._frames.get_nowait()
        except queue.Empty:
            return None
