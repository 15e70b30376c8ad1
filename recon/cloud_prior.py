"""A measured surface as the fringe-order prior: CAD-free unwrapping with a coarse burst.

With fine fringes a single period leaves the fringe order ambiguous beyond about +-1.3 mm of
depth (default rig, 40 px), and a gear's tip/root envelope spans several fringes, so without a
CAD most of the surface cannot be unwrapped (README, "Fringe orders"). A *coarse* three-step
burst (fringes wider than the envelope's depth, e.g. 160 px) is unwrapped by the envelope alone;
its cloud, carried to a later burst's encoder angle in the gear frame, is then a prior of the
surface that is accurate to a fraction of the fine range, and the fine bursts are unwrapped
around it exactly as around a CAD (:func:`~gearscan.recon.unwrap.prior_unwrap`). What it costs
is three frames per coarse burst and the surface that turned into view since it was taken;
``benchmarks/coarse_prior_report.md`` measures both against the turntable speed.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from gearscan.core.rig import Rig, rot_z


class CloudDepthPrior:
    """Camera depth of a measured gear-frame cloud at any turntable angle (same interface as
    :class:`~gearscan.recon.unwrap.CadDepthBounds.depth`).

    Each point is projected into the camera at the requested angle and the nearest one per pixel
    kept (a z-buffer); pixels without a point take the nearest of their 3x3 neighbours' depths
    when at least ``min_neighbours`` of them have one (the cloud of a turned surface thins out),
    and NaN otherwise: no prior, so the pixel stays unresolved rather than guessed.
    """

    def __init__(self, rig: Rig, points_gear: np.ndarray, *, min_neighbours: int = 3) -> None:
        pts = np.asarray(points_gear, np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points_gear: expected (N, 3) gear-frame points, got shape {pts.shape}")
        self.rig = rig
        self.points = pts[np.isfinite(pts).all(axis=1)]
        self.min_neighbours = int(min_neighbours)

    def __len__(self) -> int:
        return len(self.points)

    def depth(self, angle: float, mask: np.ndarray | None = None) -> np.ndarray:
        """Camera z-depth (mm) of the cloud's surface at turntable ``angle`` (rad), ``(H, W)`` float32."""
        cam = self.rig.camera
        h, w = cam.height, cam.width
        out = np.full((h, w), np.inf)
        if len(self.points):
            t = cam.T_from_world @ rot_z(angle)  # camera from gear frame at this angle
            p = self.points @ t[:3, :3].T + t[:3, 3]
            front = p[:, 2] > 0
            p = p[front]
            uv = np.rint(cam.project_device(p)).astype(np.int64)
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            flat = uv[inside, 1] * w + uv[inside, 0]
            np.minimum.at(out.ravel(), flat, p[inside, 2])
        known = np.isfinite(out)
        near = ndimage.minimum_filter(out, size=3, mode="constant", cval=np.inf)
        count = ndimage.convolve(known.astype(np.int32), np.ones((3, 3), np.int32), mode="constant")
        fill = ~known & (count >= self.min_neighbours)
        out = np.where(known, out, np.where(fill, near, np.nan)).astype(np.float32)
        if mask is not None:
            out[~np.asarray(mask, bool)] = np.nan
        return out
