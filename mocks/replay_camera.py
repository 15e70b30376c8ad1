"""A camera that serves the frames of a recording (twin-rendered or captured).

It implements the same :class:`~gearscan.acquisition.camera.Camera` protocol as the
hardware drivers, so the live pipeline runs unchanged on a recording:

- ``trigger="free-run"``: frames come at the recorded timing (``speed`` x real time), or
  as fast as the consumer takes them with ``realtime=False`` (then nothing is dropped:
  the producer waits for room in the bounded pool).
- ``trigger="software"``: each ``software_trigger()`` releases exactly the next frame.

Frames keep their recorded pattern index, exposure, bit depth and encoder angle; the host
timestamp is the replay time, so latency measurements downstream stay meaningful. Frame ids
are the recorded ids extended past the recorded counter's wraps (a 16-bit GigE 65535, 1 is
served as 65535, 65536; :attr:`RecordingReader.extended_ids`), so every id downstream is unique
and increasing whatever the camera's counter width. A damaged frame (unreadable, wrong
format) is skipped at once: the reader reports it, and the burst assembler sees the id gap.
"""

from __future__ import annotations

import dataclasses
import queue
import threading
import time
from pathlib import Path

from gearscan.acquisition.camera import (
    BaseCamera,
    CameraError,
    CameraInfo,
    CameraSettings,
    RawFrame,
)
from gearscan.core.recording import FrameDamaged, RecordingReader
from gearscan.core.types import Frame


class ReplayCamera(BaseCamera):
    driver = "replay"

    def __init__(self, recording: str | Path | RecordingReader, *, realtime: bool = True, speed: float = 1.0, loop: bool = False):
        super().__init__()
        if speed <= 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        self.reader = recording if isinstance(recording, RecordingReader) else RecordingReader(recording)
        self.realtime = realtime
        self.speed = speed
        self.loop = loop
        cam = self.reader.meta.get("camera", {}) if isinstance(self.reader.meta.get("camera"), dict) else {}
        self.info = CameraInfo(
            id=str(self.reader.path),
            vendor="gearscan",
            model="replay",
            serial=str(cam.get("serial", "")),
            address=str(self.reader.path),
            driver="replay",
        )
        self.dropped = 0  # frames a slow consumer missed in realtime mode
        self.exhausted = threading.Event()
        self._queue: queue.Queue[Frame] | None = None
        self._triggers = threading.Semaphore(0)
        self._stop_evt = threading.Event()
        self._thread: threading.Thread | None = None
        self._next = 0
        self._loops = 0
        recs = self.reader.records
        ids = self.reader.extended_ids
        # a looping replay keeps ids and device times increasing, as a real camera would
        self._id_period = (max(ids) - min(ids) + 1) if ids else 1
        self.skipped = 0  # damaged frames left out
        step = (recs[-1].timestamp_ns - recs[-2].timestamp_ns) if len(recs) > 1 else 0
        self._time_period = (recs[-1].timestamp_ns - recs[0].timestamp_ns + step) if recs else 0

    def open(self) -> None:
        if len(self.reader) == 0:
            raise CameraError(f"recording {self.reader.path} holds no frames")

    def close(self) -> None:
        self.stop()

    def _apply(self, settings: CameraSettings) -> None:
        if settings.trigger == "hardware":
            raise CameraError("camera.trigger: the replay camera has no hardware trigger line; use 'free-run' or 'software'")

    def _start(self) -> None:
        self._queue = queue.Queue(maxsize=self.settings.buffer_count)
        self._stop_evt.clear()
        self.exhausted.clear()
        self._thread = threading.Thread(target=self._produce, name="replay camera", daemon=True)
        self._thread.start()

    def _stop(self) -> None:
        self._stop_evt.set()
        self._triggers.release()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._thread = None

    def software_trigger(self) -> None:
        if self.settings.trigger != "software":
            raise CameraError(f"software_trigger() needs camera.trigger = 'software', it is {self.settings.trigger!r}")
        self._triggers.release()

    def _produce(self) -> None:
        assert self._queue is not None
        n = len(self.reader)
        t_start = time.monotonic_ns()
        rec_t0 = self.reader.records[self._next % n].timestamp_ns
        need_trigger = True  # a trigger that met a damaged frame releases the next one
        while not self._stop_evt.is_set():
            if self._next >= n:
                if not self.loop:
                    self.exhausted.set()
                    return
                self._next = 0
                self._loops += 1
                t_start, rec_t0 = time.monotonic_ns(), self.reader.records[0].timestamp_ns
            if self.settings.trigger == "software" and need_trigger:
                self._triggers.acquire()
                if self._stop_evt.is_set():
                    return
            elif self.realtime:
                due = t_start + (self.reader.records[self._next].timestamp_ns - rec_t0) / self.speed
                wait = (due - time.monotonic_ns()) / 1e9
                if wait > 0 and self._stop_evt.wait(wait):
                    return
            k = self._next
            self._next += 1
            try:
                frame = self.reader.frame(k)
            except FrameDamaged:  # reported by the reader; a camera would have dropped it
                self.skipped += 1
                need_trigger = False
                continue
            need_trigger = True
            frame = dataclasses.replace(
                frame,
                host_timestamp_ns=time.monotonic_ns(),
                frame_id=self.reader.extended_ids[k] + self._loops * self._id_period,
                timestamp_ns=frame.timestamp_ns + self._loops * self._time_period,
            )
            if self.realtime or self.settings.trigger == "software":
                while True:  # a camera does not wait for its consumer: drop the oldest
                    try:
                        self._queue.put_nowait(frame)
                        break
                    except queue.Full:
                        try:
                            self._queue.get_nowait()
                            self.dropped += 1
                        except queue.Empty:
                            pass  # consumer took it meanwhile; retry the put
            else:
                while not self._stop_evt.is_set():
                    try:
                        self._queue.put(frame, timeout=0.1)
                        break
                    except queue.Full:
                        continue

    def _pop(self, timeout: float) -> RawFrame | None:
        raise NotImplementedError  # grab/try_grab are overridden: recorded metadata is kept

    def _get(self, timeout: float) -> Frame | None:
        """Next frame within ``timeout`` s; None at once when the recording is served out."""
        if not self._streaming or self._queue is None:
            raise CameraError("replay camera: grab() before start()")
        deadline = time.monotonic() + timeout
        while True:
            try:
                frame = self._queue.get(timeout=min(0.05, max(deadline - time.monotonic(), 0.0)))
                break
            except queue.Empty:
                # the producer sets `exhausted` after its last put: nothing more will come
                if time.monotonic() >= deadline or (self.exhausted.is_set() and self._queue.empty()):
                    return None
        self._track_id(frame.frame_id)
        self.stats.frames += 1
        return frame

    def grab(self, timeout: float = 1.0) -> Frame:
        from gearscan.acquisition.camera import GrabTimeout

        frame = self._get(timeout)
        if frame is None:
            self.stats.timeouts += 1
            if self.exhausted.is_set():
                raise GrabTimeout(f"replay of {self.reader.path}: all {len(self.reader)} frames served")
            raise GrabTimeout(f"replay camera: no frame within {timeout:g} s (trigger mode {self.settings.trigger!r})")
        return frame

    def try_grab(self) -> Frame | None:
        return self._get(0.0)
