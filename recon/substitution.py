"""Measurement uncertainty of the ISO 1328-1 quantities from a master gear measured repeatedly, and conformity with it.

A calibrated master gear of the type to be measured is measured ``n`` times, each time mounted afresh (the idea of
ISO 15530-3's substitution method). Two ways to turn the readings into an uncertainty:

- :func:`quantity_uncertainty`, ISO 15530-3's form on the headline readings: ``U = k sqrt(u_cal^2 + u_p^2 + u_w^2) +
  |bias|``. It assumes the instrument's error on a headline does not depend on the gear. It does: the headlines are
  worst flanks and ranges, and which flank is worst follows the gear's own deviations while the reconstruction's
  errors differ by flank side. Kept to show that (``benchmarks/substitution_report.md``), not shipped.
- :func:`bound_uncertainty`, shipped: every headline ``Q`` is a range, a largest magnitude or a slope of per-flank
  traces and per-tooth positions, so ``|Q(read) - Q(true)| <= Q'(read - true)`` (:func:`error_functionals`): the
  same functional of the instrument's own error, which does not depend on the gear's micrometre deviations. The
  master gives one sample of each ``Q'`` per mounting; U is their one-sided normal tolerance bound (95 % of
  mountings at 95 % confidence) plus the certificate's U. A bound, so conservative.

Conformity (ISO 14253-1, the tolerance narrowed by U): every quantity is judged by its magnitude against one limit
``T`` (|fH_alpha| and |fp| against their ± limits): conforms when ``|y| + U <= T``, does not when ``|y| - U > T``, else
undecided.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

from gearscan.recon.inspect import ball_heights, pitch_deviations, profile_quantities

K_COVERAGE = 2.0  # certificates state U with k = 2; ours are stated at the same confidence (95.45 %)
CONFIDENCE = float(stats.norm.cdf(K_COVERAGE) - stats.norm.cdf(-K_COVERAGE))
MIN_READINGS = 3  # a standard deviation from fewer says nothing; ISO 15530-3 asks for 20 (in at least 3 series)
RECOMMENDED_READINGS = 20

# quantity key -> what it is (the inspection report's summary key, except Fr_gear_axis: the ball-probe runout about
# the inspection's datum axis (recon.inspect.DATUMS), which leaves out the gear's eccentricity on the turntable and,
# with the "teeth" datum, the teeth's eccentricity to their bore: not ISO's Fr, so it gets a U but no ISO 14253-1
# decision)
BUDGETED = {
    "fp": "single pitch deviation (the largest in magnitude)",
    "Fp": "total cumulative pitch deviation",
    "Fr_gear_axis": "runout about the gear's own axis (ball probe, tooth spaces alone)",
    "F_alpha": "total profile deviation (worst flank)",
    "ff_alpha": "profile form deviation (worst flank)",
    "fH_alpha": "profile slope deviation (the largest in magnitude, signed)",
}
# the ISO 1328-1 tolerance each is judged against (iso1328_tolerances keys); Fr_gear_axis is not ISO's Fr
TOLERANCE_KEY = {"fp": "fp", "Fp": "Fp", "F_alpha": "F_alpha", "ff_alpha": "ff_alpha", "fH_alpha": "fH_alpha"}
TOLERANCE_COVERAGE = 0.95  # the bound covers this share of mountings ...
TOLERANCE_CONFIDENCE = 0.95  # ... with this confidence


class SubstitutionError(ValueError):
    """Readings or a certificate that cannot give an uncertainty; the message names what and why."""


@dataclass(frozen=True)
class QuantityUncertainty:
    """One quantity's budget: the master's certified value and the instrument's readings of it, in µm."""

    key: str
    certified: float
    U_cal: float
    readings: tuple[float, ...]
    mean: float
    bias: float
    u_cal: float
    u_p: float
    u_w: float
    dof: float
    k: float
    U: float

    @property
    def n(self) -> int:
        return len(self.readings)


def quantity_uncertainty(key: str, certified: float, U_cal: float, readings: Sequence[float],
                         u_w: float = 0.0) -> QuantityUncertainty:
    """The budget of one quantity from its certificate value and ``U_cal`` (k = 2) and ``n`` readings (µm)."""
    y = np.asarray([float(v) for v in readings], np.float64)
    if not (math.isfinite(certified) and math.isfinite(U_cal) and U_cal >= 0):
        raise SubstitutionError(f"{key}: certificate value {certified} +- {U_cal}: expected finite numbers, U >= 0")
    if not (math.isfinite(u_w) and u_w >= 0):
        raise SubstitutionError(f"{key}: u_w {u_w}: expected a finite standard uncertainty >= 0")
    if y.size < MIN_READINGS or not np.isfinite(y).all():
        raise SubstitutionError(f"{key}: {int(np.isfinite(y).sum())} finite readings of {y.size}: the substitution "
                                f"method needs at least {MIN_READINGS} (ISO 15530-3 asks for {RECOMMENDED_READINGS})")
    mean, u_p = float(y.mean()), float(y.std(ddof=1))
    u_cal = U_cal / K_COVERAGE
    u_c2 = u_cal**2 + u_p**2 + u_w**2
    dof = math.inf if u_p == 0 else u_c2**2 / (u_p**4 / (y.size - 1))
    k = K_COVERAGE if math.isinf(dof) else float(stats.t.ppf(0.5 + CONFIDENCE / 2, dof))
    bias = mean - certified
    return QuantityUncertainty(key, float(certified), float(U_cal), tuple(float(v) for v in y), mean, bias, u_cal,
                               u_p, float(u_w), dof, k, k * math.sqrt(u_c2) + abs(bias))


def substitution_uncertainty(certificate: Mapping[str, tuple[float, float]],
                             readings: Sequence[Mapping[str, float]],
                             u_w: Mapping[str, float] | None = None) -> dict[str, QuantityUncertainty]:
    """Per quantity the certificate states (``key -> (value, U_cal)``, µm): its budget from ``readings`` (one
    mapping ``key -> value`` per measurement of the master). A quantity the certificate states but a reading lacks is
    refused by name; quantities beyond :data:`BUDGETED` are refused too."""
    unknown = sorted(set(certificate) - set(BUDGETED))
    if unknown:
        raise SubstitutionError(f"certificate: unknown quantities {unknown}; expected some of {list(BUDGETED)}")
    if not certificate:
        raise SubstitutionError(f"certificate: states no quantity; expected some of {list(BUDGETED)}")
    u_w = dict(u_w or {})
    out = {}
    for key, (value, U_cal) in certificate.items():
        missing = [i for i, r in enumerate(readings) if r.get(key) is None]
        if missing:
            raise SubstitutionError(f"{key}: not measured in reading(s) {missing} (of {len(readings)})")
        out[key] = quantity_uncertainty(key, value, U_cal, [r[key] for r in readings], u_w.get(key, 0.0))
    return out


CONFORMS, DOES_NOT_CONFORM, UNDECIDED = "conforms", "does not conform", "undecided"


def conformity(value: float, U: float, tolerance: float) -> str:
    """ISO 14253-1 decision for a quantity judged by its magnitude against ``tolerance`` with expanded
    uncertainty ``U`` (all µm): :data:`CONFORMS`, :data:`DOES_NOT_CONFORM` or :data:`UNDECIDED`."""
    if not all(math.isfinite(v) for v in (value, U, tolerance)) or U < 0 or tolerance <= 0:
        raise ValueError(f"conformity: value {value}, U {U}, tolerance {tolerance}: expected finite, U >= 0, T > 0")
    if abs(value) + U <= tolerance:
        return CONFORMS
    if abs(value) - U > tolerance:
        return DOES_NOT_CONFORM
    return UNDECIDED


def profile_truth(offset_um, xi_start: float, xi_end: float, bins: int) -> dict[str, float]:
    """F_alpha, ff_alpha and fH_alpha (µm) of a flank whose normal offset is ``offset_um(xi)`` (xi: roll fraction
    from the involute start to the tip, as :func:`~gearscan.recon.inspect.inspect_gear` bins it), evaluated as the
    inspection does: at the bins' centres over ``[xi_start, xi_end]``, the mean line by least squares."""
    edges = np.linspace(xi_start, xi_end, bins + 1)
    xi = 0.5 * (edges[:-1] + edges[1:])
    f = np.asarray(offset_um(xi), np.float64)
    slope, icept = np.polyfit(xi, f, 1)
    resid = f - (icept + slope * xi)
    return {"F_alpha": float(f.max() - f.min()), "ff_alpha": float(resid.max() - resid.min()),
            "fH_alpha": float(slope * (xi_end - xi_start))}


def runout_about_gear_axis(position_um: Mapping[str, Sequence[float]], pressure_angle_rad: float) -> float:
    """Ball-probe runout about the gear's own axis (µm) from each flank's position along +theta on the pitch circle
    (``right``/``left``, one per tooth), as :func:`~gearscan.recon.inspect.inspect_gear` reads the tooth spaces."""
    radial = ball_heights(position_um["right"], position_um["left"], pressure_angle_rad)
    return float(radial.max() - radial.min())


def tolerance_factor(n: int, coverage: float = TOLERANCE_COVERAGE, confidence: float = TOLERANCE_CONFIDENCE) -> float:
    """One-sided normal tolerance factor: ``mean + k s`` of ``n`` samples exceeds ``coverage`` of the population
    with ``confidence`` (the noncentral t; ISO 16269-6). 4.20 at n = 5, 2.91 at 10, 2.40 at 20."""
    if n < 2:
        raise SubstitutionError(f"tolerance factor: needs at least 2 samples, got {n}")
    return float(stats.nct.ppf(confidence, n - 1, stats.norm.ppf(coverage) * math.sqrt(n)) / math.sqrt(n))


@dataclass(frozen=True)
class QuantityBound:
    """One quantity's stated uncertainty by the bound method: per mounting of the master the bound ``Q'`` on its
    headline's error (µm), and U (µm) that bounds it for :data:`TOLERANCE_COVERAGE` of mountings."""

    key: str
    samples: tuple[float, ...]
    mean: float
    s: float
    k: float
    U_cal: float
    U: float

    @property
    def n(self) -> int:
        return len(self.samples)


def bound_uncertainty(key: str, samples: Sequence[float], U_cal: float = 0.0) -> QuantityBound:
    """U of one quantity from its error bounds ``samples`` (one per mounting of the master, µm) and the
    certificate's ``U_cal``: the one-sided tolerance bound ``mean + k s`` plus ``U_cal`` (added: the master's own
    deviation from its certificate moves every reading alike)."""
    y = np.asarray([float(v) for v in samples], np.float64)
    if not (math.isfinite(U_cal) and U_cal >= 0):
        raise SubstitutionError(f"{key}: certificate U {U_cal}: expected a finite number >= 0")
    if not np.isfinite(y).all() or (y < 0).any():
        raise SubstitutionError(f"{key}: error bounds {y.round(3).tolist()}: expected finite numbers >= 0")
    if y.size < MIN_READINGS:
        raise SubstitutionError(f"{key}: {y.size} measurements of the master: at least {MIN_READINGS} are needed "
                                f"(ISO 15530-3 asks for {RECOMMENDED_READINGS})")
    k = tolerance_factor(y.size)
    mean, s = float(y.mean()), float(y.std(ddof=1))
    return QuantityBound(key, tuple(float(v) for v in y), mean, s, k, float(U_cal), mean + k * s + float(U_cal))


@dataclass(frozen=True)
class FlankTrace:
    """One measured flank's profile trace as the inspection read it: roll lengths (mm) and normal deviations (µm)."""

    tooth: int
    side: str
    roll_mm: tuple[float, ...]
    trace_um: tuple[float, ...]


@dataclass(frozen=True)
class Evaluation:
    """Where the inspection evaluated the profiles: roll lengths ``l_a`` to ``l_b`` (mm), which are the roll
    fractions ``xi_start`` to ``xi_end`` from the involute's start to the tip, in ``bins`` bins."""

    l_a: float
    l_b: float
    xi_start: float
    xi_end: float
    bins: int = 20

    def xi(self, roll_mm) -> np.ndarray:
        """Roll fraction of roll lengths (mm)."""
        roll = np.asarray(roll_mm, np.float64)
        return self.xi_start + (roll - self.l_a) / (self.l_b - self.l_a) * (self.xi_end - self.xi_start)

    def centres_mm(self) -> np.ndarray:
        """Every bin's centre (mm): where a whole profile is read."""
        edges = np.linspace(self.l_a, self.l_b, self.bins + 1)
        return 0.5 * (edges[:-1] + edges[1:])


def error_functionals(flanks: Sequence[FlankTrace], positions_um: Mapping[str, Sequence[float]], evaluation: Evaluation,
                      true_offset_um, true_positions_um: Mapping[str, Sequence[float]],
                      pressure_angle_rad: float) -> dict[str, float]:
    """Per headline quantity the bound ``Q'`` on its error in one measurement (µm): ``|Q(read) - Q(true)|`` is at most
    this (``|fH_alpha|`` by magnitude), Q(true) over every bin of the flanks and the teeth that were read.

    ``true_offset_um(side, xi)``: a flank's true normal offset (µm) at roll fractions ``xi``; ``true_positions_um``:
    each flank's true position on the pitch circle (µm, per side, one per tooth). A constant in either cancels (the
    inspection's datum is its own). Per flank ``Q'`` is the functional of the error trace (read minus true at the
    bins read) plus what the bins not read change in the true profile's value. Flanks or teeth not read at all take
    no part: their headline may be larger (the inspection's coverage says so). NaN where nothing was read.
    """
    span, full = evaluation.l_b - evaluation.l_a, evaluation.centres_mm()
    whole_of = {side: profile_quantities(full, np.asarray(true_offset_um(side, evaluation.xi(full)), np.float64), span)
                for side in {fl.side for fl in flanks}}  # the true profile's values over every bin, per side
    prof: dict[str, float] = {"F_alpha": math.nan, "ff_alpha": math.nan, "fH_alpha": math.nan}
    for fl in flanks:
        roll = np.asarray(fl.roll_mm, np.float64)
        true = np.asarray(true_offset_um(fl.side, evaluation.xi(roll)), np.float64)
        err = profile_quantities(roll, np.asarray(fl.trace_um, np.float64) - true, span)
        # the bins not read: how much the true profile's value over the bins read differs from its whole one's
        part, whole = profile_quantities(roll, true, span), whole_of[fl.side]
        terms = (err[0] + abs(part[0] - whole[0]), err[1] + abs(part[1] - whole[1]),
                 abs(err[2]) + abs(abs(part[2]) - abs(whole[2])))
        prof = {k: float(np.nanmax([prof[k], v])) for k, v in zip(prof, terms, strict=True)}
    d = {s: np.asarray(positions_um[s], np.float64) - np.asarray(true_positions_um[s], np.float64)
         for s in ("left", "right")}

    pitch = [pitch_deviations(v) for v in d.values()]  # fp and Fp of the errors bound those of the readings
    radial = ball_heights(d["right"], d["left"], pressure_angle_rad)
    radial = radial[np.isfinite(radial)]
    return {**prof, "fp": float(np.nanmax([v[1] for v in pitch])), "Fp": float(np.nanmax([v[2] for v in pitch])),
            "Fr_gear_axis": float(radial.max() - radial.min()) if radial.size else math.nan}
