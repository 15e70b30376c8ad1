"""Monte Carlo uncertainty (paper §2.4), its propagation to phase, and calibration (§3.6).

Per pixel, with T stochastic passes giving means ``(M_t, D_t)`` and variances ``(s_Mt, s_Dt)``:

- model variance of M: ``var_t(M_t)`` (population variance of the T means), same for D;
- data variance of M: ``mean_t(s_Mt)``, same for D;
- phase ``phi = atan2(mean M, mean D)``; first-order propagation with
  ``dphi/dM = D / (M^2 + D^2)`` and ``dphi/dD = -M / (M^2 + D^2)`` (M, D independent):
  ``sigma_phi^2 = (dphi/dM)^2 var_M + (dphi/dD)^2 var_D``, separately for model and data;
- total ``sqrt(model^2 + data^2)`` (eq. 19).

Calibration: per pixel, ``confidence = P(|err| < eps) = erf(eps / (sigma sqrt 2))`` under
``N(0, sigma^2)``, ``eps = 0.03 rad``; pixels are binned by confidence (30 equal bins on
[0, 1]); the reliability diagram plots empirical ``P(|err| < eps)`` against mean confidence per
bin; ``ECE = sum_b (n_b / n) |acc_b - conf_b|``.

Two calibration maps are stored with a model. ``var_scale`` (fitted by training) multiplies the
M, D variances before propagation. ``sigma_calibration`` (fitted by ``gearscan calibrate-uncertainty``, one
per mode: deterministic and Monte Carlo) then maps the propagated total sigma: the power law
:class:`SigmaCalibration`, ``sigma' = a * sigma**b * (departure + d0)**c``, where the departure is
how far the network's phase lies from three-step PS's on the same frames, or :class:`AdditiveSigmaMap`,
piecewise-linear in log sigma, log departure and the log fringe density of the network's phase
(session 41, ``benchmarks/sigma_map_form_rule.md`` and ``sigma_map_form_mc_rule.md``) and, in form
``"additive-local"``, also the log curvature of that phase and the log local departure (v9's maps in both modes
since session 42, ``sigma_map_local_rule.md`` and ``sigma_map_local_mc_rule.md``); an MC map may also read the
aleatoric part of its sigma apart (form ``"additive-local-data"``, ``sigma_map_data_mc_rule.md``: not shipped).
Either is fitted by the log
score of the ECE's own event ``|err| < eps`` (:func:`event_log_score`), a proper scoring rule:
ECE alone is minimised by a constant sigma (measured: ECE 0.001 with every pixel at 0.07 rad),
which would erase where the network is unsure; the Gaussian NLL is pulled by the errors' heavy
tails. The network alone cannot tell a still burst from a moving one; the departure can, and
without it the map did not carry from one validation family to another (the model cards,
"Uncertainty calibration").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.special import erf, erfcx

from gearscan.core.phase import phase_error
from gearscan.core.types import PhaseResult
from gearscan.inference.concrete_dropout import set_stochastic
from gearscan.inference.models import PhaseNet


@dataclass(frozen=True, slots=True)
class MomentStats:
    """Per-pixel moments of M and D, each ``(..., H, W)``."""

    M: torch.Tensor
    D: torch.Tensor
    model_var_M: torch.Tensor
    model_var_D: torch.Tensor
    data_var_M: torch.Tensor
    data_var_D: torch.Tensor


def phase_sigma(M: np.ndarray, D: np.ndarray, var_M: np.ndarray, var_D: np.ndarray) -> np.ndarray:
    """First-order std of ``atan2(M, D)`` for independent M, D with these variances (rad)."""
    r2 = np.maximum(M.astype(np.float64) ** 2 + D.astype(np.float64) ** 2, 1e-12)
    return np.sqrt((D**2 * var_M + M**2 * var_D) / r2**2).astype(np.float32)


def _is_zero(t: torch.Tensor) -> bool:
    return not bool(t.any())


@torch.no_grad()
def mc_moments(
    model: torch.nn.Module,
    x: torch.Tensor,
    passes: int,
    chunk: int = 2,
    *,
    reuse_prefix: bool = True,
) -> MomentStats:
    """Run ``passes`` stochastic forward passes of ``x`` ``(B, C, H, W)`` in chunks of ``chunk``.

    Each chunk is one batched forward of ``chunk`` passes. The model is put in eval mode (BN
    running statistics) with its Concrete Dropout masks on, and restored to deterministic
    afterwards.

    ``reuse_prefix`` (a :class:`~gearscan.inference.models.PhaseNet`): what precedes the first
    stochastic layer (classical M, D, padding, the stem) is computed once, not once per pass,
    the first dropout layer's passes run as one convolution
    (:func:`~gearscan.inference.models.dropout_on_shared_input`), and the moments are accumulated
    in float32 around the first pass's means (shift-invariant; the classical M, D of a residual
    network are added once at the end). The masks are drawn in the same order and shapes as
    the plain path's, so for the same random stream both give the same samples and moments up
    to float rounding. Other models, or ``reuse_prefix=False``: every pass runs the whole model
    on ``x.repeat(chunk, 1, 1, 1)``, moments in float64.
    """
    if passes < 1:
        raise ValueError(f"passes: expected >= 1, got {passes}")
    if chunk < 1:
        raise ValueError(f"chunk: expected >= 1, got {chunk}")
    was_training = model.training
    model.eval()
    set_stochastic(model, True)
    try:
        if reuse_prefix and isinstance(model, PhaseNet):
            return _mc_moments_split(model, x, passes, chunk)
        return _mc_moments_plain(model, x, passes, chunk)
    finally:
        set_stochastic(model, False)
        model.train(was_training)


def _mc_moments_plain(
    model: torch.nn.Module, x: torch.Tensor, passes: int, chunk: int
) -> MomentStats:
    b = x.shape[0]
    s1 = torch.zeros((b, 2, *x.shape[2:]), dtype=torch.float64, device=x.device)
    s2 = torch.zeros_like(s1)
    sv = torch.zeros_like(s1)
    done = 0
    while done < passes:
        k = min(chunk, passes - done)
        out = model(x.repeat(k, 1, 1, 1)).double().view(k, b, 4, *x.shape[2:])
        s1 += out[:, :, :2].sum(0)
        s2 += (out[:, :, :2] ** 2).sum(0)
        sv += out[:, :, 2:].sum(0)
        done += k
    mean = s1 / passes
    model_var = (s2 / passes - mean**2).clamp_min(0)
    return _stats(mean, model_var, sv / passes)


def _mc_moments_split(model: PhaseNet, x: torch.Tensor, passes: int, chunk: int) -> MomentStats:
    b = x.shape[0]
    prefix = model.mc_prefix(x)
    shift = s1 = s2 = sv = None
    done = 0
    while done < passes:
        k = min(chunk, passes - done)
        mean, var = model.mc_passes(prefix, k)
        mean = mean.view(k, b, *mean.shape[1:])
        var = var.view(k, b, *var.shape[1:])
        if shift is None:
            shift = mean[0].clone()
            s1, s2, sv = torch.zeros_like(shift), torch.zeros_like(shift), torch.zeros_like(shift)
        d = mean - shift
        s1 += d.sum(0)
        s2 += (d * d).sum(0)
        sv += var.sum(0)
        done += k
    d_mean = s1 / passes
    model_var = (s2 / passes - d_mean**2).clamp_min(0)
    mean = shift + d_mean
    if prefix.base is not None:
        mean = mean + prefix.base
    return _stats(mean, model_var, sv / passes)


def _stats(mean: torch.Tensor, model_var: torch.Tensor, data_var: torch.Tensor) -> MomentStats:
    f = torch.float32
    return MomentStats(
        mean[:, 0].to(f),
        mean[:, 1].to(f),
        model_var[:, 0].to(f),
        model_var[:, 1].to(f),
        data_var[:, 0].to(f),
        data_var[:, 1].to(f),
    )


@torch.no_grad()
def deterministic_moments(model: torch.nn.Module, x: torch.Tensor) -> MomentStats:
    """One pass with dropout off: model variance zero, data variance the predicted one."""
    was_training = model.training
    model.eval()
    set_stochastic(model, False)
    try:
        out = model(x).float()
    finally:
        model.train(was_training)
    zero = torch.zeros_like(out[:, 0])
    return MomentStats(out[:, 0], out[:, 1], zero, zero, out[:, 2], out[:, 3])


def moments_about(mc: MomentStats, point: MomentStats) -> MomentStats:
    """``mc``'s moments about ``point``'s M, D instead of about their own mean: the passes' variance plus the squared
    offset of their mean from the point (their mean square deviation from it); data variance the passes' mean.

    Monte Carlo mode reports the deterministic pass's phase with the passes' spread around it
    (``benchmarks/mc_phase_rule.md``: on val the mean of 20 passes was no more accurate and varied from run to run).
    """
    return MomentStats(point.M, point.D, mc.model_var_M + (mc.M - point.M) ** 2, mc.model_var_D + (mc.D - point.D) ** 2,
                       mc.data_var_M, mc.data_var_D)


DEPARTURE_FLOOR = 0.01  # rad: the departure term's floor (noise keeps a still burst's from zero)


def departure(phase: np.ndarray, classical_phase: np.ndarray) -> np.ndarray:
    """``|wrap(phase - classical_phase)|`` (rad): how far the network moved off three-step PS.

    A run-time witness of the network's error: on a still burst three-step PS is right and this is
    the network's error; on a moving one it is the correction the network dared.
    """
    return np.abs(phase_error(phase, classical_phase)).astype(np.float32)


@dataclass(frozen=True, slots=True)
class SigmaCalibration:
    """Map of the total phase sigma: ``sigma' = a * sigma**b * (departure + d0)**c``.

    ``departure`` (:func:`departure`, rad) is how far the network's phase lies from three-step
    PS's on the same frames; ``c = 0`` (the default, and every map stored before it existed) is
    the plain power law. Identity: a = b = 1, c = 0. Applied per pixel as one factor
    ``sigma'/sigma`` on the model, data and total sigmas (their ratio is kept) and its square
    on the M, D variances, so the result stays self-consistent.
    """

    a: float = 1.0
    b: float = 1.0
    c: float = 0.0
    d0: float = DEPARTURE_FLOOR

    def __post_init__(self) -> None:
        ok = (math.isfinite(self.a) and self.a > 0 and math.isfinite(self.b) and 0 < self.b <= 3
              and math.isfinite(self.c) and -3 <= self.c <= 3 and math.isfinite(self.d0) and self.d0 > 0)
        if not ok:
            raise ValueError(
                f"sigma calibration: expected a > 0, 0 < b <= 3, -3 <= c <= 3 and d0 > 0, "
                f"got a={self.a}, b={self.b}, c={self.c}, d0={self.d0}"
            )

    @property
    def identity(self) -> bool:
        return self.a == 1.0 and self.b == 1.0 and self.c == 0.0

    @property
    def needs_departure(self) -> bool:
        """The map reads the departure from three-step PS (``c != 0``)."""
        return self.c != 0.0

    needs_density = False  # the power law does not read the fringe density
    needs_local = False  # nor the curvature or the local departure
    needs_sigma_data = False  # nor the aleatoric part apart

    @property
    def needs_classical(self) -> bool:
        """The map reads three-step PS's phase (through the departure)."""
        return self.needs_departure

    def __call__(self, sigma: np.ndarray, departure: np.ndarray | None = None,
                 density: np.ndarray | None = None, **local: np.ndarray | None) -> np.ndarray:
        return self.factor(sigma, departure) * np.maximum(np.asarray(sigma, np.float32), np.float32(1e-12))

    def departure_factor(self, departure: np.ndarray, local_departure: np.ndarray | None = None) -> np.ndarray:
        """The departure's own factor, ``(departure + d0)**c``: a still-burst gate swaps the network's departure
        for three-step PS's own (zero) by the ratio of two of these."""
        return np.power(np.asarray(departure, np.float32) + np.float32(self.d0), np.float32(self.c))

    def factor(self, sigma_total: np.ndarray, departure: np.ndarray | None = None,
               density: np.ndarray | None = None, **local: np.ndarray | None) -> np.ndarray:
        """``sigma'/sigma`` per pixel (float32: this runs on every burst); ``density`` and ``local`` are not read."""
        s = np.maximum(np.asarray(sigma_total, np.float32), np.float32(1e-12))
        f = np.float32(self.a) * np.power(s, np.float32(self.b - 1.0))
        if self.needs_departure:
            if departure is None or np.shape(departure) != s.shape:
                raise ValueError(
                    f"sigma calibration with c={self.c:g}: expected a departure map of shape {s.shape} "
                    f"(|network - three-step| phase), got {None if departure is None else np.shape(departure)}"
                )
            f = f * self.departure_factor(departure)
        return f

    def to_json(self) -> dict[str, float]:
        out = {"a": self.a, "b": self.b}
        return out | ({"c": self.c, "d0": self.d0} if self.needs_departure else {})

    @classmethod
    def from_json(cls, data: Any, source: str = "sigma_calibration") -> SigmaCalibration:
        keys = set(data) if isinstance(data, dict) else None
        if keys not in ({"a", "b"}, {"a", "b", "c", "d0"}):
            raise ValueError(
                f"{source}: expected {{'a': float, 'b': float}} or {{'a', 'b', 'c', 'd0'}}, got {data!r}"
            )
        try:
            return cls(**{k: float(v) for k, v in data.items()})
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{source}: {exc}") from exc


SIGMA_FLOOR = 1e-6  # rad: the sigma feature's floor before its log
DENSITY_FLOOR = 0.02  # rad/px: the fringe density's floor before its log
LOCAL_FLOOR = 0.01  # rad/px^2, rad: the curvature's and the local departure's floor before their logs
MAP_FEATURES = ("sigma", "departure", "density", "curvature", "local_departure", "sigma_data")
# the additive forms by the features they read (benchmarks/sigma_map_form_rule.md, sigma_map_local_rule.md,
# sigma_map_data_mc_rule.md: the aleatoric part apart, MC mode only)
FORM_FEATURES = {"additive": ("sigma", "departure", "density"),
                 "additive-local": ("sigma", "departure", "density", "curvature", "local_departure"),
                 "additive-local-data": ("sigma", "departure", "density", "curvature", "local_departure", "sigma_data")}
MC_ONLY_FORMS = ("additive-local-data",)  # the deterministic pass's aleatoric sigma is its total: nothing apart
LOCAL_WINDOW = 7  # px: the local departure's window (benchmarks/sigma_map_local_rule.md)
LOG_SIGMA_RANGE = (math.log(1e-5), math.log(10.0))  # a mapped sigma stays within 1e-5..10 rad, where hinges extrapolate


def fringe_density(phase: np.ndarray) -> np.ndarray:
    """``|grad phase|`` of a wrapped phase (rad/px; per axis the mean of the wrapped forward and backward
    differences, so a mirrored image gives the mirrored map; an edge pixel has only its inner one, halved):
    2 pi over the local fringe period, capped at pi. Dense fringes are where the network's phase errs most."""
    p = np.pad(np.asarray(phase, np.float64), 1, mode="edge")
    c = p[1:-1, 1:-1]
    gx = 0.5 * (phase_error(p[1:-1, 2:], c) + phase_error(c, p[1:-1, :-2]))
    gy = 0.5 * (phase_error(p[2:, 1:-1], c) + phase_error(c, p[:-2, 1:-1]))
    return np.minimum(np.hypot(gx, gy), np.pi).astype(np.float32)


def phase_curvature(phase: np.ndarray) -> np.ndarray:
    """``|Laplacian|`` of a wrapped phase (rad/px^2; each neighbour difference wrapped, the image's edge repeated):
    where the fringes bend or break (tooth tips, shadow and mask edges), which a sigma map reads as risk."""
    p = np.pad(np.asarray(phase, np.float64), 1, mode="edge")
    c = p[1:-1, 1:-1]
    lap = sum(phase_error(n, c) for n in (p[1:-1, 2:], p[1:-1, :-2], p[2:, 1:-1], p[:-2, 1:-1]))
    return np.abs(lap).astype(np.float32)


def local_departure(departure_map: np.ndarray, window: int = LOCAL_WINDOW) -> np.ndarray:
    """RMS of a departure map (:func:`departure`) over ``window`` x ``window`` pixels (edges mirrored): how hard the
    network corrects around a pixel, where the pixel's own departure may be small by chance."""
    from scipy.ndimage import maximum_filter, uniform_filter

    d = np.asarray(departure_map, np.float64)
    if d.ndim != 2:
        raise ValueError(f"local_departure: expected an (H, W) departure map, got shape {d.shape}")
    bad = ~np.isfinite(d)  # the filter's running sum would carry a NaN along the whole row: keep it in its window
    out = np.sqrt(np.maximum(uniform_filter(np.where(bad, 0.0, d * d), window, mode="reflect"), 0.0))
    if bad.any():
        out[maximum_filter(bad, window, mode="reflect")] = np.nan
    return out.astype(np.float32)


def log_map_feature(name: str, values: np.ndarray) -> np.ndarray:
    """The additive map's x for feature ``name`` (:data:`MAP_FEATURES`): log sigma (the total, or the aleatoric part
    ``sigma_data``), log(departure + 0.01), log(min(density, pi) + 0.02), log(curvature + 0.01), log(local departure +
    0.01)."""
    v = np.asarray(values, np.float32)
    if name in ("sigma", "sigma_data"):
        return np.log(np.maximum(v, np.float32(SIGMA_FLOOR)))
    if name == "departure":
        return np.log(v + np.float32(DEPARTURE_FLOOR))
    if name == "density":
        return np.log(np.minimum(v, np.float32(np.pi)) + np.float32(DENSITY_FLOOR))
    if name in ("curvature", "local_departure"):
        return np.log(v + np.float32(LOCAL_FLOOR))
    raise ValueError(f"sigma map feature: expected one of {MAP_FEATURES}, got {name!r}")


@dataclass(frozen=True, slots=True)
class HingeTerm:
    """One feature's part of :class:`AdditiveSigmaMap`: ``slope * x + sum_k hinges[k] * max(x - knots[k], 0)``."""

    feature: str
    slope: float
    knots: tuple[float, ...] = ()
    hinges: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        values = (self.slope, *self.knots, *self.hinges)
        if self.feature not in MAP_FEATURES or len(self.knots) != len(self.hinges) \
                or not all(math.isfinite(v) for v in values) or list(self.knots) != sorted(self.knots):
            raise ValueError(f"sigma map term: expected a feature of {MAP_FEATURES}, finite numbers and as many "
                             f"hinges as sorted knots, got {self.feature!r}, slope {self.slope}, knots {self.knots}, "
                             f"hinges {self.hinges}")

    def __call__(self, x: np.ndarray) -> np.ndarray:
        out = np.float32(self.slope) * x
        for q, g in zip(self.knots, self.hinges, strict=True):
            out = out + np.float32(g) * np.maximum(x - np.float32(q), np.float32(0))
        return out


@dataclass(frozen=True, slots=True)
class AdditiveSigmaMap:
    """Map of the total phase sigma, additive in log features: ``log sigma' = intercept + sum of terms``, each a
    piecewise-linear function (:class:`HingeTerm`) of log sigma, log(departure + 0.01) or log(fringe density + 0.02),
    and in form ``"additive-local"`` also log(curvature + 0.01) and log(local departure + 0.01)
    (:func:`phase_curvature`, :func:`local_departure`; ``benchmarks/sigma_map_local_rule.md``), and in form
    ``"additive-local-data"`` (MC mode) also the log of the aleatoric part of the sigma (``sigma_data``: the passes'
    mean data variance propagated at the reported M, D; the total adds their spread;
    ``benchmarks/sigma_map_data_mc_rule.md``).

    Where the power law (:class:`SigmaCalibration`) is one curve for every rig, the hinges let each feature bend and
    the fringe density (:func:`fringe_density`, the network's own phase, no CAD) tells dense fringes, where the
    network errs most, from sparse ones (``benchmarks/sigma_map_form_rule.md``). Applied as one factor, like the
    power law. Additive, so a still-burst gate can read it at zero departure (:meth:`departure_factor`).
    """

    intercept: float
    terms: tuple[HingeTerm, ...]

    def __post_init__(self) -> None:
        names = [t.feature for t in self.terms]
        if not math.isfinite(self.intercept) or "sigma" not in names or len(set(names)) != len(names):
            raise ValueError(f"additive sigma map: expected a finite intercept and one term per feature, the sigma's "
                             f"among them, got intercept {self.intercept}, features {names}")

    identity = False

    def _term(self, name: str) -> HingeTerm | None:
        return next((t for t in self.terms if t.feature == name), None)

    @property
    def needs_departure(self) -> bool:
        return self._term("departure") is not None

    @property
    def needs_density(self) -> bool:
        return self._term("density") is not None

    @property
    def needs_local(self) -> bool:
        """The map reads the curvature or the local departure (:data:`FORM_FEATURES` ``"additive-local"``)."""
        return self._term("curvature") is not None or self._term("local_departure") is not None

    @property
    def needs_sigma_data(self) -> bool:
        """The map reads the aleatoric part of the sigma apart (form ``"additive-local-data"``, MC mode)."""
        return self._term("sigma_data") is not None

    @property
    def needs_classical(self) -> bool:
        """The map reads three-step PS's phase (through the departure or the local departure)."""
        return self.needs_departure or self._term("local_departure") is not None

    @property
    def features(self) -> tuple[str, ...]:
        return tuple(t.feature for t in self.terms)

    def log_sigma(self, sigma: np.ndarray, departure: np.ndarray | None = None,
                  density: np.ndarray | None = None, *, curvature: np.ndarray | None = None,
                  local_departure: np.ndarray | None = None, sigma_data: np.ndarray | None = None) -> np.ndarray:
        values = {"sigma": sigma, "departure": departure, "density": density, "curvature": curvature,
                  "local_departure": local_departure, "sigma_data": sigma_data}
        s = np.asarray(sigma)
        out = np.full(s.shape, np.float32(self.intercept), np.float32)
        for t in self.terms:
            v = values[t.feature]
            if v is None or np.shape(v) != s.shape:
                raise ValueError(f"additive sigma map: reads the {t.feature}; expected a map of shape {s.shape}, "
                                 f"got {None if v is None else np.shape(v)}")
            out = out + t(log_map_feature(t.feature, v))
        return np.clip(out, np.float32(LOG_SIGMA_RANGE[0]), np.float32(LOG_SIGMA_RANGE[1]))

    def __call__(self, sigma: np.ndarray, departure: np.ndarray | None = None,
                 density: np.ndarray | None = None, *, curvature: np.ndarray | None = None,
                 local_departure: np.ndarray | None = None, sigma_data: np.ndarray | None = None) -> np.ndarray:
        return np.exp(self.log_sigma(sigma, departure, density, curvature=curvature,
                                     local_departure=local_departure, sigma_data=sigma_data)).astype(np.float32)

    def factor(self, sigma_total: np.ndarray, departure: np.ndarray | None = None,
               density: np.ndarray | None = None, *, curvature: np.ndarray | None = None,
               local_departure: np.ndarray | None = None, sigma_data: np.ndarray | None = None) -> np.ndarray:
        """``sigma'/sigma`` per pixel (float32)."""
        s = np.maximum(np.asarray(sigma_total, np.float32), np.float32(1e-12))
        return np.exp(self.log_sigma(s, departure, density, curvature=curvature, local_departure=local_departure,
                                     sigma_data=sigma_data) - np.log(s)).astype(np.float32)

    def departure_factor(self, departure: np.ndarray, local_departure: np.ndarray | None = None) -> np.ndarray:
        """``exp`` of the departure's terms (1 without one): the pixel's own and, where the map reads it, the local
        departure (which a still-burst gate, reading the map at zero departure, sets to zero too)."""
        d = np.asarray(departure, np.float32)
        out = np.zeros_like(d)
        t = self._term("departure")
        if t is not None:
            out = out + t(log_map_feature("departure", d))
        t = self._term("local_departure")
        if t is not None:
            if local_departure is None or np.shape(local_departure) != d.shape:
                raise ValueError(f"additive sigma map: reads the local departure; expected a map of shape {d.shape}, "
                                 f"got {None if local_departure is None else np.shape(local_departure)}")
            out = out + t(log_map_feature("local_departure", np.asarray(local_departure, np.float32)))
        return np.exp(out).astype(np.float32)

    def to_json(self) -> dict[str, Any]:
        return {"form": "additive", "intercept": self.intercept,
                "terms": [{"feature": t.feature, "slope": t.slope, "knots": list(t.knots), "hinges": list(t.hinges)}
                          for t in self.terms]}

    @classmethod
    def from_json(cls, data: Any, source: str = "sigma_calibration") -> AdditiveSigmaMap:
        try:
            if not isinstance(data, dict) or data.get("form") != "additive" or set(data) != {"form", "intercept", "terms"}:
                raise ValueError("keys")
            terms = tuple(HingeTerm(str(t["feature"]), float(t["slope"]), tuple(float(q) for q in t["knots"]),
                                    tuple(float(g) for g in t["hinges"])) for t in data["terms"])
            return cls(float(data["intercept"]), terms)
        except (TypeError, KeyError, ValueError) as exc:
            raise ValueError(f"{source}: expected {{'form': 'additive', 'intercept': float, 'terms': [{{'feature', "
                             f"'slope', 'knots', 'hinges'}}, ...]}}, got {data!r} ({exc})") from exc


SigmaMap = SigmaCalibration | AdditiveSigmaMap
MAP_FORMS = ("power", *FORM_FEATURES)


def sigma_map_from_json(data: Any, source: str = "sigma_calibration") -> SigmaMap:
    """A stored sigma map: the additive form where the entry says ``"form": "additive"``, else the power law (its
    entries name no form)."""
    if isinstance(data, dict) and "form" in data:
        if data["form"] != "additive":
            raise ValueError(f"{source}: form: expected 'additive' (a power law names no form), got {data['form']!r}")
        return AdditiveSigmaMap.from_json(data, source)
    return SigmaCalibration.from_json(data, source)


def map_form(cal: SigmaMap | None) -> str:
    """The map's form (:data:`MAP_FORMS`): ``"power"`` (no map: the power law too), or the additive form whose
    features it reads (:data:`FORM_FEATURES`; a map fitted on other features: ``"additive-local-data"`` if it reads
    the aleatoric sigma, else ``"additive"`` if it reads no local term), so a refit of that form reads them all."""
    if not isinstance(cal, AdditiveSigmaMap):
        return "power"
    if cal.needs_sigma_data:
        return "additive-local-data"
    return "additive-local" if cal.needs_local else "additive"


def map_inputs(cal: SigmaMap, phase: np.ndarray, classical_phase: np.ndarray | None) -> dict[str, np.ndarray | None]:
    """The per-pixel features ``cal`` reads besides the sigma, from the network's ``(H, W)`` phase and three-step
    PS's: ``departure``, ``density``, ``curvature``, ``local_departure`` (None where the map does not read it). Not
    the aleatoric sigma a data map reads (``sigma_data``): :func:`to_phase_result` adds it from the moments."""
    dep = None
    if cal.needs_classical:
        if classical_phase is None:
            raise ValueError("this sigma map reads the departure from three-step PS; pass classical_phase")
        dep = departure(phase, classical_phase)
    local = cal.needs_local
    return {"departure": dep if cal.needs_departure else None,
            "density": fringe_density(phase) if cal.needs_density else None,
            "curvature": phase_curvature(phase) if local and "curvature" in cal.features else None,
            "local_departure": local_departure(dep) if local and "local_departure" in cal.features else None}


def event_loss_grad(p: np.ndarray, X: np.ndarray, hit: np.ndarray, weights: np.ndarray,
                    eps: float = 0.03) -> tuple[float, np.ndarray]:
    """The weighted event log score of ``log sigma = clip(X @ p)`` (:data:`LOG_SIGMA_RANGE`) and its gradient in
    ``p``: ``log P(|e| < eps) = log erf z``, ``log P(|e| >= eps) = log erfcx z - z^2``, ``z = eps / (sigma sqrt 2)``,
    exact where P is near 0 or 1, so the gradient matches the loss everywhere (0 where the clip holds)."""
    lo, hi = LOG_SIGMA_RANGE
    u = X @ p
    z = (eps / math.sqrt(2.0)) * np.exp(-np.clip(u, lo, hi))
    e = np.maximum(erf(z), 1e-300)
    loss = -np.sum(weights * np.where(hit, np.log(e), np.log(erfcx(z)) - z * z))
    d_hit = -(2 / math.sqrt(math.pi)) * z * np.exp(-z * z) / e  # d log erf z / d log sigma
    d_miss = (2 / math.sqrt(math.pi)) * z / erfcx(z)  # d log erfc z / d log sigma
    dl = -np.where(hit, d_hit, d_miss) * ((u > lo) & (u < hi))
    return float(loss), X.T @ (weights * dl)


def fit_additive_map(
    error: np.ndarray,
    sigma: np.ndarray,
    departure: np.ndarray,
    density: np.ndarray,
    *,
    curvature: np.ndarray | None = None,
    local_departure: np.ndarray | None = None,
    sigma_data: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    features: tuple[str, ...] = FORM_FEATURES["additive"],
    knots: int = 3,
    eps: float = 0.03,
    max_pixels: int = 1_000_000,
    seed: int = 0,
) -> tuple[AdditiveSigmaMap, dict[str, float]]:
    """Fit :class:`AdditiveSigmaMap` (``features``, the sigma among them; ``knots`` hinges each at the quantiles of
    the fitted pixels) by the weighted event log score at ``eps`` (the ECE's event); returns it and the metrics as
    :func:`fit_sigma_calibration` does. ``weights`` per pixel (e.g. every val family x kind the same total);
    ``departure``, ``density``, ``curvature``, ``local_departure`` and ``sigma_data`` may be None where ``features``
    leaves them out."""
    from scipy.optimize import minimize

    e = np.asarray(error, np.float64).ravel()
    if "sigma" not in features or not set(features) <= set(MAP_FEATURES) or len(set(features)) != len(features):
        raise ValueError(f"features: expected distinct names of {MAP_FEATURES}, the sigma among them, got {features}")
    given = {"sigma": sigma, "departure": departure, "density": density, "curvature": curvature,
             "local_departure": local_departure, "sigma_data": sigma_data}
    cols = {n: v for n, v in given.items() if n in features}
    if any(v is None for v in cols.values()):
        raise ValueError(f"fit_additive_map: features {features} need a map for each")
    if e.size == 0 or any(np.size(v) != e.size for v in cols.values()):
        raise ValueError(f"fit_additive_map: expected equal non-empty error and feature maps, got sizes "
                         f"{e.size}, {[np.size(v) for v in cols.values()]}")
    for name, v in (("error", e), *cols.items()):
        bad = int(np.size(v) - np.count_nonzero(np.isfinite(np.asarray(v, np.float64))))
        if bad:
            raise ValueError(f"fit_additive_map: {name} has {bad} non-finite values; expected finite numbers")
    w = np.ones(e.size) if weights is None else np.asarray(weights, np.float64).ravel()
    if w.size != e.size or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError(f"fit_additive_map: expected {e.size} finite non-negative weights with a positive sum")
    pick = (np.sort(np.random.default_rng(seed).choice(e.size, max_pixels, replace=False))
            if e.size > max_pixels else slice(None))
    fe, fw = e[pick], w[pick] / w[pick].sum()
    xs = {n: log_map_feature(n, np.asarray(v).ravel()[pick]).astype(np.float64) for n, v in cols.items()}
    qs = {n: tuple(float(q) for q in np.quantile(x, np.linspace(0, 1, knots + 2)[1:-1])) if knots else ()
          for n, x in xs.items()}
    names = [n for n in MAP_FEATURES if n in cols]
    X = np.stack([np.ones(fe.size)] + [c for n in names for c in
                                       (xs[n], *(np.maximum(xs[n] - q, 0.0) for q in qs[n]))], 1)
    hit = np.abs(fe) < eps

    def loss_grad(p: np.ndarray) -> tuple[float, np.ndarray]:
        return event_loss_grad(p, X, hit, fw, eps)

    start = np.zeros(X.shape[1])
    start[1] = 1.0  # the identity: log sigma' = log sigma
    res = minimize(loss_grad, start, jac=True, method="L-BFGS-B", options={"maxiter": 1000})
    p = res.x if res.fun < loss_grad(start)[0] else start
    terms, j = [], 1
    for n in names:
        m = 1 + len(qs[n])
        terms.append(HingeTerm(n, float(p[j]), qs[n], tuple(float(v) for v in p[j + 1:j + m])))
        j += m
    cal = AdditiveSigmaMap(float(p[0]), tuple(terms))
    s_all = np.maximum(np.asarray(sigma, np.float64).ravel(), 1e-12)
    flat = {n: None if v is None else np.asarray(v).ravel() for n, v in given.items() if n != "sigma"}
    after = cal(s_all.astype(np.float32), **flat)
    return cal, {
        "score": "event", "form": map_form(cal), "weighted": weights is not None,
        "nll_before": gaussian_nll(e, s_all), "nll_after": gaussian_nll(e, after),
        "event_score_before": event_log_score(e, s_all, eps), "event_score_after": event_log_score(e, after, eps),
        "ece_before": reliability(e, s_all, eps=eps).ece, "ece_after": reliability(e, after, eps=eps).ece,
        "pixels": int(e.size),
    }


def gaussian_nll(error: np.ndarray, sigma: np.ndarray) -> float:
    """Mean Gaussian negative log-likelihood of ``error`` under ``N(0, sigma^2)`` (without log 2 pi / 2)."""
    e = np.asarray(error, np.float64)
    s = np.maximum(np.asarray(sigma, np.float64), 1e-12)
    return float(np.mean(np.log(s) + 0.5 * (e / s) ** 2))


def event_log_score(error: np.ndarray, sigma: np.ndarray, eps: float = 0.03) -> float:
    """Mean log loss of the event ``|error| < eps`` predicted as ``P = erf(eps / (sigma sqrt 2))``.

    The proper scoring rule of the event the ECE checks: unlike the ECE it is not minimised by a
    constant sigma where sigma tells the pixels apart, and unlike the Gaussian NLL it is not
    pulled by the heavy tails of the errors (measured: the NLL fit left the ECE at 0.15-0.29).
    """
    p = np.clip(confidence(sigma, eps), 1e-9, 1 - 1e-9)
    hit = np.abs(np.asarray(error, np.float64)) < eps
    return float(-np.mean(np.where(hit, np.log(p), np.log1p(-p))))


FIT_SCORES = ("event", "nll")


def fit_sigma_calibration(
    error: np.ndarray,
    sigma: np.ndarray,
    departure: np.ndarray | None = None,
    *,
    score: str = "event",
    eps: float = 0.03,
    bins: int = 30,
    max_pixels: int = 1_000_000,
    seed: int = 0,
) -> tuple[SigmaCalibration, dict[str, float]]:
    """Fit :class:`SigmaCalibration` to phase errors; returns it and the metrics.

    ``departure`` given: ``a, b, c`` of ``a * sigma**b * (departure + d0)**c``; else ``a, b``.
    ``score``: ``"event"`` (:func:`event_log_score` at ``eps``, the ECE's event) or ``"nll"``
    (Gaussian NLL). ``b`` is bounded to [0.05, 3] and ``c`` to [-3, 3]; the identity is kept when
    the fit does not lower the score. At most ``max_pixels`` (a seeded sample) enter the fit. The
    metrics hold NLL, event score and ECE (``eps``, ``bins``) before and after, and the pixel count.
    """
    from scipy.optimize import minimize

    if score not in FIT_SCORES:
        raise ValueError(f"score: expected one of {FIT_SCORES}, got {score!r}")
    e = np.asarray(error, np.float64).ravel()
    s = np.maximum(np.asarray(sigma, np.float64).ravel(), 1e-12)
    if e.size == 0 or e.shape != s.shape:
        raise ValueError(f"fit_sigma_calibration: expected equal non-empty error and sigma, got {e.shape}, {s.shape}")
    d = None if departure is None else np.asarray(departure, np.float64).ravel()
    if d is not None and d.shape != e.shape:
        raise ValueError(f"fit_sigma_calibration: departure has shape {d.shape}, expected {e.shape}")
    pick = (np.sort(np.random.default_rng(seed).choice(e.size, max_pixels, replace=False))
            if e.size > max_pixels else slice(None))
    fe, cols = e[pick], [np.log(s[pick])]
    if d is not None:
        cols.append(np.log(d[pick] + DEPARTURE_FLOOR))
    X = np.stack([np.ones_like(fe), *cols], 1)

    def loss(p: np.ndarray) -> float:
        log_sc = X @ p
        if score == "nll":
            return float(np.mean(log_sc + 0.5 * fe**2 * np.exp(-2.0 * log_sc)))
        return event_log_score(fe, np.exp(log_sc), eps)

    start = np.array([0.0, 1.0] + ([0.0] if d is not None else []))
    bounds = [(-20.0, 20.0), (0.05, 3.0)] + ([(-3.0, 3.0)] if d is not None else [])
    res = minimize(loss, x0=start, method="L-BFGS-B", bounds=bounds)
    cal = SigmaCalibration()
    if res.fun < loss(start):
        cal = SigmaCalibration(float(math.exp(res.x[0])), float(res.x[1]), float(res.x[2]) if d is not None else 0.0)
    dep = None if d is None else d.astype(np.float32)
    after = cal(s, dep)
    return cal, {
        "score": score,
        "nll_before": gaussian_nll(e, s),
        "nll_after": gaussian_nll(e, after),
        "event_score_before": event_log_score(e, s, eps),
        "event_score_after": event_log_score(e, after, eps),
        "ece_before": reliability(e, s, eps=eps, bins=bins).ece,
        "ece_after": reliability(e, after, eps=eps, bins=bins).ece,
        "pixels": int(e.size),
    }


def to_phase_result(
    stats: MomentStats,
    index: int = 0,
    *,
    mode: str = "deterministic",
    var_scale: float = 1.0,
    calibration: SigmaMap | None = None,
    classical_phase: np.ndarray | None = None,
) -> PhaseResult:
    """Turn batch element ``index`` of ``stats`` into a :class:`PhaseResult`.

    ``var_scale`` multiplies every variance (model and data) before propagation, so the phase
    sigmas scale by ``sqrt(var_scale)`` (the calibration fitted by :func:`fit_variance_scale`);
    ``calibration`` then maps the propagated sigmas (:class:`SigmaCalibration` or :class:`AdditiveSigmaMap`),
    reading the departure from ``classical_phase`` (three-step PS of the same frames, ``(H, W)``), the fringe
    density, curvature and local departure from the phase (:func:`map_inputs`) and the propagated data sigma
    when it needs them.
    """

    def np_(t: torch.Tensor) -> np.ndarray:
        return t[index].detach().cpu().numpy().astype(np.float32)

    M, D = np_(stats.M), np_(stats.D)
    dvM, dvD = np_(stats.data_var_M) * var_scale, np_(stats.data_var_D) * var_scale
    s_data = phase_sigma(M, D, dvM, dvD)
    if _is_zero(stats.model_var_M[index]) and _is_zero(stats.model_var_D[index]):
        # deterministic pass: no model variance, so skip its propagation (same numbers)
        s_model = np.zeros_like(s_data)
        s_total, var_M, var_D = s_data.copy(), dvM, dvD
    else:
        mvM, mvD = np_(stats.model_var_M) * var_scale, np_(stats.model_var_D) * var_scale
        s_model = phase_sigma(M, D, mvM, mvD)
        s_total = np.sqrt(s_model**2 + s_data**2).astype(np.float32)
        var_M, var_D = (mvM + dvM).astype(np.float32), (mvD + dvD).astype(np.float32)
    phase = np.arctan2(M, D).astype(np.float32)
    if calibration is not None and not calibration.identity:
        try:
            inputs = map_inputs(calibration, phase, classical_phase)
        except ValueError as exc:
            raise ValueError(f"to_phase_result: {exc}") from exc
        if calibration.needs_sigma_data:
            inputs["sigma_data"] = s_data
        f = calibration.factor(s_total, **inputs)
        s_model, s_data, s_total = s_model * f, s_data * f, s_total * f
        var_M, var_D = var_M * f**2, var_D * f**2
    return PhaseResult(
        phase=phase,
        M=M,
        D=D,
        sigma_model=s_model,
        sigma_data=s_data,
        sigma_total=s_total,
        mode=mode,
        var_M=var_M,
        var_D=var_D,
    )


# --- calibration ------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Reliability:
    """Reliability diagram: per-bin mean confidence, empirical accuracy, count; and the ECE."""

    confidence: np.ndarray  # (bins,), NaN for empty bins
    accuracy: np.ndarray  # (bins,)
    count: np.ndarray  # (bins,) int
    ece: float
    eps: float

    def to_json(self) -> dict:
        def clean(a: np.ndarray) -> list:
            return [None if not np.isfinite(v) else float(v) for v in a]

        return {
            "eps": self.eps,
            "ece": self.ece,
            "confidence": clean(self.confidence),
            "accuracy": clean(self.accuracy),
            "count": self.count.tolist(),
        }


def confidence(sigma: np.ndarray, eps: float = 0.03) -> np.ndarray:
    """``P(|e| < eps)`` for ``e ~ N(0, sigma^2)``."""
    s = np.maximum(np.asarray(sigma, dtype=np.float64), 1e-12)
    return erf(eps / (s * math.sqrt(2.0)))


def reliability(
    error: np.ndarray,
    sigma: np.ndarray,
    mask: np.ndarray | None = None,
    *,
    eps: float = 0.03,
    bins: int = 30,
) -> Reliability:
    """Reliability diagram and ECE of phase errors ``error`` (rad, wrapped) against ``sigma`` (rad)."""
    error = np.asarray(error)
    sigma = np.asarray(sigma)
    if error.shape != sigma.shape:
        raise ValueError(f"error and sigma: shapes differ, {error.shape} vs {sigma.shape}")
    if mask is not None:
        if mask.shape != error.shape:
            raise ValueError(f"mask: expected shape {error.shape}, got {mask.shape}")
        error, sigma = error[mask], sigma[mask]
    error, sigma = error.ravel(), sigma.ravel()
    if error.size == 0:
        raise ValueError("reliability: no valid pixels")
    conf = confidence(sigma, eps)
    hit = (np.abs(error) < eps).astype(np.float64)
    idx = np.minimum((conf * bins).astype(np.int64), bins - 1)
    count = np.bincount(idx, minlength=bins)
    csum = np.bincount(idx, weights=conf, minlength=bins)
    hsum = np.bincount(idx, weights=hit, minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mc = csum / count
        ma = hsum / count
    ece = float(np.sum(np.abs(hsum - csum)) / error.size)
    return Reliability(mc, ma, count, ece, eps)


def fit_variance_scale(
    error: np.ndarray,
    sigma: np.ndarray,
    mask: np.ndarray | None = None,
    *,
    eps: float = 0.03,
    bins: int = 30,
) -> tuple[float, float, float]:
    """Fit a variance scale ``k`` (sigma -> sqrt(k) sigma) on validation errors.

    Searches ``k`` on a log grid (1e-3 ... 1e3, plus the Gaussian maximum-likelihood value
    ``mean(e^2 / sigma^2)``) for the lowest ECE. Returns ``(k, ece_before, ece_after)``; ``k``
    is 1.0 when no candidate improves the ECE, so applying it never makes calibration worse on
    the fitting data.
    """
    error = np.asarray(error)
    sigma = np.asarray(sigma)
    if mask is not None:
        error, sigma = error[mask], sigma[mask]
    base = reliability(error, sigma, eps=eps, bins=bins).ece
    s = np.maximum(sigma.astype(np.float64), 1e-12)
    ml = float(np.mean((error.astype(np.float64) / s) ** 2))
    candidates = np.concatenate([np.logspace(-3, 3, 121), [ml]])
    best_k, best = 1.0, base
    for k in candidates:
        e = reliability(error, sigma * math.sqrt(k), eps=eps, bins=bins).ece
        if e < best - 1e-9:
            best_k, best = float(k), e
    return best_k, base, best


def plot_reliability(rel: Reliability, path: str | Path, title: str = "") -> Path:
    """Save the reliability diagram as a PNG (matplotlib, Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, ax = plt.subplots(figsize=(4.2, 4.2), dpi=120)
    ok = rel.count > 0
    ax.plot([0, 1], [0, 1], "k--", lw=1, label="ideal")
    ax.plot(rel.confidence[ok], rel.accuracy[ok], "o-", ms=3, label=f"model (ECE {rel.ece:.3f})")
    ax.set_xlabel(f"confidence P(|err| < {rel.eps:g} rad)")
    ax.set_ylabel("empirical accuracy")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.legend(loc="upper left")
    ax.set_title(title or "reliability diagram")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
