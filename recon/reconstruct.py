"""Fast single-frequency reconstruction: geometric unwrapping fused with triangulation.

The live pipeline gets one wrapped phase (and its sigma) per burst; everything that does not
depend on the phase is precomputed per rig, so a burst costs a few float32 operations per
pixel. Work runs in row blocks that stay in cache, on a small thread pool (numpy releases
the GIL). Results equal :func:`gearscan.recon.unwrap.geometric_unwrap` followed by
:class:`gearscan.recon.triangulate.Triangulator` for an undistorted projector; with
projector distortion use those (the fixed-point correction is not fused here).

Bounds are fixed per rig (tip/root cylinders) or given per call (the CAD gear at each burst's
encoder angle); per-call depth bounds become phase bounds in the same block pass, through the
projector column along the ray, ``u(z) = fx (c1 z + t1) / (c3 z + t3) + cx``.

Per pixel, with ``f = phi / 2 pi``, ``a = (phi_min - margin) / 2 pi`` and
``s = (phi_max - phi_min + 2 margin) / 2 pi``:

``k = ceil(a - f)``, valid iff ``k <= a - f + s < k + 1`` (exactly one order in the interval);
with a per-call prior instead of bounds (``centre_depth`` or ``centre_phase``: the expected
surface, e.g. the CAD at the encoder angle), the window is the whole fringe around it,
``k = ceil((phi_c - pi) / 2 pi - f)``, valid iff ``|phi_abs - phi_c| <= pi - margin`` (see
:func:`gearscan.recon.unwrap.centred_unwrap`); ``phi_abs = phi + 2 pi k``; ``z = (alpha phi_abs + beta) / (g - d phi_abs)``;
``sigma_z = |alpha g + beta d| sigma_phi / (g - d phi_abs)^2``; ``X = z (x, y, 1)``.
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from gearscan.core.rig import Rig
from gearscan.recon.triangulate import Triangulation
from gearscan.recon.unwrap import DepthBounds, phase_bounds

TWO_PI = 2.0 * math.pi


class SingleFrequencyReconstructor:
    """Wrapped phase of one fringe period -> camera-frame points with depth sigma.

    Parameters
    ----------
    rig : calibrated rig (projector without lens distortion for this fused path)
    period_px : fringe period, projector px
    bounds : per-pixel depth range (e.g. :func:`gearscan.recon.unwrap.gear_depth_bounds`); None
        when every call passes its own ``bounds=``
    margin : rad the phase interval is widened by on both sides (noise allowance)
    threads : worker threads (default: CPU count, at most 8)
    block_rows : rows per work item (cache-sized blocks)
    """

    def __init__(
        self,
        rig: Rig,
        period_px: float,
        bounds: DepthBounds | None = None,
        *,
        margin: float = 0.2,
        threads: int | None = None,
        block_rows: int = 64,
    ) -> None:
        if np.any(rig.projector.dist != 0):
            raise ValueError("rig.projector has lens distortion: use geometric_unwrap + Triangulator (fixed-point path)")
        if not period_px > 0:
            raise ValueError(f"period_px must be positive, got {period_px}")
        self.period_px = float(period_px)
        cam = rig.camera
        self.shape = (cam.height, cam.width)
        self.margin = float(margin)
        self._a = self._s = None
        if bounds is not None:
            lo, hi = phase_bounds(rig, bounds, period_px)
            self._a = ((lo - margin) / TWO_PI).astype(np.float32)
            self._s = ((hi - lo + 2 * margin) / TWO_PI).astype(np.float32)
        rays = cam.pixel_rays()
        rays = rays / rays[..., 2:3]
        self._x = rays[..., 0].astype(np.float32)
        self._y = rays[..., 1].astype(np.float32)
        t = rig.T_proj_from_cam
        r, tv = t[:3, :3], t[:3, 3]
        c1 = rays @ r[0]
        c3 = rays @ r[2]
        kp = rig.projector.K
        if kp[0, 1] != 0:
            raise ValueError(f"rig.projector.K has skew {kp[0, 1]}: use Triangulator")
        a = self.period_px / (TWO_PI * kp[0, 0])  # x_p = a phi + b
        b = -kp[0, 2] / kp[0, 0]
        # z = (x_p t3 - t1) / (c1 - x_p c3) = (alpha phi + beta) / (g - d phi)
        self._alpha = np.float32(a * tv[2])
        self._beta = np.float32(b * tv[2] - tv[0])
        self._g = (c1 - b * c3).astype(np.float32)
        self._d = (a * c3).astype(np.float32)
        self._num = np.abs(float(self._alpha) * self._g + float(self._beta) * self._d).astype(np.float32)
        # depth -> projector phase along each ray: phi(z) = (c1 z + t1) / (c3 z + t3) * q + q0
        self._c1 = c1.astype(np.float32)
        self._c3 = c3.astype(np.float32)
        self._t1, self._t3 = np.float32(tv[0]), np.float32(tv[2])
        self._q = np.float32(TWO_PI * kp[0, 0] / self.period_px)
        self._q0 = np.float32(TWO_PI * kp[0, 2] / self.period_px)
        self.block_rows = int(block_rows)
        self.threads = threads or min(8, os.cpu_count() or 1)
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __enter__(self) -> SingleFrequencyReconstructor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _phase_at(self, depth: np.ndarray, sl: slice) -> np.ndarray:
        """Absolute projector phase seen at camera z-depth ``depth`` along the rows ``sl``."""
        num = self._c1[sl] * depth
        num += self._t1
        den = self._c3[sl] * depth
        den += self._t3
        num /= den
        num *= self._q
        num += self._q0
        return num

    def _interval(self, bounds: DepthBounds, sl: slice) -> tuple[np.ndarray, np.ndarray]:
        """``a`` and ``s`` of the module docstring for per-call depth bounds, rows ``sl``."""
        p0 = self._phase_at(np.asarray(bounds.t_min[sl], np.float32), sl)
        p1 = self._phase_at(np.asarray(bounds.t_max[sl], np.float32), sl)
        lo = np.fmin(p0, p1)
        hi = np.fmax(p0, p1, out=p1)
        hi -= lo
        hi += np.float32(2 * self.margin)
        hi *= np.float32(1 / TWO_PI)
        lo -= np.float32(self.margin)
        lo *= np.float32(1 / TWO_PI)
        return lo, hi

    def _block(self, r0: int, r1: int, phase, sigma, bounds, centre, out_pts, out_z, out_sig, out_valid, out_k) -> None:
        sl = slice(r0, r1)
        phi = np.asarray(phase[sl], dtype=np.float32)
        k = out_k[sl]
        valid = out_valid[sl]
        if centre is not None:  # whole-fringe window around the prior's phase
            kind, prior = centre
            pc = (self._phase_at(np.asarray(prior[sl], np.float32), sl) if kind == "depth"
                  else np.array(prior[sl], np.float32))  # a copy: changed in place below
            u = pc - phi
            u *= np.float32(1 / TWO_PI)
            u -= np.float32(0.5)
            np.ceil(u, out=k)
            np.multiply(k, np.float32(TWO_PI), out=u)
            u += phi  # phi_abs
            pc -= u
            np.less_equal(np.abs(pc), np.float32(math.pi - self.margin), out=valid)  # NaN prior -> invalid
        else:
            a, s = self._interval(bounds, sl) if bounds is not None else (self._a[sl], self._s[sl])
            u = phi * np.float32(-1 / TWO_PI)
            u += a  # a - f
            np.ceil(u, out=k)
            top = u + s
            top -= k  # in [0, 1) iff exactly one order fits; NaN bounds -> NaN -> invalid
            np.less(top, 1.0, out=valid)
            valid &= top >= 0.0
            np.multiply(k, np.float32(TWO_PI), out=u)
            u += phi  # phi_abs
        den = self._d[sl] * u
        np.subtract(self._g[sl], den, out=den)
        z = out_z[sl]
        np.multiply(u, self._alpha, out=z)
        z += self._beta
        z /= den
        invalid = ~valid
        z[invalid] = np.nan  # z > 0 holds inside the bounds: no extra test needed
        pts = out_pts[sl]
        np.multiply(self._x[sl], z, out=pts[..., 0])
        np.multiply(self._y[sl], z, out=pts[..., 1])
        pts[..., 2] = z
        if sigma is not None:
            np.multiply(den, den, out=den)
            s = out_sig[sl]
            np.divide(self._num[sl], den, out=s)
            s *= sigma[sl] if np.ndim(sigma) == 2 else np.float32(sigma)
            s[invalid] = np.nan

    def phase_of_depth(self, depth: np.ndarray) -> np.ndarray:
        """Absolute projector phase (rad) seen at camera z-``depth`` (mm) along each ray, ``(H, W)``."""
        depth = np.asarray(depth, np.float32)
        if depth.shape != self.shape:
            raise ValueError(f"depth: expected shape {self.shape}, got {depth.shape}")
        return self._phase_at(depth, slice(None))

    def allocate(self) -> tuple[Triangulation, np.ndarray]:
        """Output buffers for ``out=``: reusing them saves ~100 MB of page faults per call."""
        h, w = self.shape
        tri = Triangulation(
            points=np.empty((h, w, 3), np.float32),
            depth=np.empty((h, w), np.float32),
            sigma_depth=np.empty((h, w), np.float32),
            valid=np.empty((h, w), bool),
        )
        return tri, np.empty((h, w), np.float32)

    def __call__(
        self,
        wrapped: np.ndarray,
        sigma_phase: np.ndarray | float | None = None,
        *,
        bounds: DepthBounds | None = None,
        centre_depth: np.ndarray | None = None,
        centre_phase: np.ndarray | None = None,
        out: tuple[Triangulation, np.ndarray] | None = None,
    ) -> tuple[Triangulation, np.ndarray]:
        """Unwrap and triangulate one wrapped phase ``(H, W)``.

        The fringe order comes from ``bounds`` (per call, or fixed at construction), or from a
        prior: ``centre_depth`` (camera z, mm) or ``centre_phase`` (absolute phase, rad) of the
        expected surface per pixel, NaN where there is none; the order is then the one nearest
        the prior, within the rig's whole unambiguous range (one fringe).

        Returns the camera-frame :class:`Triangulation` (``valid`` False where the fringe
        order is ambiguous or out of range) and the fringe order map ``(H, W)`` float32.
        ``out`` (from :meth:`allocate`) is filled in place and returned, for a live loop
        whose consumer is done with the previous result.
        """
        wrapped = np.asarray(wrapped)
        if wrapped.shape != self.shape:
            raise ValueError(f"wrapped: expected shape {self.shape} (camera H, W), got {wrapped.shape}")
        if sigma_phase is not None and np.ndim(sigma_phase) == 2 and np.shape(sigma_phase) != self.shape:
            raise ValueError(f"sigma_phase: expected a scalar or shape {self.shape}, got {np.shape(sigma_phase)}")
        centre = None
        for kind, prior in (("depth", centre_depth), ("phase", centre_phase)):
            if prior is not None:
                if centre is not None or bounds is not None:
                    raise ValueError("pass one of bounds=, centre_depth=, centre_phase=")
                if np.shape(prior) != self.shape:
                    raise ValueError(f"centre_{kind}: expected shape {self.shape}, got {np.shape(prior)}")
                centre = (kind, prior)
        if bounds is None and centre is None and self._a is None:
            raise ValueError("bounds: this reconstructor has no fixed bounds; pass bounds= per call")
        if bounds is not None:
            for name in ("t_min", "t_max"):
                if np.shape(getattr(bounds, name)) != self.shape:
                    raise ValueError(f"bounds.{name}: expected shape {self.shape}, got {np.shape(getattr(bounds, name))}")
        h, w = self.shape
        tri, order = out if out is not None else self.allocate()
        pts, z, sig, valid = tri.points, tri.depth, tri.sigma_depth, tri.valid
        if sigma_phase is None:
            sig[...] = 0.0
        sigma = None if sigma_phase is None else (np.asarray(sigma_phase, np.float32) if np.ndim(sigma_phase) == 2 else float(sigma_phase))
        args = (wrapped, sigma, bounds, centre, pts, z, sig, valid, order)
        starts = range(0, h, self.block_rows)
        if self._pool is None:
            for r0 in starts:
                self._block(r0, min(h, r0 + self.block_rows), *args)
        else:
            list(self._pool.map(lambda r0: self._block(r0, min(h, r0 + self.block_rows), *args), starts))
        if sigma_phase is None:
            sig[~valid] = np.nan
        return tri, order
