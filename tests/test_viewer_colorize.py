"""Colour mapping of the viewer's images: the colormap's ends, masked pixels and non-finite values."""

from __future__ import annotations

import matplotlib
import numpy as np

from gearscan.viewer.log import colorize


def _expect(cmap: str, pos: np.ndarray) -> np.ndarray:
    return (matplotlib.colormaps[cmap](pos)[..., :3] * 255).astype(np.uint8)


def test_colorize_maps_lo_hi_onto_the_colormap_and_blacks_out_masked_pixels():
    values = np.array([[0.0, 0.05, 0.1, 0.2], [-1.0, 5.0, np.nan, np.inf]], np.float32)
    mask = np.array([[True, True, True, True], [True, True, True, False]])
    rgb = colorize(values, 0.0, 0.2, "viridis", mask)
    assert rgb.shape == (2, 4, 3) and rgb.dtype == np.uint8
    lut = _expect("viridis", np.linspace(0, 1, 255))
    np.testing.assert_array_equal(rgb[0, 0], lut[0])  # lo -> first colour
    np.testing.assert_array_equal(rgb[0, 3], lut[-1])  # hi -> last colour
    np.testing.assert_array_equal(rgb[0, 2], lut[127])  # midpoint
    np.testing.assert_array_equal(rgb[1, 0], lut[0])  # below lo clips
    np.testing.assert_array_equal(rgb[1, 1], lut[-1])  # above hi clips
    np.testing.assert_array_equal(rgb[1, 2], lut[0])  # NaN: low end, never a random colour
    np.testing.assert_array_equal(rgb[1, 3], [0, 0, 0])  # masked out
    # a cyclic map: -pi and +pi get (almost) the same colour, as the wrapped phase wants
    ends = colorize(np.array([[-np.pi, np.pi]], np.float32), -np.pi, np.pi, "twilight")
    assert np.abs(ends[0, 0].astype(int) - ends[0, 1]).max() <= 3
