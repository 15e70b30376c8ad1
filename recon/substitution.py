"""Measurement uncertainty of the ISO 1328-1 quantities by the substitution method, and conformity with it.

A calibrated master gear of the type to be measured is measured ``n`` times on the instrument, each time mounted
afresh (after ISO 15530-3, the substitution method for coordinate measuring machines). Per quantity, against the
master's certificate value ``c`` with expanded uncertainty ``U_cal`` (k = 2):

- bias ``b = mean(y) - c``; repeatability ``u_p``: the standard deviation of single readings (a user measures once);
- ``u_c = sqrt(u_cal^2 + u_p^2 + u_w^2)`` (``u_w``: what the user's gear adds beyond the master: form, temperature;
  stated by the user, default 0);
- ``U = k u_c + |b|``, ``k`` the two-sided 95.45 % Student factor at the Welch-Satterthwaite degrees of freedom
  (``u_p`` has ``n - 1``; the certificate's and ``u_w`` are taken as exactly known), so a few readings widen it.

The bias is added, not corrected: the headline quantities are ranges and worst flanks, whose noise inflation
shrinks as the true deviation grows, so the master's bias is not the user's gear's; added, it bounds it.

Conformity (ISO 14253-1, the tolerance narrowed by U): every quantity here is judged by its magnitude against one
limit ``T`` (|fH_alpha| too): conforms when ``|y| + U <= T``, does not when ``|y| - U > T``, else undecided.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

K_COVERAGE = 2.0  # certificates state U with k = 2; ours are stated at the same confidence (95.45 %)
CONFIDENCE = float(stats.norm.cdf(K_COVERAGE) - stats.norm.cdf(-K_COVERAGE))
MIN_READINGS = 3  # a standard deviation from fewer says nothing; ISO 15530-3 asks for 20 (in at least 3 series)
RECOMMENDED_READINGS = 20

# quantity key -> what it is (the inspection report's summary key, except Fr: the runout about the gear's own axis,
# as a master's certificate states it; the headline Fr is about the turntable axis and carries the mounting)
QUANTITIES = {
    "fp": "single pitch deviation (largest |fp|)",
    "Fp": "total cumulative pitch deviation",
    "Fr_gear_axis": "runout about the gear's own axis (ball probe, tooth spaces alone)",
    "F_alpha": "total profile deviation (worst flank)",
    "ff_alpha": "profile form deviation (worst flank)",
    "fH_alpha": "profile slope deviation (largest |fH_alpha|, signed)",
}
# the ISO 1328-1 tolerance each is judged against (iso1328_tolerances keys)
TOLERANCE_KEY = {"fp": "fp", "Fp": "Fp", "Fr_gear_axis": "Fr", "F_alpha": "F_alpha", "ff_alpha": "ff_alpha",
                 "fH_alpha": "fH_alpha"}


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
    refused by name; quantities beyond :data:`QUANTITIES` are refused too."""
    unknown = sorted(set(certificate) - set(QUANTITIES))
    if unknown:
        raise SubstitutionError(f"certificate: unknown quantities {unknown}; expected some of {list(QUANTITIES)}")
    if not certificate:
        raise SubstitutionError(f"certificate: states no quantity; expected some of {list(QUANTITIES)}")
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
    right, left = (np.asarray(position_um[s], np.float64) for s in ("right", "left"))
    radial = -(np.roll(right, -1) - left) / (2 * math.tan(pressure_angle_rad))
    return float(radial.max() - radial.min())
