"""The measurement stages between a burst and the viewer: decode, then reconstruct.

``Decoder`` turns a :class:`Burst` into a :class:`PhaseResult` (CD-DCU-Net, or three-step
phase shifting as the classical fallback); ``Reconstructor`` unwraps it with the geometric
constraint of the gear's tip and root cylinders, triangulates it with per-point depth
uncertainty and moves the points into the turntable frame at the burst's encoder angle.
"""

from __future__ import annotations

import logging
import math
import os
import queue
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gearscan.recon.phase import three_step
from gearscan.rig import Rig
from gearscan.types import Burst, Cloud, PhaseResult

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
        if self.predictor is None:
            return classical_result(burst)
        if abs(burst.angles[-1] - burst.angles[0]) < self.still_span:
            self.still_bursts += 1
            return classical_result(burst)
        predictor = self._pool.get()
        try:
            return predictor.predict_burst(burst, mc=self.mc)
        finally:
            self._pool.put(predictor)


@dataclass
class Measurement:
    """Everything one burst produced, as it travels to the viewer and the metrics."""

    burst: Burst
    result: PhaseResult
    cloud: Cloud | None = None
    phase_abs: np.ndarray | None = None
    valid: np.ndarray | None = None


class Reconstructor:
    """PhaseResult -> absolute phase -> points (turntable frame) with depth sigma.

    Fringe orders come from the geometric constraint: by default the gear's CAD model at the
    burst's encoder angle bounds each pixel's depth to ``+-cad_tolerance_mm`` (works for fine
    fringes); with ``cad_tolerance_mm=None`` the tip and root cylinders bound it (needs a fringe
    period above :func:`~gearscan.recon.unwrap.min_unambiguous_period`, about 96 px on the
    default rig). Pixels are kept where the order is unambiguous, the modulation is above
    ``min_modulation`` (2B/S) and the total phase sigma is below ``max_sigma`` rad; the CAD
    rays are cast only for pixels that pass the last two tests. An undistorted projector takes
    the fused unwrap + triangulate path (:mod:`gearscan.recon.reconstruct`); a distorted one the
    fixed-point :class:`~gearscan.recon.triangulate.Triangulator`.
    """

    def __init__(self, rig: Rig, period_px: float, gear, *, min_modulation: float = 0.05,
                 max_sigma: float = 0.3, margin: float = 0.3, cad_tolerance_mm: float | None = 0.3,
                 threads: int | None = None) -> None:
        from gearscan.recon.reconstruct import SingleFrequencyReconstructor
        from gearscan.recon.triangulate import Triangulator
        from gearscan.recon.unwrap import CadDepthBounds, gear_depth_bounds, phase_bounds

        self.rig = rig
        self.period_px = period_px
        self.cad_bounds = None
        if cad_tolerance_mm:  # walls extruded along z: one layer is exact, and 5x fewer triangles
            self.cad_bounds = CadDepthBounds(rig, gear.mesh(layer_mm=gear.face_width), cad_tolerance_mm)
        fixed = None if self.cad_bounds else gear_depth_bounds(rig, gear.tip_radius, gear.root_radius, gear.face_width)
        self.fused = None
        self._fixed_phase = None  # phase interval of the cylinder bounds, fixed-point path only
        if not np.any(rig.projector.dist != 0) and rig.projector.K[0, 1] == 0:
            self.fused = SingleFrequencyReconstructor(rig, period_px, fixed, margin=margin, threads=threads)
        else:
            self.triangulator = Triangulator(rig, period_px)
            if fixed is not None:
                self._fixed_phase = phase_bounds(rig, fixed, period_px)
        self.min_modulation = min_modulation
        self.max_sigma = max_sigma
        self.margin = margin

    @classmethod
    def for_gear(cls, rig: Rig, period_px: float, gear, **kw) -> Reconstructor:
        return cls(rig, period_px, gear, **kw)

    def close(self) -> None:
        if self.fused is not None:
            self.fused.close()

    def _phase_interval(self, angle: float, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Absolute-phase interval per pixel at turntable ``angle`` (fixed-point path)."""
        if self.cad_bounds is None:
            return self._fixed_phase
        from gearscan.recon.unwrap import phase_bounds

        return phase_bounds(self.rig, self.cad_bounds(angle, mask), self.period_px)

    def __call__(self, burst: Burst, result: PhaseResult) -> Measurement:
        from gearscan.recon.triangulate import Triangulation, to_cloud
        from gearscan.recon.unwrap import geometric_unwrap

        cam_shape = (self.rig.camera.height, self.rig.camera.width)
        if result.phase.shape != cam_shape:
            raise ValueError(
                f"phase map {result.phase.shape} does not match the rig camera "
                f"{cam_shape}: wrong rig file for this camera/ROI?"
            )
        candidate = (result.modulation >= self.min_modulation) & (result.sigma_total <= self.max_sigma)
        if self.fused is not None:
            depth = self.cad_bounds(burst.angles[0], candidate) if self.cad_bounds is not None else None
            tri, order = self.fused(result.phase, result.sigma_total, bounds=depth)
            keep = tri.valid & candidate
            phase_abs = np.where(keep, result.phase + np.float32(2 * np.pi) * order, np.float32(np.nan))
            tri = Triangulation(points=tri.points, depth=tri.depth, sigma_depth=tri.sigma_depth, valid=keep)
        else:
            phi_min, phi_max = self._phase_interval(burst.angles[0], candidate)
            un = geometric_unwrap(result.phase, phi_min, phi_max, self.period_px, margin=self.margin)
            keep = un.valid & candidate
            phase_abs = np.where(keep, un.phase_abs, np.nan)
            tri = self.triangulator(phase_abs, result.sigma_total)
        cloud = to_cloud(tri, self.rig, result.angle, burst_index=burst.index)
        return Measurement(burst, result, cloud, phase_abs, tri.valid)


class CadScorer:
    """Signed distance of each point to the gear's CAD mesh (the cloud's deviation map)."""

    def __init__(self, gear) -> None:
        import open3d as o3d

        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(gear.mesh()))

    def __call__(self, m: Measurement) -> dict[str, float]:
        import open3d as o3d

        if m.cloud is None or not len(m.cloud):
            return {}
        d = self.scene.compute_signed_distance(o3d.core.Tensor(m.cloud.points.astype(np.float32))).numpy()
        m.cloud.deviation = d.astype(np.float64)
        return {"cad_rms_mm": float(np.sqrt(np.mean(d**2))), "cad_p95_mm": float(np.percentile(np.abs(d), 95))}
