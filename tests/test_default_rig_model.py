"""The default-rig option's fine-tuning script (scripts/default_rig_model.py): its time limits are one or the other,
and rendering gears in parallel writes the same folders as one at a time."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "default_rig_model.py"


def _script(monkeypatch):
    """The script as a module its render processes can import (their work is pickled by name)."""
    monkeypatch.syspath_prepend(str(SCRIPT.parent))
    return importlib.import_module("default_rig_model")


@pytest.mark.parametrize(("args", "said"), [
    (["--budget", "5", "--deadline-minutes", "3"], "--budget and --deadline-minutes: expected one"),
    (["--deadline-minutes", "0"], "--deadline-minutes: expected > 0"),
    (["--jobs", "0"], "--jobs, --steps-per-epoch: expected >= 1"),
    (["--schedule", "cosine"], "--schedule cosine: expected --epochs"),
])
def test_conflicting_or_empty_limits_are_refused_before_any_rendering(tmp_path, args, said):
    run = subprocess.run([sys.executable, str(SCRIPT), "--data", str(tmp_path / "data"), "--out", str(tmp_path / "run"),
                          *args], capture_output=True, text=True, cwd=REPO)
    assert run.returncode == 2 and said in run.stderr
    assert not (tmp_path / "data").exists()


def test_parallel_rendering_writes_what_one_process_writes(tmp_path, monkeypatch):
    script = _script(monkeypatch)
    one = script.render(tmp_path / "one", [11, 20], seed=3201, start_points=1, size=32, jobs=1)
    two = script.render(tmp_path / "two", [11, 20], seed=3201, start_points=1, size=32, jobs=2)
    assert [p.name for p in one] == [p.name for p in two] == ["z11", "z20"]
    for a, b in zip(one, two, strict=True):
        files = sorted(f.relative_to(a) for f in a.rglob("*") if f.is_file())
        assert files == sorted(f.relative_to(b) for f in b.rglob("*") if f.is_file()) and files
        for f in files:
            if f.suffix == ".npy":
                np.testing.assert_array_equal(np.load(a / f), np.load(b / f), err_msg=str(f))
            else:
                assert (a / f).read_bytes() == (b / f).read_bytes(), f
