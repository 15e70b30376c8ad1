"""Three-step PS against the shipped network by burst span: where the correction starts to pay.

    .venv/bin/python benchmarks/still_crossover.py [--scenes 4 --per-motion 3]

Uniform bursts with frame steps from 0 (a still gear) to 0.2 deg on validation scenes (val-split
gears and rigs, never trained on): radial rigs and any-view rigs. The span below which
three-step PS wins sets the Decoder's ``still_span_deg`` (bursts the encoder sees spanning
less go to three-step PS). Writes benchmarks/still_crossover_report.{md,json}.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import torch
from inspect_bench import commit, host  # same folder: the host and commit lines of every report

from gearscan.evaluate import (
    classical_method,
    network_method,
    render_cases,
    scenes_from_dataset,
    score,
)
from gearscan.inference.decoder import STILL_SPAN_DEG
from gearscan.inference.predictor import Predictor, model_path

HERE = Path(__file__).resolve().parent
STEPS_DEG = (0.0, 0.0125, 0.025, 0.05, 0.1, 0.2)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--val", nargs="+", default=["data/repro/val_radial", "data/repro/val_views"],
                    help="twin validation folders (scripts/reproduce_model.py renders these)")
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--per-motion", type=int, default=3)
    ap.add_argument("--model", default=None, help="network weights (.safetensors); default: the shipped one")
    args = ap.parse_args()
    commit()  # before this run writes its report: a tree dirty with it is not an edit
    torch.set_num_threads(2)
    predictor = Predictor.load(args.model, still_burst_rad=0.0)  # the network itself, not the still-burst gate
    weights = model_path(args.model)
    weights = str(weights.relative_to(HERE.parent) if weights.is_relative_to(HERE.parent) else weights)
    methods = {"three-step PS": classical_method, "CD-DCU-Net": network_method(predictor)}
    motions = {f"{d:g}": (d, d) for d in STEPS_DEG}
    rows = []
    for root in args.val:
        scenes = scenes_from_dataset(root, limit=args.scenes)
        cases = [c for s in scenes for c in render_cases(s, motions, args.per_motion, seed=1)]
        for s in score(methods, cases):
            rows.append({"data": root, "step_deg": float(s.motion), "method": s.method, "rmse_rad": s.rmse_rad,
                         "bursts": s.bursts})
    wins_from = {root: _wins_from(rows, root) for root in args.val}
    (HERE / "still_crossover_report.json").write_text(json.dumps(
        {"rows": rows, "network_wins_from_span_deg": wins_from, "commit": commit(), "host": host(),
         "model": weights, "loadavg": os.getloadavg()}, indent=2))
    lines = [
        "# Still and slow bursts: three-step PS against the network",
        "",
        f"`python benchmarks/still_crossover.py --per-motion {args.per_motion}`: uniform bursts (frame 1 to 2 "
        "and 2 to 3 the same step), wrapped-phase RMSE on the truth's valid pixels, validation scenes "
        f"(the first {args.scenes} gears of each folder: val-split gears and rigs, never trained on), network deterministic.",
        "",
        f"- Commit `{commit()}`; host: {host()}.",
        f"- Model: `{weights}` ({predictor.model.config.name}), precision {predictor.precision}.",
        "",
        "| data | step deg | span deg | three-step PS rad | CD-DCU-Net rad | better |",
        "|---|---|---|---|---|---|",
    ]
    for root in args.val:
        for d in STEPS_DEG:
            r = {x["method"]: x["rmse_rad"] for x in rows if x["data"] == root and x["step_deg"] == d}
            best = min(r, key=r.get)
            lines.append(f"| {root} | {d:g} | {2 * d:g} | {r['three-step PS']:.3f} | {r['CD-DCU-Net']:.3f} | {best} |")
    lines += ["", "Where the network starts to win (the smallest span from which it beats three-step PS at every",
              "larger span of the grid):", ""]
    for root in args.val:
        from_span = wins_from[root]
        lines.append(f"- {root}: " + ("no span from which it wins at every larger one" if from_span is None else
                     "at every span, a still gear included" if from_span == 0 else f"from {from_span:g} deg"))
    lines += [
        "",
        "Three-step PS has no motion error on a still gear, only noise (and the projector's residual",
        "gamma on the randomised rigs); where the network's regression error is larger than that floor,",
        f"three-step PS wins. The pipeline's Decoder sends bursts whose encoder span is below {STILL_SPAN_DEG} deg",
        "to three-step PS (`model.still_span_deg`, `gearscan replay --still-span-deg`; 0 turns it off).",
        "The crossing depends on the rig (image motion per degree grows with gear radius and",
        "magnification): re-measure it on your rig with this script's method before changing the setting.",
    ]
    (HERE / "still_crossover_report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def _wins_from(rows: list[dict], root: str) -> float | None:
    """The smallest burst span (deg) from which the network beats three-step PS at every larger span of the grid."""
    spans = sorted(2 * d for d in STEPS_DEG)
    wins = {2 * d for d in STEPS_DEG if _rmse(rows, root, d, "CD-DCU-Net") < _rmse(rows, root, d, "three-step PS")}
    return next((s for s in spans if all(x in wins for x in spans if x >= s)), None)


def _rmse(rows: list[dict], root: str, step: float, method: str) -> float:
    return next(x["rmse_rad"] for x in rows if x["data"] == root and x["step_deg"] == step and x["method"] == method)


if __name__ == "__main__":
    main()
