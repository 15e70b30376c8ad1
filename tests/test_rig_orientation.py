"""The rig's fringe orientation from its calibration (gearscan.core.rig.fringe_orientation), checked against
the ray caster's own projector columns and against the per-burst vote on still bursts, where no motion can fool it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gearscan.core.gear import GearSpec
from gearscan.core.patterns import PatternSet
from gearscan.core.rig import (
    FringeOrientation,
    PinholeDevice,
    Rig,
    default_rig,
    fringe_orientation,
    look_at,
)


def rolled(rig: Rig, device: str, deg: float) -> Rig:
    """``rig`` with its camera or projector turned ``deg`` about its own optical axis."""
    dev = getattr(rig, device)
    a = np.radians(deg)
    roll = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    t = dev.T_from_world.copy()
    t[:3] = roll @ t[:3]
    return replace(rig, **{device: replace(dev, T_from_world=t)})


def test_a_device_turned_upside_down_mirrors_the_fringes_and_a_quarter_turn_has_no_orientation():
    rig = default_rig(128, 128)
    assert fringe_orientation(rig) == FringeOrientation("normal", 1.0)
    for device in ("camera", "projector"):
        assert fringe_orientation(rolled(rig, device, 180.0)).orientation == "mirrored"
        assert fringe_orientation(rolled(rig, device, 20.0)).orientation == "normal"
    quarter = fringe_orientation(rolled(rig, "camera", 90.0))
    assert quarter.orientation is None and 0.1 < quarter.rising < 0.9
    assert "no fringe orientation" in quarter.describe()
    assert fringe_orientation(rolled(rig, "camera", 180.0)).describe() == "fringes mirrored (the calibration: 100% of the image)"


@pytest.mark.parametrize("view", ["radial", "side", "oblique", "face"])
def test_every_view_the_twin_trains_on_is_normal(view):
    """The network was trained on these rigs only: their calibration must read as the orientation it knows."""
    from gearscan.twin.randomize import view_rig

    gear = GearSpec(module=2.0, teeth=30)
    for angle in (0.0, 17.0):
        assert fringe_orientation(view_rig(128, 128, gear, view=view, angle_deg=angle)).orientation == "normal"


@pytest.mark.parametrize("turn", [0.0, 180.0])
def test_the_calibration_agrees_with_the_rendered_fringes_and_the_still_burst_vote(turn):
    """Ground truth from the ray caster: the projector column at each lit pixel (``u_proj``) rises along the camera's
    columns on a normal rig and falls on one whose projector hangs upside down; the per-burst vote on a still burst
    (no motion to fool it) says the same as the calibration."""
    from gearscan.inference.predictor import frames_to_tensor, fringe_phase_decreases_along_columns
    from gearscan.twin.render import Optics, TwinRenderer

    gear = GearSpec(module=2.0, teeth=20)
    rig = rolled(default_rig(128, 128, working_radius=gear.pitch_radius), "projector", turn)
    expected = "normal" if turn == 0.0 else "mirrored"
    assert fringe_orientation(rig).orientation == expected
    twin = TwinRenderer(rig, gear, Optics())
    u = twin.surface(0.0).u_proj
    step = np.diff(u, axis=1)
    step = step[np.isfinite(step)]
    assert step.size > 1000
    rising = float(np.mean(step > 0))
    assert (rising > 0.9) if expected == "normal" else (rising < 0.1)
    images, _ = twin.render(0.0, PatternSet.three_step(20.0))
    assert fringe_phase_decreases_along_columns(frames_to_tensor(images[:3], 255)) == (expected == "mirrored")


def _device(eye, target, width: int, height: int, focal: float) -> PinholeDevice:
    k = np.array([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return PinholeDevice(width, height, k, np.zeros(5), look_at(np.asarray(eye, float), np.asarray(target, float),
                                                                np.array([0.0, 0.0, 1.0])))


@pytest.mark.parametrize("toe_deg", [0.0, 0.3, -0.3])
def test_parallel_and_toed_out_rigs_have_an_orientation_and_a_projector_facing_away_has_none(toe_deg):
    """A side-by-side rig whose calibration came out parallel or a little toed-out (axes that never meet in front)
    still reads normal; a projector that faces away from the camera's axis is a RigError, and the Decoder then
    votes per burst instead of failing the run."""
    from gearscan.core.rig import RigError
    from gearscan.inference.decoder import Decoder

    cam = _device([200.0, 0.0, 0.0], [0.0, 0.0, 0.0], 128, 128, 1000.0)
    proj = _device([200.0, 100.0, 0.0], [0.0, 100.0 + 200.0 * np.tan(np.radians(toe_deg)), 0.0], 1280, 800, 5000.0)
    assert fringe_orientation(Rig(cam, proj)).orientation == "normal"
    away = Rig(cam, _device([200.0, 100.0, 0.0], [400.0, 100.0, 0.0], 1280, 800, 5000.0))
    with pytest.raises(RigError, match="nowhere in front of the projector"):
        fringe_orientation(away)
    dec = Decoder(workers=1)
    assert dec.adopt_rig(away) is None and dec.rig_orientation is None and dec.predictor.orientation == "auto"


@pytest.mark.parametrize("bad", [
    "folder", "binary", {"camera.width": "wide"}, {"camera.dist": "x"}, {"turntable": []},
    {"turntable": {"counts_per_rev": "abc"}}, {"projector": [1, 2]},
])
def test_a_broken_rig_file_is_a_rig_error_naming_the_file(tmp_path, bad):
    """Every malformed rig file is a RigError that names it (replay --rig and predict --rig turn it into exit 2)."""
    import json

    from gearscan.core.rig import RigError

    path = tmp_path / "rig.json"
    if bad == "folder":
        path.mkdir()
    elif bad == "binary":
        path.write_bytes(bytes(range(256)))
    else:
        data = default_rig(64, 64).to_json()
        for key, value in bad.items():
            *head, last = key.split(".")
            node = data
            for h in head:
                node = node[h]
            node[last] = value
        path.write_text(json.dumps(data))
    with pytest.raises(RigError, match="rig"):
        Rig.load(path)


def test_a_singular_camera_matrix_is_a_rig_error_and_each_run_counts_its_own_still_bursts():
    """A K whose last row is zero cannot back-project: a RigError the Decoder survives (it votes instead); and
    ``adopt_rig``, a run's start, resets the run's still-burst count that ``summary`` reports."""
    import copy

    from gearscan.core.rig import RigError
    from gearscan.inference.decoder import Decoder

    rig = default_rig(64, 64)
    k = rig.camera.K.copy()
    k[2] = 0.0
    with pytest.raises(RigError, match=r"K: expected \[\[fx, 0, cx\]"):  # a rig file cannot hold one any more
        replace(rig.camera, K=k)
    camera = copy.copy(rig.camera)  # one made past the check, as code that builds a device by hand could
    object.__setattr__(camera, "K", k)
    broken = replace(rig, camera=camera)
    with pytest.raises(RigError, match="singular"):
        fringe_orientation(broken)
    dec = Decoder(workers=1)
    dec.still_bursts = 5  # an earlier run's
    assert dec.adopt_rig(broken) is None and dec.still_bursts == 0 and dec.rig_orientation is None
    assert dec.adopt_rig(rig).orientation == "normal" and dec.summary()["orientation_source"] == "calibration"
