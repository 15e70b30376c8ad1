"""The twin prior at run time: CAD-predicted fringe shifts solve a moving burst where the model holds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gearscan.core.gear import GearSpec
from gearscan.core.patterns import PatternSet
from gearscan.core.phase import phase_error, three_step
from gearscan.core.rig import default_rig
from gearscan.twin.defects import GearDefects
from gearscan.twin.prior import TwinPrior, blend
from gearscan.twin.render import Optics, TwinRenderer

PERIOD = 40.0
GEAR = GearSpec(teeth=20, module=2.0)


@pytest.fixture(scope="module")
def rig():
    return default_rig(160, 160, working_radius=GEAR.pitch_radius)


@pytest.fixture(scope="module")
def prior(rig):
    return TwinPrior(rig, GEAR, PERIOD)


def _burst(renderer, angles_deg, seed=0):
    angles = np.radians(angles_deg)
    frames, truths = renderer.render_sequence(list(angles), PatternSet.three_step(PERIOD), [0, 1, 2], seed)
    return frames, truths[0], angles


def _rms(e):
    return float(np.sqrt(np.mean(np.square(e))))


def test_a_still_burst_is_three_step_exactly(rig, prior):
    """No motion, no predicted shift: the prior's solve is three-step PS, so it cannot make a still gear worse."""
    frames, truth, angles = _burst(TwinRenderer(rig, GEAR, Optics()), [4.0, 4.0, 4.0])
    maps = prior.maps(angles)
    np.testing.assert_allclose(maps.gain[maps.clean], 1.0, atol=1e-6)
    res, usable = prior.decode(frames, 255, angles)
    ref, _, _ = three_step(frames, 255)
    m = truth.mask
    assert usable[m].mean() > 0.95
    assert np.abs(phase_error(res.phase, ref)[usable]).max() < 1e-4


def test_a_moving_burst_is_solved_where_the_cad_sees_one_surface(rig, prior):
    """0.6 deg per frame: three-step PS is far off; on the pixels the prior calls usable its solve is
    within the noise of a still burst, and the blend never loses to the network it falls back on."""
    renderer = TwinRenderer(rig, GEAR, Optics())
    frames, truth, angles = _burst(renderer, [4.0, 4.6, 5.2])
    res, usable = prior.decode(frames, 255, angles)
    ref, _, _ = three_step(frames, 255)
    on = truth.mask & usable
    assert on.sum() > 0.3 * truth.mask.sum()
    e_prior = _rms(phase_error(res.phase, truth.phase)[on])
    e_three = _rms(phase_error(ref, truth.phase)[on])
    assert e_three > 0.3 and e_prior < 0.06, (e_three, e_prior)
    assert np.isfinite(res.sigma_total[on]).all() and np.isinf(res.sigma_total[~usable]).all()
    # the blend takes the prior where usable and the other result elsewhere, pixel for pixel
    from gearscan.core.types import PhaseResult

    z = np.zeros_like(res.phase)
    other = PhaseResult(z + 1.0, z, z, z, z, z, mode="deterministic")
    mixed = blend(res, usable, other)
    assert np.array_equal(mixed.phase[usable], res.phase[usable]) and (mixed.phase[~usable] == 1.0).all()


def test_a_gear_off_its_cad_keeps_its_own_phase(rig, prior):
    """The prior gives only phase changes: a gear cut at module 2.03 (0.3 mm off its CAD on the rim)
    decodes to its own phase, not to the CAD's."""
    renderer = TwinRenderer(rig, GEAR, Optics(), defects=GearDefects(module=2.03))
    frames, truth, angles = _burst(renderer, [4.0, 4.6, 5.2])
    res, usable = prior.decode(frames, 255, angles)
    on = truth.mask & usable
    cad_phase = prior.renderer.truth(prior.renderer.surface(float(angles[0])), PERIOD).phase
    assert _rms(phase_error(res.phase, truth.phase)[on]) < 0.08
    assert _rms(phase_error(cad_phase, truth.phase)[on & np.isfinite(cad_phase)]) > 0.25  # the CAD's is far off


def test_bad_inputs_are_named(prior):
    with pytest.raises(ValueError, match="angles"):
        prior.maps((0.0, math.nan, 0.1))
    with pytest.raises(ValueError, match="frames"):
        prior.decode(np.zeros((2, 160, 160)), 255, (0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="period_px"):
        TwinPrior(prior.rig, GEAR, 0.0)


def test_a_reversed_burst_is_solved_with_its_own_shifts(rig, prior):
    """A burst shown 0, 2, 1 (projector.alternate_order): given its nominal shifts, the prior solves
    it as well as the forward burst of the same motion; read as forward it would measure -phi."""
    from gearscan.core.phase import THREE_STEP_SHIFTS

    renderer = TwinRenderer(rig, GEAR, Optics())
    angles = np.radians([4.0, 4.6, 5.2])
    frames, truths = renderer.render_sequence(list(angles), PatternSet.three_step(PERIOD), [0, 2, 1], 0)
    res, usable = prior.decode(frames, 255, angles, nominal=THREE_STEP_SHIFTS[[0, 2, 1]])
    fwd_frames, fwd_truth, _ = _burst(renderer, [4.0, 4.6, 5.2])
    fwd, fwd_usable = prior.decode(fwd_frames, 255, angles)
    ok = usable & truths[0].mask
    assert ok.sum() > 500
    assert _rms(phase_error(res.phase, truths[0].phase)[ok]) < 1.5 * _rms(phase_error(fwd.phase, fwd_truth.phase)[fwd_usable & fwd_truth.mask]) + 0.01
    assert _rms(phase_error(prior.decode(frames, 255, angles)[0].phase, truths[0].phase)[ok]) > 1.0
