"""Fringe pattern sets: N-step phase shifting at one or several fringe periods.

Phase varies along projector columns, ``phi = 2 pi u_p / period_px``; pattern n of an
N-step group is ``I_n = A + B cos(phi + delta_n)`` with ``delta_n = 2 pi n / N``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

DEFAULT_PERIOD_PX = 40.0
"""Default fringe period (projector px): about 22 camera px and 5 periods per tooth pitch on
the default rig with a module-2, 20-tooth gear."""


BURST_ORDERS = ((0, 1, 2), (0, 2, 1))
"""The two orders a three-step burst may show its group's patterns in: forward, and reversed after
the first (shifts 0, 4pi/3, 2pi/3), which an alternating sequence shows every other burst."""


def next_offsets(seen: tuple[int, ...] | list[int]) -> tuple[int, ...]:
    """Pattern offsets within its group that a burst's next frame may show, after ``seen``."""
    k = len(seen)
    return tuple(sorted({o[k] for o in BURST_ORDERS if k < 3 and o[:k] == tuple(seen)}))


class PatternError(ValueError):
    """A pattern set parameter is out of range."""


@dataclass(frozen=True, slots=True)
class Pattern:
    """One sinusoidal fringe image: its period (projector px) and phase shift (rad)."""

    period_px: float
    shift: float


@dataclass(frozen=True)
class PatternSet:
    """An ordered list of fringe patterns, shown one per camera frame."""

    patterns: tuple[Pattern, ...]
    name: str = "custom"

    def __post_init__(self) -> None:
        if not self.patterns:
            raise PatternError("pattern set is empty")
        for p in self.patterns:
            if not (2 <= p.period_px < math.inf):
                raise PatternError(f"period_px must be finite and >= 2 projector pixels, got {p.period_px}")
            if not math.isfinite(p.shift):
                raise PatternError(f"shift must be a finite phase (rad), got {p.shift}")

    def __len__(self) -> int:
        return len(self.patterns)

    @property
    def shifts(self) -> np.ndarray:
        return np.array([p.shift for p in self.patterns])

    @property
    def periods(self) -> tuple[float, ...]:
        """Distinct periods in order of first appearance."""
        seen: list[float] = []
        for p in self.patterns:
            if p.period_px not in seen:
                seen.append(p.period_px)
        return tuple(seen)

    def group(self, period_px: float) -> tuple[np.ndarray, np.ndarray]:
        """Indices and shifts of the patterns with this period."""
        idx = np.array([i for i, p in enumerate(self.patterns) if p.period_px == period_px])
        if idx.size == 0:
            raise PatternError(f"no pattern with period {period_px} in set {self.name!r} (periods {self.periods})")
        return idx, self.shifts[idx]

    @classmethod
    def n_step(cls, steps: int, period_px: float) -> PatternSet:
        """``steps`` equally shifted patterns at one period."""
        if steps < 3:
            raise PatternError(f"steps must be >= 3 for phase shifting, got {steps}")
        return cls(
            tuple(Pattern(float(period_px), 2 * math.pi * n / steps) for n in range(steps)),
            name=f"{steps}-step@{period_px:g}px",
        )

    @classmethod
    def three_step(cls, period_px: float) -> PatternSet:
        """The dynamic burst set: shifts 0, 2pi/3, 4pi/3."""
        return cls.n_step(3, period_px)

    @classmethod
    def with_coarse(cls, period_px: float, coarse_period_px: float) -> PatternSet:
        """The measuring three-step set (indices 0-2) plus a coarse one (3-5) that a burst every
        N bursts shows, to unwrap the fine fringes without a CAD (:mod:`gearscan.recon.cloud_prior`)."""
        if not coarse_period_px > period_px:
            raise PatternError(f"coarse period {coarse_period_px:g} px must exceed the fringe period {period_px:g} px")
        pats = cls.n_step(3, period_px).patterns + cls.n_step(3, coarse_period_px).patterns
        return cls(pats, name=f"3-step@{period_px:g}px+coarse@{coarse_period_px:g}px")

    def cycle(self, coarse_every: int = 1, alternate: bool = False) -> list[int]:
        """Pattern indices of one sequence cycle: the three-step burst (0, 1, 2); with a coarse group a
        coarse burst (3, 4, 5) first and then ``coarse_every`` measuring bursts (as twin recordings do).

        ``alternate``: every other measuring burst shows its patterns as 0, 2, 1, so that on a
        turning gear no surface point sees the same two fringe phases frame after frame (a fringe
        moving a sixth of a period per frame does, in the order 0, 1, 2): the frame fit of the fused
        model (:mod:`gearscan.recon.track`) can then fit it.
        """
        orders = BURST_ORDERS if alternate else BURST_ORDERS[:1]
        if self.coarse_period_px is None:
            if len(self.patterns) != 3 and alternate:
                raise PatternError(f"alternate: a three-pattern set expected, got {len(self.patterns)} patterns")
            return [i for o in orders for i in o] if len(self.patterns) == 3 else list(range(len(self.patterns)))
        if coarse_every < 1:
            raise PatternError(f"coarse_every: expected >= 1 measuring burst per coarse burst, got {coarse_every}")
        fine = coarse_every * (2 if alternate and coarse_every % 2 else 1)  # alternation carries across cycles
        return [i for k in range(fine) for i in ([3, 4, 5] if k % coarse_every == 0 else []) + list(orders[k % len(orders)])]

    @property
    def coarse_period_px(self) -> float | None:
        """The coarse bursts' period when this set is two three-step groups (fine, coarse), else None."""
        if len(self.patterns) != 6:
            return None
        fine, coarse = self.patterns[0].period_px, self.patterns[3].period_px
        groups_ok = all(p.period_px == fine for p in self.patterns[:3]) and all(p.period_px == coarse for p in self.patterns[3:])
        return coarse if groups_ok and coarse > fine else None

    @classmethod
    def multi_frequency(cls, periods_px: list[float], steps: int = 18) -> PatternSet:
        """Static reference: an N-step group per period, finest period first."""
        if len(periods_px) < 1:
            raise PatternError("multi_frequency needs at least one period")
        pats: list[Pattern] = []
        for period in periods_px:
            pats.extend(cls.n_step(steps, period).patterns)
        return cls(tuple(pats), name=f"{steps}-step@{','.join(f'{p:g}' for p in periods_px)}px")

    def image(self, index: int, width: int, height: int, *, gamma: float = 1.0, bit_depth: int = 8) -> np.ndarray:
        """Projector image of pattern ``index``, pre-compensated for a display ``gamma``."""
        p = self.patterns[index]
        u = np.arange(width, dtype=np.float64)
        row = 0.5 + 0.5 * np.cos(2 * math.pi * u / p.period_px + p.shift)
        if gamma != 1.0:
            row = row ** (1.0 / gamma)
        scale = (1 << bit_depth) - 1
        dtype = np.uint8 if bit_depth <= 8 else np.uint16
        return np.broadcast_to(np.round(row * scale).astype(dtype), (height, width)).copy()

    def to_json(self) -> dict:
        return {"name": self.name, "patterns": [{"period_px": p.period_px, "shift": p.shift} for p in self.patterns]}

    @classmethod
    def from_json(cls, data: dict) -> PatternSet:
        try:
            pats = tuple(Pattern(float(p["period_px"]), float(p["shift"])) for p in data["patterns"])
        except (KeyError, TypeError, ValueError) as exc:
            raise PatternError(f"pattern set: expected {{'patterns': [{{'period_px', 'shift'}}...]}}, got {data!r:.200}") from exc
        return cls(pats, name=str(data.get("name", "custom")))
