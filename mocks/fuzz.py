"""Byte mutations and a small recording for robustness fuzzing (tests and benchmarks).

:func:`mutate` applies one hostile edit (bit flip, cut, insertion, hostile number) to a
file's bytes; :func:`write_small_recording` writes a recording small enough to replay
hundreds of times.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

INDEX_FILES = ("recording.json", "frames.jsonl", "encoder.jsonl")
OPS = ("flip", "cut", "insert", "number")
BAD_NUMBERS = [b"NaN", b"Infinity", b"-Infinity", b"-1", str(2**70).encode(), b"1e999", b"-9223372036854775809"]
HOSTILE_BYTES = [b"\xff\xfe", b"\xc3\x28", b"\x00", b"\n", b"{", b'"', b"[[[[[[[["]


def write_small_recording(out: Path) -> Path:
    """3 bursts of 24x16 random 8-bit frames with 30 encoder samples, written to ``out``."""
    from gearscan.core.gear import GearSpec
    from gearscan.core.patterns import PatternSet
    from gearscan.core.recording import RecordingWriter
    from gearscan.core.rig import default_rig
    from gearscan.core.types import EncoderSample, Frame

    rig = default_rig(24, 16)
    meta = {"rig": rig.to_json(), "patterns": PatternSet.three_step(40.0).to_json(), "gear": GearSpec().model_dump()}
    rng = np.random.default_rng(0)
    with RecordingWriter(out, meta) as w:
        for i in range(30):
            w.write_encoder(EncoderSample(seq=i, device_time_us=1000 * i, count=3 * i, index=i == 0,
                                          angle=0.001 * i, host_time_ns=10**6 * i))
        for i in range(9):
            w.write_frame(Frame(rng.integers(0, 256, (16, 24), dtype=np.uint8), 100 + i, 3 * 10**6 * i, i % 3,
                                1000.0, 8, 3 * 10**6 * i, 0.003 * i))
    return out


def mutate(data: bytes, op: str, pos: int, payload: bytes) -> bytes:
    """``data`` with one edit at ``pos`` (wrapped): ``flip`` a bit, ``cut`` the rest, ``insert``
    ``payload``, or replace the digit run at or after ``pos`` by the ``number`` ``payload``."""
    pos = pos % (len(data) + 1)
    if op == "flip":
        if not data:
            return data
        pos = min(pos, len(data) - 1)
        return data[:pos] + bytes([data[pos] ^ (1 << (payload[0] % 8 if payload else 0))]) + data[pos + 1:]
    if op == "cut":
        return data[:pos]
    if op == "insert":
        return data[:pos] + payload + data[pos:]
    digits = [k for k in range(pos, len(data)) if data[k:k + 1].isdigit()]
    if not digits:
        return data
    start = end = digits[0]
    while end < len(data) and data[end:end + 1].isdigit():
        end += 1
    return data[:start] + (payload or b"NaN") + data[end:]
