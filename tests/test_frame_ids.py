"""Frame ids that wrap (gearscan.core.frame_ids) and replays of recordings whose ids cross a wrap."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from gearscan.acquisition.bursts import BurstAssembler
from gearscan.core.frame_ids import FrameIdUnwrapper, FrameIdWrap
from gearscan.core.recording import RecordingReader
from gearscan.core.rig import default_rig
from gearscan.core.types import Frame
from gearscan.replay import replay
from gearscan.twin.recordings import render_recording

GIGE = FrameIdWrap.bits(16, skips_zero=True)


@pytest.mark.parametrize(
    ("wrap", "a", "b", "step"),
    [
        (GIGE, 65535, 1, 1),  # GigE v1: 0 is skipped
        (GIGE, 65534, 2, 3),  # 65535, 1 missing
        (GIGE, 2, 65535, -2),  # late frame: the shorter way round
        (GIGE, 0, 1, 1),  # a stream that starts at 0 before the first wrap
        (GIGE, 7, 7, 0),
        (FrameIdWrap.bits(16), 65535, 0, 1),
        (FrameIdWrap.bits(16), 65535, 1, 2),
        (FrameIdWrap.bits(32), 2**32 - 1, 0, 1),
        (FrameIdWrap.bits(32), 5, 2**32 - 2, -7),
        (FrameIdWrap.bits(64), 2**64 - 1, 0, 1),
        (FrameIdWrap.bits(64), 2**64 - 2, 3, 5),
        (FrameIdWrap(), 10, 3, -7),  # a counter that never wraps
    ],
)
def test_step_is_the_signed_frame_count(wrap, a, b, step):
    assert wrap.step(a, b) == step


def test_unwrapper_extends_ids_monotonically_across_every_width():
    for wrap, ids in [
        (GIGE, [65534, 65535, 1, 2]),
        (FrameIdWrap.bits(32), [2**32 - 2, 2**32 - 1, 0, 1]),
        (FrameIdWrap.bits(64), [2**64 - 2, 2**64 - 1, 0, 1]),
    ]:
        ext = FrameIdUnwrapper(wrap).extend(ids)
        assert ext == list(range(ids[0], ids[0] + 4)), (wrap, ext)
    # two wraps of a 16-bit counter, a late frame and a gap
    u = FrameIdUnwrapper(GIGE)
    ids = [*range(65530, 65536), *range(1, 65536), 1, 2, 1, 5]
    ext = u.extend(ids)
    assert ext[:6] == list(range(65530, 65536)) and ext[6] == 65536
    assert ext[-4:] == [65536 + 65535, 65536 + 65536, 65536 + 65535, 65536 + 65539]


def test_detect_infers_width_and_skipped_zero_from_recorded_ids():
    assert FrameIdWrap.detect([65533, 65534, 65535, 1, 2]) == GIGE
    assert FrameIdWrap.detect([65534, 65535, 0, 1]) == FrameIdWrap.bits(16)
    assert FrameIdWrap.detect([2**32 - 1, 0, 1]) == FrameIdWrap.bits(32)
    assert FrameIdWrap.detect([2**64 - 1, 0]) == FrameIdWrap.bits(64)
    assert FrameIdWrap.detect([3, 4, 2, 5]) == FrameIdWrap()  # a late frame is no wrap
    assert FrameIdWrap.detect([]) == FrameIdWrap()
    with pytest.raises(ValueError, match=r"power of two from 4 to 2\*\*64"):
        FrameIdWrap(1000)
    with pytest.raises(ValueError, match="skips_zero must be"):
        FrameIdWrap.from_json({"modulus": 65536, "skips_zero": "yes"})
    assert FrameIdWrap.from_json(GIGE.to_json()) == GIGE


def test_assembler_keeps_bursts_across_32_and_64_bit_wraps():
    for bits in (32, 64):
        asm = BurstAssembler(None, frame_id_modulus=1 << bits)
        top = (1 << bits) - 4
        ids = [(top + k) % (1 << bits) for k in range(9)]
        out = [asm.push(Frame(np.zeros((2, 2), np.uint8), fid, k, pattern_index=k % 3, encoder_angle=0.01 * k))
               for k, fid in enumerate(ids)]
        assert sum(b is not None for b in out) == 3, (bits, asm.events)
        assert asm.stats.order_errors == asm.stats.dropped_frames == 0


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    """A 4-burst twin recording (ids 0..11), rendered once."""
    out = tmp_path_factory.mktemp("wrap") / "twin"
    return render_recording(out, rig=default_rig(96, 80, field_mm=20.0), motion="uniform:0.3", bursts=4, seed=1)


def _with_ids(src, dst, ids, wrap: FrameIdWrap | None):
    """A copy of ``src`` whose frames carry ``ids`` (and, with ``wrap``, say how they wrap)."""
    shutil.copytree(src, dst)
    path = dst / "frames.jsonl"
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    path.write_text("".join(json.dumps({**d, "id": i}) + "\n" for d, i in zip(lines, ids, strict=True)))
    if wrap is not None:
        meta = json.loads((dst / "recording.json").read_text())
        meta["camera"]["frame_ids"] = wrap.to_json()
        (dst / "recording.json").write_text(json.dumps(meta))
    return dst


@pytest.mark.parametrize(
    ("name", "ids", "stored"),
    [
        ("gige16", [65530, 65531, 65532, 65533, 65534, 65535, 1, 2, 3, 4, 5, 6], GIGE),
        ("gige16-inferred", [65531, 65532, 65533, 65534, 65535, 1, 2, 3, 4, 5, 6, 7], None),  # wrap mid-burst
        ("v4l2-32", [2**32 - 5 + k for k in range(5)] + list(range(7)), FrameIdWrap.bits(32)),
        ("gev2-64", [2**64 - 2, 2**64 - 1] + list(range(10)), None),
    ],
)
def test_replay_keeps_every_burst_across_a_frame_id_wrap(twin, tmp_path, name, ids, stored):
    rec = _with_ids(twin, tmp_path / name, ids, stored)
    reader = RecordingReader(rec)
    assert reader.extended_ids == list(range(ids[0], ids[0] + 12))
    m = replay(rec, reconstruct=False)
    assert m.bursts == 4, m.assembler
    assert m.assembler["order_errors"] == m.assembler["dropped_frames"] == 0
    # truth is found for every burst through the same (extended) ids
    assert all(np.isfinite(row["three-step_rmse_rad"]) for row in m.per_burst)
    assert m.damage["count"] == 0

