"""Signed distance of measured points to a surface: the CAD (what a user measures) or a twin's true gear."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gearscan.core.types import Measurement


class SurfaceDistance:
    """Signed distance of gear-frame points to a surface mesh (the CAD, or a twin's true gear)."""

    def __init__(self, mesh) -> None:
        import open3d as o3d

        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))

    def distances(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (mm, positive outside the material) of gear-frame ``points`` ``(N, 3)``."""
        import open3d as o3d

        pts = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
        return self.scene.compute_signed_distance(pts).numpy().astype(np.float64)

    def normals(self, points: np.ndarray, on_surface_mm: float = 1e-3) -> np.ndarray:
        """The direction ``(N, 3)`` in which each gear-frame point's distance grows: from its closest surface point
        to it (right at edges and vertices too), or, within ``on_surface_mm`` of the surface, the closest triangle's
        normal; NaN where neither is defined (a degenerate triangle). The sign does not matter to its users."""
        import open3d as o3d

        pts = np.ascontiguousarray(points, dtype=np.float64)
        closest = self.scene.compute_closest_points(o3d.core.Tensor(pts.astype(np.float32)))
        away = pts - closest["points"].numpy().astype(np.float64)
        tri = closest["primitive_normals"].numpy().astype(np.float64)
        length = np.linalg.norm(away, axis=1, keepdims=True)
        n = np.where(length > on_surface_mm, away, tri)
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(norm > 1e-9, n / norm, np.nan)

    def deviation_sigma(self, points: np.ndarray, sigma: np.ndarray, ray: np.ndarray,
                        along_ray: np.ndarray) -> np.ndarray:
        """The standard error of each point's signed distance (mm). Where ``along_ray`` (the frame fit's points,
        ``FusedCloud.refined``), ``sigma`` is a standard error along ``ray`` (``FusedCloud.ray``) and the distance
        changes along :meth:`normals`, so to first order it is ``sigma`` times the cosine between them; elsewhere
        (an unfitted point's sigma, calibrated against the distance normal to the surface: ``rest_sigma_rule.md``),
        and where either direction is unknown, ``sigma`` itself."""
        sigma = np.asarray(sigma, dtype=np.float64)
        cos = np.abs(np.einsum("ij,ij->i", self.normals(points), ray))
        return np.where(along_ray & np.isfinite(cos), sigma * np.minimum(cos, 1.0), sigma)


class CadScorer(SurfaceDistance):
    """Signed distance of each point to the gear's CAD mesh (the cloud's deviation map)."""

    def __init__(self, gear) -> None:
        super().__init__(gear.mesh())

    def __call__(self, m: Measurement) -> tuple[Measurement, dict[str, float]]:
        """``m`` with each point's deviation on its cloud, and the deviation's RMS and p95 (mm)."""
        if m.cloud is None or not len(m.cloud):
            return m, {}
        d = self.distances(m.cloud.points)
        stats = {"cad_rms_mm": float(np.sqrt(np.mean(d**2))), "cad_p95_mm": float(np.percentile(np.abs(d), 95))}
        return replace(m, cloud=replace(m.cloud, deviation=d)), stats
