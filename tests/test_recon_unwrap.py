"""Phase unwrapping: temporal multi-frequency and geometric constraint (recon/unwrap.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gearscan.core.gear import GearSpec
from gearscan.core.patterns import PatternSet
from gearscan.core.phase import decode_phase, wrap
from gearscan.core.rig import default_rig
from gearscan.recon.unwrap import (
    TWO_PI,
    DepthBounds,
    coarse_absolute,
    gear_depth_bounds,
    geometric_unwrap,
    min_unambiguous_period,
    phase_bounds,
    temporal_unwrap,
    unambiguous_depth_window,
)
from gearscan.twin.render import Optics, TwinRenderer

PROJ_W = 1280


def _columns(shape=(64, 80), rng=0) -> np.ndarray:
    """Projector columns spanning the whole projector, with a smooth 2D variation."""
    r = np.random.default_rng(rng)
    u = np.linspace(0, PROJ_W - 1, shape[1])[None, :] + 5 * np.sin(np.arange(shape[0]) / 7.0)[:, None]
    return np.clip(u + r.normal(0, 0.5, shape), 0, PROJ_W - 1)


def test_coarse_absolute_is_unambiguous_near_both_ends():
    period = 1400.0
    u = np.array([[0.0, 0.2, 640.0, 1279.0]])
    phi = TWO_PI * u / period
    noisy = wrap(phi - 0.05)  # noise pushes column 0 below zero: must not jump by 2 pi
    got = coarse_absolute(noisy, period, PROJ_W)
    np.testing.assert_allclose(got, phi - 0.05, atol=1e-12)


def test_coarse_absolute_rejects_short_period():
    with pytest.raises(ValueError, match="projector width"):
        coarse_absolute(np.zeros((2, 2)), 800.0, PROJ_W)


@pytest.mark.parametrize("periods", [[20.0, 160.0, 1400.0], [1400.0, 36.0, 240.0], [1280.0, 128.0]])
def test_temporal_unwrap_recovers_absolute_phase(periods):
    u = _columns()
    wrapped = [wrap(TWO_PI * u / p) for p in periods]
    res = temporal_unwrap(wrapped, periods, PROJ_W)
    fine = min(periods)
    assert res.period_px == fine
    assert res.valid.all()
    np.testing.assert_allclose(res.phase_abs, TWO_PI * u / fine, atol=1e-9)
    np.testing.assert_array_equal(res.order, np.rint((TWO_PI * u / fine - wrapped[periods.index(fine)]) / TWO_PI))


def test_temporal_unwrap_flags_inconsistent_frequencies():
    periods = [20.0, 160.0, 1400.0]
    u = _columns()
    wrapped = [wrap(TWO_PI * u / p) for p in periods]
    wrapped[1] = wrapped[1].copy()
    wrapped[1][10, 10] = wrap(wrapped[1][10, 10] + math.pi)  # half a fringe off in the middle period
    res = temporal_unwrap(wrapped, periods, PROJ_W)
    assert not res.valid[10, 10] and np.isnan(res.phase_abs[10, 10])
    assert res.valid.sum() == res.valid.size - 1


def test_temporal_unwrap_checks_inputs():
    with pytest.raises(ValueError, match="2 wrapped phases but 3 periods"):
        temporal_unwrap([np.zeros((2, 2))] * 2, [1, 2, 3], PROJ_W)
    with pytest.raises(ValueError, match=r"wrapped\[0\]: expected shape \(3, 2\), got \(2, 2\)"):
        temporal_unwrap([np.zeros((2, 2)), np.zeros((3, 2))], [20.0, 1400.0], PROJ_W)


def test_geometric_unwrap_hand_values():
    # phi_min = 10.0 rad; wrapped phase 1.0 -> k = ceil((10 - 1)/2pi) = 2 -> 1 + 4 pi = 13.57
    wrapped = np.array([[1.0, 1.0, -3.0]])
    lo = np.array([[10.0, 10.0, 10.0]])
    hi = np.array([[14.0, 20.0, 15.0]])  # second: interval admits 1 + 4pi and 1 + 6pi
    res = geometric_unwrap(wrapped, lo, hi, 20.0)
    assert res.order[0, 0] == 2 and res.valid[0, 0]
    assert math.isclose(res.phase_abs[0, 0], 1.0 + 4 * math.pi)
    assert not res.valid[0, 1]  # ambiguous: reported, not guessed
    # -3 + 2pi*2 = 9.57 < 10 and -3 + 2pi*3 = 15.85 > 15: no order fits -> invalid
    assert not res.valid[0, 2]
    # a margin lets the noisy one in
    res = geometric_unwrap(wrapped, lo, hi, 20.0, margin=0.5)
    assert res.valid[0, 2] and res.order[0, 2] == 2


def test_virtual_plane_bounds_match_hand_projection():
    rig = default_rig(64, 64, distortion=False)
    b = DepthBounds.planes(rig.camera, 158.0, 170.0)
    lo, hi = phase_bounds(rig, b, period_px=100.0)
    # centre pixel (31.5 is the centre; take 32,32 close to the axis) by hand
    ray = np.linalg.inv(rig.camera.K) @ np.array([32.0, 32.0, 1.0])
    u = []
    for z in (158.0, 170.0):
        p_cam = ray * z
        p_w = rig.camera.T_world_from[:3, :3] @ p_cam + rig.camera.T_world_from[:3, 3]
        u.append(rig.projector.project(p_w[None])[0, 0])
    np.testing.assert_allclose(sorted([lo[32, 32], hi[32, 32]]), sorted(TWO_PI * np.array(u) / 100.0), rtol=1e-9)


@pytest.fixture(scope="module")
def gear_setup():
    rig = default_rig()
    gear = GearSpec()
    bounds = gear_depth_bounds(rig, gear.tip_radius, gear.root_radius, gear.face_width)
    return rig, gear, bounds, TwinRenderer(rig, gear, Optics())


def test_gear_bounds_contain_the_true_surface(gear_setup):
    rig, gear, bounds, renderer = gear_setup
    for angle in np.radians([0.0, 7.0, 13.0]):
        surf = renderer.surface(float(angle))
        tr = renderer.truth(surf, 100.0)
        d = surf.depth[tr.mask]
        assert np.all(d >= bounds.t_min[tr.mask] - 1e-3)
        assert np.all(d <= bounds.t_max[tr.mask] + 1e-3)


def test_single_frequency_geometric_unwrap_over_working_range(gear_setup):
    """Fringe order right on >= 99.5 % of valid pixels, over one pitch of rotation (noisy)."""
    rig, gear, bounds, renderer = gear_setup
    needed = min_unambiguous_period(rig, bounds)
    assert 60 < needed < 120  # ~95 projector px for the default rig and gear
    period = math.ceil(needed / 10) * 10 + 10.0  # some room for the noise margin
    lo, hi = phase_bounds(rig, bounds, period)
    patterns = PatternSet.three_step(period)
    right = total = 0
    for i, angle in enumerate(np.linspace(0.0, gear.pitch_angle, 7)[:-1]):
        images, tr = renderer.render(float(angle), patterns, rng=i)
        phase, _, _ = decode_phase(images, patterns.shifts, renderer.optics.full_scale)
        res = geometric_unwrap(phase, lo, hi, period, margin=0.2)
        k_true = np.rint((tr.phase_abs - phase) / TWO_PI)
        ok = res.valid & (res.order == k_true)
        right += int(ok[tr.mask].sum())
        total += int(tr.mask.sum())
    assert total > 50_000
    assert right / total >= 0.995, f"fringe order right on {100 * right / total:.3f}% of valid pixels"


def test_geometric_unwrap_reports_ambiguity_for_fine_fringes(gear_setup):
    """With fringes finer than the depth range, pixels are flagged, and those kept are right."""
    rig, gear, bounds, renderer = gear_setup
    period = 30.0
    lo, hi = phase_bounds(rig, bounds, period)
    patterns = PatternSet.three_step(period)
    images, tr = renderer.render(0.0, patterns, rng=0)
    phase, _, _ = decode_phase(images, patterns.shifts, renderer.optics.full_scale)
    res = geometric_unwrap(phase, lo, hi, period, margin=0.2)
    k_true = np.rint((tr.phase_abs - phase) / TWO_PI)
    kept = res.valid & tr.mask
    assert kept.sum() < 0.05 * tr.mask.sum()
    if kept.any():
        assert np.all(res.order[kept] == k_true[kept])


def test_centred_unwrap_takes_the_whole_fringe_around_the_prior():
    """Any prior within half a fringe (less the margin) of the truth gives the exact order;
    farther than that the pixel is refused, not guessed."""
    from gearscan.recon.unwrap import centred_unwrap

    rng = np.random.default_rng(0)
    truth = np.linspace(0.0, 60.0, 400).reshape(20, 20)
    wrapped = np.angle(np.exp(1j * truth))
    off = rng.uniform(-(np.pi - 0.31), np.pi - 0.31, truth.shape)  # prior error up to +-2.83 rad
    res = centred_unwrap(wrapped, truth + off, 40.0, margin=0.3)
    assert res.valid.all()
    np.testing.assert_allclose(res.phase_abs, truth, atol=1e-9)
    near_edge = centred_unwrap(wrapped, truth + np.pi - 0.1, 40.0, margin=0.3)
    assert not near_edge.valid.any() and np.isnan(near_edge.phase_abs).all()
    no_prior = centred_unwrap(wrapped, np.full(truth.shape, np.nan), 40.0)
    assert not no_prior.valid.any()


def _grow_orders_every_pixel_every_ring(wrapped, absolute, target, steps, max_step):
    """The first form of ``grow_orders`` (every pending pixel read in every ring), the reference for its frontier."""
    from gearscan.recon.unwrap import TWO_PI, _order_jumps, _wrap

    absolute = np.array(absolute, dtype=np.float64, order="C")
    conflict = np.zeros(absolute.shape, bool)
    h, w = absolute.shape
    flat_abs, flat_wr = absolute.ravel(), np.asarray(wrapped, np.float64).ravel()
    idx = np.flatnonzero(np.asarray(target, bool) & ~np.isfinite(absolute))
    for _ in range(steps):
        rows, cols = np.divmod(idx, w)
        lo, hi = np.full(idx.size, np.inf), np.full(idx.size, -np.inf)
        for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            r, c = rows + dr, cols + dc
            inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            nb = np.where(inside, r * w + c, 0)
            step = _wrap(flat_wr[idx] - flat_wr[nb])
            with np.errstate(invalid="ignore"):
                usable = inside & (np.abs(step) < max_step)
            src = np.where(usable, flat_abs[nb], np.nan)
            k = np.rint((src + step - flat_wr[idx]) / TWO_PI)
            lo = np.where(np.isfinite(src), np.minimum(lo, k), lo)
            hi = np.where(np.isfinite(src), np.maximum(hi, k), hi)
        reached = np.isfinite(lo)
        agree = reached & (lo == hi)
        conflict.flat[idx[reached & ~agree]] = True
        flat_abs[idx[agree]] = flat_wr[idx[agree]] + TWO_PI * lo[agree]
        idx = idx[~reached]
    conflict |= _order_jumps(wrapped, absolute, max_step) & np.asarray(target, bool) & np.isfinite(absolute)
    absolute[conflict] = np.nan
    return absolute, conflict


def test_grow_orders_reads_only_the_front_and_finds_what_reading_every_pixel_finds():
    """Smooth phase with depth steps, noise, seeds a fringe off in places and a ragged target: the frontier
    form resolves, leaves and flags exactly the pixels the every-pixel form does, with the same phases."""
    from gearscan.recon.unwrap import grow_orders

    rng = np.random.default_rng(11)
    h, w = 90, 120
    yy, xx = np.mgrid[0:h, 0:w]
    truth = 0.5 * xx + 0.2 * yy + 3.0 * np.sin(xx / 17.0) + 2.6 * ((xx // 30) % 2) + rng.normal(0, 0.15, (h, w))
    wrapped = np.angle(np.exp(1j * truth))
    seed = np.where(rng.random((h, w)) < 0.03, truth + 2 * np.pi * (rng.random((h, w)) < 0.2), np.nan)
    target = rng.random((h, w)) < 0.9
    for steps in (1, 5, 40):
        got, got_conflict = grow_orders(wrapped, seed, target, steps=steps, max_step=1.2)
        want, want_conflict = _grow_orders_every_pixel_every_ring(wrapped, seed, target, steps, 1.2)
        np.testing.assert_array_equal(got_conflict, want_conflict)
        np.testing.assert_array_equal(np.isfinite(got), np.isfinite(want))
        np.testing.assert_allclose(got[np.isfinite(got)], want[np.isfinite(want)], rtol=0, atol=1e-9)
    assert got_conflict.any() and np.isfinite(got[np.isnan(seed)]).mean() > 0.5  # the case grows and conflicts
    # one row, one column, an infinite seed (a target, never a source), no rings, a Fortran-ordered seed
    for sl in (np.s_[:1, :], np.s_[:, :1]):
        one = seed[sl].copy()
        one.flat[-1] = np.inf
        got, got_conflict = grow_orders(wrapped[sl], one, target[sl], steps=40)
        want, want_conflict = _grow_orders_every_pixel_every_ring(wrapped[sl], one, target[sl], 40, 1.2)
        np.testing.assert_array_equal(got_conflict, want_conflict)
        np.testing.assert_array_equal(np.isfinite(got), np.isfinite(want))
    none, _ = grow_orders(wrapped, seed, target, steps=0)  # no ring: only the seeds' own fringe jumps are dropped
    np.testing.assert_array_equal(np.isfinite(none), np.isfinite(_grow_orders_every_pixel_every_ring(
        wrapped, seed, target, 0, 1.2)[0]))
    assert not (np.isfinite(none) & np.isnan(seed)).any()
    got_f, _ = grow_orders(wrapped, np.asfortranarray(seed), target, steps=40)
    np.testing.assert_array_equal(np.isfinite(got_f), np.isfinite(got_c := grow_orders(wrapped, seed, target, steps=40)[0]))
    assert np.isfinite(got_c).sum() > np.isfinite(seed).sum()


def test_grow_orders_follows_continuous_phase_and_flags_where_two_surfaces_meet():
    from gearscan.recon.unwrap import grow_orders

    truth = np.add.outer(np.zeros(30), np.linspace(0, 25.0, 40))  # 0.64 rad per column
    wrapped = np.angle(np.exp(1j * truth))
    seed = np.full(truth.shape, np.nan)
    seed[:, :5] = truth[:, :5]
    grown, conflict = grow_orders(wrapped, seed, np.ones(truth.shape, bool), steps=40)
    np.testing.assert_allclose(grown, truth, atol=1e-9)
    assert not conflict.any()
    # seeds on both ends that disagree by a fringe: the meeting line is a conflict, not a guess
    seed[:, -5:] = truth[:, -5:] + 2 * np.pi
    grown, conflict = grow_orders(wrapped, seed, np.ones(truth.shape, bool), steps=40)
    assert conflict.any() and np.isnan(grown[conflict]).all()
    ok = np.isfinite(grown)
    left = ok & (np.arange(40) < 17)[None, :]
    np.testing.assert_allclose(grown[left], truth[left], atol=1e-9)
    # a phase step above max_step (a depth step) is never crossed
    step = truth.copy()
    step[:, 20:] += 2.5
    grown, _ = grow_orders(np.angle(np.exp(1j * step)), np.where(np.arange(40) < 5, step, np.nan),
                           np.ones(truth.shape, bool), steps=40, max_step=1.2)
    assert np.isnan(grown[:, 20:]).all() and np.isfinite(grown[:, :20]).all()


def _distorted(rig, k1: float):
    import dataclasses

    dist = np.zeros(5)
    dist[0] = k1
    return dataclasses.replace(rig, projector=dataclasses.replace(rig.projector, dist=dist))


def test_unambiguous_window_is_where_the_phase_leaves_the_fringe():
    """The search along the rays against a brute-force scan (the phase projected through phase_bounds, another path,
    every 10 um of depth, interpolated): the same window, about +-1.6 mm at the axis depth with 40 px fringes."""
    rig = default_rig(96, 96)
    z_axis = float((rig.camera.T_from_world @ np.array([0.0, 0.0, 0.0, 1.0]))[2])
    depth = np.full((96, 96), z_axis)
    depth[:4] = np.nan  # no prior: no window
    lo, hi = unambiguous_depth_window(rig, 40.0, depth, margin=0.2)
    zs = z_axis + np.arange(-3.0, 3.0 + 1e-9, 0.01)
    scan = np.stack([phase_bounds(rig, DepthBounds(np.full((96, 96), z), np.full((96, 96), z)), 40.0)[0] for z in zs])
    away = np.abs(scan - scan[len(zs) // 2])  # phase distance from the prior's, per depth and pixel
    half = math.pi - 0.2

    def crossing(k0, k1):  # depth where `away` reaches `half` between samples k0 and k1, per pixel
        a0, a1 = np.take_along_axis(away, k0[None], 0)[0], np.take_along_axis(away, k1[None], 0)[0]
        return zs[k0] + (zs[k1] - zs[k0]) * (half - a0) / (a1 - a0)

    mid = len(zs) // 2
    first_far = mid + np.argmax(away[mid:] >= half, axis=0)
    first_near = mid - np.argmax(away[mid::-1] >= half, axis=0)
    lo_c, hi_c = crossing(first_near, first_near + 1), crossing(first_far - 1, first_far)
    # the pixels the projector lights at that depth (its frame is 800 rows: the image's top and bottom rows miss it)
    rays = rig.camera.pixel_rays()
    pts = rays / rays[..., 2:3] * z_axis
    uv = rig.projector.project(pts @ rig.camera.T_world_from[:3, :3].T + rig.camera.T_world_from[:3, 3])
    lit = (uv[..., 0] >= -0.5) & (uv[..., 0] <= 1279.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] <= 799.5)
    lit[:4] = False
    assert 0.5 < lit.mean() < 1.0
    assert (np.isfinite(lo) == lit).all() and (np.isfinite(hi) == lit).all()
    np.testing.assert_allclose(lo[lit], lo_c[lit], atol=1e-4)
    np.testing.assert_allclose(hi[lit], hi_c[lit], atol=1e-4)
    assert 1.3 < np.median(z_axis - lo[lit]) < 1.9 and 1.3 < np.median(hi[lit] - z_axis) < 1.9


def test_unambiguous_window_follows_the_projector_distortion():
    """A projector with barrel distortion: at both ends of each ray's window the phase, projected through the
    distorted lens by phase_bounds (world coordinates, another path), is pi - margin from the phase at the prior; the
    window is not the undistorted one (the distortion moves it by about 25 um at the image edge)."""
    rig = _distorted(default_rig(96, 96), k1=-0.3)
    z_axis = float((rig.camera.T_from_world @ np.array([0.0, 0.0, 0.0, 1.0]))[2])
    depth = np.full((96, 96), z_axis)
    lo, hi = unambiguous_depth_window(rig, 40.0, depth, margin=0.2)
    lit = np.isfinite(lo)
    assert 0.5 < lit.mean() < 1.0 and (np.isfinite(hi) == lit).all()
    assert (lo[lit] < z_axis).all() and (hi[lit] > z_axis).all()
    depth = np.where(lit, depth, np.nan)  # phase_bounds below: the lit pixels
    centre, _ = phase_bounds(rig, DepthBounds(depth, depth), 40.0)
    at_lo, _ = phase_bounds(rig, DepthBounds(lo, lo), 40.0)
    at_hi, _ = phase_bounds(rig, DepthBounds(hi, hi), 40.0)
    np.testing.assert_allclose(np.abs(at_lo - centre)[lit], math.pi - 0.2, atol=1e-5)
    np.testing.assert_allclose(np.abs(at_hi - centre)[lit], math.pi - 0.2, atol=1e-5)
    plain_lo, _ = unambiguous_depth_window(_distorted(rig, 0.0), 40.0, depth, margin=0.2)
    assert np.nanmax(np.abs(lo - plain_lo)) > 0.015
