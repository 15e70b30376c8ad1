"""Small sets of moving three-step bursts rendered by the twin, for tests and smoke runs."""

from __future__ import annotations

import math

import numpy as np


def render_twin_bursts(
    *,
    size: int = 64,
    field_mm: float = 10.0,
    teeth: int = 20,
    starts: int = 4,
    bursts_per_start: int = 2,
    max_step_deg: float = 0.6,
    period_px: float = 18.0,
    seed: int = 0,
) -> list[dict]:
    """Render a small set of moving three-step bursts from the twin (for tests and smoke runs).

    Start points are spread over one tooth pitch; from each, ``bursts_per_start`` bursts with
    random frame steps in ``[0, max_step_deg]``. The label is the analytic truth at the first
    frame's pose (M, D normalised; DESIGN.md). ``group`` is the start-point index.
    """
    from gearscan.core.gear import GearSpec
    from gearscan.core.patterns import PatternSet
    from gearscan.core.rig import default_rig
    from gearscan.twin.render import TwinRenderer

    rng = np.random.default_rng(seed)
    gear = GearSpec(teeth=teeth)
    renderer = TwinRenderer(default_rig(size, size, field_mm=field_mm), gear)
    patterns = PatternSet.three_step(period_px)
    pitch = 2 * math.pi / teeth
    scale = float(renderer.optics.full_scale)
    items = []
    for s in range(starts):
        a0 = pitch * s / starts
        for _ in range(bursts_per_start):
            steps = np.radians(rng.uniform(0.0, max_step_deg, size=2))
            angles = [a0, a0 + steps[0], a0 + steps[0] + steps[1]]
            imgs, truths = renderer.render_sequence(angles, patterns, [0, 1, 2], rng)
            t = truths[0]
            items.append(
                {
                    "input": imgs.astype(np.float32) / scale,
                    "target": np.stack([t.M, t.D]).astype(np.float32),
                    "mask": t.mask,
                    "phase": t.phase.astype(np.float32),
                    "group": s,
                }
            )
    return items
