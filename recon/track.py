"""Refine a fused gear model on the raw frames: each point fitted to every frame that saw it.

A burst's phase carries the motion error of its three frames (the network corrects most of it,
not all: about 0.1 mm per burst at 0.6 deg/frame on the default rig), and averaging bursts in
:mod:`gearscan.recon.fuse` only shrinks that error as the square root of how many saw a point.
The frames themselves hold more: a gear-frame point ``X`` is at a known pixel in every frame
(rotate it by the frame's encoder angle, project it) where the camera measured
``I = A + B cos(psi)``, and the rig says which projector column, hence which fringe phase ``psi``,
lights ``X`` in that frame. Over the dozens of frames of a revolution that saw ``X`` the
pattern phase sweeps the whole circle (the point moves through the fringes as the gear turns),
so one linear least-squares fit per point gives the phase offset ``eps`` between what the frames
show and what ``X`` predicts. ``eps = 0`` exactly where ``X`` is on the real surface, so ``X`` is
moved along its camera ray by ``eps`` over the phase's depth sensitivity, and the fit repeated.

How the light on ``X`` changes as the gear turns is the fit's ``shading`` model. ``"drift"``: the mean intensity
and the modulation linear in the turn angle, no surface model. ``"lambert"``: both follow the projector's irradiance
``g = cos(incidence) / d^2`` at ``X`` in each frame, from ``X``'s normal (its fused neighbours' plane), times a
linear drift, plus constant ambient light: what a matt surface (and the twin) does. Over the 40-60 frames that see a
point ``g`` is not linear in the turn angle, and what a linear drift leaves of it biases the fitted phase by a few
millirad the same way for every point sampled alike (``benchmarks/frame_fit_shading_rule.md``). ``"quadratic"``: the
mean and the modulation quadratic in the turn angle, no surface model: it follows that curvature whatever the
surface's reflectance, at the price of three more terms. ``"mixed"``: each point's own choice of the two, made on
its samples when it has nearly converged: quadratic where the three more terms cost its phase little precision
(samples that span much of the turn), drift where they would cost much (few samples, lit over a short arc).

What it needs is only geometry and the encoder: the fused cloud (any decoder's) as the start,
within a fraction of a fringe of the surface. It uses no CAD, so a gear that is not its CAD
keeps its deviation. A frame that did not see the point (occluded, shadowed, another surface at
a silhouette) is left out when the burst it belongs to measured no point within ``visible_mm``
of ``X`` at that pixel, and samples far from the fit are dropped before the last solve.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from gearscan.core.phase import burst_shifts
from gearscan.core.rig import Rig, rot_z
from gearscan.core.types import Measurement
from gearscan.recon.fuse import FusedCloud

_CHUNK = 200_000  # points per vectorised block (bounds the temporary arrays to ~100 MB)
# a point the fit cannot take carries this many times its bursts' sigma (val calibration:
# benchmarks/rest_sigma_rule.md; scripts/calibrate_rest_sigma.py -> benchmarks/rest_sigma_val.json): 3.5 from session
# 34 to 49; 1.5 since session 50, whose reruns scaled the bursts' sigma by edge band (recon.depth_sigma, the
# default-rig option by its own scales) and amended the rule to judge the tail too
# (benchmarks/rest_sigma_val_before_depth_sigma.json is the run that chose 3.5); since session 54 (rerun 6) per model:
# this is the shipped model's, a model's own (its JSON's rest_sigma) replaces it; session 51's reruns with the depth
# sigma per motion class: 2.0 with the depth rule's third amendment (rest_sigma_val_amend3_depth_scales.json), 1.5
# again with its fifth, which ships (rest_sigma_val.json; session 50's run: rest_sigma_val_pooled_depth_scales.json)
REST_SIGMA_SCALE = 1.5
# a fitted point carries this many times its fit's standard error along the ray (>= 1): measured along the ray the
# unscaled error put 5-8 % of the fitted points beyond 2 sigma on val stretches (a Gaussian: 4.6 %). Val calibration
# (session 49): benchmarks/fit_sigma_rule.md, scripts/calibrate_fit_sigma.py -> benchmarks/fit_sigma_val.json
FIT_SIGMA_SCALE = 1.25
# largest phase correction (rad) the fit's last iteration may still make (None: no test, the incumbent until session 47).
# Chosen on val stretches: benchmarks/frame_fit_settle_rule.md, scripts/choose_frame_fit_settle.py
SETTLE_RAD: float | None = 0.03
# largest fitted fringe modulation over the fitted mean intensity, B / A, a fit may have (None: no test, until session 47).
# A camera intensity A + B cos(psi) >= 0 needs B <= A. Rule: benchmarks/frame_fit_modulation_rule.md
MODULATION_RATIO: float | None = 1.0
# the refined cloud's one bound on every point's sigma, fitted or not (mm): a fit must meet it to replace its fused
# point, an unfitted point above it is dropped and counted. Chosen on the seed-7 stretch (TrackRefiner's docstring);
# `inspect` and `replay --fuse` take another with --max-point-sigma-um
MAX_POINT_SIGMA_MM = 0.03
# how the fit models the intensity's change as the surface turns through the frames: "drift" (mean and modulation
# linear in the turn angle; the only model until session 58) or "lambert" (mean and modulation follow the projector's
# irradiance at the point, cos(incidence) over distance squared from the point's normal, times a linear drift; ambient
# light constant; the points it cannot take go to the drift fit). Val chose "lambert" (benchmarks/frame_fit_shading_rule.md,
# scripts/choose_frame_fit_shading.py -> frame_fit_shading_val.json), but with it the substitution benchmark's statement
# failed on a held-out gear (Fp, benchmarks/substitution_lambert_report.md) and the profile headlines did not improve:
# drift stayed the product's (until session 60's "mixed"), lambert an option (--frame-fit-shading lambert).
# "quadratic" (session 59): mean and modulation quadratic in the turn angle, no surface model: follows a curved
# shading without a normal or a reflectance.
# "mixed" (session 60): per point "quadratic" where its samples carry the three more terms, "drift" where they do not;
# the product's since session 60 (benchmarks/mixed_shading_rule.md: on the substitution benchmark U of pitch 52-65 %
# lower, of F_alpha 26 % and ff_alpha 11 % lower, fH_alpha 4 % higher, the statement held on 36 of 36 held-out readings)
SHADINGS = ("drift", "lambert", "quadratic", "mixed")
SHADING = "mixed"
# "mixed" keeps a point's quadratic fit where its phase's standard error is at most this many times the drift fit's on
# the same samples (benchmarks/mixed_shading_rule.md): the quadratic terms remove the curvature's bias, shared by the
# points sampled alike, at the price of variance, which is large only where the samples span little of the turn
MIXED_SIGMA_RATIO = 1.25
# "lambert" leaves out the samples lit more obliquely than this (cosine of the projector ray's incidence on the
# point's estimated normal): there a few degrees of normal error change the predicted irradiance by tens of percent
MIN_INCIDENCE_COS = 0.25


@dataclass
class _BurstView:
    images: np.ndarray  # (3, H, W) raw camera counts
    angles: np.ndarray  # (3,) rad
    depth: np.ndarray  # (H, W) float32 camera z (mm) of the burst's own points at angles[0]; NaN none
    shifts: np.ndarray  # (3,) rad, each frame's pattern shift in capture order


@dataclass(frozen=True)
class TrackResult:
    """Refined points (gear frame, mm) with what each fit used and how well it fitted."""

    points: np.ndarray  # (N, 3)
    sigma: np.ndarray  # (N,) mm along the ray; inf where not refined
    refined: np.ndarray  # (N,) bool: fitted on enough frames, sigma within max_sigma_mm, settled, B <= ratio x A
    frames: np.ndarray  # (N,) int: samples in the final fit
    moved_mm: np.ndarray  # (N,) distance moved along the ray (+ away from the camera)
    rays: np.ndarray  # (N, 3) unit gear-frame directions from the camera (the mean view of the bursts that saw each
    #                   point): the line the fit moves a point along and its sigma's direction; NaN where no burst saw it
    stats: dict = field(default_factory=dict)


class TrackRefiner:
    """Collects a revolution's bursts (frames, encoder angles, measured depth) and refines a fused cloud.

    ``min_frames``: fewest frames (after outlier removal) a point's fit needs; ``max_sigma_mm``:
    largest sigma along the ray a fit may have to replace the fused position (``fit_sigma_scale`` times the
    standard error from the fit's own covariance: residual noise, how evenly the frames' fringe phases cover
    the circle, the shading drift it also solves for); ``min_spread``: a floor on that evenness (twice the
    smallest eigenvalue of the fit's normalised normal matrix: 1 for an even spread, 0 at one
    phase or at two opposite ones, where sine and cosine cannot be told apart);
    ``visible_mm``: how close a burst's own point must be for its frames to count as seeing ``X``;
    ``rest_sigma_scale``: how many times its bursts' sigma a point the fit cannot take carries (>= 1;
    :data:`REST_SIGMA_SCALE`, calibrated on val: ``benchmarks/rest_sigma_rule.md``); ``fit_sigma_scale``: how many
    times its fit's standard error a fitted point carries (>= 1; :data:`FIT_SIGMA_SCALE`), the sigma the bound
    judges; ``settle_rad``: the
    largest phase offset the last iteration may still correct (None: no test; :data:`SETTLE_RAD`). A fit
    still moving its point at the last iteration has not settled: its sigma describes where the point
    was, not where the step puts it (in a dev look on val seed 31 in fixed pattern order such fits were
    the points 0.1-0.24 mm off the surface: ``benchmarks/frame_fit_settle_rule.md``); it is treated as
    a fit that could not take the point. The test needs ``iterations >= 2`` (with one, it would judge
    the first correction, not whether the fit settled). ``modulation_ratio``: the largest fitted
    modulation over fitted mean intensity, B / A, a fit may have at its last iteration (None: no test;
    :data:`MODULATION_RATIO`): intensities ``A + B cos(psi)`` never go below zero, so a fit with B well
    above A has explained its samples with an impossible fringe (few frames, phases bunched: the
    fit's sine and cosine terms and their drift trade off); it is counted ``implausible`` and not taken.
    With ``"lambert"`` shading both are taken at the point's mean irradiance over its samples: ``A = a + g b``,
    ``B = g hypot(C, S)``. ``shading``: the intensity model (:data:`SHADINGS`, module docstring; :data:`SHADING`;
    with ``"lambert"`` a point its fit cannot take, too few steeply lit samples for its seven terms or no normal, is
    fitted with the drift model: ``stats["drift_fallback"]`` counts them, and ``unsettled`` and ``implausible`` then
    count the drift fits' refusals);
    ``normal_radius_mm``: the neighbourhood of a point's normal for ``"lambert"`` (a point with fewer than 5 fused
    points that close gets none and is not fitted); ``min_incidence_cos``: ``"lambert"`` leaves out the samples lit
    more obliquely (:data:`MIN_INCIDENCE_COS`). ``mixed_sigma_ratio``: with ``"mixed"`` shading, a point is fitted
    quadratic where that fit's phase standard error is at most this many times the drift fit's on the same samples, at
    the iteration that drops outliers (``iterations - 2``; drift before it); a point the mixed fit does not take is
    fitted with the drift model from the start, as with ``"lambert"`` (``stats["drift_fallback"]``; ``unsettled`` and
    ``implausible`` then count the drift fits' refusals);
    ``stats["quadratic_points"]`` counts the fitted points it took quadratic (:data:`MIXED_SIGMA_RATIO`).

    Defaults: ``max_sigma_mm = 0.03`` and ``min_spread = 0.05`` were chosen (with the sigma unscaled) on an independent
    40-burst twin stretch (seed 7, start 11 deg, default rig, 0.6 deg/frame; 40k points against
    the true surface): they fit 90 % of the fused points at 8.2 um RMS where the former rule
    (spread >= 0.5, no sigma bound) fit 78 % at 5.6 um, and move the whole cloud from 26.8 to
    19.9 um RMS; a fit accepted at 20-30 um sigma is still three times closer to the surface than
    the fused point it replaces (57 um).
    """

    def __init__(self, rig: Rig, period_px: float, *, iterations: int = 4, min_frames: int = 9,
                 min_spread: float = 0.05, visible_mm: float = 0.3, max_step_mm: float = 0.3,
                 outlier_sigma: float = 3.0, drift: bool = True, max_sigma_mm: float = MAX_POINT_SIGMA_MM,
                 rest_sigma_scale: float = REST_SIGMA_SCALE, fit_sigma_scale: float = FIT_SIGMA_SCALE,
                 settle_rad: float | None = SETTLE_RAD, modulation_ratio: float | None = MODULATION_RATIO,
                 shading: str = SHADING, normal_radius_mm: float = 0.3,
                 min_incidence_cos: float = MIN_INCIDENCE_COS, mixed_sigma_ratio: float = MIXED_SIGMA_RATIO) -> None:
        if not period_px > 0:
            raise ValueError(f"period_px: expected > 0 projector pixels, got {period_px}")
        if iterations < 1 or min_frames < 4:
            raise ValueError(f"iterations >= 1 and min_frames >= 4 expected, got {iterations} and {min_frames}")
        if not (math.isfinite(max_sigma_mm) and max_sigma_mm > 0 and 0 <= min_spread <= 1):
            raise ValueError(f"max_sigma_mm > 0 and 0 <= min_spread <= 1 expected, got {max_sigma_mm} and {min_spread}")
        if not (math.isfinite(rest_sigma_scale) and rest_sigma_scale >= 1):
            raise ValueError(f"rest_sigma_scale: expected a finite factor >= 1 (it may not shrink a sigma), got {rest_sigma_scale}")
        if not (math.isfinite(fit_sigma_scale) and fit_sigma_scale >= 1):
            raise ValueError(f"fit_sigma_scale: expected a finite factor >= 1 (it may not shrink a sigma), got {fit_sigma_scale}")
        if settle_rad is not None and not (math.isfinite(settle_rad) and settle_rad > 0):
            raise ValueError(f"settle_rad: expected a phase > 0 rad (or None: no test), got {settle_rad}")
        if settle_rad is not None and iterations < 2:
            raise ValueError(f"settle_rad: the settle test needs iterations >= 2 (it judges the last of several "
                             f"corrections), got iterations={iterations}")
        if modulation_ratio is not None and not (math.isfinite(modulation_ratio) and modulation_ratio > 0):
            raise ValueError(f"modulation_ratio: expected a ratio B / A > 0 (or None: no test), got {modulation_ratio}")
        if shading not in SHADINGS:
            raise ValueError(f"shading: expected one of {SHADINGS}, got {shading!r}")
        if not (math.isfinite(normal_radius_mm) and normal_radius_mm > 0):
            raise ValueError(f"normal_radius_mm: expected a radius > 0 mm, got {normal_radius_mm}")
        if not 0 <= min_incidence_cos < 1:
            raise ValueError(f"min_incidence_cos: expected a cosine in [0, 1), got {min_incidence_cos}")
        if not (math.isfinite(mixed_sigma_ratio) and mixed_sigma_ratio > 0):
            raise ValueError(f"mixed_sigma_ratio: expected a finite ratio > 0, got {mixed_sigma_ratio}")
        if shading == "mixed" and not drift:
            raise ValueError("shading 'mixed' chooses between two shading drifts: it needs drift=True")
        self.rig = rig
        self.period_px = float(period_px)
        self.shading = shading
        self.min_incidence_cos = float(min_incidence_cos)
        self.normal_radius_mm = float(normal_radius_mm)
        self.iterations = int(iterations)
        self.min_frames = int(min_frames)
        self.min_spread = float(min_spread)
        self.visible_mm = float(visible_mm)
        self.max_step_mm = float(max_step_mm)
        self.outlier_sigma = float(outlier_sigma)
        self.drift = bool(drift)
        self.mixed_sigma_ratio = float(mixed_sigma_ratio)
        self.max_sigma_mm = float(max_sigma_mm)
        self.rest_sigma_scale = float(rest_sigma_scale)
        self.fit_sigma_scale = float(fit_sigma_scale)
        self.settle_rad = None if settle_rad is None else float(settle_rad)
        self.modulation_ratio = None if modulation_ratio is None else float(modulation_ratio)
        self.bursts: list[_BurstView] = []

    @property
    def degree(self) -> int:
        """The polynomial degree in the turn angle of the shading terms (0: none; 2: "quadratic", and "mixed"'s largest),
        from ``shading`` and ``drift`` as they are now (a rule script may set ``shading`` after construction)."""
        return 0 if not self.drift else 2 if self.shading in ("quadratic", "mixed") else 1

    def __len__(self) -> int:
        return len(self.bursts)

    def add(self, m: Measurement) -> None:
        """Keep one measured burst: its frames, angles and where it measured the surface."""
        cam = self.rig.camera
        h, w = cam.height, cam.width
        images = m.burst.images
        if images.shape[1:] != (h, w):
            raise ValueError(f"burst {m.burst.index}: frames {images.shape[1:]} do not match the rig camera {(h, w)}")
        depth = np.full((h, w), np.nan, np.float32)
        if m.cloud is not None and len(m.cloud):
            if m.cloud.frame != "world":
                raise ValueError(f"burst {m.burst.index}: expected a gear-frame cloud, got frame {m.cloud.frame!r}")
            t = cam.T_from_world @ rot_z(m.burst.angles[0])
            z = m.cloud.points @ t[2, :3] + t[2, 3]
            depth[m.cloud.pixels[:, 0], m.cloud.pixels[:, 1]] = z
        self.bursts.append(_BurstView(np.array(images), np.asarray(m.burst.angles, np.float64), depth,
                                      burst_shifts(m.burst)))

    @staticmethod
    def memory_bytes(frames: int, height: int, width: int, itemsize: int) -> int:
        """What :meth:`add` keeps for ``frames`` frames: the raw images and one depth map per burst."""
        return frames * height * width * itemsize + (frames // 3) * height * width * 4

    def refine_fused(self, fused: FusedCloud, fit: TrackResult | None = None) -> tuple[FusedCloud, dict]:
        """``fused`` with its refined points moved and their sigma from the fit; every point of the
        result has a sigma of at most ``max_sigma_mm``. ``fit``: a :meth:`refine` result of ``fused.points`` already
        made (or assembled from several, as a rule script's candidates are), used instead of fitting again.

        The points the fit could not take keep their fused position with ``rest_sigma_scale * sigma *
        sqrt(bursts)``. No credit for averaging: the few bursts that saw such a point saw it from nearly
        the same view and share their error, so fusion's standard error flattered it (median |error| /
        sigma 2.1-2.3 on the inspection revolution in either pattern order). Without the credit it
        still flattered the points the bound kept (up to 5.3 on val stretches), hence the scale
        (``benchmarks/rest_sigma_rule.md``; since the bursts' sigma is scaled by edge band, 1.5, the rule then
        judging the tail too; a model may carry its own, ``Predictor.rest_sigma_scale``: the default-rig option's
        2.0, at which no such point of its val stretches passes the bound). Two kinds of them are dropped and counted: those off the
        surface their fitted neighbours measured (:func:`off_surface`, ``stats["off_surface"]``),
        and those whose sigma exceeds ``max_sigma_mm``, the bound a fit must meet too
        (``stats["uncertain"]``): one bound for every point of the refined cloud, so what it
        holds was measured to within it and what it lacks is counted, not guessed. The fits the settle
        test refused (``stats["unsettled"]``) and those with an impossible modulation
        (``stats["implausible"]``) are among the points the fit could not take, so those counts overlap the
        two drop counts.
        """
        out, off, stats = self.fit_fused(fused, fit)
        uncertain = ~out.refined & ~off & (out.sigma > self.max_sigma_mm)
        stats = {**stats, "off_surface": int(off.sum()), "uncertain": int(uncertain.sum()),
                 "sigma_bound_mm": self.max_sigma_mm}
        drop = off | uncertain
        return (out.select(~drop) if drop.any() else out), stats

    def fit_fused(self, fused: FusedCloud, fit: TrackResult | None = None) -> tuple[FusedCloud, np.ndarray, dict]:
        """:meth:`refine_fused` before it drops anything: every fused point, fitted or with its scaled burst
        sigma, the (N,) off-surface mask, and the fit's stats (what the val calibration of the scale reads)."""
        res = self.refine(fused.points) if fit is None else fit
        if len(res.points) != len(fused):
            raise ValueError(f"fit: {len(res.points)} points for a fused cloud of {len(fused)}")
        r = res.refined
        points = np.where(r[:, None], res.points, fused.points)
        sigma = np.where(r, res.sigma, self.rest_sigma_scale * fused.sigma * np.sqrt(np.maximum(fused.bursts, 1)))
        return (replace(fused, points=points, sigma=sigma, refined=r, deviation=None, deviation_sigma=None, ray=res.rays),
                off_surface(points, r), res.stats)

    # -- geometry ---------------------------------------------------------------------------
    def _camera_xyz(self, pts: np.ndarray, angle: float) -> np.ndarray:
        t = self.rig.camera.T_from_world @ rot_z(angle)
        return pts @ t[:3, :3].T + t[:3, 3]

    def _visible(self, pts: np.ndarray, b: _BurstView) -> np.ndarray:
        cam = self.rig.camera
        p = self._camera_xyz(pts, b.angles[0])
        uv = np.rint(cam.project_device(p))
        h, w = b.depth.shape
        ok = np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        vis = np.zeros(len(pts), bool)
        idx = np.flatnonzero(ok)
        d = b.depth[uv[idx, 1].astype(np.int64), uv[idx, 0].astype(np.int64)]
        vis[idx] = np.abs(d - p[idx, 2]) <= self.visible_mm  # NaN (no point there) compares False
        return vis

    def _samples(self, pts: np.ndarray, ip: np.ndarray, bounds: np.ndarray, k: int, rays: np.ndarray,
                 normals: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """For visible (point, burst) pairs, frame ``k`` of the burst: intensity, model phase, its
        derivative along the ray (rad/mm), whether the sample lies inside the image, frame angle, and (with
        ``normals``) the projector's relative irradiance there, cos(incidence) (d_ref / d)^2 (0 where unlit)."""
        cam, proj = self.rig.camera, self.rig.projector
        c_proj = proj.center_world
        d_ref = float(np.linalg.norm(c_proj))
        gain = np.zeros(len(ip))
        intensity = np.zeros(len(ip))
        psi = np.zeros(len(ip))
        dpsi = np.zeros(len(ip))
        inside = np.zeros(len(ip), bool)
        angle = np.zeros(len(ip))
        scale = 2 * math.pi / self.period_px
        eps = 0.01  # mm, finite-difference step along the ray
        for bi, b in enumerate(self.bursts):  # the pairs are grouped by burst: one slice each
            sel = slice(bounds[bi], bounds[bi + 1])
            if sel.start == sel.stop:
                continue
            x = pts[ip[sel]]
            world = x @ rot_z(b.angles[k])[:3, :3].T
            world_d = (x + eps * rays[ip[sel]]) @ rot_z(b.angles[k])[:3, :3].T
            uv = cam.project(world)
            u_p, u_pd = proj.project(world)[:, 0], proj.project(world_d)[:, 0]
            img = b.images[k].astype(np.float32)
            h, w = img.shape
            ok = np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
            uvc = np.where(ok[:, None], uv, 0.0)
            x0 = np.minimum(np.floor(uvc[:, 0]).astype(np.int64), w - 2)
            y0 = np.minimum(np.floor(uvc[:, 1]).astype(np.int64), h - 2)
            fx, fy = uvc[:, 0] - x0, uvc[:, 1] - y0
            val = ((1 - fy) * ((1 - fx) * img[y0, x0] + fx * img[y0, x0 + 1])
                   + fy * ((1 - fx) * img[y0 + 1, x0] + fx * img[y0 + 1, x0 + 1]))
            intensity[sel] = val
            psi[sel] = scale * u_p + b.shifts[k]
            dpsi[sel] = scale * (u_pd - u_p) / eps
            inside[sel] = ok
            angle[sel] = b.angles[k]
            if normals is not None:
                to_proj = c_proj - world
                dist = np.linalg.norm(to_proj, axis=1)
                n_world = normals[ip[sel]] @ rot_z(b.angles[k])[:3, :3].T
                cos = np.einsum("ij,ij->i", n_world, to_proj) / dist
                gain[sel] = np.where(cos >= self.min_incidence_cos, cos, 0.0) * (d_ref / dist) ** 2
        return intensity, psi, dpsi, inside, angle, gain

    # -- the fit ------------------------------------------------------------------------------
    def refine(self, points: np.ndarray) -> TrackResult:
        """Move each gear-frame point onto the surface the frames saw (see the module docstring)."""
        pts0 = np.asarray(points, np.float64)
        if pts0.ndim != 2 or pts0.shape[1] != 3:
            raise ValueError(f"points: expected (N, 3) gear-frame points, got shape {pts0.shape}")
        if not self.bursts:
            raise ValueError("no bursts added: nothing to refine on")
        normals = surface_normals(pts0, self.normal_radius_mm) if self.shading == "lambert" else None
        out_pts, out_sigma = pts0.copy(), np.full(len(pts0), np.inf)
        out_rays = np.zeros_like(pts0)
        refined = np.zeros(len(pts0), bool)
        frames = np.zeros(len(pts0), np.int64)
        moved = np.zeros(len(pts0))
        unsettled = implausible = fallback = quadratic = 0
        for start in range(0, len(pts0), _CHUNK):
            sl = slice(start, start + _CHUNK)
            p, s, r, f, mv, ray, u, im, q = self._refine_chunk(pts0[sl], None if normals is None else normals[sl],
                                                               self.degree, self.shading == "mixed")
            quadratic += q
            if (normals is not None or self.shading == "mixed") and not r.all():
                # what lambert or the mixed fit cannot take, the drift model may: its counts then
                miss = np.flatnonzero(~r)
                p2, s2, r2, f2, mv2, ray2, u, im, _ = self._refine_chunk(pts0[sl][miss], None, min(self.degree, 1), False)
                take = miss[r2]
                p[take], s[take], r[take], f[take], mv[take], ray[take] = p2[r2], s2[r2], True, f2[r2], mv2[r2], ray2[r2]
                fallback += len(take)
            out_pts[sl], out_sigma[sl], refined[sl], frames[sl], moved[sl], out_rays[sl] = p, s, r, f, mv, ray
            unsettled += u
            implausible += im
        stats = {"shading": self.shading, "points": len(pts0), "refined": int(refined.sum()), "unsettled": unsettled,
                 "implausible": implausible, "drift_fallback": fallback, "quadratic_points": quadratic,
                 "median_frames": float(np.median(frames[refined])) if refined.any() else 0.0,
                 "median_abs_move_mm": float(np.median(np.abs(moved[refined]))) if refined.any() else 0.0}
        return TrackResult(out_pts, out_sigma, refined, frames.astype(np.int32), moved, out_rays, stats)

    def _refine_chunk(self, pts: np.ndarray, normals: np.ndarray | None, degree: int, mixed: bool):
        n = len(pts)
        vis_rows, vis_cols = [], []
        for bi, b in enumerate(self.bursts):
            v = np.flatnonzero(self._visible(pts, b))
            vis_rows.append(v)
            vis_cols.append(np.full(len(v), bi))
        ip, ib = np.concatenate(vis_rows), np.concatenate(vis_cols)
        bounds = np.searchsorted(ib, np.arange(len(self.bursts) + 1))  # ib ascends: burst bi is ip[bounds[bi]:bounds[bi+1]]
        # each point moves along the camera ray of the mean angle of the bursts that saw it
        ang = np.array([b.angles[0] for b in self.bursts])
        count = np.bincount(ip, minlength=n)
        mean_c = np.bincount(ip, np.cos(ang[ib]), minlength=n) / np.maximum(count, 1)
        mean_s = np.bincount(ip, np.sin(ang[ib]), minlength=n) / np.maximum(count, 1)
        theta = np.arctan2(mean_s, mean_c)
        c_world = self.rig.camera.center_world
        # camera centre in the gear frame at angle theta: rot_z(-theta) c_world
        cth, sth = np.cos(theta), np.sin(theta)
        c_gear = np.stack([cth * c_world[0] + sth * c_world[1], -sth * c_world[0] + cth * c_world[1],
                           np.full(n, c_world[2])], axis=1)
        rays = _unit(pts - c_gear)
        if normals is not None:  # facing the camera that saw the point: the side the projector lit too
            normals = normals * -np.sign(np.einsum("ij,ij->i", normals, rays))[:, None]
        x = pts.copy()
        sigma = np.full(n, np.inf)
        ok_fit = np.zeros(n, bool)
        used = np.zeros(n, np.int64)
        keep = None
        # "mixed": the drift fit until the iteration that drops outliers, where both fits on the same samples choose
        # each point's degree for the rest (a near-converged point's samples; the choice then fixed)
        quad = np.zeros(n, bool) if mixed else None
        decide = max(self.iterations - 2, 0)
        for it in range(self.iterations):
            cols = [self._samples(x, ip, bounds, k, rays, normals) for k in range(3)]
            idx = np.concatenate([ip] * 3)
            val = np.concatenate([c[0] for c in cols])
            psi = np.concatenate([c[1] for c in cols])
            dpsi = np.concatenate([c[2] for c in cols])
            good = np.concatenate([c[3] for c in cols])
            tau = np.angle(np.exp(1j * (np.concatenate([c[4] for c in cols]) - theta[idx])))
            gain = None if normals is None else np.concatenate([c[5] for c in cols])
            if gain is not None:  # lit steeply enough to trust the predicted irradiance
                good &= gain > 0
            if keep is not None:
                good &= keep
            g_good = None if gain is None else gain[good]
            if quad is None:
                coef, res_sd, nfr, spread, sig_eps = _fit(idx[good], val[good], psi[good], tau[good], n, degree, g_good)
            else:
                if it == decide:  # both fits of every point, each point then keeps its own
                    both = {d: _fit(idx[good], val[good], psi[good], tau[good], n, d) for d in (1, 2)}
                    with np.errstate(invalid="ignore"):
                        quad = np.isfinite(both[2][4]) & (both[2][4] <= self.mixed_sigma_ratio * both[1][4])
                    coef, res_sd, nfr, spread, sig_eps = _merge_degrees(both, quad)
                else:
                    coef, res_sd, nfr, spread, sig_eps = _fit_degrees(idx[good], val[good], psi[good], tau[good], n, quad)
            cc, ss = coef[:, 1], coef[:, 2]
            if it == self.iterations - 2 or self.iterations == 1:  # drop samples far from the fit
                pred = np.einsum("ij,ij->i", _design(psi, tau, degree, gain), coef[idx])
                keep = np.abs(val - pred) <= self.outlier_sigma * np.maximum(res_sd[idx], 1e-6)
                if gain is not None:  # unlit now, judged if the point's move lights it: not refused unseen
                    keep |= gain == 0
            eps = np.arctan2(ss, cc)  # phase the frames show minus the point's model phase
            slope = np.bincount(idx[good], dpsi[good], minlength=n) / np.maximum(nfr, 1)
            with np.errstate(divide="ignore", invalid="ignore"):
                sigma_mm = self.fit_sigma_scale * np.abs(sig_eps / slope)
            fit = ((nfr >= self.min_frames) & (spread >= self.min_spread) & (np.abs(slope) > 1e-3)
                   & (sigma_mm <= self.max_sigma_mm))
            unsettled = np.zeros(n, bool)
            implausible = np.zeros(n, bool)
            if it == self.iterations - 1 and self.settle_rad is not None:  # still moving at the last iteration
                unsettled = fit & ~(np.abs(eps) <= self.settle_rad)  # NaN counts as unsettled
                fit &= ~unsettled
            if it == self.iterations - 1 and self.modulation_ratio is not None:  # B > A: a negative intensity
                mean_a, mod_b = coef[:, 0], np.hypot(cc, ss)
                if gain is not None:  # at the point's mean irradiance: A = ambient + g b, B = g hypot(C, S)
                    g_mean = np.bincount(idx[good], g_good, minlength=n) / np.maximum(nfr, 1)
                    mean_a, mod_b = coef[:, -1] + g_mean * coef[:, 0], g_mean * mod_b
                implausible = fit & ~(mod_b <= self.modulation_ratio * mean_a)
                fit &= ~implausible
            with np.errstate(divide="ignore", invalid="ignore"):
                step = np.where(fit, eps / slope, 0.0)
            step = np.clip(step, -self.max_step_mm, self.max_step_mm)
            x = x + step[:, None] * rays
            sigma = np.where(fit, sigma_mm, np.inf)
            ok_fit, used = fit, nfr
        x = np.where(ok_fit[:, None], x, pts)  # a point the last fit could not take stays where it was
        moved = np.einsum("ij,ij->i", x - pts, rays)
        rays = np.where((count > 0)[:, None], rays, np.nan)  # no burst saw it: no view, no ray
        return (x, sigma, ok_fit, used, moved, rays, int(unsettled.sum()),
                int(implausible.sum()), 0 if quad is None else int((quad & ok_fit).sum()))


def surface_normals(points: np.ndarray, radius_mm: float, min_neighbours: int = 5) -> np.ndarray:
    """Unit normals ``(N, 3)`` of a fused cloud from its neighbours within ``radius_mm`` (at most 30; the plane through
    them), unoriented; NaN where fewer than ``min_neighbours`` points lie that close (no plane to trust: open3d would
    put a default normal there, and a wrong irradiance is worse than no lambert fit)."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_mm, max_nn=30))
    normals = np.asarray(pcd.normals).copy()
    near = cKDTree(pts).query_ball_point(pts, radius_mm, return_length=True)  # the point itself included
    normals[near < min_neighbours] = np.nan
    return normals


def off_surface(points: np.ndarray, fitted: np.ndarray, *, radius_mm: float = 0.5, min_neighbours: int = 6,
                max_off_mm: float = 0.15) -> np.ndarray:
    """Points not ``fitted`` that lie more than ``max_off_mm`` off the plane through the fitted points
    within ``radius_mm`` (at least ``min_neighbours`` of them); ``(N,)`` bool.

    The frames confirm the fitted points (a few um from the surface); an unfitted point that far
    off the surface they measured around it is not a surface point: a silhouette or shadow-edge
    pixel that several bursts put in the same voxel (0.26-0.5 mm off the true surface on the
    inspection benchmark revolution, where the unfitted points on the surface are within 0.1 mm).
    Points with too few fitted neighbours are kept: nothing contradicts them.
    """
    from scipy.spatial import cKDTree

    out = np.zeros(len(points), bool)
    todo = np.flatnonzero(~fitted)
    if not todo.size or fitted.sum() < min_neighbours:
        return out
    anchors = points[fitted]
    tree = cKDTree(anchors)
    for j, nb in zip(todo, tree.query_ball_point(points[todo], radius_mm), strict=True):
        if len(nb) < min_neighbours:
            continue
        q = anchors[nb]
        centre = q.mean(axis=0)
        normal = np.linalg.svd(q - centre, full_matrices=False)[2][2]
        out[j] = abs(float((points[j] - centre) @ normal)) > max_off_mm
    return out


def _design(psi: np.ndarray, tau: np.ndarray, degree: int, gain: np.ndarray | None = None) -> np.ndarray:
    """Columns of ``I = a + C cos(psi) - S sin(psi)``, each also a polynomial of ``degree`` (0, 1 or 2) in ``tau``. With
    ``gain`` (the projector's relative irradiance per sample, ``"lambert"`` shading): ``I = g (b + C cos(psi) - S
    sin(psi)) + a``, ``b``, ``C``, ``S`` polynomials of ``degree`` in ``tau``, ``a`` (ambient) constant. ``a`` (or
    ``b``), ``C``, ``S`` at ``tau = 0`` come first."""
    c, s = np.cos(psi), -np.sin(psi)
    base = [np.ones_like(c), c, s] if gain is None else [gain, gain * c, gain * s]
    cols = list(base)
    for power in range(1, degree + 1):  # shading that changes as the surface turns
        t = tau**power
        cols += [t * b for b in base]
    if gain is not None:
        cols.append(np.ones_like(c))
    return np.stack(cols, axis=1)


def _fit(idx: np.ndarray, val: np.ndarray, psi: np.ndarray, tau: np.ndarray, n: int, degree: int,
         gain: np.ndarray | None = None):
    """Per-point least squares over its samples (:func:`_design`): coefficients ``(n, 3 to 10)``
    (the mean or, with ``gain``, the projector's share of it, then C, S, then their terms in ``tau``), the residual standard deviation, the number of
    samples and the spread of ``psi``."""
    x = _design(psi, tau, degree, gain)
    p = x.shape[1]
    ata = np.empty((n, p, p))
    atb = np.empty((n, p))
    for i in range(p):
        atb[:, i] = np.bincount(idx, x[:, i] * val, minlength=n)
        for j in range(i, p):
            ata[:, i, j] = ata[:, j, i] = np.bincount(idx, x[:, i] * x[:, j], minlength=n)
    count = np.bincount(idx, minlength=n).astype(np.float64)
    # how well the phases cover the circle: 1 for an even spread, 0 at one phase (or at two
    # opposite ones, which leave sin and cos apart unresolved); with gain, weighted by its square
    spread = 2.0 * np.linalg.eigvalsh(ata[:, :3, :3] / np.maximum(ata[:, 0, 0], 1e-12)[:, None, None])[:, 0]
    solvable = (count >= 2 * p) & (spread > 1e-3)
    if degree or gain is not None:
        solvable &= np.linalg.eigvalsh(ata)[:, 0] > 1e-12 * np.maximum(count, 1)
    sol = np.zeros((n, p))
    cov_cs = np.full((n, 2, 2), np.inf)  # (C, S) block of the inverse normal matrix
    if solvable.any():
        inv = np.linalg.inv(ata[solvable])
        sol[solvable] = np.einsum("nij,nj->ni", inv, atb[solvable])
        cov_cs[solvable] = inv[:, 1:3, 1:3]
    pred = np.einsum("ij,ij->i", x, sol[idx])
    sse = np.bincount(idx, (val - pred) ** 2, minlength=n)
    res_sd = np.sqrt(sse / np.maximum(count - p, 1))
    # first-order variance of eps = atan2(S, C): gradient (-S, C) / B^2 through the (C, S) covariance
    c, s = sol[:, 1], sol[:, 2]
    b2 = np.maximum(c * c + s * s, 1e-12)
    with np.errstate(invalid="ignore"):
        q = (s * s * cov_cs[:, 0, 0] - 2 * c * s * cov_cs[:, 0, 1] + c * c * cov_cs[:, 1, 1]) / (b2 * b2)
    sigma_eps = np.where(solvable, res_sd * np.sqrt(np.maximum(q, 0.0)), np.inf)
    return sol, res_sd, count.astype(np.int64), np.where(solvable, spread, 0.0), sigma_eps


def _fit_degrees(idx: np.ndarray, val: np.ndarray, psi: np.ndarray, tau: np.ndarray, n: int, quad: np.ndarray):
    """:func:`_fit` of degree 2 for the points ``quad``, of degree 1 for the others, in one result (the coefficients in
    degree 2's columns, zero where degree 1 has none: its columns are degree 2's first six)."""
    fits = {}
    for degree, mine in ((1, ~quad), (2, quad)):
        if mine.any():  # a point's fit reads only its own samples: each degree on its points' samples alone
            m = mine[idx]
            fits[degree] = _fit(idx[m], val[m], psi[m], tau[m], n, degree)
    return _merge_degrees(fits, quad)


def _merge_degrees(fits: dict, quad: np.ndarray):
    """One :func:`_fit` result from ``fits`` (degree -> its result): degree 2's for the points ``quad``, degree 1's for
    the others (a degree no point takes may be missing)."""
    n = len(quad)
    coef, res_sd = np.zeros((n, 9)), np.zeros(n)
    count, spread, sig_eps = np.zeros(n, np.int64), np.zeros(n), np.full(n, np.inf)
    for degree, mine in ((1, ~quad), (2, quad)):
        if not mine.any():
            continue
        sol, sd, cnt, spr, sig = fits[degree]
        coef[mine, : sol.shape[1]] = sol[mine]
        res_sd[mine], count[mine], spread[mine], sig_eps[mine] = sd[mine], cnt[mine], spr[mine], sig[mine]
    return coef, res_sd, count, spread, sig_eps


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)
