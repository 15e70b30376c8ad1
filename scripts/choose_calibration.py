"""Choose the form of the sigma calibration on the VAL split: which map carries from one val folder to another.

    python scripts/choose_calibration.py data/repro/val_radial data/repro/val_views   # the shipped default (v6)

Per folder, 96 moving bursts (both senses) and 48 still ones through the uncalibrated network
(deterministic; ``--mc T`` for Monte Carlo). Each candidate map is fitted on one folder and
scored on the other (leave one folder out): ECE of the moving and of the still pixels apart,
and the median ``|err| / sigma`` (0.674 for a Gaussian that fits). Candidates: the power law
``a sigma^b`` and the departure map ``a sigma^b (departure + d0)^c``, each fitted by Gaussian NLL
and by the log score of the ECE's event. Val only: this chose the shipped form, so its numbers
are never reported as test numbers (benchmarks/generalization.py does that).
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from gearscan.inference.calibrate import PixelErrors, collect_errors, val_samples
from gearscan.inference.predictor import Predictor
from gearscan.inference.uncertainty import fit_sigma_calibration, reliability

CANDIDATES = {  # name: (uses the departure, fit score)
    "a sigma^b, NLL": (False, "nll"),
    "a sigma^b, event score": (False, "event"),
    "a sigma^b (dep + d0)^c, NLL": (True, "nll"),
    "a sigma^b (dep + d0)^c, event score": (True, "event"),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("val", nargs="+", help="two or more val folders")
    ap.add_argument("--model", default=None)
    ap.add_argument("--items", type=int, default=96, help="moving bursts per folder (half as many still)")
    ap.add_argument("--mc", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    if len(args.val) < 2:
        ap.error("val: expected two or more folders (each is scored by a map fitted on the others)")
    torch.set_num_threads(args.threads)
    predictor = Predictor.load(args.model, still_burst_rad=0.0)  # the map's form for the network's own pixels
    predictor.calibration = {}
    # the bursts calibrate_model fits the shipped map on (same sample, seed 0)
    px = PixelErrors.concat([collect_errors(predictor, ds, pick, args.mc, folder=k, still=still)
                             for k, ds, pick, still in val_samples(args.val, args.items, 0, predictor.needs_angles)])
    rows = []
    for name, (use_dep, score) in CANDIDATES.items():
        for k, folder in enumerate(args.val):
            held = px.folder == k
            fit, test = px.take(~held), px.take(held)
            cal, _ = fit_sigma_calibration(fit.error, fit.sigma, fit.departure if use_dep else None, score=score)
            sigma = cal(test.sigma, test.departure)
            row = {"map": name, "scored": folder, "fitted": cal.to_json(),
                   "median_abs_err_over_sigma": float(np.median(np.abs(test.error) / sigma))}
            for kind, keep in (("moving", ~test.still), ("still", test.still)):
                row[f"ece_{kind}"] = reliability(test.error[keep], sigma[keep]).ece
            rows.append(row)
    print("| map | scored on (fitted on the others) | ECE moving | ECE still | median abs(err)/sigma |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['map']} | {r['scored']} | {r['ece_moving']:.3f} | {r['ece_still']:.3f} | "
              f"{r['median_abs_err_over_sigma']:.2f} |")
    print(json.dumps({"model": str(args.model), "mc": args.mc, "items": args.items, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
