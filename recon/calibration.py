"""Camera-projector calibration: Zhang's method, projector as inverse camera, turntable axis.

Steps (:func:`calibrate_rig`):

1. Camera intrinsics and per-view board poses from checkerboard corners (OpenCV
   ``findChessboardCorners`` + ``cornerSubPix``, then ``calibrateCameraExtended``).
2. The projector pixel of every corner from the absolute phase of horizontal (``u_p``) and
   vertical (``v_p``) fringes, temporally unwrapped; a modulation-weighted local quadratic fit
   around the corner evaluates the phase at the sub-pixel corner. The projector is then
   calibrated as an inverse camera from the same board points.
   Each device's lens model (none, k1, k1 k2, k1 k2 p1 p2) is chosen by the views' evidence: the
   simplest whose reprojection RMS on views held out of its fit is within 1 % of the best
   (:func:`choose_lens_model`); a narrow board footprint otherwise fits wild coefficients that
   nothing in the views pins (the twin's undistorted projector came out k2 = 7.4).
3. Stereo extrinsics ``T_proj_from_cam`` (``stereoCalibrateExtended`` with both intrinsics
   fixed), per-view reprojection errors of both devices.
4. The turntable axis from the views of a board fixed on the turntable at known encoder
   angles: the relative board motions are rotations about one axis; its direction and a point
   on it are fitted in least squares. The world (turntable) frame has z along that axis,
   its origin on the axis level with the first turntable view's board centre, x towards the
   camera.
5. A joint bundle adjustment of all of it (:mod:`gearscan.recon.bundle`): every corner in both
   devices, the turntable views as one board pose turned by the encoder's angles; the same fit
   with the angles' scale free checks the encoder first (:data:`ENCODER_SCALE_TOLERANCE`). The
   world frame as in step 4.

References
----------
Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11) (2000).
Zhang, Huang, "Novel method for structured light system calibration", Opt. Eng. 45(8) (2006).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from gearscan.core.phase import decode_phase
from gearscan.core.rig import CalibrationStatement, PinholeDevice, Rig, RigError
from gearscan.recon.bundle import pose_matrix, pose_vectors
from gearscan.recon.unwrap import temporal_unwrap


class CalibrationError(RuntimeError):
    """Calibration cannot proceed (too few usable views, board not found...)."""


@dataclass(frozen=True, slots=True)
class Checkerboard:
    """A printed checkerboard: ``cols x rows`` inner corners, ``square_mm`` pitch.

    Board frame: inner corner ``(i, j)`` at ``(i s, j s, 0)``; the square between corners
    ``(0, 0)`` and ``(1, 1)`` is black, which fixes the 180 degree ambiguity (use one odd
    and one even count). The plate extends ``margin_squares`` white squares beyond the
    outer black/white squares.
    """

    cols: int = 9
    rows: int = 6
    square_mm: float = 1.6
    margin_squares: float = 1.0

    def __post_init__(self) -> None:
        if self.cols < 3 or self.rows < 3:
            raise ValueError(f"board needs >= 3x3 inner corners, got {self.cols}x{self.rows}")
        if (self.cols + self.rows) % 2 == 0:
            raise ValueError(
                f"use one odd and one even inner-corner count so the board orientation is unique, got {self.cols}x{self.rows}"
            )
        if not self.square_mm > 0:
            raise ValueError(f"square_mm must be positive, got {self.square_mm}")

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.cols, self.rows)

    @property
    def centre(self) -> np.ndarray:
        """Board-frame centre of the corner grid, mm."""
        return np.array([(self.cols - 1) / 2, (self.rows - 1) / 2, 0.0]) * self.square_mm

    def object_points(self) -> np.ndarray:
        """``(cols*rows, 3)`` float32 corner coordinates in OpenCV's row-major order."""
        i, j = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        pts = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=1) * self.square_mm
        return pts.astype(np.float32)

    def to_json(self) -> dict:
        return {"type": "checkerboard", "cols": self.cols, "rows": self.rows, "square_mm": self.square_mm, "margin_squares": self.margin_squares}

    @classmethod
    def from_json(cls, data: dict) -> Checkerboard:
        if data.get("type", "checkerboard") != "checkerboard":
            raise ValueError(f"board.type: only 'checkerboard' is supported, got {data.get('type')!r}")
        return cls(int(data["cols"]), int(data["rows"]), float(data["square_mm"]), float(data.get("margin_squares", 1.0)))


@dataclass(slots=True)
class BoardCapture:
    """Raw captures of one board pose (camera images in raw dtype).

    ``fringes_u[period]`` is the ``(steps, H, W)`` stack of fringes varying along projector
    columns (phase ``2 pi u_p / period``), ``fringes_v`` along projector rows; shifts are
    ``2 pi n / steps``. ``turntable_angle`` (rad) is set for views of a board fixed on the
    turntable (used to fit the axis), None for free-hand views.
    """

    name: str
    white: np.ndarray
    fringes_u: dict[float, np.ndarray]
    fringes_v: dict[float, np.ndarray]
    full_scale: int
    turntable_angle: float | None = None


@dataclass(slots=True)
class BoardView:
    """Decoded board pose: projector coordinate maps and modulation, ``(H, W)`` each."""

    name: str
    white: np.ndarray
    u_proj: np.ndarray  # projector column, NaN where not decoded
    v_proj: np.ndarray  # projector row, NaN where not decoded
    modulation: np.ndarray  # 2B/S of the finest fringes (min of both orientations)
    turntable_angle: float | None = None


def decode_capture(capture: BoardCapture, projector_size: tuple[int, int], *, min_modulation: float = 0.01) -> BoardView:
    """N-step decode and temporal unwrapping of both fringe orientations of one pose."""
    pw, ph = projector_size
    maps, mods = [], []
    for fringes, width, label in ((capture.fringes_u, pw, "fringes_u"), (capture.fringes_v, ph, "fringes_v")):
        if not fringes:
            raise CalibrationError(f"{capture.name}: {label} is empty (need horizontal and vertical fringes)")
        periods = sorted(fringes)
        wrapped, fine_mod = [], None
        for p in periods:
            stack = fringes[p]
            n = stack.shape[0]
            phase, m, d = decode_phase(stack, 2 * np.pi * np.arange(n) / n, capture.full_scale)
            wrapped.append(phase)
            if p == periods[0]:
                fine_mod = np.hypot(m, d)
        res = temporal_unwrap(wrapped, periods, width)
        maps.append(res.phase_abs * periods[0] / (2 * np.pi))
        mods.append(fine_mod)
    mod = np.minimum(mods[0], mods[1])
    ok = mod >= min_modulation
    return BoardView(
        name=capture.name,
        white=capture.white,
        u_proj=np.where(ok, maps[0], np.nan),
        v_proj=np.where(ok, maps[1], np.nan),
        modulation=mod,
        turntable_angle=capture.turntable_angle,
    )


def detect_corners(image: np.ndarray, board: Checkerboard, *, refine_sigma_px: float = 1.5) -> np.ndarray | None:
    """Sub-pixel inner corners ``(cols*rows, 2)`` in board order, or None if not found."""
    import cv2

    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"image: expected (H, W) grayscale, got shape {img.shape}")
    if img.dtype != np.uint8:
        img = cv2.normalize(img.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(img, board.pattern_size, flags=flags)
    if not found:
        return None
    # Refine on a Gaussian-smoothed float image: on a sharp image the gradient-based
    # refinement locks towards pixel centres (~0.06 px bias at quarter-pixel offsets);
    # a symmetric blur does not move the saddle point and cuts that bias to ~0.02 px.
    smooth = cv2.GaussianBlur(np.asarray(image, dtype=np.float32), (0, 0), refine_sigma_px)
    spacing = np.median(np.linalg.norm(np.diff(corners.reshape(-1, 2), axis=0), axis=1))
    win = int(max(3, min(8, spacing * 0.3)))
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    corners = cv2.cornerSubPix(smooth, corners, (win, win), (-1, -1), crit).reshape(-1, 2).astype(np.float64)
    # orientation: the square between corners 0, 1, cols, cols+1 must be the dark one
    c = board.cols
    first = corners[[0, 1, c, c + 1]].mean(axis=0)
    second = corners[[1, 2, c + 1, c + 2]].mean(axis=0)
    if _sample(img, first) > _sample(img, second):
        corners = corners[::-1].copy()
    return corners


def _sample(img: np.ndarray, xy: np.ndarray) -> float:
    x, y = int(round(xy[0])), int(round(xy[1]))
    return float(img[max(y - 1, 0) : y + 2, max(x - 1, 0) : x + 2].mean())


def sample_projector_coords(view: BoardView, corners: np.ndarray, radius: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Projector pixel ``(N, 2)`` of each camera corner, and a per-corner ok flag ``(N,)``.

    A quadratic in the pixel offset is fitted to ``u_p`` and ``v_p`` in a ``(2r+1)^2``
    window, weighted by modulation squared (the inverse phase variance), and evaluated at
    the sub-pixel corner. Near a checker corner the blurred dark/bright squares bias the
    phase in a pattern odd about the corner, which a centred window cancels to first order.
    """
    h, w = view.u_proj.shape
    corners = np.asarray(corners, dtype=np.float64)
    dy, dx = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    base = np.rint(corners).astype(int)
    xs = base[:, 0:1] + dx.ravel()[None, :]
    ys = base[:, 1:2] + dy.ravel()[None, :]
    inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
    xs_c, ys_c = np.clip(xs, 0, w - 1), np.clip(ys, 0, h - 1)
    u = view.u_proj[ys_c, xs_c]
    v = view.v_proj[ys_c, xs_c]
    wgt = np.where(inside & np.isfinite(u) & np.isfinite(v), view.modulation[ys_c, xs_c] ** 2, 0.0)
    ox = xs - corners[:, 0:1]
    oy = ys - corners[:, 1:2]
    basis = np.stack([np.ones_like(ox), ox, oy, ox * ox, ox * oy, oy * oy], axis=-1)  # (N, K, 6)
    bw = basis * wgt[..., None]
    ata = np.einsum("nki,nkj->nij", bw, basis)
    rhs = np.stack([np.einsum("nki,nk->ni", bw, np.nan_to_num(u)), np.einsum("nki,nk->ni", bw, np.nan_to_num(v))], axis=-1)
    good = (wgt > 0).sum(axis=1) >= 0.6 * wgt.shape[1]
    ata[~good] = np.eye(6)
    coef = np.linalg.solve(ata, rhs)  # (N, 6, 2)
    out = coef[:, 0, :]
    return out, good & np.all(np.isfinite(out), axis=1)


@dataclass
class CalibrationResult:
    """Calibrated rig plus the numbers a user checks it by."""

    rig: Rig
    report: dict
    residuals_camera: list[np.ndarray] = field(default_factory=list)  # per view (N, 2) px
    residuals_projector: list[np.ndarray] = field(default_factory=list)
    view_names: list[str] = field(default_factory=list)


# the board's measured rotation between turntable views against the encoder's: a wrong counts_per_rev or unit is
# tens of degrees (the twin's calibration agrees within a few hundredths)
MAX_ANGLE_ERROR_DEG = 1.0
# the joint adjustment trusts the encoder's angles; their scale, fitted as a check, must be within this share of 1. An
# error in the angles' scale reads a 20 mm radius about 9 um off per 0.1 % (the twin's seed 1, session 55: angles 0.2 /
# 0.4 / 1 % short moved it -17 / -35 / -86 um). The twin's exact encoder reads 0.9997-1.0003 with its 24 views placed
# by hand (seeds 51-70, benchmarks/calibration_views_wide-dense_report.json). Off beyond 0.5 % by more than twice the
# scale's standard error (ENCODER_SIGMA_FACTOR): refused, no rig; beyond 0.15 %: written, with a warning in the
# report (ENCODER_SCALE_WARN), which says so where the views leave the scale too loose to refuse; beyond 2 %
# (ENCODER_SCALE_CEILING, 4096 counts read as 4000 is 2.4 %) refused whatever the views
ENCODER_SCALE_TOLERANCE = 0.005
ENCODER_SCALE_WARN = 0.0015
ENCODER_SCALE_CEILING = 0.02
# the scale's standard error from the fit's covariance understates its seed-to-seed scatter: on the twin's hand-placed
# 24-view sets 4.0x (seeds 71-80) and 5.2x (seeds 81-90) (RMS about 1 over the median standard error, session 56): a
# view's corners share errors fixed by its pose, which the fit counts as independent. The check multiplies it by this
ENCODER_SIGMA_FACTOR = 5.0
# fewer usable views than this calibrate, with a warning: the fit's RMS says nothing about what so few views leave
# unconstrained (session 55's 16 views put the twin's axis 0.034-0.057 deg from the truth over ten render seeds, jointly
# adjusted, benchmarks/calibration_accuracy_report.md; three of them 0.33 deg (its first three turntable views) or
# 1.58 deg (another three), from the staged fit in session 53's audit)
FEW_VIEWS = 8


# lens models a device is fitted with, simplest first (OpenCV flags: what each leaves free); k3 is never fitted
LENS_MODELS = ("none", "k1", "k1k2", "k1k2p1p2")
# a richer lens model is taken only where it lowers the held-out reprojection RMS by more than this share. On the
# twin's undistorted projector every model held out within 0.4 % of the others while a free k2 came out 4.4-7.4 (an
# extrapolation hazard outside the board's footprint): none is chosen. The twin's camera lens (k1 -0.08, k2 0.12,
# p1 5e-4, p2 -3e-4: 0.13 px at the image corner, nearly all of it k1) gets k1 on every seed (1.8 % lower held out)
LENS_PARSIMONY = 0.01
# calibrations drawn from the joint adjustment's covariance to state the calibration's own uncertainty
# (recon.rig_check.calibration_uncertainty; 64 state a standard deviation within about 9 %), and their seed
UNCERTAINTY_DRAWS = 64
UNCERTAINTY_SEED = 0


def lens_flags(model: str) -> int:
    """OpenCV calibration flags that fit exactly the coefficients of a :data:`LENS_MODELS` entry."""
    import cv2

    fixed = {"none": cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_ZERO_TANGENT_DIST,
             "k1": cv2.CALIB_FIX_K2 | cv2.CALIB_ZERO_TANGENT_DIST,
             "k1k2": cv2.CALIB_ZERO_TANGENT_DIST, "k1k2p1p2": 0}
    if model not in fixed:
        raise ValueError(f"lens model: expected one of {', '.join(LENS_MODELS)}, got {model!r}")
    return fixed[model] | cv2.CALIB_FIX_K3


def choose_lens_model(objs: list, imgs: list, size: tuple[int, int], criteria) -> tuple[int, dict]:
    """The lens model the views support: each model's reprojection RMS on views it was not fitted to (up to 5 folds;
    a held-out view's pose re-solved with the fold's intrinsics), the simplest within :data:`LENS_PARSIMONY` of the
    best. Returns its flags and what chose it (with fewer than 4 views: the richest model, said)."""
    import cv2

    n = len(objs)
    if n < 4:
        return lens_flags("k1k2p1p2"), {"chosen": "k1k2p1p2", "why": f"not chosen: {n} views are too few to hold "
                                        "any out (4 needed); the richest model fitted"}
    folds = min(n, 5)
    heldout: dict[str, float] = {}
    for model in LENS_MODELS:
        sq, count = 0.0, 0
        try:
            for f in range(folds):
                fit = [i for i in range(n) if i % folds != f]
                _, k, d, *_ = cv2.calibrateCamera([objs[i] for i in fit], [imgs[i] for i in fit], size, None, None,
                                                  flags=lens_flags(model), criteria=criteria)
                for i in range(f, n, folds):
                    ok, rv, tv = cv2.solvePnP(objs[i], imgs[i], k, d)
                    if not ok:
                        raise cv2.error(f"no pose for held-out view {i}")
                    proj, _ = cv2.projectPoints(objs[i], rv, tv, k, d)
                    sq += float(np.sum((proj.reshape(-1, 2) - imgs[i].reshape(-1, 2)) ** 2))
                    count += len(objs[i])
        except cv2.error:  # this model cannot be fitted on the folds: not a candidate
            continue
        if count and math.isfinite(sq):  # a fit that put NaN into a held-out view is not a candidate either
            heldout[model] = math.sqrt(sq / count)
    if not heldout:
        return lens_flags("k1k2p1p2"), {"chosen": "k1k2p1p2", "why": "not chosen: no model fitted on the folds; the "
                                        "richest model fitted"}
    best = min(heldout.values())
    chosen = next(m for m in LENS_MODELS if m in heldout and heldout[m] <= best * (1 + LENS_PARSIMONY))
    return lens_flags(chosen), {"chosen": chosen, "heldout_rms_px": heldout, "folds": folds,
                                "why": f"the simplest model within {100 * LENS_PARSIMONY:g} % of the best held-out RMS"}


def fit_turntable_axis(t_cam_from_board: Sequence[np.ndarray], angles: Sequence[float]) -> tuple[np.ndarray, np.ndarray, dict]:
    """Rotation axis of a board turned on the turntable, in the camera frame.

    Parameters
    ----------
    t_cam_from_board : >= 3 poses ``T_cam_from_board`` (4x4) of the same board on the turntable
    angles : encoder angle (rad) of each pose

    Returns
    -------
    (direction (3,), point (3,), stats): unit axis oriented so that a positive encoder
    step is a right-handed rotation about it, a point on it, and fit residuals. Every
    relative motion ``T_i T_0^-1 = [R | t]`` must satisfy ``t = (I - R) p`` with ``R`` a
    rotation about the axis by ``angle_i - angle_0``.
    """
    import cv2

    if len(t_cam_from_board) != len(angles):
        raise ValueError(f"got {len(t_cam_from_board)} poses but {len(angles)} angles")
    if len(angles) < 3:
        raise CalibrationError(f"turntable axis needs >= 3 board poses on the turntable, got {len(angles)}")
    t0_inv = np.linalg.inv(t_cam_from_board[0])
    dirs, weights, rows, rhs, angle_err = [], [], [], [], []
    for t_i, a_i in zip(t_cam_from_board[1:], angles[1:], strict=True):
        rel = t_i @ t0_inv
        rvec = cv2.Rodrigues(rel[:3, :3])[0].ravel()
        theta = np.linalg.norm(rvec)
        step = (a_i - angles[0] + math.pi) % (2 * math.pi) - math.pi  # a dial's 350 deg after 0 is -10 deg
        if theta < 1e-6 or abs(step) < 1e-6:
            continue
        d = rvec / theta * np.sign(step)
        dirs.append(d)
        weights.append(theta)
        angle_err.append(theta - abs(step))
        rows.append(np.eye(3) - rel[:3, :3])
        rhs.append(rel[:3, 3])
    if len(dirs) < 2:
        raise CalibrationError("turntable views must be at >= 3 distinct encoder angles")
    dirs = np.asarray(dirs)
    # align signs to the first (sign(step) already used) and average weighted by angle
    direction = np.average(dirs, axis=0, weights=weights)
    direction /= np.linalg.norm(direction)
    a = np.concatenate(rows)
    b = np.concatenate(rhs)
    # the point is free along the axis: pin it with the constraint direction . p = direction . c0
    c0 = t_cam_from_board[0][:3, 3]
    a = np.vstack([a, direction[None, :]])
    b = np.concatenate([b, [direction @ c0]])
    point, *_ = np.linalg.lstsq(a, b, rcond=None)
    spread = np.degrees(np.arccos(np.clip(dirs @ direction, -1, 1)))
    stats = {
        "views": len(angles),
        "direction_spread_deg": float(spread.max()),
        "angle_error_deg_rms": float(np.degrees(np.sqrt(np.mean(np.square(angle_err))))),
        "point_residual_mm_rms": float(np.sqrt(np.mean((a[:-1] @ point - b[:-1]) ** 2))),
    }
    return direction, point, stats


def world_from_axis(direction: np.ndarray, point: np.ndarray, level_point: np.ndarray) -> np.ndarray:
    """``T_cam_from_world`` of the turntable frame: z = axis, origin on the axis level with
    ``level_point`` (camera frame), x from the axis towards the camera centre."""
    z = np.asarray(direction, float) / np.linalg.norm(direction)
    origin = point + z * (z @ (np.asarray(level_point, float) - point))
    v = -origin  # towards the camera centre (origin of the camera frame)
    x = v - z * (z @ v)
    if np.linalg.norm(x) < 1e-9:
        raise CalibrationError("the camera lies on the turntable axis: cannot orient the world x axis")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    t = np.eye(4)
    t[:3, :3] = np.stack([x, y, z], axis=1)
    t[:3, 3] = origin
    return t


def calibrate_rig(
    views: Sequence[BoardView],
    board: Checkerboard,
    camera_size: tuple[int, int],
    projector_size: tuple[int, int],
    *,
    camera_flags: int | None = None,
    projector_flags: int | None = None,
    name: str = "calibrated",
    joint: bool = True,
) -> CalibrationResult:
    """Full calibration from decoded board views (see module docstring).

    ``camera_size``/``projector_size`` are ``(width, height)``. Each device's lens model is chosen on held-out
    views (:func:`choose_lens_model`) unless its OpenCV ``*_flags`` are given; the staged fit is then adjusted jointly
    (:mod:`gearscan.recon.bundle`) unless ``joint`` is False (benchmarks). Views where the board is not
    found are skipped and listed in the report; at least 3 are needed, 3 of them on the
    turntable (``turntable_angle`` set) for the axis.
    """
    import cv2

    obj = board.object_points()
    used, img_c, img_p, skipped = [], [], [], []
    for view in views:
        if view.white.shape != (camera_size[1], camera_size[0]):
            raise ValueError(f"{view.name}: image shape {view.white.shape} does not match camera_size {camera_size} (W, H)")
        corners = detect_corners(view.white, board)
        if corners is None:
            skipped.append({"view": view.name, "reason": "board not found"})
            continue
        proj, ok = sample_projector_coords(view, corners)
        if not ok.all():
            skipped.append({"view": view.name, "reason": f"{int((~ok).sum())} corners without projector phase"})
            continue
        used.append(view)
        img_c.append(corners.astype(np.float32).reshape(-1, 1, 2))
        img_p.append(proj.astype(np.float32).reshape(-1, 1, 2))
    if len(used) < 3:
        raise CalibrationError(f"only {len(used)} usable board views (need >= 3); skipped: {skipped}")
    objs = [obj.reshape(-1, 1, 3)] * len(used)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    lens = {}
    if camera_flags is None:
        camera_flags, lens["camera"] = choose_lens_model(objs, img_c, camera_size, crit)
    else:
        lens["camera"] = {"chosen": "given", "flags": int(camera_flags)}
    if projector_flags is None:
        projector_flags, lens["projector"] = choose_lens_model(objs, img_p, projector_size, crit)
    else:
        lens["projector"] = {"chosen": "given", "flags": int(projector_flags)}
    cflags, pflags = camera_flags, projector_flags
    rms_c, k_c, d_c, rv_c, tv_c, *_, err_c = cv2.calibrateCameraExtended(objs, img_c, camera_size, None, None, flags=cflags, criteria=crit)
    rms_p, k_p, d_p, rv_p, tv_p, *_, err_p = cv2.calibrateCameraExtended(objs, img_p, projector_size, None, None, flags=pflags, criteria=crit)
    stereo = cv2.stereoCalibrateExtended(
        objs, img_c, img_p, k_c, d_c, k_p, d_p, camera_size, None, None, flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit
    )
    rms_s, r_pc, t_pc, rv_s, tv_s, err_s = stereo[0], stereo[5], stereo[6], stereo[9], stereo[10], stereo[11]
    t_proj_from_cam = np.eye(4)
    t_proj_from_cam[:3, :3] = r_pc
    t_proj_from_cam[:3, 3] = np.asarray(t_pc).ravel()

    # board poses refined by both devices: the projector's 24-degree baseline pins the board
    # tilt far better than the narrow-field camera alone (the axis fit hinges on it)
    poses = [pose_matrix(r, t) for r, t in zip(rv_s, tv_s, strict=True)]
    turn = [i for i, v in enumerate(used) if v.turntable_angle is not None]
    axis_stats: dict = {}
    if len(turn) >= 3:
        direction, point, axis_stats = fit_turntable_axis([poses[i] for i in turn], [used[i].turntable_angle for i in turn])
        if axis_stats["angle_error_deg_rms"] > MAX_ANGLE_ERROR_DEG:  # the encoder and the board disagree: no rig
            raise CalibrationError(
                f"the board's measured rotations disagree with its views' turntable_angle_deg by "
                f"{axis_stats['angle_error_deg_rms']:.2f} deg RMS (expected within {MAX_ANGLE_ERROR_DEG:g}): a wrong "
                "encoder counts_per_rev, angles stored in radians, or angles of other views? No rig written")
        level = (poses[turn[0]] @ np.append(board.centre, 1.0))[:3]
        t_cam_from_world = world_from_axis(direction, point, level)
    else:
        raise CalibrationError(
            f"only {len(turn)} usable views with a turntable angle (need >= 3 to fit the axis)"
        )
    staged = {"camera_rms_px": float(rms_c), "projector_rms_px": float(rms_p), "stereo_rms_px": float(rms_s),
              "turntable_axis": {"direction_cam": direction.tolist(), "point_cam_mm": point.tolist(), **axis_stats}}
    adjustment = _joint(obj, img_c, img_p, [v.turntable_angle for v in used], lens, (k_c, d_c, k_p, d_p),
                        t_proj_from_cam, t_cam_from_world, poses, (float(rms_c), float(rms_p))) if joint else \
        {"run": False, "why": "not asked (joint=False)", "fit": None}
    fit = None if adjustment is None else adjustment.pop("fit")
    uncertainty = {"stated": False, "why": "the staged fit: only the joint adjustment states its covariance"}
    if fit is not None:  # the product: everything refined at once (recon.bundle); the world frame as above
        rig = _rig_of(fit, board, turn[0], camera_size, projector_size, name)
        k_c, d_c, k_p, d_p, t_proj_from_cam = fit.k_camera, fit.dist_camera, fit.k_projector, fit.dist_projector, \
            fit.t_proj_from_cam
        direction, point = fit.t_cam_from_turntable[:3, 2], fit.t_cam_from_turntable[:3, 3]
        poses = fit.poses
        uncertainty = _uncertainty(rig, fit, board, turn[0], camera_size, projector_size)
        if uncertainty["stated"]:  # the rig carries it: a recording holds the rig, and inspect reads it there
            try:
                rig = replace(rig, calibration=CalibrationStatement(
                    uncertainty["radius_um"], uncertainty["shape_rms_um_p95"], uncertainty["draws"]))
            except RigError as exc:  # a non-finite spread: not a statement
                uncertainty = {"stated": False, "why": f"the drawn calibrations gave no finite spread ({exc})"}
    else:
        rig = _rig(k_c, d_c, k_p, d_p, t_proj_from_cam, t_cam_from_world, camera_size, projector_size, name)

    res_c, res_p = [], []  # of the rig written: each view's corners through its final pose
    for i in range(len(used)):
        pc, _ = cv2.projectPoints(obj, *pose_vectors(poses[i]), k_c, d_c)
        res_c.append(pc.reshape(-1, 2) - img_c[i].reshape(-1, 2))
        pp, _ = cv2.projectPoints(obj, *pose_vectors(t_proj_from_cam @ poses[i]), k_p, d_p)
        res_p.append(pp.reshape(-1, 2) - img_p[i].reshape(-1, 2))

    def rms(res: list[np.ndarray]) -> float:
        return float(np.sqrt(np.mean(np.sum(np.concatenate(res) ** 2, axis=1))))

    report = {
        "board": board.to_json(),
        "views_used": [v.name for v in used],
        "views_skipped": skipped,
        "camera_rms_px": rms(res_c),
        "projector_rms_px": rms(res_p),
        "camera_view_rms_px": [float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) for r in res_c],
        "projector_view_rms_px": [float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) for r in res_p],
        "staged": {**staged, "camera_view_rms_px": np.asarray(err_c).ravel().tolist(),
                   "projector_view_rms_px": np.asarray(err_p).ravel().tolist(),
                   "stereo_view_rms_px": np.asarray(err_s).reshape(len(used), -1).tolist()},
        "joint_adjustment": adjustment if adjustment is not None else {"run": False, "why": "custom lens flags: their free "
                                                                 "coefficients are not one of LENS_MODELS"},
        "baseline_mm": rig.baseline_mm,
        "uncertainty": uncertainty,
        "lens_model": lens,
        "turntable_axis": {  # of the rig written; the fit statistics are the staged fit's (its check of the encoder)
            "direction_cam": direction.tolist(),
            "point_cam_mm": point.tolist(),
            "views": [used[i].name for i in turn],
            **axis_stats,
        },
    }
    return CalibrationResult(rig=rig, report=report, residuals_camera=res_c, residuals_projector=res_p, view_names=[v.name for v in used])


def _rig_of(fit, board: Checkerboard, first_turn: int, camera_size: tuple[int, int], projector_size: tuple[int, int],
            name: str) -> Rig:
    """The rig of a joint fit (:class:`gearscan.recon.bundle.JointFit`): world z along its turntable axis, the origin
    at the height of the first turntable view's board centre, x towards the camera (:func:`world_from_axis`)."""
    level = (fit.poses[first_turn] @ np.append(board.centre, 1.0))[:3]
    t_cam_from_world = world_from_axis(fit.t_cam_from_turntable[:3, 2], fit.t_cam_from_turntable[:3, 3], level)
    return _rig(fit.k_camera, fit.dist_camera, fit.k_projector, fit.dist_projector, fit.t_proj_from_cam,
                t_cam_from_world, camera_size, projector_size, name)


def _rig(k_c, d_c, k_p, d_p, t_proj_from_cam: np.ndarray, t_cam_from_world: np.ndarray, camera_size: tuple[int, int],
         projector_size: tuple[int, int], name: str) -> Rig:
    """The rig of intrinsics, lens vectors (OpenCV's first five), the projector's pose from the camera and the
    camera's pose in the turntable frame: the one place a calibration becomes a Rig."""
    cam_dev = PinholeDevice(camera_size[0], camera_size[1], k_c, np.asarray(d_c).ravel()[:5], t_cam_from_world)
    proj_dev = PinholeDevice(projector_size[0], projector_size[1], k_p, np.asarray(d_p).ravel()[:5],
                             t_proj_from_cam @ t_cam_from_world)
    return Rig(camera=cam_dev, projector=proj_dev, name=name)


def _uncertainty(rig: Rig, fit, board: Checkerboard, first_turn: int, camera_size: tuple[int, int],
                 projector_size: tuple[int, int]) -> dict:
    """The report's ``uncertainty``: the calibration's own contribution to a measurement, from the rigs of the
    joint fit's draws (:func:`gearscan.recon.rig_check.calibration_uncertainty`), or why it is not stated."""
    from gearscan.recon.rig_check import calibration_uncertainty

    if len(fit.draws) < 2:
        return {"stated": False, "why": fit.draws_why or "the adjustment drew no calibrations from its covariance"}
    draws = [_rig_of(d, board, first_turn, camera_size, projector_size, rig.name) for d in fit.draws]
    try:
        return {"stated": True, **calibration_uncertainty(rig, draws, fit.variance_factor)}
    except (ValueError, np.linalg.LinAlgError) as exc:  # draws too wide to read the cylinder as the rig does
        return {"stated": False, "why": f"the drawn calibrations could not be evaluated ({exc})"}


def _joint(obj, img_c, img_p, angles, lens: dict, staged: tuple, t_proj_from_cam, t_cam_from_world, poses,
           sigma: tuple[float, float]) -> dict | None:
    """The joint adjustment of the staged fit (:func:`gearscan.recon.bundle.adjust_jointly`) as a report entry with
    its ``fit``; None where a device's lens flags were given and match no :data:`LENS_MODELS` entry."""
    from gearscan.recon.bundle import adjust_jointly

    models = []
    for device in ("camera", "projector"):
        entry = lens[device]
        if entry["chosen"] != "given":
            models.append(entry["chosen"])
            continue
        match = [m for m in LENS_MODELS if lens_flags(m) == entry["flags"]]
        if not match:
            return None
        models.append(match[0])
    k_c, d_c, k_p, d_p = staged
    args = (obj, img_c, img_p, angles, (models[0], models[1]), k_c, d_c, k_p, d_p, t_proj_from_cam, t_cam_from_world,
            poses, (sigma[0] / math.sqrt(2), sigma[1] / math.sqrt(2)))  # OpenCV's RMS is per corner: per coordinate
    try:  # first the encoder's scale, which the rig's fit then trusts
        check = adjust_jointly(*args, fit_scale=True)
    except (ValueError, np.linalg.LinAlgError) as exc:  # a staged RMS of 0, a non-finite start: the stages stand
        return {"run": False, "models": models, "why": f"the encoder check failed ({exc}): the staged fit is kept",
                "fit": None}
    if not (math.isfinite(check.encoder_scale) and check.rms_after <= check.rms_before):
        return {"run": False, "models": models, "fit": None,
                "why": "the encoder check did not converge: the staged fit is kept, the encoder unchecked"}
    off = abs(check.encoder_scale - 1)
    sd = ENCODER_SIGMA_FACTOR * check.encoder_scale_sigma  # NaN where the fit could not state it
    told = "" if not math.isfinite(sd) else f" +- {sd:.4f}"
    # refused where the views show it beyond doubt (off beyond the tolerance by twice the standard error; an unknown
    # one: by the tolerance alone) and beyond the ceiling whatever they show; few or narrow turntable views leave the
    # scale loose, and a correct encoder must not be refused for it
    if off > ENCODER_SCALE_CEILING or not off - (2 * sd if math.isfinite(sd) else 0.0) <= ENCODER_SCALE_TOLERANCE:
        raise CalibrationError(
            f"the board's turns are {check.encoder_scale:.4f}{told} times the encoder's angles (expected within "
            f"{100 * ENCODER_SCALE_TOLERANCE:g} % of 1): the encoder's counts_per_rev or a gear ratio is off. No rig "
            "written")
    scale = {"encoder_scale": check.encoder_scale, "encoder_scale_sigma": sd if math.isfinite(sd) else None}
    if not math.isfinite(sd):
        scale["encoder_scale_sigma_why"] = check.encoder_scale_sigma_why or "not stated"
    if off > ENCODER_SCALE_WARN:
        loose = off > ENCODER_SCALE_TOLERANCE  # and yet not refused: within two standard errors of it
        scale["encoder_warning"] = (
            f"the board's turns are {check.encoder_scale:.4f}{told} times the encoder's angles: beyond "
            f"{100 * ENCODER_SCALE_WARN:g} % a size reading is off by about 9 um per 0.1 % at a 20 mm radius; check the "
            "encoder's counts_per_rev and any gear ratio"
            + (f"; the views leave the scale too loose to refuse the rig (two standard errors, {200 * sd:.1f} %, "
               f"would move a 20 mm radius by about {2 * sd * 9e4:.0f} um, which the stated uncertainty does not "
               "include; more turntable views over a wider turn would tell)" if loose else ""))
    try:
        fit = adjust_jointly(*args, draws=UNCERTAINTY_DRAWS, seed=UNCERTAINTY_SEED)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return {"run": False, "models": models, **scale, "fit": None,
                "why": f"the adjustment failed ({exc}): the staged fit is kept"}
    entry = {"run": True, "models": models, "rms_before": fit.rms_before, "rms_after": fit.rms_after, **scale,
             "evaluations": fit.evaluations, "fit": fit}
    if not fit.rms_after <= fit.rms_before:  # never worse than the stages it started from (NaN included)
        entry |= {"fit": None, "why": "the adjustment did not lower the residuals: the staged fit is kept"}
    return entry


def save_calibration(result: CalibrationResult, path) -> None:
    """Write the rig JSON (readable by ``Rig.load``) with an extra ``calibration_report`` key."""
    import json
    from pathlib import Path

    path = Path(path)
    data = result.rig.to_json()
    data["calibration_report"] = result.report
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2))
    tmp.replace(path)


def plot_residuals(result: CalibrationResult, path) -> None:
    """PNG: residual vectors of camera and projector corners, and per-view RMS bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    for ax, res, label in ((axes[0], result.residuals_camera, "camera"), (axes[1], result.residuals_projector, "projector")):
        allr = np.concatenate(res)
        ax.scatter(allr[:, 0], allr[:, 1], s=3, alpha=0.5)
        lim = max(1e-3, 1.1 * float(np.abs(allr).max()))
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.axhline(0, color="k", lw=0.5)
        ax.axvline(0, color="k", lw=0.5)
        rms = math.sqrt(float(np.mean(np.sum(allr**2, axis=1))))
        ax.set_title(f"{label} reprojection residuals (RMS {rms:.3f} px)")
        ax.set_xlabel("du [px]")
        ax.set_ylabel("dv [px]")
    x = np.arange(len(result.view_names))
    axes[2].bar(x - 0.2, result.report["camera_view_rms_px"], 0.4, label="camera")
    axes[2].bar(x + 0.2, result.report["projector_view_rms_px"], 0.4, label="projector")
    axes[2].set_xticks(x, result.view_names, rotation=90, fontsize=7)
    axes[2].set_ylabel("RMS [px]")
    axes[2].set_title("per-view reprojection error")
    axes[2].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
