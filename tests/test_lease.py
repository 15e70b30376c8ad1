"""The GPU lease's one command (scripts/lease_train.sh), run here on the CPU at a tiny size: it renders, trains
from the shipped model within its time limit and leaves what the device tool can bring back."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_lease_command_fits_the_device_limits(tmp_path):
    out = tmp_path / "OUT"
    limit = 170
    env = os.environ | {
        "OUT": str(out), "LEASE_WORK": str(tmp_path / "work"), "LEASE_PYTHON": sys.executable, "LEASE_DEVICE": "cpu",
        "LEASE_LIMIT_S": str(limit), "LEASE_SIZE": "64", "LEASE_CROP": "32", "LEASE_JOBS": "2", "LEASE_BATCH": "8",
        "LEASE_THREADS": "2", "LEASE_PROBE_STEPS": "5", "LEASE_PROFILE": "4 2", "LEASE_LINK": "1",
        "LEASE_COMPILE": "0",  # compiling on this CPU costs more than this tiny run (the choice: the test below)
        "LEASE_EXTRA": "--gears-per-set 1 --steps-per-epoch 20 --val-items 16",
    }
    t0 = time.time()
    run = subprocess.run(["bash", str(REPO / "scripts" / "lease_train.sh")], env=env, capture_output=True, text=True,
                         timeout=limit + 60)
    took = time.time() - t0
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert took <= limit + 15  # it keeps to its own limit (the device kills a command at 600 s)
    # what the device tool brings back: at most 8 plain files of 16 MiB, plain names, here at the top of $OUT
    files = sorted(out.iterdir())
    assert len(files) <= 8 and all(f.is_file() and f.stat().st_size <= 16 * 2**20 for f in files)
    assert all(re.fullmatch(r"[A-Za-z0-9._-]+", f.name) for f in files)
    assert {f.name for f in files} == {"lease.log", "best.safetensors", "best.json", "stage1_best.safetensors",
                                       "stage1_best.json", "metrics.csv", "reproduce.json", "train_step_profile.md"}
    log = (out / "lease.log").read_text()
    assert "preflight: torch" in log and "the twin casts rays" in log and "exited 0" in log
    # gearscan ran from the layout the machine gets (links by pyproject's package map), not this venv's install
    assert "gearscan laid out as links" in log and f"gearscan from {tmp_path / 'work' / 'site' / 'gearscan'}" in log
    meta = json.loads((out / "best.json").read_text())
    cfg = meta["training"]
    assert cfg["bank"] and cfg["deadline"] > t0 and cfg["init"].endswith("inference/weights/default.safetensors")
    assert cfg["loss"]["outside_weight"] == 0.05 and cfg["val_objective"] == "full" and not meta["calibration"]
    info = json.loads((out / "reproduce.json").read_text())
    # the training kept its deadline (its last save within the 20 s left for it) and both stages ran
    run_best = tmp_path / "work" / "run" / "best.json"
    assert run_best.stat().st_mtime <= cfg["deadline"] + 20 and info["stages_run"] == [1, 2]
    assert "training compiled: no (LEASE_COMPILE=0)" in log and cfg["compile"] is False


@pytest.mark.parametrize(("eager_ms", "compiled_ms", "first_s", "train_s", "chose"), [
    (30.0, 20.0, 40.0, 400.0, 1),  # 1.5x: saves 133 s of 400, more than 3 compiles of 40 s
    (30.0, 20.0, 60.0, 400.0, 0),  # 3 compiles of 60 s cost more than the 133 s saved
    (30.0, 25.0, 1.0, 400.0, 0),  # 1.2x: under the 1.25x floor
    (30.0, None, 1.0, 400.0, 0),  # the compiled row missing (the profile cut off): eager
])
def test_the_lease_compiles_only_when_its_profile_pays_for_it(tmp_path, eager_ms, compiled_ms, first_s, train_s, chose):
    """The lease's choice to train compiled, read off its own profile (train_step_profile.py --worth-compiling)."""
    rows = [{"width": 8, "batch": 128, "compiled": False, "ms_per_step": eager_ms, "first_step_s": 0.1}]
    if compiled_ms is not None:
        rows.append({"width": 8, "batch": 128, "compiled": True, "ms_per_step": compiled_ms, "first_step_s": first_s})
    profile = tmp_path / "profile.json"
    profile.write_text(json.dumps({"rows": rows}))
    run = subprocess.run([sys.executable, str(REPO / "benchmarks" / "train_step_profile.py"), "--worth-compiling",
                          str(profile), "--compiled", "8x128", "--train-seconds", str(train_s)],
                         capture_output=True, text=True, check=True)
    assert run.stdout.strip() == str(chose)
