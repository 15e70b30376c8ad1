"""Score a model's stored sigma map on VAL folders: ECE of moving and still bursts per folder.

    python scripts/score_sigma_map.py data/repro/val_radial data/repro/val_views [--model M] [--items 64] [--mc 20]

The same burst sample as ``gearscan calibrate-uncertainty`` draws for these folders in this order
(:func:`gearscan.inference.calibrate.val_samples`), so a map already stored can be set beside the
held-out maps a refit reports (``benchmarks/v6_recalibration_rule.md``). Val only. JSON on stdout.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from gearscan.inference.calibrate import PixelErrors, collect_errors, val_samples
from gearscan.inference.predictor import Predictor
from gearscan.inference.uncertainty import reliability


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--model", default=None)
    ap.add_argument("--items", type=int, default=64)
    ap.add_argument("--mc", type=int, default=20, help="Monte Carlo passes (0: deterministic only)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    predictor = Predictor.load(args.model, orientation="normal")
    sets = val_samples(args.folders, args.items, args.seed, predictor.needs_angles)
    out: dict[str, dict] = {}
    for mode, passes in (("deterministic", 0), *((("mc", args.mc),) if args.mc > 0 else ())):
        parts: dict[tuple[int, bool], list[PixelErrors]] = {}
        for k, ds, picked, still in sets:
            parts.setdefault((k, still), []).append(collect_errors(predictor, ds, picked, passes, folder=k, still=still))
        out[mode] = {
            f"{args.folders[k]} {'still' if still else 'moving'}": float(reliability(px.error, px.sigma).ece)
            for (k, still), pieces in sorted(parts.items()) for px in [PixelErrors.concat(pieces)]
        }
        out[mode]["worst"] = float(np.max(list(out[mode].values())))
    print(json.dumps({"model": args.model or "shipped", "items": args.items, "seed": args.seed, **out}, indent=1))


if __name__ == "__main__":
    main()
