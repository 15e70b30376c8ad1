"""Test-split scene families: gears and rigs a user would bring, drawn from fixed test seeds.

Each family turns a seed of the test split (:mod:`gearscan.twin.splits`) into a scene (rig,
optics, gear, fringe period) that the twin renders on the fly, so the test data never sits on
disk and cannot leak into training:

- ``default``: the product's default rig (:func:`gearscan.core.rig.default_rig`, default optics,
  projector period 40 px) with test gears (module 2, the module it was designed for).

All families set the projector power for the target
(:func:`~gearscan.twin.randomize.balance_projector_power`), as a user sets the exposure: without
it the twin's falloff saturates large gears on the default rig.
- ``radial-wide``: radial views outside the training ranges of :data:`~gearscan.twin.randomize.RANGES`
  where it matters (stand-off 80-120 or 220-320 mm, triangulation 8-15 or 32-40 deg, elevation
  +-15 deg, 2-8 teeth in view, resolutions 192-320 px).
- ``side``, ``oblique``, ``face``: the other views of :func:`~gearscan.twin.randomize.view_rig`.

Every family except ``default`` draws the camera fringe period log-uniformly in 5-60 px (the
median over the lit pixels; training saw 12-40), the module log-uniformly in 0.5-5 mm (training:
1.5-3) and the tooth count among the test split's (10-80); photometry comes from the training
ranges (:func:`~gearscan.twin.randomize.random_optics`), so what changes is geometry.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from gearscan.core.gear import GearSpec
from gearscan.core.rig import Rig, default_rig
from gearscan.twin.randomize import (
    View,
    balance_projector_power,
    projector_period_for_surface,
    random_optics,
    view_rig,
)
from gearscan.twin.render import Optics, RenderError, TwinRenderer
from gearscan.twin.splits import SPLITS

FAMILIES: tuple[str, ...] = ("default", "radial-wide", "side", "oblique", "face")
SEED_BLOCK = 1000  # test seeds per family: family k owns test seeds k*1000 .. k*1000+999
RESOLUTIONS = ((192, 192), (256, 192), (256, 256), (320, 240))
CAMERA_PERIOD_PX = (5.0, 60.0)
MODULE_MM = (0.5, 5.0)
MIN_MASK_SHARE = 0.03  # a scene whose truth mask covers less of the image is redrawn
_ANGLE_DEG: dict[View, tuple[float, float]] = {
    "radial": (-15.0, 15.0), "side": (40.0, 75.0), "oblique": (30.0, 60.0), "face": (0.0, 12.0),
}


@dataclass(frozen=True)
class FamilyScene:
    """One test scene: what to render, where it comes from, and its renderer (built once)."""

    name: str
    family: str
    seed: int
    rig: Rig
    optics: Optics
    gear: GearSpec
    period_px: float  # projector period
    params: tuple[tuple[str, float | str], ...]  # the drawn parameters, for the report
    renderer: TwinRenderer = field(repr=False, compare=False)


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _either(rng: np.random.Generator, low: tuple[float, float], high: tuple[float, float]) -> float:
    """Uniform in ``low`` or in ``high`` (equal odds): values on both sides of a training range."""
    lo, hi = low if rng.random() < 0.5 else high
    return float(rng.uniform(lo, hi))


def draw_gear(rng: np.random.Generator, module: float | None = None, teeth: int | None = None) -> GearSpec:
    """A gear with a test-split tooth count (or ``teeth``); module log-uniform in 0.5-5 mm unless given."""
    teeth = int(rng.choice(sorted(SPLITS["test"].teeth))) if teeth is None else int(teeth)
    m = round(_log_uniform(rng, *MODULE_MM), 3) if module is None else module
    root_d = m * (teeth - 2.5)
    return GearSpec(teeth=teeth, module=m, pressure_angle_deg=float(rng.uniform(17.5, 25.0)),
                    face_width=float(np.clip(10 * m, 4.0, 40.0)), bore=round(min(10.0, 0.5 * root_d), 3))


DEFAULT_RIG_MODULE = 2.0  # the product's default rig is set up for module-2 gears
DEFAULT_RIG_PERIOD_PX = 40.0  # its projector fringe period


def default_rig_scene(gear: GearSpec, size: tuple[int, int] = (256, 256)) -> tuple[Rig, Optics]:
    """The product's default rig aimed at ``gear`` (working radius at its pitch circle), balanced optics."""
    rig = default_rig(*size, working_radius=gear.pitch_radius)
    return rig, balance_projector_power(rig, Optics())


def _default_draw(rng: np.random.Generator, size: tuple[int, int]) -> tuple[Rig, Optics, GearSpec, float | None, dict]:
    gear = draw_gear(rng, module=DEFAULT_RIG_MODULE)
    rig, optics = default_rig_scene(gear, size)
    return rig, optics, gear, None, {"teeth": gear.teeth, "module": gear.module}


def _view_draw(view: View, wide: bool) -> Callable:
    def draw(rng: np.random.Generator, size: tuple[int, int]) -> tuple[Rig, Optics, GearSpec, float | None, dict]:
        gear = draw_gear(rng)
        if wide:  # outside the training stand-offs and triangulation angles, both sides
            standoff = _either(rng, (80.0, 120.0), (220.0, 320.0))
            tri = _either(rng, (8.0, 15.0), (32.0, 40.0))
        else:
            standoff = float(rng.uniform(80.0, 320.0))
            tri = float(rng.uniform(8.0, 40.0))
        tri *= 1 if rng.random() < 0.5 else -1
        angle = float(rng.uniform(*_ANGLE_DEG[view]))
        teeth_in_view = float(rng.uniform(2.0, 8.0))
        w, h = RESOLUTIONS[int(rng.integers(len(RESOLUTIONS)))]
        cam_period = _log_uniform(rng, *CAMERA_PERIOD_PX)
        field_mm = teeth_in_view * gear.pitch_angle * gear.pitch_radius
        rig = view_rig(w, h, gear, view=view, angle_deg=angle, standoff=standoff, field_mm=field_mm,
                       triangulation_deg=tri)
        optics = balance_projector_power(rig, random_optics(rng))
        params = {"teeth": gear.teeth, "module": gear.module, "view_angle_deg": round(angle, 1),
                  "standoff_mm": round(standoff, 1), "triangulation_deg": round(tri, 1),
                  "teeth_in_view": round(teeth_in_view, 2), "resolution": f"{w}x{h}",
                  "camera_period_px": round(cam_period, 1)}
        return rig, optics, gear, cam_period, params

    return draw


_DRAWS: dict[str, Callable] = {
    "default": _default_draw,
    "radial-wide": _view_draw("radial", wide=True),
    "side": _view_draw("side", wide=False),
    "oblique": _view_draw("oblique", wide=False),
    "face": _view_draw("face", wide=False),
}


def family_seed(family: str, index: int) -> int:
    """The test seed of scene ``index`` of ``family`` (disjoint blocks per family)."""
    if family not in FAMILIES:
        raise ValueError(f"family: expected one of {FAMILIES}, got {family!r}")
    if not 0 <= index < SEED_BLOCK:
        raise ValueError(f"index: expected 0..{SEED_BLOCK - 1}, got {index}")
    return SPLITS["test"].seed(FAMILIES.index(family) * SEED_BLOCK + index)


def make_scene(family: str, seed: int, size: tuple[int, int] = (256, 256), attempts: int = 20) -> FamilyScene:
    """The scene of ``family`` drawn from test seed ``seed`` (redrawn until the gear is seen).

    ``size`` is the resolution of the ``default`` family (the others draw their own).
    """
    if family not in _DRAWS:
        raise ValueError(f"family: expected one of {FAMILIES}, got {family!r}")
    SPLITS["test"].check(rig_family=family, seed=seed)
    rng = np.random.default_rng([seed, 7919])
    last = ""
    for _ in range(attempts):
        rig, optics, gear, cam_period, params = _DRAWS[family](rng, size)
        SPLITS["test"].check(teeth=gear.teeth)
        try:
            renderer = TwinRenderer(rig, gear, optics)
        except RenderError as exc:
            last = str(exc)
            continue
        surface = renderer.surface(0.0)
        period = DEFAULT_RIG_PERIOD_PX if cam_period is None else projector_period_for_surface(surface, cam_period)
        share = float(renderer.truth(surface, period).mask.mean())
        if share < MIN_MASK_SHARE:
            last = f"truth mask covers {100 * share:.1f}% of the image"
            continue
        return FamilyScene(f"{family}#{seed} z={gear.teeth} m={gear.module:g}", family, seed, rig, optics, gear,
                         period, tuple(params.items()), renderer)
    raise RenderError(f"family {family!r}, seed {seed}: no visible scene in {attempts} draws ({last})")


def family_scenes(family: str, count: int, size: tuple[int, int] = (256, 256)) -> list[FamilyScene]:
    """The first ``count`` scenes of ``family`` (fixed test seeds: the same scenes every run)."""
    return [make_scene(family, family_seed(family, i), size) for i in range(count)]
