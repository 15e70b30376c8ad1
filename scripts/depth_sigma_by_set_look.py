"""Dev look (val, chooses nothing): per-class depth-sigma scales per val family, on the rule's check seed set.

    python scripts/depth_sigma_by_set_look.py [--seed 2400] [--scales benchmarks/depth_sigma_val_amend3.json]
        [--out benchmarks/depth_sigma_by_set_look.json]

The third amendment of ``benchmarks/depth_sigma_rule.md`` pooled its 18 val scenes; on test the default rig's gears put
4.2-6.4 % of the in-span network class's points beyond 2 sigma on the paper's motions. This look renders the rule's
check seed set again (``calibrate_depth_sigma.collect``, the same scenes, motions and decode) and splits each (class,
band) cell by val family (``calibrate_depth_sigma.family``), with the scales a rule run recorded (``--scales``, its
JSON's ``scales``): does val show a family those scales flatter? It writes the shares; it decides nothing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "benchmarks"), str(ROOT / "scripts")]
from calibrate_depth_sigma import by_family_cell, by_family_motion, collect, family_scales, table  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=2400)
    ap.add_argument("--scales", type=Path, default=ROOT / "benchmarks" / "depth_sigma_val_amend3.json",
                    help="a rule run's JSON whose per-class scales to look at (default: the third amendment's)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "depth_sigma_by_set_look.json")
    args = ap.parse_args()

    from inspect_bench import commit, host

    scales = {c: tuple(v) for c, v in json.loads(args.scales.read_text())["scales"].items()}
    zs = collect(args.seed, "wide", 1)
    cells = by_family_cell(zs)
    out = {"split": "val", "purpose": "dev look, chooses nothing", "commit": commit(), "host": host(),
           "seed": args.seed, "scales_from": args.scales.name, "scales": {c: list(v) for c, v in scales.items()},
           "cells": table(cells, family_scales(table(cells), scales)), "motions": by_family_motion(zs, scales)}
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    for fam, ms in out["motions"].items():
        print(fam, {m: f"{v['beyond_2sigma']:.1%}" for m, v in ms.items()})


if __name__ == "__main__":
    main()
