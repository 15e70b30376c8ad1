"""``gearscan live``: camera + projector + encoder -> CD-DCU-Net -> point cloud -> rerun.

Acquisition (sequencing, burst assembly, recording) runs in the source thread and never
waits on inference: bursts reach the decoder through a drop-oldest queue. Ctrl-C or
SIGTERM stops acquisition, lets the bursts in flight finish, closes the recording (which
then replays) and flushes the viewer stream.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from gearscan.config import LiveConfig
from gearscan.measure import CadScorer, Decoder, Measurement, Reconstructor
from gearscan.pipeline import Pipeline, PipelineReport, StageSpec
from gearscan.types import Burst

log = logging.getLogger(__name__)


@dataclass
class LiveReport:
    bursts: int
    pipeline: PipelineReport
    recording: Path | None
    assembler: dict[str, int]


def run_live(
    cfg: LiveConfig,
    *,
    record: Path | None = None,
    overwrite: bool = False,
    bursts: int | None = None,
    duration: float | None = None,
    decoder: Callable[[Burst], object] | None = None,
    save: Path | None = None,
    connect: str | None = None,
    spawn: bool = False,
    on_burst: Callable[[Measurement, dict], None] | None = None,
    handle_signals: bool = True,
) -> LiveReport:
    """Measure until ``bursts`` are done, ``duration`` s pass, or Ctrl-C / SIGTERM."""
    from gearscan.acquisition.record import AcquisitionSession

    rig = cfg.load_rig()
    decoder = decoder or Decoder(cfg.model.path, mc=cfg.model.mc, precision=cfg.model.precision,
                                 workers=cfg.model.workers, still_span_deg=cfg.model.still_span_deg)
    recon = Reconstructor.for_gear(rig, cfg.projector.period_px, cfg.gear,
                                   min_modulation=cfg.recon.min_modulation, max_sigma=cfg.recon.max_sigma_rad,
                                   unwrap=cfg.recon.unwrap)
    cad = CadScorer(cfg.gear) if cfg.recon.cad_deviation else None
    logger = None
    if save or connect or spawn:
        from gearscan.viewer.log import RerunLogger

        logger = RerunLogger(save=save, connect=connect, spawn=spawn)
        logger.log_rig(rig)
    session = AcquisitionSession(
        cfg, record, overwrite=overwrite,
        extra_meta={"source": "live", "rig": rig.to_json(), "gear": cfg.gear.model_dump(),
                    "live_config": cfg.model_dump(mode="json")},
    )
    pipeline: Pipeline | None = None

    def source() -> Iterator[Burst]:
        with session:
            for burst in session.bursts(max_frames=30):
                yield burst
                if bursts is not None and session.burst_count >= bursts:
                    return

    def output(m: Measurement) -> None:
        row: dict[str, float] = {"burst": m.burst.index, "points": len(m.cloud) if m.cloud else 0}
        if cad is not None:
            row.update(cad(m))
        if logger is not None:
            stats = {k: v for k, v in row.items() if k.startswith("cad_")}
            for name, st in (pipeline.stats.items() if pipeline else []):
                stats[f"latency_ms/{name}"] = st.as_dict()["latency_ms_mean"]
                stats[f"dropped/{name}"] = st.dropped_in
            logger.log_burst(m.burst, m.result, cloud=m.cloud, stats=stats)
        if on_burst is not None:
            on_burst(m, row)

    pipeline = Pipeline(
        source,
        [
            StageSpec("infer", lambda b: Measurement(b, decoder(b)), queue_size=2, workers=getattr(decoder, "workers", 1)),
            StageSpec("reconstruct", lambda m: recon(m.burst, m.result), queue_size=2, close=recon.close),
            StageSpec("output", output, close=logger.close if logger else None, queue_size=4),
        ],
        source_name="acquisition",
    )
    report = pipeline.run(duration=duration, handle_signals=handle_signals)
    return LiveReport(
        bursts=session.burst_count,
        pipeline=report,
        recording=record,
        assembler=session.assembler.stats.as_dict() if session.assembler else {},
    )
