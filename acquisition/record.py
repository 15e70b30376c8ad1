"""Record bursts from the configured camera, projector and encoder into a recording folder.

Frames go through the :class:`BurstAssembler`; only frames of complete, valid bursts are
written, each with its encoder angle at the exposure midpoint, so the recording replays
into exactly the bursts that were measured. Raw encoder samples go to ``encoder.jsonl``.
The writer is closed in ``finally``: Ctrl-C or a pulled cable leaves a readable recording.
"""

from __future__ import annotations

import dataclasses
import queue
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from gearscan.acquisition.bursts import BurstAssembler
from gearscan.acquisition.camera import BaseCamera, CameraError
from gearscan.acquisition.config import AcquisitionConfig, ConfigError
from gearscan.acquisition.encoder import EncoderReader
from gearscan.projector.patterns import PatternSet

from gearscan.types import EncoderSample


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
        return ReplayCamera(c.id)
    from gearscan.acquisition.v4l2 import V4L2Camera

    return V4L2Camera(c.id or "/dev/video0")


def make_projector(cfg: AcquisitionConfig):
    from gearscan.projector.sequencer import MockProjector, WindowProjector

    p = cfg.projector
    if p.backend == "mock":
        return MockProjector(width=p.width, height=p.height)
    if p.backend == "window":
        return WindowProjector(display=p.display, width=p.width, height=p.height)
    raise ConfigError(
        "projector.backend: 'lightcrafter' plays its sequence by itself; set camera.trigger = 'hardware' "
        "and camera.pattern_cycle = 3 and the projector is not driven by record (got 'lightcrafter' with software trigger)"
    )


def record_bursts(
    cfg: AcquisitionConfig,
    out: Path,
    n_bursts: int,
    *,
    overwrite: bool = False,
    on_burst: Callable[[int], None] | None = None,
    max_frames: int | None = None,
) -> RecordSummary:
    import time

    from gearscan.recording import RecordingWriter

    if n_bursts <= 0:
        raise ConfigError(f"bursts must be > 0, got {n_bursts}")
    settings = cfg.camera.settings()
    patterns = PatternSet.three_step(cfg.projector.period_px)
    if settings.trigger != "software" and settings.pattern_cycle != 3:
        raise ConfigError(
            f"camera.pattern_cycle: must be 3 with trigger {settings.trigger!r} (the projector cycles the "
            f"three patterns by itself), got {settings.pattern_cycle}"
        )
    samples: queue.Queue[EncoderSample] = queue.Queue()
    reader = None
    if cfg.encoder is not None:
        reader = EncoderReader(
            cfg.encoder.port,
            cfg.encoder.counts_per_rev,
            baudrate=cfg.encoder.baudrate,
            zero_on_index=cfg.encoder.zero_on_index,
            on_sample=samples.put,
        )
    camera = open_camera(cfg)
    t0 = time.monotonic()
    n_frames = n_samples = 0
    max_frames = max_frames or n_bursts * 3 * 10
    with camera:
        camera.configure(settings)
        assembler = BurstAssembler(
            reader.history if reader else None,
            max_encoder_gap_ns=int((cfg.encoder.max_gap_ms if cfg.encoder else 20.0) * 1e6),
            frame_id_modulus=camera.frame_id_modulus,
            frame_id_skips_zero=camera.frame_id_skips_zero,
        )
        meta = {
            "camera": {**dataclasses.asdict(camera.info), "settings": settings.model_dump()},
            "patterns": patterns.to_json(),
            "encoder": None if cfg.encoder is None else cfg.encoder.model_dump(),
            "acquisition_config": cfg.model_dump(mode="json"),
        }
        if reader is not None:
            reader.start()
        projector = None
        try:
            with RecordingWriter(out, meta, overwrite=overwrite) as writer:
                camera.start()
                if settings.trigger == "software":
                    from gearscan.projector.sequencer import SoftwareSequencer

                    projector = make_projector(cfg)
                    projector.open()
                    frames = SoftwareSequencer(projector, camera, patterns, settle_s=cfg.projector.settle_ms / 1e3).run()
                else:
                    frames = iter(lambda: camera.grab(2.0), None)
                bursts = 0
                for frame in frames:
                    n_frames += 1
                    while not samples.empty():
                        writer.write_encoder(samples.get_nowait())
                        n_samples += 1
                    burst = assembler.push(frame)
                    if burst is not None:
                        for f, a in zip(burst.frames, burst.angles, strict=True):
                            writer.write_frame(dataclasses.replace(f, encoder_angle=a))
                        bursts += 1
                        if on_burst is not None:
                            on_burst(bursts)
                        if bursts >= n_bursts:
                            break
                    if n_frames >= max_frames:
                        raise CameraError(
                            f"only {bursts} valid bursts from {n_frames} frames; assembler: {assembler.stats.as_dict()}, "
                            f"last events: {[e.detail for e in assembler.events[-3:]]}"
                        )
                writer.update_meta(assembler=assembler.stats.as_dict(), camera_stats=camera.stats.as_dict())
        finally:
            camera.stop()
            if projector is not None:
                projector.close()
            if reader is not None:
                reader.stop()
    return RecordSummary(
        out=Path(out),
        bursts=bursts,
        frames=n_frames,
        encoder_samples=n_samples,
        assembler=assembler.stats.as_dict(),
        camera=camera.stats.as_dict(),
        encoder=None if reader is None else reader.stats.as_dict(),
        seconds=time.monotonic() - t0,
    )
