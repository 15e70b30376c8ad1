"""Lay gearscan out as links in SITE/gearscan by pyproject's package map: a lent GPU machine imports it from this
tree without a build (scripts/lease_train.sh, scripts/lease_bench.sh). Run with ``python -P`` from the repo root:
the tree's own gearscan/ lacks the mapped subpackages and must not shadow the layout.

    python -P scripts/lease_layout.py SITE
"""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path


def lay_out(root: Path, site: Path) -> Path:
    """Link the top package's own entries and each mapped subpackage's folder into ``site/gearscan``."""
    pkg = site / "gearscan"
    pkg.mkdir(parents=True, exist_ok=True)
    for entry in (root / "gearscan").iterdir():
        if entry.name != "__pycache__" and not (pkg / entry.name).exists():
            (pkg / entry.name).symlink_to(entry)
    dirs = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    for name, folder in dirs.items():
        sub = name.split(".", 1)[-1]
        if name != "gearscan" and not (pkg / sub).exists():
            (pkg / sub).symlink_to(root / folder)
    return pkg


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python -P scripts/lease_layout.py SITE (the folder to lay gearscan out in)")
    print(f"gearscan laid out in {lay_out(Path.cwd(), Path(sys.argv[1]))}")
