"""As-built twin gears against the geometry of each injected defect (not the mesher's own output).

The camera of the default rig looks at tooth 0 on +x; tooth 1's right (-theta) flank and
its right tip corner face it. Points are ray-cast hits (lit or not), brought into the gear
frame and compared with the nominal CAD mesh moved the way the defect says.
"""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
from pydantic import ValidationError
from typer.testing import CliRunner

from gearscan.core.gear import GearSpec, involute
from gearscan.core.rig import rot_z
from gearscan.twin.defects import Chip, DefectError, GearDefects, Wear, true_mesh
from gearscan.twin.render import Optics, TwinRenderer

UM = 1e-3  # mm
TOL = 1 * UM  # chords of the involute polygon and float32 ray hits stay below this


@pytest.fixture(scope="module")
def rig128():
    from gearscan.core.rig import default_rig

    return default_rig(128, 128)


def _points(rig, gear, defects, angle=0.0):
    """Ray-cast hits of the as-built gear at turntable ``angle``, in the gear frame ``(N, 3)``."""
    surf = TwinRenderer(rig, gear, Optics().noise_free(), defects=defects).surface(angle)
    return _to_gear(rig, surf.points_cam[surf.hit], angle)


def _to_gear(rig, points_cam, angle):
    t = rot_z(-angle) @ rig.camera.T_world_from
    return points_cam @ t[:3, :3].T + t[:3, 3]


def _distance(mesh, pts, signed=False):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    q = o3d.core.Tensor(np.asarray(pts, np.float32))
    return (scene.compute_signed_distance(q) if signed else scene.compute_distance(q)).numpy()


def _tooth_and_side(gear, pts):
    """Nearest tooth index and side (-1 right, +1 left of its centre line) of each point."""
    th = np.arctan2(pts[:, 1], pts[:, 0])
    k = np.round(th / gear.pitch_angle)
    return k.astype(int) % gear.teeth, np.sign(th - k * gear.pitch_angle)


def _on_flank(gear, pts):
    """Points on an involute, away from its ends and the faces (nearer to those than to it)."""
    r = np.hypot(pts[:, 0], pts[:, 1])
    inside = np.abs(pts[:, 2]) < gear.face_width / 2 - 0.1
    return inside & (r > max(gear.base_radius, gear.root_radius) + 0.3) & (r < gear.tip_radius - 0.2)


def _rotate(pts, angle):
    out = pts.copy()
    out[:, :2] = pts[:, :2] @ rot_z(angle)[:2, :2].T
    return out


def _closed(mesh) -> bool:
    """Every directed edge once and its reverse once: closed and consistently oriented."""
    t = np.asarray(mesh.triangles)
    directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    keys = directed[:, 0].astype(np.int64) * (1 << 32) + directed[:, 1]
    rev = directed[:, 1].astype(np.int64) * (1 << 32) + directed[:, 0]
    return np.unique(keys).size == keys.size and bool(np.isin(rev, keys).all())


def _volume(mesh) -> float:
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    return float(np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])).sum() / 6)


def _quality(mesh) -> np.ndarray:
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    e = np.linalg.norm(v[t] - v[np.roll(t, 1, axis=1)], axis=2)
    area = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    return 4 * math.sqrt(3) * area / (e**2).sum(axis=1)  # 1 for equilateral


def _xi(gear, r):
    """Roll length fraction along the involute: 0 at its start, 1 at the tip (the defects' definition)."""
    rb = gear.base_radius
    length = lambda x: np.sqrt(np.maximum(np.square(x) - rb**2, 0))  # noqa: E731
    return (length(r) - length(max(rb, gear.root_radius))) / (length(gear.tip_radius) - length(max(rb, gear.root_radius)))


def _chip_corner(gear, size, tooth, side, n=2000):
    """The chipped piece's section ``(n, 2)``: involute flank from the cut up to the tip corner, tip
    arc back to the cut, for a tooth centred at ``tooth * pitch``; and the cut's two ends."""
    ra = gear.tip_radius
    r = np.linspace(ra - size, ra, n)
    th_flank = gear.half_angle(r)
    th_tip = np.linspace(gear.half_angle(ra), gear.half_angle(ra) - size / ra, n)
    polar = np.concatenate([np.stack([r, th_flank], 1), np.stack([np.full(n, ra), th_tip], 1)[1:]])
    ang = tooth * gear.pitch_angle + side * polar[:, 1]
    return np.stack([polar[:, 0] * np.cos(ang), polar[:, 0] * np.sin(ang)], 1)


def _polygon_area(xy):
    return 0.5 * abs(np.dot(xy[:, 0], np.roll(xy[:, 1], -1)) - np.dot(xy[:, 1], np.roll(xy[:, 0], -1)))


# --- rendered geometry ------------------------------------------------------------------------
def test_eccentric_gear_turns_about_the_table_axis(rig128, gear, gear_mesh):
    e, phi = 50 * UM, math.radians(30)
    d = GearDefects(eccentricity_um=50, eccentricity_deg=30)
    moved = copy.deepcopy(gear_mesh).translate((e * math.cos(phi), e * math.sin(phi), 0))
    for angle in (0.0, math.pi / 2):  # other teeth in view: the centre went round with the gear
        pts = _points(rig128, gear, d, angle)
        assert len(pts) > 5000
        assert np.abs(_distance(moved, pts)).max() < TOL
        off = _distance(gear_mesh, pts)
        assert off.max() < e + TOL
        assert np.percentile(off, 75) > 0.3 * e


def test_pitch_error_moves_one_tooth_along_the_pitch_circle(rig128, gear, gear_mesh):
    u = 30 * UM
    pts = _points(rig128, gear, GearDefects(pitch_errors_um={1: 30}))
    tooth, _ = _tooth_and_side(gear, pts)
    one, others = pts[tooth == 1], pts[tooth != 1]
    assert len(one) > 1000 and len(others) > 5000
    # tooth 1 is the nominal tooth turned by u / r_pitch; the others did not move
    assert _distance(gear_mesh, _rotate(one, -u / gear.pitch_radius)).max() < TOL
    assert _distance(gear_mesh, others).max() < TOL
    # a turned involute lies r_b * turn = u cos(alpha) from the nominal one, all along the flank
    flank = one[_on_flank(gear, one)]
    assert len(flank) > 500
    np.testing.assert_allclose(_distance(gear_mesh, flank), u * math.cos(gear.pressure_angle), atol=TOL)


def test_chip_removes_the_chipped_volume_only(rig128, gear, gear_mesh):
    size, z0, z1 = 0.5, -4.0, 4.0
    d = GearDefects(chips=(Chip(tooth=1, side="right", size_mm=size, z_mm=(z0, z1)),))
    corner = _chip_corner(gear, size, tooth=1, side=-1)
    a, b = corner[0], corner[-1]  # the cut: flank point and tip-land point

    def in_chip(p, margin):
        """Beyond the cut (towards the corner), inside the z range, with ``margin`` mm of slack."""
        normal = np.array([a[1] - b[1], b[0] - a[0]]) / np.linalg.norm(b - a)
        normal *= np.sign((corner[len(corner) // 2] - a) @ normal)
        return ((p[:, :2] - a) @ normal > -margin) & (p[:, 2] > z0 - margin) & (p[:, 2] < z1 + margin)

    renderer = TwinRenderer(rig128, gear, Optics().noise_free(), defects=d)
    surf, nominal = renderer.surface(0.0), TwinRenderer(rig128, gear, Optics().noise_free(), mesh=gear_mesh).surface(0.0)
    both = surf.hit & nominal.hit
    p_chip, p_nom = _to_gear(rig128, surf.points_cam[both], 0.0), _to_gear(rig128, nominal.points_cam[both], 0.0)
    changed = np.linalg.norm(p_chip - p_nom, axis=1) > TOL
    assert changed.sum() > 20  # the chip is in view ...
    assert in_chip(p_nom[changed], TOL).all()  # ... and only points of the chipped piece went
    off = _distance(gear_mesh, p_chip) > TOL
    assert in_chip(p_chip[off], TOL).all()  # new surface (the cut) lies in the chipped piece too
    assert not (surf.hit & ~nominal.hit).any()  # nothing appears where the nominal gear was not
    # the mesh lost exactly the piece's volume, and stays closed
    mesh = d.mesh(gear)
    assert _closed(mesh)
    piece = _polygon_area(corner) * (z1 - z0)
    assert _volume(gear_mesh) - _volume(mesh) == pytest.approx(piece, rel=2e-3)


def test_worn_flank_loses_its_wear_depth_along_the_normal(rig128, gear, gear_mesh):
    depth = 40 * UM
    pts = _points(rig128, gear, GearDefects(wear=(Wear(tooth=1, side="right", depth_um=40),)))
    tooth, side = _tooth_and_side(gear, pts)
    worn = (tooth == 1) & (side < 0) & _on_flank(gear, pts)
    assert worn.sum() > 500
    r = np.hypot(pts[worn, 0], pts[worn, 1])
    expect = -depth * np.sin(np.pi * _xi(gear, r))  # signed: inside the nominal tooth
    np.testing.assert_allclose(_distance(gear_mesh, pts[worn], signed=True), expect, atol=TOL)
    assert _distance(gear_mesh, pts[~((tooth == 1) & (side < 0))]).max() < TOL


def test_true_module_sets_the_tip_circle(rig128):
    nominal = GearSpec(module=2.0)
    pts = _points(rig128, nominal, GearDefects(module=2.06))
    r = np.hypot(pts[:, 0], pts[:, 1])
    tip = 2.06 * (20 + 2) / 2  # m (z + 2 h_a*) / 2
    assert r.max() == pytest.approx(tip, abs=TOL)
    assert (r > tip - 0.01).sum() > 100  # the tip lands are in view, at the as-built radius
    assert r.min() > 2.06 * (20 - 2.5) / 2 - TOL  # and nothing below the as-built root circle


# --- the mesh -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def all_defects():
    return GearDefects(
        pitch_errors_um={1: 30, 7: -12},
        eccentricity_um=50,
        eccentricity_deg=-40,
        chips=(Chip(tooth=2, side="right", size_mm=0.5, z_mm=(-4, 4)), Chip(tooth=2, side="left", size_mm=0.3, z_mm=(4, 10)),
               Chip(tooth=9, size_mm=0.3)),  # away from the worn flanks: their pieces would overlap
        wear=(Wear(tooth=1, side="right", depth_um=40), Wear(tooth=3, side="left", depth_um=25)),
    )


def test_defective_mesh_is_closed_with_the_volume_of_its_defects(gear, gear_mesh, all_defects):
    mesh = all_defects.mesh(gear)
    assert _closed(mesh)
    # turning teeth and moving the axis keep the volume; wear takes b * integral(depth ds) along
    # the involute (ds = r_b t dt at roll angle t); each chip its piece
    rb = gear.base_radius
    t = np.linspace(math.sqrt(max((gear.root_radius / rb) ** 2 - 1, 0)), math.sqrt((gear.tip_radius / rb) ** 2 - 1), 20001)
    shape = np.trapezoid(np.sin(np.pi * (t - t[0]) / (t[-1] - t[0])) * rb * t, t)
    wear = gear.face_width * shape * sum(w.depth_um * UM for w in all_defects.wear)
    chips = sum(
        _polygon_area(_chip_corner(gear, c.size_mm, c.tooth, 1)) * (lambda z: z[1] - z[0])(c.z_range(gear.face_width))
        for c in all_defects.chips
    )
    assert _volume(gear_mesh) - _volume(mesh) == pytest.approx(wear + chips, rel=2e-3)


def test_defective_mesh_keeps_triangle_quality(gear, gear_mesh, all_defects):
    q, q0 = _quality(all_defects.mesh(gear)), _quality(gear_mesh)
    assert np.percentile(q, 5) > 0.02
    assert q.min() > 0.5 * q0.min()


def test_profile_slope_and_crown_offset_every_flank(gear, gear_mesh):
    """A normal offset d(xi) on 2 z flanks adds b * 2z * integral(d ds) of material."""
    d = GearDefects(profile_slope_um=8, profile_crown_um=-5)
    rb = gear.base_radius
    t = np.linspace(math.sqrt(max((gear.root_radius / rb) ** 2 - 1, 0)), math.sqrt((gear.tip_radius / rb) ** 2 - 1), 20001)
    xi = (t - t[0]) / (t[-1] - t[0])
    offset = np.trapezoid((8 * xi - 5 * 4 * xi * (1 - xi)) * UM * rb * t, t)
    mesh = d.mesh(gear)
    assert _closed(mesh)
    assert _volume(mesh) - _volume(gear_mesh) == pytest.approx(gear.face_width * 2 * gear.teeth * offset, rel=5e-3)


def test_pressure_angle_change_keeps_pitch_thickness(gear):
    """A base-circle error (profile slope): same thickness on the pitch circle, other involute."""
    built = GearDefects(pressure_angle_deg=20.5).as_built(gear)
    assert built.pitch_thickness == pytest.approx(gear.pitch_thickness)
    r = gear.pitch_radius + 0.8
    a, a_built = math.acos(gear.base_radius / r), math.acos(built.base_radius / r)
    assert built.thickness_at(r) - gear.thickness_at(r) == pytest.approx(
        2 * r * (involute(a) - involute(a_built) + involute(built.pressure_angle) - involute(gear.pressure_angle))
    )


# --- the answer and the recording ---------------------------------------------------------------
def test_truth_states_pitch_and_runout(gear, all_defects):
    truth = all_defects.truth(gear)
    assert json.loads(json.dumps(truth)) == truth
    right, left = np.array(truth["flank_position_um"]["right"]), np.array(truth["flank_position_um"]["left"])
    assert left[1] == pytest.approx(30) and left[7] == pytest.approx(-12) and left[0] == 0
    # tooth 1's worn right flank sits deeper by the wear at the pitch circle, along the circle
    along = math.sin(math.pi * _xi(gear, gear.pitch_radius)) * gear.pitch_radius / gear.base_radius
    assert right[1] == pytest.approx(30 + 40 * along)
    assert left[3] == pytest.approx(-25 * along)  # worn left flank of tooth 3: towards -theta
    assert truth["single_pitch_um"]["left"][1] == pytest.approx(30) and truth["single_pitch_um"]["left"][2] == pytest.approx(-30)
    assert truth["total_cumulative_pitch_um"]["left"] == pytest.approx(30 + max(12, 25 * along))
    # a ball in each gap sees the centre offset: range 2 e cos(half a pitch) at most
    assert truth["runout_from_eccentricity_um"] <= 100 and truth["runout_from_eccentricity_um"] > 100 * math.cos(math.radians(9)) - 1
    assert truth["chipped_teeth"] == [2, 9] and GearDefects(**truth["defects"]) == all_defects


def test_recording_states_the_cad_and_holds_the_as_built_truth(tmp_path, rig128, gear):
    from gearscan.core.recording import RecordingReader
    from gearscan.twin.recordings import render_recording

    d = GearDefects(module=2.03, eccentricity_um=50, pitch_errors_um={1: 30})
    out = render_recording(tmp_path / "rec", rig=rig128, gear=gear, defects=d, optics=Optics().noise_free(), motion="uniform:5", bursts=1)
    reader = RecordingReader(out)
    assert reader.gear == gear  # the CAD the user believes
    assert GearDefects.from_meta(reader.meta) == d and reader.meta["truth"]["gear"]["module"] == 2.03
    built = true_mesh(gear, d)
    for i in range(len(reader)):
        tr = reader.truth(i)
        pts = _to_gear(rig128, tr["points"][tr["mask"]].astype(np.float64), float(tr["angle"]))
        assert _distance(built, pts).max() < 2 * TOL  # float32 in the npz
        assert np.median(_distance(gear.mesh(), pts)) > 0.02  # 30 µm bigger in radius than the CAD


# --- validation -----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "kwargs,name",
    [
        ({"eccentricity_um": -1}, "eccentricity_um"),
        ({"pitch_errors_um": {3: 900}}, "pitch_errors_um.3"),
        ({"module": 0}, "module"),
        ({"chips": [{"tooth": 1, "size_mm": 9}]}, "chips.0.size_mm"),
        ({"wear": [{"tooth": 1, "depth_um": 20, "side": "top"}]}, "wear.0.side"),
    ],
)
def test_bad_fields_are_named(kwargs, name):
    with pytest.raises(ValidationError) as err:
        GearDefects(**kwargs)
    assert name in str(err.value).replace("\n", ".").replace(" ", "")


@pytest.mark.parametrize(
    "defects,words",
    [
        (GearDefects(pitch_errors_um={20: 5}), ["pitch_errors_um", "0 to 19"]),
        (GearDefects(chips=(Chip(tooth=2, size_mm=1.5),)), ["chips[0].size_mm=1.5", "below"]),
        (GearDefects(chips=(Chip(tooth=2, z_mm=(5, 12)),)), ["chips[0].z_mm", "[-10, 10]"]),
        (GearDefects(chips=(Chip(tooth=2, z_mm=(0, 5)), Chip(tooth=3, z_mm=(5.05, 8)))), ["z_mm", "0.1 mm apart"]),
        (GearDefects(wear=(Wear(tooth=2, depth_um=5), Wear(tooth=2, depth_um=9))), ["wear[1]", "twice"]),
    ],
)
def test_defects_that_do_not_fit_the_gear_are_named(gear, defects, words):
    with pytest.raises(DefectError) as err:
        defects.check(gear)
    assert all(w in str(err.value) for w in words), str(err.value)


def test_cli_renders_a_defective_gear(tmp_path):
    from gearscan.cli import app

    out = tmp_path / "rec"
    args = ["twin", "render", str(out), "--bursts", "1", "--width", "96", "--height", "96", "--motion", "static"]
    defects = ["--eccentricity-um", "50", "--pitch-error", "3:30", "--chip", "1:0.3:right", "--wear", "2:20", "--true-module", "2.06"]
    res = CliRunner().invoke(app, args + defects)
    assert res.exit_code == 0, res.output
    meta = json.loads((out / "recording.json").read_text())
    assert meta["gear"]["module"] == 2.0 and meta["truth"]["gear"]["module"] == 2.06
    assert GearDefects.from_meta(meta) == GearDefects(
        module=2.06, eccentricity_um=50, pitch_errors_um={3: 30}, chips=(Chip(tooth=1, side="right"),), wear=(Wear(tooth=2, depth_um=20),)
    )
    for bad, words in ((["--chip", "1x"], ["--chip", "TOOTH:MM"]), (["--chip", "1:1.5"], ["chips[0].size_mm"])):
        res = CliRunner().invoke(app, [*args[:2], str(tmp_path / "bad"), *args[3:], *bad])
        assert res.exit_code == 2 and all(w in res.output for w in words), res.output


def test_options_add_to_a_defects_file(tmp_path):
    path = tmp_path / "defects.json"
    path.write_text(json.dumps({"eccentricity_um": 20, "pitch_errors_um": {"3": 10}, "chips": [{"tooth": 4}]}))
    d = GearDefects.from_options(path, eccentricity_um=50, pitch_errors=["5:-8"], chips=["7:0.2:right:-2:2"])
    assert d == GearDefects(
        eccentricity_um=50, pitch_errors_um={3: 10, 5: -8}, chips=(Chip(tooth=4), Chip(tooth=7, side="right", size_mm=0.2, z_mm=(-2, 2)))
    )
    assert GearDefects.from_options() is None
    with pytest.raises(DefectError, match="--wear"):
        GearDefects.from_options(wear=["2"])
    with pytest.raises(DefectError, match=r"pitch_errors_um\.5"):
        GearDefects.from_options(pitch_errors=["5:-800"])
