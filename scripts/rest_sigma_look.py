"""Dev look (VAL only, chooses nothing): the amended rest-sigma rule on the fit-sigma rule's 12 val cells, shipped v9.

    python scripts/rest_sigma_look.py [--out benchmarks/rest_sigma_look_12cells.json]

The rest-sigma rule (``benchmarks/rest_sigma_rule.md``) reads 8 cells: seeds 31 and 47, both pattern orders, v9 and
the default-rig option. Held out, the fixed order of seed 23 then kept unfitted points 14.7 % beyond 2 sigma at the
chosen 1.5 (``frame_fit_heldout_report.md``, session 50). This look replays the 12 cells of ``fit_sigma_rule.md``
(six val seeds, both orders; the shipped v9 with the product's settings) exactly as ``calibrate_rest_sigma.py`` does
and scans the scale by the amended rule (median z <= 0.6745 and <= 4.55 % beyond 2 sigma among the kept unfitted
points), to size the rule's next rerun. Arrays under ``--recordings`` (``rest_look_*.npz``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "scripts"))
from calibrate_rest_sigma import at_scale, honest, rest_z  # noqa: E402
from choose_frame_fit_joint import STRETCHES  # noqa: E402  (the fit-sigma rule's 12 cells)
from frame_fit_heldout import render_stretch  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "rest_sigma_look_12cells.json")
    ap.add_argument("--recordings", type=Path, default=ROOT / "out" / "fused_support_val")
    ap.add_argument("--bursts", type=int, default=60)
    args = ap.parse_args()

    from inspect_bench import commit, host

    from gearscan.inference.decoder import Decoder
    from gearscan.recon.depth_sigma import DEPTH_SIGMA_SCALES
    from gearscan.recon.track import REST_SIGMA_SCALE, TrackRefiner

    decoder = Decoder(None)
    out = {"split": "val", "look": "chooses nothing; sizes the rest-sigma rule's next rerun", "commit": commit(),
           "host": host(), "shipped_rest_sigma_scale": REST_SIGMA_SCALE,
           "depth_sigma_scales": DEPTH_SIGMA_SCALES.as_dict(), "bursts": args.bursts, "cells": []}
    arrays = []
    for s in STRETCHES:
        for alternate in (True, False):
            order = "alternating" if alternate else "fixed"
            rec = render_stretch(args.recordings, s, alternate, args.bursts)
            keep = args.recordings / f"rest_look_v9_{s['seed']}_{order}.npz"
            cell = {"seed": s["seed"], "order": order, **rest_z(rec, decoder, keep)}
            out["cells"].append(cell)
            arrays.append(np.load(keep))
            print({k: cell[k] for k in ("seed", "order", "rest", "rest_rms_um", "median_z")}, flush=True)
    bound = TrackRefiner.__init__.__kwdefaults__["max_sigma_mm"]
    out["scan"], out["scale"] = [], None
    for c in np.arange(1.0, 6.5, 0.5):
        per_cell = at_scale(arrays, float(c), bound)
        out["scan"].append({"scale": float(c), "cells": per_cell})
        if out["scale"] is None and honest(per_cell):
            out["scale"] = float(c)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(f"the amended rule on these 12 cells: {out['scale']} (shipped {REST_SIGMA_SCALE})")


if __name__ == "__main__":
    main()
