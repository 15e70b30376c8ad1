"""Triangulation, depth uncertainty, turntable stacking and CAD deviation (recon/)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gearscan.core.gear import GearSpec
from gearscan.core.patterns import PatternSet
from gearscan.core.phase import decode_phase
from gearscan.core.rig import PinholeDevice, Rig, default_rig, rot_z
from gearscan.recon.cloud import (
    cad_deviation,
    deviation_stats,
    load_cloud,
    merge_clouds,
    save_cloud,
)
from gearscan.recon.triangulate import Triangulator, to_cloud, to_turntable
from gearscan.recon.unwrap import TWO_PI, temporal_unwrap
from gearscan.twin.render import Optics, TwinRenderer

PERIODS = [20.0, 160.0, 1400.0]


def _plane_phase(rig: Rig, z: float, period: float) -> np.ndarray:
    """Absolute phase of a fronto-parallel plane at camera depth ``z`` (hand projection)."""
    rays = rig.camera.pixel_rays()
    p_cam = rays / rays[..., 2:3] * z
    p_w = p_cam @ rig.camera.T_world_from[:3, :3].T + rig.camera.T_world_from[:3, 3]
    return TWO_PI * rig.projector.project(p_w)[..., 0] / period


@pytest.mark.parametrize("projector_dist", [False, True])
def test_plane_is_recovered(projector_dist):
    rig = default_rig(48, 40)
    if projector_dist:
        p = rig.projector
        rig = Rig(rig.camera, PinholeDevice(p.width, p.height, p.K, [0.05, -0.1, 0.001, 0.0005, 0.0], p.T_from_world))
    phase = _plane_phase(rig, 163.0, 24.0)
    tri = Triangulator(rig, 24.0, projector_iterations=3)(phase)
    assert tri.valid.all()
    np.testing.assert_allclose(tri.depth, 163.0, atol=2e-3 if projector_dist else 1e-4)


def test_depth_sigma_matches_finite_difference():
    rig = default_rig(32, 32)
    phase = _plane_phase(rig, 161.0, 20.0)
    tri = Triangulator(rig, 20.0)
    h = 1e-2
    dz = (tri(phase + h).depth.astype(np.float64) - tri(phase - h).depth) / (2 * h)
    sig = tri(phase, sigma_phase=0.1).sigma_depth
    np.testing.assert_allclose(sig, 0.1 * np.abs(dz), rtol=2e-2)


def test_triangulator_checks_shape():
    tri = Triangulator(default_rig(16, 16), 20.0)
    with pytest.raises(ValueError, match=r"expected shape \(16, 16\) \(camera H, W\), got \(8, 16\)"):
        tri(np.zeros((8, 16)))


def test_to_turntable_undoes_the_rotation():
    rig = default_rig(16, 16)
    p_gear = np.array([[21.0, 1.0, 2.0]])
    angle = 0.3
    # the gear point at angle: world = rot_z(angle) p; camera = T_cam_from_world world
    c, s = math.cos(angle), math.sin(angle)
    p_world = p_gear @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    t = rig.camera.T_from_world
    p_cam = p_world @ t[:3, :3].T + t[:3, 3]
    np.testing.assert_allclose(to_turntable(p_cam, rig, angle), p_gear, atol=1e-9)


def _static_reconstruction(renderer: TwinRenderer, angle: float, rng: int):
    """18-step, three-frequency scan at one pose: (cloud in gear frame, triangulation, truth, sigma_phi)."""
    optics = renderer.optics
    patterns = PatternSet.multi_frequency(PERIODS, 18)
    images, truth = renderer.render(angle, patterns, rng=rng)
    wrapped = []
    for period in PERIODS:
        idx, shifts = patterns.group(period)
        phase, m, d = decode_phase(images[idx], shifts, optics.full_scale)
        wrapped.append(phase)
        if period == PERIODS[0]:
            fine_imgs, modulation = images[idx].astype(np.float64), np.hypot(m, d)
    res = temporal_unwrap(wrapped, PERIODS, renderer.rig.projector.width)
    # phase sigma of N-step PS: s_I sqrt(2/N) / B, s_I from shot + read + quantisation noise
    b = modulation * optics.full_scale / 2
    mean_i = fine_imgs.mean(axis=0)
    shot = mean_i * optics.full_scale / optics.full_well if math.isfinite(optics.full_well) else 0.0
    s_i = np.sqrt(shot + optics.read_noise**2 + 1 / 12)
    sigma_phi = s_i * math.sqrt(2 / 18) / np.maximum(b, 1e-6)
    phase_abs = np.where(truth.mask, res.phase_abs, np.nan)
    tri = Triangulator(renderer.rig, PERIODS[0])(phase_abs, sigma_phi)
    return to_cloud(tri, renderer.rig, angle), tri, truth, res


@pytest.fixture(scope="module")
def gear():
    return GearSpec()


@pytest.mark.parametrize(("optics", "limit"), [(Optics().noise_free(), 0.01), (Optics(), 0.05)])
def test_static_scan_matches_cad(gear, optics, limit):
    rig = default_rig()
    renderer = TwinRenderer(rig, gear, optics)
    angle = math.radians(5.0)
    cloud, tri, truth, res = _static_reconstruction(renderer, angle, rng=3)
    assert res.valid[truth.mask].mean() > 0.999
    assert len(cloud) > 0.99 * truth.mask.sum()
    cloud, stats = cad_deviation(cloud, gear.mesh())
    assert stats.rms < limit, stats
    assert cloud.deviation.shape == (len(cloud),)


def test_predicted_depth_sigma_is_consistent(gear):
    """RMS measured depth error / RMS predicted sigma in [0.7, 1.4] on noisy renders."""
    renderer = TwinRenderer(default_rig(), gear, Optics())
    errs, sigmas = [], []
    for i, deg in enumerate([0.0, 9.0]):
        _, tri, truth, _ = _static_reconstruction(renderer, math.radians(deg), rng=10 + i)
        sel = tri.valid & truth.mask
        errs.append(tri.depth[sel] - truth.depth[sel])
        sigmas.append(tri.sigma_depth[sel])
    err, sig = np.concatenate(errs), np.concatenate(sigmas)
    ratio = np.sqrt(np.mean(err**2)) / np.sqrt(np.mean(sig**2))
    assert 0.7 <= ratio <= 1.4, f"ratio {ratio:.3f}"


def test_bursts_stack_into_one_gear_frame_cloud(gear, tmp_path):
    rig = default_rig(128, 128)
    renderer = TwinRenderer(rig, gear, Optics().noise_free())
    clouds = []
    for i, deg in enumerate([0.0, 90.0, 180.0, 270.0]):
        cloud, _, _, _ = _static_reconstruction(renderer, math.radians(deg), rng=i)
        clouds.append(cloud)
    merged = merge_clouds(clouds)
    assert len(merged) == sum(len(c) for c in clouds)
    # 90 deg is 5 pitches of the 20-tooth gear: every burst sees the same view, so in the
    # gear frame its points are the first burst's turned by -angle about the axis
    from scipy.spatial import cKDTree

    tree = cKDTree(clouds[0].points)
    for c, deg in zip(clouds[1:], [90.0, 180.0, 270.0], strict=True):
        back = c.points @ rot_z(math.radians(deg))[:3, :3].T
        assert np.median(tree.query(back)[0]) < 0.05
        assert np.median(tree.query(c.points)[0]) > 5.0  # a different sector of the gear
    _, stats = cad_deviation(merged, gear.mesh())
    assert stats.rms < 0.01
    down = merge_clouds(clouds, voxel_mm=0.5)
    assert 0 < len(down) < len(merged)
    path = save_cloud(down, tmp_path / "gear.ply")
    back = load_cloud(path)
    np.testing.assert_allclose(back.points, down.points, atol=1e-5)
    np.testing.assert_allclose(back.sigma, down.sigma, atol=1e-7)
    save_cloud(down, tmp_path / "gear.pcd")
    with pytest.raises(ValueError, match="suffix"):
        save_cloud(down, tmp_path / "gear.xyz")


def test_deviation_stats_hand_values():
    st = deviation_stats(np.array([3.0, -4.0, np.nan]))
    assert st.count == 2 and math.isclose(st.rms, math.sqrt(12.5)) and st.max == 4.0
