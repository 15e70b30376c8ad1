"""Domain randomisation: rigs, optics and gears that differ the way real set-ups do.

Used to render training data that generalises to rigs and gears the network never saw.
The ranges are the model's validity range (stated in its model card).
"""

from __future__ import annotations

import numpy as np

from gearscan.rig import Rig, default_rig
from gearscan.twin.gear import GearSpec
from gearscan.twin.render import Optics

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


def random_scene(
    rng: np.random.Generator, gear: GearSpec, width: int, height: int
) -> tuple[Rig, Optics, GearSpec, float]:
    """A random rig aimed at a randomly scaled copy of ``gear``, random optics and fringe period."""

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
    optics = Optics(
        albedo=u("albedo"),
        projector_power=u("projector_power"),
        ambient=u("ambient"),
        projector_gamma=u("projector_gamma"),
        camera_gamma=u("camera_gamma"),
        camera_defocus_px=u("camera_defocus_px"),
        projector_defocus_px=u("projector_defocus_px"),
        full_well=u("full_well"),
        read_noise=u("read_noise"),
    )
    period = projector_period_for(rig, u("camera_period_px"), g.pitch_radius)
    return rig, optics, g, period
