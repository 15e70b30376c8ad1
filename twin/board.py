"""Twin rendering of a planar calibration board under white light and fringes.

The board is a plane (analytic ray intersection, no mesh); each camera pixel is supersampled
``s x s`` times, n-rooks (every sample its own row and column), so checker edges are anti-aliased in
``s * s`` steps whatever their direction (sub-pixel corners need it). The projector
is an inverse camera: a board point's projector pixel ``(u_p, v_p)`` gives the phase of
fringes varying along projector columns (``2 pi u_p / period``, the gearscan convention) or,
for the vertical set the calibration also needs, along rows (``2 pi v_p / period``).
Photometry, blur and noise reuse :class:`gearscan.twin.render.Optics` and
:meth:`TwinRenderer.expose`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from gearscan.core.rig import PinholeDevice, Rig, look_at, rot_z
from gearscan.recon.calibration import BoardCapture, Checkerboard
from gearscan.twin.render import Optics, TwinRenderer

BLACK_ALBEDO = 0.12  # printed black relative to the optics' albedo (white)


def _subsample_rays(cam: PinholeDevice, s: int) -> np.ndarray:
    """Undistorted unit rays ``(H*s, W*s, 3)`` at ``s x s`` sub-pixel samples (n-rooks: no two share a row or a
    column), sample ``(i, j)`` of pixel ``(x, y)`` at ``[y*s + j, x*s + i]``.

    Undistorting every sub-sample is slow (iterative); the normalised coordinates are a
    smooth field, so they are computed at pixel centres on a one-pixel padded grid and
    interpolated bilinearly (error far below 1e-4 px for lens distortion).
    """
    if s == 1:
        return cam.pixel_rays()
    k = cam.K.copy()
    k[0, 2] += 1
    k[1, 2] += 1
    padded = PinholeDevice(cam.width + 2, cam.height + 2, k, cam.dist, cam.T_from_world).pixel_rays()
    xy = (padded[..., :2] / padded[..., 2:3]).astype(np.float32)
    # n-rooks sub-samples: each of a pixel's s*s samples has a column and a row offset of its own, so an edge along
    # the pixel grid is integrated in s*s steps; on a regular s x s grid a tilted board's rows (edges along the pixel
    # rows: every corner of a row at one sub-pixel phase) came out up to 1/(2s) px off, together (0.06 px at s = 4,
    # which biased a calibration's focal length; session 55)
    i, j = np.meshgrid(np.arange(s), np.arange(s))  # the sample's column and row within its pixel
    # multiples of 1/32 px for s = 4, kept exactly by remap's 1/32 px grid; from s = 6 on some samples share a position
    ox, oy = (i + (j + 0.5) / s) / s - 0.5, (j + (i + 0.5) / s) / s - 0.5
    shape = (cam.height, s, cam.width, s)
    mx = np.broadcast_to(np.arange(cam.width)[None, None, :, None] + ox[None, :, None, :] + 1, shape)
    my = np.broadcast_to(np.arange(cam.height)[:, None, None, None] + oy[None, :, None, :] + 1, shape)
    flat = (cam.height * s, cam.width * s)
    fine = cv2.remap(xy, mx.reshape(flat).astype(np.float32), my.reshape(flat).astype(np.float32),
                     cv2.INTER_LINEAR).astype(np.float64)
    rays = np.concatenate([fine, np.ones((*fine.shape[:2], 1))], axis=-1)
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


class BoardRenderer:
    """Renders a checkerboard at given poses as the rig's camera sees it.

    Parameters
    ----------
    rig : camera + projector
    board : the printed checkerboard
    optics : photometry and noise (``Optics().noise_free()`` for exact images)
    supersample : sub-samples per pixel along each axis (anti-aliasing)
    """

    def __init__(self, rig: Rig, board: Checkerboard, optics: Optics | None = None, *, supersample: int = 4) -> None:
        if supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        self.rig = rig
        self.board = board
        self.optics = optics or Optics()
        self.s = int(supersample)
        cam = rig.camera
        rays = _subsample_rays(cam, self.s).reshape(-1, 3)
        self._rays_world = np.ascontiguousarray((rays @ cam.T_world_from[:3, :3].T).T, dtype=np.float32)  # (3, n)
        self._rays_center = cam.pixel_rays().reshape(-1, 3) @ cam.T_world_from[:3, :3].T
        self._cam_center = cam.center_world
        self._proj_center = rig.projector.center_world
        self._shape = (cam.height, cam.width)
        self._d0 = float(np.linalg.norm(self._proj_center[:2]))  # as TwinRenderer: projector to axis
        # exposure helper: TwinRenderer.expose only uses the optics
        self._expose = TwinRenderer.expose.__get__(_OpticsHolder(self.optics))

    def _bin(self, x: np.ndarray) -> np.ndarray:
        """Average ``s x s`` sub-samples into camera pixels: ``(H*s*W*s,) -> (H, W)``."""
        h, w = self._shape
        return x.reshape(h, self.s, w, self.s).mean(axis=(1, 3), dtype=np.float64)

    def _plane_hits(self, rays_world: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points, board-frame points and hit flags of rays from the camera centre."""
        normal, origin = t[:3, 2], t[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            dist = ((origin - self._cam_center) @ normal) / (rays_world @ normal)
        hit = np.isfinite(dist) & (dist > 0)
        pts = self._cam_center + np.where(hit, dist, 0.0)[:, None] * rays_world
        return pts, (pts - origin) @ t[:3, :3], hit

    def _albedo(self, x: np.ndarray, y: np.ndarray, hit: np.ndarray) -> np.ndarray:
        b = self.board
        sq = np.float32(b.square_mm)
        lo, hi_x, hi_y = -(1 + b.margin_squares) * sq, (b.cols + b.margin_squares) * sq, (b.rows + b.margin_squares) * sq
        on_plate = hit & (x >= lo) & (x <= hi_x) & (y >= lo) & (y <= hi_y)
        in_pattern = (x >= -sq) & (x <= b.cols * sq) & (y >= -sq) & (y <= b.rows * sq)
        # square (a, b) with lower corner (a s, b s), a, b >= -1, is black when a + b is even
        parity = (np.floor(x / sq) + np.floor(y / sq)).astype(np.int64) & 1
        black = in_pattern & (parity == 0)
        white = np.float32(self.optics.albedo)
        return np.where(on_plate, np.where(black, np.float32(BLACK_ALBEDO) * white, white), np.float32(0.0))

    def _local_fine(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Board-plane coordinates ``(x, y)`` of every sub-sample ray, float32, and hit flags.

        ``p = c + lam d`` with ``lam = n.(o - c) / n.d``; board coordinates are
        ``e_k.(c - o) + lam e_k.d`` for the board's in-plane axes ``e_1, e_2``.
        """
        axes = t[:3, :3]
        dx, dy, dz = self._rays_world

        def dot(k: int) -> np.ndarray:  # e_k . d for every ray (three fused scalings: fast)
            e = axes[:, k].astype(np.float32)
            return dx * e[0] + dy * e[1] + dz * e[2]

        rel = self._cam_center - t[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = np.float32(-(axes[:, 2] @ rel)) / dot(2)
        hit = np.isfinite(lam) & (lam > 0)
        x = np.float32(axes[:, 0] @ rel) + lam * dot(0)
        y = np.float32(axes[:, 1] @ rel) + lam * dot(1)
        return x, y, hit

    def _geometry(self, t_world_from_board: np.ndarray) -> dict:
        """Albedo (supersampled, binned) and the smooth projector terms at pixel centres.

        Albedo edges are integrated over ``s x s`` sub-samples; projector coordinates and the
        irradiance factor vary slowly and are taken at pixel centres.
        """
        t = np.asarray(t_world_from_board, dtype=np.float64)
        albedo = self._bin(self._albedo(*self._local_fine(t))).astype(np.float64)
        pts, _, hit = self._plane_hits(self._rays_center, t)
        normal, origin = t[:3, 2], t[:3, 3]
        uv = self.rig.projector.project(pts)
        inside = self.rig.projector.in_frame(uv)
        to_pt = pts - self._proj_center
        dp = np.linalg.norm(to_pt, axis=1)
        cos_inc = np.abs(to_pt @ normal) / dp
        facing = ((self._proj_center - origin) @ normal) * ((self._cam_center - origin) @ normal) > 0
        lit = (hit & inside & facing).reshape(self._shape)
        factor = (self.optics.projector_power * cos_inc * (self._d0 / dp) ** 2).reshape(self._shape)
        irr = np.where(lit, albedo * factor, 0.0)
        uv = np.where(lit[..., None], uv.reshape(*self._shape, 2), 0.0)
        return {"albedo": albedo, "irr": irr, "uv": uv}

    def _blur(self, img: np.ndarray) -> np.ndarray:
        s = self.optics.camera_defocus_px
        img = np.ascontiguousarray(img, dtype=np.float32)
        if s <= 0:
            return img
        return cv2.GaussianBlur(img, (0, 0), s, borderType=cv2.BORDER_REPLICATE)

    def _contrast(self, period_px: float) -> float:
        s = self.optics.projector_defocus_px
        return math.exp(-2 * (math.pi * s / period_px) ** 2)

    def render(
        self,
        t_world_from_board: np.ndarray,
        *,
        periods_u: Sequence[float] = (20.0, 160.0, 1400.0),
        periods_v: Sequence[float] = (20.0, 160.0, 900.0),
        steps: int = 12,
        rng: np.random.Generator | int | None = 0,
        name: str = "view",
        turntable_angle: float | None = None,
    ) -> BoardCapture:
        """White image plus ``steps``-step fringes at each period, both orientations.

        The white image is the projector's full-white frame; fringe images are
        ``A + B cos(phi + 2 pi n / steps)`` with ``phi = 2 pi u_p / period`` (``fringes_u``)
        or ``2 pi v_p / period`` (``fringes_v``).
        """
        if steps < 3:
            raise ValueError(f"steps must be >= 3, got {steps}")
        rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        g = self._geometry(t_world_from_board)
        o = self.optics
        amb = g["albedo"] * o.ambient
        white = self._expose(self._blur(amb + g["irr"])[None], rng)[0]
        half = 0.5 * g["irr"]
        dc = self._blur(amb + half)
        shifts = 2 * np.pi * np.arange(steps) / steps
        cos_s = np.cos(shifts).astype(np.float32)[:, None, None]
        sin_s = np.sin(shifts).astype(np.float32)[:, None, None]
        out: dict[str, dict[float, np.ndarray]] = {"u": {}, "v": {}}
        for axis, periods in (("u", periods_u), ("v", periods_v)):
            coord = g["uv"][..., 0 if axis == "u" else 1]
            for period in periods:
                phi = 2 * np.pi * coord / period
                b = half * self._contrast(period)
                bc = self._blur(b * np.cos(phi))
                bs = self._blur(b * np.sin(phi))
                lin = dc[None] + cos_s * bc[None] - sin_s * bs[None]
                out[axis][float(period)] = self._expose(lin, rng)
        return BoardCapture(
            name=name,
            white=white,
            fringes_u=out["u"],
            fringes_v=out["v"],
            full_scale=o.full_scale,
            turntable_angle=turntable_angle,
        )

    def corners_truth(self, t_world_from_board: np.ndarray) -> np.ndarray:
        """Exact camera pixels ``(N, 2)`` of the board's inner corners (with distortion)."""
        obj = self.board.object_points().astype(np.float64)
        t = np.asarray(t_world_from_board, dtype=np.float64)
        return self.rig.camera.project(obj @ t[:3, :3].T + t[:3, 3])

    def projector_truth(self, t_world_from_board: np.ndarray) -> np.ndarray:
        """Exact projector pixels ``(N, 2)`` of the board's inner corners."""
        obj = self.board.object_points().astype(np.float64)
        t = np.asarray(t_world_from_board, dtype=np.float64)
        return self.rig.projector.project(obj @ t[:3, :3].T + t[:3, 3])


class _OpticsHolder:
    """Minimal stand-in so :meth:`TwinRenderer.expose` can be reused without a gear scene."""

    def __init__(self, optics: Optics) -> None:
        self.optics = optics


def calibration_poses(
    rig: Rig,
    board: Checkerboard,
    *,
    free_views: Sequence[tuple[float, float, float, float]] = (
        (0, 0, 0, 0),
        (18, 0, 0, 0),
        (-18, 0, 0, 0),
        (0, 18, 0, 0),
        (0, -18, 0, 0),
        (12, 12, 2.5, 3.5),
        (-12, 12, -2.5, 3.5),
        (12, -12, 2.5, -3.5),
        (-12, -12, -2.5, -3.5),
        (0, 0, 0, 4.0),
        (0, 0, 0, -4.0),
    ),
    # every 7.5 deg over +-45 deg: chosen on hand-placed seeds over +-24 deg in 12 deg steps and over +-45 deg in 15 deg
    # steps (benchmarks/calibration_views_rule.md): the radius error's RMS 2.30 -> 1.22 um, the shape's median
    # 2.27 -> 1.32 um on those seeds
    turntable_angles_deg: Sequence[float] = (-45.0, -37.5, -30.0, -22.5, -15.0, -7.5, 0.0, 7.5, 15.0, 22.5, 30.0, 37.5,
                                             45.0),
    free_distance_mm: float | None = None,
) -> list[tuple[str, np.ndarray, float | None]]:
    """Board poses for a calibration set: ``(name, T_world_from_board, turntable angle rad or None)``.

    Free-hand views ``(tilt_x, tilt_y, shift_x, shift_y)`` (deg, mm) face the camera at the
    working distance, tilted about the board's x and y axes and shifted across the field so
    the corners reach the image edges (distortion is only observable there). Turntable views stand the board in a plane through the rotation axis, facing the
    camera at encoder angle 0 with its centre on the axis (so the fitted world origin is the
    rig's), turned by each encoder angle.
    """
    cam = rig.camera
    c = cam.center_world
    # board centre for free views: where the camera's optical axis meets the plane x = axis + ~working radius
    fwd = cam.T_world_from[:3, 2]
    target_free = c + fwd * (free_distance_mm or float(np.linalg.norm(c[:2]) - 21.0))
    poses: list[tuple[str, np.ndarray, float | None]] = []

    def facing(centre: np.ndarray, tilt_x: float, tilt_y: float, shift: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        # board frame: x along the image columns, y along the image rows, z away from the camera
        t_cb = look_at(c, centre, np.array([0.0, 0.0, 1.0]))  # camera-like frame at the camera
        r = t_cb[:3, :3].T  # world from that frame: columns x (right), y (down), z (forward)
        rx = cv2.Rodrigues(np.array([math.radians(tilt_x), 0.0, 0.0]))[0]
        ry = cv2.Rodrigues(np.array([0.0, math.radians(tilt_y), 0.0]))[0]
        rot = r @ rx @ ry
        t = np.eye(4)
        t[:3, :3] = rot
        t[:3, 3] = centre + r[:, 0] * shift[0] + r[:, 1] * shift[1] - rot @ board.centre
        return t

    for i, (tx, ty, sx, sy) in enumerate(free_views):
        poses.append((f"free_{i:02d}", facing(target_free, tx, ty, (sx, sy)), None))
    base = facing(np.zeros(3), 0.0, 0.0)
    for i, a in enumerate(turntable_angles_deg):
        ang = math.radians(a)
        poses.append((f"turntable_{i:02d}", rot_z(ang) @ base, ang))
    return poses


def render_calibration_set(
    rig: Rig,
    board: Checkerboard | None = None,
    optics: Optics | None = None,
    *,
    steps: int = 12,
    supersample: int = 4,
    seed: int = 0,
    poses: list[tuple[str, np.ndarray, float | None]] | None = None,
) -> list[BoardCapture]:
    """Render every pose of :func:`calibration_poses` (or ``poses``)."""
    board = board or Checkerboard()
    renderer = BoardRenderer(rig, board, optics, supersample=supersample)
    rng = np.random.default_rng(seed)
    poses = poses if poses is not None else calibration_poses(rig, board)
    ph = rig.projector.height
    pw = rig.projector.width
    periods_u = (20.0, 160.0, float(math.ceil(pw * 1.1)))
    periods_v = (20.0, 160.0, float(math.ceil(ph * 1.1)))
    return [
        renderer.render(t, periods_u=periods_u, periods_v=periods_v, steps=steps, rng=rng, name=name, turntable_angle=ang)
        for name, t, ang in poses
    ]
