"""Decode + reconstruct stages against the twin's truth and the CAD gear."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from gearscan.core.patterns import PatternSet
from gearscan.core.phase import classical_result
from gearscan.core.types import Burst, Frame, PhaseResult
from gearscan.recon.measure import Reconstructor

PERIOD = 40.0


def _burst(frames, angles):
    fr = tuple(Frame(f, i, 1000 * i, i) for i, f in enumerate(frames))
    return Burst(fr, tuple(angles))


@pytest.mark.parametrize("angle_deg", [0.0, 7.3])
def test_cad_constrained_unwrapping_recovers_every_fringe_order(clean_renderer, gear, angle_deg):
    """Default fringes (40 px, ~22 camera px) are far finer than the tip-root depth range allows
    for cylinder bounds; the CAD pose bounds still give the right order on >= 99.5 % of pixels."""
    angle = math.radians(angle_deg)
    surf = clean_renderer.surface(angle)
    truth = clean_renderer.truth(surf, PERIOD)
    ps = PatternSet.three_step(PERIOD)
    frames, _ = clean_renderer.render(angle, ps)
    burst = _burst(frames, (angle, angle, angle))
    result = classical_result(burst)
    rc = Reconstructor.for_gear(clean_renderer.rig, PERIOD, gear)
    m = rc(burst, result)
    mask = truth.mask
    ok = np.isfinite(m.phase_abs) & mask
    assert ok.sum() >= 0.9 * mask.sum()
    order_right = np.abs(m.phase_abs[ok] - truth.phase_abs[ok]) < 0.5
    assert order_right.all()
    # points match the truth's 3D points (camera frame -> turntable frame at the burst angle)
    from gearscan.recon.triangulate import to_turntable

    rows, cols = m.cloud.pixels.T
    sel = mask[rows, cols]
    expect = to_turntable(truth.points[rows[sel], cols[sel]], clean_renderer.rig, angle)
    err = np.linalg.norm(m.cloud.points[sel] - expect, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.01  # mm, static noise-free three-step


@pytest.fixture(scope="module")
def oversize(rig256):
    """A still burst of a gear cut at module 2.06 whose CAD says 2.0 (0.66 mm p95 off its CAD)."""
    from gearscan.core.gear import GearSpec
    from gearscan.twin.render import Optics, TwinRenderer

    renderer = TwinRenderer(rig256, GearSpec(module=2.06), Optics().noise_free())
    angle = math.radians(3.0)
    frames, _ = renderer.render(angle, PatternSet.three_step(PERIOD))
    truth = renderer.truth(renderer.surface(angle), PERIOD)
    return _burst(frames, (angle,) * 3), truth


def _true_deviation(gear, rig, truth, angle):
    from gearscan.recon.deviation import CadScorer
    from gearscan.recon.triangulate import to_turntable

    return CadScorer(gear).distances(to_turntable(truth.points[truth.mask], rig, angle))


def test_a_gear_off_its_cad_keeps_its_points_and_its_true_deviation(rig256, gear, oversize):
    """The fringe order window is the rig's whole unambiguous range around the CAD (one fringe,
    +-1.3 mm of depth here), not a fixed band: a gear 0.6 mm off its CAD is measured whole and
    its deviation vs CAD is the true one (it used to lose half its points and report half)."""
    from gearscan.recon.deviation import CadScorer
    from gearscan.recon.triangulate import to_turntable

    burst, truth = oversize
    m = Reconstructor.for_gear(rig256, PERIOD, gear)(burst, classical_result(burst))
    ok = np.isfinite(m.phase_abs) & truth.mask
    assert ok.sum() >= 0.9 * truth.mask.sum()
    assert (np.abs(m.phase_abs[ok] - truth.phase_abs[ok]) < 0.5).all()  # no point a fringe off
    # every point lies on its own pixel's true surface point: nothing pulled toward the CAD, and
    # no pixel whose blur mixes two surfaces (silhouettes, depth steps) left in the cloud
    rows, cols = m.cloud.pixels.T
    assert np.isfinite(truth.depth[rows, cols]).all()
    rays = rig256.camera.pixel_rays()
    rays = rays / rays[..., 2:3]  # camera z = 1: the true point is the ray times the true depth
    expect = to_turntable(rays[rows, cols] * truth.depth[rows, cols, None], rig256, burst.angles[0])
    err = np.linalg.norm(m.cloud.points - expect, axis=1)
    assert np.median(err) < 0.01 and err.max() < 0.2, np.percentile(err, [50, 99, 100])
    assert m.unwrap["mixed"] < 0.15 * m.unwrap["candidates"]  # the filter takes edge pixels only
    true = np.abs(_true_deviation(gear, rig256, truth, burst.angles[0]))
    measured = np.abs(CadScorer(gear).distances(m.cloud.points))
    assert np.percentile(true, 95) > 0.5  # the defect is real
    assert np.percentile(measured, 95) == pytest.approx(np.percentile(true, 95), rel=0.05)
    assert m.unwrap["points"] == len(m.cloud) and m.unwrap["unresolved"] + m.unwrap["mixed"] == (
        m.unwrap["candidates"] - m.unwrap["points"])


def test_the_depth_range_is_the_rigs(rig256, gear):
    """The stated unambiguous range is half a fringe's depth either side of the CAD, less the margin."""
    rc = Reconstructor.for_gear(rig256, PERIOD, gear, margin=0.3)
    r = rc.depth_range_mm()
    # default rig, 40 px fringes: a fringe spans ~2.8 mm of camera depth on the rim
    assert 1.1 < r["minus_median_mm"] < 1.6 and 1.1 < r["plus_median_mm"] < 1.6
    assert r["minus_min_mm"] > 0.8
    wide = Reconstructor.for_gear(rig256, 2 * PERIOD, gear, margin=0.3).depth_range_mm()
    assert wide["plus_median_mm"] == pytest.approx(2 * r["plus_median_mm"], rel=0.1)


def test_cad_free_unwrapping_keeps_only_what_the_envelope_decides(clean_renderer, gear, oversize):
    """Without a CAD surface, regions of continuous phase take the one order the gear's tip/root
    envelope admits; with fringes this fine the envelope spans ~2.4 fringes, so many regions stay
    ambiguous: they are counted, never guessed. With fringes wider than the envelope, all resolve."""
    burst, truth = oversize
    m = Reconstructor.for_gear(clean_renderer.rig, PERIOD, gear, unwrap="envelope")(burst, classical_result(burst))
    ok = np.isfinite(m.phase_abs) & truth.mask
    assert (np.abs(m.phase_abs[ok] - truth.phase_abs[ok]) < 0.5).all()
    assert m.unwrap["unresolved"] > 0.2 * m.unwrap["candidates"]
    from gearscan.core.gear import GearSpec
    from gearscan.twin.render import Optics, TwinRenderer

    wide = 120.0  # wider than the envelope's depth on this rig (min_unambiguous_period ~96 px)
    renderer = TwinRenderer(clean_renderer.rig, GearSpec(module=2.06), Optics().noise_free())
    frames, t2 = renderer.render(burst.angles[0], PatternSet.three_step(wide))
    b2 = _burst(frames, burst.angles)
    m2 = Reconstructor.for_gear(clean_renderer.rig, wide, gear, unwrap="envelope")(b2, classical_result(b2))
    ok = np.isfinite(m2.phase_abs) & t2.mask
    assert ok.sum() >= 0.95 * t2.mask.sum()
    assert (np.abs(m2.phase_abs[ok] - t2.phase_abs[ok]) < 0.5).all()


def test_reconstructor_rejects_a_mismatched_rig(clean_renderer, gear):
    rc = Reconstructor.for_gear(clean_renderer.rig, PERIOD, gear)
    z = np.zeros((10, 10), np.float32)
    res = PhaseResult(z, z, z, z, z, z)
    with pytest.raises(ValueError, match=r"phase map \(10, 10\) does not match the rig camera \(256, 256\)"):
        rc(_burst(np.zeros((3, 10, 10), np.uint8), (0, 0, 0)), res)


def test_parallel_decoder_matches_one_worker_and_keeps_its_own_networks(noisy_renderer):
    """Two bursts decoded at once on separate network copies give the single worker's results."""
    import threading

    import torch

    from gearscan.inference.decoder import Decoder

    threads = torch.get_num_threads()
    try:
        ps = PatternSet.three_step(PERIOD)
        bursts = []
        for k in range(4):
            angles = [math.radians(0.4 * k + 0.3 * i) for i in range(3)]
            frames, _ = noisy_renderer.render_sequence(angles, ps, [0, 1, 2], rng=k)
            bursts.append(_burst(frames, angles))
        cores = len(os.sched_getaffinity(0))
        assert Decoder().workers == (2 if cores >= 2 else 1)  # the CPU default
        one = Decoder(workers=1)
        assert torch.get_num_threads() == cores
        two = Decoder(workers=2)
        assert torch.get_num_threads() == max(1, cores // 2)
        pool = [two._pool.get(), two._pool.get()]
        assert pool[0].model is not pool[1].model  # MC switches dropout masks per call: never shared
        for p in pool:
            two._pool.put(p)
        results: list[PhaseResult | None] = [None] * len(bursts)

        def decode(k: int) -> None:
            results[k] = two(bursts[k])

        workers = [threading.Thread(target=decode, args=(k,)) for k in range(len(bursts))]
        for w in workers:
            w.start()
        for w in workers:
            w.join()
        for b, r in zip(bursts, results, strict=True):
            np.testing.assert_allclose(r.phase, one(b).phase, atol=1e-5)
        with pytest.raises(ValueError, match=r"model.workers: expected >= 1, got 0"):
            Decoder(workers=0)
    finally:
        torch.set_num_threads(threads)


def test_still_bursts_go_to_three_step_and_moving_ones_to_the_network(noisy_renderer):
    """The encoder span routes a still gear to three-step PS, which has no motion error."""
    from gearscan.inference.decoder import Decoder

    ps = PatternSet.three_step(PERIOD)

    def burst(step_deg):
        angles = [math.radians(3.0 + step_deg * i) for i in range(3)]
        return _burst(noisy_renderer.render_sequence(angles, ps, [0, 1, 2], rng=1)[0], angles)

    still, moving = burst(0.015), burst(0.6)  # spans 0.03 and 1.2 deg
    assert Decoder.__init__.__kwdefaults__["still_span_deg"] > 0.03  # the shipped route takes the first
    dec = Decoder(workers=1)
    r = dec(still)
    assert r.mode == "three-step" and dec.still_bursts == 1
    np.testing.assert_array_equal(r.phase, classical_result(still).phase)
    assert dec(moving).mode == "deterministic" and dec.still_bursts == 1
    # without the encoder route the network's path decodes it: there the shipped still-burst gate (0.03 rad; this
    # burst's interior departure is below it) hands it to three-step PS, and with that gate off the network's
    # own phase stands
    no_route = Decoder(workers=1, still_span_deg=0)
    assert no_route(still).mode == "three-step" and no_route.still_bursts == 0
    no_route.predictor.still_burst_rad = 0.0
    assert no_route(still).mode == "deterministic"
    with pytest.raises(ValueError, match="model.still_span_deg: expected >= 0"):
        Decoder(still_span_deg=-1)


def test_live_check_states_the_unambiguous_range(rig256, gear):
    from gearscan.cli import unambiguous_range_line

    line = unambiguous_range_line(rig256, PERIOD, gear, "cad")
    assert line.startswith("unambiguous depth range at 40 px fringes: -1.") and "mm around the CAD" in line
    free = unambiguous_range_line(rig256, PERIOD, gear, "envelope")
    assert "CAD-free unwrapping resolves every pixel from" in free and "counted, not guessed" in free
    # a projector calibrated with lens distortion: stated too (it once said "not stated"), about the same range
    import dataclasses

    lens = dataclasses.replace(rig256.projector, dist=np.array([-0.05, 0.01, 1e-4, -1e-4, 0.0]))
    distorted = unambiguous_range_line(dataclasses.replace(rig256, projector=lens), PERIOD, gear, "cad")
    import re

    def medians(text):
        return [float(v) for v in re.findall(r"fringes: -(\d+\.\d+)/\+(\d+\.\d+) mm around the CAD", text)[0]]

    assert all(abs(d - u) < 0.05 for d, u in zip(medians(distorted), medians(line), strict=True))


def test_auto_orientation_is_set_by_agreeing_still_bursts_and_honours_the_pattern_order(noisy_renderer):
    """In "auto" the Decoder takes the rig's fringe orientation from still bursts (three-step PS's
    bursts, where no motion fools the vote) once 3 agree; a reversed-order burst (shifts 0, 4pi/3,
    2pi/3) shows the negated phase and counts the same way; a disagreeing still burst keeps the vote
    per burst. With the orientation set, a reversed-order moving burst decodes as the vote decodes it."""
    from gearscan.core.phase import wrapped_rmse
    from gearscan.inference.decoder import ORIENTATION_VOTES, Decoder

    ps = PatternSet.three_step(PERIOD)

    def burst(start_deg, step_deg, order=(0, 1, 2), mirror=False):
        angles = [math.radians(start_deg + step_deg * i) for i in range(3)]
        images = noisy_renderer.render_sequence(angles, ps, list(order), rng=1)[0]
        if mirror:
            images = [np.ascontiguousarray(im[:, ::-1]) for im in images]
        fr = tuple(Frame(im, i, 1000 * i, p) for i, (im, p) in enumerate(zip(images, order, strict=True)))
        return Burst(fr, tuple(angles))

    dec = Decoder(workers=1)
    assert dec.rig_orientation is None
    for k in range(ORIENTATION_VOTES):
        order = (0, 2, 1) if k % 2 else (0, 1, 2)
        b = burst(3.0 + k, 0.01, order)
        assert b.reversed_order == bool(k % 2)
        dec(b)
    assert dec.rig_orientation == "normal" and dec.predictor.orientation == "normal"
    mirrored = Decoder(workers=1)
    for k in range(ORIENTATION_VOTES):
        mirrored(burst(3.0 + k, 0.01, mirror=True))
    assert mirrored.rig_orientation == "mirrored"
    mixed = Decoder(workers=1)
    for k in range(ORIENTATION_VOTES + 1):
        mixed(burst(3.0 + k, 0.01, mirror=k == 0))
    assert mixed.rig_orientation is None and mixed.predictor.orientation == "auto"
    # a slow reversed-order moving burst: the set orientation decodes it as the per-burst vote does
    slow = burst(5.0, 0.1, (0, 2, 1))
    set_result, vote_result = dec(slow), mixed(slow)
    assert wrapped_rmse(set_result.phase, vote_result.phase) < 1e-5


def _fabricated_network_result(result: PhaseResult, frames: np.ndarray, full_scale: float):
    """``result`` relabelled as a network's, with a confident fringe invented where the frames are dark."""
    from dataclasses import replace

    from gearscan.core.phase import frame_swing

    dark = 2.0 * frame_swing(frames.astype(np.float32) / full_scale) < 0.02
    m = np.where(dark, np.float32(0.5) * np.sin(result.phase + 1.0), result.M).astype(np.float32)
    d = np.where(dark, np.float32(0.5) * np.cos(result.phase + 1.0), result.D).astype(np.float32)
    sigma = np.where(dark, np.float32(0.05), result.sigma_total).astype(np.float32)
    fake = replace(result, M=m, D=d, phase=np.arctan2(m, d).astype(np.float32), sigma_total=sigma, mode="deterministic")
    return fake, dark


def test_a_networks_pixels_need_fringes_in_their_own_frames(clean_renderer, gear):
    """A decoder that invents fringes where the frames are dark (what the network does at shadow borders: it
    was trained on the truth mask only) gets no point there; the pixels are counted as unsupported. Three-step
    PS, whose modulation is the frames' own, is untouched by the test."""
    from gearscan.core.phase import fringe_support

    angle = math.radians(2.0)
    frames, _ = clean_renderer.render(angle, PatternSet.three_step(PERIOD))
    burst = _burst(frames, (angle,) * 3)
    three = classical_result(burst)
    fake, dark = _fabricated_network_result(three, burst.images, burst.full_scale)
    assert dark.sum() > 1000  # the scene has shadow and background to invent on
    guarded = Reconstructor.for_gear(clean_renderer.rig, PERIOD, gear, network_support_px=2)
    open_ = Reconstructor.for_gear(clean_renderer.rig, PERIOD, gear, network_support_px=None)
    m_guard, m_open = guarded(burst, fake), open_(burst, fake)
    support = fringe_support(burst.images, burst.full_scale, guarded.min_modulation, 2)
    rows, cols = m_guard.cloud.pixels.T
    assert support[rows, cols].all()
    invented = dark & (fake.sigma_total <= open_.max_sigma)
    assert m_open.unwrap["candidates"] - m_guard.unwrap["candidates"] == m_guard.unwrap["unsupported"]
    assert m_guard.unwrap["unsupported"] >= invented.sum()
    assert m_open.unwrap["unsupported"] == 0
    # three-step PS, and any decoder that reads its modulation off the frames: the same points with and without it
    from dataclasses import replace

    for classical in (three, replace(three, mode="aia"), replace(three, mode="twin prior")):
        a, b = guarded(burst, classical), open_(burst, classical)
        assert a.unwrap["unsupported"] == 0
        np.testing.assert_array_equal(a.cloud.pixels, b.cloud.pixels)
    # Monte Carlo results are a network's too
    assert guarded(burst, replace(fake, mode="mc20")).unwrap["unsupported"] == m_guard.unwrap["unsupported"]


@pytest.mark.parametrize("mode, network", [("deterministic", True), ("mc20", True), ("three-step", False),
                                           ("aia", False), ("hilbert", False), ("twin prior", False), ("mcx", False)])
def test_which_results_come_from_a_network(mode, network):
    r = PhaseResult(*(np.zeros((2, 2), np.float32) for _ in range(6)), mode=mode)
    assert r.from_network is network


def _shipped_network_still_burst(rig, seed: int):
    """The shipped network's decode of a still burst of a val-split gear (25 teeth: no test gear in a test of the
    code), with the still-burst gate off: ``(gear, burst, result, distances)``, ``distances(m)`` of a measurement's
    points to the true gear surface (mm)."""
    from dataclasses import replace

    from gearscan.core.gear import GearSpec
    from gearscan.evaluate import surface_distances
    from gearscan.inference.predictor import Predictor
    from gearscan.recon.deviation import SurfaceDistance
    from gearscan.twin.render import Optics, TwinRenderer

    gear = GearSpec(teeth=25)
    angle = math.radians(1.0)
    frames, _ = TwinRenderer(rig, gear, Optics()).render(angle, PatternSet.three_step(PERIOD), np.random.default_rng(seed))
    burst = _burst(frames, (angle,) * 3)
    net = replace(Predictor.load(orientation="normal", still_burst_rad=0.0).predict(frames, 0, full_scale=burst.full_scale),
                  angle=angle)
    surface = SurfaceDistance(gear.mesh()).scene
    return gear, burst, net, lambda m: surface_distances(surface, m.cloud.points)


def test_the_support_test_brings_the_shipped_networks_still_cloud_toward_the_true_surface(rig256):
    """The shipped network on a still burst (a val-split gear): the points the fringe-support test drops lie
    far off the true surface, and the cloud it keeps is closer to it than the unguarded one."""
    gear, burst, net, distances = _shipped_network_still_burst(rig256, seed=3)

    m_open = Reconstructor.for_gear(rig256, PERIOD, gear, network_support_px=None)(burst, net)
    m_guard = Reconstructor.for_gear(rig256, PERIOD, gear, network_support_px=2)(burst, net)
    d_open, d_guard = distances(m_open), distances(m_guard)
    kept = {tuple(p) for p in m_guard.cloud.pixels}
    dropped = np.array([tuple(p) not in kept for p in m_open.cloud.pixels])
    assert m_guard.unwrap["unsupported"] > 0 and dropped.sum() > 100
    rms = lambda d: float(np.sqrt(np.mean(d.astype(np.float64) ** 2)))  # noqa: E731
    assert rms(d_open[dropped]) > 2 * rms(d_open[~dropped])  # 122 against 43 um when written
    assert rms(d_guard) < 0.9 * rms(d_open)  # 43 against 56 um when written


def test_auto_orientation_comes_from_the_calibration_and_still_bursts_that_outvote_it_win(noisy_renderer, caplog):
    """With a rig calibration (replay, live, inspect) "auto" decodes by the rig's geometric fringe orientation from
    the first burst: a burst turning 3 deg per frame, whose fringes drift about a third of a period and fool the
    per-burst vote, decodes as the rig is. Still bursts whose frames read the other way (a camera mirroring its
    images) outvote the calibration, and the change is logged."""
    from gearscan.core.phase import wrapped_rmse
    from gearscan.core.rig import fringe_orientation
    from gearscan.inference.decoder import ORIENTATION_VOTES, Decoder
    from gearscan.inference.predictor import frames_to_tensor, fringe_phase_decreases_along_columns

    ps = PatternSet.three_step(PERIOD)
    rig = noisy_renderer.rig

    def burst(start_deg, step_deg, mirror=False):
        angles = [math.radians(start_deg + step_deg * i) for i in range(3)]
        images, truths = noisy_renderer.render_sequence(angles, ps, [0, 1, 2], rng=1)
        if mirror:
            images = [np.ascontiguousarray(im[:, ::-1]) for im in images]
        fr = tuple(Frame(im, i, 1000 * i, p) for i, (im, p) in enumerate(zip(images, (0, 1, 2), strict=True)))
        return Burst(fr, tuple(angles)), truths[0]

    fast, truth = burst(3.0, 3.0)
    assert fringe_phase_decreases_along_columns(frames_to_tensor(fast.images, fast.full_scale))  # the vote misreads it
    calibrated, voted = Decoder(workers=1), Decoder(workers=1)
    assert calibrated.adopt_rig(rig) == fringe_orientation(rig) and fringe_orientation(rig).orientation == "normal"
    assert calibrated.rig_orientation == "normal" and calibrated.orientation_status() == "fringes normal (rig calibration)"
    assert Decoder(workers=1, orientation="mirrored").adopt_rig(rig) is None  # a set orientation stays set
    assert Decoder(classical=True).adopt_rig(rig) is None
    a, v = calibrated(fast), voted(fast)
    normal = Decoder(workers=1, orientation="normal")(fast)
    assert wrapped_rmse(a.phase, normal.phase) < 1e-6
    m = truth.mask
    assert wrapped_rmse(a.phase[m], truth.phase[m]) < 0.5 * wrapped_rmse(v.phase[m], truth.phase[m])
    # still bursts of mirrored images outvote the calibration: the network reads the frames
    with caplog.at_level("WARNING", logger="gearscan.inference.decoder"):
        for k in range(ORIENTATION_VOTES):
            calibrated(burst(10.0 + k, 0.0, mirror=True)[0])
    assert calibrated.rig_orientation == "mirrored" and calibrated.summary()["orientation_source"] == "still bursts"
    assert calibrated.predictor.orientation == "mirrored"
    assert any("rig calibration normal" in r.getMessage() for r in caplog.records)
    assert calibrated.orientation_status() == "fringes mirrored (from 3 still bursts, against the rig calibration)"
    # the next run (adopt_rig at its start) forgets this run's votes and starts from its own calibration
    assert calibrated.adopt_rig(rig).orientation == "normal"
    assert calibrated.summary()["orientation_votes"] == {"normal": 0, "mirrored": 0}
    assert calibrated.orientation_status() == "fringes normal (rig calibration)"
    assert calibrated.predictor.orientation == "normal"


def test_the_keep_bound_picks_points_not_fringe_orders(rig256):
    """With ``unwrap_max_sigma=inf`` the sigma bound is applied after unwrapping (benchmarks/keep_bound_rule.md): on
    the shipped network's still burst the bounded cloud is the unbounded one on the pixels within the bound, with the
    same fringe orders (the mixed-pixel filter off, which reads the kept points' depths). With the shipped settings
    (since session 45 the unwrapper sees the keep bound's pixels, the val choice on the wide sample) no point lies a
    fringe order off the true surface. At 0.3 rad with the bound first, the holes hid the neighbours that expose a
    wrong order (on val 2,731 still-burst points beyond 0.5 mm); at the shipped 0.7 rad they do not on this burst."""
    from gearscan.recon.measure import MAX_SIGMA_RAD

    gear, burst, net, distances = _shipped_network_still_burst(rig256, seed=4)
    kw = {"mixed_border_px": None, "unwrap_max_sigma": math.inf}  # v9: no per-burst support test
    bounded = Reconstructor.for_gear(rig256, PERIOD, gear, **kw)(burst, net)
    unbounded = Reconstructor.for_gear(rig256, PERIOD, gear, max_sigma=math.inf, **kw)(burst, net)
    assert bounded.unwrap["points"] < unbounded.unwrap["points"]  # the bound drops points on this burst ...
    within = np.isfinite(unbounded.phase_abs) & (net.sigma_total <= MAX_SIGMA_RAD)
    np.testing.assert_array_equal(np.isfinite(bounded.phase_abs), within)  # ... and only those beyond it
    np.testing.assert_array_equal(bounded.phase_abs[within], unbounded.phase_abs[within])  # the same orders
    shipped = Reconstructor.for_gear(rig256, PERIOD, gear)(burst, net)  # every setting as shipped, mixed pixels dropped
    d = distances(shipped)
    assert len(d) > 30000 and (d > 0.5).sum() == 0  # no point a fringe order (about 2.8 mm) off
    with pytest.raises(ValueError, match="unwrap_max_sigma"):
        Reconstructor.for_gear(rig256, PERIOD, gear, max_sigma=0.5, unwrap_max_sigma=0.3)
