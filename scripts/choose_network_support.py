"""Choose the reconstructor's fringe-support guard for network phase on the VAL split.

    python scripts/choose_network_support.py --seed FRESH [--motions wide] [--out benchmarks/network_support_val.json]

Rule, written before this ran: ``benchmarks/network_support_rule.md``. Per val scene (one per gear of
``data/repro/val_radial``, ``data/repro/val_views`` and the default rig's val gears ``data/default_rig/val/z*``),
``--per-motion`` bursts of each motion (``--motions``: "wide", since session 45, still, the paper's two motions
both ways and the 0.5-3 deg steps of ``evaluate.GENERALISATION``; "paper" without those), seeds ``--seed`` + scene; the
shipped model (deterministic, rig orientation, still-burst gate as shipped) decodes each burst once and every
candidate ``network_support_px`` reconstructs it. Scored: cloud RMS over every point against the true gear
surface, and coverage of the truth mask, per kind (still, moving). Val only: the test split reports it
(``benchmarks/inference_accuracy.py``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

import torch

from gearscan.evaluate import VAL_CLOUD_SETS, VAL_MOTIONS, scenes_from_dataset, val_cloud_table
from gearscan.inference.model_io import model_fingerprint
from gearscan.inference.predictor import Predictor, model_path
from gearscan.provenance import run_stamp

CANDIDATES: tuple[int | None, ...] = (None, 0, 1, 2, 3, 4)
STILL_COVERAGE, MOVING_COVERAGE, TIE = 0.98, 0.90, 0.01


def key(px: int | None) -> str:
    return "none" if px is None else str(px)


def choose(table: dict) -> int | None:
    """The rule over ``table[key][kind]`` (kinds "still", "moving", and "three-step moving")."""
    base = table["none"]
    ok = [px for px in CANDIDATES
          if table[key(px)]["still"]["coverage"] >= STILL_COVERAGE * base["still"]["coverage"]
          and table[key(px)]["moving"]["coverage"] >= MOVING_COVERAGE * base["moving"]["coverage"]
          and table[key(px)]["moving"]["coverage"] >= table["three-step"]["moving"]["coverage"]]
    mean = {px: 0.5 * (table[key(px)]["still"]["rms_um"] + table[key(px)]["moving"]["rms_um"]) for px in ok}
    if not mean:
        return None
    best = min(mean.values())
    return next(px for px in ok if mean[px] <= best * (1 + TIE))  # ok is in CANDIDATES order: None, then smaller E


def keep_bound_settings() -> dict:
    """The reconstructor's keep bound as this run used it (the product's: ``recon.measure``)."""
    from gearscan.recon.measure import MAX_SIGMA_RAD, unwrapper_sees

    return {"max_sigma_rad": MAX_SIGMA_RAD,
            "unwrapper_sees": unwrapper_sees()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, required=True, help="fresh val burst seeds seed + scene (used: 900, 1300, 1500)")
    ap.add_argument("--per-motion", type=int, default=2)
    ap.add_argument("--motions", choices=sorted(VAL_MOTIONS), default="wide", help="the val sample's motions")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/network_support_val.json"))
    ap.add_argument("--model", type=Path, default=None, help="weights to score (default: the shipped model)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    predictor = Predictor.load(args.model, orientation="normal")
    scenes = [s for root in VAL_CLOUD_SETS for s in scenes_from_dataset(root)]
    configs = {key(px): {"network_support_px": px} for px in CANDIDATES}
    table = val_cloud_table(predictor, scenes, configs, seed=args.seed, per_motion=args.per_motion, three_step="none",
                            progress=lambda line: print(line, flush=True), motions=args.motions)
    chosen = choose(table)
    res = {"rule": "benchmarks/network_support_rule.md", "split": "val", "scenes": [s.name for s in scenes],
           "seed": args.seed, "per_motion": args.per_motion, "motions": args.motions, "model": str(args.model or "inference/weights/default.safetensors"),
           "weights_sha256": hashlib.sha256(model_path(args.model).read_bytes()).hexdigest()[:12],
           "model_fingerprint": model_fingerprint(model_path(args.model)),  # weights and sigma maps (since session 43)
           "orientation": "normal", "table": table, "chosen_network_support_px": chosen,
           "keep_bound": keep_bound_settings(), **run_stamp()}  # the keep bound every candidate ran with (since session 44)
    args.out.write_text(json.dumps(res, indent=1))
    for name in [key(px) for px in CANDIDATES] + ["three-step"]:
        row = table[name]
        print(f"{name:>10}: still {row['still']['rms_um']:.1f} um, coverage {row['still']['coverage']:.3f}; "
              f"moving {row['moving']['rms_um']:.1f} um, coverage {row['moving']['coverage']:.3f}")
    print(f"chosen network_support_px: {chosen}")


if __name__ == "__main__":
    main()
