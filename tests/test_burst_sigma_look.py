"""The per-burst depth-sigma look's helpers (scripts/burst_sigma_look.py)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from burst_sigma_look import edge_distance, summary  # noqa: E402


def test_edge_distance_counts_pixels_to_the_nearest_pixel_without_a_point():
    rows, cols = np.mgrid[2:9, 2:9]  # a 7 x 7 block of points in a 12 x 12 image
    pixels = np.stack([rows.ravel(), cols.ravel()], axis=1)
    d = edge_distance(pixels, (12, 12))
    border = (rows.ravel() == 2) | (rows.ravel() == 8) | (cols.ravel() == 2) | (cols.ravel() == 8)
    np.testing.assert_allclose(d[border], 1.0)
    centre = (rows.ravel() == 5) & (cols.ravel() == 5)
    assert d[centre][0] == pytest.approx(4.0, abs=0.5) and d[~border].min() > 1.0


def test_summary_gives_the_scale_the_body_or_the_tail_needs():
    rng = np.random.default_rng(0)
    honest = np.abs(rng.standard_normal(200_000))
    s = summary(honest)
    assert s["median"] == pytest.approx(0.6745, abs=0.01) and s["beyond_2sigma"] == pytest.approx(0.0455, abs=0.002)
    assert s["needed_scale"] == pytest.approx(1.0, abs=0.02)
    wide = summary(2.0 * honest)  # a sigma half the error's size needs twice itself
    assert wide["needed_scale"] == pytest.approx(2.0, abs=0.04)
    assert summary(np.zeros(0)) == {"points": 0}
