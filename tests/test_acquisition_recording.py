"""The recorder (gearscan.core.recording.RecordingWriter) under abuse: SIGKILL mid-write, a
missing frame file, a damaged metadata line (both skipped and named, the rest read). Every image encodes its own index, so what
is replayed is checked pixel for pixel."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings

import numpy as np
import pytest

from gearscan.core.recording import RecordingReader, RecordingWriter
from gearscan.core.types import Frame


def _image(i: int) -> np.ndarray:
    y, x = np.mgrid[0:48, 0:64]
    return ((x + 3 * y + 7 * i) % 4096).astype(np.uint16)


def _frame(i: int) -> Frame:
    return Frame(_image(i), i, 1_000_000_000 + i * 10_000_000, i % 3, 5000.0, 12, 0, 0.01 * i)


def _write(path, n: int) -> None:
    with RecordingWriter(path, {"camera": {"serial": "TEST"}}) as w:
        for i in range(n):
            w.write_frame(_frame(i))


def test_sigkill_mid_write_replays_to_last_complete_frame(tmp_path):
    out = tmp_path / "rec"
    script = textwrap.dedent(
        f"""
        import numpy as np, sys
        sys.path.insert(0, {os.path.dirname(__file__)!r})
        from test_acquisition_recording import _frame
        from gearscan.core.recording import RecordingWriter
        w = RecordingWriter({str(out)!r}, {{}})
        i = 0
        while True:
            w.write_frame(_frame(i)); i += 1
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", script])
    try:
        deadline = time.monotonic() + 30
        lines = out / "frames.jsonl"
        while time.monotonic() < deadline:
            if lines.exists() and lines.read_bytes().count(b"\n") >= 40:
                break
            time.sleep(0.01)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=5)
    finally:
        if proc.poll() is None:
            proc.kill()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # an incomplete last line is expected and warned about
        rec = RecordingReader(out)
    assert len(rec) >= 40 and not rec.finished
    for i in range(len(rec)):  # every listed frame is complete and exact
        f = rec.frame(i)
        assert f.frame_id == i and f.pattern_index == i % 3 and f.bit_depth == 12
        np.testing.assert_array_equal(f.image, _image(i))
    assert rec.frame(len(rec) - 1).encoder_angle == pytest.approx(0.01 * (len(rec) - 1))


def test_missing_frame_file_names_file_and_line(tmp_path, caplog):
    _write(tmp_path / "rec", 6)
    os.remove(tmp_path / "rec" / "frames" / "000003.png")
    rec = RecordingReader(tmp_path / "rec")
    assert [f.frame_id for f in rec.frames()] == [0, 1, 2, 4, 5]  # the rest is read
    assert [str(d) for d in rec.damage] == ["frames/000003.png:4: frame file is missing"]
    assert caplog.text.count("000003.png") == 1


def test_truncated_metadata_line_names_file_and_line(tmp_path):
    _write(tmp_path / "rec", 6)
    path = tmp_path / "rec" / "frames.jsonl"
    lines = path.read_text().splitlines(keepends=True)
    lines[2] = lines[2][: len(lines[2]) // 2] + "\n"  # line 3 cut in half
    path.write_text("".join(lines))
    rec = RecordingReader(tmp_path / "rec")
    assert len(rec) == 5 and [(d.kind, d.file, d.line) for d in rec.damage] == [("index_line", "frames.jsonl", 3)]


def test_cut_last_line_is_an_interrupted_tail(tmp_path):
    _write(tmp_path / "rec", 5)
    path = tmp_path / "rec" / "frames.jsonl"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 20])  # last line cut, no newline
    with pytest.warns(UserWarning, match=r"frames\.jsonl:5: incomplete last line ignored"):
        rec = RecordingReader(tmp_path / "rec")
    assert len(rec) == 4
