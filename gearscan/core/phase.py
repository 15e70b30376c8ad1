"""Classical phase-shifting decoders and wrap-aware error metrics.

Decoding follows paper eq. 2: ``M = -sum I_n sin(delta_n)``, ``D = sum I_n cos(delta_n)``,
``phi = atan2(M, D)``. M and D are returned normalised by ``N S / 4`` so that
``hypot(M, D) = 2B/S`` (DESIGN.md), the same scale as the network's targets.
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np

from gearscan.core.types import Burst, PhaseResult

THREE_STEP_SHIFTS = np.array([0.0, 2 * math.pi / 3, 4 * math.pi / 3])


def _check_stack(images: np.ndarray, shifts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    images = np.asarray(images)
    shifts = np.asarray(shifts, dtype=np.float64).ravel()
    if images.ndim != 3:
        raise ValueError(f"images: expected (N, H, W), got shape {images.shape}")
    if images.shape[0] != shifts.size:
        raise ValueError(f"images has {images.shape[0]} frames but {shifts.size} shifts were given")
    if shifts.size < 3:
        raise ValueError(f"phase shifting needs >= 3 frames, got {shifts.size}")
    return images, shifts


def decode_md(images: np.ndarray, shifts: np.ndarray, full_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares numerator and denominator (eq. 2), normalised by ``N S / 4``.

    Parameters
    ----------
    images : (N, H, W) array, any real dtype
    shifts : (N,) phase shifts delta_n in rad
    full_scale : S, the largest pixel value (255 for 8-bit)
    """
    images, shifts = _check_stack(images, shifts)
    n = shifts.size
    norm = n * float(full_scale) / 4.0
    s = (-np.sin(shifts) / norm).astype(np.float32)
    c = (np.cos(shifts) / norm).astype(np.float32)
    flat = images.reshape(n, -1).astype(np.float32, copy=False)
    m = (s @ flat).reshape(images.shape[1:])
    d = (c @ flat).reshape(images.shape[1:])
    return m, d


def decode_phase(images: np.ndarray, shifts: np.ndarray, full_scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wrapped phase in (-pi, pi], normalised M and D of an N-step stack."""
    m, d = decode_md(images, shifts, full_scale)
    return np.arctan2(m, d), m, d


# Immerkaer's noise operator: blind to planes and linear ramps, noise gain sqrt(36) = 6
_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
NOISE_MIN_PIXELS = 256
NOISE_MODULATION = 0.05  # the pixels a still stack's noise is measured on: 2B/S at least this (the keep test's)


def still_frame_noise(images: np.ndarray, where: np.ndarray | None = None) -> float | None:
    """Per-frame noise standard deviation (the frames' units) of a still phase-shifting stack, measured on
    the stack itself: on a still scene the frames' sum is free of fringes (the shifts cover the circle),
    so what a Laplacian-like operator finds there is noise. Median-based over ``where`` (default: every
    pixel), so outlines and creases count little; None with fewer than :data:`NOISE_MIN_PIXELS` pixels.
    Not for a moving stack: its sum keeps part of the fringes and reads high.
    """
    images = np.asarray(images, np.float32)
    if images.ndim != 3 or images.shape[0] < 3:
        raise ValueError(f"images: expected (N >= 3, H, W), got shape {images.shape}")
    response = np.abs(cv2.filter2D(images.sum(0), cv2.CV_32F, _NOISE_KERNEL, borderType=cv2.BORDER_REFLECT))
    keep = np.ones(response.shape, bool) if where is None else np.array(where, bool)  # a copy: edited below
    keep[[0, -1], :] = keep[:, [0, -1]] = False  # the border's reflected rows are not independent noise
    if int(keep.sum()) < NOISE_MIN_PIXELS:
        return None
    # median |N(0, s)| = 0.6745 s; the sum of N frames has sqrt(N) times one frame's noise
    return float(np.median(response[keep]) / 0.6745 / 6.0 / np.sqrt(images.shape[0]))


def frame_swing(frames: np.ndarray) -> np.ndarray:
    """Three-step amplitude B' of ``(3, H, W)`` frames (order-free: from the three pairwise differences).

    On a still pixel it is three-step PS's own B; on a moving one it stays near B unless the three fringe
    phases nearly coincide, where the frames hold no fringe information at all."""
    f = np.asarray(frames, np.float32)  # raw integer frames would wrap in the differences
    return np.sqrt(2.0 * ((f[0] - f[1]) ** 2 + (f[1] - f[2]) ** 2 + (f[0] - f[2]) ** 2)) / 3.0


SUPPORT_BLOCK_PX = 1 << 15  # pixels per row block of :func:`fringe_support` (two float32 blocks: 256 KB)


def fringe_support(images: np.ndarray, full_scale: float, min_modulation: float, px: int) -> np.ndarray:
    """Pixels whose own frames, and every frame pixel within ``px`` (a (2 px + 1)^2 square), show fringes:
    ``2 B' / S >= min_modulation`` (:func:`frame_swing`). The image border does not erode. Evidence from the
    frames alone, for decoders (a network) whose modulation is their own estimate."""
    images = np.asarray(images)
    if images.ndim != 3 or images.shape[0] != 3:
        raise ValueError(f"images: expected (3, H, W), got shape {images.shape}")
    if px < 0:
        raise ValueError(f"px: expected >= 0, got {px}")
    if not full_scale > 0:
        raise ValueError(f"full_scale: expected > 0, got {full_scale}")
    if not min_modulation >= 0:
        raise ValueError(f"min_modulation: expected >= 0, got {min_modulation}")
    # 2 B'/S >= m with B' = sqrt(2 sum d^2) / 3 is sum d^2 >= 9/8 (m S)^2: no sqrt, no division, in row blocks that
    # stay in cache (a live-path step on every network burst: benchmarks/recon_report.md)
    h, w = images.shape[1:]
    threshold = np.float32(1.125 * (min_modulation * full_scale) ** 2)
    lit = np.empty((h, w), np.uint8)
    rows = max(1, SUPPORT_BLOCK_PX // max(w, 1))
    total, d = np.empty((rows, w), np.float32), np.empty((rows, w), np.float32)
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        t, e = total[: r1 - r0], d[: r1 - r0]
        block = images[:, r0:r1]
        np.subtract(block[0], block[1], out=t, dtype=np.float32)  # in float32: raw integer frames would wrap
        np.square(t, out=t)
        for a, b in ((1, 2), (0, 2)):
            np.subtract(block[a], block[b], out=e, dtype=np.float32)
            np.square(e, out=e)
            t += e
        np.greater_equal(t, threshold, out=lit[r0:r1].view(bool))
    if px:
        lit = cv2.erode(lit, np.ones((2 * px + 1, 2 * px + 1), np.uint8), borderType=cv2.BORDER_REPLICATE)
    return lit.view(bool)


# Three-step PS's error from non-sinusoidal fringes (residual projector/camera gamma): harmonics 2 and 4
# alias onto the fundamental, so the decoded phase is ``phi - r sin(3 phi)`` (in-phase harmonics of a
# pointwise non-linearity; r ~ B2/B1). Its gradient then ripples as ``1 - 3 r cos(3 phi)``, which the
# phase map itself shows wherever the true phase is smooth (Pan et al., Opt. Lett. 2009, estimate the
# same error from the phase map; here from its gradient).
HARMONIC_BLUR_PX = 4.0  # the local mean gradient: Gaussian sigma, px
HARMONIC_TILE_PX = 32  # r is fitted per tile and the median taken: tiles where the surface bends are outvoted
HARMONIC_TILE_MIN_PIXELS = 200
HARMONIC_MIN_TILES = 8
HARMONIC_ITERATIONS = 4  # re-estimates on the corrected phase (each removes most of what the blur hid)
HARMONIC_SETTLED = 0.001  # an iteration that moves r less than this ends them
HARMONIC_DEAD_ZONE = 0.006  # |r| shrunk by this: what the estimator finds on sinusoidal fringes (val, dev look)
HARMONIC_MAX_RATIO = 0.2  # |r| beyond this is no gamma residual: no correction


HARMONIC_WINDOW_PX = 128  # larger images: r is read in windows of this size spread over the image ...
HARMONIC_MAX_WINDOWS = 16  # ... at most this many (about 512 x 512 px read, whatever the sensor)


def _wrap_fast(x: np.ndarray) -> np.ndarray:
    return (x + np.pi) % (2 * np.pi) - np.pi


def _tile_ripples(phase: np.ndarray, where: np.ndarray) -> np.ndarray:
    """Per tile of :data:`HARMONIC_TILE_PX` with :data:`HARMONIC_TILE_MIN_PIXELS` usable pixels: the cos(3 phi)
    coefficient of the gradient ripple ``|grad phase| / local mean - 1`` (least squares with the sin term)."""
    gx = _wrap_fast(np.diff(phase, axis=1, append=phase[:, -1:]))
    gy = _wrap_fast(np.diff(phase, axis=0, append=phase[-1:, :]))
    ok = where & np.roll(where, -1, 1) & np.roll(where, -1, 0)
    ok[-1, :] = ok[:, -1] = False
    ok = cv2.erode(ok.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    grad = np.hypot(gx, gy)
    w = ok.astype(phase.dtype)
    mean = cv2.GaussianBlur(grad * w, (0, 0), HARMONIC_BLUR_PX) / np.maximum(
        cv2.GaussianBlur(w, (0, 0), HARMONIC_BLUR_PX), phase.dtype.type(1e-12))
    use = ok & (mean > 0.05) & (mean < 1.2)  # a fringe period of 5 to 125 px: the ripple resolved, the noise small
    rows, cols = np.nonzero(use)
    if rows.size == 0:
        return np.zeros(0)
    ripple = (grad[use] / mean[use] - 1.0).astype(np.float64)
    mid = phase[use] + 0.5 * mean[use]  # the phase between the two pixels a difference spans
    c3, s3 = np.cos(3 * mid).astype(np.float64), np.sin(3 * mid).astype(np.float64)
    tile = (rows // HARMONIC_TILE_PX) * (phase.shape[1] // HARMONIC_TILE_PX + 1) + cols // HARMONIC_TILE_PX
    # per-tile normal equations of ripple ~ a cos(3 phi) + b sin(3 phi), by bincount
    n_tiles = int(tile.max()) + 1
    sums = [np.bincount(tile, v, n_tiles) for v in (c3 * c3, c3 * s3, s3 * s3, c3 * ripple, s3 * ripple)]
    count = np.bincount(tile, minlength=n_tiles)
    cc, cs, ss, cy, sy = (v[count >= HARMONIC_TILE_MIN_PIXELS] for v in sums)
    det = cc * ss - cs * cs
    good = det > 1e-9 * np.maximum(cc * ss, 1e-300)
    return ((ss * cy - cs * sy)[good] / det[good]).astype(np.float64)


def _windows(shape: tuple[int, int]) -> list[tuple[slice, slice]]:
    """The whole image up to 512 x 512 px; beyond, up to :data:`HARMONIC_MAX_WINDOWS` windows of
    :data:`HARMONIC_WINDOW_PX` on a regular grid over it."""
    h, w = shape
    if h * w <= 512 * 512:
        return [(slice(None), slice(None))]
    side = HARMONIC_WINDOW_PX
    per_axis = max(1, int(math.sqrt(HARMONIC_MAX_WINDOWS)))
    ys = np.linspace(0, max(h - side, 0), per_axis).astype(int)
    xs = np.linspace(0, max(w - side, 0), per_axis).astype(int)
    return [(slice(y, y + side), slice(x, x + side)) for y in ys for x in xs]


def _ratio(crops: list[tuple[np.ndarray, np.ndarray]]) -> float | None:
    a = np.concatenate([_tile_ripples(p, m) for p, m in crops])
    if a.size < HARMONIC_MIN_TILES:
        return None
    return float(-np.median(a) / 3.0)


def _crops(phase: np.ndarray, where: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The windows :func:`_windows` reads ``r`` in, as float32 phase (speed) and bool mask; shapes checked."""
    phase = np.asarray(phase)
    where = np.asarray(where, bool)
    if phase.ndim != 2 or where.shape != phase.shape:
        raise ValueError(f"phase, where: expected two (H, W) arrays of one shape, got {phase.shape} and {where.shape}")
    return [(phase[win].astype(np.float32), where[win]) for win in _windows(phase.shape)]


def harmonic_ratio(phase: np.ndarray, where: np.ndarray) -> float | None:
    """One estimate of ``r`` in ``phase = psi - r sin(3 psi)`` (:func:`correct_harmonics`) from the
    ripple of the phase gradient over ``where`` (pixels with fringes; the true phase smooth there): the
    median over tiles of :data:`HARMONIC_TILE_PX` of a least-squares fit per tile (over windows spread on a
    large image, :func:`_windows`). None with fewer than :data:`HARMONIC_MIN_TILES` tiles of
    :data:`HARMONIC_TILE_MIN_PIXELS` usable pixels."""
    return _ratio(_crops(phase, where))


def correct_harmonics(phase: np.ndarray, r: float) -> np.ndarray:
    """The phase ``psi`` with ``phase = psi - r sin(3 psi)`` (fixed-point solve; |r| < 1/3 converges), wrapped;
    in ``phase``'s float precision."""
    phase = np.asarray(phase)
    if phase.dtype != np.float32:
        phase = phase.astype(np.float64)
    r = phase.dtype.type(r)
    psi = phase
    for _ in range(4):
        psi = phase + r * np.sin(3 * psi)
    return _wrap_fast(psi)


def harmonic_estimate(phase: np.ndarray, where: np.ndarray) -> float:
    """The ``r`` of three-step PS's non-sinusoidal-fringe error ``phase = psi - r sin(3 psi)`` (0: none found).

    :func:`harmonic_ratio` re-estimated up to :data:`HARMONIC_ITERATIONS` times on the corrected phase (of the
    windows it is read in), then shrunk by :data:`HARMONIC_DEAD_ZONE` toward 0. For a still stack only: a
    moving one's phase carries its motion error. ``where``: the pixels with fringes (e.g. 2B/S >= 0.05).
    """
    crops = _crops(phase, where)
    total, current = 0.0, crops
    for _ in range(HARMONIC_ITERATIONS):
        r = _ratio(current)
        if r is None:
            break
        total += r
        if abs(total) > HARMONIC_MAX_RATIO:
            return 0.0
        if abs(r) < HARMONIC_SETTLED:
            break
        current = [(correct_harmonics(p, total), m) for p, m in crops]
    return math.copysign(max(abs(total) - HARMONIC_DEAD_ZONE, 0.0), total)


def harmonic_correction(phase: np.ndarray, where: np.ndarray) -> tuple[np.ndarray, float]:
    """``phase`` (float64) freed of the error :func:`harmonic_estimate` finds, and the ``r`` removed (0: none)."""
    phase = np.asarray(phase, np.float64)
    r = harmonic_estimate(phase, where)
    return (correct_harmonics(phase, r) if r != 0.0 else phase), r


def three_step(images: np.ndarray, full_scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three-step phase shifting (shifts 0, 2pi/3, 4pi/3): phase, M, D."""
    return decode_phase(images, THREE_STEP_SHIFTS, full_scale)


def burst_shifts(burst: Burst) -> np.ndarray:
    """The phase shift of each of the burst's frames, in capture order (rad)."""
    return THREE_STEP_SHIFTS[list(burst.offsets)]


def in_capture_order(result: PhaseResult, burst: Burst) -> PhaseResult:
    """``result`` of decoding the burst's frames as if their shifts were 0, 2pi/3, 4pi/3, turned
    into the phase of its real shifts.

    Frames shown in the order 0, 4pi/3, 2pi/3 read ``A + B cos(phi - 2 pi k / 3)``: a forward
    burst of ``-phi`` (and of the opposite fringe motion), so any forward decoder measures
    ``-phi``: the phase and M change sign, D and every uncertainty stay.
    """
    if not burst.reversed_order:
        return result
    return replace(result, phase=(-result.phase).astype(np.float32), M=(-result.M).astype(np.float32))


def wrap(phase: np.ndarray) -> np.ndarray:
    """Wrap to (-pi, pi]."""
    return np.angle(np.exp(1j * np.asarray(phase)))


def phase_error(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Wrap-aware difference ``angle(exp(1j (a - b)))``."""
    diff = np.asarray(estimate, dtype=np.float64) - np.asarray(truth, dtype=np.float64)
    return (diff + np.pi) % (2 * np.pi) - np.pi


def wrapped_rmse(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Root-mean-square wrap-aware phase error over ``mask`` (all pixels if None)."""
    err = phase_error(estimate, truth)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != err.shape:
            raise ValueError(f"mask: expected shape {err.shape}, got {mask.shape}")
        err = err[mask]
    if err.size == 0:
        raise ValueError("wrapped_rmse: mask selects no pixels")
    return float(np.sqrt(np.mean(err**2)))


def classical_result(burst: Burst, read_noise_dn: float = 1.0) -> PhaseResult:
    """Three-step phase shifting of a burst (its frames' own shift order).

    Its data uncertainty is the noise-only phase sigma ``s_I sqrt(2/N) / B`` for a read noise
    of ``read_noise_dn``; three-step PS has no estimate of its (dominant) motion error.
    """
    result = three_step_result(burst.images, burst.full_scale, burst_shifts(burst), read_noise_dn)
    return replace(result, burst_index=burst.index, angle=float(burst.angles[0]))


def still_result(burst: Burst) -> PhaseResult:
    """:func:`classical_result` of a burst known to stand still (the encoder saw no turn), with the frames'
    noise measured on the burst itself (:func:`still_frame_noise`) instead of an assumed 1 DN."""
    result = still_three_step_result(burst.images, burst.full_scale, burst_shifts(burst))
    return replace(result, burst_index=burst.index, angle=float(burst.angles[0]))


def still_three_step_result(images: np.ndarray, full_scale: float,
                            shifts: np.ndarray = THREE_STEP_SHIFTS) -> PhaseResult:
    """:func:`three_step_result` of a still ``(3, H, W)`` stack: its phase freed of the non-sinusoidal-fringe
    error (:func:`still_phase`), its noise sigma from the noise measured on its frame sum over the modulated
    pixels (2B/S >= :data:`NOISE_MODULATION`; 1 DN where too few are)."""
    result = three_step_result(images, full_scale, shifts, 1.0)
    phase, m, d = still_phase(result.M, result.D)
    result = replace(result, phase=phase, M=m, D=d)
    noise = still_frame_noise(images, result.modulation >= NOISE_MODULATION)
    if noise is None:
        return result
    sigma = (result.sigma_data * np.float32(noise)).astype(np.float32)  # sigma is linear in the noise (1 DN above)
    return replace(result, sigma_data=sigma, sigma_total=sigma.copy())


def still_phase(m: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Phase, M and D of a still burst's three-step M, D with the non-sinusoidal-fringe error removed
    (:func:`harmonic_estimate` over 2B/S >= :data:`NOISE_MODULATION`; adopted on val by
    ``benchmarks/still_harmonic_rule.md``); the modulation is kept. float32."""
    m = np.asarray(m, np.float32)
    d = np.asarray(d, np.float32)
    mod = np.hypot(m, d)
    plain = np.arctan2(m, d)
    r = harmonic_estimate(plain, mod >= NOISE_MODULATION)
    if r == 0.0:
        return plain, m, d
    phase = correct_harmonics(plain, r)
    return phase, (mod * np.sin(phase)).astype(np.float32), (mod * np.cos(phase)).astype(np.float32)


def noise_sigma(modulation: np.ndarray, noise: float, full_scale: float) -> np.ndarray:
    """Three-step PS's noise-only phase sigma ``sqrt(2/3) s_n / B`` from the normalised modulation ``2B/S`` and
    a per-frame noise ``s_n`` in the frames' units (inf where there is no modulation)."""
    mod = np.asarray(modulation, np.float32)
    with np.errstate(divide="ignore"):
        sigma = np.where(mod > 0, np.float32(2.0 * noise / full_scale * np.sqrt(2 / 3)) / mod, np.inf)
    return sigma.astype(np.float32)


def three_step_result(images: np.ndarray, full_scale: float, shifts: np.ndarray = THREE_STEP_SHIFTS,
                      read_noise_dn: float = 1.0) -> PhaseResult:
    """:func:`classical_result` of a ``(3, H, W)`` stack with these ``shifts`` (rad)."""
    phase, m, d = decode_phase(images, shifts, full_scale)
    sigma = noise_sigma(np.hypot(m, d), read_noise_dn, full_scale)
    return PhaseResult(phase=phase, M=m, D=d, sigma_model=np.zeros_like(sigma), sigma_data=sigma,
                       sigma_total=sigma, mode="three-step")
