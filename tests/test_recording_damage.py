"""Damaged recordings: replay skips each damaged part, keeps every good burst, names the damage
once by file and line and counts it; `gearscan check` lists it without decoding; `--strict`
fails on it; `--overwrite` replaces a recording whole."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from gearscan.cli import app
from gearscan.core.recording import RecordingError, RecordingReader, RecordingWriter
from gearscan.core.rig import default_rig
from gearscan.core.types import Frame
from gearscan.replay import replay
from gearscan.twin.recordings import render_recording

runner = CliRunner()


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """A 3-burst, 8-bit twin recording (frames 000000..000008), rendered once."""
    out = tmp_path_factory.mktemp("damage") / "clean"
    return render_recording(out, rig=default_rig(96, 80, field_mm=20.0), motion="uniform:0.3", bursts=3, seed=2)


@pytest.fixture()
def rec(clean, tmp_path):
    return shutil.copytree(clean, tmp_path / "rec")


def _set_value(path, n: int, key: str, value) -> None:
    """Set ``key`` on JSON line ``n`` (json.dumps writes NaN as the bare token a damaged file would hold)."""
    _edit_line(path, n, lambda s: json.dumps({**json.loads(s), key: value}))


def _edit_line(path, n: int, fn) -> None:
    """Replace line ``n`` (1-based) of a JSONL file with ``fn(old line)``."""
    lines = path.read_text().splitlines()
    lines[n - 1] = fn(lines[n - 1])
    path.write_text("\n".join(lines) + "\n")


def _replay(rec, caplog):
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="gearscan.core.recording"):
        t0 = time.monotonic()
        m = replay(rec, reconstruct=False, metrics_path=rec.parent / "m.json")
        seconds = time.monotonic() - t0
    return m, seconds, json.loads((rec.parent / "m.json").read_text())["damage"]


def _truncate_png(path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def test_truncated_png_skips_its_burst_only_and_names_it_once(rec, caplog):
    _truncate_png(rec / "frames" / "000004.png")  # burst 1, second frame
    m, seconds, damage = _replay(rec, caplog)
    assert m.bursts == 2 and [row["burst"] for row in m.per_burst] == [0, 1]
    assert seconds < 5.0  # no GrabTimeout wait for the skipped frame
    assert damage["count"] == 1 and damage["by_kind"] == {"unreadable_frame": 1}
    item = damage["items"][0]
    assert (item["file"], item["line"]) == ("frames/000004.png", 5) and "truncated" in item["what"]
    warnings_ = [r.getMessage() for r in caplog.records if "000004.png" in r.getMessage()]
    assert len(warnings_) == 1 and "frames/000004.png:5: PNG truncated" in warnings_[0]
    assert m.assembler["bursts"] == 2 and m.assembler["discarded_frames"] >= 2  # the rest of burst 1


@pytest.mark.parametrize(
    ("damage_it", "kind", "where"),
    [
        (lambda r: os.remove(r / "frames" / "000004.png"), "missing_frame", ("frames/000004.png", 5)),
        (lambda r: _edit_line(r / "frames.jsonl", 5, lambda s: "{garbage"), "index_line", ("frames.jsonl", 5)),
        (lambda r: _edit_line(r / "frames.jsonl", 5, lambda s: s.replace('"frames/000004.png"', '"../../etc/hostname"')),
         "path_escape", ("frames.jsonl", 5)),
        # one 16-bit frame in an 8-bit recording: damage, not data (it would decode to nonsense phase)
        (lambda r: cv2.imwrite(str(r / "frames" / "000004.png"),
                               cv2.imread(str(r / "frames" / "000004.png"), cv2.IMREAD_UNCHANGED).astype(np.uint16) * 257),
         "frame_format", ("frames/000004.png", 5)),
        # a wrong size: as bad
        (lambda r: cv2.imwrite(str(r / "frames" / "000004.png"), np.zeros((40, 96), np.uint8)),
         "frame_format", ("frames/000004.png", 5)),
        # a line claiming 16 bits in an 8-bit recording
        (lambda r: _edit_line(r / "frames.jsonl", 5, lambda s: s.replace('"bit_depth": 8', '"bit_depth": 16')),
         "frame_format", ("frames/000004.png", 5)),
        (lambda r: _set_value(r / "frames.jsonl", 5, "encoder_angle_rad", float("nan")),
         "index_line", ("frames.jsonl", 5)),
    ],
    ids=["missing", "garbage-index-line", "path-escape", "16-bit-in-8-bit", "wrong-size", "bit-depth-line", "nan-angle"],
)
def test_damaged_frame_is_skipped_and_the_other_bursts_replay(rec, caplog, damage_it, kind, where):
    damage_it(rec)
    m, seconds, damage = _replay(rec, caplog)
    assert m.bursts == 2 and seconds < 5.0
    assert damage["by_kind"] == {kind: 1}, damage
    assert (damage["items"][0]["file"], damage["items"][0]["line"]) == where
    assert sum(f"{where[0]}:{where[1]}" in r.getMessage() for r in caplog.records) == 1


def test_garbage_encoder_line_is_counted_not_silently_skipped(rec, caplog):
    _edit_line(rec / "encoder.jsonl", 7, lambda s: "\x00\x01 not json")
    _set_value(rec / "encoder.jsonl", 9, "count", 2**70)
    m, _, damage = _replay(rec, caplog)
    assert m.bursts == 3  # replay uses the frames' angles: every burst is still measured
    assert damage["by_kind"] == {"encoder_line": 2}
    assert [(d["file"], d["line"]) for d in damage["items"]] == [("encoder.jsonl", 7), ("encoder.jsonl", 9)]
    assert "count: expected an integer" in damage["items"][1]["what"]


def test_unreadable_encoder_file_is_damage_not_a_traceback(rec):
    (rec / "encoder.jsonl").unlink()
    (rec / "encoder.jsonl").mkdir()  # something in its place that cannot be read as a file
    r = RecordingReader(rec, warn=False)
    assert r.encoder_samples() == [] and [(d.kind, d.file) for d in r.damage] == [("encoder_line", "encoder.jsonl")]
    assert "cannot read" in r.damage[0].what


def test_reader_reports_damage_once_however_often_a_frame_is_read(rec):
    _truncate_png(rec / "frames" / "000002.png")
    r = RecordingReader(rec, warn=False)
    assert len(list(r.frames())) == 8 and len(list(r.frames())) == 8
    assert len(r.damage) == 1


def test_check_lists_damage_without_decoding_and_exit_codes(rec, tmp_path, monkeypatch):
    res = runner.invoke(app, ["check", str(rec)])
    assert res.exit_code == 0 and "OK (9 frames)" in res.output, res.output
    (rec / "frames" / "000009.tmp.png").write_bytes(b"\x89PNG half")  # kill -9 during record
    res = runner.invoke(app, ["check", str(rec)])
    assert res.exit_code == 0 and "000009.tmp.png: temporary file of an interrupted write" in res.output
    assert len(RecordingReader(rec)) == 9  # the reader ignores it: no line names it

    _truncate_png(rec / "frames" / "000004.png")
    flipped = bytearray((rec / "frames" / "000007.png").read_bytes())
    flipped[60] ^= 0x04  # one bit inside the image data: the chunk CRC catches it
    (rec / "frames" / "000007.png").write_bytes(bytes(flipped))
    _edit_line(rec / "encoder.jsonl", 3, lambda s: "{")
    monkeypatch.setattr(cv2, "imdecode", lambda *a: pytest.fail("check decoded an image"))
    monkeypatch.setattr(cv2, "imread", lambda *a: pytest.fail("check decoded an image"))
    res = runner.invoke(app, ["check", str(rec)])
    assert res.exit_code == 1, res.output
    lines = [line for line in res.output.splitlines() if line.startswith("damaged:")]
    assert len(lines) == 3
    assert any("frames/000004.png:5: PNG truncated" in line for line in lines)
    assert any("frames/000007.png:8: PNG chunk b'IDAT'" in line and "CRC mismatch" in line for line in lines)
    assert any("encoder.jsonl:3: not a JSON line" in line for line in lines)

    res = runner.invoke(app, ["check", str(tmp_path)])  # no recording.json
    assert res.exit_code == 2 and "not a recording" in res.output


def test_check_says_a_damaged_header_is_unreadable_as_replay_does(rec):
    """A header section replay cannot measure without (here the gear's module) is exit 2 in `check`, as replay refuses
    it, not exit 1 with "replay skips them and measures the rest"."""
    meta = json.loads((rec / "recording.json").read_text())
    meta["gear"]["module"] = -2.0
    (rec / "recording.json").write_text(json.dumps(meta))
    res = runner.invoke(app, ["check", str(rec)])
    assert res.exit_code == 2 and "gear" in res.output and "replay refuses it" in res.output, res.output
    assert "measures the rest" not in res.output
    res = runner.invoke(app, ["replay", str(rec), "--classical", "--save", str(rec.parent / "x.rrd")])
    assert res.exit_code == 2, res.output
    # a damaged rig alone: replay measures with --rig, so it is damage (exit 1) that says how
    meta["gear"]["module"] = 2.0
    rig = meta["rig"]
    meta["rig"] = {k: v for k, v in rig.items() if k != "camera"}
    (rec / "recording.json").write_text(json.dumps(meta))
    res = runner.invoke(app, ["check", str(rec)])
    assert res.exit_code == 1 and "replay it with --rig" in res.output, res.output


def test_replay_strict_exits_1_on_damage_and_0_without(rec, tmp_path):
    os.remove(rec / "frames" / "000000.png")
    args = ["replay", str(rec), "--classical", "--save", str(tmp_path / "o.rrd"), "--no-truth"]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "bursts: 2" in res.output and "damage: 1 part(s) skipped (missing_frame 1)" in res.output
    res = runner.invoke(app, [*args, "--strict"])
    assert res.exit_code == 1 and "--strict" in res.output


def test_pipeline_error_is_printed_once(rec, tmp_path):
    """A damaged truth file fails the scoring stage: one message naming the file, not two."""
    (rec / "truth" / "000003.npz").write_bytes(b"PK\x03\x04 not a zip")
    proc = subprocess.run(
        [sys.executable, "-c", "from gearscan.cli import main; main()", "replay", str(rec), "--classical",
         "--save", str(tmp_path / "o.rrd")],
        capture_output=True, text=True, timeout=300, env={**os.environ, "MPLBACKEND": "Agg"},
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("000003.npz") == 1, proc.stderr
    assert "damaged truth file" in proc.stderr


def test_overwrite_replaces_the_recording_whole(rec):
    assert RecordingReader(rec).has_truth()
    (rec / "notes.txt").write_text("mine")
    with RecordingWriter(rec, {}, overwrite=True) as w:
        w.write_frame(Frame(np.zeros((8, 8), np.uint8), 1, 0))
    r = RecordingReader(rec)
    assert len(r) == 1 and not r.has_truth() and not (rec / "frames" / "000008.png").exists()
    assert (rec / "notes.txt").read_text() == "mine"  # not part of the recording: kept
    # a folder that holds no recording keeps what it has, even a frames/ of its own
    (rec.parent / "other" / "frames").mkdir(parents=True)
    (rec.parent / "other" / "frames" / "keep.png").write_bytes(b"x")
    RecordingWriter(rec.parent / "other", {}, overwrite=True).close()
    assert (rec.parent / "other" / "frames" / "keep.png").exists()


def test_writer_refuses_a_frame_of_another_format(tmp_path):
    with RecordingWriter(tmp_path / "r", {}) as w:
        w.write_frame(Frame(np.zeros((8, 8), np.uint8), 1, 0))
        with pytest.raises(RecordingError, match=r"frame 2 is 8x8 uint16 \(16-bit\), the recording holds 8x8 uint8 \(8-bit\)"):
            w.write_frame(Frame(np.zeros((8, 8), np.uint16), 2, 0, bit_depth=16))
    assert RecordingReader(tmp_path / "r").meta["frame_format"] == {"dtype": "uint8", "width": 8, "height": 8, "bit_depth": 8}


def test_a_blank_or_merged_index_line_loses_no_burst(rec, caplog):
    """A blank line in frames.jsonl, or two records on one line (a lost newline), had shifted every later burst's
    position and so thrown away every burst after it: each record keeps its place and every burst replays."""
    index = rec / "frames.jsonl"
    lines = index.read_text().splitlines()
    assert len(lines) == 9
    index.write_text("\n".join([*lines[:4], "", *lines[4:]]) + "\n")  # a blank line inside burst 1
    m, _, damage = _replay(rec, caplog)
    assert m.bursts == 3 and damage["count"] == 0
    index.write_text("\n".join([*lines[:3], lines[3] + " " + lines[4], *lines[5:]]) + "\n")  # burst 1's first two
    m, _, damage = _replay(rec, caplog)
    assert m.bursts == 3 and damage["count"] == 0 and "2 records on one line" in caplog.text
    r = RecordingReader(rec)
    assert len(r) == 9 and [rec_.pattern_index for rec_ in r.records] == [0, 1, 2] * 3


def test_a_recording_without_its_header_is_not_written_over(rec, tmp_path):
    """What is left of a recording whose recording.json was lost (its index, frames) is refused as a target without
    --overwrite (a new one had replaced its frames and appended to its index); a path that cannot hold one is named."""
    (rec / "recording.json").unlink()
    before = (rec / "frames.jsonl").read_bytes()
    with pytest.raises(RecordingError, match="part of a recording without its recording.json"):
        RecordingWriter(rec, {})
    assert (rec / "frames.jsonl").read_bytes() == before
    res = runner.invoke(app, ["twin", "render", str(rec), "--bursts", "1", "--width", "64", "--height", "64"])
    assert res.exit_code == 2 and "--overwrite" in res.output and (rec / "frames.jsonl").read_bytes() == before
    (tmp_path / "a_file").write_text("x")
    for bad in (tmp_path / "a_file", "/proc/gearscan_rec"):
        with pytest.raises(RecordingError, match="not a folder|cannot write a recording there"):
            RecordingWriter(bad, {})


@pytest.mark.parametrize("lost", [b"\x1a", b"*", b"\xff", b""], ids=["SUB", "star", "0xff", "nothing"])
def test_a_newline_turned_into_another_byte_keeps_both_records(rec, caplog, lost):
    index = rec / "frames.jsonl"
    lines = index.read_bytes().splitlines()
    index.write_bytes(b"\n".join([*lines[:3], lines[3] + lost + lines[4], *lines[5:]]) + b"\n")
    m, _, damage = _replay(rec, caplog)
    assert m.bursts == 3 and damage["count"] == 0, damage


def test_overwrite_replaces_what_is_left_of_a_recording_whole(rec):
    """Remains without a header (an encoder log, a first frame) refuse the folder without --overwrite and are removed
    by it, not appended to."""
    (rec / "recording.json").unlink()
    (rec / "frames.jsonl").unlink()
    assert RecordingWriter.remains(rec) == ["encoder.jsonl", "frames/000000.png"]
    with pytest.raises(RecordingError, match="part of a recording"):
        RecordingWriter(rec, {})
    with RecordingWriter(rec, {}, overwrite=True) as w:
        w.write_frame(Frame(np.zeros((8, 8), np.uint8), 1, 0))
    r = RecordingReader(rec)
    assert len(r) == 1 and r.encoder_samples() == [] and not (rec / "frames" / "000004.png").exists()
