"""Rig calibration: camera and projector pinhole models and the turntable frame.

The calibration file is JSON in OpenCV conventions (the file ``gearscan calibrate``
writes and the twin and pipeline read)::

    {
      "format": "gearscan-rig", "version": 1, "units": "mm",
      "camera":    {"width": W, "height": H, "K": [[fx,0,cx],[0,fy,cy],[0,0,1]],
                    "dist": [k1,k2,p1,p2,k3], "T_from_world": 4x4},
      "projector": {... same keys ...},
      "turntable": {"counts_per_rev": 0 or N},
      "calibration": {"radius_um": u, "shape_rms_um_p95": s, "draws": n}   (optional)
    }

``T_from_world`` maps turntable-frame points (origin on the rotation axis, z along the
axis, mm) into the device's OpenCV frame (x right, y down, z forward). The projector is
an inverse camera; its fringe phase varies along its columns (u). ``calibration``, where ``gearscan calibrate``'s joint
adjustment wrote the rig, is the calibration's own stated uncertainty (:class:`CalibrationStatement`), so a recording
that holds the rig carries it to ``inspect``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

RIG_FORMAT = "gearscan-rig"
RIG_VERSION = 1


class RigError(ValueError):
    """A calibration file or rig parameter is invalid."""


def _as_matrix(value: object, shape: tuple[int, ...], name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise RigError(f"{name}: expected numbers of shape {shape}, got {value!r}") from exc
    if arr.shape != shape:
        raise RigError(f"{name}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise RigError(f"{name}: contains non-finite values")
    return arr


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` (rad) about unit ``axis`` (Rodrigues)."""
    import cv2

    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    rot, _ = cv2.Rodrigues(axis * angle)
    return rot


def rot_z(angle: float) -> np.ndarray:
    """4x4 homogeneous rotation about the turntable axis (world z) by ``angle`` rad."""
    c, s = math.cos(angle), math.sin(angle)
    t = np.eye(4)
    t[:2, :2] = [[c, -s], [s, c]]
    return t


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``T_device_from_world`` of a device at ``eye`` looking at ``target``.

    OpenCV frame: z towards the target, y along ``-up`` projected on the image plane.
    """
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)
    if np.linalg.norm(x) < 1e-9:
        raise RigError("look_at: up vector is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])  # rows: device axes in world coordinates
    t = np.eye(4)
    t[:3, :3] = r
    t[:3, 3] = -r @ eye
    return t


@dataclass(frozen=True)
class PinholeDevice:
    """A camera or projector: OpenCV pinhole intrinsics, distortion and pose."""

    width: int
    height: int
    K: np.ndarray  # 3x3
    dist: np.ndarray  # (5,) k1 k2 p1 p2 k3
    T_from_world: np.ndarray  # 4x4

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise RigError(f"resolution must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "K", _as_matrix(self.K, (3, 3), "K"))
        dist = np.zeros(5)
        d = np.asarray(self.dist, dtype=np.float64).ravel()
        if d.size not in (4, 5, 8):
            raise RigError(f"dist: expected 4, 5 or 8 OpenCV coefficients, got {d.size}")
        if not np.all(np.isfinite(d)):
            raise RigError(f"dist: contains non-finite values: {d.tolist()}")
        dist = d if d.size != 4 else np.append(d, 0.0)
        object.__setattr__(self, "dist", dist)
        t = _as_matrix(self.T_from_world, (4, 4), "T_from_world")
        r = t[:3, :3]
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
            raise RigError("T_from_world: rotation part is not a proper rotation matrix")
        if not np.array_equal(t[3], [0.0, 0.0, 0.0, 1.0]):  # a rigid transform: any other row scales or projects
            raise RigError(f"T_from_world: last row must be [0, 0, 0, 1] (a rigid transform), got {t[3].tolist()}")
        object.__setattr__(self, "T_from_world", t)
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise RigError(f"K: focal lengths must be positive, got fx={self.K[0, 0]}, fy={self.K[1, 1]}")
        if not np.array_equal(self.K[2], [0.0, 0.0, 1.0]) or self.K[1, 0] != 0 or self.K[0, 1] != 0:
            # OpenCV's pinhole intrinsics, which model no skew (its calibration never estimates one)
            raise RigError(f"K: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {self.K.tolist()}")

    @property
    def T_world_from(self) -> np.ndarray:
        return np.linalg.inv(self.T_from_world)

    @property
    def center_world(self) -> np.ndarray:
        """Optical centre in world coordinates, ``C = -R^T t`` (paper eq. 20)."""
        r, t = self.T_from_world[:3, :3], self.T_from_world[:3, 3]
        return -r.T @ t

    def scaled(self, width: int, height: int) -> PinholeDevice:
        """The same device resampled to another resolution (K scaled, pose kept)."""
        sx, sy = width / self.width, height / self.height
        k = self.K.copy()
        k[0, :] *= sx
        k[1, :] *= sy
        k[0, 2] = (self.K[0, 2] + 0.5) * sx - 0.5
        k[1, 2] = (self.K[1, 2] + 0.5) * sy - 0.5
        return replace(self, width=width, height=height, K=k)

    def normalized(self, pixels: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates ``(N, 2)`` (x/z, y/z in the device frame) of pixel positions ``(N, 2)``."""
        import cv2

        pts = np.asarray(pixels, np.float64).reshape(-1, 1, 2)
        if np.any(self.dist != 0):
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
            if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
                norm = cv2.undistortPointsIter(pts, self.K, self.dist, np.eye(3), np.eye(3), crit)
            else:  # OpenCV 5 folded the iterative variant into undistortPoints
                norm = cv2.undistortPoints(pts, self.K, self.dist, criteria=crit)
            return norm.reshape(-1, 2)
        kinv = np.linalg.inv(self.K)
        return (pts.reshape(-1, 2) - self.K[:2, 2]) @ np.diag([kinv[0, 0], kinv[1, 1]])

    def in_frame(self, uv: np.ndarray) -> np.ndarray:
        """Which pixel positions ``(..., 2)`` fall on the device's frame (its outer pixels' edges at -0.5 and
        size - 0.5); NaN is outside."""
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5) & (u <= self.width - 0.5) & (v >= -0.5) & (v <= self.height - 0.5)

    def pixel_rays(self) -> np.ndarray:
        """Unit ray directions ``(H, W, 3)`` in the device frame for every pixel centre."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        norm = self.normalized(np.stack([u.ravel(), v.ravel()], axis=1))
        d = np.concatenate([norm, np.ones((norm.shape[0], 1))], axis=1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return d.reshape(self.height, self.width, 3)

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """Pixel coordinates ``(..., 2)`` of world points ``(..., 3)`` (with distortion)."""
        p = points_world.reshape(-1, 3) @ self.T_from_world[:3, :3].T + self.T_from_world[:3, 3]
        return self.project_device(p).reshape(*points_world.shape[:-1], 2)

    def project_device(self, p: np.ndarray) -> np.ndarray:
        """Pixel coordinates ``(N, 2)`` of points ``(N, 3)`` already in this device's frame."""
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = p[:, 0] / z, p[:, 1] / z
        k1, k2, p1, p2, k3 = self.dist[:5]
        if np.any(self.dist[:5] != 0):
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
            xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        else:
            xd, yd = x, y
        u = self.K[0, 0] * xd + self.K[0, 1] * yd + self.K[0, 2]
        v = self.K[1, 1] * yd + self.K[1, 2]
        out = np.stack([u, v], axis=-1)
        out[z <= 0] = np.nan
        return out

    def to_json(self) -> dict:
        return {
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "T_from_world": self.T_from_world.tolist(),
        }

    @classmethod
    def from_json(cls, data: dict, name: str) -> PinholeDevice:
        keys = ("width", "height", "K", "dist", "T_from_world")
        if not isinstance(data, dict):
            raise RigError(f"{name}: expected an object with {', '.join(keys)}, got {type(data).__name__}")
        missing = [k for k in keys if k not in data]
        if missing:
            raise RigError(f"{name}: missing keys {missing}")
        try:
            return cls(int(data["width"]), int(data["height"]), data["K"], data["dist"], data["T_from_world"])
        except RigError as exc:
            raise RigError(f"{name}.{exc}") from exc
        except (TypeError, ValueError) as exc:  # "width": "wide", "dist": "x"
            raise RigError(f"{name}: {exc}") from exc


@dataclass(frozen=True)
class CalibrationStatement:
    """What a rig's calibration says of its own uncertainty (``recon.rig_check.calibration_uncertainty``): the
    standard deviation of a 20 mm radius read through it (um, k = 1) and the 95th percentile of a fused revolution's
    shape RMS (um), from ``draws`` calibrations drawn from its adjustment's covariance. Corner noise only."""

    radius_um: float
    shape_rms_um_p95: float
    draws: int

    def __post_init__(self) -> None:
        for key in ("radius_um", "shape_rms_um_p95"):
            value = getattr(self, key)
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise RigError(f"calibration.{key}: expected a finite number >= 0 (um), got {value!r}")
        if isinstance(self.draws, bool) or not (isinstance(self.draws, int) and self.draws >= 2):
            raise RigError(f"calibration.draws: expected an integer >= 2, got {self.draws!r}")

    def to_json(self) -> dict:
        return {"radius_um": self.radius_um, "shape_rms_um_p95": self.shape_rms_um_p95, "draws": self.draws}

    @classmethod
    def from_json(cls, data: object, source: str) -> CalibrationStatement:
        if not isinstance(data, dict) or not {"radius_um", "shape_rms_um_p95", "draws"} <= set(data):
            raise RigError(f"{source}: \"calibration\" must be an object with radius_um, shape_rms_um_p95 and draws, "
                           f"got {data!r}")
        try:
            return cls(data["radius_um"], data["shape_rms_um_p95"], data["draws"])
        except RigError as exc:
            raise RigError(f"{source}: {exc}") from exc

    def line(self) -> str:
        """One sentence for reports."""
        return (f"its calibration states +-{2 * self.radius_um:.1f} um (k = 2) on a 20 mm radius and a fused shape up to "
                f"{self.shape_rms_um_p95:.1f} um RMS (95 %) of its own (corner noise through its adjustment, "
                f"{self.draws} drawn calibrations; the lens model and the encoder not included)")


def _calibration_of(data: dict, source: str) -> CalibrationStatement | None:
    """A rig file's ``calibration``; a file ``gearscan calibrate`` wrote before the key existed (session 56) holds the
    same statement in its ``calibration_report``'s ``uncertainty``."""
    if data.get("calibration") is not None:
        return CalibrationStatement.from_json(data["calibration"], source)
    unc = (data.get("calibration_report") or {}).get("uncertainty") if isinstance(data.get("calibration_report"), dict) \
        else None
    if isinstance(unc, dict) and unc.get("stated"):
        return CalibrationStatement.from_json(unc, f"{source}: calibration_report.uncertainty")
    return None


@dataclass(frozen=True)
class Rig:
    """Camera + projector + turntable: everything needed to render or triangulate."""

    camera: PinholeDevice
    projector: PinholeDevice
    counts_per_rev: int = 0
    name: str = "rig"
    calibration: CalibrationStatement | None = None  # the calibration's stated uncertainty, where it stated one

    @property
    def T_proj_from_cam(self) -> np.ndarray:
        return self.projector.T_from_world @ self.camera.T_world_from

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.camera.center_world - self.projector.center_world))

    def with_camera_resolution(self, width: int, height: int) -> Rig:
        return replace(self, camera=self.camera.scaled(width, height))

    def to_json(self) -> dict:
        return {
            "format": RIG_FORMAT,
            "version": RIG_VERSION,
            "units": "mm",
            "name": self.name,
            "camera": self.camera.to_json(),
            "projector": self.projector.to_json(),
            "turntable": {"counts_per_rev": self.counts_per_rev},
            **({} if self.calibration is None else {"calibration": self.calibration.to_json()}),
        }

    @classmethod
    def from_json(cls, data: dict, source: str = "rig") -> Rig:
        if not isinstance(data, dict) or data.get("format") != RIG_FORMAT:
            raise RigError(f"{source}: not a gearscan rig file (expected \"format\": \"{RIG_FORMAT}\")")
        if data.get("version") != RIG_VERSION:
            raise RigError(f"{source}: rig version {data.get('version')!r} unsupported (expected {RIG_VERSION})")
        if data.get("units", "mm") != "mm":
            raise RigError(f"{source}: units must be \"mm\", got {data.get('units')!r}")
        for key in ("camera", "projector"):
            if key not in data:
                raise RigError(f"{source}: missing section \"{key}\"")
        turntable = data.get("turntable", {})
        if not isinstance(turntable, dict):
            raise RigError(f"{source}: \"turntable\" must be an object, got {turntable!r}")
        try:
            counts = int(turntable.get("counts_per_rev", 0))
        except (TypeError, ValueError) as exc:
            raise RigError(f"{source}: turntable.counts_per_rev: expected an integer, got "
                           f"{turntable.get('counts_per_rev')!r}") from exc
        return cls(
            camera=PinholeDevice.from_json(data["camera"], f"{source}: camera"),
            projector=PinholeDevice.from_json(data["projector"], f"{source}: projector"),
            counts_per_rev=counts,
            name=str(data.get("name", "rig")),
            calibration=_calibration_of(data, source),
        )

    def save(self, path: str | Path) -> None:
        path = Path(path)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(self.to_json(), indent=2))
        tmp.replace(path)

    @classmethod
    def load(cls, path: str | Path) -> Rig:
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError as exc:
            raise RigError(f"rig file not found: {path}") from exc
        except json.JSONDecodeError as exc:
            raise RigError(f"{path}: invalid JSON at line {exc.lineno}: {exc.msg}") from exc
        except (OSError, UnicodeDecodeError) as exc:  # a folder, no permission, a binary file
            raise RigError(f"{path}: cannot read a rig file ({exc})") from exc
        return cls.from_json(data, str(path))


def default_rig(
    width: int = 512,
    height: int = 512,
    *,
    working_radius: float = 21.0,
    standoff: float = 160.0,
    field_mm: float = 26.0,
    triangulation_deg: float = 24.0,
    elevation_deg: float = 0.0,
    projector_size: tuple[int, int] = (1280, 800),
    projector_field_mm: float = 36.0,
    distortion: bool = True,
) -> Rig:
    """A rig like the paper's: camera and projector look at the gear's toothed rim.

    The camera looks radially at the rim point ``(working_radius, 0, 0)`` from ``standoff``
    mm away, image columns along the circumference (the direction teeth move), rows along
    the axis. The projector sits ``triangulation_deg`` around the target in the plane normal
    to the axis, so fringes (varying along projector columns) cross the teeth and tooth flanks
    shadow each other. ``field_mm`` is the width seen by the camera at the target: 26 mm
    covers about four teeth of a module-2, 20-tooth gear.
    """
    target = np.array([working_radius, 0.0, 0.0])
    up = np.array([0.0, 0.0, 1.0])  # image rows run along -z
    elev = math.radians(elevation_deg)

    def device(az_deg: float, w: int, h: int, field: float, dist: bool) -> PinholeDevice:
        az = math.radians(az_deg)
        direction = np.array([math.cos(az) * math.cos(elev), math.sin(az) * math.cos(elev), math.sin(elev)])
        eye = target + standoff * direction
        f = w * standoff / field
        k = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
        d = np.array([-0.08, 0.12, 0.0005, -0.0003, 0.0]) if dist else np.zeros(5)
        return PinholeDevice(w, h, k, d, look_at(eye, target, up))

    camera = device(0.0, width, height, field_mm, distortion)
    projector = device(triangulation_deg, projector_size[0], projector_size[1], projector_field_mm, False)
    return Rig(camera=camera, projector=projector, counts_per_rev=0, name="default")


FRINGE_ORIENTATION_AGREEMENT = 0.9
"""Share of the sampled camera pixels whose fringe phase must run one way for a rig to have an orientation."""


@dataclass(frozen=True, slots=True)
class FringeOrientation:
    """Which way the projector's fringe phase runs along the camera's columns, from the calibration alone.

    ``rising``: the share of sampled camera pixels (over the image, on the plane through the rig's working
    point that faces both devices, and on the one facing the camera) where the phase rises along the
    columns. ``orientation``: ``"normal"`` (rising, as on the twin's rigs), ``"mirrored"``, or None where
    neither side holds :data:`FRINGE_ORIENTATION_AGREEMENT` of them (fringes within about a degree
    of the columns, or rows that cross the epipolar lines steeply).
    """

    orientation: str | None
    rising: float

    def describe(self) -> str:
        if self.orientation is None:
            return (f"the calibration's fringe phase rises along the camera columns at {self.rising:.0%} of the image "
                    "and falls at the rest (fringes along the columns?): no fringe orientation")
        side = self.rising if self.orientation == "normal" else 1.0 - self.rising
        return f"fringes {self.orientation} (the calibration: {side:.0%} of the image)"


def working_point(rig: Rig) -> np.ndarray:
    """The point on the camera's optical axis that the projector shows nearest its image centre (world, mm): what
    both devices look at. The axes' closest approach is no answer for parallel or diverging axes (a calibration
    of a parallel rig comes out a little toed-out) nor for a projector with lens shift."""
    cam, proj = rig.camera, rig.projector
    depths = np.geomspace(1.0, 1e5, 4001)
    pts = cam.center_world + depths[:, None] * cam.T_world_from[:3, 2]
    uv = proj.project(pts)
    miss = np.hypot(uv[:, 0] - (proj.width - 1) / 2, uv[:, 1] - (proj.height - 1) / 2)
    if not np.isfinite(miss).any():
        raise RigError("fringe orientation: the camera's optical axis is nowhere in front of the projector")
    return pts[int(np.nanargmin(miss))]


def fringe_orientation(rig: Rig, samples: int = 17) -> FringeOrientation:
    """The rig's fringe orientation (:class:`FringeOrientation`), from its geometry.

    Along an epipolar line a lit surface that both devices see from the same side keeps the order of its
    points in both images, so where the camera's rows run along the epipolar lines (the fringes cross the
    columns, as the network needs) the sign of d(projector column)/d(camera column) is the rig's, not the
    surface's: the network's "normal" (trained on) or "mirrored" (decoded flipped). With rows across the
    epipolar lines, steep surfaces can flip it locally (the twin's four views, 20 and 60 teeth, two angles each: none
    of 564,930 column steps of the ray caster's projector column falls; session 43). Read on two
    planes through :func:`working_point` (facing the camera; facing the bisector of both devices) at a
    ``samples`` x ``samples`` grid of camera pixels. No frames needed: unlike a vote on a burst's phase,
    motion cannot fool it. :class:`RigError` where no sampled pixel sees those planes in front of both.
    """
    import cv2

    cam = rig.camera
    target = working_point(rig)
    to_cam = cam.center_world - target
    to_proj = rig.projector.center_world - target
    to_cam, to_proj = to_cam / np.linalg.norm(to_cam), to_proj / np.linalg.norm(to_proj)
    normals = [to_cam, (to_cam + to_proj) / np.linalg.norm(to_cam + to_proj)]
    u, v = np.meshgrid(np.linspace(0.1, 0.9, samples) * (cam.width - 1), np.linspace(0.1, 0.9, samples) * (cam.height - 1))
    pix = np.stack([u.ravel(), v.ravel()], axis=1)
    try:
        k_inv = np.linalg.inv(cam.K)
    except np.linalg.LinAlgError as exc:
        raise RigError(f"fringe orientation: the camera's K is singular: {cam.K.tolist()}") from exc
    r_wc = cam.T_world_from[:3, :3]
    signs = []
    for n in normals:
        cols = []
        for du in (-0.5, 0.5):
            pts = (pix + [du, 0.0]).reshape(-1, 1, 2)
            norm = cv2.undistortPoints(pts, cam.K, cam.dist).reshape(-1, 2) if np.any(cam.dist != 0) else \
                (np.c_[pts.reshape(-1, 2), np.ones(len(pix))] @ k_inv.T)[:, :2]
            rays = np.c_[norm, np.ones(len(norm))] @ r_wc.T  # world directions from the camera centre
            with np.errstate(divide="ignore", invalid="ignore"):  # a ray along the plane: no point, NaN below
                depth = ((target - cam.center_world) @ n) / (rays @ n)
                uv = rig.projector.project(cam.center_world + rays * depth[:, None])
            cols.append(np.where(depth > 0, uv[:, 0], np.nan))
        signs.append(np.sign(cols[1] - cols[0]))
    s = np.concatenate(signs)
    s = s[np.isfinite(s) & (s != 0)]
    if s.size == 0:
        raise RigError("fringe orientation: no camera pixel sees the working point's planes in front of the projector")
    rising = float(np.mean(s > 0))
    if rising >= FRINGE_ORIENTATION_AGREEMENT:
        return FringeOrientation("normal", rising)
    if rising <= 1.0 - FRINGE_ORIENTATION_AGREEMENT:
        return FringeOrientation("mirrored", rising)
    return FringeOrientation(None, rising)
