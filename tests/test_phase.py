"""Classical decoders on synthetic fringes with known phase (scikit-image unwrap style)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gearscan.core.phase import (
    decode_md,
    decode_phase,
    phase_error,
    three_step,
    wrap,
    wrapped_rmse,
)


@pytest.mark.parametrize("steps", [3, 4, 18])
def test_n_step_recovers_phase_and_normalised_modulation(steps):
    rng = np.random.default_rng(0)
    phi = rng.uniform(-math.pi, math.pi, (20, 30))
    a, b, s = 100.0, 60.0, 255.0
    shifts = 2 * math.pi * np.arange(steps) / steps
    imgs = a + b * np.cos(phi[None] + shifts[:, None, None])
    phase, m, d = decode_phase(imgs, shifts, s)
    assert np.abs(phase_error(phase, phi)).max() < 1e-5
    assert np.allclose(np.hypot(m, d), 2 * b / s, rtol=1e-5)


def test_three_step_matches_closed_form():
    rng = np.random.default_rng(1)
    i1, i2, i3 = rng.uniform(0, 255, (3, 8, 8))
    phase, _, _ = three_step(np.stack([i1, i2, i3]), 255)
    # delta = 0, 2pi/3, 4pi/3: phi = atan2(sqrt(3)(I3 - I2), 2 I1 - I2 - I3)
    ref = np.arctan2(math.sqrt(3) * (i3 - i2), 2 * i1 - i2 - i3)
    assert np.abs(phase_error(phase, ref)).max() < 1e-5


def test_wrap_aware_error_and_rmse():
    a = np.array([math.pi - 0.01, -math.pi + 0.01, 0.5])
    b = np.array([-math.pi + 0.01, math.pi - 0.01, 0.4])
    assert np.allclose(phase_error(a, b), [-0.02, 0.02, 0.1])
    assert wrapped_rmse(a, b, np.array([True, True, False])) == pytest.approx(0.02)
    assert np.allclose(wrap(np.array([3 * math.pi / 2])), [-math.pi / 2])


def test_input_checks_name_the_problem():
    with pytest.raises(ValueError, match=r"expected \(N, H, W\)"):
        decode_md(np.zeros((4, 4)), np.zeros(3), 255)
    with pytest.raises(ValueError, match="3 frames but 4 shifts"):
        decode_md(np.zeros((3, 4, 4)), np.zeros(4), 255)
    with pytest.raises(ValueError, match="mask selects no pixels"):
        wrapped_rmse(np.zeros(3), np.zeros(3), np.zeros(3, bool))


@pytest.mark.parametrize("noise", [0.002, 0.006, 0.02])
def test_still_frame_noise_reads_the_noise_off_a_still_stack(noise):
    """The frames' sum of a still three-step stack has no fringes left; the noise estimate on it recovers the
    per-frame noise under shading, fringes and an outline, within 5 %."""
    from gearscan.core.phase import still_frame_noise

    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[0:200, 0:240].astype(np.float32)
    shade = (0.35 + 0.1 * np.sin(yy / 30)) * (np.hypot(yy - 100, xx - 120) < 90)  # a lit disc on black
    phi = 2 * math.pi * xx / 13 + 0.002 * (xx - 120) ** 2 / 10
    frames = np.stack([shade * (1 + 0.8 * np.cos(phi + d)) for d in (0, 2 * math.pi / 3, 4 * math.pi / 3)])
    noisy = frames + rng.normal(0, noise, frames.shape).astype(np.float32)
    assert still_frame_noise(noisy, shade > 0) == pytest.approx(noise, rel=0.05)
    assert still_frame_noise(noisy[:, :10, :10]) is None  # too few pixels for a verdict
    with pytest.raises(ValueError, match="images"):
        still_frame_noise(noisy[0])


def _still_stack(rng: np.random.Generator, noise_dn: float) -> np.ndarray:
    """A still three-step stack in 8-bit DN (uint8): shaded fringes on a disc, ``noise_dn`` Gaussian noise."""
    yy, xx = np.mgrid[0:160, 0:200].astype(np.float32)
    shade = 90 * (np.hypot(yy - 80, xx - 100) < 70)
    frames = np.stack([shade * (1 + 0.7 * np.cos(2 * math.pi * xx / 16 + d)) for d in (0, 2 * math.pi / 3, 4 * math.pi / 3)])
    return np.clip(np.round(frames + rng.normal(0, noise_dn, frames.shape)), 0, 255).astype(np.uint8)


def test_a_still_bursts_sigma_is_the_scatter_of_repeated_captures():
    """A still burst's three-step sigma from the noise measured on it matches how its phase scatters between two
    captures of the same scene (robust z ~ 1); the assumed 1 DN of :func:`classical_result` is 3x too confident
    at 3 DN of noise. Through the Decoder, a burst the encoder saw standing still gets the measured sigma."""
    from gearscan.core.phase import still_result, still_three_step_result, three_step_result
    from gearscan.core.types import Burst, Frame
    from gearscan.inference.decoder import Decoder

    rng = np.random.default_rng(4)
    a, b = _still_stack(rng, 3.0), _still_stack(rng, 3.0)
    measured, assumed = still_three_step_result(a, 255), three_step_result(a, 255)
    lit = measured.modulation >= 0.1
    diff = phase_error(measured.phase, three_step(b, 255)[0])[lit]
    z_measured = 1.4826 * np.median(np.abs(diff / (np.sqrt(2) * measured.sigma_total[lit])))
    z_assumed = 1.4826 * np.median(np.abs(diff / (np.sqrt(2) * assumed.sigma_total[lit])))
    assert z_measured == pytest.approx(1.0, abs=0.1) and z_assumed == pytest.approx(3.0, rel=0.15)
    np.testing.assert_array_equal(measured.phase, assumed.phase)  # the same decode, only the sigma differs
    burst = Burst(tuple(Frame(f, i, 0, i) for i, f in enumerate(a)), (0.3, 0.3, 0.3))
    np.testing.assert_allclose(still_result(burst).sigma_total, measured.sigma_total)
    routed = Decoder()(burst)
    assert routed.mode == "three-step"
    np.testing.assert_allclose(routed.sigma_total, measured.sigma_total)
