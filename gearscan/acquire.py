"""The devices of a live configuration (camera, projector, encoder) as one session: bursts, optionally recorded.

This is where the stages meet (acquisition, projector sequencing, the recording format, the replay
camera of mocks/), so it lives in the app.

Frames go through the :class:`BurstAssembler`; only frames of complete, valid bursts are
written, each with its encoder angle at the exposure midpoint, so the recording replays
into exactly the bursts that were measured. Raw encoder samples go to ``encoder.jsonl``.
The writer is closed in ``finally``: Ctrl-C or a pulled cable leaves a readable recording.
"""

from __future__ import annotations

import dataclasses
import queue
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from gearscan.acquisition.bursts import BurstAssembler
from gearscan.acquisition.camera import BaseCamera, CameraError, GrabTimeout
from gearscan.acquisition.config import AcquisitionConfig, ConfigError
from gearscan.acquisition.encoder import EncoderError, EncoderReader
from gearscan.core.types import Burst, EncoderSample, Frame

# A rig without encoder: the gear is taken as standing still at its CAD zero (angle 0), so
# every burst spans 0 deg (three-step PS, which has no motion error on a still gear) and the
# CAD bounds sit at angle 0. A turning gear needs the encoder.
NO_ENCODER_ANGLE = 0.0
NO_ENCODER_REFERENCE = "none: no encoder, the gear taken as still at angle 0"


@dataclass
class RecordSummary:
    out: Path
    bursts: int
    frames: int
    encoder_samples: int
    assembler: dict[str, int]
    camera: dict[str, int]
    encoder: dict[str, int] | None
    seconds: float


def open_camera(cfg: AcquisitionConfig) -> BaseCamera:
    c = cfg.camera
    if c.driver == "aravis":
        from gearscan.acquisition.aravis import AravisCamera

        return AravisCamera(c.id, discovery_attempts=3)
    if c.driver == "replay":
        from gearscan.mocks.replay_camera import ReplayCamera

        if c.id is None:
            raise ConfigError("camera.id: the replay driver needs the recording folder as id (got None)")
        return ReplayCamera(c.id, loop=c.loop)
    from gearscan.acquisition.v4l2 import V4L2Camera

    return V4L2Camera(c.id or "/dev/video0")


def make_projector(cfg: AcquisitionConfig):
    from gearscan.mocks.projector import MockProjector
    from gearscan.projector.sequencer import WindowProjector

    p = cfg.projector
    if p.backend == "mock":
        return MockProjector(width=p.width, height=p.height)
    if p.backend == "window":
        return WindowProjector(display=p.display, width=p.width, height=p.height)
    raise ConfigError(
        "projector.backend: 'lightcrafter' plays its sequence by itself; set camera.trigger = 'hardware' "
        "and camera.pattern_cycle to the sequence's length (3; 6 with projector.alternate_order), and the projector "
        "is not driven by record (got 'lightcrafter' with software trigger)"
    )


class AcquisitionSession:
    """Camera + projector + encoder from a config, yielding assembled bursts (and recording them).

    Use as a context manager; :meth:`bursts` yields :class:`Burst` objects whose frames carry
    the encoder angle at their exposure midpoint. With ``out`` set, every frame of every valid
    burst is written (flushed per frame) before the burst is handed on, so a recording holds
    exactly what was measured, and closing (also on Ctrl-C or a fault) finalises it.
    """

    def __init__(self, cfg: AcquisitionConfig, out: Path | None = None, *, overwrite: bool = False,
                 extra_meta: dict | None = None) -> None:
        self.cfg = cfg
        self.settings = cfg.camera.settings()
        self.patterns = cfg.projector.patterns()
        # one cycle of the projector sequence
        self.order = self.patterns.cycle(cfg.projector.coarse_every, alternate=cfg.projector.alternate_order)
        if self.settings.trigger != "software":  # the projector plays self.order by itself, frame n its n-th entry
            if self.settings.pattern_cycle != len(self.order):
                raise ConfigError(
                    f"camera.pattern_cycle: must be {len(self.order)} with trigger {self.settings.trigger!r}: the "
                    f"projector plays the sequence {self.order} by itself (program it so, starting with the camera's "
                    f"first frame), got {self.settings.pattern_cycle}"
                )
            if self.settings.pattern_sequence not in (None, tuple(self.order)):
                raise ConfigError(
                    f"camera.pattern_sequence: {list(self.settings.pattern_sequence)} is not the sequence the projector "
                    f"section asks for, {self.order}; leave it out (it is taken from [projector])"
                )
            self.settings = self.settings.model_copy(update={"pattern_sequence": tuple(self.order)})
        self.out, self.overwrite, self.extra_meta = out, overwrite, extra_meta or {}
        rig = self.extra_meta.get("rig")  # a recording's rig must fit its frames, or replay refuses it
        self.rig_size = (rig["camera"]["width"], rig["camera"]["height"]) if isinstance(rig, dict) else None
        self._samples: queue.Queue[EncoderSample] = queue.Queue()
        self.encoder = None
        if cfg.encoder is not None:
            self.encoder = EncoderReader(
                cfg.encoder.port,
                cfg.encoder.counts_per_rev,
                baudrate=cfg.encoder.baudrate,
                zero_on_index=cfg.encoder.zero_on_index,
                on_sample=self._samples.put,
            )
        self.camera = open_camera(cfg)
        self.projector = None
        self.writer = None
        self.assembler: BurstAssembler | None = None
        self.frames = self.encoder_samples = self.burst_count = 0  # burst_count: measuring bursts
        self.coarse_bursts = 0  # the coarse bursts between them (projector.coarse_period_px)

    def __enter__(self) -> AcquisitionSession:
        from gearscan.core.recording import RecordingWriter

        cfg = self.cfg
        if self.out is not None:  # before any device wait
            RecordingWriter.check_target(self.out, self.overwrite)
        try:
            self.camera.__enter__()
            self.camera.configure(self.settings)
            self.assembler = BurstAssembler(
                self.encoder.history if self.encoder else None,
                max_encoder_gap_ns=int((cfg.encoder.max_gap_ms if cfg.encoder else 20.0) * 1e6),
                frame_id_modulus=self.camera.frame_id_modulus,
                frame_id_skips_zero=self.camera.frame_id_skips_zero,
                fixed_angle=None if self.encoder else NO_ENCODER_ANGLE,
                groups=1 if self.patterns.coarse_period_px is None else 2,
            )
            reference = None if self.encoder else NO_ENCODER_REFERENCE
            if self.encoder is not None:  # before the recording exists: a missing index leaves no folder
                self.encoder.start()
                reference = self._settle_encoder_reference()
            if self.out is not None:
                meta = {
                    "camera": {**dataclasses.asdict(self.camera.info), "settings": self.settings.model_dump(),
                               "frame_ids": self.camera.frame_id_wrap.to_json()},  # how replay orders the ids
                    "patterns": self.patterns.to_json(),
                    "encoder": None if cfg.encoder is None else cfg.encoder.model_dump(),
                    "encoder_reference": reference,
                    "acquisition_config": cfg.model_dump(mode="json"),
                    **self.extra_meta,
                }
                self.writer = RecordingWriter(self.out, meta, overwrite=self.overwrite)
            self.camera.start()
            if self.settings.trigger == "software":
                self.projector = make_projector(cfg)
                self.projector.open()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.camera.stop()
        finally:
            if self.projector is not None:
                self.projector.close()
            if self.encoder is not None:
                self.encoder.stop()
            if self.writer is not None:
                self._drain_encoder()
                if self.assembler is not None:
                    self.writer.update_meta(assembler=self.assembler.stats.as_dict(),
                                            camera_stats=self.camera.stats.as_dict(),
                                            **({"encoder_stats": self.encoder.stats.as_dict()} if self.encoder else {}))
                self.writer.close()
            self.camera.__exit__(None, None, None)

    def _settle_encoder_reference(self) -> str:
        """Wait for the index mark (``encoder.index_wait_s``), then freeze the angle reference:
        the CAD pose and the turntable transform need angles from the index, and no recording
        may mix angles from before and after it."""
        enc_cfg = self.cfg.encoder
        if enc_cfg.zero_on_index and enc_cfg.index_wait_s > 0 and not self.encoder.wait_for_index(enc_cfg.index_wait_s):
            raise EncoderError(
                f"encoder on {enc_cfg.port}: no index mark within encoder.index_wait_s = {enc_cfg.index_wait_s:g} s "
                f"({self.encoder.stats.samples} samples read): is the turntable turning? Set encoder.index_wait_s = 0 "
                "to measure with angles from the first count instead"
            )
        return self.encoder.freeze_reference()

    def _drain_encoder(self) -> None:
        while not self._samples.empty():
            sample = self._samples.get_nowait()
            if self.writer is not None:
                self.writer.write_encoder(sample)
            self.encoder_samples += 1

    def _frames(self) -> Iterator[Frame]:
        if self.settings.trigger == "software":
            from gearscan.projector.sequencer import SoftwareSequencer

            yield from SoftwareSequencer(self.projector, self.camera, self.patterns,
                                         settle_s=self.cfg.projector.settle_ms / 1e3).run(order=self.order)
        else:
            yield from iter(lambda: self.camera.grab(2.0), None)

    def _check_frame_size(self, frame: Frame) -> None:
        height, width = frame.image.shape[:2]
        if self.rig_size is not None and (width, height) != self.rig_size:
            raise ConfigError(
                f"rig.calibration: the rig is calibrated for a {self.rig_size[0]}x{self.rig_size[1]} camera image, the "
                f"camera delivers {width}x{height} frames: set camera.roi to the calibrated area or calibrate this setting"
            )

    def bursts(self, max_frames: int | None = None, stop: Callable[[], bool] | None = None) -> Iterator[Burst]:
        """Valid bursts, recorded before they are yielded; raises if ``max_frames`` yield none. ``stop``: asked after
        every frame; True ends the bursts there (a caller in another thread, e.g. live's --duration or Ctrl-C, must
        not wait for the next burst: a restarted encoder waiting for its index mark yields none for long)."""
        assert self.assembler is not None, "use AcquisitionSession as a context manager"
        try:
            yield from self._assemble(max_frames, stop)
        except GrabTimeout:
            exhausted = getattr(self.camera, "exhausted", None)
            if exhausted is not None and exhausted.is_set():
                return  # a replay camera reached the end of its recording: end of input
            raise

    def _assemble(self, max_frames: int | None, stop: Callable[[], bool] | None = None) -> Iterator[Burst]:
        since_burst = 0
        for frame in self._frames():
            if stop is not None and stop():
                return
            self.frames += 1
            since_burst += 1
            if self.frames == 1:
                self._check_frame_size(frame)
            self._drain_encoder()
            if self.encoder is not None:
                self.encoder.raise_if_failed()  # a dead reader thread: its cause, at once
                if self.encoder.resyncing:  # a restarted encoder waits for its index: no abort meanwhile
                    since_burst = 0
            burst = self.assembler.push(frame)
            if burst is not None:
                since_burst = 0
                if burst.group:
                    self.coarse_bursts += 1
                else:
                    self.burst_count += 1
                if self.writer is not None:
                    for f, a in zip(burst.frames, burst.angles, strict=True):
                        self.writer.write_frame(dataclasses.replace(f, encoder_angle=a))
                yield burst
            elif max_frames is not None and since_burst >= max_frames:
                if self.encoder is not None and not self.encoder.connected.is_set():  # the cause, not its symptom
                    raise EncoderError(
                        f"encoder on {self.encoder.port} is disconnected (cable or power?): no angle for the last "
                        f"{since_burst} frames, so no burst could be measured and the run stopped; reconnect it and "
                        "start again (what was measured before is recorded)"
                    )
                raise CameraError(
                    f"no valid burst in {since_burst} frames; assembler: {self.assembler.stats.as_dict()}, "
                    f"last events: {[e.detail for e in self.assembler.events[-3:]]}"
                )


def record_bursts(
    cfg: AcquisitionConfig,
    out: Path,
    n_bursts: int,
    *,
    overwrite: bool = False,
    on_burst: Callable[[int], None] | None = None,
    max_frames: int | None = None,
    extra_meta: dict | None = None,
) -> RecordSummary:
    """Record ``n_bursts`` valid bursts into ``out``; ``extra_meta`` goes into its recording.json
    (``gearscan record`` stores the rig, gear and config there, as ``gearscan live --record``)."""
    import time

    if n_bursts <= 0:
        raise ConfigError(f"bursts must be > 0, got {n_bursts}")
    t0 = time.monotonic()
    max_frames = max_frames or n_bursts * 3 * 10
    session = AcquisitionSession(cfg, out, overwrite=overwrite, extra_meta=extra_meta)
    with session:
        for _ in session.bursts(max_frames=max_frames):
            if on_burst is not None:
                on_burst(session.burst_count)
            if session.burst_count >= n_bursts:
                break
    return RecordSummary(
        out=Path(out),
        bursts=session.burst_count,
        frames=session.frames,
        encoder_samples=session.encoder_samples,
        assembler=session.assembler.stats.as_dict(),
        camera=session.camera.stats.as_dict(),
        encoder=None if session.encoder is None else session.encoder.stats.as_dict(),
        seconds=time.monotonic() - t0,
    )


def check_camera(cfg: AcquisitionConfig, size: tuple[int, int] | None = None) -> str:
    """Open the configured camera, apply its settings, grab one frame; what was verified, in words.

    ``size`` (width, height): the image size the rig was calibrated for; another size is a
    :class:`ConfigError`. Raises CameraError when the camera is missing or refuses a setting.
    """
    camera = open_camera(cfg)
    settings = cfg.camera.settings()
    with camera:
        camera.configure(settings)
        who = " ".join(x for x in (camera.info.vendor, camera.info.model, camera.info.serial) if x) or str(cfg.camera.id)
        if settings.trigger == "hardware":
            return f"{cfg.camera.driver} camera {who} found and configured (hardware trigger: no frame grabbed)"
        camera.start()
        try:
            if settings.trigger == "software":
                camera.software_trigger()
            frame = camera.grab(5.0)
        finally:
            camera.stop()
    h, w = frame.image.shape[:2]
    if size is not None and (w, h) != tuple(size):
        raise ConfigError(f"camera: it delivers {w}x{h} px images, the rig (rig.calibration) is calibrated for "
                          f"{size[0]}x{size[1]}: set camera.roi = [x, y, {size[0]}, {size[1]}] or calibrate this camera")
    return f"{cfg.camera.driver} camera {who}: configured, one {w}x{h} {settings.pixel_format} frame grabbed"
