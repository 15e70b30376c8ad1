"""Classical motion-compensation peers for three-step bursts of a moving object.

A burst is three frames with nominal shifts ``0, 2pi/3, 4pi/3`` captured at increasing
turntable angles (DESIGN.md). Motion adds an unknown, spatially varying offset to the
effective shift of frames 1 and 2, which three-step decoding turns into a ripple at twice
the fringe frequency. Two classical remedies serve as baselines for CD-DCU-Net:

* :func:`aia_compensate` estimates the actual shifts per image region with Wang & Han's
  advanced iterative algorithm (AIA) and decodes with them;
* :func:`hilbert_compensate` averages the three-step phase with the phase of the
  Hilbert-transformed fringes, whose doubled-frequency error has the opposite sign.

On twin gear bursts (benchmarks/recon_compensation_report.md, 256x256, noisy) AIA cuts the
frame-0 phase RMSE from 0.49 to 0.26 rad (uniform 0.6/0.6 deg steps) and from 0.57 to 0.45 rad
(0.1/1.6 deg), but adds error on a static burst (0.017 -> 0.02-0.05 rad). Hilbert removes the
ripple yet leaves the phase at the middle pose (0.07 rad vs the middle-pose truth), so against
the frame-0 truth it barely helps (0.49 -> 0.47 rad).

Both return ``(phase, M, D)`` like :func:`gearscan.core.phase.decode_phase`: wrapped phase in
(-pi, pi] at the pose of the first frame and M, D normalised by ``N S / 4`` (so
``hypot(M, D) = 2B/S``).

References
----------
Z. Wang, B. Han, "Advanced iterative algorithm for phase extraction of randomly
phase-shifted interferograms", Opt. Lett. 29(14), 1671-1673 (2004).

Y. Wang, Z. Liu, C. Jiang, S. Zhang, "Motion induced phase error reduction using a Hilbert
transform", Opt. Express 26(26), 34224-34235 (2018).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.signal import hilbert

from gearscan.core.phase import THREE_STEP_SHIFTS, three_step

_N = 3


def _check_burst(frames: np.ndarray, full_scale: float, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    frames = np.asarray(frames)
    if frames.ndim != 3 or frames.shape[0] != _N:
        raise ValueError(f"frames: expected a three-step burst of shape (3, H, W), got {frames.shape}")
    if not float(full_scale) > 0:
        raise ValueError(f"full_scale: expected > 0, got {full_scale}")
    if mask is None:
        valid = np.ones(frames.shape[1:], dtype=bool)
    else:
        valid = np.asarray(mask, dtype=bool)
        if valid.shape != frames.shape[1:]:
            raise ValueError(f"mask: expected shape {frames.shape[1:]}, got {valid.shape}")
    return frames.astype(np.float64), valid


def _masked_blur(values: np.ndarray, weight: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian average of ``values`` over pixels with ``weight`` (normalised convolution)."""
    num = cv2.GaussianBlur(values * weight, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    den = cv2.GaussianBlur(weight, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    return num / np.maximum(den, 1e-12)


def solve_shifted(frames: np.ndarray, shifts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel exact solve of ``I_n = a + C cos(d_n) - S sin(d_n)`` for three frames.

    ``shifts`` is (3, H, W) (per-pixel shifts, e.g. interpolated from tiles). Differences
    against frame 0 remove ``a``; the remaining 2x2 system is solved by Cramer's rule.
    Returns ``a, C = b cos(phi), S = b sin(phi)``, each (H, W).
    """
    cos, sin = np.cos(shifts), np.sin(shifts)
    # I0 - In = C (cos d0 - cos dn) - S (sin d0 - sin dn), n = 1, 2
    p1, q1 = cos[0] - cos[1], -(sin[0] - sin[1])
    p2, q2 = cos[0] - cos[2], -(sin[0] - sin[2])
    r1, r2 = frames[0] - frames[1], frames[0] - frames[2]
    det = p1 * q2 - p2 * q1
    det = np.where(np.abs(det) < 1e-9, 1e-9, det)  # coincident shifts: ill-posed, keep finite
    c = (r1 * q2 - r2 * q1) / det
    s = (p1 * r2 - p2 * r1) / det
    a = frames[0] - c * cos[0] + s * sin[0]
    return a, c, s


def _tile_grid(shape: tuple[int, int], region: int) -> tuple[int, int, int, int]:
    h, w = shape
    ty, tx = math.ceil(h / region), math.ceil(w / region)
    return ty, tx, ty * region - h, tx * region - w


def _tile_sums(x: np.ndarray, region: int) -> np.ndarray:
    """Sum of ``x`` (..., H, W) over ``region`` x ``region`` tiles (zero-padded) -> (..., ty, tx)."""
    ty, tx, py, px = _tile_grid(x.shape[-2:], region)
    pad = [(0, 0)] * (x.ndim - 2) + [(0, py), (0, px)]
    x = np.pad(x, pad)
    return x.reshape(*x.shape[:-2], ty, region, tx, region).sum(axis=(-3, -1))


def _tiles_to_pixels(tile_values: np.ndarray, shape: tuple[int, int], region: int) -> np.ndarray:
    """Bilinear blend of per-tile values (..., ty, tx) placed at tile centres -> (..., H, W)."""
    ty, tx = tile_values.shape[-2:]
    h, w = shape
    yc = (np.arange(h) + 0.5) / region - 0.5  # pixel position in tile-centre units
    xc = (np.arange(w) + 0.5) / region - 0.5
    yc, xc = np.clip(yc, 0, ty - 1), np.clip(xc, 0, tx - 1)
    y0, x0 = np.minimum(np.floor(yc).astype(int), max(ty - 2, 0)), np.minimum(np.floor(xc).astype(int), max(tx - 2, 0))
    y1, x1 = np.minimum(y0 + 1, ty - 1), np.minimum(x0 + 1, tx - 1)
    fy, fx = (yc - y0)[:, None], (xc - x0)[None, :]
    v = tile_values
    top = v[..., y0[:, None], x0[None, :]] * (1 - fx) + v[..., y0[:, None], x1[None, :]] * fx
    bot = v[..., y1[:, None], x0[None, :]] * (1 - fx) + v[..., y1[:, None], x1[None, :]] * fx
    return top * (1 - fy) + bot * fy


def _frame_step(
    normalised: np.ndarray, phase: np.ndarray, weight: np.ndarray, region: int, min_pixels: int, min_spread: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per-tile least squares of ``J_n = alpha_n + cos(d_n) cos(phi) - sin(d_n) sin(phi)``.

    Returns shifts (3, ty, tx) relative to frame 0 and a (ty, tx) bool "tile is usable":
    enough weighted pixels and a phase spread wide enough that (cos phi, sin phi) are not
    collinear (smallest eigenvalue of their weighted covariance >= ``min_spread``).
    """
    basis = np.stack([np.ones_like(phase), np.cos(phase), np.sin(phase)])  # (3, H, W)
    gram = _tile_sums(basis[:, None] * basis[None, :] * weight, region)  # (3, 3, ty, tx)
    rhs = _tile_sums(normalised[:, None] * basis[None] * weight, region)  # (N, 3, ty, tx)
    gram = np.moveaxis(gram, (0, 1), (-2, -1))  # (ty, tx, 3, 3)
    rhs = np.moveaxis(rhs, (0, 1), (-1, -2))  # (ty, tx, 3, N)
    count = _tile_sums(weight > 0, region)
    wsum = np.maximum(gram[..., 0, 0], 1e-12)
    mean = gram[..., 0, 1:] / wsum[..., None]
    cov = gram[..., 1:, 1:] / wsum[..., None, None] - mean[..., :, None] * mean[..., None, :]
    usable = (count >= min_pixels) & (np.linalg.eigvalsh(cov)[..., 0] >= min_spread)
    gram = np.where(usable[..., None, None], gram, np.eye(3))  # unusable tiles: dummy, overwritten
    coef = np.linalg.solve(gram, rhs)  # (ty, tx, 3, N): rows alpha, cos d, -sin d
    delta = np.arctan2(-coef[..., 2, :], coef[..., 1, :])  # (ty, tx, N)
    delta = np.angle(np.exp(1j * (delta - delta[..., :1])))  # relative to frame 0
    return np.moveaxis(delta, -1, 0), usable


def aia_compensate(
    frames: np.ndarray,
    full_scale: float,
    *,
    region: int = 32,
    iterations: int = 20,
    tol: float = 1e-6,
    mask: np.ndarray | None = None,
    smooth_px: float | None = None,
    min_fraction: float = 0.25,
    min_spread: float = 0.1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three-step decoding with shifts estimated per region by Wang & Han's AIA.

    AIA alternates two least-squares steps until the shifts settle:

    (a) pixel step, shifts known: per pixel solve ``I_n = a + C cos(d_n) - S sin(d_n)`` for
        ``(a, C, S) = (a, b cos phi, b sin phi)``;
    (b) frame step, phase known: per region (``region`` x ``region`` tiles) solve
        ``J_n = alpha_n + cos(d_n) cos(phi) - sin(d_n) sin(phi)`` for
        ``(alpha_n, cos d_n, sin d_n)`` on the normalised fringes ``J_n = (I_n - a~) / b~``.

    Tile shifts are blended bilinearly between tile centres, so the shift field is smooth
    (gear motion varies across the image). Frame 0's shift is fixed at 0, so the phase is
    the phase at the first frame's pose. Tiles with fewer than ``min_fraction`` valid
    pixels, or whose phase does not spread over the circle (``min_spread``), keep the
    nominal shifts 0, 2pi/3, 4pi/3 (or their last estimate).

    Conditioning with three frames: the pixel step has three unknowns and three equations,
    so it fits the data exactly for *any* shifts, and the alternation would have every shift
    set as a fixed point. What identifies the shifts is a prior on ``a`` and ``b``: they vary
    slowly compared with the fringes (Wang & Han take them constant over the whole image).
    We impose it by normalising with ``a~, b~``, the per-pixel ``a`` and ``b = hypot(C, S)``
    Gaussian-smoothed over ``smooth_px`` (default ``region / 4``). Wrong shifts put ripples at
    the fringe frequency and twice it into the per-pixel ``a`` and ``b``; smoothing removes
    them, so ``J_n`` no longer matches the wrong shifts and the frame step moves toward the
    true ones. ``smooth_px`` must therefore exceed about half a fringe period (camera px).

    Parameters
    ----------
    frames : (3, H, W) raw burst, any real dtype, nominal shifts 0, 2pi/3, 4pi/3
    full_scale : S, the largest pixel value
    region : tile size in pixels for the per-region shifts
    iterations : maximum number of (a)+(b) rounds
    tol : stop when the largest shift change (rad) falls below this
    mask : (H, W) bool, pixels used to estimate shifts (all if None); the phase is returned
        everywhere
    smooth_px : Gaussian sigma (px) for the background/modulation prior
    min_fraction : fraction of a tile's pixels that must be valid to estimate its shifts
    min_spread : smallest eigenvalue of the covariance of (cos phi, sin phi) in a tile (a
        uniform phase distribution gives 0.5)

    Returns
    -------
    phase : (H, W) float64 wrapped to (-pi, pi]
    M, D : (H, W) float64, ``2 b sin(phi) / S`` and ``2 b cos(phi) / S``
    """
    frames, valid = _check_burst(frames, full_scale, mask)
    if region < 4:
        raise ValueError(f"region: expected >= 4 px, got {region}")
    if iterations < 1:
        raise ValueError(f"iterations: expected >= 1, got {iterations}")
    sigma = region / 4 if smooth_px is None else float(smooth_px)
    if sigma <= 0:
        raise ValueError(f"smooth_px: expected > 0, got {smooth_px}")
    shape = frames.shape[1:]
    ty, tx, _, _ = _tile_grid(shape, region)
    tile_shifts = np.broadcast_to(THREE_STEP_SHIFTS[:, None, None], (_N, ty, tx)).copy()
    weight = valid.astype(np.float64)
    min_pixels = int(min_fraction * region * region)
    for _ in range(iterations):
        a, c, s = solve_shifted(frames, _tiles_to_pixels(tile_shifts, shape, region))
        b = np.hypot(c, s)
        a_s, b_s = _masked_blur(a, weight, sigma), _masked_blur(b, weight, sigma)
        modulated = valid & (b_s > 1e-6 * float(full_scale))
        normalised = (frames - a_s) / np.where(modulated, b_s, 1.0)
        new, usable = _frame_step(
            normalised, np.arctan2(s, c), modulated.astype(np.float64), region, min_pixels, min_spread
        )
        # a tile whose phase spread collapses keeps its previous shifts (nominal at first), so
        # the tile set cannot flip between iterations
        new = np.where(usable, new, tile_shifts)
        # continuous shift field: unwrap each tile's shifts next to the previous estimate
        new = tile_shifts + np.angle(np.exp(1j * (new - tile_shifts)))
        change = float(np.abs(new - tile_shifts).max())
        tile_shifts = new
        if change < tol:
            break
    a, c, s = solve_shifted(frames, _tiles_to_pixels(tile_shifts, shape, region))
    scale = 2.0 / float(full_scale)
    return np.arctan2(s, c), s * scale, c * scale


def _fringe_direction(phase: np.ndarray, axis: int, sigma: float = 4.0) -> np.ndarray:
    """Sign (+1/-1) of the local phase slope along ``axis``, smoothed over ``sigma`` px."""
    diff = np.angle(np.exp(1j * np.diff(phase, axis=axis, append=np.take(phase, [-1], axis=axis))))
    diff = cv2.GaussianBlur(diff, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    return np.where(diff >= 0, 1.0, -1.0)


def hilbert_compensate(frames: np.ndarray, full_scale: float, *, axis: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three-step phase with motion ripple reduced by a Hilbert-transformed twin set.

    Wang et al. (2018): a small shift error turns three-step decoding into
    ``phi + e0 + e2 sin(2 phi + psi)``, a ripple at twice the fringe frequency. The Hilbert
    transform of a background-removed fringe ``b cos(phi + d_n)`` along the fringe direction is
    ``b sin(phi + d_n) = b cos(phi - pi/2 + d_n)`` (for a phase increasing along ``axis``), a
    second three-step set whose phase is shifted by ``pi/2``; its ripple
    ``sin(2 phi - pi + psi)`` has the opposite sign. Decoding both, undoing the ``pi/2``
    and averaging (circularly) cancels the ripple to first order; the constant part ``e0``
    (phase at the middle of the burst rather than at frame 0) remains.

    Assumptions: background ``a`` = mean of the three frames (exact for nominal shifts,
    first-order for small errors); fringes vary along ``axis`` (axis=1, image columns, for
    the default rig) with a locally single-signed frequency, whose sign is taken from the
    three-step phase slope; the Hilbert transform (``scipy.signal.hilbert``, FFT over the
    whole line) is exact for an infinitely long pure sinusoid, so it rings near the ends of
    lines and at edges of the fringe field (shadows, tooth tips). The whole lines are
    transformed as captured: zeroing pixels outside a validity mask was tried and is worse
    (static twin burst: 0.23 rad instead of 0.03 rad RMSE), because the cut edges ring.

    Parameters
    ----------
    frames : (3, H, W) raw burst, nominal shifts 0, 2pi/3, 4pi/3
    full_scale : S, the largest pixel value
    axis : image axis along which the fringe phase varies (1 = columns)

    Returns
    -------
    phase : (H, W) float64 wrapped to (-pi, pi]
    M, D : (H, W) float64, normalised like :func:`gearscan.core.phase.decode_md`
    """
    frames, _ = _check_burst(frames, full_scale, None)
    if axis not in (0, 1):
        raise ValueError(f"axis: expected 0 (rows) or 1 (columns), got {axis}")
    phase_ps, m_ps, d_ps = three_step(frames, full_scale)
    fringes = frames - frames.mean(axis=0)
    quadrature = np.imag(hilbert(fringes, axis=axis + 1))
    phase_ht, m_ht, d_ht = three_step(quadrature, full_scale)
    # H[cos(phi)] = sin(phi) for increasing phi (shift -pi/2), -sin(phi) for decreasing
    phase_ht = phase_ht + (math.pi / 2) * _fringe_direction(phase_ps.astype(np.float64), axis)
    phase = phase_ps + 0.5 * np.angle(np.exp(1j * (phase_ht - phase_ps)))
    phase = np.angle(np.exp(1j * phase))
    amp = 0.5 * (np.hypot(m_ps, d_ps) + np.hypot(m_ht, d_ht))
    return phase, amp * np.sin(phase), amp * np.cos(phase)
