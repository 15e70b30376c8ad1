"""Burst assembly: frames in pattern order 0, 1, 2 (or 0, 2, 1) -> :class:`~gearscan.core.types.Burst`.

Each frame gets the turntable angle at its exposure midpoint, linearly interpolated in the
encoder history (host clock). The assembler never emits a wrong burst: a frame-id gap
(dropped frame), a pattern out of order, a duplicate/late frame or a missing encoder
reading discards the partial burst and is reported in ``events`` and counted in ``stats``.

    assembler = BurstAssembler(reader.history)
    for frame in frames:
        burst = assembler.push(frame)      # Burst or None
    assembler.stats, assembler.events

Frames that already carry ``encoder_angle`` (replayed recordings) use it as is, so the
replay pipeline needs no history at all. Without an encoder (``history`` None) and with
``fixed_angle`` set, every frame gets that angle: the gear is taken as standing still there.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

from gearscan.acquisition.encoder import EncoderHistory
from gearscan.core.frame_ids import FrameIdWrap
from gearscan.core.patterns import next_offsets
from gearscan.core.types import Burst, Frame


@dataclass(frozen=True, slots=True)
class AssemblyEvent:
    kind: str  # "dropped_frames", "pattern_order", "frame_order", "encoder_gap"
    frame_id: int
    detail: str


@dataclass(slots=True)
class AssemblerStats:
    frames: int = 0
    bursts: int = 0
    dropped_frames: int = 0  # frames missing according to frame-id gaps
    pattern_errors: int = 0
    order_errors: int = 0  # duplicate or backwards frame ids
    encoder_gaps: int = 0
    discarded_frames: int = 0  # received frames not used in any burst
    events_dropped: int = 0  # events beyond the bounded event list

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass
class BurstAssembler:
    """Groups frames into three-pattern bursts.

    history: encoder angles in host time (None: frames must carry ``encoder_angle``).
    max_encoder_gap_ns: bracketing encoder samples farther apart than this are a gap.
    encoder_wait_s: how long ``push`` may wait for encoder samples to cover the newest
    exposure (the serial link can lag the camera by a few ms).
    fixed_angle: with no history, the angle of frames that carry none (a rig without encoder:
    the gear stands still at this angle, rad); None: such frames cannot form a burst.
    frame_id_modulus, frame_id_skips_zero: wrap of the camera's frame counter (GigE v1: 65536,
    skipping 0; :attr:`BaseCamera.frame_id_wrap <gearscan.acquisition.camera.BaseCamera.frame_id_wrap>`).
    """

    history: EncoderHistory | None = None
    n_patterns: int = 3
    max_encoder_gap_ns: int = 20_000_000
    encoder_wait_s: float = 0.05
    frame_id_modulus: int | None = None
    frame_id_skips_zero: bool = False
    fixed_angle: float | None = None
    groups: int = 1  # three-step pattern groups: 2 when coarse bursts (patterns 3-5) are interleaved
    max_events: int = 10_000
    stats: AssemblerStats = field(default_factory=AssemblerStats)
    events: list[AssemblyEvent] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.n_patterns != 3:
            raise ValueError(f"n_patterns must be 3 (Burst holds three frames), got {self.n_patterns}")
        self._wrap = FrameIdWrap(self.frame_id_modulus, self.frame_id_skips_zero)
        self._pending: list[Frame] = []
        self._last_id: int | None = None
        self._next_index = 0

    # -- helpers --------------------------------------------------------------------------
    def _event(self, kind: str, frame_id: int, detail: str) -> None:
        if len(self.events) < self.max_events:
            self.events.append(AssemblyEvent(kind, frame_id, detail))
        else:
            self.stats.events_dropped += 1

    def _discard_pending(self) -> None:
        self.stats.discarded_frames += len(self._pending)
        self._pending.clear()

    @staticmethod
    def host_midpoint_ns(frame: Frame) -> int:
        """Host-clock time of the exposure midpoint (device time if no host time is known)."""
        if frame.host_timestamp_ns:
            return frame.host_timestamp_ns + int(round(frame.exposure_us * 500.0))
        return frame.midpoint_ns

    def _angle(self, frame: Frame) -> tuple[float | None, str]:
        if frame.encoder_angle is not None:
            return frame.encoder_angle, ""
        if self.history is None:
            if self.fixed_angle is not None:
                return self.fixed_angle, ""
            return None, "frame has no encoder_angle and the assembler has no encoder history"
        t = self.host_midpoint_ns(frame)
        deadline = time.monotonic() + self.encoder_wait_s
        while True:
            angle, why = self.history.interpolate(t, self.max_encoder_gap_ns)
            if angle is not None or "after last" not in why or time.monotonic() >= deadline:
                return angle, why
            time.sleep(0.001)

    def _expected(self) -> list[int]:
        """Pattern indices the next frame may have: a group's first pattern to start a burst, then
        the other two in either order (:data:`~gearscan.core.patterns.BURST_ORDERS`)."""
        if not self._pending:
            return [3 * g for g in range(self.groups)]
        first = self._pending[0].pattern_index
        return [first + o for o in next_offsets([f.pattern_index - first for f in self._pending])]

    # -- API ------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the partial burst and the last frame id (after a camera reconnect)."""
        self._discard_pending()
        self._last_id = None

    def push(self, frame: Frame) -> Burst | None:
        """Add one frame; returns a complete burst or None."""
        self.stats.frames += 1
        if self._last_id is not None:
            step = self._wrap.step(self._last_id, frame.frame_id)
            if step <= 0:
                self.stats.order_errors += 1
                self.stats.discarded_frames += 1
                self._event("frame_order", frame.frame_id, f"frame id {frame.frame_id} after {self._last_id}: duplicate or late, ignored")
                return None
            if step > 1:
                self.stats.dropped_frames += step - 1
                self._event(
                    "dropped_frames",
                    frame.frame_id,
                    f"{step - 1} frame(s) missing between ids {self._last_id} and {frame.frame_id}; "
                    f"partial burst of {len(self._pending)} discarded",
                )
                self._discard_pending()
        self._last_id = frame.frame_id

        starts = [3 * g for g in range(self.groups)]  # a burst starts at the first pattern of a group
        expected = self._expected()
        if frame.pattern_index not in expected:
            self.stats.pattern_errors += 1
            self._event(
                "pattern_order",
                frame.frame_id,
                f"pattern {frame.pattern_index} where {' or '.join(map(str, expected))} "
                f"was expected; partial burst of {len(self._pending)} discarded",
            )
            self._discard_pending()
            if frame.pattern_index not in starts:
                self.stats.discarded_frames += 1
                return None
        self._pending.append(frame)
        if len(self._pending) < self.n_patterns:
            return None

        frames = tuple(self._pending)
        self._pending.clear()
        angles = []
        for f in frames:
            angle, why = self._angle(f)
            if angle is None:
                self.stats.encoder_gaps += 1
                self.stats.discarded_frames += len(frames)
                self._event("encoder_gap", f.frame_id, f"no encoder angle for frame {f.frame_id}: {why}; burst discarded")
                return None
            angles.append(angle)
        burst = Burst(frames=frames, angles=(angles[0], angles[1], angles[2]), index=self._next_index,  # type: ignore[arg-type]
                      group=frames[0].pattern_index // 3)
        self._next_index += 1
        self.stats.bursts += 1
        return burst
