"""Decode + reconstruct stages against the twin's truth and the CAD gear."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from gearscan.measure import Reconstructor, classical_result
from gearscan.projector.patterns import PatternSet
from gearscan.types import Burst, Frame, PhaseResult

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
    assert ok.sum() >= 0.995 * mask.sum()
    order_right = np.abs(m.phase_abs[ok] - truth.phase_abs[ok]) < 0.5
    assert order_right.all()
    # points match the truth's 3D points (camera frame -> turntable frame at the burst angle)
    from gearscan.recon.triangulate import to_turntable

    rows, cols = m.cloud.pixels.T
    sel = mask[rows, cols]
    expect = to_turntable(truth.points[rows[sel], cols[sel]], clean_renderer.rig, angle)
    err = np.linalg.norm(m.cloud.points[sel] - expect, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.01  # mm, static noise-free three-step


def test_cylinder_bounds_refuse_to_guess_with_fine_fringes(clean_renderer, gear):
    ps = PatternSet.three_step(PERIOD)
    frames, truth = clean_renderer.render(0.0, ps)
    burst = _burst(frames, (0.0, 0.0, 0.0))
    rc = Reconstructor.for_gear(clean_renderer.rig, PERIOD, gear, cad_tolerance_mm=None)
    m = rc(burst, classical_result(burst))
    ok = np.isfinite(m.phase_abs) & truth.mask
    # most pixels are ambiguous (reported, not guessed); the few kept are right
    assert ok.sum() < 0.5 * truth.mask.sum()
    assert (np.abs(m.phase_abs[ok] - truth.phase_abs[ok]) < 0.5).all()


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

    from gearscan.measure import Decoder

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
    from gearscan.measure import Decoder

    ps = PatternSet.three_step(PERIOD)

    def burst(step_deg):
        angles = [math.radians(3.0 + step_deg * i) for i in range(3)]
        return _burst(noisy_renderer.render_sequence(angles, ps, [0, 1, 2], rng=1)[0], angles)

    still, moving = burst(0.02), burst(0.6)  # spans 0.04 and 1.2 deg
    dec = Decoder(workers=1)
    r = dec(still)
    assert r.mode == "three-step" and dec.still_bursts == 1
    np.testing.assert_array_equal(r.phase, classical_result(still).phase)
    assert dec(moving).mode == "deterministic" and dec.still_bursts == 1
    assert Decoder(workers=1, still_span_deg=0)(still).mode == "deterministic"
    with pytest.raises(ValueError, match="model.still_span_deg: expected >= 0"):
        Decoder(still_span_deg=-1)
