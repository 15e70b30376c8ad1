"""Domain randomisation: rigs, optics and gears that differ the way real set-ups do.

Used to render training data that generalises to rigs and gears the network never saw.
The ranges are the model's validity range (stated in its model card).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Literal

import numpy as np

from gearscan.core.gear import GearSpec
from gearscan.core.rig import Rig, default_rig, look_at, rotation_about
from gearscan.twin.render import Optics, Surface

RANGES = {
    "standoff_mm": (120.0, 220.0),
    "triangulation_deg": (15.0, 32.0),
    "elevation_deg": (-8.0, 8.0),
    "teeth_in_view": (3.0, 5.5),
    "camera_period_px": (12.0, 40.0),
    "module_scale": (0.75, 1.5),
    "pressure_angle_deg": (17.5, 25.0),
    "albedo": (0.35, 1.0),
    "projector_power": (0.45, 1.0),
    "ambient": (0.0, 0.2),
    "projector_gamma": (0.85, 1.25),
    "camera_gamma": (0.9, 1.1),
    "camera_defocus_px": (0.3, 1.2),
    "projector_defocus_px": (0.5, 2.5),
    "full_well": (4000.0, 20000.0),
    "read_noise": (0.3, 2.0),
}


def projector_period_for(rig: Rig, camera_period_px: float, radius: float) -> float:
    """Projector period (px) whose fringes are ``camera_period_px`` wide in the camera on the rim."""
    p = np.array([radius, 0.0, 0.0])
    t = np.array([0.0, 0.05, 0.0])
    cam = np.linalg.norm(rig.camera.project(p + t) - rig.camera.project(p)) / 0.05
    proj = abs(rig.projector.project(p + t)[0] - rig.projector.project(p)[0]) / 0.05
    return float(camera_period_px * proj / cam)


def random_optics(rng: np.random.Generator) -> Optics:
    """Photometry drawn from :data:`RANGES` (albedo, power, ambient, gammas, defocus, noise), in that order."""
    keys = ("albedo", "projector_power", "ambient", "projector_gamma", "camera_gamma", "camera_defocus_px",
            "projector_defocus_px", "full_well", "read_noise")
    return Optics(**{k: float(rng.uniform(*RANGES[k])) for k in keys})


def random_scene(
    rng: np.random.Generator, gear: GearSpec, width: int, height: int,
    camera_period_px: tuple[float, float] | None = None,
) -> tuple[Rig, Optics, GearSpec, float]:
    """A random rig aimed at a randomly scaled copy of ``gear``, random optics and fringe period.

    ``camera_period_px`` (LO, HI) widens the fringe period in the camera, drawn log-uniformly (dense
    fringes of large gears on short-period rigs); None draws it uniformly from :data:`RANGES`. Either
    way it is the last draw, so the rest of the scene is the same for a seed.
    """

    def u(key: str) -> float:
        lo, hi = RANGES[key]
        return float(rng.uniform(lo, hi))

    g = gear.model_copy(
        update={
            "module": round(gear.module * u("module_scale"), 3),
            "pressure_angle_deg": u("pressure_angle_deg"),
        }
    )
    g = GearSpec(**g.model_dump())  # re-validate
    field = u("teeth_in_view") * g.pitch_angle * g.pitch_radius
    rig = default_rig(
        width,
        height,
        working_radius=g.pitch_radius,
        standoff=u("standoff_mm"),
        field_mm=field,
        triangulation_deg=u("triangulation_deg") * (1 if rng.random() < 0.5 else -1),
        elevation_deg=u("elevation_deg"),
        projector_field_mm=field * 1.4,
    )
    optics = random_optics(rng)
    if camera_period_px is None:
        cam_period = u("camera_period_px")
    else:
        lo, hi = camera_period_px
        cam_period = float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
    period = projector_period_for(rig, cam_period, g.pitch_radius)
    return rig, optics, g, period


# --- view geometries ---------------------------------------------------------------------------
View = Literal["radial", "side", "oblique", "face"]
VIEWS: tuple[View, ...] = ("radial", "side", "oblique", "face")


def view_rig(
    width: int,
    height: int,
    gear: GearSpec,
    *,
    view: View,
    angle_deg: float = 0.0,
    standoff: float = 160.0,
    field_mm: float = 26.0,
    triangulation_deg: float = 24.0,
    projector_field_mm: float | None = None,
) -> Rig:
    """A rig looking at ``gear``'s rim from one of four views, fringes across the camera columns.

    ``radial``: from outside the rim, ``angle_deg`` of elevation (the default rig's view).
    ``side``: in the plane normal to the axis, ``angle_deg`` (40-80) around from radial, so the
    camera sees the flanks facing it side-on. ``oblique``: from above the face edge at the pitch
    circle, ``angle_deg`` (30-60) of elevation. ``face``: along the axis onto the face at the pitch
    circle, tilted ``angle_deg`` towards the rim; only the tooth outline moves as the gear turns.
    The projector sits ``triangulation_deg`` around the target about the camera's up axis (so the
    phase varies along camera columns), both at ``standoff`` mm; intrinsics and distortion are
    the default rig's (:func:`gearscan.core.rig.default_rig` with the same field and stand-off).
    """
    if view not in VIEWS:
        raise ValueError(f"view: expected one of {VIEWS}, got {view!r}")
    a = math.radians(angle_deg)
    r, top = gear.pitch_radius, gear.face_width / 2
    axis, radial = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    if view == "radial":
        target, look, up = np.array([r, 0, 0.0]), np.array([math.cos(a), 0, math.sin(a)]), axis
    elif view == "side":
        target, look, up = np.array([r, 0, 0.0]), np.array([math.cos(a), math.sin(a), 0]), axis
    elif view == "oblique":
        target, look, up = np.array([r, 0, top]), np.array([math.cos(a), 0, math.sin(a)]), axis
    else:
        target, look, up = np.array([r, 0, top]), np.array([math.sin(a), 0, math.cos(a)]), radial
    base = default_rig(width, height, working_radius=r, standoff=standoff, field_mm=field_mm,
                       triangulation_deg=triangulation_deg, projector_field_mm=projector_field_mm or 1.4 * field_mm)
    cam_t = look_at(target + standoff * look, target, up)
    cam_up = -cam_t[1, :3]  # the camera's image-up axis in world coordinates
    proj_dir = rotation_about(cam_up, math.radians(triangulation_deg)) @ look
    proj_t = look_at(target + standoff * proj_dir, target, cam_up)
    return replace(base, camera=replace(base.camera, T_from_world=cam_t),
                   projector=replace(base.projector, T_from_world=proj_t), name=f"{view} view")


def projector_period_for_surface(surface: Surface, camera_period_px: float) -> float:
    """Projector period (px) whose fringes are ``camera_period_px`` wide (median) where the camera sees them lit.

    Measured from the gradient of the projector column over the lit pixels, so it holds for any
    view (:func:`projector_period_for` assumes the radial one).
    """
    if not camera_period_px > 0:
        raise ValueError(f"camera_period_px must be > 0, got {camera_period_px}")
    gy, gx = np.gradient(surface.u_proj)
    g = np.hypot(gx, gy)[surface.lit]
    g = g[np.isfinite(g) & (g > 0)]
    if g.size == 0:
        raise ValueError("projector_period_for_surface: no lit pixel with a finite projector-column gradient")
    return float(camera_period_px * np.median(g))


def aim_point(rig: Rig) -> np.ndarray:
    """Where the camera's and the projector's optical axes pass closest (midpoint): the rig's target."""
    p1, d1 = rig.camera.center_world, rig.camera.T_world_from[:3, 2]
    p2, d2 = rig.projector.center_world, rig.projector.T_world_from[:3, 2]
    w = p1 - p2
    b = float(d1 @ d2)
    den = 1.0 - b * b
    if den < 1e-12:
        raise ValueError("aim_point: camera and projector axes are parallel")
    s = (b * (d2 @ w) - (d1 @ w)) / den
    t = ((d2 @ w) - b * (d1 @ w)) / den
    return (p1 + s * d1 + p2 + t * d2) / 2


def balance_projector_power(rig: Rig, optics: Optics) -> Optics:
    """Scale the projector power so the renderer's falloff factor is 1 at the rig's target.

    The twin scales irradiance by ``(d0/d)^2`` with ``d0`` the projector's distance to the rotation
    axis: a projector above the face (small ``d0``) leaves the target dim, one far off the axis of a
    large gear (``d0`` > ``d``) saturates it (2B/S up to 1.3 on the default rig with a 69-tooth
    module-2 gear). A user sets the exposure for the target, so the power is divided by that
    factor (capped at 4, the Optics limit).
    """
    c = rig.projector.center_world
    factor = (np.linalg.norm(c[:2]) / np.linalg.norm(c - aim_point(rig))) ** 2
    return optics.model_copy(update={"projector_power": float(min(4.0, optics.projector_power / factor))})


VIEW_RANGES = {  # the training range of random_view_scene (any view; radial RANGES for the rest)
    "camera_period_px": (5.0, 60.0),  # log-uniform: dense fringes on flanks turning away, wide ones
    "module_mm": (0.5, 5.0),          # log-uniform
    "teeth_in_view": (2.0, 8.0),
    "view_angle_deg": {"radial": (-8.0, 8.0), "side": (40.0, 75.0), "oblique": (30.0, 60.0), "face": (0.0, 12.0)},
}


def random_view_scene(
    rng: np.random.Generator, gear: GearSpec, width: int, height: int
) -> tuple[Rig, Optics, GearSpec, float]:
    """A random rig from any of the four views (:func:`view_rig`) aimed at ``gear`` resized to a
    random module, random optics, and a projector period giving a random camera fringe period.

    Stand-off, triangulation and elevation stay in :data:`RANGES` (the radial training ranges), so
    the test family ``radial-wide`` stays outside them; view, module, teeth in view and fringe
    period span what users bring (:data:`VIEW_RANGES`). The camera period is the median over the
    lit pixels of the first pose, so it holds for any view.
    """
    from gearscan.twin.render import TwinRenderer

    def log_u(lo: float, hi: float) -> float:
        return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))

    view = VIEWS[int(rng.integers(len(VIEWS)))]
    m = round(log_u(*VIEW_RANGES["module_mm"]), 3)
    root_d = m * (gear.teeth - 2.5)
    g = GearSpec(**{**gear.model_dump(), "module": m, "pressure_angle_deg": float(rng.uniform(*RANGES["pressure_angle_deg"])),
                    "face_width": float(np.clip(10 * m, 4.0, 40.0)), "bore": round(min(10.0, 0.5 * root_d), 3)})
    field = float(rng.uniform(*VIEW_RANGES["teeth_in_view"])) * g.pitch_angle * g.pitch_radius
    tri = float(rng.uniform(*RANGES["triangulation_deg"])) * (1 if rng.random() < 0.5 else -1)
    rig = view_rig(width, height, g, view=view, angle_deg=float(rng.uniform(*VIEW_RANGES["view_angle_deg"][view])),
                   standoff=float(rng.uniform(*RANGES["standoff_mm"])), field_mm=field, triangulation_deg=tri)
    optics = balance_projector_power(rig, random_optics(rng))
    surface = TwinRenderer(rig, g, optics).surface(0.0)
    period = projector_period_for_surface(surface, log_u(*VIEW_RANGES["camera_period_px"]))
    return rig, optics, g, period
