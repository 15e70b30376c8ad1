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
