"""Model choice on the VAL split: phase RMSE of candidate models on a twin validation dataset.

    python scripts/val_compare.py data/views_val inference/weights/default.safetensors runs/v6/best.safetensors

Scores the first frame's truth phase over its valid mask, for moving bursts (both rotation
senses) and still bursts separately, next to three-step PS; the same seeded sample of bursts
for every model. Val only: this chooses a model, so its numbers are never reported as test
numbers (benchmarks/generalization.py does that).
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from gearscan.core.phase import phase_error, three_step
from gearscan.inference.predictor import ORIENTATIONS, Predictor
from gearscan.twin.dataset import TwinBurstDataset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("val")
    ap.add_argument("models", nargs="+")
    ap.add_argument("--items", type=int, default=96, help="moving bursts sampled (still: all start points)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--orientation", choices=ORIENTATIONS, default="auto",
                    help="the Predictor's fringe orientation: auto votes per burst (the shipped default; it misreads "
                         "some fast bursts); normal is every twin rig's, as a user sets it for the rig")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    moving = TwinBurstDataset(args.val, reverse=True)
    still = TwinBurstDataset(args.val, static=True, motion="uniform", max_span=0)
    pick = np.random.default_rng(0).choice(len(moving), min(args.items, len(moving)), replace=False)
    still_pick = np.random.default_rng(1).choice(len(still), min(args.items // 2, len(still)), replace=False)
    sets = {"moving": [moving[int(i)] for i in sorted(pick)], "still": [still[int(i)] for i in sorted(still_pick)]}
    out = {}
    for name, items in sets.items():
        if not items:
            continue
        row = {}
        err = [phase_error(three_step(it["input"][:3], 1.0)[0], it["phase"])[it["mask"]] for it in items]
        row["three-step"] = float(np.sqrt(np.mean(np.concatenate(err) ** 2)))
        for path in args.models:
            pred = Predictor.load(path, orientation=args.orientation, still_burst_rad=0.0)
            err = []
            for it in items:
                r = pred.predict_tensor(torch.from_numpy(np.asarray(it["input"], np.float32))[None])
                err.append(phase_error(r.phase, it["phase"])[it["mask"]])
            row[path] = float(np.sqrt(np.mean(np.concatenate(err) ** 2)))
        out[name] = {"bursts": len(items), "orientation": args.orientation, **row}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
