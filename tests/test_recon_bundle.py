"""The joint bundle adjustment (recon/bundle.py) on exact synthetic corners of the twin's default rig: from a start
that is off the way OpenCV's stages leave it (focal lengths, principal points, the projector's pose, the axis), it
returns the true rig, and a cylinder measured with it reads its true radius and shape. With Gaussian corner noise,
the uncertainty it states matches the scatter of repeated calibrations."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from gearscan.core.rig import Rig, default_rig
from gearscan.recon.bundle import adjust_jointly, covariance_steps, parameter_sigma
from gearscan.recon.calibration import Checkerboard
from gearscan.recon.calibration import _rig_of as rig_of_fit
from gearscan.recon.rig_check import calibration_uncertainty, cylinder_check
from gearscan.twin.board import calibration_poses


def _observe(rig: Rig, board: Checkerboard, noise_px: float = 0.0, seed: int = 0,
             turntable_deg: tuple[float, ...] | None = None):
    """Every calibration pose's corners in both devices (exact, or with Gaussian noise of ``noise_px`` in the camera
    and 5/3 of it in the projector, as the twin's renders measure: 0.028 and 0.051 px), the poses and angles; the
    turntable views at ``turntable_deg`` (None: the twin's set)."""
    rng = np.random.default_rng(seed)
    obj = board.object_points().astype(np.float64)
    cam_c, cam_p, poses, angles = [], [], [], []
    turn = {} if turntable_deg is None else {"turntable_angles_deg": turntable_deg}
    for _, t_world_from_board, angle in calibration_poses(rig, board, **turn):
        world = obj @ t_world_from_board[:3, :3].T + t_world_from_board[:3, 3]
        cam_c.append(rig.camera.project(world) + rng.normal(0, noise_px, (len(obj), 2)))
        cam_p.append(rig.projector.project(world) + rng.normal(0, noise_px * 5 / 3, (len(obj), 2)))
        poses.append(rig.camera.T_from_world @ t_world_from_board)
        angles.append(angle)
    return obj, cam_c, cam_p, poses, angles


def _rig_of(fit, angles, board: Checkerboard) -> Rig:
    """The rig of a joint fit, built as the calibration builds its own (world origin at the first turntable view)."""
    first_turn = next(i for i, a in enumerate(angles) if a is not None)
    return rig_of_fit(fit, board, first_turn, (512, 512), (1280, 800), "calibrated")


def _nudged(t: np.ndarray, rot_deg: float, shift_mm: float) -> np.ndarray:
    out = t.copy()
    out[:3, :3] = cv2.Rodrigues(np.radians([rot_deg, -rot_deg, 0.5 * rot_deg]))[0] @ t[:3, :3]
    out[:3, 3] += [shift_mm, -shift_mm, 2 * shift_mm]
    return out


@pytest.mark.parametrize(("noise_px", "camera_lens"), [(0.0, "k1k2p1p2"), (0.03, "k1")])
def test_joint_adjustment_returns_the_true_rig(noise_px, camera_lens):
    """Exact corners with every coefficient of the camera's lens free: every parameter back. With the twin's noise
    (0.03 / 0.05 px) and the lens model the held-out rule picks on the twin (k1: its lens is nearly all k1): residuals
    at the noise, and a cylinder within the noise's reach (noise seeds 0-4: shape 2.4-8.8 um, radius -7.3 to +3.0 um;
    k1 k2 p1 p2 free instead: the same within 0.6 um; a report, not a choice)."""
    rig, board = default_rig(), Checkerboard()
    obj, img_c, img_p, poses, angles = _observe(rig, board, noise_px)
    k_c, k_p = rig.camera.K.copy(), rig.projector.K.copy()
    k_c[0, 0] *= 1.005  # a staged fit's focal lengths, principal points, stereo pose and axis: all a little off
    k_c[1, 1] *= 1.004
    k_c[:2, 2] += [3.0, -4.0]
    k_p[0, 0] *= 0.996
    k_p[1, 1] *= 0.997
    k_p[:2, 2] += [-5.0, 2.0]
    t_pc = _nudged(rig.T_proj_from_cam, 0.05, 0.2)
    t_cw = _nudged(rig.camera.T_from_world, 0.08, 0.15)
    start = [_nudged(p, 0.05, 0.05) for p in poses]
    # the twin's camera lens (k1 -0.08, k2 0.12, p1 5e-4, p2 -3e-4) from zero; the projector has none
    fit = adjust_jointly(obj, img_c, img_p, angles, (camera_lens, "none"), k_c, np.zeros(5), k_p, np.zeros(5), t_pc,
                         t_cw, start, (0.03, 0.05))
    assert fit.rms_after < 0.05 * fit.rms_before if noise_px == 0 else 0.9 < fit.rms_after < 1.05  # exact / the noise
    if noise_px == 0:  # exact corners: every parameter back
        np.testing.assert_allclose(fit.k_camera, rig.camera.K, rtol=1e-6, atol=1e-3)
        np.testing.assert_allclose(fit.dist_camera, rig.camera.dist, atol=1e-6)
        np.testing.assert_allclose(fit.k_projector, rig.projector.K, rtol=1e-6, atol=1e-3)
        np.testing.assert_allclose(fit.t_proj_from_cam[:3, 3], rig.T_proj_from_cam[:3, 3], atol=1e-4)
    else:  # noisy: the focal lengths within 0.1 % (a 9 deg field trades the principal point against p1, p2 and pose)
        np.testing.assert_allclose(np.diag(fit.k_camera)[:2], np.diag(rig.camera.K)[:2], rtol=1e-3)
        np.testing.assert_allclose(np.diag(fit.k_projector)[:2], np.diag(rig.projector.K)[:2], rtol=1e-3)
    # the axis: the fitted turntable frame's z against the truth's, in the camera frame (with noise it turns with the
    # camera's principal point, which the measurement shares: the cylinder below is the test of it)
    axis = math.degrees(math.acos(min(1.0, float(fit.t_cam_from_turntable[:3, 2] @ rig.camera.T_from_world[:3, 2]))))
    assert axis < (1e-4 if noise_px == 0 else 0.2)
    cyl = cylinder_check(_rig_of(fit, angles, board), rig)  # the rig the calibration writes, by what a user sees
    assert cyl["shape_rms_um"] < (0.01 if noise_px == 0 else 12.0)
    assert abs(cyl["radius_bias_um"]) < (0.01 if noise_px == 0 else 10.0)


@pytest.mark.parametrize("turntable_deg", [(-24.0, -12.0, 0.0, 12.0, 24.0), None])
def test_the_encoder_scale_is_measured_not_absorbed(turntable_deg):
    """Exact corners of a turntable that turned 1.01 times what the encoder says: the fit with the scale free reads
    1.01 and fits them exactly. With turntable views over +-24 deg (the set before session 56) the fit that trusts
    the angles bends the rig to them (the focal length 0.9 % off) with residuals under the noise, which is why the
    caller checks the scale and refuses such an encoder; over +-45 deg (the twin's set now) the bend no longer fits
    and the residuals show it (2.8 x the noise)."""
    rig, board = default_rig(), Checkerboard()
    obj, img_c, img_p, poses, angles = _observe(rig, board, turntable_deg=turntable_deg)
    told = [None if a is None else a / 1.01 for a in angles]
    args = (obj, img_c, img_p, told, ("k1k2p1p2", "none"), rig.camera.K, rig.camera.dist, rig.projector.K, np.zeros(5),
            rig.T_proj_from_cam, rig.camera.T_from_world, poses, (0.03, 0.05))
    check = adjust_jointly(*args, fit_scale=True)
    assert abs(check.encoder_scale - 1.01) < 1e-5 and check.rms_after < 1e-3
    trusting = adjust_jointly(*args)
    assert trusting.encoder_scale == 1.0
    if turntable_deg is not None:  # absorbed: under the noise, the rig bent
        assert trusting.rms_after < 1.0 and abs(trusting.k_camera[0, 0] / rig.camera.K[0, 0] - 1) > 0.005
    else:  # seen
        assert trusting.rms_after > 2.0


def test_a_lens_coefficient_is_fitted_when_its_model_frees_it():
    """A camera with k1 = -0.5 seen exactly: the 'k1' model recovers it from a start at 0; 'none' cannot."""
    rig, board = default_rig(), Checkerboard()
    dist = np.array([-0.5, 0.0, 0.0, 0.0, 0.0])
    lens = dataclasses.replace(rig, camera=dataclasses.replace(rig.camera, dist=dist))
    obj, img_c, img_p, poses, angles = _observe(lens, board)
    args = (rig.camera.K, np.zeros(5), rig.projector.K, np.zeros(5), rig.T_proj_from_cam, rig.camera.T_from_world, poses,
            (0.05, 0.05))  # the twin camera's own lens replaced by k1 alone
    fit = adjust_jointly(obj, img_c, img_p, angles, ("k1", "none"), *args)
    assert abs(fit.dist_camera[0] + 0.5) < 1e-4 and fit.rms_after < 1e-3
    plain = adjust_jointly(obj, img_c, img_p, angles, ("none", "none"), *args)
    assert plain.dist_camera[0] == 0.0 and plain.rms_after > 100 * fit.rms_after


def test_covariance_draws_follow_the_least_squares_covariance():
    """On a linear least-squares problem whose columns differ by 1e4 in scale, the draws' covariance is
    factor (J^T J)^-1 within sampling error (4,000 draws: about 2 % per standard deviation)."""
    rng = np.random.default_rng(1)
    jac = rng.normal(size=(300, 4)) * np.array([1.0, 1e4, 1e-2, 3.0])
    steps = covariance_steps(jac, 2.5, 4000, seed=3)
    want = 2.5 * np.linalg.inv(jac.T @ jac)
    got = np.cov(steps.T)
    np.testing.assert_allclose(np.sqrt(np.diag(got)), np.sqrt(np.diag(want)), rtol=0.06)
    corr = got / np.sqrt(np.outer(np.diag(got), np.diag(got)))
    np.testing.assert_allclose(corr, want / np.sqrt(np.outer(np.diag(want), np.diag(want))), atol=0.05)
    with pytest.raises(ValueError, match="degrees of freedom"):
        covariance_steps(jac, float("nan"), 2, seed=0)
    # one parameter's standard error, exactly (the encoder check's)
    for i in range(4):
        assert parameter_sigma(jac, 2.5, i) == pytest.approx(math.sqrt(want[i, i]), rel=1e-9)
    # a parameter the residuals do not feel (a column repeated): refused, not drawn as infinite or left out
    with pytest.raises(ValueError, match="unconstrained"):
        covariance_steps(np.concatenate([jac, jac[:, :1]], axis=1), 1.0, 2, seed=0)


def test_the_stated_uncertainty_matches_repeated_calibrations():
    """Thirty calibrations of the same rig from corners with independent Gaussian noise (0.03 / 0.05 px, told to the
    fit): the radius each reads on the 20 mm cylinder, and its camera focal length, scatter as the calibrations state
    from their own corners (the draws' spread, the median over four of them), within what thirty samples allow (a
    ratio of 0.6-1.5; forty such calibrations gave 0.92 for the radius). A statement 1.7x too small or too large
    fails."""
    rig, board = default_rig(), Checkerboard()
    radius, focal, u_radius, u_focal = [], [], [], []
    for seed in range(30):
        obj, img_c, img_p, poses, angles = _observe(rig, board, 0.03, seed=100 + seed)
        fit = adjust_jointly(obj, img_c, img_p, angles, ("k1", "none"), rig.camera.K, rig.camera.dist, rig.projector.K,
                             np.zeros(5), rig.T_proj_from_cam, rig.camera.T_from_world, poses, (0.03, 0.05),
                             draws=32 if seed < 4 else 0, seed=seed)
        est = _rig_of(fit, angles, board)
        radius.append(cylinder_check(est, rig)["radius_bias_um"])
        focal.append(est.camera.K[0, 0])
        assert 0.7 < fit.variance_factor < 1.3  # the residuals at the noise the fit was told
        if fit.draws:
            stated = calibration_uncertainty(est, [_rig_of(d, angles, board) for d in fit.draws], fit.variance_factor)
            u_radius.append(stated["radius_um"])
            u_focal.append(stated["camera_focal_pct"] / 100 * est.camera.K[0, 0])
    assert 0.6 < np.std(radius, ddof=1) / np.median(u_radius) < 1.5
    assert 0.6 < np.std(focal, ddof=1) / np.median(u_focal) < 1.5


def test_the_stated_uncertainty_comes_from_the_residuals_not_the_noise_told():
    """The fit told twice the corners' noise weighs its residuals at a quarter of the variance factor: the stated
    radius uncertainty is the same (the a-posteriori factor carries the noise the corners show)."""
    rig, board = default_rig(), Checkerboard()
    obj, img_c, img_p, poses, angles = _observe(rig, board, 0.03, seed=7)
    stated = []
    for sigma in ((0.03, 0.05), (0.06, 0.10)):
        fit = adjust_jointly(obj, img_c, img_p, angles, ("k1", "none"), rig.camera.K, rig.camera.dist, rig.projector.K,
                             np.zeros(5), rig.T_proj_from_cam, rig.camera.T_from_world, poses, sigma, draws=16, seed=1)
        est = _rig_of(fit, angles, board)
        stated.append((fit.variance_factor, calibration_uncertainty(
            est, [_rig_of(d, angles, board) for d in fit.draws], fit.variance_factor)["radius_um"]))
    assert stated[1][0] == pytest.approx(stated[0][0] / 4, rel=1e-3)
    assert stated[1][1] == pytest.approx(stated[0][1], rel=1e-3)


def test_draws_too_wide_to_read_the_cylinder_are_refused():
    """A drawn calibration that triangulates far fewer cylinder points than the calibration itself (here: its projector
    150 mm further back, 1,610 of 4,000) is beyond the covariance's linearisation, and one that triangulates none
    (300 mm) cannot be read at all: each refused with a reason, never a number."""
    rig = default_rig()

    def moved(dz_mm: float) -> Rig:
        t = rig.projector.T_from_world.copy()
        t[2, 3] += dz_mm
        return dataclasses.replace(rig, projector=dataclasses.replace(rig.projector, T_from_world=t))

    with pytest.raises(ValueError, match="too wide"):
        calibration_uncertainty(rig, [rig, moved(-150.0)], 1.0)
    with pytest.raises(ValueError, match="triangulates none"):
        calibration_uncertainty(rig, [rig, moved(-300.0)], 1.0)


def test_the_encoder_scale_sigma_matches_repeated_checks():
    """Twenty encoder checks (the scale free) on corners with independent Gaussian noise: the scales scatter about 1
    as their own standard errors say (a wrong parameter index or variance factor would be off by orders of
    magnitude); the product multiplies it by 5 for the twin's renders, whose errors are not independent
    (recon.calibration.ENCODER_SIGMA_FACTOR)."""
    rig, board = default_rig(), Checkerboard()
    scales, sigmas = [], []
    for seed in range(20):
        obj, img_c, img_p, poses, angles = _observe(rig, board, 0.03, seed=300 + seed)
        fit = adjust_jointly(obj, img_c, img_p, angles, ("k1", "none"), rig.camera.K, rig.camera.dist, rig.projector.K,
                             np.zeros(5), rig.T_proj_from_cam, rig.camera.T_from_world, poses, (0.03, 0.05),
                             fit_scale=True)
        scales.append(fit.encoder_scale)
        sigmas.append(fit.encoder_scale_sigma)
    assert 0.6 < np.sqrt(np.mean((np.array(scales) - 1) ** 2)) / np.median(sigmas) < 1.5


def test_a_covariance_that_cannot_be_drawn_keeps_the_fit(monkeypatch):
    """Draws refused (here: forced) leave the adjusted calibration as it is, with the reason, and no draws."""
    import gearscan.recon.bundle as bundle

    rig, board = default_rig(), Checkerboard()
    obj, img_c, img_p, poses, angles = _observe(rig, board, 0.03, seed=5)
    args = (obj, img_c, img_p, angles, ("k1", "none"), rig.camera.K, rig.camera.dist, rig.projector.K, np.zeros(5),
            rig.T_proj_from_cam, rig.camera.T_from_world, poses, (0.03, 0.05))
    plain = adjust_jointly(*args)

    def refuse(*a, **k):
        raise ValueError("the corners leave 1 direction(s) of the calibration unconstrained")

    monkeypatch.setattr(bundle, "covariance_steps", refuse)
    fit = adjust_jointly(*args, draws=8)
    assert fit.draws == () and "unconstrained" in fit.draws_why
    np.testing.assert_allclose(fit.k_camera, plain.k_camera)
