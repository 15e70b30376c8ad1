"""Val sample for the per-burst fringe-orientation decision (``Predictor(orientation="auto")`` without a rig).

    python scripts/orientation_val.py --seed S --out out/orientation_val.json [--views 24]

Per burst of the val scenes (``evaluate.VAL_CLOUD_SETS`` and ``--views`` fresh ``view-random-val`` scenes drawn from
seeds ``S`` + i: val gears, val seeds), each motion once (still, the paper's motions both ways, the wider
generalisation motions): the column-step vote's falling share (:func:`~gearscan.inference.predictor.falling_phase_share`)
and, for each orientation the network could decode with, statistics a decision can read without the truth (the
network's sigma over the frames' modulated pixels, the falling share of its own phase in its input's frame) beside
the truth's RMSE. Every scene is rendered upright (the twin's orientation is "normal"); a mirrored rig is the same
burst with its columns flipped, which flips every statistic here with it, so a rule symmetric in the two decodes
reads it the same. No rule reads it yet: ``benchmarks/orientation_vote_look.md`` is a dev look on seed 16000, so a
rule written later needs fresh seeds.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from gearscan.core.rig import fringe_orientation
from gearscan.evaluate import (
    GENERALISATION,
    PAPER_MOTIONS,
    REVERSED,
    STATIC,
    VAL_CLOUD_SETS,
    Scene,
    render_cases,
    scenes_from_dataset,
)
from gearscan.inference.models import classical_md
from gearscan.inference.predictor import (
    Predictor,
    burst_departure,
    falling_phase_share,
    falling_step_share,
    frames_to_tensor,
)
from gearscan.twin.splits import SPLITS

MOTIONS = {**STATIC, **PAPER_MOTIONS, **REVERSED, **GENERALISATION}
MIN_MODULATION = 0.05


def view_scenes(count: int, seed: int, size: int = 256) -> list[Scene]:
    """``count`` fresh ``view-random-val`` scenes: val gears in turn, val seeds ``seed`` + i."""
    from gearscan.core.gear import GearSpec
    from gearscan.twin.randomize import random_view_scene

    val = SPLITS["val"]
    teeth = sorted(val.teeth)
    out = []
    for i in range(count):
        s = seed + i
        val.check(teeth=teeth[i % len(teeth)], rig_family="view-random-val", seed=s)
        rig, optics, gear, period = random_view_scene(np.random.default_rng(s), GearSpec(teeth=teeth[i % len(teeth)]),
                                                      size, size)
        out.append(Scene(f"view-random-val#{s} z={gear.teeth} m={gear.module}", rig, optics, gear, float(period)))
    return out


def nan_if_none(value: float | None) -> float:
    return float("nan") if value is None else value


def agree_share(phase: np.ndarray, three_step: np.ndarray, weight: np.ndarray) -> float:
    """Weighted share of pixels where ``phase`` is within pi/2 of three-step PS's."""
    d = np.abs(np.angle(np.exp(1j * (phase - three_step))))
    total = float(weight.sum())
    return float(weight[d < math.pi / 2].sum()) / total if total > 0 else float("nan")


def burst_record(predictor: Predictor, case) -> dict:
    x = frames_to_tensor(case.frames, case.full_scale)
    m3, d3 = classical_md(x[:, :3].float())[0].numpy()
    mod = np.hypot(m3, d3)
    lit = mod >= MIN_MODULATION
    weight = np.where(lit, mod, 0.0)
    truth = case.truth
    rec = {"scene": case.scene.name, "motion": case.motion, "vote_share": falling_phase_share(x),
           "rig_orientation": fringe_orientation(case.scene.rig).orientation,  # the truth: from the rig's geometry
           "lit_px": int(lit.sum())}
    for name, mirror in (("normal", False), ("mirrored", True)):
        r = predictor.predict_tensor(x, 0, mirror=mirror)
        err = np.angle(np.exp(1j * (r.phase - truth.phase)))[truth.mask]
        own = r.phase[:, ::-1] if mirror else r.phase  # the network's phase in the frame it decoded in
        s = r.sigma_total[lit]
        rec[name] = {"rmse": float(np.sqrt(np.mean(err ** 2))), "mode": r.mode,
                     "sigma_median": float(np.median(s)) if s.size else float("nan"),
                     "sigma_mean": float(np.mean(s)) if s.size else float("nan"),
                     "sigma_p90": float(np.percentile(s, 90)) if s.size else float("nan"),
                     "own_falling": nan_if_none(falling_step_share(torch.from_numpy(own.copy()), torch.from_numpy(
                         (mod[:, ::-1] if mirror else mod).copy()), MIN_MODULATION)),
                     "departure": burst_departure(r.phase, np.stack([m3, d3])),
                     "agree_share": agree_share(r.phase, np.arctan2(m3, d3), weight),
                     "net_modulation": float(np.median(r.modulation[lit])) if lit.any() else float("nan")}
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, required=True, help="burst seeds seed + scene index; view scenes' seeds too")
    ap.add_argument("--views", type=int, default=24, help="fresh view-random-val scenes beside the rendered val sets")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    predictor = Predictor.load(None, orientation="auto")
    scenes = [s for root in VAL_CLOUD_SETS for s in scenes_from_dataset(root)] + view_scenes(args.views, args.seed)
    records, t0 = [], time.time()
    for i, scene in enumerate(scenes):
        for case in render_cases(scene, MOTIONS, 1, seed=args.seed + i):
            records.append(burst_record(predictor, case))
        print(f"{i + 1}/{len(scenes)} {scene.name} {time.time() - t0:.0f} s", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    from gearscan.provenance import run_stamp

    args.out.write_text(json.dumps({"split": "val", "seed": args.seed, **run_stamp(), "scenes": [s.name for s in scenes],
                                    "motions": list(MOTIONS), "records": records}, indent=1))


if __name__ == "__main__":
    main()
