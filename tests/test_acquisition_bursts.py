"""Burst assembler: correct grouping, angles at exposure midpoints, refusal of bad bursts.

Truth: the turntable turns at a known constant rate, so the angle at a frame's exposure
midpoint is ``w * t_mid`` exactly (linear interpolation of a linear signal is exact).
"""

from __future__ import annotations

import numpy as np
import pytest

from gearscan.acquisition.bursts import BurstAssembler
from gearscan.acquisition.encoder import EncoderHistory
from gearscan.core.types import Frame

W = 0.5  # rad/s
PERIOD_NS = 10_000_000  # 100 fps
EXPOSURE_US = 4000.0
T0 = 1_000_000_000


def _frame(i: int, pattern: int | None = None, angle: float | None = None) -> Frame:
    t = T0 + i * PERIOD_NS
    return Frame(
        image=np.full((4, 5), i, np.uint8),
        frame_id=i,
        timestamp_ns=t + 123,  # device clock differs; the host time is what counts
        pattern_index=i % 3 if pattern is None else pattern,
        exposure_us=EXPOSURE_US,
        host_timestamp_ns=t,
        encoder_angle=angle,
    )


def _history(t_end_ns: int, skip: tuple[int, int] | None = None) -> EncoderHistory:
    h = EncoderHistory()
    for t in range(T0 - 5_000_000, t_end_ns, 1_000_000):  # 1 kHz
        if skip and skip[0] <= t < skip[1]:
            continue
        h.append(t, W * t / 1e9)
    return h


def _truth(i: int) -> float:
    return W * (T0 + i * PERIOD_NS + EXPOSURE_US * 500) / 1e9


def test_clean_stream_gives_bursts_with_midpoint_angles():
    asm = BurstAssembler(_history(T0 + 20 * PERIOD_NS), encoder_wait_s=0)
    bursts = [b for b in (asm.push(_frame(i)) for i in range(9)) if b is not None]
    assert [tuple(f.frame_id for f in b.frames) for b in bursts] == [(0, 1, 2), (3, 4, 5), (6, 7, 8)]
    assert [b.index for b in bursts] == [0, 1, 2]
    for b in bursts:
        np.testing.assert_allclose(b.angles, [_truth(f.frame_id) for f in b.frames], atol=1e-12)
    assert bursts[1].images.shape == (3, 4, 5) and asm.events == []


def test_one_dropped_frame_no_burst_spans_the_gap():
    asm = BurstAssembler(_history(T0 + 20 * PERIOD_NS), encoder_wait_s=0)
    out = [asm.push(_frame(i)) for i in range(12) if i != 4]
    bursts = [b for b in out if b is not None]
    ids = [tuple(f.frame_id for f in b.frames) for b in bursts]
    assert ids == [(0, 1, 2), (6, 7, 8), (9, 10, 11)]
    for b in bursts:  # consecutive ids inside every burst
        assert np.all(np.diff([f.frame_id for f in b.frames]) == 1)
    assert asm.stats.dropped_frames == 1
    kinds = [(e.kind, e.frame_id) for e in asm.events]
    assert ("dropped_frames", 5) in kinds
    assert "1 frame(s) missing between ids 3 and 5" in asm.events[0].detail
    # frame 3 (partial burst) and frame 5 (pattern 2 cannot start a burst) unused
    assert asm.stats.discarded_frames == 2


def test_pattern_out_of_order_and_duplicate_ids_refused():
    asm = BurstAssembler(_history(T0 + 20 * PERIOD_NS), encoder_wait_s=0)
    frames = [_frame(0), _frame(1, pattern=2), _frame(2, pattern=0), _frame(2), _frame(3, pattern=1), _frame(4, pattern=2)]
    bursts = [b for b in map(asm.push, frames) if b is not None]
    assert [tuple(f.frame_id for f in b.frames) for b in bursts] == [(2, 3, 4)]
    assert asm.stats.pattern_errors == 1 and asm.stats.order_errors == 1
    assert [e.kind for e in asm.events] == ["pattern_order", "frame_order"]


def test_encoder_gap_refuses_the_burst():
    # no encoder samples between T0+31 ms and T0+55 ms: frames 3..5 (midpoints 32..52 ms)
    gap = (T0 + 31_000_000, T0 + 55_000_000)
    asm = BurstAssembler(_history(T0 + 20 * PERIOD_NS, skip=gap), encoder_wait_s=0)
    bursts = [b for b in (asm.push(_frame(i)) for i in range(9)) if b is not None]
    assert [b.frames[0].frame_id for b in bursts] == [0, 6]
    assert asm.stats.encoder_gaps == 1 and asm.events[0].kind == "encoder_gap"
    assert "encoder gap of 25.00 ms" in asm.events[0].detail
    # frames past the end of the history are refused, not extrapolated
    asm2 = BurstAssembler(_history(T0 + 2 * PERIOD_NS), encoder_wait_s=0)
    assert [asm2.push(_frame(i)) for i in range(3)][-1] is None
    assert "after last encoder sample" in asm2.events[0].detail


def test_recorded_angles_are_used_and_gigE_ids_wrap():
    asm = BurstAssembler(None, frame_id_modulus=1 << 16, frame_id_skips_zero=True)
    frames = [
        Frame(np.zeros((2, 2), np.uint8), fid, 0, pattern_index=p, encoder_angle=a)
        for fid, p, a in [(65534, 0, 0.1), (65535, 1, 0.2), (1, 2, 0.3)]
    ]
    b = [asm.push(f) for f in frames][-1]
    assert b is not None and b.angles == (0.1, 0.2, 0.3) and asm.stats.dropped_frames == 0
    with pytest.raises(ValueError, match="n_patterns must be 3"):
        BurstAssembler(n_patterns=4)


def test_without_encoder_frames_get_the_fixed_angle_and_recorded_angles_still_win():
    """A rig without encoder: without ``fixed_angle`` every burst is refused (issue 16); with it
    the gear is taken as still at that angle, and a frame that carries an angle keeps it."""
    refused = BurstAssembler(None)
    assert [refused.push(_frame(i)) for i in range(3)][-1] is None and refused.stats.encoder_gaps == 1
    asm = BurstAssembler(None, fixed_angle=0.0)
    bursts = [b for b in (asm.push(_frame(i)) for i in range(9)) if b is not None]
    assert [b.angles for b in bursts] == [(0.0, 0.0, 0.0)] * 3 and asm.stats.encoder_gaps == 0
    b = [asm.push(_frame(i, angle=0.5)) for i in range(9, 12)][-1]
    assert b is not None and b.angles == (0.5, 0.5, 0.5)


def test_coarse_bursts_are_assembled_in_their_own_group():
    """With two pattern groups (fine 0-2, coarse 3-5) a burst starts at 0 or 3 and keeps its group;
    a group switch inside a burst is a pattern error."""
    import numpy as np

    from gearscan.acquisition.bursts import BurstAssembler
    from gearscan.core.types import Frame

    img = np.zeros((4, 4), np.uint8)
    asm = BurstAssembler(groups=2)
    order = [3, 4, 5, 0, 1, 2, 0, 4, 5]
    out = [asm.push(Frame(img, i, 1000 * i, p, encoder_angle=0.0)) for i, p in enumerate(order)]
    bursts = [b for b in out if b is not None]
    assert [b.group for b in bursts] == [1, 0]
    assert asm.stats.pattern_errors == 2  # the 4 breaks the burst begun at 0; the 5 starts none
    assert BurstAssembler().push(Frame(img, 0, 0, 3, encoder_angle=0.0)) is None  # one group: 3 never starts


def test_alternating_order_is_a_burst_and_a_broken_one_is_refused():
    """0, 2, 1 is a burst (reversed order, as projector.alternate_order shows it); 0, 2, 2 is not."""
    asm = BurstAssembler(fixed_angle=0.0)
    patterns = [0, 1, 2, 0, 2, 1, 0, 2, 2, 0, 1, 2]
    bursts = [b for i, p in enumerate(patterns) if (b := asm.push(_frame(i, pattern=p))) is not None]
    assert [[f.frame_id for f in b.frames] for b in bursts] == [[0, 1, 2], [3, 4, 5], [9, 10, 11]]
    assert [b.reversed_order for b in bursts] == [False, True, False]
    assert asm.stats.pattern_errors == 1 and [e.kind for e in asm.events] == ["pattern_order"]
    assert "pattern 2 where 1 was expected" in asm.events[0].detail
