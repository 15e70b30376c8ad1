"""The per-burst depth sigma, calibrated by each point's distance to the edge of its burst's cloud and by what decoded it.

A burst's depth sigma is the phase sigma propagated through the triangulation. The phase sigma is calibrated per
pixel (ECE 0.02-0.06), yet the depth error's tail is heavier than that sigma says, and most at the cloud's edge
(val, ``benchmarks/burst_sigma_look.md``: 29.7 % of the moving bursts' points within 1.5 px of the edge lie beyond
2 sigma, 9.2 % in the interior). So the depth sigma is scaled per band of that distance, by the val choice of
``benchmarks/depth_sigma_rule.md`` (``scripts/calibrate_depth_sigma.py`` -> ``benchmarks/depth_sigma_val.json``).
The edge is the burst's own kept cloud's (its pixels without a point), as a user sees it.

The scales differ by the burst's motion class (:func:`motion_class`, the rule's second to fifth amendments): three-step
PS (a still burst, by the encoder or the frames' gate) carries its own measured noise; the network on a burst spanning
more than it was trained on (:data:`TRAINED_SPAN_DEG`) needs more, the more the farther (session 50's test: 6.8-9.3 %
beyond 2 sigma at 2 deg/frame with one pooled set). Each class's scale per band is the largest that any val family
(the twin's radial rigs, its any-view rigs, the default rig) needs: pooled, the any-view rigs hid the others. These are the product's scales, chosen for the
shipped model (:data:`SCALES_CHOSEN_FOR`), with a table of their own for its Monte Carlo mode (the rule's ninth
amendment); a model whose sigma differs carries its own in its JSON (``depth_sigma``, the rule's amendment;
``inference.predictor.model_depth_sigma_scales``), which ``replay``, ``inspect`` and ``live`` pass on
(:func:`decoder_depth_sigma`), and a run says where its scales were not measured for its decode
(:func:`depth_sigma_source`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

# upper bounds (px, exclusive) of the edge-distance bands; the last band is everything beyond
EDGE_BANDS_PX: tuple[float, ...] = (1.5, 2.5, 4.5, 8.5)
# one scale per band (len(EDGE_BANDS_PX) + 1), nearest the edge first, per motion class; the val choice of
# depth_sigma_rule.md (its fifth amendment, session 51: per class and band the largest need of the val families, the
# twin's radial and any-view rigs and the default rig; benchmarks/depth_sigma_val.json, fit seed set 2000, 5 bursts per
# motion, passed its check on seed set 2800 in every family). Session 50's one set for every burst:
# FIRST_CHOICE_SCALES.
DEPTH_SIGMA_BY_CLASS: Mapping[str, tuple[float, ...]] = MappingProxyType({
    "three_step": (4.15, 3.25, 1.75, 1.65, 1.6),
    "network": (3.6, 2.5, 2.0, 1.7, 1.65),
    "network_fast": (7.25, 4.85, 3.35, 2.15, 2.15),
    "network_faster": (8.95, 6.4, 4.75, 3.35, 2.4),
})
# Monte Carlo mode's (the rule's ninth amendment, session 52: the same form on MC decodes, T = 20, of the same val
# scenes, benchmarks/depth_sigma_val_mc.json, check seed set 3400 passed in every family; the deterministic table
# missed there once, val_radial network_faster beyond 8.5 px 6.0 %). Three-step PS decodes alike in both modes.
DEPTH_SIGMA_BY_CLASS_MC: Mapping[str, tuple[float, ...]] = MappingProxyType({
    "three_step": (4.15, 3.25, 1.75, 1.65, 1.6),
    "network": (3.45, 2.4, 1.95, 1.65, 1.6),
    "network_fast": (6.9, 5.0, 3.4, 2.15, 2.2),
    "network_faster": (7.85, 5.9, 4.45, 3.25, 2.5),
})
FIRST_CHOICE_SCALES: tuple[float, ...] = (4.95, 3.55, 2.6, 1.85, 1.4)  # benchmarks/depth_sigma_val_pooled.json
NO_SCALES: tuple[float, ...] = (1.0,) * (len(EDGE_BANDS_PX) + 1)  # the raw propagated sigma (calibration runs)
# the network's training bursts span at most 1.7 deg from the first frame to the last (18 poses 0.1 deg apart,
# twin.dataset); a burst that spans more is beyond what it learnt, and its error grows with the span (val, the rule's
# second amendment): up to twice that span is one class, more another
TRAINED_SPAN_DEG = 1.75
# the widest span the rule's val motions hold (2+3 deg/frame): a network burst spanning more carries network_faster's
# scales, which no val run measured there (the reconstructor counts such bursts and warns)
CALIBRATED_SPAN_DEG = 5.0
MOTION_CLASSES: tuple[str, ...] = ("three_step", "network", "network_fast", "network_faster")
# the network decode the product's scales were chosen for: the shipped model's weights, sigma maps and gates
# (inference.model_io.model_fingerprint; benchmarks/depth_sigma_val.json). Another network decode that carries no
# scales of its own borrows them unmeasured (depth_sigma_source)
SCALES_CHOSEN_FOR = "751d358c3dfe"


def depth_sigma_source(*, network: bool, mc: int = 0, decode: str | None = None, own: bool = False,
                       own_chosen_for: str | None = None) -> str:
    """Whether a run's depth-sigma scales were measured for its decode, and whose they are: ``"model"`` (the
    decoding model's own, chosen on its rig's val scenes for this decode), ``"product"`` (the product's, chosen for
    this decode: the shipped network's ``decode`` fingerprint, :data:`SCALES_CHOSEN_FOR`, or three-step PS), or not
    measured: ``"borrowed"`` (the product's on another network decode: a fine-tuned model, refitted sigma maps, an
    older model), ``"stale"`` (the model's own, chosen for a decode its files no longer are, e.g. after a sigma-map
    refit) or ``"mc"`` (a model's own in Monte Carlo mode: they were chosen on its deterministic decode, whose sigma
    is another map's; the product's have a Monte Carlo table, :data:`DEPTH_SIGMA_BY_CLASS_MC`).
    ``own_chosen_for``: the fingerprint the model's own scales name (None: not recorded, trusted)."""
    if own:
        if network and mc > 0:
            return "mc"
        return "model" if own_chosen_for is None or own_chosen_for == decode else "stale"
    return "product" if not network or decode == SCALES_CHOSEN_FOR else "borrowed"


def run_depth_sigma_scales(own, *, network: bool, mc: int = 0) -> DepthSigmaScales | None:
    """The scales a run reconstructs with: the decoding model's ``own`` (its JSON; flat or per class), else in Monte
    Carlo mode the product's MC table, else None (the reconstructor's default, the product's deterministic table)."""
    if own is not None:
        return check_scales(own)
    return DEPTH_SIGMA_SCALES_MC if network and mc > 0 else None


def decoder_depth_sigma(decoder: object) -> tuple[DepthSigmaScales | None, str]:
    """An app decoder's run (``inference.decoder.Decoder``: its ``predictor``, ``mc``, ``model_fingerprint``,
    ``depth_sigma_scales`` and ``depth_sigma_chosen_for``; a plain callable counts as no network): the scales its
    reconstructor reads (:func:`run_depth_sigma_scales`) and whether they were measured for it
    (:func:`depth_sigma_source`)."""
    own = getattr(decoder, "depth_sigma_scales", None)
    network, mc = getattr(decoder, "predictor", None) is not None, getattr(decoder, "mc", 0)
    source = depth_sigma_source(network=network, mc=mc, decode=getattr(decoder, "model_fingerprint", None),
                                own=own is not None, own_chosen_for=getattr(decoder, "depth_sigma_chosen_for", None))
    return run_depth_sigma_scales(own, network=network, mc=mc), source


def decoder_rest_sigma(decoder: object) -> tuple[float | None, str]:
    """The scale the frame fit multiplies its unfitted points' sigma by for an app decoder's run (``rest_sigma_scale``
    and ``rest_sigma_chosen_for`` of ``inference.decoder.Decoder``; None: the product's, ``recon.track.REST_SIGMA_SCALE``)
    and its source: ``model`` (chosen for this decode, or naming none: as for depth-sigma scales), ``stale`` (the
    model's own, chosen for another decode of it: still applied, said so), ``mc`` (the model's own, chosen on its
    deterministic decode, in Monte Carlo mode) or ``product``."""
    own = getattr(decoder, "rest_sigma_scale", None)
    if own is None:
        return None, "product"
    chosen_for = getattr(decoder, "rest_sigma_chosen_for", None)
    if chosen_for is not None and chosen_for != getattr(decoder, "model_fingerprint", None):
        return own, "stale"
    return own, ("mc" if getattr(decoder, "mc", 0) else "model")


REST_STALE_NOTE = ("the model's own scale for the frame fit's unfitted points (rest_sigma) was chosen for another decode "
                   "of it (its weights, sigma maps or still gates changed since), so those points' sigma is not a "
                   "measured k = 2 bound: choose it anew on the model's own val stretches (benchmarks/rest_sigma_rule.md; "
                   "for the default-rig option `python scripts/calibrate_rest_sigma.py --write`)")


def turning_three_step_note(bursts: int) -> str:
    """What to say where three-step PS (``--classical``, a baseline) decoded ``bursts`` that turned: its phase sigma has
    no motion term and its class's depth scales were measured on still bursts (``decoder.turning_three_step``)."""
    return (f"three-step PS decoded {bursts} burst(s) that turned (--classical, a baseline): its sigma has no motion "
            "term and its depth scales were measured on still bursts, so their points' sigma is not a measured k = 2 "
            "bound")


_CHOOSE_OWN = ("choose its own on its rig's val scenes: `python scripts/calibrate_depth_sigma.py --model M.safetensors "
               "--sets VAL1,VAL2 --out M_depth_sigma.json --write` (benchmarks/depth_sigma_rule.md)")
# what a user is told where the scales were not measured for the run's decode (depth_sigma_source)
UNMEASURED_NOTES: Mapping[str, str] = MappingProxyType({
    "borrowed": "the per-burst depth sigma is scaled by the product's depth-sigma scales, chosen for the shipped "
                "model's decode; this model carries none of its own, so its points' sigma is not a measured k = 2 "
                "bound (the default-rig option, with them, put up to 7.5 % of its moving points beyond 2 sigma in one band "
                "of distance to the edge on its val gears, its predecessor 8.9-15.1 %): " + _CHOOSE_OWN,
    "stale": "the model's own depth-sigma scales were chosen for another decode of it (its weights, sigma maps or still gates "
             "changed since), so its points' sigma is not a measured k = 2 bound: " + _CHOOSE_OWN,
    "mc": "the model's own depth-sigma scales were chosen on its deterministic decode; in Monte Carlo mode the phase "
          "sigma is its MC map's, so the points' sigma is not a measured k = 2 bound (use the deterministic decode, "
          "--mc 0, for a measured one)",
})


def span_deg(angles: Sequence[float]) -> float:
    """How far (deg) the turntable turned from a burst's first frame to its last (encoder angles in rad)."""
    return abs(math.degrees(float(angles[-1]) - float(angles[0])))


def sigma_calibrated(angles: Sequence[float], from_network: bool) -> bool:
    """Whether a burst's depth-sigma scales were measured for bursts like it: three-step PS, or the network within
    :data:`CALIBRATED_SPAN_DEG`."""
    return not from_network or span_deg(angles) <= CALIBRATED_SPAN_DEG + 1e-9


def motion_class(angles: Sequence[float], from_network: bool) -> str:
    """The class of a burst whose depth sigma is scaled: ``three_step`` (not the network's decode: a still burst by
    the encoder or the frames' gate, a coarse burst, a classical run), ``network`` (its encoder angles, rad, span at
    most :data:`TRAINED_SPAN_DEG` from the first frame to the last), ``network_fast`` (up to twice that) or
    ``network_faster`` (more)."""
    if not from_network:
        return "three_step"
    span = span_deg(angles)
    if span <= TRAINED_SPAN_DEG:
        return "network"
    return "network_fast" if span <= 2 * TRAINED_SPAN_DEG else "network_faster"


@dataclass(frozen=True)
class DepthSigmaScales:
    """One scale per edge band (nearest the edge first) for each motion class (:data:`MOTION_CLASSES`)."""

    by_class: Mapping[str, tuple[float, ...]]

    @classmethod
    def uniform(cls, scales: Sequence[float]) -> DepthSigmaScales:
        """The same scales for every class (a model's own scales chosen before the classes, the raw sigma)."""
        return cls(MappingProxyType({c: tuple(scales) for c in MOTION_CLASSES}))

    def for_burst(self, angles: Sequence[float], from_network: bool) -> tuple[float, ...]:
        return self.by_class[motion_class(angles, from_network)]

    def as_dict(self) -> dict[str, list[float]]:
        """JSON-ready: class -> scales (what benches and replay summaries record)."""
        return {c: list(self.by_class[c]) for c in MOTION_CLASSES}

    @property
    def is_uniform(self) -> bool:
        return len({self.by_class[c] for c in MOTION_CLASSES}) == 1

    def describe(self) -> str:
        """As text, nearest the edge first: "4.95/3.55/2.6/1.85/1.4" or "three_step 2/1.5/...; network ..."."""
        def one(c: str) -> str:
            return "/".join(f"{x:g}" for x in self.by_class[c])
        if self.is_uniform:
            return one(MOTION_CLASSES[0])
        return "; ".join(f"{c} {one(c)}" for c in MOTION_CLASSES)


DEPTH_SIGMA_SCALES = DepthSigmaScales(DEPTH_SIGMA_BY_CLASS)
DEPTH_SIGMA_SCALES_MC = DepthSigmaScales(DEPTH_SIGMA_BY_CLASS_MC)


def band_labels() -> list[str]:
    """The bands as text, nearest the edge first ("0-1.5 px", ..., "8.5-inf px")."""
    lo = (0.0, *EDGE_BANDS_PX)
    hi = (*EDGE_BANDS_PX, math.inf)
    return [f"{a:g}-{b:g} px" for a, b in zip(lo, hi, strict=True)]


def edge_distance(keep: np.ndarray) -> np.ndarray:
    """Each pixel's Euclidean distance (px) to the nearest pixel outside ``keep`` (0 outside; OpenCV's exact
    transform). The image border counts as outside: a cloud cut by the frame has an edge there too."""
    import cv2

    keep = np.asarray(keep, bool)
    if keep.ndim != 2:
        raise ValueError(f"keep: expected a 2-D mask, got shape {keep.shape}")
    padded = np.pad(keep.astype(np.uint8), 1)
    return cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]


def band_index(distance: np.ndarray) -> np.ndarray:
    """Which band (0 nearest the edge) each distance falls in."""
    return np.searchsorted(np.asarray(EDGE_BANDS_PX), distance, side="right")


def _check_band_scales(scales, what: str) -> tuple[float, ...]:
    try:
        out = tuple(float(s) for s in scales)
    except (TypeError, ValueError):
        out = ()
    if len(out) != len(EDGE_BANDS_PX) + 1 or not all(math.isfinite(s) and s >= 1 for s in out):
        raise ValueError(f"depth sigma scales{what}: expected {len(EDGE_BANDS_PX) + 1} finite factors >= 1 (bands "
                         f"{', '.join(band_labels())}), got {scales}")
    return out


def check_scales(scales: DepthSigmaScales | Mapping[str, Sequence[float]] | Sequence[float]) -> DepthSigmaScales:
    """``scales`` as :class:`DepthSigmaScales`: one factor per band, each finite and at least 1 (a calibration may
    widen a sigma, never shrink it), either for every motion class at once (a flat sequence) or per class (a mapping
    naming each of :data:`MOTION_CLASSES`); else a ValueError naming what was expected."""
    if isinstance(scales, DepthSigmaScales):
        scales = scales.by_class
    if isinstance(scales, Mapping):
        if set(scales) != set(MOTION_CLASSES):
            raise ValueError(f"depth sigma scales: expected one entry per motion class {MOTION_CLASSES}, "
                             f"got {sorted(scales)}")
        return DepthSigmaScales(MappingProxyType({c: _check_band_scales(scales[c], f" ({c})") for c in MOTION_CLASSES}))
    if isinstance(scales, str):
        raise ValueError(f"depth sigma scales: expected factors, got {scales!r}")
    return DepthSigmaScales.uniform(_check_band_scales(scales, ""))


def scale_depth_sigma(sigma_depth: np.ndarray, keep: np.ndarray, scales: Sequence[float]) -> np.ndarray:
    """``sigma_depth`` (H, W) times its band's scale (one burst's: :meth:`DepthSigmaScales.for_burst`) by distance to
    the edge of ``keep`` (the burst's points)."""
    factors = np.asarray(_check_band_scales(scales, ""), np.float32)
    if all(f == 1.0 for f in factors):
        return sigma_depth
    band = band_index(edge_distance(keep))
    return (sigma_depth * factors[band]).astype(sigma_depth.dtype, copy=False)
