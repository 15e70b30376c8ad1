"""Dev look (val, chooses nothing): the shipped per-class depth-sigma scales per val folder, on the rule's check set.

    python scripts/depth_sigma_by_set_look.py [--seed 2400] [--out benchmarks/depth_sigma_by_set_look.json]

The third amendment of ``benchmarks/depth_sigma_rule.md`` pools its 18 val scenes; on test the default rig's gears put
4.2-6.4 % of the in-span network class's points beyond 2 sigma on the paper's motions. This look renders the rule's
check seed set again (``calibrate_depth_sigma.collect``, the same scenes, motions and decode) and splits each (class,
band) cell by val folder: does val show a family the pooled scales flatter? It writes the shares; it decides nothing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "benchmarks"), str(ROOT / "scripts")]
from calibrate_depth_sigma import collect  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=2400)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "depth_sigma_by_set_look.json")
    args = ap.parse_args()

    from inspect_bench import commit, host

    from gearscan.evaluate import z_summary
    from gearscan.recon.depth_sigma import DEPTH_SIGMA_SCALES, band_labels

    zs = collect(args.seed, "wide", 1)
    family = {root: ("default rig" if "default_rig" in root else root.split("/")[-1]) for *_, root in zs}
    out: dict = {"split": "val", "purpose": "dev look, chooses nothing", "commit": commit(), "host": host(),
                 "seed": args.seed, "scales": DEPTH_SIGMA_SCALES.as_dict(), "cells": {}, "motions": {}}
    for fam in sorted(set(family.values())):
        for cls, scales in DEPTH_SIGMA_SCALES.by_class.items():
            for b, label in enumerate(band_labels()):
                parts = [z / scales[b] for (c, bb, _, root), z in zs.items() if c == cls and bb == b and family[root] == fam]
                if parts:
                    s = z_summary(np.concatenate(parts))
                    out["cells"].setdefault(fam, {}).setdefault(cls, {})[label] = {
                        "points": int(sum(p.size for p in parts)), "median": s["median_z"],
                        "beyond_2sigma": s["beyond_2sigma"]}
        motions = sorted({m for (_, _, m, root) in zs if family[root] == fam})
        for m in motions:
            parts = [z / DEPTH_SIGMA_SCALES.by_class[c][b] for (c, b, mm, root), z in zs.items()
                     if mm == m and family[root] == fam]
            s = z_summary(np.concatenate(parts))
            out["motions"].setdefault(fam, {})[m] = {"points": int(sum(p.size for p in parts)),
                                                      "median": s["median_z"], "beyond_2sigma": s["beyond_2sigma"]}
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    for fam, ms in out["motions"].items():
        print(fam, {m: f"{v['beyond_2sigma']:.1%}" for m, v in ms.items()})


if __name__ == "__main__":
    main()
