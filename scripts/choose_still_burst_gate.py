"""Choose a model's still-burst gate on the VAL split (or on one rig's own twin data) and store it in the model's JSON.

    python scripts/choose_still_burst_gate.py data/repro/val_radial data/repro/val_views \\
        data/default_rig/val/z25,data/default_rig/val/z32,data/default_rig/val/z46,data/default_rig/val/z62 \\
        [--model inference/weights/default.safetensors] [--write]

Each argument is a val family (comma-joined folders are pooled into one). The gate
(:func:`gearscan.inference.predictor.still_burst_gate`) decodes a whole burst by three-step PS when
the network's median departure from it over the burst's interior is below ``rad`` and, with a motion
check, the share of lit pixels whose frames swing more than a still fringe can
(:func:`~gearscan.inference.predictor.frame_motion_share`) is below ``max_motion``.

Rules (written before their runs): ``benchmarks/still_burst_gate_rule.md`` (``rad`` alone; within a
moving and a slow cost of 3 % and an ECE bound in every family, the smallest ``rad`` that brings the
still bursts to 1.05 x three-step PS wherever the network is above that; none reaches it: the largest
within cost; none within cost: 0) and, with ``--motion``, ``benchmarks/still_burst_motion_rule.md``
(``rad`` and ``max_motion`` together). Val only: the test split reports it
(``benchmarks/generalization.py``).

The rule's pieces live in :mod:`gearscan.inference.still_gate_choice`. The twin workflow runs the shipped rule
on a user's rig, that rig as its only family (``benchmarks/rig_still_gate_rule.md``), as
``gearscan still-gate ADAPT/ --model my_rig.safetensors`` (the same as this script's
``ADAPT/ --model my_rig.safetensors --motion --noise-sigma --write``).
"""

from __future__ import annotations

import argparse
import json

import torch

from gearscan.inference.model_io import read_config, write_config
from gearscan.inference.predictor import Predictor, burst_sigma_map, model_path
from gearscan.inference.still_gate_choice import (
    GRID,
    NOISE_SIGMA,
    STATISTIC,
    THREE_STEP_NOISE,
    Folders,
    by_view,
    choose,
    family_bursts,
    fit_gated_sigma,
    gate_table,
    motion_choice,
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("families", nargs="+", help="val folders; comma-joined folders pool into one family")
    ap.add_argument("--model", default=None)
    ap.add_argument("--seed", type=int, default=29)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--fit-sigma", action="store_true",
                    help="fit the gated bursts' sigma map on still val bursts drawn with seed + 1 (else: the model's, "
                         "or none: the model's departure map at departure 0)")
    ap.add_argument("--noise-sigma", action="store_true",
                    help="gated bursts get three-step's own noise propagation of the frames' measured noise "
                         "(no fitted parameter; the amendment in benchmarks/still_burst_motion_rule.md)")
    ap.add_argument("--by-view", action="store_true",
                    help="score each family's rig views (the rig name of each start point) as families of their own: "
                         "a cost in one view cannot hide in a pooled number")
    ap.add_argument("--motion", action="store_true",
                    help="choose rad and the frames' motion check together (benchmarks/still_burst_motion_rule.md)")
    ap.add_argument("--write", action="store_true", help="store the choice in the model's JSON")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    predictor = Predictor.load(args.model, orientation="normal", still_gate_rad=0.0, still_burst_rad=0.0)
    sigma_map, sigma_entry = burst_sigma_map(predictor.meta), (predictor.meta.get("still_burst_gate") or {}).get("sigma")
    families: dict[str, Folders] = {}
    for fam in args.families:
        folders: Folders = [(f, None) for f in fam.split(",")]
        if args.by_view:
            families |= {f"{fam} [{view}]": part for view, part in by_view(folders).items()}
        else:
            families[fam] = folders
    if args.noise_sigma and args.fit_sigma:
        ap.error("--noise-sigma and --fit-sigma: choose one sigma for the gated bursts")
    if args.noise_sigma:
        sigma_map, sigma_entry = THREE_STEP_NOISE, NOISE_SIGMA
    if args.fit_sigma:
        fit_rows = [r for folders in families.values()
                    for r in family_bursts(predictor, folders, args.seed + 1, None, ("still",))["still"]]
        sigma_map = fit_gated_sigma(fit_rows)
        sigma_entry = dict(zip("abc", sigma_map, strict=True)) | {
            "fitted_on": f"val still bursts, seed {args.seed + 1}, the families below pooled", "score": "event"}
        print(f"gated bursts' sigma map: a {sigma_map[0]:.4g}, b {sigma_map[1]:.4g}, c {sigma_map[2]:.4g}", flush=True)

    def show(fam: str, rows: dict) -> None:
        print(f"{fam}: " + "; ".join(f"rad {r}: " + ", ".join(f"{k} {v['rmse']:.4f} (3-step {v['three_step']:.4f}, "
                                                           f"ECE {v['ece']:.3f}, taken {v['taken']}/{v['bursts']})"
                                                           for k, v in row.items())
                                     for r, row in rows.items()), flush=True)

    table = gate_table(predictor, families, args.seed, sigma_map, motion=args.motion, progress=show)
    if args.motion:
        choice = motion_choice(table, args.families, args.seed, "normal", args.by_view, sigma_entry)
    else:
        choice = {
            "rad": choose(table), "chosen_on": "val split: " + "; ".join(families), "grid": list(GRID),
            "rule": ("benchmarks/still_burst_gate_rule.md: within moving and slow RMSE <= 1.03 x ungated and ECE "
                     "<= max(ungated + 0.005, 0.05) in every family, the smallest rad with still RMSE <= 1.05 x "
                     "three-step where the network is above it; else the largest within cost; else 0"),
            "statistic": STATISTIC, "orientation": "normal", "mode": "deterministic", "seed": args.seed,
            "by_view": args.by_view, "val": table,
        }
        if sigma_entry is not None:
            choice["sigma"] = sigma_entry
    print(json.dumps({k: v for k, v in choice.items() if k != "val"}, indent=1))
    if args.write:
        weights = model_path(args.model)
        meta = read_config(weights)
        meta["still_burst_gate"] = choice
        print(f"wrote still_burst_gate to {write_config(weights, meta)}")


if __name__ == "__main__":
    main()
