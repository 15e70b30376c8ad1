"""Gamma pre-compensation from a measured projector response curve.

A projector's light output is not linear in the grey level it is sent (gamma ~2.2 plus a
black level). Fringes must be sinusoidal in LIGHT, so the pattern is passed through the
inverse response before display. Measure the response by projecting a few uniform grey
levels and averaging the camera intensity on a white target; then::

    gc = GammaCorrection.from_measurements(levels, measured)
    shown = gc.apply(pattern)           # uint8 pattern -> pre-compensated uint8

The measured curve is made monotone (running maximum) and normalised to [0, 1]; the
inverse is a lookup table over all input codes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class GammaError(ValueError):
    """The measured response cannot be inverted (too few points, not increasing)."""


@dataclass(frozen=True)
class GammaCorrection:
    """Lookup table ``lut[code] -> code to send`` for ``bit_depth``-bit patterns."""

    lut: np.ndarray
    bit_depth: int = 8

    @classmethod
    def from_measurements(cls, levels: np.ndarray, measured: np.ndarray, bit_depth: int = 8) -> GammaCorrection:
        """levels: grey codes sent (K,), measured: light seen for each (K,), any units."""
        levels = np.asarray(levels, dtype=np.float64)
        measured = np.asarray(measured, dtype=np.float64)
        if levels.shape != measured.shape or levels.ndim != 1:
            raise GammaError(f"levels and measured must be equal 1-D arrays, got {levels.shape} and {measured.shape}")
        if levels.size < 3:
            raise GammaError(f"need >= 3 measured levels, got {levels.size}")
        order = np.argsort(levels)
        levels, measured = levels[order], np.maximum.accumulate(measured[order])
        span = measured[-1] - measured[0]
        if not span > 0:
            raise GammaError(f"measured response is flat ({measured[0]:g}..{measured[-1]:g}): projector off or camera saturated?")
        full = (1 << bit_depth) - 1
        codes = np.arange(full + 1, dtype=np.float64)
        response = (np.interp(codes, levels, measured) - measured[0]) / span  # light(code), 0..1
        # inverse: for desired light fraction v = code/full, the code whose light is v
        inv = np.interp(codes / full, response + np.arange(full + 1) * 1e-12, codes)
        dtype = np.uint8 if bit_depth <= 8 else np.uint16
        return cls(np.clip(np.round(inv), 0, full).astype(dtype), bit_depth)

    @classmethod
    def power_law(cls, gamma: float, bit_depth: int = 8) -> GammaCorrection:
        """Ideal display ``light = code**gamma`` (for tests and as a first guess)."""
        full = (1 << bit_depth) - 1
        codes = np.arange(full + 1) / full
        return cls.from_measurements(codes * full, codes**gamma, bit_depth)

    def apply(self, image: np.ndarray) -> np.ndarray:
        """Pre-compensate an integer pattern image (any shape) by table lookup."""
        if not np.issubdtype(image.dtype, np.integer):
            raise GammaError(f"pattern must be integer codes, got dtype {image.dtype}")
        return self.lut[image]
