"""Where a benchmark's numbers came from: the commit, and whether the code it ran differed from that commit."""

from __future__ import annotations

import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# What the benchmarks write into the tree (reports, tables, figures): a run in a chain that finds an earlier run's
# fresh report has not run edited code. Rules (benchmarks/*_rule.md) are committed before their runs.
GENERATED = tuple(f":(exclude,glob)benchmarks/**/*.{ext}" for ext in ("md", "json", "png", "txt", "csv"))


def code_edits(repo: str | Path = REPO) -> list[str]:
    """Tracked files of ``repo`` with uncommitted edits, the benchmarks' written outputs (:data:`GENERATED`) not
    counted; ``["unknown"]`` where git cannot say (no git, not a work tree)."""
    try:
        out = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".", *GENERATED],
                             cwd=repo, capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return ["unknown"]
    return [line[3:] for line in out.splitlines() if line.strip()]
