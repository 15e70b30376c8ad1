"""Choose the shipped model's still gate on the VAL split and store it in the model's JSON.

    python scripts/choose_still_gate.py data/views_val [--model inference/weights/default.safetensors] [--write]

The gate (:func:`gearscan.inference.predictor.still_gate`) replaces the network's phase by
three-step PS's wherever the two differ by less than ``rad``. Rule: the smallest ``rad`` of the
grid whose val still-burst RMSE is within 5 % of three-step PS's and whose calibration (ECE of the
network's sigma, moving and still) is no worse than without a gate (+0.005); none: 0 (no gate),
with the table that says why. Val only: the test split reports it (benchmarks/generalization.py).
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from gearscan.core.phase import phase_error, three_step
from gearscan.inference.model_io import read_config, write_config
from gearscan.inference.predictor import Predictor, model_path
from gearscan.inference.uncertainty import reliability
from gearscan.twin.dataset import TwinBurstDataset

GRID = (0.0, 0.05, 0.1, 0.15, 0.2, 0.3)
STILL_TOLERANCE = 1.05
ECE_TOLERANCE = 0.005


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("val")
    ap.add_argument("--model", default=None)
    ap.add_argument("--items", type=int, default=96, help="moving bursts sampled (still: half as many)")
    ap.add_argument("--write", action="store_true", help="store the choice in the model's JSON")
    args = ap.parse_args()
    torch.set_num_threads(2)
    sets = {
        "moving": TwinBurstDataset(args.val, reverse=True),
        "still": TwinBurstDataset(args.val, static=True, motion="uniform", max_span=0),
    }
    predictors = {rad: Predictor.load(args.model, still_gate_rad=rad, still_burst_rad=0.0) for rad in GRID}
    table: dict[str, dict[str, float]] = {}
    ece: dict[str, dict[str, float]] = {}
    for seed, (name, ds) in enumerate(sets.items()):
        n = min(args.items // (1 + seed), len(ds))
        pick = sorted(np.random.default_rng(seed).choice(len(ds), n, replace=False))
        errs: dict[str, list[np.ndarray]] = {"three-step": [], **{f"{r:g}": [] for r in GRID}}
        sigmas: dict[str, list[np.ndarray]] = {f"{r:g}": [] for r in GRID}
        for i in pick:
            it = ds[int(i)]
            x = torch.from_numpy(np.asarray(it["input"], np.float32))[None]
            m = it["mask"]
            errs["three-step"].append(phase_error(three_step(it["input"][:3], 1.0)[0], it["phase"])[m])
            for rad, pred in predictors.items():
                res = pred.predict_tensor(x)
                errs[f"{rad:g}"].append(phase_error(res.phase, it["phase"])[m])
                sigmas[f"{rad:g}"].append(res.sigma_total[m])
        table[name] = {k: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for k, v in errs.items()}
        table[name]["bursts"] = n
        ece[name] = {k: float(reliability(np.concatenate(errs[k]), np.concatenate(v)).ece) for k, v in sigmas.items()}
    still, moving = table["still"], table["moving"]
    ok = [r for r in GRID if r > 0 and still[f"{r:g}"] <= STILL_TOLERANCE * still["three-step"]
          and all(ece[k][f"{r:g}"] <= ece[k]["0"] + ECE_TOLERANCE for k in ece)]
    chosen = min(ok) if ok else 0.0
    choice = {
        "rad": chosen, "chosen_on": f"val split: {args.val}", "grid": list(GRID),
        "rule": f"smallest rad with val still RMSE <= {STILL_TOLERANCE} x three-step PS and ECE (moving, still) "
                f"<= the ungated network's + {ECE_TOLERANCE}; none: 0 (no gate)",
        "val_rmse_rad": table, "val_ece": ece,
        "val_moving_cost": moving[f"{chosen:g}"] / moving["0"] - 1.0,
    }
    print(json.dumps(choice, indent=1))
    if args.write:
        weights = model_path(args.model)
        meta = read_config(weights)
        meta["still_gate"] = choice
        print(f"wrote still_gate to {write_config(weights, meta)}")


if __name__ == "__main__":
    main()
