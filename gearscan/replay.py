"""``gearscan replay``: the live pipeline fed by a recording, with accuracy when it holds truth.

Stages: replay camera -> burst assembler -> decoder -> reconstructor -> output (viewer,
metrics). With ``speed="max"`` frames are served as fast as the pipeline takes them and no
queue drops anything; with a real-time speed a slow stage drops its oldest input, as live.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Literal

import numpy as np

from gearscan.core.phase import classical_result, phase_error
from gearscan.core.recording import RecordingError, RecordingReader
from gearscan.core.rig import Rig, RigError
from gearscan.core.types import Burst, Cloud, Measurement
from gearscan.inference.decoder import Decoder
from gearscan.pipeline import Pipeline, PipelineReport, StageSpec
from gearscan.recon.cloud import EXPORT_SUFFIXES, save_cloud
from gearscan.recon.depth_sigma import decoder_depth_sigma, decoder_rest_sigma
from gearscan.recon.deviation import CadScorer, SurfaceDistance
from gearscan.recon.fuse import CloudFuser, FusedCloud
from gearscan.recon.measure import (
    PRODUCT_SUPPORT,
    CoarseStage,
    Reconstructor,
    keep_bound_option,
    network_support_option,
    unwrapper_sees,
)

log = logging.getLogger(__name__)


@dataclass
class ReplayMetrics:
    """Per-burst accuracy against the twin's truth, and pipeline statistics."""

    per_burst: list[dict[str, float]] = field(default_factory=list)
    pipeline: dict[str, dict[str, float]] = field(default_factory=dict)
    assembler: dict[str, int] = field(default_factory=dict)
    damage: dict = field(default_factory=dict)  # RecordingReader.damage_summary(): skipped damage
    fused: FusedCloud | None = None  # the revolution fused in the gear frame (replay(fuse=...))
    refine: dict = field(default_factory=dict)  # replay(refine=True): what the frame fit refined
    decoder: dict = field(default_factory=dict)  # mode, still bursts, the fringe orientation used (Decoder)
    recon: dict = field(default_factory=dict)  # the reconstructor's settings that ran (the fringe-support test)

    @property
    def bursts(self) -> int:
        return len(self.per_burst)

    def summary(self) -> dict[str, float]:
        out: dict[str, float] = {"bursts": self.bursts}
        if self.per_burst:
            for key in self.per_burst[0]:
                vals = np.array([b[key] for b in self.per_burst if key in b], dtype=float)
                if key.endswith("_rmse_rad") or key.endswith("_rms_mm"):
                    out[key] = float(np.sqrt(np.nanmean(vals**2)))
                elif key.endswith(("_sigma_rad", "_p95_mm", "coverage")):
                    out[key] = float(np.nanmean(vals))
                elif key.startswith("unwrap_") or key in ("cloud_points", "points_off_gear", "pixel_depth_mismatch"):
                    out[key] = float(np.nansum(vals))
                elif key.endswith("_max_mm"):
                    out[key] = float(np.nanmax(vals))
        return out

    def to_json(self) -> dict:
        out = {"summary": self.summary(), "bursts": self.per_burst, "pipeline": self.pipeline,
               "assembler": self.assembler, "damage": self.damage, "decoder": self.decoder, "recon": self.recon}
        if self.refine:
            out["refine"] = self.refine
        return out


class TruthScorer:
    """Phase and cloud accuracy of a measurement against a twin recording's truth.

    Two different questions, never mixed (DESIGN.md, "Numbers we can trust"):

    * accuracy vs truth: each point's distance to the true gear surface (the twin's gear as
      built, defects included; ``accuracy_*_mm`` over every point, edge and spurious points
      included), with coverage = share of the truth mask that got a point. Beside it, against
      the truth of the point's own pixel: ``pixel_depth_mismatch`` counts points more than 1 mm
      from the true depth along their pixel's ray (a silhouette pixel whose blur mixes two
      surfaces measures the one in front, a wrong fringe order lands anywhere) and
      ``points_off_gear`` those whose ray meets no gear. None of these depends on the CAD that
      guided the unwrapping.
    * deviation vs CAD: what a user measures (``cad_dev_*_mm``), next to the deviation the
      true surface has on the same pixels (``true_cad_dev_*_mm``), so a deviation that the
      reconstruction hides shows as a gap between the two.
    """

    def __init__(self, reader: RecordingReader) -> None:
        self.reader = reader
        self.index = {fid: i for i, fid in enumerate(reader.extended_ids)}  # the ids ReplayCamera serves
        self.cad = CadScorer(reader.gear) if reader.gear is not None else None
        self.true_surface = None
        if reader.gear is not None:
            from gearscan.twin.defects import GearDefects, true_mesh

            self.true_surface = SurfaceDistance(true_mesh(reader.gear, GearDefects.from_meta(reader.meta)))
        rays = reader.rig.camera.pixel_rays()
        self._rays = rays / rays[..., 2:3]  # camera z = 1: true point = ray * true depth

    def __call__(self, m: Measurement) -> tuple[Measurement, dict[str, float], np.ndarray, np.ndarray]:
        from gearscan.recon.triangulate import to_turntable

        truth = self.reader.truth(self.index[m.burst.frames[0].frame_id])
        mask = truth["mask"]
        err = np.where(mask, phase_error(m.result.phase, truth["phase"]), 0.0)
        row = {
            "burst": m.burst.index,
            "angle_deg": float(np.degrees(m.burst.angles[0])),
            "span_deg": float(np.degrees(m.burst.angles[2] - m.burst.angles[0])),
            f"{m.result.mode}_rmse_rad": float(np.sqrt(np.mean(err[mask] ** 2))),
            "mean_sigma_rad": float(np.mean(m.result.sigma_total[mask])),
        }
        if m.result.mode != "three-step":
            base = classical_result(m.burst)
            row["three-step_rmse_rad"] = float(np.sqrt(np.mean(phase_error(base.phase, truth["phase"])[mask] ** 2)))
        if m.cloud is not None:
            rows, cols = m.cloud.pixels[:, 0], m.cloud.pixels[:, 1]
            depth = truth["depth"][rows, cols]
            gear = np.isfinite(depth)
            true_cam = self._rays[rows[gear], cols[gear]] * depth[gear, None]
            true_pts = to_turntable(true_cam, self.reader.rig, m.cloud.angle)
            ray_err = np.linalg.norm(m.cloud.points[gear] - true_pts, axis=1)
            row["cloud_points"] = len(m.cloud)
            row["coverage"] = float(mask[rows, cols].sum() / max(int(mask.sum()), 1))
            row["points_off_gear"] = int((~gear).sum())
            row["pixel_depth_mismatch"] = int((ray_err > 1.0).sum() + (~gear).sum())
            if self.true_surface is not None and len(m.cloud):
                dist = np.abs(self.true_surface.distances(m.cloud.points))
                row["accuracy_rms_mm"] = float(np.sqrt(np.mean(dist**2)))
                row["accuracy_p95_mm"] = float(np.percentile(dist, 95))
                row["accuracy_max_mm"] = float(dist.max())
            for key, val in m.unwrap.items():
                row[f"unwrap_{key}"] = val
            if self.cad is not None and len(m.cloud):
                m, dev = self.cad(m)  # the cloud with each point's deviation
                row["cad_dev_rms_mm"] = dev["cad_rms_mm"]
                row["cad_dev_p95_mm"] = dev["cad_p95_mm"]
                true_dev = self.cad.distances(to_turntable(truth["points"][mask], self.reader.rig, m.cloud.angle))
                row["true_cad_dev_rms_mm"] = float(np.sqrt(np.mean(true_dev**2)))
                row["true_cad_dev_p95_mm"] = float(np.percentile(np.abs(true_dev), 95))
        return m, row, err, mask


def recording_rig(reader: RecordingReader, rig: str | Path | Rig | None = None) -> Rig:
    """The rig to measure ``reader``'s frames with: ``rig`` (a file or a Rig) when given, else the
    recording's own; either must have the frames' size. A recording without one (made by
    ``gearscan record`` before it stored the rig) and no ``rig`` is an error saying what to pass."""
    if rig is None:
        if "rig" not in reader.meta:
            raise RecordingError(f"{reader.path / 'recording.json'} holds no rig calibration (recorded without one): "
                                 "pass the rig it was recorded with, e.g. `gearscan replay "
                                 f"{reader.path} --rig rig.json` (the file `gearscan calibrate` wrote)")
        return reader.rig
    if not isinstance(rig, Rig):
        try:
            rig = Rig.load(rig)
        except RigError as exc:
            raise RecordingError(f"--rig: {exc}") from exc
    return reader.check_rig(rig, "--rig")


@dataclass
class CloudExport:
    """Writes every burst's cloud (gear frame, mm) as ``burst_NNNNNN.ply`` and/or ``.csv`` into a folder.

    Each file holds x, y, z (mm), sigma (mm) and, when the recording names its gear, the signed
    deviation from the CAD (mm, + outside the material; :func:`~gearscan.recon.cloud.save_cloud`). A folder that already holds burst clouds is
    refused, so that two runs never mix.
    """

    ply: Path | None = None
    csv: Path | None = None
    written: int = 0

    def __post_init__(self) -> None:
        for opt, folder in (("--ply", self.ply), ("--csv", self.csv)):
            if folder is None:
                continue
            if folder.suffix.lower() in EXPORT_SUFFIXES:
                raise ValueError(f"{opt}: expected a folder (one file per burst), got the file name {folder}; "
                                 "the fused cloud goes to --fuse FILE.ply/.csv")
            if folder.exists() and not folder.is_dir():
                raise ValueError(f"{opt}: {folder} exists and is not a folder")
            if folder.is_dir() and any(folder.glob("burst_*.*")):
                raise ValueError(f"{opt}: {folder} already holds burst clouds; choose an empty folder")

    def __call__(self, cloud: Cloud) -> None:
        if not len(cloud):
            return
        for folder, suffix in ((self.ply, ".ply"), (self.csv, ".csv")):
            if folder is not None:
                save_cloud(cloud, folder / f"burst_{cloud.burst_index:06d}{suffix}")
        self.written += 1


#: Largest memory the frame fit of ``replay(refine=True)`` may keep (frames and depth maps).
REFINE_MAX_BYTES = 8 << 30


def make_refiner(reader: RecordingReader, rig: Rig, period_px: float, fuse: CloudFuser | None, factory=None,
                 rest_sigma_scale: float | None = None):
    """The frame fit of a fused replay (``factory(rig, period_px, rest_sigma_scale=c)``, default
    :class:`~gearscan.recon.track.TrackRefiner` with the product's settings), its unfitted points' sigma scale ``c``
    the decoding model's own where it names one, else the product's; refused up front (not after the replay) when it
    cannot run."""
    from gearscan.recon.track import REST_SIGMA_SCALE, TrackRefiner

    if fuse is None:
        raise ValueError("refine: the frame fit refines a fused model; fuse the replay too (--fuse FILE)")
    first = reader.frame(0).image
    need = TrackRefiner.memory_bytes(len(reader), *first.shape, first.dtype.itemsize)
    if need > REFINE_MAX_BYTES:
        raise RecordingError(f"{reader.path}: refining keeps every frame in memory, {need / 2**30:.1f} GiB for "
                             f"{len(reader)} frames (limit {REFINE_MAX_BYTES / 2**30:.0f} GiB); replay a shorter "
                             "stretch (one revolution) or leave refinement off (--no-refine)")
    if isinstance(factory, partial) and "rest_sigma_scale" in factory.keywords:  # it would be overridden silently
        raise ValueError("refiner_factory: the unfitted points' sigma scale is the decoding model's (its JSON's "
                         "rest_sigma) or the product's; a factory may not set rest_sigma_scale")
    return (factory or TrackRefiner)(rig, period_px,
                                     rest_sigma_scale=REST_SIGMA_SCALE if rest_sigma_scale is None else rest_sigma_scale)


def replay(
    recording: str | Path,
    *,
    decoder: Callable[[Burst], object] | None = None,
    save: str | Path | None = None,
    connect: str | None = None,
    spawn: bool = False,
    metrics_path: str | Path | None = None,
    speed: float | None = None,
    reconstruct: bool = True,
    truth: bool = True,
    on_burst: Callable[[Measurement, dict], None] | None = None,
    unwrap: str = "cad",
    fuse: CloudFuser | None = None,
    rig: str | Path | Rig | None = None,
    export: CloudExport | None = None,
    refine: bool = False,
    network_support_px: int | None | Literal["product"] = PRODUCT_SUPPORT,
    max_sigma: float | None = None,
    refiner_factory: Callable[..., object] | None = None,
    point_sigma_mm: float | None = None,
    shading: str | None = None,
) -> ReplayMetrics:
    """Run ``recording`` through the pipeline. ``speed=None`` means as fast as possible.

    ``network_support_px``: the reconstructor's fringe-support test of a network's pixels (None: off; ``"product"``:
    the decoding model's own for this call, its ``frame_fit_px`` when ``fuse`` and ``refine`` fit the fused points
    to the frames, else its ``per_burst_px`` (``decoder.network_support``); where it names none, the product's,
    :data:`~gearscan.recon.measure.FRAME_FIT_NETWORK_SUPPORT_PX` or :data:`~gearscan.recon.measure.NETWORK_SUPPORT_PX`).
    ``max_sigma``: the keep bound, rad (a point is reported where its total phase sigma is at most this; the fringe
    orders are found on the pixels within ``recon.measure.UNWRAP_MAX_SIGMA``, since session 45 the keep bound itself);
    None: the product's for the path, :data:`~gearscan.recon.measure.FRAME_FIT_MAX_SIGMA_RAD` when ``fuse`` and
    ``refine`` fit the fused points to the frames, else :data:`~gearscan.recon.measure.MAX_SIGMA_RAD`. ``unwrap`` picks how fringe orders are found (``"cad"``, or CAD-free ``"envelope"`` or
    ``"coarse"`` around the recording's coarse bursts, :class:`~gearscan.recon.measure.Reconstructor`). ``truth=False`` skips the scoring against a twin recording's truth (CAD distance of every
    point, a three-step baseline), so the run costs what a live run costs.

    Damage (a bad frame, index or encoder line) is skipped and logged once; the bursts it
    touches are dropped by the assembler, every other burst is measured, and
    ``metrics.damage`` lists it (``gearscan replay --strict`` turns it into a failure).

    ``fuse``: every burst's cloud goes into this fuser; at the end ``metrics.fused`` holds the
    fused model with its signed deviation from the CAD, also logged to the viewer. ``refine``
    (with ``fuse``): the fused points are then fitted to every raw frame that saw them
    (:class:`~gearscan.recon.track.TrackRefiner`; keeps the recording's frames in memory).
    ``refiner_factory(rig, period_px, rest_sigma_scale=c)``: that fit with other settings than the product's (the rule scripts'
    candidates), e.g. ``functools.partial(TrackRefiner, settle_rad=0.1)``. ``point_sigma_mm``: the fitted cloud's bound
    on every point's sigma, mm (None: the fit's own, :data:`~gearscan.recon.track.MAX_POINT_SIGMA_MM`); needs the fit.
    ``shading``: how the fit models the light a point gets as the gear turns (``"drift"``, ``"lambert"``, ``"quadratic"`` or ``"mixed"``,
    :data:`~gearscan.recon.track.SHADINGS`; None: the product's, :data:`~gearscan.recon.track.SHADING`); needs the fit.

    ``rig``: the calibration (file or :class:`Rig`) for a recording made without one; it
    replaces the recording's own when both exist. ``export``: every burst's cloud is also
    written as files (:class:`CloudExport`).
    """
    from gearscan.acquisition.bursts import BurstAssembler
    from gearscan.acquisition.camera import GrabTimeout
    from gearscan.mocks.replay_camera import ReplayCamera

    fit_options: dict = {}
    if point_sigma_mm is not None:  # refused before anything is replayed
        if not (refine and fuse is not None):
            raise ValueError("point_sigma_mm: the bound on the fitted cloud's points needs the frame fit (refine with fuse)")
        if refiner_factory is not None:
            raise ValueError("point_sigma_mm: give the bound to the refiner_factory's refiner instead")
        if not (math.isfinite(point_sigma_mm) and point_sigma_mm > 0):
            raise ValueError(f"point_sigma_mm: expected a finite sigma > 0 mm, got {point_sigma_mm}")
        fit_options["max_sigma_mm"] = point_sigma_mm
    if shading is not None:
        from gearscan.recon.track import SHADINGS

        if not (refine and fuse is not None):
            raise ValueError("shading: the shading model is the frame fit's; it needs the fit (refine with fuse)")
        if refiner_factory is not None:
            raise ValueError("shading: give the shading model to the refiner_factory's refiner instead")
        if shading not in SHADINGS:
            raise ValueError(f"shading: expected one of {', '.join(SHADINGS)}, got {shading!r}")
        fit_options["shading"] = shading
    if fit_options:
        from gearscan.recon.track import TrackRefiner

        refiner_factory = partial(TrackRefiner, **fit_options)
    reader = RecordingReader(recording)
    reader.encoder_samples()  # replay uses the frames' angles; this counts encoder.jsonl damage
    if len(reader) < 3:
        raise RecordingError(f"{reader.path}: {len(reader)} complete frames, a burst needs 3")
    decoder = decoder or Decoder(classical=True)
    rig = recording_rig(reader, rig)
    adopt_rig = getattr(decoder, "adopt_rig", None)  # the network's fringe orientation from the calibration
    if adopt_rig is not None:
        adopt_rig(rig)
    patterns = reader.patterns
    period = patterns.periods[0]
    coarse_period = patterns.coarse_period_px
    if unwrap == "coarse" and coarse_period is None:
        raise RecordingError(f"{reader.path}: --unwrap coarse needs coarse bursts, and this recording's pattern set "
                             f"({patterns.name}) has none; use --unwrap cad (with the gear's CAD) or envelope")
    gear = reader.gear
    if network_support_px == PRODUCT_SUPPORT:
        network_support_px = network_support_option(None, frame_fit=refine and fuse is not None,
                                                     model=getattr(decoder, "network_support", None))
    max_sigma = keep_bound_option(max_sigma, frame_fit=refine and fuse is not None)
    depth_scales, depth_source = decoder_depth_sigma(decoder)
    recon = (Reconstructor.for_gear(rig, period, gear, unwrap=unwrap, network_support_px=network_support_px,
                                    max_sigma=max_sigma,  # the decoding model's own depth-sigma scales, else the product's
                                    depth_sigma_scales=depth_scales)
             if (reconstruct and gear is not None) else None)
    coarse = CoarseStage(rig, coarse_period, gear, recon if unwrap == "coarse" else None)
    scorer = TruthScorer(reader) if (truth and reader.has_truth()) else None
    export_cad = CadScorer(gear) if (export is not None and gear is not None) else None  # deviation in every file
    logger = None
    if save or connect or spawn:
        from gearscan.viewer.log import RerunLogger

        logger = RerunLogger(save=save, connect=connect, spawn=spawn)
        logger.log_rig(rig)
    metrics = ReplayMetrics()
    if recon is not None:  # what the reconstructor ran: network_support_px None is no test
        metrics.recon = {"unwrap": unwrap, "network_support_px": network_support_px, "max_sigma_rad": max_sigma,
                         "unwrapper_sees": unwrapper_sees(recon.unwrap_max_sigma),
                         "depth_sigma_scales": recon.depth_sigma_scales.as_dict(),
                         "depth_sigma_source": depth_source,
                         "frame_fit": bool(refine and fuse is not None)}
    refiner = None
    if refine:
        rest_scale, rest_source = decoder_rest_sigma(decoder)
        refiner = make_refiner(reader, rig, period, fuse, refiner_factory, rest_sigma_scale=rest_scale)
        if metrics.recon is not None:  # the scale the unfitted points' sigma carried (the model's own or the product's)
            metrics.recon["rest_sigma_scale"] = getattr(refiner, "rest_sigma_scale", None)
            metrics.recon["rest_sigma_source"] = rest_source
    assembler = BurstAssembler(groups=1 if coarse_period is None else 2)
    camera = ReplayCamera(reader, realtime=speed is not None, speed=speed or 1.0)

    def frames():
        camera.open()
        camera.start()
        while True:
            try:
                yield camera.grab(timeout=5.0)
            except GrabTimeout:
                if camera.exhausted.is_set():  # every frame served (damaged ones skipped)
                    return
                raise

    def close_camera():
        camera.stop()
        camera.close()

    def output(m: Measurement) -> None:
        m, row, err, mask = scorer(m) if scorer else (m, {"burst": m.burst.index}, None, None)
        metrics.per_burst.append(row)
        if logger:
            logger.log_burst(m.burst, m.result, mask=mask, cloud=m.cloud, error=err,
                             stats={k: v for k, v in row.items() if k.endswith(("rmse_rad", "rms_mm"))},
                             unresolved=m.unresolved, mixed=m.mixed)
        if fuse is not None and m.cloud is not None and len(m.cloud):
            fuse.add(m.cloud)
        if refiner is not None:
            refiner.add(m)
        if export is not None and m.cloud is not None:
            cloud = m.cloud
            if cloud.deviation is None and export_cad is not None and len(cloud):
                cloud = replace(cloud, deviation=export_cad.distances(cloud.points))
            export(cloud)
        if on_burst:
            on_burst(m, row)

    def close_output() -> None:
        if fuse is not None and fuse.bursts_added:
            try:
                fused = fuse.result()
            except ValueError as exc:  # no point in any burst
                log.warning("nothing fused: %s", exc)
            else:
                if refiner is not None and len(refiner):
                    fused, metrics.refine = refiner.refine_fused(fused)
                if gear is not None:  # the deviation's own sigma needs the fit's rays (fusion's sigma flatters)
                    cad = CadScorer(gear)
                    fused = fused.with_deviation(cad.distances(fused.points), None if fused.ray is None else
                                                 cad.deviation_sigma(fused.points, fused.sigma, fused.ray, fused.refined))
                metrics.fused = fused
                if logger and metrics.fused.deviation is not None:
                    logger.log_fused(metrics.fused.points, metrics.fused.deviation, bursts=fused.bursts_added,
                                     sigma=fused.sigma, deviation_sigma=fused.deviation_sigma)
        if logger:
            logger.close()

    stages = [
        StageSpec("assemble", assembler.push),
        StageSpec("infer", lambda b: Measurement(b, decoder(b)), queue_size=2, workers=getattr(decoder, "workers", 1)),
        StageSpec("reconstruct", lambda m: coarse(m) if m.burst.group else (recon(m.burst, m.result) if recon else m),
                  close=recon.close if recon else None),
        StageSpec("output", output, close=close_output, queue_size=8),
    ]
    if speed is None:  # as fast as possible: nothing may be dropped
        for s in stages:
            s.queue_size = max(s.queue_size, len(reader))
    pipeline = Pipeline(frames, stages, source_name="camera", source_close=close_camera)
    report: PipelineReport = pipeline.run()
    metrics.pipeline = report.stages
    metrics.assembler = assembler.stats.as_dict() | {"coarse_bursts": coarse.bursts}
    metrics.damage = reader.damage_summary()
    if isinstance(decoder, Decoder):
        metrics.decoder = decoder.summary()
    if recon is not None:  # network bursts whose span no val run calibrated the depth sigma for
        metrics.recon["bursts_sigma_uncalibrated"] = recon.uncalibrated_bursts
    if metrics_path:
        Path(metrics_path).write_text(json.dumps(metrics.to_json(), indent=2))
    return metrics
