"""Where a benchmark's numbers came from: the commit, and whether the code it ran differed from that commit."""

from __future__ import annotations

import platform
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# The reports the benchmarks write into the tree (``benchmarks/**/*_report.{md,json,png}``): a run in a chain that
# finds an earlier run's fresh report has not run edited code. Not counted with them: a few benchmarks read another's
# committed report for a context table (adaptation.py: generalization_report.json). Every other file counts, the
# rules and the val-choice JSONs under benchmarks/ included; so does any other output a run writes there (a chain
# of such runs is stamped dirty, the safe side).
GENERATED = tuple(f":(exclude,glob)benchmarks/**/*_report.{ext}" for ext in ("md", "json", "png"))


def code_edits(repo: str | Path = REPO) -> list[str]:
    """Tracked files of ``repo`` with uncommitted edits, the benchmarks' written reports (:data:`GENERATED`) not
    counted; ``["unknown"]`` where git cannot say (no git, not a work tree): stamped as edited, the safe side."""
    try:
        out = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".", *GENERATED],
                             cwd=repo, capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return ["unknown"]
    return [line[3:] for line in out.splitlines() if line.strip()]


def run_stamp(repo: str | Path = REPO) -> dict:
    """What a val run's json records about where it ran: the commit, the files edited beyond it, the CPU."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True, text=True,
                                check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    cpuinfo = Path("/proc/cpuinfo")
    models = [line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines()
              if line.startswith("model name")] if cpuinfo.exists() else []
    return {"commit": commit, "uncommitted_edits": code_edits(repo), "host": models[0] if models else platform.processor()}
