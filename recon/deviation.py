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

    def normals(self, points: np.ndarray) -> np.ndarray:
        """Unit normal ``(N, 3)`` of the surface's triangle closest to each gear-frame point."""
        import open3d as o3d

        pts = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
        n = self.scene.compute_closest_points(pts)["primitive_normals"].numpy().astype(np.float64)
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def deviation_sigma(self, points: np.ndarray, sigma: np.ndarray, ray: np.ndarray | None) -> np.ndarray:
        """The standard error of each point's signed distance (mm): ``sigma`` runs along ``ray`` (the frame fit's,
        :attr:`~gearscan.recon.fuse.FusedCloud.ray`), the distance along the surface normal, so it is ``sigma``
        times the cosine between them. Where no ray is known, ``sigma`` itself (an upper bound)."""
        sigma = np.asarray(sigma, dtype=np.float64)
        if ray is None:
            return sigma.copy()
        cos = np.abs(np.einsum("ij,ij->i", self.normals(points), ray))
        return np.where(np.isfinite(cos), sigma * np.minimum(cos, 1.0), sigma)


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
