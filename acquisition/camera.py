"""The camera interface every driver implements, its settings and its errors.

Modelled on Harvesters/pypylon (bounded buffer pool, fetch with a timeout) and linuxpy
(reentrant context manager, small ``Frame``)::

    with AravisCamera("Aravis-Fake-GS1") as cam:
        cam.configure(CameraSettings(exposure_us=10_000, trigger="software"))
        cam.start()
        cam.software_trigger()
        frame = cam.grab(timeout=1.0)      # raises GrabTimeout, never returns None
        maybe = cam.try_grab()             # None when nothing is ready

A driver implements the ``_``-prefixed hooks of :class:`BaseCamera`; the base class keeps the
bookkeeping every driver shares: the reentrant open count, frame-id gap detection
(``stats.missing_frames``), host-clock mapping of device timestamps and the pattern index.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from dataclasses import dataclass, field
from typing import Literal, Protocol, runtime_checkable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from gearscan.acquisition.clock import ClockSync
from gearscan.core.frame_ids import FrameIdUnwrapper, FrameIdWrap
from gearscan.core.types import Frame

TriggerMode = Literal["free-run", "software", "hardware"]

#: Pixel formats the drivers understand: numpy dtype and significant bits.
PIXEL_FORMATS: dict[str, tuple[type[np.unsignedinteger], int]] = {
    "Mono8": (np.uint8, 8),
    "Mono10": (np.uint16, 10),
    "Mono12": (np.uint16, 12),
    "Mono14": (np.uint16, 14),
    "Mono16": (np.uint16, 16),
}


class CameraError(RuntimeError):
    """Base class of every camera failure."""


class CameraConfigError(CameraError, ValueError):
    """A setting the camera cannot take; the message names the setting and what was found."""


class CameraNotFound(CameraConfigError):
    """No camera with the requested id; the message lists the cameras that were found."""


class GrabTimeout(CameraError, TimeoutError):
    """No frame arrived within the timeout (camera alive, but nothing was triggered or sent)."""


class CameraDisconnected(CameraError):
    """The camera stopped answering (cable pulled, power lost); call ``reconnect``."""


class CameraSettings(BaseModel):
    """What :meth:`Camera.configure` applies. Times in microseconds, gain in dB.

    ``roi`` is ``(x, y, width, height)`` in sensor pixels (None = driver default / full).
    ``frame_rate_hz`` applies in free-run only. ``buffer_count`` bounds the driver's buffer
    pool: when the consumer falls behind, the camera drops frames (seen as frame-id gaps)
    instead of memory growing. ``packet_size`` (GigE only): None negotiates the largest
    size the path allows, 0 keeps the camera's value. ``pattern_cycle``: frames of a sequence
    the projector plays by itself (hardware trigger) get pattern ``n % pattern_cycle``, or
    ``pattern_sequence[n % pattern_cycle]`` when that gives the patterns in the order played.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # a setting is a finite number

    exposure_us: float = Field(10_000.0, gt=0)
    gain_db: float = Field(0.0, ge=0)
    pixel_format: str = "Mono8"
    roi: tuple[int, int, int, int] | None = None
    frame_rate_hz: float | None = Field(None, gt=0)
    trigger: TriggerMode = "free-run"
    trigger_line: str = "Line0"
    buffer_count: int = Field(8, ge=2, le=256)
    packet_size: int | None = None
    pattern_cycle: int = Field(0, ge=0)
    pattern_sequence: tuple[int, ...] | None = None

    @model_validator(mode="after")
    def _sequence_fits_the_cycle(self) -> CameraSettings:
        seq = self.pattern_sequence
        if seq is not None and (len(seq) != self.pattern_cycle or min(seq, default=0) < 0):
            raise ValueError(f"pattern_sequence: expected {self.pattern_cycle} pattern indices >= 0 "
                             f"(one per frame of the cycle), got {list(seq)}")
        return self

    @field_validator("pixel_format")
    @classmethod
    def _known_format(cls, v: str) -> str:
        if v not in PIXEL_FORMATS:
            raise ValueError(f"pixel_format must be one of {sorted(PIXEL_FORMATS)}, got {v!r}")
        return v

    @field_validator("roi")
    @classmethod
    def _roi_positive(cls, v: tuple[int, int, int, int] | None) -> tuple[int, int, int, int] | None:
        if v is not None and (v[0] < 0 or v[1] < 0 or v[2] <= 0 or v[3] <= 0):
            raise ValueError(f"roi must be (x>=0, y>=0, width>0, height>0), got {v}")
        return v


@dataclass(frozen=True, slots=True)
class CameraInfo:
    """One discovered camera (what ``gearscan devices`` prints)."""

    id: str
    vendor: str
    model: str
    serial: str
    address: str
    driver: str


@dataclass(slots=True)
class CameraStats:
    """Counters a driver keeps while streaming."""

    frames: int = 0
    missing_frames: int = 0  # frame-id gaps: frames the camera took but we never got
    incomplete: int = 0  # buffers that arrived damaged (missing packets, ...) and were dropped
    timeouts: int = 0
    gaps: list[tuple[int, int]] = field(default_factory=list)  # (last id, next id) per gap

    def as_dict(self) -> dict[str, int]:
        return {k: v for k, v in dataclasses.asdict(self).items() if k != "gaps"}


@runtime_checkable
class Camera(Protocol):
    """The interface the pipeline sees; every driver (Aravis, V4L2, replay) provides it."""

    info: CameraInfo
    settings: CameraSettings
    stats: CameraStats

    def __enter__(self) -> Camera: ...
    def __exit__(self, *exc: object) -> None: ...
    def open(self) -> None: ...
    def close(self) -> None: ...
    def configure(self, settings: CameraSettings) -> None: ...
    def start(self) -> None: ...
    def stop(self) -> None: ...
    def software_trigger(self) -> None: ...
    def grab(self, timeout: float = 1.0) -> Frame: ...
    def try_grab(self) -> Frame | None: ...


@dataclass(frozen=True, slots=True)
class RawFrame:
    """What a driver's ``_pop`` hands the base class before bookkeeping."""

    image: np.ndarray
    frame_id: int
    device_timestamp_ns: int
    host_arrival_ns: int  # time.monotonic_ns() when the buffer was received
    bit_depth: int


class BaseCamera:
    """Shared bookkeeping; drivers override the ``_`` hooks.

    ``frame_id_modulus`` handles counters that wrap (GigE Vision v1 block ids are 16-bit and
    skip 0, so 65535 is followed by 1); :attr:`frame_id_wrap` is the rule every consumer of
    this camera's ids uses (:mod:`gearscan.core.frame_ids`).
    """

    driver = "base"
    frame_id_modulus: int | None = None
    frame_id_skips_zero = False
    timestamps_are_host = False  # device stamps in CLOCK_MONOTONIC already (V4L2)

    def __init__(self) -> None:
        self.settings = CameraSettings()
        self.stats = CameraStats()
        self.clock = ClockSync(window=256)
        self._open_count = 0
        self._streaming = False
        self._last_id: int | None = None
        self._ids = FrameIdUnwrapper(self.frame_id_wrap)
        self._first_ext: int | None = None  # extended id of the stream's first frame
        self._lock = threading.RLock()

    # -- context manager (reentrant, like linuxpy devices) -------------------------------
    def __enter__(self):
        with self._lock:
            if self._open_count == 0:
                self.open()
            self._open_count += 1
        return self

    def __exit__(self, *exc: object) -> None:
        with self._lock:
            self._open_count -= 1
            if self._open_count == 0:
                self.close()

    # -- hooks ---------------------------------------------------------------------------
    def open(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def _apply(self, settings: CameraSettings) -> None:
        raise NotImplementedError

    def _start(self) -> None:
        raise NotImplementedError

    def _stop(self) -> None:
        raise NotImplementedError

    def _pop(self, timeout: float) -> RawFrame | None:
        """Wait up to ``timeout`` s for one good buffer; None on timeout."""
        raise NotImplementedError

    def _check_alive(self) -> None:
        """Raise CameraDisconnected when the device no longer answers."""

    def software_trigger(self) -> None:
        raise CameraError(f"{self.driver} camera has no software trigger")

    # -- public API ----------------------------------------------------------------------
    @property
    def frame_id_wrap(self) -> FrameIdWrap:
        """How this camera's frame counter wraps (from ``frame_id_modulus`` and ``frame_id_skips_zero``)."""
        return FrameIdWrap(self.frame_id_modulus, self.frame_id_skips_zero)

    @property
    def streaming(self) -> bool:
        return self._streaming

    def configure(self, settings: CameraSettings) -> None:
        """Apply settings (stops and restarts streaming if needed)."""
        was = self._streaming
        if was:
            self.stop()
        self._apply(settings)
        self.settings = settings
        if was:
            self.start()

    def start(self) -> None:
        if self._streaming:
            return
        self._last_id = None
        self._ids.reset()
        self._first_ext = None
        self._start()
        self._streaming = True

    def stop(self) -> None:
        if not self._streaming:
            return
        self._streaming = False
        self._stop()

    def grab(self, timeout: float = 1.0) -> Frame:
        """Next frame; raises :class:`GrabTimeout` or :class:`CameraDisconnected`."""
        if not self._streaming:
            raise CameraError(f"{self.driver} camera: grab() before start()")
        if timeout < 0:
            raise ValueError(f"timeout must be >= 0 s, got {timeout}")
        raw = self._pop(timeout)
        if raw is None:
            self.stats.timeouts += 1
            self._check_alive()
            raise GrabTimeout(
                f"{self.driver} camera {getattr(self, 'info', None) and self.info.id!s}: no frame within "
                f"{timeout:g} s (trigger mode {self.settings.trigger!r}; was it triggered?)"
            )
        return self._finish(raw)

    def try_grab(self) -> Frame | None:
        """A frame if one is ready now, else None (never blocks)."""
        if not self._streaming:
            raise CameraError(f"{self.driver} camera: try_grab() before start()")
        raw = self._pop(0.0)
        return None if raw is None else self._finish(raw)

    def _finish(self, raw: RawFrame) -> Frame:
        ext = self._track_id(raw.frame_id)
        self.clock.add(raw.device_timestamp_ns, raw.host_arrival_ns)
        cycle = self.settings.pattern_cycle
        pattern = 0
        if cycle and self._first_ext is not None:
            # counted on extended ids: a 2**32 counter is no multiple of 3, its wrap must not shift the cycle
            pattern = (ext - self._first_ext) % cycle
            if self.settings.pattern_sequence is not None:
                pattern = self.settings.pattern_sequence[pattern]
        self.stats.frames += 1
        return Frame(
            image=raw.image,
            frame_id=raw.frame_id,
            timestamp_ns=raw.device_timestamp_ns,
            pattern_index=pattern,
            exposure_us=float(self.settings.exposure_us),
            bit_depth=raw.bit_depth,
            host_timestamp_ns=raw.device_timestamp_ns if self.timestamps_are_host else self.clock.to_host(raw.device_timestamp_ns),
        )

    def _track_id(self, frame_id: int) -> int:
        """Count frame-id gaps (wrap-aware); returns the extended id of ``frame_id``."""
        ext = self._ids(frame_id)
        if self._first_ext is None:
            self._first_ext = ext
        elif self._last_id is not None:
            step = self.frame_id_wrap.step(self._last_id, frame_id)
            if step > 1:
                self.stats.missing_frames += step - 1
                self.stats.gaps.append((self._last_id, frame_id))
        self._last_id = frame_id
        return ext


def host_now_ns() -> int:
    """Host clock every stage uses (monotonic, ns)."""
    return time.monotonic_ns()
