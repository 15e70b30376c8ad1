"""The twin renderer against its own analytic truth and the physics of eq. 9."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gearscan.core.patterns import PatternError, PatternSet
from gearscan.core.phase import decode_phase, phase_error, three_step, wrapped_rmse
from gearscan.core.rig import rot_z
from gearscan.twin.render import Optics, RenderError, TwinRenderer

PERIOD = 40.0


def test_noise_free_18_step_matches_analytic_phase(clean_renderer):
    ps = PatternSet.n_step(18, PERIOD)
    imgs, truth = clean_renderer.render(0.0, ps)
    assert imgs.dtype == np.uint8 and imgs.shape == (18, 256, 256)
    assert truth.mask.mean() > 0.2
    phase, m, d = decode_phase(imgs, ps.shifts, 255)
    assert wrapped_rmse(phase, truth.phase, truth.mask) < 0.005
    # normalised modulation |(M, D)| = 2B/S: the analytic value times the camera blur's
    # attenuation of the local fringe frequency, exp(-sigma^2 |grad phi|^2 / 2)
    gy, gx = np.gradient(np.nan_to_num(truth.phase_abs))
    sigma = clean_renderer.optics.camera_defocus_px
    expect = np.hypot(truth.M, truth.D) * np.exp(-(sigma**2) * (gx**2 + gy**2) / 2)
    rel = np.abs(np.hypot(m, d) - expect)[truth.mask] / expect[truth.mask]
    assert np.median(rel) < 0.01


def test_static_three_step_burst(clean_renderer):
    ps = PatternSet.three_step(PERIOD)
    imgs, truth = clean_renderer.render(0.0, ps)
    phase, _, _ = three_step(imgs, 255)
    assert wrapped_rmse(phase, truth.phase, truth.mask) < 0.01


@pytest.fixture(scope="module")
def moving_burst(clean_renderer):
    ps = PatternSet.three_step(PERIOD)
    step = math.radians(0.6)
    frames, truths = clean_renderer.render_sequence([0.0, step, 2 * step], ps, [0, 1, 2])
    static, _ = clean_renderer.render(0.0, ps)
    return frames, truths, static


def test_rotation_error_is_ten_times_static_and_follows_motion(moving_burst):
    frames, truths, static = moving_burst
    t0 = truths[0]
    mask = t0.mask & truths[2].mask
    moving_err = phase_error(three_step(frames, 255)[0], t0.phase)
    static_rmse = wrapped_rmse(three_step(static, 255)[0], t0.phase, mask)
    moving_rmse = float(np.sqrt(np.mean(moving_err[mask] ** 2)))
    assert moving_rmse > 10 * static_rmse
    # concentrated where the surface moves: the truth's phase change from frame 1 to frame 3.
    # Flanks moving along the projector rays barely change phase and keep the static error.
    motion = np.abs(truths[2].phase_abs - t0.phase_abs)
    still, moving = mask & (motion < 0.05), mask & (motion > np.median(motion[mask]))
    assert still.sum() > 100
    rms = lambda sel: float(np.sqrt(np.mean(moving_err[sel] ** 2)))  # noqa: E731
    assert rms(still) < 3 * static_rmse
    assert rms(moving) > 20 * rms(still)


def test_error_has_second_harmonic_structure(moving_burst):
    """On a patch that moves almost uniformly the error is A cos(2 phi + Phi) + B (eq. 9)."""
    frames, truths, _ = moving_burst
    t0 = truths[0]
    eps1 = phase_error(truths[1].phase_abs, t0.phase_abs)
    eps2 = phase_error(truths[2].phase_abs, t0.phase_abs)
    mask = t0.mask & truths[1].mask & truths[2].mask
    moving = mask & (np.abs(eps1) > 0.2)  # flanks moving along the projector rays barely shift
    med = np.median(eps1[moving])
    patch = mask & (np.abs(eps1 - med) < 0.1 * abs(med)) & (np.abs(eps2 - 2 * med) < 0.2 * abs(med))
    assert patch.sum() > 300
    err = phase_error(three_step(frames, 255)[0], t0.phase)[patch]
    phi = t0.phase[patch].astype(np.float64)

    def r2(basis):
        x = np.column_stack([np.ones_like(phi), *basis])
        coef, *_ = np.linalg.lstsq(x, err, rcond=None)
        return 1 - np.var(err - x @ coef) / np.var(err), coef

    r2_second, coef = r2([np.cos(2 * phi), np.sin(2 * phi)])
    r2_first, _ = r2([np.cos(phi), np.sin(phi)])
    assert r2_second > 0.8
    assert r2_second > 3 * r2_first
    # the offset B is the mean motion-induced shift, (0 + eps1 + eps2)/3 for a linear motion
    assert coef[0] == pytest.approx(med, rel=0.25)


def test_points_lie_on_the_gear_and_masked_pixels_are_lit_and_visible(clean_renderer, gear_mesh):
    import open3d as o3d

    angle = math.radians(3.3)
    surf = clean_renderer.surface(angle)
    truth = clean_renderer.truth(surf, PERIOD)
    cam = clean_renderer.rig.camera
    pts = truth.points[truth.mask].astype(np.float64)
    pts_w = pts @ cam.T_world_from[:3, :3].T + cam.T_world_from[:3, 3]
    pts_gear = pts_w @ rot_z(-angle)[:3, :3].T
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(gear_mesh))
    dist = scene.compute_distance(o3d.core.Tensor(pts_gear.astype(np.float32))).numpy()
    assert dist.max() < 1e-3  # mm
    # shadowed / unlit pixels exist in this rig and are outside the mask
    shadowed = surf.hit & ~surf.lit
    assert shadowed.sum() > 100
    assert not (truth.mask & shadowed).any()
    # every masked point is the first surface the camera ray meets (no self-occlusion)
    d = np.linalg.norm(pts, axis=1)
    centre = cam.center_world @ rot_z(-angle)[:3, :3].T
    dirs = (pts_gear - centre) / d[:, None]
    rays = np.concatenate([np.broadcast_to(centre, dirs.shape), dirs], axis=1).astype(np.float32)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    assert np.abs(t_hit - d).max() < 1e-3


def test_deterministic_by_seed(noisy_renderer):
    ps = PatternSet.three_step(PERIOD)
    a, _ = noisy_renderer.render(0.1, ps, 7)
    b, _ = noisy_renderer.render(0.1, ps, 7)
    c, _ = noisy_renderer.render(0.1, ps, 8)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_noise_level_matches_the_sensor_model(rig256, gear, gear_mesh):
    optics = Optics(full_well=math.inf, read_noise=2.0, bit_depth=16)
    r = TwinRenderer(rig256, gear, optics, mesh=gear_mesh)
    ps = PatternSet.three_step(PERIOD)
    a, t = r.render(0.0, ps, 1)
    b, _ = r.render(0.0, ps, 2)
    diff = (a.astype(np.float64) - b)[:, t.mask]
    assert np.std(diff) / math.sqrt(2) == pytest.approx(2.0, rel=0.05)


@pytest.mark.parametrize(
    ("bit_depth", "full_well", "read_noise"),
    [(16, 12000.0, 40.0), (8, 12000.0, 0.6), (12, math.inf, 3.0)],
)
def test_expose_noise_is_shot_plus_read_noise(rig256, gear, gear_mesh, bit_depth, full_well, read_noise):
    """Per-pixel mean and variance over many exposures of flat images against the sensor model.

    Signal ``x S`` DN is ``x full_well`` electrons: shot variance ``x S^2 / full_well`` DN^2,
    plus read noise^2, plus 1/12 DN^2 of rounding (Sheppard). Images are independent.
    """
    optics = Optics(full_well=full_well, read_noise=read_noise, bit_depth=bit_depth)
    r = TwinRenderer(rig256, gear, optics, mesh=gear_mesh)
    s = optics.full_scale
    levels = np.array([0.05, 0.3, 0.7], np.float32)
    linear = np.broadcast_to(levels[None, :, None, None], (400, 3, 24, 24)).copy()
    raw = r.expose(linear, np.random.default_rng(3))
    assert raw.dtype == optics.dtype and raw.shape == (400, 3, 24, 24)
    img = raw.astype(np.float64)
    shot = levels * s * s / full_well if math.isfinite(full_well) else 0 * levels
    expect_var = shot + read_noise**2 + 1 / 12
    var = img.var(axis=0, ddof=1).mean(axis=(1, 2))  # per pixel over realisations, then averaged
    mean = img.mean(axis=(0, 2, 3))
    # 400 realisations x 576 pixels: the variance is known to ~0.3 %, the mean to < 0.01 DN
    np.testing.assert_allclose(var, expect_var, rtol=0.03)
    assert np.all(np.abs(mean - levels * s) < 0.02 * np.sqrt(expect_var))
    # different images get independent noise: neighbours in the stack are uncorrelated
    noise = (img - img.mean(axis=0))[:, 1].reshape(400, -1)
    corr = np.mean(noise[:-1] * noise[1:]) / np.mean(noise * noise)
    assert abs(corr) < 0.02


def test_expose_checks_shape_and_is_reproducible(noisy_renderer):
    lin = np.full((3, 16, 16), 0.5, np.float32)
    a = noisy_renderer.expose(lin.copy(), np.random.default_rng(5))
    b = noisy_renderer.expose(lin.copy(), np.random.default_rng(5))
    assert np.array_equal(a, b) and not np.array_equal(a[0], a[1])
    assert noisy_renderer.expose(lin[0].copy(), np.random.default_rng(5)).shape == (16, 16)
    with pytest.raises(RenderError, match=r"expected \(\.\.\., H, W\) images, got shape \(16,\)"):
        noisy_renderer.expose(lin[0, 0].copy(), np.random.default_rng(5))


def test_multi_frequency_and_16_bit(rig256, gear, gear_mesh):
    r = TwinRenderer(rig256, gear, Optics(bit_depth=16).noise_free(), mesh=gear_mesh)
    ps = PatternSet.multi_frequency([PERIOD, 4 * PERIOD], steps=4)
    imgs, truth = r.render(0.0, ps)
    assert imgs.dtype == np.uint16 and imgs.max() > 1000
    idx, shifts = ps.group(4 * PERIOD)
    coarse = decode_phase(imgs[idx], shifts, 65535)[0]
    expect = np.angle(np.exp(1j * truth.phase_abs / 4))
    assert wrapped_rmse(coarse, expect, truth.mask) < 0.01


def test_motion_blur_reduces_modulation(clean_renderer):
    ps = PatternSet.n_step(6, PERIOD)
    sharp, t = clean_renderer.render(0.0, ps)
    blurred, _ = clean_renderer.render(0.0, ps, motion_span=math.radians(1.5))
    mod_s = np.hypot(*decode_phase(sharp, ps.shifts, 255)[1:])[t.mask]
    mod_b = np.hypot(*decode_phase(blurred, ps.shifts, 255)[1:])[t.mask]
    assert np.median(mod_b) < 0.9 * np.median(mod_s)


def test_bad_inputs_are_named(gear, gear_mesh):
    from gearscan.core.rig import default_rig

    away = default_rig(64, 64, working_radius=200.0)  # looks at empty space beyond the gear
    with pytest.raises(RenderError, match="sees the lit gear on 0.00%"):
        TwinRenderer(away, gear, mesh=gear_mesh)
    with pytest.raises(PatternError, match="steps must be >= 3"):
        PatternSet.n_step(2, PERIOD)
    with pytest.raises(ValueError, match="bit_depth"):
        Optics(bit_depth=9)
