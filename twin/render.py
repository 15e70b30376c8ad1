"""Digital-twin renderer: fringe images of a rotating gear with exact ground truth.

Camera pixels are ray-cast to the gear mesh (open3d RaycastingScene), hits are projected
into the projector to get their absolute phase, a ray from the projector tells whether
they are lit, and the image is formed as

``L = albedo * (ambient + power * cos(incidence) * (d0/d)^2 * P(phi + delta))``

with ``P`` the projector's (gamma-distorted, defocus-attenuated) sinusoid, followed by
camera defocus, camera gamma, shot + read noise and quantisation. Everything is seeded.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gearscan.core.gear import GearSpec
from gearscan.core.patterns import PatternSet
from gearscan.core.rig import Rig, rot_z
from gearscan.twin.defects import GearDefects, true_mesh

Fringe = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # TwinRenderer._fringe


class RenderError(ValueError):
    """The scene cannot be rendered as asked (e.g. the camera sees no gear)."""


class Optics(BaseModel):
    """Photometric and optical parameters of the twin (fractions of full scale S)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    albedo: float = Field(0.85, gt=0, le=1)
    ambient: float = Field(0.06, ge=0, le=1, description="ambient irradiance, fraction of S")
    projector_power: float = Field(0.8, gt=0, le=4, description="projector irradiance at normal incidence, fraction of S")
    projector_gamma: float = Field(1.0, ge=0.3, le=3.5, description="residual projector gamma after pre-compensation")
    camera_gamma: float = Field(1.0, ge=0.3, le=3.5)
    camera_defocus_px: float = Field(0.5, ge=0, le=10, description="Gaussian sigma of camera blur, camera px")
    projector_defocus_px: float = Field(1.0, ge=0, le=20, description="Gaussian sigma of projector blur, projector px")
    full_well: float = Field(12000.0, gt=0, description="electrons at full scale (shot noise); inf for none")
    read_noise: float = Field(0.6, ge=0, description="read noise std, DN")
    bit_depth: int = Field(8, description="8, 10, 12 or 16")
    min_modulation: float = Field(0.05, ge=0, le=1, description="mask threshold on 2B/S")
    min_incidence_cos: float = Field(0.08, ge=0, le=1, description="mask threshold on cos(projector incidence)")

    def model_post_init(self, __context: object) -> None:
        if self.bit_depth not in (8, 10, 12, 16):
            raise ValueError(f"bit_depth must be 8, 10, 12 or 16, got {self.bit_depth}")

    @property
    def full_scale(self) -> int:
        return (1 << self.bit_depth) - 1

    @property
    def dtype(self) -> type:
        return np.uint8 if self.bit_depth == 8 else np.uint16

    def noise_free(self) -> Optics:
        return self.model_copy(update={"full_well": math.inf, "read_noise": 0.0})


@dataclass(slots=True)
class Surface:
    """Per-pixel geometry of the gear at one pose (camera image grid)."""

    angle: float
    hit: np.ndarray  # (H, W) bool, ray hits the gear
    points_cam: np.ndarray  # (H, W, 3) float64, NaN where no hit
    depth: np.ndarray  # (H, W) z in camera frame, NaN where no hit
    u_proj: np.ndarray  # (H, W) projector column coordinate, NaN where not lit
    lit: np.ndarray  # (H, W) bool: hit, inside the projector image, not shadowed
    irradiance: np.ndarray  # (H, W) float32, albedo * power * cos(inc) * falloff, 0 where not lit
    cos_incidence: np.ndarray  # (H, W) float32, cosine of the projector ray's incidence, 0 where not lit


@dataclass(slots=True)
class Truth:
    """Ground truth of one rendered pose for the pattern period ``period_px``."""

    angle: float
    period_px: float
    phase_abs: np.ndarray  # (H, W) float64, NaN where unlit
    phase: np.ndarray  # (H, W) float32 wrapped to (-pi, pi], 0 where invalid
    M: np.ndarray  # (H, W) float32, 2B/S sin(phi)
    D: np.ndarray  # (H, W) float32, 2B/S cos(phi)
    mask: np.ndarray  # (H, W) bool
    depth: np.ndarray  # (H, W) float32, NaN where no hit
    points: np.ndarray  # (H, W, 3) float32 camera frame, NaN where invalid


LinearOf = Callable[[int, np.ndarray], np.ndarray]  # (k, scratch) -> linear image k, consumed


def _expose(o: Optics, shape: tuple[int, int, int], linear_of: LinearOf, rng: np.random.Generator) -> np.ndarray:
    """Raw images ``shape`` (n, H, W) of :meth:`TwinRenderer.expose`, image k from ``linear_of``.

    One noise stream per image, seeded from ``rng``, so the two halves of the stack can be
    exposed on two threads and the result does not depend on which thread took which image.
    """
    n = shape[0]
    out = np.empty(shape, o.dtype)
    noisy = math.isfinite(o.full_well) or o.read_noise > 0
    seeds = rng.integers(0, 2**31 - 1, size=n) if noisy else np.zeros(n, np.int64)
    if n == 1:
        _expose_range(range(n), linear_of, out, seeds, o)
    else:
        half = (n + 1) // 2
        with ThreadPoolExecutor(1, thread_name_prefix="twin-expose") as beside:
            job = beside.submit(_expose_range, range(half, n), linear_of, out, seeds, o)
            _expose_range(range(half), linear_of, out, seeds, o)
            job.result()
    if o.full_scale != np.iinfo(o.dtype).max:
        np.minimum(out, o.full_scale, out=out)
    return out


def _expose_range(ks: range, linear_of: LinearOf, out: np.ndarray, seeds: np.ndarray, o: Optics) -> None:
    """Expose images ``ks`` into ``out[ks]`` one by one, so the temporaries stay in cache."""
    s = float(o.full_scale)
    depth = cv2.CV_8U if o.dtype == np.uint8 else cv2.CV_16U
    noisy = math.isfinite(o.full_well) or o.read_noise > 0
    scratch = np.empty(out.shape[1:], np.float32)
    noise = np.zeros(out.shape[1:], np.float32)
    if noisy:
        shot = s * s / o.full_well if math.isfinite(o.full_well) else 0.0  # DN^2 per unit of x
        read2 = np.full(out.shape[1:], o.read_noise**2, np.float32)
        std = np.empty(out.shape[1:], np.float32)
    for k in ks:
        x = linear_of(k, scratch)
        np.clip(x, 0.0, 1.0, out=x)
        if o.camera_gamma != 1.0:
            np.power(x, 1.0 / o.camera_gamma, out=x)
        if noisy:
            cv2.scaleAdd(x, shot, read2, std)  # variance in DN^2
            cv2.sqrt(std, std)
            cv2.setRNGSeed(int(seeds[k]))  # OpenCV's generator is per thread
            cv2.randn(noise, 0.0, 1.0)
            noise *= std
        # x S + noise, rounded to nearest (ties to even) and saturated to the raw dtype
        cv2.addWeighted(x, s, noise, 1.0, 0.0, out[k], dtype=depth)


class TwinRenderer:
    """Renders a gear on the turntable as the rig's camera sees it under fringe light."""

    def __init__(
        self, rig: Rig, gear: GearSpec, optics: Optics | None = None, *, mesh=None, defects: GearDefects | None = None
    ) -> None:
        """Render ``gear`` as built with ``defects`` (``gear`` stays the nominal spec), or ``mesh``."""
        import open3d as o3d

        self.rig = rig
        self.gear = gear
        self.defects = defects
        self.optics = optics or Optics()
        legacy = mesh if mesh is not None else true_mesh(gear, defects)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(legacy))
        cam = rig.camera
        self._rays_cam = cam.pixel_rays().reshape(-1, 3).astype(np.float32)  # (HW, 3) camera frame
        n = self._rays_cam.shape[0]
        # surface() work buffers: rays (origin, direction), gear-frame points, a (3, HW) and a row
        self._buffers = (np.empty((n, 6), np.float32), np.empty((3, n)), np.empty((3, n)), np.empty(n))
        self._cam_center = cam.center_world
        self._proj_center = rig.projector.center_world
        self._shape = (cam.height, cam.width)
        # nominal distance for the inverse-square falloff: projector to the rotation axis
        self._d0 = float(np.linalg.norm(self._proj_center[:2]))
        self._check_visibility()

    # --- geometry -------------------------------------------------------------------
    def _cast(self, rays: np.ndarray) -> dict:
        import open3d as o3d

        return self.scene.cast_rays(o3d.core.Tensor.from_numpy(rays))

    def surface(self, angle: float) -> Surface:
        """Ray-cast the camera at turntable angle ``angle`` (rad).

        Work happens in the gear's frame (the mesh stays put, the rig turns by ``-angle``) on
        whole-image arrays, NaN where the ray misses, one row per coordinate: numpy's
        ``(N, 3)`` broadcasts run 3-element inner loops, and its ``(N, 3) @ (3, 3)`` is a
        threaded BLAS call, both many times slower here. Temporaries live in buffers kept
        between calls (fresh ones cost a page fault per 4 KiB), so a renderer serves one thread
        at a time.
        """
        h, w = self._shape
        n = h * w
        rays, pts_g, work, row = self._buffers
        t_gw = rot_z(-angle)  # gear frame from world
        t_gc = t_gw @ self.rig.camera.T_world_from
        cam_g = t_gc[:3, 3]
        m = np.zeros((6, 4), np.float32)  # one ray per row: origin (camera centre), direction
        m[:3, 3] = cam_g
        m[3:, :3] = t_gc[:3, :3]
        cv2.transform(self._rays_cam.reshape(n, 1, 3), m, rays.reshape(n, 1, 6))
        ans = self._cast(rays)
        t = ans["t_hit"].numpy()
        hit = np.isfinite(t)
        t_hit = np.where(hit, t, np.float32(np.nan)).astype(np.float64)
        for c in range(3):
            np.multiply(t_hit, rays[:, 3 + c], out=pts_g[c])
            pts_g[c] += cam_g[c]

        # projector: column coordinate, incidence, and a shadow test (ray from the projector
        # centre to the point) for the points that face it inside its image
        proj_g = t_gw[:3, :3] @ self._proj_center
        to_pt = np.subtract(pts_g, proj_g[:, None], out=work)
        dist = np.sqrt(to_pt[0] * to_pt[0] + to_pt[1] * to_pt[1] + to_pt[2] * to_pt[2])
        dir_p = np.divide(to_pt, dist, out=work).astype(np.float32)
        normals = ans["primitive_normals"].numpy()
        cos_inc = -(normals[:, 0] * dir_p[0] + normals[:, 1] * dir_p[1] + normals[:, 2] * dir_p[2])
        t_pg = self.rig.projector.T_from_world @ np.linalg.inv(t_gw)
        pts_p = work
        for c in range(3):
            np.multiply(pts_g[0], t_pg[c, 0], out=pts_p[c])
            pts_p[c] += np.multiply(pts_g[1], t_pg[c, 1], out=row)
            pts_p[c] += np.multiply(pts_g[2], t_pg[c, 2], out=row)
            pts_p[c] += t_pg[c, 3]
        uv = self.rig.projector.project_device(pts_p.T)
        inside = self.rig.projector.in_frame(uv)
        cand = np.flatnonzero(inside & (cos_inc > 0))  # NaN (no hit) compares False
        rays_p = rays[: len(cand)]  # the camera's rays are spent
        rays_p[:, :3] = proj_g
        for c in range(3):
            np.take(dir_p[c], cand, out=rays_p[:, 3 + c])
        tp = self._cast(rays_p)["t_hit"].numpy()
        d_c = dist[cand]
        lit = np.zeros(n, dtype=bool)
        lit[cand[np.abs(tp - d_c) < 1e-3 + 1e-5 * d_c]] = True  # unshadowed

        o = self.optics
        cos_lit = np.where(lit, cos_inc, np.float32(0.0))
        irr = (o.albedo * o.projector_power * cos_lit * (self._d0 / dist) ** 2).astype(np.float32)
        irr[~lit] = 0.0  # NaN where no hit
        # camera-frame points: t * ray is exact in float64 (float32 factors), NaN where no hit
        points = np.empty((n, 3))
        for c in range(3):
            np.multiply(t_hit, self._rays_cam[:, c], out=points[:, c])
        points = points.reshape(h, w, 3)
        return Surface(
            angle=angle,
            hit=hit.reshape(h, w),
            points_cam=points,
            depth=points[..., 2],
            u_proj=np.where(lit, uv[:, 0], np.nan).reshape(h, w),
            lit=lit.reshape(h, w),
            irradiance=irr.reshape(h, w),
            cos_incidence=cos_lit.reshape(h, w),
        )

    def _check_visibility(self) -> None:
        surf = self.surface(0.0)
        frac = surf.lit.mean()
        if frac < 0.02:
            raise RenderError(
                f"the camera sees the lit gear on {100 * frac:.2f}% of its pixels at angle 0 "
                "(expected >= 2%): check the rig extrinsics against the gear size"
            )

    # --- photometry -----------------------------------------------------------------
    def _contrast(self, period_px: float) -> float:
        """Projector defocus attenuation of a sinusoid of this period (Gaussian MTF)."""
        s = self.optics.projector_defocus_px
        return math.exp(-2 * (math.pi * s / period_px) ** 2)

    @staticmethod
    def _fringe(surf: Surface, period_px: float) -> Fringe:
        """Fringe phase terms of ``surf`` for ``period_px``, shared by the images and the truth.

        Returns the absolute phase ``2 pi u_p / period`` (float64, NaN where unlit); the phase
        wrapped to [-pi, pi] (wrapped in float64, rounded to float32); its cosine and sine in
        float32 (float64 ones cost 30x more here). The last three are 0, 1, 0 where unlit.
        """
        phase_abs = 2 * np.pi * surf.u_proj / period_px
        phi = np.where(surf.lit, phase_abs, 0.0)
        wrapped = (phi - 2 * np.pi * np.rint(phi / (2 * np.pi))).astype(np.float32)
        return phase_abs, wrapped, np.cos(wrapped), np.sin(wrapped)

    def _linear_terms(self, surf: Surface, period_px: float, fringe: Fringe) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """DC, B cos(phi), B sin(phi) images (fractions of S) for the linear model."""
        o = self.optics
        _, _, cos_phi, sin_phi = fringe
        half = 0.5 * surf.irradiance
        dc = (o.albedo * o.ambient * surf.hit + half).astype(np.float32)
        b = half * self._contrast(period_px)
        return dc, b * cos_phi, b * sin_phi

    def _blur(self, img: np.ndarray) -> np.ndarray:
        s = self.optics.camera_defocus_px
        if s <= 0:
            return img
        return cv2.GaussianBlur(img, (0, 0), s, borderType=cv2.BORDER_REPLICATE)

    def _sinusoid_terms(
        self, surf: Surface, patterns: PatternSet, indices: list[int], fringes: dict[float, Fringe]
    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, float, float]]:
        """Per image: blurred DC, B cos(phi), B sin(phi) of its period, cos(delta), sin(delta).

        ``A + B cos(phi + delta) = A + cos(delta) B cos(phi) - sin(delta) B sin(phi)`` and the
        camera blur is linear, so three blurred images per period make every image (projector
        gamma 1). Fringe terms are kept per period in ``fringes``.
        """
        blurred: dict[float, tuple[np.ndarray, ...]] = {}
        out = []
        for i in indices:
            p = patterns.patterns[i]
            if p.period_px not in blurred:
                if p.period_px not in fringes:
                    fringes[p.period_px] = self._fringe(surf, p.period_px)
                terms = self._linear_terms(surf, p.period_px, fringes[p.period_px])
                blurred[p.period_px] = tuple(self._blur(x) for x in terms)
            out.append((*blurred[p.period_px], math.cos(p.shift), math.sin(p.shift)))
        return out

    @staticmethod
    def _sinusoid(terms: tuple[np.ndarray, np.ndarray, np.ndarray, float, float], out: np.ndarray) -> np.ndarray:
        """One linear image from :meth:`_sinusoid_terms` into ``out``."""
        dc, bc, bs, cos_d, sin_d = terms
        cv2.scaleAdd(bc, cos_d, dc, out)
        return cv2.scaleAdd(bs, -sin_d, out, out)

    def linear_images(self, surf: Surface, patterns: PatternSet, indices: list[int] | None = None) -> np.ndarray:
        """Noise-free linear radiance images ``(n, H, W)`` float32 (fractions of S), blurred."""
        indices = list(range(len(patterns))) if indices is None else indices
        o = self.optics
        out = np.empty((len(indices), *self._shape), dtype=np.float32)
        if o.projector_gamma == 1.0:
            for k, terms in enumerate(self._sinusoid_terms(surf, patterns, indices, {})):
                self._sinusoid(terms, out[k])
            return out
        amb = (o.albedo * o.ambient * surf.hit).astype(np.float32)
        phases: dict[float, np.ndarray] = {}
        for k, i in enumerate(indices):
            p = patterns.patterns[i]
            if p.period_px not in phases:
                phases[p.period_px] = np.where(surf.lit, 2 * np.pi * np.nan_to_num(surf.u_proj) / p.period_px, 0.0)
            # blur-before-gamma is approximated by attenuating the sinusoid, then applying gamma
            val = (0.5 + 0.5 * self._contrast(p.period_px) * np.cos(phases[p.period_px] + p.shift)) ** o.projector_gamma
            out[k] = self._blur((amb + surf.irradiance * val).astype(np.float32))
        return out

    def expose(self, linear: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Camera response: gamma, shot + read noise, quantisation to the raw dtype.

        ``linear`` ``(..., H, W)`` float32, fractions of S, is consumed in place. The noise in DN
        is Gaussian with variance ``signal_DN * S / full_well + read_noise^2``: the Poisson shot
        noise of ``signal_DN * full_well / S`` electrons (Gaussian at these counts) plus read
        noise. It comes from OpenCV's generator (4x faster than numpy's), one stream per image
        seeded from ``rng``.
        """
        if linear.ndim < 2:
            raise RenderError(f"linear: expected (..., H, W) images, got shape {linear.shape}")
        x = np.ascontiguousarray(linear, dtype=np.float32)
        planes = x.reshape(-1, *x.shape[-2:])
        return _expose(self.optics, planes.shape, lambda k, _: planes[k], rng).reshape(x.shape)

    # --- public API -----------------------------------------------------------------
    def truth(self, surf: Surface, period_px: float) -> Truth:
        """Analytic truth at this pose for fringes of ``period_px``."""
        return self._truth(surf, period_px, self._fringe(surf, period_px))

    def _truth(self, surf: Surface, period_px: float, fringe: Fringe) -> Truth:
        o = self.optics
        phase_abs, wrapped, cos_phi, sin_phi = fringe
        mod = surf.irradiance * self._contrast(period_px)  # 2B/S of the linear model
        mask = surf.lit & (mod >= o.min_modulation) & (surf.cos_incidence >= o.min_incidence_cos)
        mask = self.clean_mask(mask, surf)
        points = np.where(mask[..., None], surf.points_cam, np.nan).astype(np.float32)
        zero = np.float32(0.0)
        return Truth(
            angle=surf.angle,
            period_px=period_px,
            phase_abs=phase_abs,
            phase=np.where(mask, wrapped, zero),
            M=np.where(mask, mod * sin_phi, zero),
            D=np.where(mask, mod * cos_phi, zero),
            mask=mask,
            depth=surf.depth.astype(np.float32),
            points=points,
        )

    def clean_mask(self, mask: np.ndarray, surf: Surface) -> np.ndarray:
        """Drop pixels whose blur footprint reaches unlit pixels or a depth jump."""
        rad = int(math.ceil(3 * self.optics.camera_defocus_px)) + 1
        k = np.ones((2 * rad + 1, 2 * rad + 1), np.uint8)
        lit_core = cv2.erode(surf.lit.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        # depth discontinuities: a step between neighbours far above a steep (84 deg) slope
        pixel_mm = float(np.median(surf.depth[surf.hit])) / self.rig.camera.K[0, 0] if surf.hit.any() else 1.0
        depth = np.where(surf.hit, surf.depth, 1e6)
        jump = np.zeros(depth.shape, dtype=bool)
        dx = np.abs(np.diff(depth, axis=1)) > 10 * pixel_mm
        dy = np.abs(np.diff(depth, axis=0)) > 10 * pixel_mm
        jump[:, 1:] |= dx
        jump[:, :-1] |= dx
        jump[1:, :] |= dy
        jump[:-1, :] |= dy
        # shading creases (flank to tip land): a step in irradiance, which a blur turns into a
        # phase bias. A second difference finds steps and ignores smooth shading gradients at
        # any resolution.
        irr = surf.irradiance
        ref = np.maximum(irr, 1e-3)
        cx = np.abs(irr[:, 2:] - 2 * irr[:, 1:-1] + irr[:, :-2]) > 0.1 * ref[:, 1:-1]
        cy = np.abs(irr[2:, :] - 2 * irr[1:-1, :] + irr[:-2, :]) > 0.1 * ref[1:-1, :]
        jump[:, 1:-1] |= cx
        jump[1:-1, :] |= cy
        smooth = ~cv2.dilate(jump.astype(np.uint8), k).astype(bool)
        return mask & lit_core.astype(bool) & smooth

    def render(
        self,
        angle: float,
        patterns: PatternSet,
        rng: np.random.Generator | int | None = 0,
        *,
        indices: list[int] | None = None,
        motion_span: float = 0.0,
        motion_samples: int = 5,
    ) -> tuple[np.ndarray, Truth]:
        """Images ``(n, H, W)`` of ``patterns`` (or the given indices) at one pose, plus truth.

        ``motion_span`` (rad) integrates the exposure over angles ``angle +- span/2``.
        Truth is for the first pattern's period at ``angle``.
        """
        rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        surf = self.surface(angle)
        first = patterns.patterns[(indices or [0])[0]].period_px
        fringes = {first: self._fringe(surf, first)}
        with ThreadPoolExecutor(1, thread_name_prefix="twin-truth") as beside:  # truth beside the images
            truth = beside.submit(self._truth, surf, first, fringes[first])
            if motion_span > 0:
                lin = np.zeros((len(indices or patterns.patterns), *self._shape), np.float32)
                for a in np.linspace(angle - motion_span / 2, angle + motion_span / 2, motion_samples):
                    lin += self.linear_images(self.surface(float(a)), patterns, indices)
                lin /= motion_samples
                images = self.expose(lin, rng)
            elif self.optics.projector_gamma == 1.0:  # each image formed where it is exposed
                which = list(range(len(patterns))) if indices is None else indices
                terms = self._sinusoid_terms(surf, patterns, which, fringes)
                shape = (len(terms), *self._shape)
                images = _expose(self.optics, shape, lambda k, buf: self._sinusoid(terms[k], buf), rng)
            else:
                images = self.expose(self.linear_images(surf, patterns, indices), rng)
            return images, truth.result()

    def render_sequence(
        self,
        angles: list[float],
        patterns: PatternSet,
        pattern_indices: list[int],
        rng: np.random.Generator | int | None = 0,
        *,
        motion_span: float = 0.0,
    ) -> tuple[np.ndarray, list[Truth]]:
        """One frame per angle, showing ``pattern_indices[i]`` at ``angles[i]`` (a moving burst)."""
        if len(angles) != len(pattern_indices):
            raise RenderError(f"{len(angles)} angles but {len(pattern_indices)} pattern indices")
        rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        frames, truths = [], []
        for a, i in zip(angles, pattern_indices, strict=True):
            img, tr = self.render(float(a), patterns, rng, indices=[i], motion_span=motion_span)
            frames.append(img[0])
            truths.append(tr)
        return np.stack(frames), truths
