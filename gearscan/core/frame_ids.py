"""Camera frame ids that wrap: signed steps and monotonic extension for any counter width.

Camera frame counters are finite: GigE Vision v1 block ids are 16-bit and skip 0 (..., 65534,
65535, 1, 2, ...), V4L2 sequence numbers are 32-bit, GigE Vision 2 / GenTL ids 64-bit. Every
place that compares or orders frame ids (camera bookkeeping, burst assembly, the recorder's
metadata, replay) goes through :class:`FrameIdWrap`, so one rule decides what "next",
"missing" and "late" mean::

    wrap = FrameIdWrap.bits(16, skips_zero=True)
    wrap.step(65535, 1)          # 1: the next frame
    wrap.step(2, 65535)          # -3: a late frame
    ext = FrameIdUnwrapper(wrap)
    [ext(i) for i in (65534, 65535, 1)]   # [65534, 65535, 65536]

This module imports nothing from gearscan, so every package may use it.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

#: Counter widths cameras use, narrowest first (what :meth:`FrameIdWrap.detect` may infer).
COUNTER_BITS = (16, 32, 64)


@dataclass(frozen=True, slots=True)
class FrameIdWrap:
    """How a camera's frame counter wraps.

    modulus: the counter's range, ``2**bits`` (None: the ids never wrap).
    skips_zero: after the wrap the counter restarts at 1, not 0 (GigE Vision v1: id 0 is
    invalid). An id 0 then sits where ``modulus - 1`` would, just before 1.
    """

    modulus: int | None = None
    skips_zero: bool = False

    def __post_init__(self) -> None:
        if self.modulus is not None and (not 4 <= self.modulus <= 1 << 64 or self.modulus & (self.modulus - 1)):
            raise ValueError(f"frame id modulus must be a power of two from 4 to 2**64, got {self.modulus}")
        if self.skips_zero and self.modulus is None:
            raise ValueError("skips_zero needs a modulus (a counter that never wraps never skips 0)")

    @classmethod
    def bits(cls, n: int, *, skips_zero: bool = False) -> FrameIdWrap:
        """The wrap of an ``n``-bit counter."""
        return cls(1 << n, skips_zero)

    @property
    def period(self) -> int | None:
        """Distinct ids per cycle (``modulus - 1`` when 0 is skipped)."""
        if self.modulus is None:
            return None
        return self.modulus - 1 if self.skips_zero else self.modulus

    def _position(self, frame_id: int) -> int:
        return (frame_id - 1) % self.period if self.skips_zero else frame_id % self.period  # type: ignore[operator]

    def step(self, a: int, b: int) -> int:
        """Frames from id ``a`` to id ``b``: 1 for the next frame, > 1 across missing frames,
        <= 0 for a duplicate or late one (the shorter way round the counter decides)."""
        if self.period is None:
            return b - a
        n = self.period
        d = (self._position(b) - self._position(a)) % n
        return d - n if d > n // 2 else d

    def to_json(self) -> dict[str, Any]:
        return {"modulus": self.modulus, "skips_zero": self.skips_zero}

    @classmethod
    def from_json(cls, data: Any) -> FrameIdWrap:
        """Parse :meth:`to_json` output; raises ValueError naming what is wrong."""
        if not isinstance(data, dict):
            raise ValueError(f"expected {{'modulus': int or null, 'skips_zero': bool}}, got {data!r:.80}")
        modulus, skips = data.get("modulus"), data.get("skips_zero", False)
        if modulus is not None and (isinstance(modulus, bool) or not isinstance(modulus, int)):
            raise ValueError(f"modulus must be an integer or null, got {modulus!r:.40}")
        if not isinstance(skips, bool):
            raise ValueError(f"skips_zero must be true or false, got {skips!r:.40}")
        return cls(modulus, skips)

    @classmethod
    def detect(cls, ids: Sequence[int]) -> FrameIdWrap:
        """Infer the wrap from ids in capture order (recordings made before the wrap was stored).

        A wrap is a drop from the upper half of the narrowest counter that holds every id to
        its lower half; without one the ids need no wrap rule. The counter skips 0 when no id
        after a wrap is 0 (GigE Vision v1 restarts at 1).
        """
        if not ids:
            return cls()
        top = max(ids)
        bits = next((b for b in COUNTER_BITS if top < 1 << b), None)
        if bits is None:
            return cls()
        half = 1 << (bits - 1)
        wraps = [k for k in range(1, len(ids)) if ids[k - 1] >= half > ids[k]]
        if not wraps:
            return cls()
        return cls(1 << bits, skips_zero=0 not in ids[wraps[0]:])


class FrameIdUnwrapper:
    """Extends wrapped ids into a count that keeps growing across wraps.

    The first id is kept as is; each later one is the previous extended id plus
    :meth:`FrameIdWrap.step`, so a late frame comes out smaller than its predecessor.
    """

    def __init__(self, wrap: FrameIdWrap) -> None:
        self.wrap = wrap
        self._last: tuple[int, int] | None = None  # (raw, extended)

    def __call__(self, frame_id: int) -> int:
        if self._last is None:
            ext = frame_id
        else:
            raw, prev = self._last
            ext = prev + self.wrap.step(raw, frame_id)
        self._last = (frame_id, ext)
        return ext

    def reset(self) -> None:
        """Forget the history (a new stream starts)."""
        self._last = None

    def extend(self, ids: Iterable[int]) -> list[int]:
        """Extended ids of ``ids`` in order."""
        return [self(i) for i in ids]
