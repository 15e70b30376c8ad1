"""Rig model: projection, rays, calibration file round trip and errors."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from gearscan.core.rig import CalibrationStatement, Rig, RigError, default_rig


def test_rays_and_projection_are_inverse():
    rig = default_rig(200, 160)
    cam = rig.camera
    rays = cam.pixel_rays()
    pts_cam = rays * 150.0
    pts_w = pts_cam.reshape(-1, 3) @ cam.T_world_from[:3, :3].T + cam.T_world_from[:3, 3]
    uv = cam.project(pts_w).reshape(160, 200, 2)
    u, v = np.meshgrid(np.arange(200), np.arange(160))
    assert np.abs(uv[..., 0] - u).max() < 1e-6
    assert np.abs(uv[..., 1] - v).max() < 1e-6


def test_projection_matches_opencv():
    import cv2

    rig = default_rig()
    cam = rig.camera
    pts = np.random.default_rng(0).uniform([15, -8, -8], [25, 8, 8], (50, 3))
    rvec, _ = cv2.Rodrigues(cam.T_from_world[:3, :3])
    ref, _ = cv2.projectPoints(pts, rvec, cam.T_from_world[:3, 3], cam.K, cam.dist)
    assert np.abs(cam.project(pts) - ref.reshape(-1, 2)).max() < 1e-9


def test_default_rig_geometry():
    rig = default_rig()
    # camera looks at the rim radially from the standoff; optical centre by eq. 20
    assert np.allclose(rig.camera.center_world, [21.0 + 160.0, 0, 0])
    assert rig.baseline_mm == pytest.approx(2 * 160 * np.sin(np.radians(12)), rel=1e-9)
    # the target point projects to the image centre of both devices
    uv = rig.camera.project(np.array([21.0, 0, 0]))
    assert np.allclose(uv, [255.5, 255.5], atol=1e-9)


def test_json_round_trip(tmp_path):
    rig = default_rig(300, 200)
    path = tmp_path / "rig.json"
    rig.save(path)
    back = Rig.load(path)
    assert back.camera.width == 300 and back.camera.height == 200
    assert back.calibration is None and "calibration" not in json.loads(path.read_text())
    # a calibration's stated uncertainty travels with the rig (gearscan calibrate writes it; a recording holds it)
    stated = dataclasses.replace(rig, calibration=CalibrationStatement(1.6, 3.4, 64))
    stated.save(path)
    assert Rig.load(path).calibration == CalibrationStatement(1.6, 3.4, 64)
    assert "+-3.2 um (k = 2) on a 20 mm radius" in stated.calibration.line()
    # a rig file gearscan calibrate wrote before the key existed: the statement read from its calibration report
    data = rig.to_json() | {"calibration_report": {"uncertainty": {"stated": True, "radius_um": 1.6,
                                                                     "shape_rms_um_p95": 3.4, "draws": 64}}}
    path.write_text(json.dumps(data))
    assert Rig.load(path).calibration == CalibrationStatement(1.6, 3.4, 64)
    data["calibration_report"]["uncertainty"] = {"stated": False, "why": "the staged fit"}
    path.write_text(json.dumps(data))
    assert Rig.load(path).calibration is None
    for a, b in ((rig.camera, back.camera), (rig.projector, back.projector)):
        assert np.array_equal(a.K, b.K) and np.array_equal(a.dist, b.dist)
        assert np.array_equal(a.T_from_world, b.T_from_world)


@pytest.mark.parametrize(
    "mutate,needle",
    [
        (lambda d: d.pop("camera"), 'missing section "camera"'),
        (lambda d: d["camera"].update(K=[[1, 0], [0, 1]]), "camera.K: expected shape (3, 3)"),
        (lambda d: d["projector"].pop("dist"), "projector: missing keys ['dist']"),
        (lambda d: d.update(units="inch"), 'units must be "mm"'),
        (lambda d: d["camera"].update(T_from_world=np.diag([1, 1, -1, 1]).tolist()), "not a proper rotation"),
        # a hand-edited last row: singular (zeros) or a silent scale (2): both refused, naming the row
        (lambda d: d["camera"]["T_from_world"].__setitem__(3, [0, 0, 0, 0]), "last row must be [0, 0, 0, 1]"),
        (lambda d: d["projector"]["T_from_world"].__setitem__(3, [0, 0, 0, 2]), "last row must be [0, 0, 0, 1]"),
        (lambda d: d["camera"]["K"].__setitem__(2, [0, 0, 0]), "K: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]"),
        (lambda d: d["projector"]["K"][0].__setitem__(1, 0.5), "K: expected [[fx, 0, cx]"),  # skew: no OpenCV model
        (lambda d: d["camera"]["K"][1].__setitem__(0, 0.5), "K: expected [[fx, 0, cx]"),
        # the calibration's statement: an object with finite, non-negative numbers
        (lambda d: d.update(calibration="1.6 um"), '"calibration" must be an object'),
        (lambda d: d.update(calibration={"radius_um": -1.0, "shape_rms_um_p95": 3.0, "draws": 64}),
         "calibration.radius_um: expected a finite number >= 0"),
        (lambda d: d.update(calibration={"radius_um": 1.6, "shape_rms_um_p95": float("nan"), "draws": 64}),
         "calibration.shape_rms_um_p95"),
        (lambda d: d.update(calibration={"radius_um": 1.6, "shape_rms_um_p95": 3.0, "draws": 1}),
         "calibration.draws: expected an integer >= 2"),
        (lambda d: d.update(calibration={"radius_um": True, "shape_rms_um_p95": 3.0, "draws": 64}),
         "calibration.radius_um"),
    ],
)
def test_bad_calibration_file_names_the_key(tmp_path, mutate, needle):
    data = default_rig().to_json()
    mutate(data)
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    with pytest.raises(RigError) as err:
        Rig.load(path)
    assert needle in str(err.value)
    assert str(path) in str(err.value)
