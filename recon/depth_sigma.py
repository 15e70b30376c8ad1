"""The per-burst depth sigma, calibrated by each point's distance to the edge of its burst's cloud.

A burst's depth sigma is the phase sigma propagated through the triangulation. The phase sigma is calibrated per
pixel (ECE 0.02-0.06), yet the depth error's tail is heavier than that sigma says, and most at the cloud's edge
(val, ``benchmarks/burst_sigma_look.md``: 29.7 % of the moving bursts' points within 1.5 px of the edge lie beyond
2 sigma, 9.2 % in the interior). So the depth sigma is scaled per band of that distance, by the val choice of
``benchmarks/depth_sigma_rule.md`` (``scripts/calibrate_depth_sigma.py`` -> ``benchmarks/depth_sigma_val.json``):
one scale per band, the largest that still or moving bursts need (body or tail); on the rule's check set at most
5.5 % of either lie beyond 2 sigma in any band (worst 5.3 %; a Gaussian 4.6 %). The edge is the burst's own kept
cloud's (its pixels without a point), as a user sees it. These are the product's scales, chosen for the shipped model; a model whose sigma differs carries its own in its JSON (``depth_sigma``, the
rule's amendment; ``inference.predictor.model_depth_sigma_scales``), which ``replay``, ``inspect`` and ``live`` pass on.
"""

from __future__ import annotations

import math

import numpy as np

# upper bounds (px, exclusive) of the edge-distance bands; the last band is everything beyond
EDGE_BANDS_PX: tuple[float, ...] = (1.5, 2.5, 4.5, 8.5)
# one scale per band (len(EDGE_BANDS_PX) + 1), nearest the edge first; the val choice of depth_sigma_rule.md
# (session 50, benchmarks/depth_sigma_val.json: fit seed set 2000, passed its check on seed set 2200)
DEPTH_SIGMA_SCALES: tuple[float, ...] = (4.95, 3.55, 2.6, 1.85, 1.4)
NO_SCALES: tuple[float, ...] = (1.0,) * (len(EDGE_BANDS_PX) + 1)  # the raw propagated sigma (calibration runs)


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


def check_scales(scales: tuple[float, ...]) -> tuple[float, ...]:
    """``scales`` as floats, one per band, each finite and at least 1 (a calibration may widen a sigma, never shrink
    it); else a ValueError naming what was expected."""
    out = tuple(float(s) for s in scales)
    if len(out) != len(EDGE_BANDS_PX) + 1 or not all(math.isfinite(s) and s >= 1 for s in out):
        raise ValueError(f"depth sigma scales: expected {len(EDGE_BANDS_PX) + 1} finite factors >= 1 (bands "
                         f"{', '.join(band_labels())}), got {scales}")
    return out


def scale_depth_sigma(sigma_depth: np.ndarray, keep: np.ndarray,
                      scales: tuple[float, ...] = DEPTH_SIGMA_SCALES) -> np.ndarray:
    """``sigma_depth`` (H, W) times its band's scale by distance to the edge of ``keep`` (the burst's points)."""
    factors = np.asarray(check_scales(scales), np.float32)
    if all(f == 1.0 for f in factors):
        return sigma_depth
    band = band_index(edge_distance(keep))
    return (sigma_depth * factors[band]).astype(sigma_depth.dtype, copy=False)
