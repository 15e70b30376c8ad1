"""The reconstruct stage: PhaseResult -> fringe orders -> points in the turntable frame with depth sigma.

``Reconstructor`` unwraps a burst's phase within the rig's whole unambiguous range around the gear's
CAD at the burst's encoder angle (or CAD-free from the gear's envelope, or around a coarse burst's
surface), triangulates it with per-point depth uncertainty and moves the points into the turntable
frame at that angle.
"""

from __future__ import annotations

import logging
import math
from typing import Protocol

import numpy as np

from gearscan.core.rig import Rig
from gearscan.core.types import Burst, Measurement, PhaseResult
from gearscan.recon.depth_sigma import (
    CALIBRATED_SPAN_DEG,
    DEPTH_SIGMA_SCALES,
    DepthSigmaScales,
    check_scales,
    scale_depth_sigma,
    sigma_calibrated,
    span_deg,
)

logger = logging.getLogger(__name__)

UNWRAP_MODES = ("cad", "envelope", "coarse")
# The product's fringe-support tests, for a model whose JSON names none (each shipped model carries its own,
# `network_support`, which `network_support_option` prefers); both are the shipped v9's val choices.
# A network's pixel needs fringes in its own frames on every pixel within this many px (val choice,
# benchmarks/network_support_rule.md; scripts/choose_network_support.py -> benchmarks/network_support_val.json):
# 2 px for v6; for v9 0 px (its own pixel only: the outside-mask loss taught it not to invent phase there), and
# 1 px since its additive-local sigma maps (session 43's rerun: within 1 % of the best mean RMS, the smallest E), and
# no test (None) since session 44, kept by session 45's reruns on a val sample with the 0.5-3 deg motions users bring
# (0 px, chosen for an hour on the paper's motions alone, missed both coverage floors there), the last under the
# unwrap setting that ships (seed 1500)
NETWORK_SUPPORT_PX: int | None = None
# ... and where the fused points are then fitted to the raw frames (`inspect`, `replay --fuse`): the frame fit
# takes the pixels a test removes better than the test does (val choice, benchmarks/fused_support_rule.md;
# scripts/choose_fused_support.py -> benchmarks/fused_support_val.json): 0 px for v6, no test (None) for v9, and 0 px
# again since session 46's rerun at this path's own keep bound (0.5 rad); none since session 48's joint choice of this
# path's bound and test with the fit's settle and modulation tests in place (benchmarks/frame_fit_joint_rule.md,
# scripts/choose_frame_fit_joint.py -> benchmarks/frame_fit_joint_val.json)
FRAME_FIT_NETWORK_SUPPORT_PX: int | None = None
PRODUCT_SUPPORT = "product"  # a library default (replay, run_inspection): the decoding model's test for the path
# taken, else the product's (network_support_option)
# The keep bound: a point is reported where its total phase sigma is at most this (rad). 0.3 until session 44 (never
# chosen on data); the val choice (benchmarks/keep_bound_rule.md; scripts/choose_keep_bound.py ->
# benchmarks/keep_bound_val.json): 0.5 with v9's per-burst fringe-support test at 1 px, 0.7 without it (session 44) ...
MAX_SIGMA_RAD = 0.7
# ... and the unwrapper sees the modulated pixels within this bound (inf: all of them; None: the keep bound itself).
# Session 44 chose inf on the paper's motions (at 0.3 rad the bound first hid the neighbours that expose a wrong
# fringe order: 2,731 still-burst points beyond 0.5 mm against 4); session 45's rerun on a val sample with the 0.5-3
# deg motions chose the keep bound itself (None): there every modulated pixel gave more moving gross points at 0.3 rad
# (41,075 against 39,501), which the rule's first step then did not allow, and at 0.7 rad the two are close; session
# 46's amended first step compares them at the bounds that ship and kept None on a fresh sample (seed 1600)
UNWRAP_MAX_SIGMA: float | None = None
# ... and on the path that fits fused points to the raw frames (`inspect`, `replay --fuse`), its own keep bound: a
# fused voxel's frame fit can settle on a wrong solution from per-burst points the bound let in (held-out stretch
# seed 23, fixed order, session 46); val choice, benchmarks/frame_fit_keep_bound_rule.md
# (scripts/choose_frame_fit_keep_bound.py -> benchmarks/frame_fit_keep_bound_val.json): 0.5 with the path's support
# test off (7 % below 0.7 in the geometric-mean cloud RMS of four val stretches), then 0.7 again once that test went
# to 0 px (0.5 missed a coverage floor by 0.02 points): session 46, the last iteration that session; 0.5 with the
# test off since session 48, the two chosen jointly on 12 val cells with the fit's settle and modulation tests in
# place (benchmarks/frame_fit_joint_rule.md -> frame_fit_joint_val.json: 3.4 % below 0.7 rad / 0 px)
FRAME_FIT_MAX_SIGMA_RAD = 0.5


def keep_bound_option(max_sigma: float | None, *, frame_fit: bool = False) -> float:
    """A ``--max-sigma-rad`` as the reconstructor's keep bound: None keeps the product's for the path taken
    (:data:`FRAME_FIT_MAX_SIGMA_RAD` where fused points are fitted to the frames, else :data:`MAX_SIGMA_RAD`)."""
    if max_sigma is None:
        return FRAME_FIT_MAX_SIGMA_RAD if frame_fit else MAX_SIGMA_RAD
    return max_sigma


class ModelSupport(Protocol):
    """A model's own fringe-support tests, chosen on val (``inference.predictor.NetworkSupport``)."""

    per_burst_px: int | None
    frame_fit_px: int | None


def network_support_option(px: int | None, *, frame_fit: bool = False, model: ModelSupport | None = None) -> int | None:
    """A ``--network-support-px`` (or the live config's) as the reconstructor's setting. None keeps the decoding
    model's own (``model``: its ``frame_fit_px`` where fused points are fitted to the frames, else its
    ``per_burst_px``), or, where the model names none, the product's (:data:`FRAME_FIT_NETWORK_SUPPORT_PX`,
    :data:`NETWORK_SUPPORT_PX`); a negative value turns the test off."""
    if px is None:
        if model is not None:
            return model.frame_fit_px if frame_fit else model.per_burst_px
        return FRAME_FIT_NETWORK_SUPPORT_PX if frame_fit else NETWORK_SUPPORT_PX
    return None if px < 0 else px


ENVELOPE_MM = 1.0  # CAD-free unwrapping: how far the gear may stand outside its tip/root cylinders


def envelope_bounds(rig: Rig, gear, envelope_mm: float = ENVELOPE_MM):
    """Depth bounds of the gear's envelope (tip and root cylinders and face slab, widened by
    ``envelope_mm``): what CAD-free unwrapping knows of the gear."""
    from gearscan.recon.unwrap import gear_depth_bounds

    return gear_depth_bounds(rig, gear.tip_radius + envelope_mm, max(gear.root_radius - envelope_mm, 1e-3),
                             gear.face_width + 2 * envelope_mm)


def unwrapper_sees(unwrap_max_sigma: float | None = UNWRAP_MAX_SIGMA, max_sigma: float = MAX_SIGMA_RAD) -> str:
    """Which pixels the unwrapper sees, in words (the replay metrics and the val choices' records); None: those
    within the keep bound ``max_sigma``, as the reconstructor reads it. Defaults: what ships."""
    bound = max_sigma if unwrap_max_sigma is None else unwrap_max_sigma
    return "every modulated pixel" if math.isinf(bound) else f"modulated pixels with sigma <= {bound} rad"


def keep_candidates(result: PhaseResult, images: np.ndarray, full_scale: float, *, min_modulation: float = 0.05,
                    max_sigma: float = MAX_SIGMA_RAD, network_support_px: int | None = NETWORK_SUPPORT_PX) -> tuple[np.ndarray, np.ndarray]:
    """The reconstructor's keep test: ``(candidate, unsupported)`` pixel masks.

    Candidates have a finite phase, modulation >= ``min_modulation`` and total sigma <= ``max_sigma``; a network's
    (:attr:`~gearscan.core.types.PhaseResult.from_network`) also need fringes in the burst's own ``images`` on every pixel
    within ``network_support_px`` (:func:`~gearscan.core.phase.fringe_support`); ``unsupported``: the pixels that
    test alone removed."""
    candidate = np.isfinite(result.phase) & (result.modulation >= min_modulation) & (result.sigma_total <= max_sigma)
    unsupported = np.zeros(candidate.shape, bool)
    if network_support_px is not None and result.from_network:
        from gearscan.core.phase import fringe_support

        support = fringe_support(images, full_scale, min_modulation, network_support_px)
        unsupported = candidate & ~support
        candidate = candidate & support
    return candidate, unsupported


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
    The fringe orders are found first on every modulated pixel with a sigma within
    ``unwrap_max_sigma`` (inf: all, so the sigma bound picks the reported points, not the neighbours that expose a
    wrong order; None: ``max_sigma``, the default since session 45's val rerun, benchmarks/keep_bound_rule.md).
    Points whose pixel may blend two surfaces (at a silhouette or depth step, camera blur mixes
    their fringes) are dropped and counted as ``mixed`` (:func:`~gearscan.recon.edges.mixed_pixels`,
    ``mixed_border_px=None`` keeps them). A network's phase (``PhaseResult.from_network``: mode "deterministic" or "mc<T>")
    is a candidate only where the burst's own frames show fringes on every pixel within
    ``network_support_px`` (:func:`~gearscan.core.phase.fringe_support`): the network was trained on the twin's
    truth mask alone and invents phase, modulation and a small sigma at shadow borders, creases and silhouettes;
    such pixels are counted as ``unsupported`` (``None``: no such test). Each point's depth sigma is the phase
    sigma propagated through the triangulation, times the scale of its band of distance to the edge of the burst's
    cloud for the burst's motion class (three-step PS, the network within its trained span, beyond it:
    ``depth_sigma_scales``, per class or one set for all; None: the product's, :mod:`gearscan.recon.depth_sigma`). An
    undistorted projector takes the fused unwrap + triangulate path
    (:mod:`gearscan.recon.reconstruct`); a distorted one the fixed-point
    :class:`~gearscan.recon.triangulate.Triangulator`.
    """

    def __init__(self, rig: Rig, period_px: float, gear, *, min_modulation: float = 0.05,
                 max_sigma: float = MAX_SIGMA_RAD, margin: float = 0.3, unwrap: str = "cad",
                 envelope_mm: float = ENVELOPE_MM, silhouette_mm: float = 0.4, mixed_border_px: int | None = 1,
                 network_support_px: int | None = NETWORK_SUPPORT_PX, unwrap_max_sigma: float | None = UNWRAP_MAX_SIGMA,
                 depth_sigma_scales: DepthSigmaScales | tuple[float, ...] | None = None, threads: int | None = None) -> None:
        from gearscan.recon.reconstruct import SingleFrequencyReconstructor
        from gearscan.recon.triangulate import Triangulator
        from gearscan.recon.unwrap import CadDepthBounds, phase_bounds

        if unwrap not in UNWRAP_MODES:
            raise ValueError(f"unwrap: expected one of {UNWRAP_MODES}, got {unwrap!r}")
        if not 0 <= margin < math.pi / 2:
            raise ValueError(f"margin: expected 0 <= margin < pi/2 rad, got {margin}")
        if network_support_px is not None and network_support_px < 0:
            raise ValueError(f"network_support_px: expected None or >= 0 px, got {network_support_px}")
        if not max_sigma > 0:
            raise ValueError(f"max_sigma: expected > 0 rad, got {max_sigma}")
        if unwrap_max_sigma is not None and not unwrap_max_sigma >= max_sigma:
            raise ValueError(f"unwrap_max_sigma: expected None or >= max_sigma ({max_sigma} rad), got {unwrap_max_sigma}")
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
        if not np.any(rig.projector.dist != 0):  # (a rig's K has no skew: PinholeDevice refuses one)
            self.fused = SingleFrequencyReconstructor(rig, period_px, margin=margin, threads=threads)
        else:
            self.triangulator = Triangulator(rig, period_px)
        self.min_modulation = min_modulation
        self.max_sigma = max_sigma
        self.unwrap_max_sigma = max_sigma if unwrap_max_sigma is None else float(unwrap_max_sigma)
        self.margin = margin
        self.mixed_border_px = mixed_border_px
        self.network_support_px = network_support_px
        self.depth_sigma_scales = check_scales(DEPTH_SIGMA_SCALES if depth_sigma_scales is None else depth_sigma_scales)
        self.uncalibrated_bursts = 0  # network bursts spanning beyond CALIBRATED_SPAN_DEG: their sigma is unmeasured

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
        from gearscan.recon.unwrap import unambiguous_depth_window

        cad = self.cad
        if cad is None:
            raise ValueError("depth_range_mm needs the gear's CAD (unwrap='cad')")
        depth = cad.depth(angle)
        # along each ray, through the projector's lens, where it lights the surface
        lo, hi = unambiguous_depth_window(self.rig, self.period_px, depth, margin=self.margin)
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
        # the unwrapper sees every pixel within the unwrap bound (by default the keep bound); the keep bound then picks the points
        usable, unsupported = keep_candidates(result, burst.images, burst.full_scale, min_modulation=self.min_modulation,
                                              max_sigma=self.unwrap_max_sigma, network_support_px=self.network_support_px)
        within = result.sigma_total <= self.max_sigma
        candidate = usable & within
        unsupported &= within
        if self.mode in ("cad", "coarse"):
            source = self.cad if self.mode == "cad" else self.prior
            depth = (source.depth(burst.angles[0], usable) if source is not None
                     else np.full(cam_shape, np.nan, np.float32))
            prior = (self.fused.phase_of_depth(depth) if self.fused is not None
                     else phase_bounds(self.rig, DepthBounds(depth, depth), self.period_px)[0])
            regions = prior_unwrap(result.phase, usable, prior, margin=self.margin,
                                   silhouette_px=self.silhouette_px)
        else:
            regions = envelope_unwrap(result.phase, usable, *self._envelope, margin=self.margin)
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
        # the depth sigma by distance to the edge of this burst's cloud, for its motion class (recon/depth_sigma.py)
        scales = self.depth_sigma_scales.for_burst(burst.angles, result.from_network)
        if not sigma_calibrated(burst.angles, result.from_network):
            self.uncalibrated_bursts += 1
            if self.uncalibrated_bursts == 1:
                logger.warning("burst %d spans %.2f deg (frame 1 to 3): the depth sigma's scales were calibrated on val "
                               "up to %.1f deg (recon.depth_sigma); its points' sigma beyond that is not measured "
                               "(later such bursts are counted, not logged)", burst.index,
                               span_deg(burst.angles), CALIBRATED_SPAN_DEG)
        tri = Triangulation(points=tri.points, depth=tri.depth,
                            sigma_depth=scale_depth_sigma(tri.sigma_depth, tri.valid, scales), valid=tri.valid)
        stats = {
            "candidates": int(candidate.sum()),
            "points": int(keep.sum()),
            "regions": regions.regions,
            "regions_resolved": regions.resolved_regions,
            "unresolved": int(unresolved.sum()),
            "mixed": int(mixed.sum()),
            "unsupported": int(unsupported.sum()),
        }
        cloud = to_cloud(tri, self.rig, result.angle, burst_index=burst.index)
        return Measurement(burst, result, cloud, phase_abs, tri.valid, unresolved, stats, mixed)


class CoarseStage:
    """Takes the coarse bursts out of the stream: with ``unwrap="coarse"`` each one is unwrapped by
    the gear's envelope and its cloud becomes the prior of the fine bursts after it
    (:mod:`gearscan.recon.cloud_prior`); otherwise it is only counted. It emits nothing."""

    def __init__(self, rig: Rig, period_px: float | None, gear, fine: Reconstructor | None) -> None:
        self.bursts = 0
        self.rig = rig
        self.fine = fine
        self.recon = None
        if fine is not None and period_px is not None:
            # no mixed-pixel filter: a prior needs the surface to a fraction of the fine range, edges included
            self.recon = Reconstructor.for_gear(rig, period_px, gear, unwrap="envelope", mixed_border_px=None)

    def __call__(self, m: Measurement) -> None:
        from gearscan.recon.cloud_prior import CloudDepthPrior

        self.bursts += 1
        if self.recon is not None:
            measured = self.recon(m.burst, m.result)
            self.fine.set_prior(CloudDepthPrior(self.rig, measured.cloud.points))
