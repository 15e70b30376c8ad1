"""The mixed-pixel filter: drops pixels at depth steps and silhouettes, keeps flanks however steep."""

from __future__ import annotations

import numpy as np
import pytest

from gearscan.recon.edges import mixed_pixels


def test_a_depth_step_and_the_border_are_mixed_a_steep_flank_is_not():
    h, w = 40, 60
    valid = np.zeros((h, w), bool)
    valid[5:35, 5:55] = True
    cols = np.arange(w, dtype=float)
    depth = np.tile(np.where(cols < 30, 100.0, 103.0), (h, 1))  # a 3 mm step at column 30
    depth[:, 40:] += 0.3 * (cols[40:] - 40)  # a flank rising 0.3 mm per pixel (2 footprints)
    mixed = mixed_pixels(valid, depth, 0.15, border_px=1)
    assert mixed[10:30, 29:31].all()  # both sides of the step
    assert mixed[10:30, 28].all() and mixed[10:30, 31].all()  # and their neighbours (blur reach)
    assert not mixed[10:30, 33:53].any()  # the steep flank is surface, not a step
    assert mixed[5, 10:20].all() and mixed[10:30, 5].all()  # the border of the lit region
    assert not mixed[~valid].any()  # only pixels with a point are ever marked
    assert mixed_pixels(valid, depth, 0.15, border_px=0)[5, 10:20].sum() == 0


def test_shapes_must_match():
    with pytest.raises(ValueError, match="depth"):
        mixed_pixels(np.ones((4, 4), bool), np.ones((4, 5)), 0.1)
