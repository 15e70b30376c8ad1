"""``gearscan live``: camera + projector + encoder -> CD-DCU-Net -> point cloud -> rerun.

Acquisition (sequencing, burst assembly, recording) runs in the source thread and never
waits on inference: bursts reach the decoder through a drop-oldest queue. Ctrl-C or
SIGTERM stops acquisition, lets the bursts in flight finish, closes the recording (which
then replays) and flushes the viewer stream.
"""

from __future__ import annotations

import collections
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from gearscan.config import LiveConfig
from gearscan.core.types import Burst, Measurement
from gearscan.inference.decoder import Decoder
from gearscan.pipeline import Pipeline, PipelineError, PipelineReport, StageSpec
from gearscan.recon.depth_sigma import UNMEASURED_NOTES, decoder_depth_sigma
from gearscan.recon.deviation import CadScorer
from gearscan.recon.measure import CoarseStage, Reconstructor, network_support_option

log = logging.getLogger(__name__)

# Why bursts (or frames) went missing: (source, counter) -> (short cause for the status line,
# what it counts and means for the end summary).
DROP_CAUSES = {
    ("assembler", "dropped_frames"): ("frames lost", "frames the camera sent that never arrived (frame-id gaps)"),
    ("assembler", "pattern_errors"): ("pattern order", "frames out of pattern order (their partial burst discarded)"),
    ("assembler", "order_errors"): ("frame order", "late or duplicate frames, ignored"),
    ("assembler", "encoder_gaps"): ("no angle", "bursts discarded without an encoder angle (encoder gap or late)"),
    ("queue", "infer"): ("decoder busy", "bursts skipped while the decoder was busy"),
    ("queue", "reconstruct"): ("reconstruct busy", "bursts skipped while reconstruction was busy"),
    ("queue", "output"): ("viewer busy", "bursts skipped while the viewer output was busy"),
}
# What a skipped burst means, once, under the end summary.
QUEUE_DROP_NOTE = "a busy stage skips its oldest waiting burst so the measurement stays live; acquisition never waits"
SIGNAL_REASONS = {"SIGINT": "Ctrl-C (SIGINT)", "SIGTERM": "SIGTERM",
                  "end of input": "end of input (the camera delivered no more frames)"}


class LiveError(PipelineError):
    """A stage of ``live`` failed; ``live_report`` holds what was measured before (None: nothing ran)."""

    def __init__(self, error: PipelineError, live_report: LiveReport | None) -> None:
        super().__init__(error.stage, error.__cause__ or error)
        self.report = error.report
        self.live_report = live_report


@dataclass(frozen=True)
class LiveStatus:
    """A snapshot of a running ``live``: what the one-line status shows."""

    elapsed_s: float
    acquired: int  # bursts assembled (and recorded)
    measured: int  # bursts through the whole pipeline
    rate_per_s: float  # measured bursts per second over the last few seconds
    drops: dict[str, int]  # short cause (DROP_CAUSES) -> count, non-zero only
    encoder_hz: float | None  # encoder samples per second; None: no encoder
    rrd: Path | None
    rrd_mb: float | None
    rrd_full: bool = False
    fringes: str | None = None  # the network's fringe orientation (Decoder.orientation_status); None: not known

    def line(self) -> str:
        parts = [f"{self.elapsed_s:4.0f} s {self.measured} bursts {self.rate_per_s:.1f}/s",
                 "drops " + (", ".join(f"{n} {c}" for c, n in self.drops.items()) or "none"),
                 "no encoder" if self.encoder_hz is None else f"encoder {self.encoder_hz:.0f} Hz"]
        if self.fringes:
            parts.append(self.fringes)
        if self.rrd is not None:
            parts.append(f"{self.rrd} {self.rrd_mb or 0:.0f} MB" + (" FULL" if self.rrd_full else ""))
        return " | ".join(parts)


@dataclass
class LiveReport:
    bursts: int
    pipeline: PipelineReport
    recording: Path | None
    assembler: dict[str, int]
    stopped_by: str = ""
    status: LiveStatus | None = None
    encoder: dict[str, int] | None = field(default=None)
    coarse_bursts: int = 0  # acquired between the measuring bursts (projector.coarse_period_px)

    @property
    def skipped(self) -> int:
        """Acquired bursts a busy stage skipped (every other acquired burst was measured)."""
        queue_causes = {short for (src, _), (short, _) in DROP_CAUSES.items() if src == "queue"}
        return sum(n for c, n in (self.status.drops if self.status else {}).items() if c in queue_causes)

    def summary(self) -> str:
        """The end summary: why it stopped, what was measured, what was dropped and why, where the stream is."""
        measured = self.status.measured if self.status else 0
        lines = [f"stopped by {self.stopped_by} after {self.pipeline.wall_s:.1f} s: {self.bursts} bursts acquired, "
                 f"{measured} measured ({measured / max(self.pipeline.wall_s, 1e-9):.1f}/s)"
                 + (f", {self.coarse_bursts} coarse bursts for CAD-free unwrapping" if self.coarse_bursts else "")]
        drops = self.status.drops if self.status else {}
        meaning = dict(DROP_CAUSES.values())
        lines.append("dropped: " + ("; ".join(f"{n} {meaning[c]}" for c, n in drops.items()) or "nothing"))
        if self.skipped:
            lines.append(f"  ({QUEUE_DROP_NOTE})")
        lines.append("latency per burst (mean / p95): " + ", ".join(
            f"{n} {s['latency_ms_mean']:.0f} / {s['latency_ms_p95']:.0f} ms" for n, s in self.pipeline.stages.items()))
        if self.encoder is not None:
            e = self.encoder
            lines.append(f"encoder: {e['samples']} samples, {e['lost']} lost, {e['corrupt']} corrupt, "
                         f"{e['disconnects']} disconnects"
                         + (f", last {self.status.encoder_hz:.0f} samples/s" if self.status and self.status.encoder_hz else ""))
        if self.status is not None and self.status.fringes:
            lines.append(f"network: {self.status.fringes}")
        if self.status is not None and self.status.rrd is not None:
            full = "; size cap reached, the stream stops there" if self.status.rrd_full else ""
            lines.append(f"viewer stream: {self.status.rrd} ({self.status.rrd_mb or 0:.1f} MB{full}; "
                         f"open with: rerun {self.status.rrd})")
        return "\n".join(lines)


class StatusLine:
    """Shows :class:`LiveStatus` as one line redrawn in place on a terminal; elsewhere (a log
    file, a service) it prints the line every ``every_s`` seconds."""

    def __init__(self, console=None, every_s: float = 10.0) -> None:
        from rich.console import Console

        self.console = console or Console()
        self.every_s = every_s
        self._live = None
        self._last = 0.0

    def __enter__(self) -> StatusLine:
        if self.console.is_terminal:
            from rich.live import Live

            self._live = Live(console=self.console, refresh_per_second=4, transient=True)
            self._live.__enter__()
        self._last = time.monotonic()
        return self

    def update(self, status: LiveStatus) -> None:
        if self._live is not None:
            from rich.text import Text

            self._live.update(Text(status.line(), overflow="ellipsis", no_wrap=True))
        elif time.monotonic() - self._last >= self.every_s:
            self._last = time.monotonic()
            self.console.print(status.line(), highlight=False, soft_wrap=True)

    def __exit__(self, *exc: object) -> None:
        if self._live is not None:
            self._live.__exit__(None, None, None)


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
    on_status: Callable[[LiveStatus], None] | None = None,
    max_save_mb: float | None = None,
) -> LiveReport:
    """Measure until ``bursts`` are done, ``duration`` s pass, or Ctrl-C / SIGTERM.

    ``on_status`` gets a :class:`LiveStatus` about five times a second. ``max_save_mb`` caps
    the ``save`` file: past it the viewer stream stops (the measurement and any recording go on).
    """
    from gearscan.acquire import AcquisitionSession

    rig = cfg.load_rig()
    decoder = decoder or Decoder(cfg.model.path, mc=cfg.model.mc, precision=cfg.model.precision,
                                 workers=cfg.model.workers, still_span_deg=cfg.model.still_span_deg,
                                 orientation=cfg.model.orientation)
    adopt_rig = getattr(decoder, "adopt_rig", None)  # the network's fringe orientation from the calibration
    if adopt_rig is not None:
        adopt_rig(rig)
    support = network_support_option(cfg.recon.network_support_px,  # unset: the model's own (its JSON)
                                     model=getattr(decoder, "network_support", None))
    depth_scales, depth_source = decoder_depth_sigma(decoder)  # the model's own, else the product's
    recon = Reconstructor.for_gear(rig, cfg.projector.period_px, cfg.gear,
                                   min_modulation=cfg.recon.min_modulation, max_sigma=cfg.recon.max_sigma_rad,
                                   unwrap=cfg.recon.unwrap, network_support_px=support,
                                   depth_sigma_scales=depth_scales)
    if note := UNMEASURED_NOTES.get(depth_source):
        log.warning("%s", note)
    coarse = CoarseStage(rig, cfg.projector.coarse_period_px, cfg.gear, recon if cfg.recon.unwrap == "coarse" else None)
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
    state = {"full": False, "measured": 0}  # .rrd full, bursts output; written by the output thread
    cap_bytes = max_save_mb * 1e6 if save is not None and max_save_mb else None

    def source() -> Iterator[Burst]:
        with session:
            # the pipeline's stop (--duration, Ctrl-C, an error downstream) is asked after every frame, not only at
            # a burst: a restarted encoder waiting for its index mark delivers frames but no burst for long
            for burst in session.bursts(max_frames=30, stop=lambda: pipeline.stopping):
                yield burst
                if bursts is not None and session.burst_count >= bursts:
                    pipeline.stop(f"--bursts {bursts} reached")
                    return

    def stream_full() -> bool:
        if cap_bytes is not None and not state["full"] and save.exists() and save.stat().st_size >= cap_bytes:
            state["full"] = True
            log.warning("%s reached its size cap of %g MB: the viewer stream stops here, the measurement goes on "
                        "(viewer.max_save_mb / --max-save-mb; 0: no cap)", save, max_save_mb)
        return state["full"]

    def output(m: Measurement) -> None:
        row: dict[str, float] = {"burst": m.burst.index, "points": len(m.cloud) if m.cloud else 0}
        if cad is not None:
            m, deviation = cad(m)  # the cloud with each point's deviation, for the viewer
            row.update(deviation)
        if logger is not None and not stream_full():
            stats = {k: v for k, v in row.items() if k.startswith("cad_")}
            for name, st in (pipeline.stats.items() if pipeline else []):
                stats[f"latency_ms/{name}"] = st.as_dict()["latency_ms_mean"]
                stats[f"dropped/{name}"] = st.dropped_in
            logger.log_burst(m.burst, m.result, cloud=m.cloud, stats=stats, unresolved=m.unresolved, mixed=m.mixed)
        if on_burst is not None:
            on_burst(m, row)
        state["measured"] += 1  # only bursts that really came out (after a failure the rest drain undone)

    pipeline = Pipeline(
        source,
        [
            StageSpec("infer", lambda b: Measurement(b, decoder(b)), queue_size=2, workers=getattr(decoder, "workers", 1)),
            StageSpec("reconstruct", lambda m: coarse(m) if m.burst.group else recon(m.burst, m.result),
                      queue_size=2, close=recon.close),
            StageSpec("output", output, close=logger.close if logger else None, queue_size=4),
        ],
        source_name="acquisition",
        on_stats=None if on_status is None else lambda stats: on_status(snapshot()),
    )
    orientation_status = getattr(decoder, "orientation_status", None)  # a stand-in decoder may not say
    window: collections.deque[tuple[float, int, int]] = collections.deque()  # (t, measured, encoder samples)
    t_start = time.monotonic()

    def snapshot() -> LiveStatus:
        now = time.monotonic()
        measured = state["measured"]
        samples = session.encoder.stats.samples if session.encoder else 0
        window.append((now, measured, samples))
        while len(window) > 2 and now - window[0][0] > 5.0:
            window.popleft()
        span = max(now - window[0][0], 1e-9)
        return LiveStatus(
            elapsed_s=now - t_start, acquired=session.burst_count, measured=measured,
            rate_per_s=(measured - window[0][1]) / span if len(window) > 1 else 0.0,
            drops=drops(), rrd=save,
            encoder_hz=None if session.encoder is None else ((samples - window[0][2]) / span if len(window) > 1 else 0.0),
            rrd_mb=save.stat().st_size / 1e6 if save is not None and save.exists() else None,
            rrd_full=state["full"],
            fringes=orientation_status() if orientation_status else None,
        )

    def drops() -> dict[str, int]:
        asm = session.assembler.stats.as_dict() if session.assembler else {}
        counts = {short: asm.get(key, 0) if src == "assembler" else pipeline.stats[key].dropped_in
                  for (src, key), (short, _) in DROP_CAUSES.items()}
        return {cause: n for cause, n in counts.items() if n}

    def report(pipeline_report: PipelineReport, stopped_by: str) -> LiveReport:
        return LiveReport(
            bursts=session.burst_count,
            pipeline=pipeline_report,
            recording=record,
            assembler=session.assembler.stats.as_dict() if session.assembler else {},
            stopped_by=stopped_by,
            status=snapshot(),
            encoder=session.encoder.stats.as_dict() if session.encoder else None,
            coarse_bursts=session.coarse_bursts,
        )

    try:
        result = pipeline.run(duration=duration, handle_signals=handle_signals)
    except PipelineError as exc:  # with what was measured before the failure, for the end summary
        partial = report(exc.report, f"an error in stage {exc.stage!r}") if exc.report is not None else None
        raise LiveError(exc, partial) from exc.__cause__
    reason = result.stopped_by
    if reason == "duration reached":
        reason = f"--duration {duration:g} s reached"
    return report(result, SIGNAL_REASONS.get(reason, reason))
