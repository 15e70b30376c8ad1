"""Fuzzing the recording reader and the encoder line parser (hypothesis, seeded and small).

Byte mutations of ``recording.json``, ``frames.jsonl`` and ``encoder.jsonl`` (bit flips, cuts,
invalid UTF-8, huge numbers, NaN/inf, negatives) must give a :class:`RecordingError` or a
replay whose damage report names every line holding a value outside the format's ranges,
never another exception and never a hang. Targeted mutations put an invalid value into each
field a result depends on and check that it is reported, not silently used. The encoder
parser must turn any bytes into a sample or a ProtocolError the reader counts.
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
import time
import warnings
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gearscan.acquisition.encoder_protocol import (
    Banner,
    ProtocolError,
    RawSample,
    frame_line,
    parse_line,
)
from gearscan.core.recording import RecordingError
from gearscan.mocks.fuzz import (
    BAD_NUMBERS,
    HOSTILE_BYTES,
    INDEX_FILES,
    OPS,
    mutate,
    write_small_recording,
)
from gearscan.replay import replay

FUZZ = settings(max_examples=25, derandomize=True, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """3 bursts of 24x16 random 8-bit frames with 30 encoder samples: small enough to replay 100 times."""
    return write_small_recording(tmp_path_factory.mktemp("fuzz") / "rec")


def _outcome(rec: Path) -> tuple[str, object, list]:
    """("error", message, []) for a RecordingError, else ("ok", metrics, what each burst measured);
    any other exception fails the test."""
    rows: list = []

    def on_burst(m, row) -> None:
        rows.append((tuple(f.frame_id for f in m.burst.frames), m.burst.angles, m.result.phase.tobytes()))

    t0 = time.monotonic()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # an interrupted tail is warned about; not what is tested here
        try:
            result: tuple[str, object, list] = ("ok", replay(rec, reconstruct=False, truth=False, on_burst=on_burst), rows)
        except RecordingError as exc:
            result = ("error", str(exc), [])
    assert time.monotonic() - t0 < 10.0, "replay hung"
    return result


@pytest.fixture(scope="module")
def reference(base) -> list:
    kind, metrics, rows = _outcome(base)
    assert kind == "ok" and metrics.bursts == 3 and metrics.damage["count"] == 0
    return rows


# -- the format's ranges, written out independently of the reader ---------------------------
def _is_int(v, lo, hi) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi


def _is_num(v, lo=-math.inf, hi=math.inf) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and lo <= v <= hi


FRAME_KEYS = {"id", "timestamp_ns", "host_timestamp_ns", "pattern_index", "encoder_angle_rad", "exposure_us",
              "bit_depth", "file"}
ENCODER_KEYS = {"seq", "device_time_us", "count", "index", "angle_rad", "host_time_ns"}


def _frame_line_ok(d) -> bool:
    if not isinstance(d, dict) or set(d) != FRAME_KEYS:  # the writer writes every key, nothing else
        return False
    a = d.get("encoder_angle_rad")
    return (_is_int(d.get("id"), 0, 2**64 - 1) and _is_int(d.get("timestamp_ns"), 0, 2**63 - 1)
            and _is_int(d.get("pattern_index"), 0, 2) and _is_num(d.get("exposure_us", 0.0), 0, 1e9)
            and d.get("bit_depth", 8) == 8 and (a is None or _is_num(a, -1e9, 1e9))
            and _is_int(d.get("host_timestamp_ns", 0), 0, 2**63 - 1) and isinstance(d.get("file"), str))


def _encoder_line_ok(d) -> bool:
    return (isinstance(d, dict) and set(d) == ENCODER_KEYS and _is_int(d.get("seq"), 0, 2**32 - 1)
            and _is_int(d.get("device_time_us"), 0, (2**63 - 1) // 1000)
            and _is_int(d.get("count"), -(2**63 - 1), 2**63 - 1) and isinstance(d.get("index"), bool)
            and _is_num(d.get("angle_rad")) and _is_int(d.get("host_time_ns", 0), 0, 2**63 - 1))


def _invalid_lines(path: Path, ok) -> set[int]:
    """Complete lines of a JSONL file that do not parse or hold a value out of range."""
    bad = set()
    lines = path.read_bytes().split(b"\n")[:-1]  # the last piece has no newline: an interrupted tail
    for n, raw in enumerate(lines, start=1):
        if not raw.strip():
            continue
        try:
            if not ok(json.loads(raw)):
                bad.add(n)
        except (ValueError, RecursionError):
            bad.add(n)
    return bad


mutation = st.tuples(
    st.sampled_from(INDEX_FILES),
    st.sampled_from(OPS),
    st.integers(0, 10_000),
    st.one_of(st.sampled_from(HOSTILE_BYTES),
              st.sampled_from(BAD_NUMBERS), st.binary(min_size=1, max_size=6)),
)


@FUZZ
@given(mutations=st.lists(mutation, min_size=1, max_size=3))
def test_mutated_index_files_give_a_clean_error_or_named_damage(base, reference, mutations):
    with tempfile.TemporaryDirectory() as tmp:
        rec = Path(shutil.copytree(base, Path(tmp) / "rec"))
        for name, op, pos, payload in mutations:
            path = rec / name
            path.write_bytes(mutate(path.read_bytes(), op, pos, payload))
        kind, result, rows = _outcome(rec)
        if kind == "error":
            assert "recording.json" in result or "a burst needs 3" in result, result
            return
        if not result.damage["count"]:  # nothing reported: nothing may have changed
            assert rows == reference, "a mutation changed the result without being reported"
            return
        damaged = {(d["file"], d["line"]) for d in result.damage["items"]}
        for n in _invalid_lines(rec / "frames.jsonl", _frame_line_ok):
            assert any(line == n for _, line in damaged), f"frames.jsonl:{n} invalid but not reported: {damaged}"
        for n in _invalid_lines(rec / "encoder.jsonl", _encoder_line_ok):
            assert ("encoder.jsonl", n) in damaged, f"encoder.jsonl:{n} invalid but not reported: {damaged}"


def _set(rec: Path, name: str, line: int, keys: tuple, value) -> None:
    """Put ``value`` at ``keys`` in line ``line`` of ``name`` (recording.json: line 0)."""
    path = rec / name
    if name == "recording.json":
        docs = [json.loads(path.read_text())]
    else:
        docs = [json.loads(s) for s in path.read_text().splitlines()]
    d = docs[max(line - 1, 0)]
    for k in keys[:-1]:
        d = d[k]
    d[keys[-1]] = value
    text = "\n".join(json.dumps(x) for x in docs) + ("\n" if name != "recording.json" else "")
    path.write_text(text)  # json.dumps writes NaN and Infinity as the bare tokens a mutation would


HUGE, NAN, INF = 2**70, float("nan"), float("inf")
TARGETED = [
    *[("frames.jsonl", 5, (k,), v) for k, vs in {
        # line 5 is burst 1's second frame: id 104, pattern 1 (valid values in the wrong place count too)
        "id": [-1, HUGE, NAN, "7", True, 103, 150], "timestamp_ns": [-1, HUGE, 1.5], "pattern_index": [-1, 3, 7, NAN, 0, 2],
        "exposure_us": [-1, NAN, INF, 1e300], "bit_depth": [0, 16, 17, NAN], "encoder_angle_rad": [NAN, INF, 1e300, "x", None],
        "encoder_angle": [0.01],  # a damaged key name
        "host_timestamp_ns": [-1, HUGE], "file": ["../../etc/hostname", "/etc/hostname", 5, "frames/missing.png"],
    }.items() for v in vs],
    *[("encoder.jsonl", 4, (k,), v) for k, vs in {
        "seq": [-1, 2**32, HUGE, NAN], "device_time_us": [-1, 2**64 - 1, NAN], "count": [HUGE, -HUGE, NAN, 1.5],
        "index": [2, "yes"], "angle_rad": [NAN, INF], "host_time_ns": [-1, HUGE],
    }.items() for v in vs],
    *[("recording.json", 0, keys, v) for keys, vs in {
        ("rig", "camera", "K", 0, 0): [NAN, INF, -1, 0], ("rig", "camera", "width"): [HUGE, -1, 0, NAN, 25],
        ("rig", "camera", "dist", 0): [NAN, INF], ("rig", "projector", "T_from_world", 0, 3): [NAN],
        ("patterns", "patterns", 0, "period_px"): [NAN, INF, -1, 0], ("patterns", "patterns", 1, "shift"): [NAN, INF],
        ("frame_format", "width"): [HUGE, -1, NAN, 25], ("frame_format", "dtype"): ["float64"],
        ("camera",): [{"frame_ids": {"modulus": HUGE}}, {"frame_ids": {"modulus": 1000}}],
        ("gear", "teeth"): [NAN, -1, HUGE], ("gear", "module"): [NAN, INF, -1],
    }.items() for v in vs],
]


@pytest.mark.parametrize(("name", "line", "keys", "value"), TARGETED,
                         ids=[f"{n}:{'.'.join(map(str, k))}={v!r:.12}" for n, _, k, v in TARGETED])
def test_an_invalid_value_is_reported_not_used(base, tmp_path, name, line, keys, value):
    rec = Path(shutil.copytree(base, tmp_path / "rec"))
    _set(rec, name, line, keys, value)
    kind, result, _ = _outcome(rec)
    if name == "recording.json":
        assert kind == "error" and "recording.json" in result, (kind, result)
        return
    assert kind == "ok", result
    items = result.damage["items"]
    # pattern 2 second is the order 0, 2, 1 of an alternating sequence: the burst breaks at its third line (2 again)
    lines = {line, line + 1} if (keys, value) == (("pattern_index",), 2) else {line}
    assert any(d["line"] in lines for d in items), items
    if name == "frames.jsonl":
        assert result.bursts == 2  # the other bursts are measured
    else:
        assert result.bursts == 3


# -- the encoder line parser ------------------------------------------------------------------
def _checked(body: bytes, sigil: bytes = b"$") -> bytes:
    """A line whose checksum is right, so the field checks are what is tested."""
    x = 0
    for b in body:
        x ^= b
    return sigil + body + b"*" + f"{x:02X}".encode() + b"\n"


field = st.one_of(st.integers(-(2**70), 2**70).map(lambda v: str(v).encode()),
                  st.sampled_from([b"", b"nan", b"inf", b"1e5", b"+5", b"1_0", b" 7", b"0x10", b"\xff", str(2**64 - 1).encode()]))


@settings(max_examples=300, derandomize=True, deadline=None, database=None)
@given(st.one_of(st.binary(max_size=80),
                 st.lists(field, min_size=5, max_size=6).map(lambda fs: _checked(b"E," + b",".join(fs))),
                 st.lists(field, min_size=3, max_size=3).map(lambda fs: _checked(b"GSENC," + b",".join(fs), b"#"))))
def test_any_encoder_line_parses_to_a_sample_in_range_or_a_protocol_error(line):
    try:
        msg = parse_line(line)
    except ProtocolError:
        return
    if isinstance(msg, RawSample):
        assert 0 <= msg.seq < 2**32 and 0 <= msg.t_us <= (2**63 - 1) // 1000 and abs(msg.count) < 2**63
        assert msg.t_us * 1000 < 2**63  # the reader keeps device time in int64 nanoseconds
    else:
        assert isinstance(msg, Banner) and msg.counts_per_rev > 0


def test_out_of_range_encoder_lines_are_counted_not_fatal():
    """t_us = 2**64-1 (checksum right) used to kill the reader thread with OverflowError."""
    from gearscan.acquisition.encoder import EncoderReader

    reader = EncoderReader("loop://", 4096)
    good = RawSample(1, 1000, 5, False, None).encode()
    for bad in (RawSample(2, 2**64 - 1, 5, False, None).encode(), RawSample(3, 1000, 2**70, False, None).encode(),
                frame_line("$", "E,4,1000,5,2,"), frame_line("#", "GSENC,1,-5,dev")):
        reader._handle(bad, 10**9)
    reader._handle(good, 10**9)
    assert reader.stats.corrupt == 4 and reader.stats.samples == 1
