"""Point clouds with per-point uncertainty (open3d), export, merging and CAD deviation.

A :class:`gearscan.core.types.Cloud` crosses stage boundaries; this module converts it to an
open3d tensor ``PointCloud`` (attribute ``sigma``, plus ``deviation`` when known), writes
PLY/PCD/CSV, merges clouds of successive bursts (turntable frame) with an optional voxel
downsample, and measures the distance of every point to the gear's CAD mesh.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from gearscan.core.types import Cloud

EXPORT_SUFFIXES = (".ply", ".pcd", ".csv")


def _check_cloud(cloud: Cloud) -> None:
    n = len(cloud)
    if cloud.points.ndim != 2 or cloud.points.shape[1] != 3:
        raise ValueError(f"cloud.points: expected (N, 3), got {cloud.points.shape}")
    if cloud.sigma.shape != (n,):
        raise ValueError(f"cloud.sigma: expected ({n},), got {cloud.sigma.shape}")


def to_open3d(cloud: Cloud):
    """``open3d.t.geometry.PointCloud`` with ``positions``, ``sigma`` and (if set) ``deviation``.

    Attributes are ``(N, 1)`` float32 tensors, as open3d's PLY/PCD writers expect.
    """
    import open3d as o3d

    _check_cloud(cloud)
    pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(cloud.points.astype(np.float32)))
    pcd.point["sigma"] = o3d.core.Tensor(cloud.sigma.astype(np.float32).reshape(-1, 1))
    if cloud.deviation is not None:
        pcd.point["deviation"] = o3d.core.Tensor(cloud.deviation.astype(np.float32).reshape(-1, 1))
    return pcd


def from_open3d(pcd, frame: str = "world") -> Cloud:
    """Back from an open3d tensor point cloud (pixels are unknown: ``(N, 2)`` of -1)."""
    pts = pcd.point["positions"].numpy().astype(np.float64)
    n = len(pts)
    sigma = pcd.point["sigma"].numpy().reshape(-1).astype(np.float64) if "sigma" in pcd.point else np.zeros(n)
    dev = pcd.point["deviation"].numpy().reshape(-1).astype(np.float64) if "deviation" in pcd.point else None
    return Cloud(points=pts, sigma=sigma, pixels=np.full((n, 2), -1, np.int32), frame=frame, deviation=dev)


def save_cloud(cloud: Cloud, path: str | Path, extra: dict[str, np.ndarray] | None = None) -> Path:
    """Write ``.ply``/``.pcd`` (open3d) or ``.csv`` with x, y, z (mm), ``sigma`` (mm), ``deviation``
    (mm, when set) and each per-point array of ``extra`` (e.g. a fused cloud's burst counts).

    The CSV has one header line (``x_mm,y_mm,z_mm,sigma_mm,...``) and one row per point, for
    tools that read no PLY (spreadsheets, CMM software).
    """
    import open3d as o3d

    path = Path(path)
    if path.suffix.lower() not in EXPORT_SUFFIXES:
        raise ValueError(f"path: expected a suffix in {EXPORT_SUFFIXES}, got {path.suffix!r} ({path})")
    if len(cloud) == 0:
        raise ValueError("cloud is empty: nothing to write")
    extra = extra or {}
    for name, values in extra.items():
        if np.shape(values) != (len(cloud),):
            raise ValueError(f"extra[{name!r}]: expected ({len(cloud)},), got {np.shape(values)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".csv":
        _check_cloud(cloud)
        cols = {"x_mm": cloud.points[:, 0], "y_mm": cloud.points[:, 1], "z_mm": cloud.points[:, 2], "sigma_mm": cloud.sigma}
        if cloud.deviation is not None:
            cols["deviation_mm"] = cloud.deviation
        # positions and deviation to the nanometre, sigma to 6 digits, counts as they are
        fmt = ["%.6f", "%.6f", "%.6f", "%.6g"] + ["%.6f"] * (len(cols) - 4) + ["%.6g"] * len(extra)
        cols.update(extra)
        np.savetxt(path, np.column_stack(list(cols.values())), fmt=fmt, delimiter=",", header=",".join(cols), comments="")
        return path
    pcd = to_open3d(cloud)
    for name, values in extra.items():
        pcd.point[name] = o3d.core.Tensor(np.asarray(values, dtype=np.float32).reshape(-1, 1))
    if not o3d.t.io.write_point_cloud(str(path), pcd):
        raise OSError(f"open3d could not write {path}: check the folder is writable")
    return path


def load_cloud(path: str | Path, frame: str = "world") -> Cloud:
    """Read a cloud written by :func:`save_cloud` (PLY, PCD or CSV)."""
    import open3d as o3d

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"point cloud not found: {path}")
    if path.suffix.lower() != ".csv":
        return from_open3d(o3d.t.io.read_point_cloud(str(path)), frame)
    data = np.genfromtxt(path, delimiter=",", names=True, dtype=np.float64, ndmin=1)
    names = data.dtype.names or ()
    if not {"x_mm", "y_mm", "z_mm", "sigma_mm"} <= set(names):
        raise ValueError(f"{path}: expected columns x_mm, y_mm, z_mm, sigma_mm, got {list(names)}")
    n = len(data)
    return Cloud(points=np.column_stack([data["x_mm"], data["y_mm"], data["z_mm"]]), sigma=np.asarray(data["sigma_mm"]),
                 pixels=np.full((n, 2), -1, np.int32), frame=frame,
                 deviation=np.asarray(data["deviation_mm"]) if "deviation_mm" in names else None)


def merge_clouds(clouds: Sequence[Cloud], voxel_mm: float | None = None) -> Cloud:
    """Stack clouds in the same frame; optionally voxel-downsample (attributes averaged).

    With ``voxel_mm`` the sigma of a voxel is the mean of its points' sigmas (a conservative
    choice: averaging n independent points would divide it by sqrt(n)).
    """
    if not clouds:
        raise ValueError("merge_clouds: got no clouds")
    frames = {c.frame for c in clouds}
    if len(frames) != 1:
        raise ValueError(f"merge_clouds: clouds are in different frames {sorted(frames)}; transform them first")
    has_dev = all(c.deviation is not None for c in clouds)
    merged = Cloud(
        points=np.concatenate([c.points for c in clouds]),
        sigma=np.concatenate([c.sigma for c in clouds]),
        pixels=np.concatenate([c.pixels for c in clouds]),
        frame=clouds[0].frame,
        burst_index=clouds[0].burst_index,
        angle=clouds[0].angle,
        deviation=np.concatenate([c.deviation for c in clouds]) if has_dev else None,
    )
    if voxel_mm is None:
        return merged
    if not voxel_mm > 0:
        raise ValueError(f"voxel_mm must be positive, got {voxel_mm}")
    down = to_open3d(merged).voxel_down_sample(float(voxel_mm))
    return replace(from_open3d(down, merged.frame), burst_index=merged.burst_index, angle=merged.angle)


@dataclass(frozen=True, slots=True)
class DeviationStats:
    """Summary of point-to-CAD distances (mm) over the points that have one."""

    count: int
    rms: float
    mean: float
    p95: float
    max: float

    def as_dict(self) -> dict[str, float]:
        return {"count": self.count, "rms_mm": self.rms, "mean_mm": self.mean, "p95_mm": self.p95, "max_mm": self.max}


def deviation_stats(deviation: np.ndarray) -> DeviationStats:
    """RMS, mean, 95th percentile and max of the absolute deviation (NaNs ignored)."""
    d = np.abs(np.asarray(deviation, dtype=np.float64))
    d = d[np.isfinite(d)]
    if d.size == 0:
        raise ValueError("deviation_stats: no finite deviation values")
    return DeviationStats(
        count=int(d.size),
        rms=float(np.sqrt(np.mean(d**2))),
        mean=float(np.mean(d)),
        p95=float(np.percentile(d, 95)),
        max=float(np.max(d)),
    )


def cad_deviation(cloud: Cloud, mesh, *, signed: bool = True) -> tuple[Cloud, DeviationStats]:
    """Distance of every point to the CAD mesh (turntable/gear frame), as a deviation map.

    Parameters
    ----------
    cloud : points in the gear's frame (``frame="world"`` at the burst's encoder angle, see
        :func:`gearscan.recon.triangulate.to_turntable`)
    mesh : watertight ``open3d.geometry.TriangleMesh`` (legacy) or tensor mesh, e.g.
        ``GearSpec.mesh()``
    signed : signed distance (positive outside the material) if True, else unsigned

    Returns
    -------
    The cloud with ``deviation`` set (mm, (N,)) and its summary statistics.
    """
    import open3d as o3d

    _check_cloud(cloud)
    if cloud.frame != "world":
        raise ValueError(f"cloud.frame: expected 'world' (turntable/gear frame), got {cloud.frame!r}")
    tmesh = mesh if isinstance(mesh, o3d.t.geometry.TriangleMesh) else o3d.t.geometry.TriangleMesh.from_legacy(mesh)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(tmesh)
    q = o3d.core.Tensor(cloud.points.astype(np.float32))
    dist = (scene.compute_signed_distance(q) if signed else scene.compute_distance(q)).numpy().astype(np.float64)
    out = Cloud(
        points=cloud.points,
        sigma=cloud.sigma,
        pixels=cloud.pixels,
        frame=cloud.frame,
        burst_index=cloud.burst_index,
        angle=cloud.angle,
        deviation=dist,
        extras=dict(cloud.extras),
    )
    return out, deviation_stats(dist)
