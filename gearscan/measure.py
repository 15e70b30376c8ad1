"""The measurement stages between a burst and the viewer: decode, then reconstruct.

``Decoder`` turns a :class:`Burst` into a :class:`PhaseResult` (CD-DCU-Net, or three-step
phase shifting as the classical fallback); ``Reconstructor`` unwraps it within the rig's whole
unambiguous range around the gear's CAD at the burst's encoder angle (or CAD-free from the
gear's envelope), triangulates it with per-point depth uncertainty and moves the points into
the turntable frame at that angle; ``CadScorer`` measures their deviation from the CAD.
"""

from __future__ import annotations

import logging
import math
import os
import queue
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gearscan.core.phase import three_step
from gearscan.core.rig import Rig
from gearscan.core.types import Burst, Cloud, PhaseResult

log = logging.getLogger(__name__)

STILL_SPAN_DEG = 0.075  # below this burst span three-step PS beats the network (Decoder)


def classical_result(burst: Burst, read_noise_dn: float = 1.0) -> PhaseResult:
    """Three-step phase shifting of a burst.

    Its data uncertainty is the noise-only phase sigma ``s_I sqrt(2/N) / B`` for a read noise
    of ``read_noise_dn``; three-step PS has no estimate of its (dominant) motion error.
    """
    phase, m, d = three_step(burst.images, burst.full_scale)
    mod = np.hypot(m, d)  # 2B/S
    with np.errstate(divide="ignore"):
        sigma = np.where(mod > 0, (2.0 * read_noise_dn / burst.full_scale) * np.sqrt(2 / 3) / mod, np.inf)
    sigma = sigma.astype(np.float32)
    return PhaseResult(
        phase=phase, M=m, D=d, sigma_model=np.zeros_like(sigma), sigma_data=sigma, sigma_total=sigma,
        mode="three-step", burst_index=burst.index, angle=float(burst.angles[0]),
    )


class Decoder:
    """Burst -> PhaseResult with the network (``mc`` passes, 0 = deterministic) or three-step PS.

    ``workers`` > 1 decodes that many bursts at once, each on its own copy of the network
    with ``cores // workers`` torch threads (a process-wide torch setting): on a few CPU cores
    this beats one pass spread over all of them, whose threads stall whenever another stage
    takes a core (2 cores, 512x512: 3.6-4.8 -> 5.2-6.3 bursts/s, benchmarks/pipeline_report.md). The
    pipeline runs the infer stage with this many workers. None: 2 on a CPU with >= 2 cores, else 1.

    Bursts whose encoder angles span less than ``still_span_deg`` (frame 1 to 3) go to
    three-step PS instead of the network: without motion it has no motion error, and below
    about 0.075 deg it beat the shipped network on twin validation gears (static: 0.018 vs
    0.053 rad on the default rig, 0.064 vs 0.070 on randomised rigs; the network wins from
    0.1 deg on; benchmarks/still_crossover_report.md). 0 sends every burst to the network.
    """

    def __init__(self, model: str | Path | None = None, *, mc: int = 0, classical: bool = False,
                 precision: str = "auto", workers: int | None = None,
                 still_span_deg: float = STILL_SPAN_DEG) -> None:
        if workers is not None and workers < 1:
            raise ValueError(f"model.workers: expected >= 1, got {workers}")
        if not still_span_deg >= 0:
            raise ValueError(f"model.still_span_deg: expected >= 0 degrees, got {still_span_deg}")
        self.still_span = math.radians(still_span_deg)
        self.still_bursts = 0
        self.mc = mc
        self.workers = 1
        self.predictor = None
        self._pool: queue.SimpleQueue = queue.SimpleQueue()
        if not classical:
            from gearscan.inference.predictor import Predictor

            self.predictor = Predictor.load(model, precision=precision)
            cpu, cores = self.predictor.device.type == "cpu", len(os.sched_getaffinity(0))
            self.workers = workers if workers is not None else (2 if cpu and cores >= 2 else 1)
            for _ in range(self.workers - 1):  # own copies: MC switches the dropout masks per call
                self._pool.put(self.predictor.replica())
            self._pool.put(self.predictor)
            if cpu:
                self.use_threads(self.workers)
        self.mode = "three-step" if classical else (f"mc{mc}" if mc else "deterministic")

    @staticmethod
    def use_threads(workers: int) -> None:
        """Give each of ``workers`` concurrent CPU passes an equal share of the cores (torch is process-wide)."""
        import torch

        torch.set_num_threads(max(1, len(os.sched_getaffinity(0)) // workers))

    def __call__(self, burst: Burst) -> PhaseResult:
        if self.predictor is None or burst.group != 0:  # coarse bursts: three-step PS (the net knows fine fringes)
            return classical_result(burst)
        if abs(burst.angles[-1] - burst.angles[0]) < self.still_span:
            self.still_bursts += 1
            return classical_result(burst)
        predictor = self._pool.get()
        try:
            return predictor.predict_burst(burst, mc=self.mc)
        finally:
            self._pool.put(predictor)


UNWRAP_MODES = ("cad", "envelope", "coarse")
ENVELOPE_MM = 1.0  # CAD-free unwrapping: how far the gear may stand outside its tip/root cylinders


def envelope_bounds(rig: Rig, gear, envelope_mm: float = ENVELOPE_MM):
    """Depth bounds of the gear's envelope (tip and root cylinders and face slab, widened by
    ``envelope_mm``): what CAD-free unwrapping knows of the gear."""
    from gearscan.recon.unwrap import gear_depth_bounds

    return gear_depth_bounds(rig, gear.tip_radius + envelope_mm, max(gear.root_radius - envelope_mm, 1e-3),
                             gear.face_width + 2 * envelope_mm)


@dataclass
class Measurement:
    """Everything one burst produced, as it travels to the viewer and the metrics.

    ``unresolved`` marks pixels that passed the modulation and sigma tests but got no point
    (no prior there, or the surface outside the rig's unambiguous range); ``unwrap`` counts
    them by cause (``unresolved``; ``mixed``: points dropped because their pixel may blend two
    surfaces, :func:`~gearscan.recon.edges.mixed_pixels`), so nothing is dropped silently.
    """

    burst: Burst
    result: PhaseResult
    cloud: Cloud | None = None
    phase_abs: np.ndarray | None = None
    valid: np.ndarray | None = None
    unresolved: np.ndarray | None = None
    unwrap: dict[str, int] = field(default_factory=dict)


class Reconstructor:
    """PhaseResult -> absolute phase -> points (turntable frame) with depth sigma.

    One fringe period leaves each pixel's fringe order ambiguous beyond the rig's unambiguous
    depth range (one fringe along the ray: about 2.8 mm of camera depth on the default rig at
    40 px, :meth:`depth_range_mm`). The order comes from a prior that never narrows that range:

    * ``unwrap="cad"``: the gear's CAD at the burst's encoder angle; each pixel takes the order
      nearest the CAD surface, so a surface up to half a fringe off its CAD (about +-1.3 mm
      on the default rig) keeps its point and its true deviation. Within ``silhouette_mm`` of
      the CAD's silhouettes (where the CAD may see another surface than the real gear) the order
      is carried in from the surrounding surface instead (:func:`~gearscan.recon.unwrap.prior_unwrap`).
    * ``unwrap="envelope"`` (CAD-free): spatial unwrapping per connected region, each region's
      order fixed by the gear's envelope (tip and root cylinders widened by ``envelope_mm``);
      needs no CAD surface, only the radii and face width.
    * ``unwrap="coarse"`` (CAD-free, any fringe period): as ``"cad"``, around the surface a coarse
      burst measured (:meth:`set_prior`, :mod:`gearscan.recon.cloud_prior`).

    In both modes the order is made consistent over each connected region of continuous phase
    (:func:`~gearscan.recon.unwrap.prior_unwrap`, :func:`~gearscan.recon.unwrap.envelope_unwrap`).
    Pixels are candidates where the modulation is above ``min_modulation`` (2B/S) and the total
    phase sigma is below ``max_sigma`` rad; a candidate without a point is ``unresolved`` and
    counted in ``Measurement.unwrap`` (no order could be trusted there), never dropped silently.
    Points whose pixel may blend two surfaces (at a silhouette or depth step, camera blur mixes
    their fringes) are dropped and counted as ``mixed`` (:func:`~gearscan.recon.edges.mixed_pixels`,
    ``mixed_border_px=None`` keeps them). An
    undistorted projector takes the fused unwrap + triangulate path
    (:mod:`gearscan.recon.reconstruct`); a distorted one the fixed-point
    :class:`~gearscan.recon.triangulate.Triangulator`.
    """

    def __init__(self, rig: Rig, period_px: float, gear, *, min_modulation: float = 0.05,
                 max_sigma: float = 0.3, margin: float = 0.3, unwrap: str = "cad",
                 envelope_mm: float = ENVELOPE_MM, silhouette_mm: float = 0.4, mixed_border_px: int | None = 1,
                 threads: int | None = None) -> None:
        from gearscan.recon.reconstruct import SingleFrequencyReconstructor
        from gearscan.recon.triangulate import Triangulator
        from gearscan.recon.unwrap import CadDepthBounds, phase_bounds

        if unwrap not in UNWRAP_MODES:
            raise ValueError(f"unwrap: expected one of {UNWRAP_MODES}, got {unwrap!r}")
        if not 0 <= margin < math.pi / 2:
            raise ValueError(f"margin: expected 0 <= margin < pi/2 rad, got {margin}")
        self.rig = rig
        self.period_px = period_px
        self.mode = unwrap
        self.cad = None
        self._envelope = None
        self.silhouette_px = 0.0
        self.prior = None  # unwrap="coarse": the surface measured by the last coarse burst (set_prior)
        if unwrap == "cad":  # walls extruded along z: one layer is exact, and 5x fewer triangles
            self.cad = CadDepthBounds(rig, gear.mesh(layer_mm=gear.face_width))
            depth = self.cad.depth(0.0)
            z = float(np.nanmedian(depth)) if np.isfinite(depth).any() else np.nan
        elif unwrap == "coarse":  # the rim's distance from the camera sets the pixel scale
            z = float(np.linalg.norm(rig.camera.center_world[:2])) - gear.tip_radius
        if unwrap in ("cad", "coarse"):
            # how far (px) a silhouette moves when the surface is silhouette_mm off its prior
            px_per_mm = rig.camera.K[0, 0] / z if np.isfinite(z) and z > 0 else 1.0
            self.silhouette_px = max(1.5, silhouette_mm * px_per_mm)
        else:
            if not envelope_mm >= 0:
                raise ValueError(f"envelope_mm: expected >= 0, got {envelope_mm}")
            self._envelope = phase_bounds(rig, envelope_bounds(rig, gear, envelope_mm), period_px)
        self.fused = None
        if not np.any(rig.projector.dist != 0) and rig.projector.K[0, 1] == 0:
            self.fused = SingleFrequencyReconstructor(rig, period_px, margin=margin, threads=threads)
        else:
            self.triangulator = Triangulator(rig, period_px)
        self.min_modulation = min_modulation
        self.max_sigma = max_sigma
        self.margin = margin
        self.mixed_border_px = mixed_border_px

    @classmethod
    def for_gear(cls, rig: Rig, period_px: float, gear, **kw) -> Reconstructor:
        return cls(rig, period_px, gear, **kw)

    def close(self) -> None:
        if self.fused is not None:
            self.fused.close()

    def set_prior(self, prior) -> None:
        """``unwrap="coarse"``: unwrap the next bursts around this measured surface (an object with
        ``depth(angle, mask)``, e.g. :class:`~gearscan.recon.cloud_prior.CloudDepthPrior` of a coarse
        burst's cloud). Until one is set, every candidate pixel is unresolved."""
        if self.mode != "coarse":
            raise ValueError(f"set_prior: this reconstructor unwraps with {self.mode!r}, not 'coarse'")
        self.prior = prior

    def depth_range_mm(self, angle: float = 0.0) -> dict[str, float]:
        """The rig's unambiguous depth range (camera z, mm) on the gear's CAD surface at ``angle``:
        how far a surface may deviate from its prior and still get the right fringe order."""
        from gearscan.recon.reconstruct import SingleFrequencyReconstructor

        cad = self.cad
        if cad is None:
            raise ValueError("depth_range_mm needs the gear's CAD (unwrap='cad')")
        depth = cad.depth(angle)
        sf = self.fused or SingleFrequencyReconstructor(self.rig, self.period_px, margin=self.margin, threads=1)
        lo, hi = sf.depth_window(depth)
        ok = np.isfinite(lo) & np.isfinite(hi)
        if not ok.any():
            raise ValueError("the camera does not see the gear: no unambiguous range to state")
        minus, plus = (depth - lo)[ok], (hi - depth)[ok]
        return {"minus_median_mm": float(np.median(minus)), "plus_median_mm": float(np.median(plus)),
                "minus_min_mm": float(minus.min()), "plus_min_mm": float(plus.min())}

    def __call__(self, burst: Burst, result: PhaseResult) -> Measurement:
        from gearscan.recon.triangulate import Triangulation, to_cloud
        from gearscan.recon.unwrap import (
            DepthBounds,
            centred_unwrap,
            envelope_unwrap,
            phase_bounds,
            prior_unwrap,
        )

        cam_shape = (self.rig.camera.height, self.rig.camera.width)
        if result.phase.shape != cam_shape:
            raise ValueError(
                f"phase map {result.phase.shape} does not match the rig camera "
                f"{cam_shape}: wrong rig file for this camera/ROI?"
            )
        candidate = (result.modulation >= self.min_modulation) & (result.sigma_total <= self.max_sigma)
        if self.mode in ("cad", "coarse"):
            source = self.cad if self.mode == "cad" else self.prior
            depth = (source.depth(burst.angles[0], candidate) if source is not None
                     else np.full(cam_shape, np.nan, np.float32))
            prior = (self.fused.phase_of_depth(depth) if self.fused is not None
                     else phase_bounds(self.rig, DepthBounds(depth, depth), self.period_px)[0])
            regions = prior_unwrap(result.phase, candidate, prior, margin=self.margin,
                                   silhouette_px=self.silhouette_px)
        else:
            regions = envelope_unwrap(result.phase, candidate, *self._envelope, margin=self.margin)
        estimate = regions.phase_abs.astype(np.float32)  # the order: the phase is re-read from the burst
        if self.fused is not None:
            tri, order = self.fused(result.phase, result.sigma_total, centre_phase=estimate)
            keep = tri.valid & candidate
            phase_abs = np.where(keep, result.phase + np.float32(2 * np.pi) * order, np.float32(np.nan))
            tri = Triangulation(points=tri.points, depth=tri.depth, sigma_depth=tri.sigma_depth, valid=keep)
        else:
            un = centred_unwrap(result.phase, estimate, self.period_px, margin=self.margin)
            keep = un.valid & candidate
            tri = self.triangulator(np.where(keep, un.phase_abs, np.nan), result.sigma_total)
            keep = tri.valid
            phase_abs = np.where(keep, un.phase_abs, np.nan)
        unresolved = candidate & ~keep
        mixed = np.zeros(keep.shape, bool)
        if self.mixed_border_px is not None:
            from gearscan.recon.edges import mixed_pixels

            mixed = mixed_pixels(keep, tri.depth, tri.depth / self.rig.camera.K[0, 0], border_px=self.mixed_border_px)
            keep = keep & ~mixed
            phase_abs = np.where(keep, phase_abs, np.float32(np.nan))
            tri = Triangulation(points=tri.points, depth=tri.depth, sigma_depth=tri.sigma_depth, valid=keep)
        stats = {
            "candidates": int(candidate.sum()),
            "points": int(keep.sum()),
            "regions": regions.regions,
            "regions_resolved": regions.resolved_regions,
            "unresolved": int(unresolved.sum()),
            "mixed": int(mixed.sum()),
        }
        cloud = to_cloud(tri, self.rig, result.angle, burst_index=burst.index)
        return Measurement(burst, result, cloud, phase_abs, tri.valid, unresolved, stats)


class SurfaceDistance:
    """Signed distance of gear-frame points to a surface mesh (the CAD, or a twin's true gear)."""

    def __init__(self, mesh) -> None:
        import open3d as o3d

        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))

    def distances(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (mm, positive outside the material) of gear-frame ``points`` ``(N, 3)``."""
        import open3d as o3d

        pts = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
        return self.scene.compute_signed_distance(pts).numpy().astype(np.float64)


class CadScorer(SurfaceDistance):
    """Signed distance of each point to the gear's CAD mesh (the cloud's deviation map)."""

    def __init__(self, gear) -> None:
        super().__init__(gear.mesh())

    def __call__(self, m: Measurement) -> dict[str, float]:
        if m.cloud is None or not len(m.cloud):
            return {}
        d = self.distances(m.cloud.points)
        m.cloud.deviation = d
        return {"cad_rms_mm": float(np.sqrt(np.mean(d**2))), "cad_p95_mm": float(np.percentile(np.abs(d), 95))}
