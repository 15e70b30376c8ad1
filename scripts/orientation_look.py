"""Dev look (val, chooses nothing): which per-burst orientation vote reads fast bursts right, without the rig.

    python scripts/orientation_look.py [--seed 3000] [--out benchmarks/orientation_look.json]

``Predictor(orientation="auto")`` (``gearscan predict`` without ``--rig``) votes each burst's fringe direction on its
three-step phase (:func:`~gearscan.inference.predictor.falling_phase_share`); fringes drifting a third of a period per
frame make the reversed three-step set and mislead it (test: 1.3-1.8 rad at 1-2 deg/frame as shipped, 0.22-0.30 with
the rig's orientation). Candidates, per burst of the val scenes of the cloud choices (one per motion of the wide set)
and the same burst mirrored along the columns (a mirrored rig; its answer is "mirrored"):
- ``three_step``: today's vote;
- ``sigma``: decode both ways with the network, take the way whose median total sigma over the lit pixels is lower
  (the network never saw a mirrored burst; its sigma may say so);
- ``net_phase``: the share of falling column steps of the network's phase decoded as normal.
Records each candidate's share right per motion. Decides nothing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=3000)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "orientation_look.json")
    args = ap.parse_args()

    import torch
    from inspect_bench import commit, host

    from gearscan.evaluate import VAL_CLOUD_SETS, VAL_MOTIONS, render_cases, scenes_from_dataset
    from gearscan.inference.predictor import (
        Predictor,
        falling_phase_share,
        falling_step_share,
        frames_to_tensor,
    )

    predictor = Predictor.load(None, orientation="normal")
    scenes = [s for root in VAL_CLOUD_SETS for s in scenes_from_dataset(ROOT / root)]
    rows = []
    for i, scene in enumerate(scenes):
        for case in render_cases(scene, VAL_MOTIONS["wide"], 1, seed=args.seed + i):
            for mirrored in (False, True):
                frames = case.frames[..., ::-1].copy() if mirrored else case.frames
                x = frames_to_tensor(frames, case.full_scale)
                lit = case.truth.mask[:, ::-1] if mirrored else case.truth.mask
                share3 = falling_phase_share(x)
                res = {m: predictor.predict_tensor(x, 0, mirror=m) for m in (False, True)}
                med = {m: float(np.median(r.sigma_total[lit])) if lit.any() else float("nan") for m, r in res.items()}
                net = falling_step_share(torch.from_numpy(res[False].phase), torch.from_numpy(res[False].modulation))
                rows.append({"scene": scene.name, "motion": case.motion, "mirrored": mirrored,
                             "three_step_share": share3, "sigma_normal": med[False], "sigma_mirrored": med[True],
                             "net_phase_share": net,
                             "votes": {"three_step": share3 is not None and share3 > 0.5,
                                       "sigma": med[True] < med[False],
                                       "net_phase": net is not None and net > 0.5}})
        print(f"{i + 1}/{len(scenes)} {scene.name}", flush=True)
    summary: dict = {}
    for r in rows:
        for cand, vote in r["votes"].items():
            cell = summary.setdefault(cand, {}).setdefault(r["motion"], [0, 0])
            cell[0] += int(vote == r["mirrored"])
            cell[1] += 1
    out = {"split": "val", "purpose": "dev look, chooses nothing", "commit": commit(), "host": host(),
           "seed": args.seed, "right_of": {c: {m: f"{a}/{n}" for m, (a, n) in ms.items()} for c, ms in summary.items()},
           "rows": rows}
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    for cand, ms in out["right_of"].items():
        print(cand, ms)


if __name__ == "__main__":
    main()
