"""Turntable motion profiles for twin recordings: the angle of every frame.

Specs (degrees at this CLI edge, radians out):

- ``uniform:0.6``: every frame 0.6 deg after the previous one;
- ``nonuniform:0.1,1.6`` or ``nonuniform:0.1,1.6,0.3``: inside a burst the steps are 0.1 then
  1.6 deg; the step to the next burst is the third value (default: the first);
- ``angles:0,0.6,1.2,...``: explicit frame angles (bursts take them three at a time);
- ``static``: no motion (every frame at the start angle).
"""

from __future__ import annotations

import numpy as np


class MotionError(ValueError):
    """A motion spec cannot be parsed."""


def frame_angles(spec: str, bursts: int, start_deg: float = 0.0) -> np.ndarray:
    """Angles (rad) of ``3 * bursts`` frames for a motion ``spec``."""
    if bursts < 1:
        raise MotionError(f"bursts must be >= 1, got {bursts}")
    kind, _, args = spec.partition(":")
    kind = kind.strip().lower()
    n = 3 * bursts
    try:
        values = [float(v) for v in args.split(",") if v.strip()] if args else []
    except ValueError as exc:
        raise MotionError(f"motion {spec!r}: values must be numbers in degrees") from exc
    if kind == "static":
        steps = np.zeros(n - 1)
    elif kind == "uniform":
        if len(values) != 1 or values[0] < 0:
            raise MotionError(f"motion {spec!r}: expected uniform:STEP_DEG with STEP_DEG >= 0")
        steps = np.full(n - 1, values[0])
    elif kind == "nonuniform":
        if len(values) not in (2, 3) or min(values) < 0:
            raise MotionError(f"motion {spec!r}: expected nonuniform:D1,D2[,GAP] in degrees, each >= 0")
        d1, d2 = values[:2]
        gap = values[2] if len(values) == 3 else d1
        steps = np.resize([d1, d2, gap], n - 1)
    elif kind == "angles":
        if len(values) < 3 or len(values) % 3:
            raise MotionError(f"motion {spec!r}: expected a multiple of 3 angles, got {len(values)}")
        if len(values) < n:
            raise MotionError(f"motion {spec!r}: {len(values)} angles for {bursts} bursts (need {n})")
        return np.radians(np.asarray(values[:n]) + start_deg)
    else:
        raise MotionError(f"motion {spec!r}: kind must be static, uniform, nonuniform or angles")
    return np.radians(start_deg + np.concatenate([[0.0], np.cumsum(steps)]))
