"""Involute gear geometry against textbook formulas (ISO 21771)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from gearscan.core.gear import GearSpec, involute


@pytest.mark.parametrize("teeth,module,alpha", [(12, 2.0, 20.0), (20, 2.0, 20.0), (30, 1.5, 25.0)])
def test_radii(teeth, module, alpha):
    g = GearSpec(teeth=teeth, module=module, pressure_angle_deg=alpha)
    r = module * teeth / 2
    assert g.pitch_radius == pytest.approx(r)
    assert g.base_radius == pytest.approx(r * math.cos(math.radians(alpha)))
    assert g.tip_radius == pytest.approx(r + module)
    assert g.root_radius == pytest.approx(r - 1.25 * module)
    xy = g.outline()
    rad = np.hypot(xy[:, 0], xy[:, 1])
    assert rad.max() == pytest.approx(g.tip_radius, abs=1e-9)
    assert rad.min() == pytest.approx(g.root_radius, abs=1e-9)


def _thickness_from_outline(g: GearSpec, radius: float) -> float:
    """Arc thickness of tooth 0 where the outline crosses ``radius``."""
    xy = g.outline(flank_points=400)
    rad = np.hypot(xy[:, 0], xy[:, 1])
    ang = np.arctan2(xy[:, 1], xy[:, 0])
    near0 = np.abs(ang) < g.pitch_angle / 2
    crossings = []
    for i in np.flatnonzero(near0[:-1] & near0[1:]):
        r0, r1 = rad[i], rad[i + 1]
        if (r0 - radius) * (r1 - radius) < 0:
            t = (radius - r0) / (r1 - r0)
            crossings.append(ang[i] + t * (ang[i + 1] - ang[i]))
    assert len(crossings) == 2, crossings
    return abs(crossings[1] - crossings[0]) * radius


@pytest.mark.parametrize("shift", [0.0, 0.3])
def test_tooth_thickness(shift):
    g = GearSpec(teeth=20, module=2.0, profile_shift=shift)
    s_pitch = g.module * (math.pi / 2 + 2 * shift * math.tan(g.pressure_angle))
    assert g.pitch_thickness == pytest.approx(s_pitch)
    assert _thickness_from_outline(g, g.pitch_radius) == pytest.approx(s_pitch, rel=2e-4)
    # thickness at another radius from the involute function: s_r = 2 r (s/2r + inv(a) - inv(a_r))
    r = g.pitch_radius + 0.6 * g.module
    a_r = math.acos(g.base_radius / r)
    expect = 2 * r * (s_pitch / (2 * g.pitch_radius) + involute(g.pressure_angle) - involute(a_r))
    assert _thickness_from_outline(g, r) == pytest.approx(expect, rel=2e-4)


def test_mesh_is_watertight_with_the_section_volume(gear, gear_mesh):
    # closed and consistently oriented: every directed edge appears once, its reverse once
    t = np.asarray(gear_mesh.triangles)
    directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    keys = directed[:, 0].astype(np.int64) * (1 << 32) + directed[:, 1]
    rev = directed[:, 1].astype(np.int64) * (1 << 32) + directed[:, 0]
    assert np.unique(keys).size == keys.size
    assert np.isin(rev, keys).all()
    xy = gear.outline()
    area = 0.5 * abs(np.dot(xy[:, 0], np.roll(xy[:, 1], -1)) - np.dot(xy[:, 1], np.roll(xy[:, 0], -1)))
    bore_n = max(48, math.ceil(math.pi * gear.bore / (0.5 * gear.module)))
    bore_area = 0.5 * bore_n * (gear.bore / 2) ** 2 * math.sin(2 * math.pi / bore_n)
    v = np.asarray(gear_mesh.vertices)
    volume = np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])).sum() / 6  # divergence theorem
    assert volume == pytest.approx((area - bore_area) * gear.face_width, rel=1e-9)


def test_mesh_triangles_are_not_slivers(gear_mesh):
    v = np.asarray(gear_mesh.vertices)
    t = np.asarray(gear_mesh.triangles)
    e = np.linalg.norm(v[t] - v[np.roll(t, 1, axis=1)], axis=2)
    area = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    quality = 4 * math.sqrt(3) * area / (e**2).sum(axis=1)  # 1 for equilateral
    assert np.percentile(quality, 5) > 0.02


@pytest.mark.parametrize(
    "kwargs,name", [({"teeth": 5}, "teeth"), ({"module": 0}, "module"), ({"bore": 40}, "bore"), ({"pressure_angle_deg": 50}, "pressure_angle_deg")]
)
def test_bad_parameters_name_the_parameter(kwargs, name):
    with pytest.raises(ValidationError) as err:
        GearSpec(**kwargs)
    assert name in str(err.value)
