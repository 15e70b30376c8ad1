"""Choose a model's Monte Carlo phase on the VAL split and, with --write, store it and refit its MC sigma map.

    python scripts/choose_mc_phase.py data/repro/val_radial data/repro/val_views \\
        data/default_rig/val/z25,data/default_rig/val/z32,data/default_rig/val/z46,data/default_rig/val/z62 \\
        [--model inference/weights/default.safetensors] [--write] \
        [--rule two-sided --seed 11 --moving 96 --still 48]

Each argument is a val family (comma-joined folders are pooled into one). The rule is
``benchmarks/mc_phase_rule_v2.md`` (``--rule two-sided``, the default: the phase whose worst family x kind cell
against the other is lower) or, to reproduce the choices of sessions 38-39, ``benchmarks/mc_phase_rule.md``
(``--rule one-sided --seed 9 --moving 48 --still 24``); :mod:`gearscan.inference.mc_phase_choice`. With ``--write`` the choice goes into the model's JSON (``mc_phase``) and,
when it changes MC mode's phase, the MC sigma map is refitted on the sample the model's MC map was fitted on
(``uncertainty_calibration.mc`` in its JSON, else the top level: folders, items, seed, orientation; torch seeded 0); the deterministic map
is kept. Val only: the test split reports it (``benchmarks/generalization.py``, its MC section).
"""

from __future__ import annotations

import argparse
import json

import torch

from gearscan.inference.calibrate import calibrate_model
from gearscan.inference.mc_phase_choice import RULES, mc_phase_table
from gearscan.inference.model_io import read_config, write_config
from gearscan.inference.predictor import model_mc_phase, model_path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("families", nargs="+", help="val folders; comma-joined folders pool into one family")
    ap.add_argument("--model", default=None)
    ap.add_argument("--rule", choices=sorted(RULES), default="two-sided")
    ap.add_argument("--seed", type=int, default=11, help="draws the val bursts (the one-sided runs used 9)")
    ap.add_argument("--moving", type=int, default=96, help="moving bursts per family (the one-sided runs: 48)")
    ap.add_argument("--still", type=int, default=48, help="still bursts per family (the one-sided runs: 24)")
    ap.add_argument("--passes", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--write", action="store_true", help="store the choice and refit the MC sigma map")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    families = {fam: fam.split(",") for fam in args.families}
    table = mc_phase_table(args.model, families, seed=args.seed, moving=args.moving, still=args.still,
                           passes=args.passes, rule=args.rule, progress=print)
    phase = "deterministic" if table["rule"]["adopt"] else "mean"
    rule_text, draws = RULES[args.rule]
    choice = {"phase": phase, "rule": rule_text, "chosen_on": "val split: " + "; ".join(args.families),
              "seed": args.seed, "bursts_per_family": {"moving": args.moving, "still": args.still},
              "passes": args.passes,
              "statistic": "RMSE over the truth mask, pooled by pixels; MC: the mean of the draws' RMSEs "
                           f"(torch seeds {', '.join(map(str, draws))})",
              "val": table}
    print(json.dumps({k: v for k, v in choice.items() if k != "val"} | {"rule_verdict": table["rule"]}, indent=1))
    if not args.write:
        return
    weights = model_path(args.model)
    meta = read_config(weights)
    before = model_mc_phase(meta)
    meta["mc_phase"] = choice
    print(f"wrote mc_phase to {write_config(weights, meta)}")
    if phase != before:
        top = meta.get("uncertainty_calibration") or {}
        cal = {**top, **(top.get("mc") or {})}  # the MC map's own sample where it names one (since session 41)
        if not cal.get("data"):
            raise SystemExit(f"{weights.with_suffix('.json')}: no uncertainty_calibration.data to refit the MC map on; "
                             "run `gearscan calibrate-uncertainty` on your val folders")
        torch.manual_seed(0)
        rep = calibrate_model(weights, cal["data"], items=cal.get("items", {}).get("moving", 96) // len(cal["data"]),
                              mc=args.passes, seed=cal.get("seed", 0), orientation=cal.get("orientation", "normal"),
                              modes=("mc",))
        print(f"refitted the MC sigma map for MC mode's {phase} phase: {rep['mc']['map']}")


if __name__ == "__main__":
    main()
