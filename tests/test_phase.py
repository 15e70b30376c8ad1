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


def _gamma_stack(gamma: float, noise_dn: float, rng: np.random.Generator, size: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """A still three-step stack of a smoothly curved surface lit by fringes through a projector ``gamma``
    (``(0.5 + 0.5 cos)^gamma``: non-sinusoidal), 8-bit with noise; and its true phase."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    phi = 2 * math.pi * xx / 21 + 0.0004 * (xx - size / 2) ** 2 + 0.3 * np.sin(yy / 40)  # a bending surface
    shade = 40 + 150 * (0.8 + 0.2 * np.cos(yy / 70))
    frames = np.stack([20 + shade * (0.5 + 0.5 * np.cos(phi + d)) ** gamma
                       for d in (0, 2 * math.pi / 3, 4 * math.pi / 3)])
    frames = np.clip(np.round(frames + rng.normal(0, noise_dn, frames.shape)), 0, 255).astype(np.uint8)
    return frames, wrap(phi)


def _three_step_harmonic_ratio(gamma: float) -> float:
    """The r of ``phi - r sin(3 phi)`` that three-step PS makes of a ``(0.5 + 0.5 cos)^gamma`` fringe, from its
    Fourier harmonics (2 and 4 alias onto the fundamental with opposite signs of the 3 phi term)."""
    t = np.linspace(0, 2 * math.pi, 4096, endpoint=False)
    c = np.fft.rfft((0.5 + 0.5 * np.cos(t)) ** gamma)
    return float((c[2].real - c[4].real) / c[1].real)


@pytest.mark.parametrize("gamma, mirrored, size", [(0.8, False, 256), (1.2, False, 256), (1.3, False, 256),
                                                   (1.2, True, 256), (1.2, False, 640)])
def test_harmonic_correction_removes_three_steps_gamma_error(gamma, mirrored, size):
    """Non-sinusoidal fringes (a projector gamma) give three-step PS an error ``-r sin(3 phi)``; the ratio read
    off the phase map's own gradient matches the fringe's Fourier harmonics, and removing it brings the phase
    to the noise floor of sinusoidal fringes. Beyond 512 x 512 px the ratio is read in windows spread over the image."""
    from gearscan.core.phase import harmonic_correction

    rng = np.random.default_rng(11)
    frames, truth = _gamma_stack(gamma, 1.5, rng, size)
    floor = wrapped_rmse(three_step(_gamma_stack(1.0, 1.5, np.random.default_rng(11), size)[0], 255)[0], truth)
    if mirrored:  # the phase falling along the columns (a mirrored rig)
        frames, truth = np.ascontiguousarray(frames[:, :, ::-1]), np.ascontiguousarray(truth[:, ::-1])
    phase, m, d = three_step(frames, 255)
    lit = np.hypot(m, d) >= 0.05
    corrected, r = harmonic_correction(phase, lit)
    expected = _three_step_harmonic_ratio(gamma)
    assert abs(expected) > 0.02  # a visible error to remove
    assert r == pytest.approx(expected, abs=0.15 * abs(expected) + 0.006)  # the dead zone shrinks it by 0.006
    before, after = wrapped_rmse(phase, truth), wrapped_rmse(corrected, truth)
    assert before > 2.5 * floor
    assert after < 0.5 * before and after < 1.6 * floor


def test_harmonic_correction_leaves_sinusoidal_fringes_alone():
    """Sinusoidal fringes: no ratio is found beyond the dead zone, the phase comes back unchanged."""
    from gearscan.core.phase import harmonic_correction, still_phase

    frames, _ = _gamma_stack(1.0, 2.0, np.random.default_rng(5))
    phase, m, d = three_step(frames, 255)
    corrected, r = harmonic_correction(phase, np.hypot(m, d) >= 0.05)
    assert r == 0.0
    np.testing.assert_array_equal(corrected, phase)
    p, m2, d2 = still_phase(m, d)
    np.testing.assert_array_equal(p, np.arctan2(m, d).astype(np.float32))
    np.testing.assert_array_equal(m2, m)


def test_harmonic_correction_needs_fringes_to_read_and_says_so_on_bad_input():
    from gearscan.core.phase import harmonic_correction, harmonic_ratio

    phase = np.zeros((64, 64))
    assert harmonic_ratio(phase, np.zeros((64, 64), bool)) is None  # nothing lit: no estimate
    corrected, r = harmonic_correction(phase, np.zeros((64, 64), bool))
    assert r == 0.0 and corrected is not None
    with pytest.raises(ValueError, match="expected two"):
        harmonic_ratio(phase, np.zeros((32, 64), bool))


def test_still_routes_decode_with_the_correction():
    """The encoder's still route (Decoder) and a still burst the gate takes both return the corrected phase:
    on gamma-1.2 fringes closer to the truth than plain three-step PS, with the modulation kept."""
    from gearscan.core.phase import still_phase
    from gearscan.core.types import Burst, Frame
    from gearscan.inference.decoder import Decoder

    frames, truth = _gamma_stack(1.2, 1.5, np.random.default_rng(2))
    burst = Burst(tuple(Frame(f, i, 0, i) for i, f in enumerate(frames)), (0.3, 0.3, 0.3))
    routed = Decoder()(burst)
    plain, m, d = three_step(frames, 255)
    expected, _, _ = still_phase(m, d)
    assert routed.mode == "three-step"
    np.testing.assert_allclose(routed.phase, expected, atol=1e-6)
    np.testing.assert_allclose(routed.modulation, np.hypot(m, d), rtol=1e-5, atol=1e-6)
    assert wrapped_rmse(routed.phase, truth) < 0.5 * wrapped_rmse(plain, truth)


def test_fringe_support_needs_fringes_on_every_pixel_around():
    """Left of column 40 the frames swing (2B/S = 0.5), right of it they are dark: support ends ``px`` short
    of the dark side, the image border does not erode it, and bad input is named."""
    from gearscan.core.phase import frame_swing, fringe_support

    h, w = 32, 64
    phi = np.linspace(0, 8 * np.pi, w)[None, :].repeat(h, 0)
    frames = np.stack([100 + 60 * np.cos(phi + k * 2 * np.pi / 3) for k in range(3)])
    frames[:, :, 40:] = 100.0  # lit, no fringes
    s0 = fringe_support(frames, 255.0, 0.05, 0)
    s2 = fringe_support(frames, 255.0, 0.05, 2)
    assert s0[:, :40].all() and not s0[:, 40:].any()
    assert s2[:, :38].all() and not s2[:, 38:].any()  # the border rows and column 0 stay supported
    raw12 = np.round(frames * 16).astype(np.uint16)  # the same scene from a 12-bit camera, raw integers
    np.testing.assert_array_equal(fringe_support(raw12, 4095.0, 0.05, 2), s2)
    # the threshold is frame_swing's, wherever a pixel is not within rounding of it
    rng = np.random.default_rng(5)
    noisy = rng.integers(0, 256, (3, 300, 200)).astype(np.uint8)  # two row blocks
    want = 2.0 * frame_swing(noisy.astype(np.float64) / 255.0)
    clear = np.abs(want - 0.3) > 1e-4
    np.testing.assert_array_equal(fringe_support(noisy, 255.0, 0.3, 0)[clear], (want >= 0.3)[clear])
    as_float = frames.astype(np.float32)
    before = as_float.copy()
    fringe_support(as_float, 255.0, 0.05, 2)
    np.testing.assert_array_equal(as_float, before)  # the caller's frames are only read
    with pytest.raises(ValueError, match="full_scale"):
        fringe_support(frames, 0.0, 0.05, 1)
    with pytest.raises(ValueError, match="min_modulation"):
        fringe_support(frames, 255.0, -0.1, 1)
    with pytest.raises(ValueError, match="images"):
        fringe_support(frames[:2], 255.0, 0.05, 1)
    with pytest.raises(ValueError, match="px"):
        fringe_support(frames, 255.0, 0.05, -1)
