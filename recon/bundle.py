"""Joint bundle adjustment of a camera-projector-turntable calibration over every board corner.

OpenCV's stages (each device's intrinsics on its own, the stereo pose with them fixed, the turntable axis fitted
to board poses solved one by one) leave each stage's error in the next: on the twin's default rig, with a 9 deg
camera field, a 20 mm cylinder measured with the staged rig read its radius up to 18 um off over five noise seeds.
Here one least-squares fit moves everything at once: both devices' intrinsics and chosen lens coefficients, the
projector's pose, the free views' board poses, and the turntable views as ONE board pose turned about one axis by
the encoder's angles (the constraint the turntable gives). The angles are trusted: a wrong counts-per-revolution
would bend the rig (on the twin, angles 1 % short moved a 20 mm cylinder's radius 86 um), so ``fit_scale`` fits their
scale as well, for the caller's check of the encoder; the rig comes from the fit that trusts them (on the twin,
whose encoder is exact, a free scale came out 1.0004-1.0008 over ten seeds of session 55's 16 repeated poses and read
the radius 1.7-7.0 um worse on seeds 1-3). Residuals are the corners' reprojections in both devices, per coordinate, each divided by that device's
noise per coordinate. Being a least-squares fit, it also states its own uncertainty: calibrations drawn from its
parameter covariance (``draws``), for the caller to carry into what a measurement inherits
(:func:`gearscan.recon.rig_check.calibration_uncertainty`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gearscan.core.rig import rot_z

# the lens coefficients each model of recon.calibration.LENS_MODELS leaves free, as positions in OpenCV's vector
FREE_COEFFS = {"none": (), "k1": (0,), "k1k2": (0, 1), "k1k2p1p2": (0, 1, 2, 3)}


@dataclass(frozen=True)
class JointFit:
    """The adjusted calibration: intrinsics, lens vectors, the projector's pose from the camera, the turntable frame
    (``t_cam_from_turntable``: z along the axis) and every view's board pose, with the residuals before and after."""

    k_camera: np.ndarray
    dist_camera: np.ndarray
    k_projector: np.ndarray
    dist_projector: np.ndarray
    t_proj_from_cam: np.ndarray
    t_cam_from_turntable: np.ndarray
    poses: list[np.ndarray]  # T_cam_from_board per view
    encoder_scale: float  # the board's turns over the encoder's: fitted with fit_scale, else 1
    rms_before: float  # normalised residual RMS per coordinate (1: residuals at the given noise)
    rms_after: float
    evaluations: int
    variance_factor: float = float("nan")  # residual sum of squares over its degrees of freedom (1: noise as given)
    # calibrations drawn from the fit's covariance (adjust_jointly's ``draws``; their rms and evaluation fields are the
    # solution's), or why none could be drawn
    draws: tuple[JointFit, ...] = ()
    draws_why: str = ""
    encoder_scale_sigma: float = float("nan")  # the fitted scale's standard error (fit_scale; NaN: not fitted or unknown)
    encoder_scale_sigma_why: str = ""  # why it is NaN with fit_scale


def pose_vectors(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's rotation vector and translation of a 4x4 pose."""
    import cv2

    return cv2.Rodrigues(t[:3, :3])[0].ravel(), t[:3, 3].copy()


def pose_matrix(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The 4x4 pose of OpenCV's rotation vector and translation."""
    import cv2

    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(np.asarray(r, np.float64))[0]
    out[:3, 3] = np.asarray(t, np.float64).ravel()
    return out


def _rot_yx(a: float, b: float) -> np.ndarray:
    """``Ry(b) Rx(a)``: a board pose on the turntable modulo a turn about the axis (which the frame absorbs). Singular
    where the board's x axis lies along the turntable axis (b = +-90 deg: a board mounted a quarter turn round); it
    still converges there, in many more evaluations."""
    ca, sa, cb, sb = math.cos(a), math.sin(a), math.cos(b), math.sin(b)
    rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    return ry @ rx


def adjust_jointly(
    obj: np.ndarray,
    img_camera: Sequence[np.ndarray],
    img_projector: Sequence[np.ndarray],
    angles: Sequence[float | None],
    models: tuple[str, str],
    k_camera: np.ndarray,
    dist_camera: np.ndarray,
    k_projector: np.ndarray,
    dist_projector: np.ndarray,
    t_proj_from_cam: np.ndarray,
    t_cam_from_world: np.ndarray,
    poses: Sequence[np.ndarray],
    sigma: tuple[float, float],
    *,
    fit_scale: bool = False,
    draws: int = 0,
    seed: int = 0,
) -> JointFit:
    """Refine the staged calibration jointly (module docstring). ``obj``: the board's corners ``(N, 3)``;
    ``img_*``: each view's observed corners ``(N, 2)``; ``angles``: each view's encoder angle (rad), None for a
    free view; ``models``: the camera's and the projector's lens model; the staged estimates as starting point
    (``t_cam_from_world``: its turntable frame, z along the axis; ``poses``: T_cam_from_board per view);
    ``sigma``: each device's noise per coordinate (px), the residuals' units; ``fit_scale``: also fit one scale of
    the encoder's angles (a check of the encoder; the module docstring says why a rig should not come from it);
    ``draws``: how many calibrations to draw (``seed``) from the parameter covariance ``s^2 (J^T J)^-1`` at the
    solution, ``s^2`` the :attr:`JointFit.variance_factor`."""
    import cv2
    from scipy.optimize import least_squares

    obj = np.asarray(obj, np.float64).reshape(-1, 3)
    obs = [(np.asarray(c, np.float64).reshape(-1, 2), np.asarray(p, np.float64).reshape(-1, 2))
           for c, p in zip(img_camera, img_projector, strict=True)]
    turn = [i for i, a in enumerate(angles) if a is not None]
    free = [i for i, a in enumerate(angles) if a is None]
    free_c, free_p = FREE_COEFFS[models[0]], FREE_COEFFS[models[1]]
    # the turntable's board pose at encoder angle 0, from the first turntable view; its turn about the axis and its
    # height along it are folded into the frame (gauge), leaving Ry Rx and an in-plane offset
    i0 = turn[0]
    board0 = rot_z(-angles[i0]) @ np.linalg.inv(t_cam_from_world) @ poses[i0]
    spin = math.atan2(board0[1, 0], board0[0, 0])
    r = rot_z(-spin)[:3, :3] @ board0[:3, :3]
    b0, a0 = math.asin(float(np.clip(-r[2, 0], -1, 1))), math.atan2(r[2, 1], r[2, 2])
    offset = rot_z(-spin)[:3, :3] @ board0[:3, 3]
    lift = np.eye(4)
    lift[2, 3] = offset[2]
    frame0 = t_cam_from_world @ rot_z(spin) @ lift

    def intrinsics(k: np.ndarray, d: np.ndarray, free_idx: tuple[int, ...]) -> list[float]:
        return [k[0, 0], k[1, 1], k[0, 2], k[1, 2], *(float(np.ravel(d)[j]) for j in free_idx)]

    x0 = np.array([*intrinsics(k_camera, dist_camera, free_c), *intrinsics(k_projector, dist_projector, free_p),
                   *np.concatenate(pose_vectors(t_proj_from_cam)), *np.concatenate(pose_vectors(frame0)), a0, b0, offset[0], offset[1],
                   *([1.0] if fit_scale else []),
                   *(v for i in free for v in np.concatenate(pose_vectors(poses[i])))])
    nc, npj = 4 + len(free_c), 4 + len(free_p)

    def device(x: np.ndarray, free_idx: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        k = np.array([[x[0], 0.0, x[2]], [0.0, x[1], x[3]], [0.0, 0.0, 1.0]])
        d = np.zeros(5)
        d[list(free_idx)] = x[4:]
        return k, d

    def unpack(x: np.ndarray):
        kc, dc = device(x[:nc], free_c)
        kp, dp = device(x[nc:nc + npj], free_p)
        o = nc + npj
        t_pc, frame = pose_matrix(x[o:o + 3], x[o + 3:o + 6]), pose_matrix(x[o + 6:o + 9], x[o + 9:o + 12])
        a, b, tx, ty = x[o + 12:o + 16]
        scale = x[o + 16] if fit_scale else 1.0
        on_table = np.eye(4)
        on_table[:3, :3] = _rot_yx(a, b)
        on_table[:2, 3] = tx, ty
        views = {i: frame @ rot_z(scale * angles[i]) @ on_table for i in turn}
        o += 17 if fit_scale else 16
        for i in free:
            views[i] = pose_matrix(x[o:o + 3], x[o + 3:o + 6])
            o += 6
        return kc, dc, kp, dp, t_pc, frame, [views[i] for i in range(len(obs))]

    def residuals(x: np.ndarray) -> np.ndarray:
        kc, dc, kp, dp, t_pc, _, views = unpack(x)
        out = []
        for (c, p), pose in zip(obs, views, strict=True):
            pc, _ = cv2.projectPoints(obj, *pose_vectors(pose), kc, dc)
            pp, _ = cv2.projectPoints(obj, *pose_vectors(t_pc @ pose), kp, dp)
            out += [((pc.reshape(-1, 2) - c) / sigma[0]).ravel(), ((pp.reshape(-1, 2) - p) / sigma[1]).ravel()]
        return np.concatenate(out)

    before = float(np.sqrt(np.mean(residuals(x0) ** 2)))
    sol = least_squares(residuals, x0, method="lm", x_scale="jac")
    m, n = sol.fun.size, sol.x.size
    factor = float(np.sum(sol.fun**2) / (m - n)) if m > n else float("nan")
    after = float(np.sqrt(np.mean(sol.fun**2)))

    def fit_of(x: np.ndarray, **extra) -> JointFit:
        kc, dc, kp, dp, t_pc, frame, views = unpack(x)
        scale = float(x[nc + npj + 16]) if fit_scale else 1.0
        return JointFit(kc, dc, kp, dp, t_pc, frame, views, scale, before, after, int(sol.nfev), factor, **extra)

    extra = {}
    if fit_scale:  # the check's own precision: few or narrow turntable views leave the scale loose
        try:
            extra["encoder_scale_sigma"] = parameter_sigma(sol.jac, factor, nc + npj + 16)
        except (ValueError, np.linalg.LinAlgError) as exc:
            extra["encoder_scale_sigma_why"] = str(exc)
    if draws <= 0:
        return fit_of(sol.x, **extra)
    try:  # the fit stands whether or not its uncertainty can be stated
        steps = covariance_steps(sol.jac, factor, draws, seed)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return fit_of(sol.x, draws_why=str(exc), **extra)
    return fit_of(sol.x, draws=tuple(fit_of(sol.x + step) for step in steps), **extra)


# a direction of the column-scaled Jacobian with a singular value below this share of the largest is taken as one the
# corners do not constrain: far above the finite-difference Jacobian's own noise (about 1e-8), far below the twin's
# weakest constrained direction (about 1e-4, measured on its 16-view set of session 55)
UNCONSTRAINED = 1e-6


def _scaled_svd(jac: np.ndarray, factor: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The SVD ``(sv, vt, norm)`` of the column-scaled Jacobian, refused (ValueError) with no degrees of freedom or a
    direction the residuals leave unconstrained (:data:`UNCONSTRAINED`)."""
    if not math.isfinite(factor):
        raise ValueError("no degrees of freedom left: as many parameters as residuals, no covariance")
    jac = np.asarray(jac, np.float64)
    norm = np.linalg.norm(jac, axis=0)
    norm[norm == 0] = 1.0
    _, sv, vt = np.linalg.svd(jac / norm, full_matrices=False)
    weak = int(np.sum(sv <= UNCONSTRAINED * sv[0]))
    if weak:
        raise ValueError(f"the corners leave {weak} direction(s) of the calibration unconstrained (singular value "
                         f"below {UNCONSTRAINED:g} of the largest): no covariance to draw from; add views")
    return sv, vt, norm


def parameter_sigma(jac: np.ndarray, factor: float, index: int) -> float:
    """One parameter's standard error, ``sqrt(factor (J^T J)^-1)`` at ``index`` (:func:`covariance_steps`' terms)."""
    sv, vt, norm = _scaled_svd(jac, factor)
    return float(math.sqrt(factor * np.sum((vt[:, index] / sv) ** 2)) / norm[index])


def covariance_steps(jac: np.ndarray, factor: float, n: int, seed: int) -> np.ndarray:
    """``n`` draws ``(n, p)`` from N(0, factor (J^T J)^-1), through the SVD of the column-scaled Jacobian (the
    parameters span focal lengths in px to lens coefficients near 0.1). Refused (ValueError) with no degrees of
    freedom or where the corners leave a direction unconstrained (:data:`UNCONSTRAINED`): its variance would be
    infinite, and leaving it out would understate the rest."""
    sv, vt, norm = _scaled_svd(jac, factor)
    z = np.random.default_rng(seed).standard_normal((n, sv.size))
    return math.sqrt(factor) * (z / sv) @ vt / norm
