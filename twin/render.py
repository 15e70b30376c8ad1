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
from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gearscan.core.gear import GearSpec
from gearscan.core.patterns import PatternSet
from gearscan.core.rig import Rig, rot_z
from gearscan.twin.defects import GearDefects, true_mesh


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
        self._rays_buf = np.empty((self._rays_cam.shape[0], 6), np.float32)
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

        Work happens in the gear's frame (the mesh stays put, the rig turns by ``-angle``).
        """
        h, w = self._shape
        t_gw = rot_z(-angle)  # gear frame from world
        t_gc = t_gw @ self.rig.camera.T_world_from
        cam_g = t_gc[:3, 3]
        buf = self._rays_buf
        buf[:, :3] = cam_g
        np.matmul(self._rays_cam, t_gc[:3, :3].T.astype(np.float32), out=buf[:, 3:])
        ans = self._cast(buf)
        t = ans["t_hit"].numpy()
        idx = np.flatnonzero(np.isfinite(t))
        t_i = t[idx].astype(np.float64)[:, None]
        pts_cam = t_i * self._rays_cam[idx]
        pts_g = cam_g + t_i * buf[idx, 3:]
        normals_g = ans["primitive_normals"].numpy()[idx]

        # projector: column coordinate and shadow test (ray from the projector centre to the point)
        proj_g = t_gw[:3, :3] @ self._proj_center
        to_pt = pts_g - proj_g
        dist = np.sqrt(np.einsum("ij,ij->i", to_pt, to_pt))
        dir_p = (to_pt / dist[:, None]).astype(np.float32)
        rays_p = np.empty((len(idx), 6), np.float32)
        rays_p[:, :3] = proj_g
        rays_p[:, 3:] = dir_p
        tp = self._cast(rays_p)["t_hit"].numpy()
        unshadowed = np.abs(tp - dist) < 1e-3 + 1e-5 * dist
        cos_inc = -np.einsum("ij,ij->i", normals_g, dir_p)
        t_pg = self.rig.projector.T_from_world @ np.linalg.inv(t_gw)
        uv = self.rig.projector.project_device(pts_g @ t_pg[:3, :3].T + t_pg[:3, 3])
        pw, ph = self.rig.projector.width, self.rig.projector.height
        inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= pw - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= ph - 0.5)
        lit_i = inside & unshadowed & (cos_inc > 0)
        lit_idx = idx[lit_i]

        n = h * w
        hit = np.zeros(n, dtype=bool)
        hit[idx] = True
        points = np.full((n, 3), np.nan)
        points[idx] = pts_cam
        u_proj = np.full(n, np.nan)
        u_proj[lit_idx] = uv[lit_i, 0]
        lit = np.zeros(n, dtype=bool)
        lit[lit_idx] = True
        o = self.optics
        irr = np.zeros(n, dtype=np.float32)
        irr[lit_idx] = o.albedo * o.projector_power * cos_inc[lit_i] * (self._d0 / dist[lit_i]) ** 2
        cos_full = np.zeros(n, dtype=np.float32)
        cos_full[lit_idx] = cos_inc[lit_i]
        points = points.reshape(h, w, 3)
        return Surface(
            angle=angle,
            hit=hit.reshape(h, w),
            points_cam=points,
            depth=points[..., 2],
            u_proj=u_proj.reshape(h, w),
            lit=lit.reshape(h, w),
            irradiance=irr.reshape(h, w),
            cos_incidence=cos_full.reshape(h, w),
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

    def _linear_terms(self, surf: Surface, period_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Blurred DC, B cos(phi), B sin(phi) images (fractions of S) for the linear model."""
        o = self.optics
        phi = np.where(surf.lit, 2 * np.pi * np.nan_to_num(surf.u_proj) / period_px, 0.0)
        half = 0.5 * surf.irradiance
        dc = (o.albedo * o.ambient * surf.hit + half).astype(np.float32)
        b = half * self._contrast(period_px)
        bc = (b * np.cos(phi)).astype(np.float32)
        bs = (b * np.sin(phi)).astype(np.float32)
        return dc, bc, bs

    def _blur(self, img: np.ndarray) -> np.ndarray:
        s = self.optics.camera_defocus_px
        if s <= 0:
            return img
        return cv2.GaussianBlur(img, (0, 0), s, borderType=cv2.BORDER_REPLICATE)

    def linear_images(self, surf: Surface, patterns: PatternSet, indices: list[int] | None = None) -> np.ndarray:
        """Noise-free linear radiance images ``(n, H, W)`` float32 (fractions of S), blurred."""
        indices = list(range(len(patterns))) if indices is None else indices
        o = self.optics
        out = np.empty((len(indices), *self._shape), dtype=np.float32)
        if o.projector_gamma == 1.0:
            cache: dict[float, tuple[np.ndarray, ...]] = {}
            for k, i in enumerate(indices):
                p = patterns.patterns[i]
                if p.period_px not in cache:
                    cache[p.period_px] = tuple(self._blur(x) for x in self._linear_terms(surf, p.period_px))
                dc, bc, bs = cache[p.period_px]
                out[k] = dc + math.cos(p.shift) * bc - math.sin(p.shift) * bs
            return out
        amb = (o.albedo * o.ambient * surf.hit).astype(np.float32)
        for k, i in enumerate(indices):
            p = patterns.patterns[i]
            phi = np.where(surf.lit, 2 * np.pi * np.nan_to_num(surf.u_proj) / p.period_px, 0.0)
            # blur-before-gamma is approximated by attenuating the sinusoid, then applying gamma
            val = (0.5 + 0.5 * self._contrast(p.period_px) * np.cos(phi + p.shift)) ** o.projector_gamma
            out[k] = self._blur((amb + surf.irradiance * val).astype(np.float32))
        return out

    def expose(self, linear: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Camera response: gamma, shot + read noise, quantisation to the raw dtype.

        Consumes ``linear`` (float32, fractions of S) in place. Gaussian noise comes from
        OpenCV's generator (8x faster than numpy's here), seeded from ``rng``.
        """
        o = self.optics
        s = float(o.full_scale)
        x = np.ascontiguousarray(linear, dtype=np.float32)
        np.clip(x, 0.0, 1.0, out=x)
        if o.camera_gamma != 1.0:
            np.power(x, 1.0 / o.camera_gamma, out=x)
        x *= s
        if math.isfinite(o.full_well) or o.read_noise > 0:
            flat = x.reshape(-1, x.shape[-1])
            std = flat * np.float32(s / o.full_well) if math.isfinite(o.full_well) else np.zeros_like(flat)
            std += np.float32(o.read_noise**2)
            np.sqrt(std, out=std)
            noise = np.empty_like(flat)
            cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
            cv2.randn(noise, 0.0, 1.0)
            noise *= std
            flat += noise
        np.rint(x, out=x)
        np.clip(x, 0.0, s, out=x)
        return x.astype(o.dtype)

    # --- public API -----------------------------------------------------------------
    def truth(self, surf: Surface, period_px: float) -> Truth:
        """Analytic truth at this pose for fringes of ``period_px``."""
        o = self.optics
        phase_abs = 2 * np.pi * surf.u_proj / period_px
        mod = surf.irradiance * self._contrast(period_px)  # 2B/S of the linear model
        mask = surf.lit & (mod >= o.min_modulation) & (surf.cos_incidence >= o.min_incidence_cos)
        mask = self.clean_mask(mask, surf)
        phi = np.where(mask, np.nan_to_num(phase_abs), 0.0)
        wrapped = np.angle(np.exp(1j * phi)).astype(np.float32)
        points = np.where(mask[..., None], surf.points_cam, np.nan).astype(np.float32)
        return Truth(
            angle=surf.angle,
            period_px=period_px,
            phase_abs=phase_abs,
            phase=np.where(mask, wrapped, 0).astype(np.float32),
            M=np.where(mask, mod * np.sin(phi), 0).astype(np.float32),
            D=np.where(mask, mod * np.cos(phi), 0).astype(np.float32),
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
        pixel_mm = float(np.nanmedian(surf.depth)) / self.rig.camera.K[0, 0] if surf.hit.any() else 1.0
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
        if motion_span > 0:
            lin = np.zeros((len(indices or patterns.patterns), *self._shape), np.float32)
            for a in np.linspace(angle - motion_span / 2, angle + motion_span / 2, motion_samples):
                lin += self.linear_images(self.surface(float(a)), patterns, indices)
            lin /= motion_samples
        else:
            lin = self.linear_images(surf, patterns, indices)
        first = patterns.patterns[(indices or [0])[0]].period_px
        return self.expose(lin, rng), self.truth(surf, first)

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
