"""Gear inspection from a fused gear-frame cloud: the quantities of ISO 1328-1:2013.

Input: a fused cloud of a whole revolution (:mod:`gearscan.recon.fuse`) in the turntable
frame and the gear's nominal spec (``teeth``, ``module``, ``pitch_radius``, ``base_radius``,
``tip_radius``, ``root_radius``, ``pitch_angle``, ``pressure_angle``, ``face_width``,
``half_angle(r)``: a :class:`~gearscan.core.gear.GearSpec`; recon does not import twin).

Steps and definitions (all in the transverse section band around mid-face):

1. **Datum axis** (``datum``, :data:`DATUM`): ``"tip"``, a least-squares circle through the tip lands
   (:func:`fit_centre`: the points within ``0.1 m`` of the tip circle, refitted with those within 3 MADs). Tip lands
   do not move with pitch deviations, so the axis is not pulled by them; on the twin's gears it lay within 0.04-0.6 um
   of the true axis. It assumes the tip circle concentric with the teeth (a turned blank's tip runout would read as
   pitch and runout). ``"teeth"``: from the flanks, each tooth turned freely (its pitch deviation), so that only their
   radial part (tooth spaces opening and closing around the gear) places the axis: 2.5-5x noisier on the twin
   (sin 20 deg of the flank information carries it). The first harmonic of the pitch deviations and a shift of the
   axis move the teeth alike along the pitch circle; from the flanks alone they cannot be told apart, so no fit of the
   axis that lets both do it is a datum. Not assumed to be the turntable axis: its offset is the mounting eccentricity
   ``e`` (direction ``phi``).
2. **Flank deviations**: about that axis every flank point of tooth ``k``, side ``s``
   (-1 right / -theta, +1 left / +theta, ISO 21771 seen from +z) has the normal deviation
   ``f = s r_b (theta - theta0 - k tau - s h(r))`` (mm, + = material added; ``h`` the nominal
   half tooth angle; an involute moved by ``f`` along its normal is turned by ``f / r_b``), a
   function of the roll length ``L = sqrt(r^2 - r_b^2)``. ``theta0`` (where tooth 0 sits) is
   the mean of the teeth's own turns (each fitted to both its flanks, so a tooth-thickness error cancels between the
   sides; :func:`_fit_axis`).
3. **Profile** per flank over the evaluation range ``L_alpha`` (from ``xi_start`` of the
   roll length from the involute start to ``xi_end``, default 0.1 to 0.95; ISO's start of
   active profile depends on the mating gear, which a measurement does not know): the trace
   is the sigma-weighted mean of ``f`` in ``bins`` roll-length bins (a bin with fewer than
   :data:`MIN_BIN_POINTS` points or a standard error above :data:`BIN_SE_MAX_MM` is left out, as one
   never seen, and counted: ``profile_bins_left_out``); the mean profile line is
   its least-squares line. ``F_alpha`` = range of the trace (two design profiles enclosing
   it), ``ff_alpha`` = range of the trace minus the mean line, ``fH_alpha`` = the mean line's
   rise over ``L_alpha`` (+: more material towards the tip).
4. **Pitch** (ISO 1328-1 3.2): the flank's position on the pitch circle along +theta,
   ``u = s f(L_p) r_p / r_b`` (``f(L_p)`` from a local line fit around the pitch circle).
   Single pitch deviation ``fp_k = u_k - u_(k-1)`` (pitch k: from tooth k-1 to tooth k),
   cumulative (index) deviation ``Fp_k = u_k - u_0``, total cumulative ``Fp = max u - min u``.
5. **Runout** ``Fr`` (ISO 1328-1:2013 annex, radial runout with a ball probe): a ball that
   touches both flanks of tooth space ``k`` (tooth k's left and tooth k+1's right flank) on
   the pitch circle sits radially at ``-w_k / (2 tan alpha)`` when the space is ``w_k`` wider
   than nominal along the pitch circle, plus ``e cos(theta_k - phi)`` from the eccentricity.
   The radial positions are taken about the turntable axis, the axis the gear turns about
   (the datum of a measurement on its mounting): ``Fr`` = their range. Also reported:
   ``runout_from_eccentricity_um`` (the range of ``e cos(theta_k - phi)`` over the spaces, about
   ``2 e``) and ``runout_about_gear_axis_um`` (the spaces alone).
6. **Chipped teeth**: in each tooth's tip zone (radius above ``r_a - tip_zone``, the whole
   face) the signed distance to the CAD moved onto the fitted axis is averaged in tooth-local
   cells (across the tooth x along the face, all radii of the zone in one cell: a chip face lies
   at a smaller radius than the surface it replaced, and cells split by radius put the two in
   different cells, where the chip was missed on a twin revolution) and compared with the median
   tooth's in the same cell (errors that every tooth shares,
   since all are seen through the same views, cancel); the cells more than ``chip_mm`` below
   it cover ``missing_mm2``; a tooth is flagged when that area exceeds ``chip_area_mm2`` or its
   tip zone has under half the median tooth's points. The check is *inconclusive* (no tooth
   flagged, ``chip_check_conclusive`` False) when 5 % of the cells stray from the median tooth by
   more than ``chip_mm / CHIP_NOISE_MARGIN``: then a threshold at ``chip_mm`` flags noise
   and misses chips alike (measured on a moving revolution with the chip on tooth 12: four other
   teeth flagged, tooth 12 not; at a spread of chip_mm / 1.7, two intact teeth flagged).

Tolerances: :func:`iso1328_tolerances` (ISO 1328-1:2013, eq. 5-9; runout annex).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

GRADES = range(1, 12)  # ISO 1328-1:2013 flank tolerance classes 1 (finest) to 11
# the chip threshold must exceed this many times the tip cells' p95 spread. 1.5 until session 39: on the inspection
# revolution decoded by v9 without the frame fit the spread was 29.3 um (x 1.5 = 44 < 50) and two intact teeth had
# 1.4 and 3.0 mm2 of cells 50 um below the median tooth (the chip: 6.4); at 2 that cloud is inconclusive
CHIP_NOISE_MARGIN = 2.0
# a profile trace's roll-length bin counts only with at least MIN_BIN_POINTS points AND a weighted mean known within
# BIN_SE_MAX_MM (its standard error from the points' sigma). Until session 56 one point made a bin: on the inspection
# revolution measured with a hand-placed calibration (benchmarks/calibration_inspection_before_min_bin_report.md,
# seed 53) a single point at the root end of tooth 18's right flank, 22.6 um off, set that flank's F_alpha to 26.7 um
# and the gear's with it (9.7-10.0 with the true rig and the four other calibrations). Bins hold ten times fewer points
# at the root end than at the tip (the involute's arc per bin grows with the roll length), so a count of ten left out
# 15-19 of 800 bins on those clouds, all near the root, shortening the range F_alpha spans; three points and 3 um leave
# out 2-8 (the same F_alpha). Chosen by argument on that one revolution (a lone point is no profile; 3 um is a
# seventh of the class-8 F_alpha tolerance, 22 um, of the benchmark gear), not tuned; the report counts what was left out
MIN_BIN_POINTS = 3
BIN_SE_MAX_MM = 0.003
# the datum axis pitch, runout and the flank deviations are read about (step 1 of the module docstring): "tip", the tip
# lands' circle; "teeth", the axis the flanks' radial part places. Until session 59 the axis was fitted to the flanks
# with one turn for all teeth, and a single tooth's pitch deviation moved it by as much as the robust window happened
# to keep of that tooth (benchmarks/datum_and_quadratic_rule.md)
DATUMS = ("tip", "teeth")
DATUM = "tip"


# --- ISO 1328-1:2013 tolerances ------------------------------------------------------------
def iso1328_round(value_um: float) -> float:
    """ISO 1328-1:2013 5.2.3 rounding: above 10 µm to 1 µm, 5 to 10 µm to 0.5 µm, below 5 µm to 0.1 µm."""
    step = 1.0 if value_um > 10 else 0.5 if value_um >= 5 else 0.1
    return round(value_um / step) * step


def iso1328_tolerances(module: float, diameter: float, grade: int) -> dict[str, float]:
    """Flank tolerances (µm, rounded) of ISO 1328-1:2013 class ``grade`` for module ``module`` and
    reference diameter ``diameter`` (mm). With ``F = sqrt(2)**(grade - 5)``:

    - single pitch (eq. 5): ``f_pT = (0.001 d + 0.4 m_n + 5) F``
    - total cumulative pitch (eq. 6): ``F_pT = (0.002 d + 0.55 sqrt(d) + 0.7 m_n + 12) F``
    - profile slope (eq. 7): ``f_HaT = (0.4 m_n + 0.001 d + 4) F``
    - profile form (eq. 8): ``f_faT = (0.55 m_n + 5) F``
    - total profile (eq. 9): ``F_aT = sqrt(f_HaT**2 + f_faT**2)`` from the unrounded values
    - runout (informative annex): ``F_rT = 0.9 F_pT``

    Valid (5.2.1) for 0.5 <= m_n <= 70 mm, 5 <= d <= 15000 mm and classes 1 to 11; outside
    that a ValueError names the input (the standard forbids extrapolating).
    """
    if int(grade) != grade or grade not in GRADES:
        raise ValueError(f"grade: ISO 1328-1:2013 classes are 1 to 11, got {grade}")
    if not 0.5 <= module <= 70:
        raise ValueError(f"module {module} mm is outside ISO 1328-1:2013's range 0.5 to 70 mm")
    if not 5 <= diameter <= 15000:
        raise ValueError(f"reference diameter {diameter} mm is outside ISO 1328-1:2013's range 5 to 15000 mm")
    f = math.sqrt(2) ** (grade - 5)
    m, d = module, diameter
    fp = (0.001 * d + 0.4 * m + 5) * f
    fp_total = (0.002 * d + 0.55 * math.sqrt(d) + 0.7 * m + 12) * f
    fh = (0.4 * m + 0.001 * d + 4) * f
    ff = (0.55 * m + 5) * f
    raw = {"fp": fp, "Fp": fp_total, "fH_alpha": fh, "ff_alpha": ff, "F_alpha": math.hypot(fh, ff), "Fr": 0.9 * fp_total}
    return {k: iso1328_round(v) for k, v in raw.items()}


def iso1328_class(values_um: dict[str, float], module: float, diameter: float) -> dict[str, int | None]:
    """The finest class (1-11) whose tolerance holds each measured value (None: worse than class 11)."""
    tables = {g: iso1328_tolerances(module, diameter, g) for g in GRADES}
    out: dict[str, int | None] = {}
    for key, value in values_um.items():
        fits = [g for g in GRADES if np.isfinite(value) and abs(value) <= tables[g][key]]
        out[key] = min(fits) if fits else None
    return out


# --- results ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Flank:
    """One flank's profile and pitch-circle position (µm); ``measured`` False when too little was seen."""

    tooth: int
    side: str  # "left" (+theta) or "right" (-theta)
    points: int
    measured: bool
    position_um: float = math.nan
    F_alpha_um: float = math.nan
    ff_alpha_um: float = math.nan
    fH_alpha_um: float = math.nan
    roll_mm: tuple[float, ...] = ()
    trace_um: tuple[float, ...] = ()


@dataclass(frozen=True)
class ToothTip:
    """A tooth's tip zone: its points, the area deviating below ``-chip_mm`` from the median tooth, and
    the deepest such deviation (mm)."""

    tooth: int
    points: int
    missing_mm2: float
    depth_mm: float
    chipped: bool


@dataclass(frozen=True)
class Inspection:
    """What a gear inspector reads (module docstring); µm unless the name says mm or deg."""

    teeth: int
    module: float
    pitch_diameter_mm: float
    centre_mm: tuple[float, float]
    eccentricity_um: float
    eccentricity_deg: float
    rotation_deg: float
    section_mm: tuple[float, float]
    flanks: tuple[Flank, ...]
    position_um: dict[str, list[float]]
    single_pitch_um: dict[str, list[float]]
    cumulative_pitch_um: dict[str, list[float]]
    fp_um: dict[str, float]
    Fp_um: dict[str, float]
    runout_curve_um: list[float]
    Fr_um: float
    runout_from_eccentricity_um: float
    runout_about_gear_axis_um: float
    tips: tuple[ToothTip, ...]
    chipped_teeth: tuple[int, ...]
    profile_um: dict[str, float]
    chip_noise_um: float = math.nan  # 95th percentile of the tip cells' |deviation from the median tooth|
    chip_check_conclusive: bool = True  # False: the cells are too noisy to tell a chip (none flagged)
    settings: dict[str, float] = field(default_factory=dict)
    # profile bins whose few points or loose mean did not count (MIN_BIN_POINTS, BIN_SE_MAX_MM), of teeth x 2 x bins
    profile_bins_left_out: int = 0

    def summary(self) -> dict[str, float]:
        """The headline values per quantity (worst over the flanks/sides measured; NaN: none was), µm, for grading."""
        return {"fp": _worst(self.fp_um.values()), "Fp": _worst(self.Fp_um.values()), "Fr": self.Fr_um,
                **self.profile_um}

    def coverage(self) -> dict[str, tuple[int, int]]:
        """Per :meth:`summary` quantity: how many of the values it is the worst (or range) of were measured, and how
        many a whole gear has. Short of all, the headline is a lower bound: teeth not measured may deviate more."""
        def finite(v) -> int:
            return int(np.isfinite(np.asarray(v, np.float64)).sum())

        sides = ("left", "right")
        flanks = sum(fl.measured for fl in self.flanks)
        return {"fp": (sum(finite(self.single_pitch_um[s]) for s in sides), 2 * self.teeth),
                "Fp": (sum(finite(self.position_um[s]) for s in sides), 2 * self.teeth),
                "Fr": (finite(self.runout_curve_um), self.teeth),
                **{k: (flanks, 2 * self.teeth) for k in self.profile_um}}

    def to_json(self) -> dict:
        """Plain JSON (NaN as null)."""
        return jsonable(asdict(self))


def _worst(values) -> float:
    """The largest finite value (NaN when none is finite): a side not measured leaves the other's."""
    finite = [float(v) for v in values if v is not None and np.isfinite(v)]
    return max(finite) if finite else math.nan


def jsonable(x):
    """``x`` with NaN and infinite floats as None and numpy scalars as Python ones: strict JSON."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [jsonable(v) for v in x]
    if isinstance(x, float | np.floating):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


# --- geometry -------------------------------------------------------------------------------
def fit_centre(points: np.ndarray, radius: float, band: float, iterations: int = 4) -> tuple[np.ndarray, float, int]:
    """Centre ``(x, y)`` of the circle of ``radius`` through ``points`` near it (mm).

    Starts at the origin and keeps the points within ``band`` of the circle (then within 3
    MADs of the fitted one); algebraic (Kasa) circle fit. Returns centre, rms and points used.
    """
    c = np.zeros(2)
    keep = None
    for i in range(iterations):
        r = np.hypot(points[:, 0] - c[0], points[:, 1] - c[1])
        res = r - radius
        if i == 0:
            keep = np.abs(res) < band
        else:
            mad = 1.4826 * np.median(np.abs(res[keep] - np.median(res[keep])))
            keep = np.abs(res - np.median(res[keep])) < max(3 * mad, 1e-4)
        if keep.sum() < 10:
            raise ValueError(f"fit_centre: {int(keep.sum())} points within {band} mm of the {radius:.3f} mm circle; "
                             "is the cloud a whole revolution in the gear frame?")
        x, y = points[keep, 0], points[keep, 1]
        a = np.stack([2 * x, 2 * y, np.ones_like(x)], axis=1)
        sol, *_ = np.linalg.lstsq(a, x**2 + y**2, rcond=None)
        c = sol[:2]
    r = np.hypot(points[keep, 0] - c[0], points[keep, 1] - c[1])
    return c, float(np.sqrt(np.mean((r - r.mean()) ** 2))), int(keep.sum())


def _flank_deviation(pts: np.ndarray, q: np.ndarray, gear, k: np.ndarray | None = None,
                     s: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Tooth, side, normal deviation ``f`` (mm) and roll length of ``pts`` about centre ``q[:2]`` with
    tooth 0 turned by ``q[2]`` (module docstring, step 2); ``k``, ``s`` keep a given assignment."""
    x, y = pts[:, 0] - q[0], pts[:, 1] - q[1]
    r, t = np.hypot(x, y), np.arctan2(y, x) - q[2]
    rb = gear.base_radius
    if k is None:
        k = np.round(t / gear.pitch_angle).astype(int)
        s = np.where(t - k * gear.pitch_angle >= 0, 1.0, -1.0)
        k = k % gear.teeth
    d = np.angle(np.exp(1j * (t - k * gear.pitch_angle)))
    h = np.asarray(gear.half_angle(np.maximum(r, rb)), dtype=float)
    return k, s, s * rb * (d - s * h), np.sqrt(np.maximum(r**2 - rb**2, 0.0))


def _fit_axis(sec: np.ndarray, w: np.ndarray, q: np.ndarray, gear, l_a: float, l_b: float, fit_centre_too: bool) -> np.ndarray:
    """The datum ``q`` (axis x, y in mm, tooth 0's turn in rad) from the flank points ``sec`` (weights ``w``), starting
    from ``q``: step 2 of the module docstring. Each tooth's own turn is fitted (its pitch deviation); their mean, weighted
    by the points, is tooth 0's. With ``fit_centre_too`` the axis is fitted as well, by Gauss-Newton, from what the teeth's
    own turns cannot take: the radial part of the flank deviations (tooth spaces opening and closing around the gear).
    Points beyond 3 MADs of their own tooth's fit are left out of each step."""
    m, rb = gear.module, gear.base_radius
    steps = (np.array([1e-3, 0, 0]), np.array([0, 1e-3, 0])) if fit_centre_too else ()
    for _ in range(8):
        k, s, f, roll = _flank_deviation(sec, q, gear)
        on = (roll >= l_a) & (roll <= l_b) & (np.abs(f) < 0.25 * m)
        k, s, res, ww = k[on], s[on], f[on], w[on]
        v = -s * rb  # d f / d (a tooth's own turn): both flanks move the same way along the pitch circle
        ok = np.ones(len(res), bool)
        for _pass in range(2):  # each tooth's turn on the points kept, then the window on what it leaves
            den = np.bincount(k[ok], ww[ok] * v[ok] ** 2, minlength=gear.teeth)
            turn = np.bincount(k[ok], ww[ok] * v[ok] * res[ok], minlength=gear.teeth) / np.where(den > 0, den, np.inf)
            left = res - v * turn[k]
            centre_left = np.median(left[ok])
            mad = 1.4826 * np.median(np.abs(left[ok] - centre_left))
            ok = np.abs(left - centre_left) < max(3 * mad, 1e-3)
        step = np.zeros(2)
        if steps:  # the axis from what each tooth's own turn cannot take: projected out of residual and Jacobian
            jac = np.stack([(_flank_deviation(sec[on], q + dq, gear, k, s)[2] - res) / dq.max() for dq in steps], axis=1)
            proj = np.stack([np.bincount(k[ok], ww[ok] * v[ok] * jac[ok, i], minlength=gear.teeth)
                             / np.where(den > 0, den, np.inf) for i in range(2)], axis=1)
            sw = np.sqrt(ww[ok])
            step, *_ = np.linalg.lstsq((jac - v[:, None] * proj[k])[ok] * sw[:, None], -left[ok] * sw, rcond=None)
        seen = den > 0
        mean_turn = float(np.average(turn[seen], weights=den[seen])) if seen.any() else 0.0
        # f = s rb (angle - q[2] - ...): the teeth's mean turn moves tooth 0's the other way
        q = q + np.array([step[0], step[1], -mean_turn])
        if np.abs(step).max() < 1e-5 and abs(mean_turn) < 1e-7:
            break
    return q


def _line(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """Weighted least-squares line ``y = a + b x``."""
    sw = w.sum()
    xm, ym = (w * x).sum() / sw, (w * y).sum() / sw
    sxx = (w * (x - xm) ** 2).sum()
    b = (w * (x - xm) * (y - ym)).sum() / sxx if sxx > 0 else 0.0
    return ym - b * xm, b


def profile_quantities(roll: np.ndarray, trace: np.ndarray, span: float) -> tuple[float, float, float]:
    """F_alpha, ff_alpha and fH_alpha of a profile trace (step 3 of the module docstring), in the trace's units:
    its range, the range about its least-squares line, and that line's rise over ``span`` (the evaluation range)."""
    roll, trace = np.asarray(roll, np.float64), np.asarray(trace, np.float64)
    a0, b0 = _line(roll, trace, np.ones_like(roll))
    resid = trace - (a0 + b0 * roll)
    return float(trace.max() - trace.min()), float(resid.max() - resid.min()), float(b0 * span)


def pitch_deviations(positions: np.ndarray) -> tuple[np.ndarray, float, float]:
    """One flank side's single pitch deviations ``p_k - p_(k-1)`` and its headlines fp (their largest magnitude) and
    Fp (the positions' range), from its flanks' positions along the pitch circle (step 4); NaN: not measured."""
    p = np.asarray(positions, np.float64)
    single = p - np.roll(p, 1)
    fp = float(np.nanmax(np.abs(single))) if np.isfinite(single).any() else math.nan
    return single, fp, float(np.nanmax(p) - np.nanmin(p)) if np.isfinite(p).any() else math.nan


def ball_heights(right: np.ndarray, left: np.ndarray, pressure_angle: float) -> np.ndarray:
    """Radial height of a ball probe in each tooth space k (tooth k's left, tooth k+1's right flank) from the flanks'
    positions along +theta on the pitch circle (step 5): a space ``w`` wider sits the ball ``w / (2 tan alpha)`` in."""
    return -(np.roll(np.asarray(right, np.float64), -1) - np.asarray(left, np.float64)) / (2 * math.tan(pressure_angle))


def inspect_gear(
    points: np.ndarray,
    sigma: np.ndarray,
    gear,
    *,
    cad_mesh=None,
    section_fraction: float = 0.6,
    xi_start: float = 0.1,
    xi_end: float = 0.95,
    bins: int = 20,
    min_coverage: float = 0.5,
    tip_zone_mm: float | None = None,
    chip_mm: float = 0.05,
    chip_area_mm2: float = 1.0,
    voxel_mm: float = 0.1,
    datum: str = DATUM,
) -> Inspection:
    """Inspect a fused gear-frame cloud (``points (N, 3)`` mm, ``sigma (N,)`` mm) of ``gear``.

    ``section_fraction`` of the face width around mid-face is the transverse band for pitch,
    profile and axis; ``cad_mesh`` (open3d, gear frame, default ``gear.mesh()``) scores the
    tip zones for chips over the whole face; ``voxel_mm`` is the fused cloud's voxel (one
    point per ``voxel_mm**2`` of surface, for areas); ``datum``: the axis pitch and runout are read about
    (:data:`DATUMS`, :data:`DATUM`). See the module docstring.
    """
    points = np.asarray(points, dtype=np.float64)
    sigma = np.asarray(sigma, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or sigma.shape != (len(points),):
        raise ValueError(f"points (N, 3) and sigma (N,) expected, got {points.shape} and {sigma.shape}")
    if not 0 < section_fraction <= 1:
        raise ValueError(f"section_fraction: expected in (0, 1], got {section_fraction}")
    if not 0 <= xi_start < xi_end <= 1:
        raise ValueError(f"xi_start/xi_end: expected 0 <= start < end <= 1, got {xi_start}, {xi_end}")
    if datum not in DATUMS:
        raise ValueError(f"datum: expected one of {', '.join(DATUMS)}, got {datum!r}")
    z, tau, m = gear.teeth, gear.pitch_angle, gear.module
    ra, rb, rp = gear.tip_radius, gear.base_radius, gear.pitch_radius
    r_start = max(rb, gear.root_radius)
    # mid-face from the data (a real gear need not sit at z = 0 on the table)
    z_lo, z_hi = np.percentile(points[:, 2], [0.5, 99.5])
    z_mid = 0.5 * (z_lo + z_hi)
    half = 0.5 * section_fraction * gear.face_width
    band = np.abs(points[:, 2] - z_mid) <= half
    sec, sec_sigma = points[band], sigma[band]

    w = 1.0 / np.square(np.maximum(sec_sigma, 1e-6))
    centre, _, _ = fit_centre(sec, ra, 0.1 * m)
    l_start, l_tip = math.sqrt(max(r_start**2 - rb**2, 0.0)), math.sqrt(ra**2 - rb**2)
    l_a, l_b = l_start + xi_start * (l_tip - l_start), l_start + xi_end * (l_tip - l_start)
    q = np.array([centre[0], centre[1], 0.0])
    q = _fit_axis(sec, w, q, gear, l_a, l_b, fit_centre_too=datum == "teeth")
    centre, theta0 = q[:2], float(q[2])
    ecc = float(np.hypot(*centre))
    phi = float(np.arctan2(centre[1], centre[0]))
    k, s, f, roll = _flank_deviation(sec, q, gear)
    near = (roll >= l_a) & (roll <= l_b) & (np.abs(f) < 0.25 * m)

    edges = np.linspace(l_a, l_b, bins + 1)
    mids = 0.5 * (edges[:-1] + edges[1:])
    l_p = math.sqrt(max(rp**2 - rb**2, 0.0))
    order = np.lexsort((roll, s, k))  # flank by flank
    flank_id = (k * 2 + (s > 0)).astype(int)
    flanks: list[Flank] = []
    positions = {"right": np.full(z, np.nan), "left": np.full(z, np.nan)}
    sel = order[near[order]]
    groups = np.split(sel, np.flatnonzero(np.diff(flank_id[sel])) + 1) if len(sel) else []
    by_id = {int(flank_id[g[0]]): g for g in groups if len(g)}
    left_out = {"right": 0, "left": 0}  # bins with points that did not count (MIN_BIN_POINTS, BIN_SE_MAX_MM)
    for tooth in range(z):
        for side, name in ((-1, "right"), (1, "left")):
            g = by_id.get(tooth * 2 + (side > 0), np.empty(0, int))
            b = np.clip(np.searchsorted(edges, roll[g]) - 1, 0, bins - 1)
            sw = np.bincount(b, w[g], minlength=bins)
            seen = (np.bincount(b, minlength=bins) >= MIN_BIN_POINTS) & (sw >= BIN_SE_MAX_MM**-2)
            left_out[name] += int(np.count_nonzero((sw > 0) & ~seen))
            trace = np.bincount(b, w[g] * f[g], minlength=bins) / np.where(seen, sw, np.nan)
            if seen.mean() < min_coverage:
                flanks.append(Flank(tooth, name, len(g), False))
                continue
            lx, ly = mids[seen], trace[seen]
            F_a, ff_a, fH_a = profile_quantities(lx, ly, l_b - l_a)
            near_p = np.abs(lx - l_p) <= 0.15 * (l_tip - l_start)
            near_p = near_p if near_p.sum() >= 3 else np.ones_like(near_p)  # too few near it: the whole trace's line
            ap, bp = _line(lx[near_p], ly[near_p], np.ones(int(near_p.sum())))
            pos = side * (ap + bp * l_p) * rp / rb
            positions[name][tooth] = 1e3 * pos
            flanks.append(Flank(
                tooth, name, len(g), True, position_um=1e3 * pos,
                F_alpha_um=1e3 * F_a, ff_alpha_um=1e3 * ff_a, fH_alpha_um=1e3 * fH_a, roll_mm=tuple(float(v) for v in lx),
                trace_um=tuple(float(1e3 * v) for v in ly),
            ))

    pitch = {n: pitch_deviations(p) for n, p in positions.items()}
    single = {n: v[0] for n, v in pitch.items()}
    cumulative = {n: p - p[0] for n, p in positions.items()}
    fp = {n: v[1] for n, v in pitch.items()}
    fp_total = {n: v[2] for n, v in pitch.items()}

    # ball probe in each tooth space k (tooth k left flank, tooth k+1 right flank), on the pitch circle
    gaps = (np.arange(z) + 0.5) * tau + theta0
    from_axis = ball_heights(positions["right"], positions["left"], gear.pressure_angle)
    from_ecc = 1e3 * ecc * np.cos(gaps - phi)
    curve = from_axis + from_ecc
    rng = lambda v: float(np.nanmax(v) - np.nanmin(v)) if np.isfinite(v).any() else math.nan  # noqa: E731

    tips, chip_noise, chip_conclusive = _tips(points, gear, centre, theta0, cad_mesh,
                                              tip_zone_mm if tip_zone_mm is not None else 0.25 * m,
                                              chip_mm, chip_area_mm2, voxel_mm)
    measured = [fl for fl in flanks if fl.measured]
    profile = {key: max((getattr(fl, f"{key}_um") for fl in measured), key=abs) if measured else math.nan
               for key in ("F_alpha", "ff_alpha", "fH_alpha")}
    return Inspection(
        teeth=z, module=m, pitch_diameter_mm=2 * rp, centre_mm=(float(centre[0]), float(centre[1])),
        eccentricity_um=1e3 * ecc, eccentricity_deg=math.degrees(phi), rotation_deg=math.degrees(theta0),
        section_mm=(float(z_mid - half), float(z_mid + half)), flanks=tuple(flanks),
        position_um={n: p.tolist() for n, p in positions.items()},
        single_pitch_um={n: v.tolist() for n, v in single.items()},
        cumulative_pitch_um={n: v.tolist() for n, v in cumulative.items()},
        fp_um=fp, Fp_um=fp_total, runout_curve_um=curve.tolist(), Fr_um=rng(curve),
        runout_from_eccentricity_um=rng(from_ecc), runout_about_gear_axis_um=rng(from_axis),
        tips=tips, chipped_teeth=tuple(t.tooth for t in tips if t.chipped), profile_um=profile,
        chip_noise_um=1e3 * chip_noise, chip_check_conclusive=chip_conclusive,
        settings={"section_fraction": section_fraction, "xi_start": xi_start, "xi_end": xi_end, "bins": bins,
                  "chip_mm": chip_mm, "chip_area_mm2": chip_area_mm2, "voxel_mm": voxel_mm,
                  "evaluation_roll_mm": (l_a, l_b), "min_bin_points": MIN_BIN_POINTS,
                  "bin_se_max_um": 1e3 * BIN_SE_MAX_MM, "datum": datum},
        profile_bins_left_out=sum(left_out.values()),
    )


def _tips(points, gear, centre, theta0, cad_mesh, zone, chip_mm, area_mm2, voxel_mm) -> tuple[tuple[ToothTip, ...], float, bool]:
    """Per tooth: tip-zone points, area below ``-chip_mm`` vs the CAD on the fitted axis, deepest deviation;
    with the cells' noise (mm) and whether the check can tell a chip from it."""
    import open3d as o3d

    z, tau = gear.teeth, gear.pitch_angle
    x, y = points[:, 0] - centre[0], points[:, 1] - centre[1]
    r = np.hypot(x, y)
    zone_pts = r > gear.tip_radius - zone
    if not zone_pts.any():
        raise ValueError(f"no point within {zone} mm of the tip circle: the cloud does not show the teeth's tips")
    c, s = math.cos(-theta0), math.sin(-theta0)
    aligned = np.stack([c * x - s * y, s * x + c * y, points[:, 2]], axis=1)[zone_pts]
    mesh = cad_mesh if cad_mesh is not None else gear.mesh()
    tmesh = mesh if isinstance(mesh, o3d.t.geometry.TriangleMesh) else o3d.t.geometry.TriangleMesh.from_legacy(mesh)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(tmesh)
    dev = scene.compute_signed_distance(o3d.core.Tensor(aligned.astype(np.float32))).numpy().astype(np.float64)
    ang = np.arctan2(aligned[:, 1], aligned[:, 0])
    kk = np.round(ang / tau)
    tooth = kk.astype(int) % z
    counts = np.bincount(tooth, minlength=z)
    # tooth-local cells (arc across the tooth x z, every radius of the zone): each tooth against the
    # median tooth in the same cell, so errors every tooth shares (all are seen through the same
    # views) cancel; a chipped corner's face sits in the cells of the surface it replaced
    cell = 0.1 if voxel_mm <= 0.1 else voxel_mm
    arc = (ang - kk * tau) * gear.tip_radius
    ia = np.floor((arc + gear.tip_radius * tau / 2) / cell).astype(int)
    iz = np.floor((aligned[:, 2] - aligned[:, 2].min()) / (4 * cell)).astype(int)
    shape = (ia.max() + 1, iz.max() + 1)
    flat = np.ravel_multi_index((ia, iz), shape)
    n_cells = int(np.prod(shape))
    idx = tooth * n_cells + flat
    sums = np.bincount(idx, dev, minlength=z * n_cells).reshape(z, n_cells)
    cnt = np.bincount(idx, minlength=z * n_cells).reshape(z, n_cells)
    mean = np.where(cnt > 0, sums / np.maximum(cnt, 1), np.nan)
    seen = np.isfinite(mean).sum(axis=0) >= max(3, z // 2)  # cells most teeth have
    rel = mean[:, seen] - np.nanmedian(mean[:, seen], axis=0)
    # how far the cells stray from the median tooth (95th percentile: a chip is a few cells of one
    # tooth, far fewer than 5 %): the chip threshold must stand above it, else the check flags noise
    # and misses chips alike
    noise = float(np.nanpercentile(np.abs(rel), 95)) if np.isfinite(rel).any() else math.inf
    low = np.nan_to_num(rel, nan=0.0) < -chip_mm
    missing = low.sum(axis=1) * cell * 4 * cell  # cell footprint across the tooth x along z
    depth = np.nanmin(np.where(np.isfinite(rel), rel, 0.0), axis=1) if rel.size else np.zeros(z)
    typical = float(np.median(counts)) if counts.any() else 0.0
    conclusive = CHIP_NOISE_MARGIN * noise <= chip_mm
    tips = tuple(
        ToothTip(int(t), int(counts[t]), float(missing[t]), float(depth[t]),
                 conclusive and bool(missing[t] > area_mm2 or counts[t] < 0.5 * typical))
        for t in range(z)
    )
    return tips, noise, conclusive
