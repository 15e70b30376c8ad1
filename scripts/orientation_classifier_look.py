"""Dev look (session 45, not shipped): can a small learned classifier tell a burst's fringe orientation where the
per-burst vote misreads fast bursts? ``benchmarks/orientation_vote_look.md`` has the numbers.

    python scripts/orientation_classifier_look.py train --bursts 1600 --epochs 8 --out out/orient_clf.pt
    python scripts/orientation_classifier_look.py eval --seed 16000 --weights out/orient_clf.pt --out out/orient_eval.json

The classifier reads three-step PS's normalised M, D of a burst (they carry the frames' shift direction) and sums local evidence for "mirrored" over the image; it is antisymmetric by construction (evidence of
the column-flipped burst is the negated evidence), so a mirrored rig gets exactly the opposite call. Trained on
train-split twin bursts (radial-random and view-random rigs, train gears and seeds, 256x256, steps of 0-3 deg per
frame either way, 15 % still), each shown as rendered or column-flipped at random, and rows flipped at random (which
keeps the orientation). ``eval`` scores it on the val sample of ``scripts/orientation_val.py`` (same scenes, motions
and seeds) beside the vote.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from gearscan.core.gear import GearSpec
from gearscan.core.patterns import PatternError, PatternSet
from gearscan.inference.models import classical_md
from gearscan.twin.randomize import random_scene, random_view_scene
from gearscan.twin.render import RenderError, TwinRenderer
from gearscan.twin.splits import SPLITS

SIZE = 256
FIRST_SEED = 3000  # train seeds 3000 + i (train split: 3-9999)


def _render(seed: int) -> np.ndarray:
    """One train-split burst's three-step M, D (float16, (2, SIZE, SIZE))."""
    train = SPLITS["train"]
    teeth = sorted(t for t in train.teeth if 10 <= t <= 80)
    rng = np.random.default_rng(seed)
    z = int(teeth[int(rng.integers(len(teeth)))])
    train.check(teeth=z, seed=seed)  # 1000-9999: train seeds
    if seed % 2:
        rig, optics, gear, period = random_view_scene(rng, GearSpec(teeth=z), SIZE, SIZE)
    else:
        rig, optics, gear, period = random_scene(rng, GearSpec(teeth=z), SIZE, SIZE, camera_period_px=(5, 60))
    u = rng.random()
    if u < 0.15:
        s1 = s2 = 0.0
    elif u < 0.6:
        s1 = s2 = float(rng.uniform(0.2, 3.0))
    else:
        s1, s2 = float(rng.uniform(0.0, 3.0)), float(rng.uniform(0.0, 3.0))
    sign = 1 if rng.random() < 0.5 else -1
    a0 = float(rng.uniform(0, 360.0 / gear.teeth))
    angles = [a0, a0 + sign * s1, a0 + sign * (s1 + s2)]
    frames, _ = TwinRenderer(rig, gear, optics).render_sequence([math.radians(a) for a in angles],
                                                                 PatternSet.three_step(period), [0, 1, 2], rng)
    x = torch.from_numpy(frames.astype(np.float32) / float(optics.full_scale))[None]
    return classical_md(x)[0].numpy().astype(np.float16)


def render_one(index: int) -> np.ndarray:
    """Burst ``index`` from train seed ``FIRST_SEED + index``; a draw the twin refuses (a projector period under 2 px)
    moves on to another train seed (the recipe of the run the look reports)."""
    seed = FIRST_SEED + index
    for k in range(10):
        try:
            return _render(seed if k == 0 else seed * 7 % 8990 + 1000 + k)
        except (PatternError, RenderError):
            continue
    raise RuntimeError(f"burst {index}: ten train seeds refused by the twin")


class Evidence(nn.Module):
    """Evidence (logit) for "mirrored" from three-step M, D ``(B, 2, H, W)``; odd under column flips."""

    def __init__(self, width: int = 24):
        super().__init__()
        chans = [2, width, width, 2 * width, 2 * width, 2 * width]
        layers: list[nn.Module] = []
        for i in range(5):
            layers += [nn.Conv2d(chans[i], chans[i + 1], 3, stride=2 if i else 1, padding=1),
                       nn.GroupNorm(4, chans[i + 1]), nn.ReLU(inplace=True)]
        self.body = nn.Sequential(*layers)
        self.head = nn.Conv2d(chans[-1], 1, 1)

    def local(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.body(x)).mean(dim=(1, 2, 3))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.local(x) - self.local(torch.flip(x, dims=[-1]))


def train(args: argparse.Namespace) -> None:
    t0 = time.time()
    data = []
    with Pool(2) as pool:
        for i, d in enumerate(pool.imap(render_one, range(args.bursts), chunksize=4)):
            data.append(d)
            if i % 200 == 0:
                print(f"{i} rendered {time.time() - t0:.0f} s", flush=True)
    x_all = torch.from_numpy(np.stack(data))
    print(f"rendered {args.bursts} in {time.time() - t0:.0f} s", flush=True)
    torch.manual_seed(args.torch_seed)  # the reported run left torch unseeded
    model = Evidence()
    opt = torch.optim.AdamW(model.parameters(), 2e-3, weight_decay=1e-4)
    n, bs = args.bursts, 16
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, 3e-3, total_steps=args.epochs * (n // bs))
    for ep in range(args.epochs):
        perm = torch.randperm(n)
        tot, correct, t1 = 0.0, 0, time.time()
        for b in range(n // bs):
            x = x_all[perm[b * bs:(b + 1) * bs]].float()
            y = (torch.rand(bs) < 0.5).float()
            x = torch.where(y[:, None, None, None] > 0, torch.flip(x, dims=[-1]), x)
            rows = torch.rand(bs) < 0.5
            x = torch.where(rows[:, None, None, None], torch.flip(x, dims=[-2]), x)
            logit = model(x)
            loss = F.binary_cross_entropy_with_logits(logit, y)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            tot += float(loss.detach()) * bs
            correct += int(((logit > 0).float() == y).sum())
        print(f"epoch {ep}: loss {tot / (n // bs * bs):.4f} train accuracy {correct / (n // bs * bs):.3f} "
              f"{time.time() - t1:.0f} s", flush=True)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        torch.save(model.state_dict(), args.out)


def evaluate(args: argparse.Namespace) -> None:
    sys.path.insert(0, str(Path(__file__).parent))
    from orientation_val import MOTIONS, view_scenes

    from gearscan.evaluate import VAL_CLOUD_SETS, render_cases, scenes_from_dataset
    from gearscan.inference.predictor import falling_phase_share, frames_to_tensor

    model = Evidence()
    model.load_state_dict(torch.load(args.weights))
    model.eval()
    scenes = [s for root in VAL_CLOUD_SETS for s in scenes_from_dataset(root)] + view_scenes(24, args.seed)
    rows = []
    with torch.inference_mode():
        for i, scene in enumerate(scenes):
            for case in render_cases(scene, MOTIONS, 1, seed=args.seed + i):
                x = frames_to_tensor(case.frames, case.full_scale)
                rows.append({"scene": scene.name, "motion": case.motion, "vote_share": falling_phase_share(x),
                             "logit": float(model(classical_md(x[:, :3].float()))[0])})
    from gearscan.provenance import run_stamp

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"split": "val", "seed": args.seed, **run_stamp(), "rows": rows}, indent=1))
    logit = np.array([r["logit"] for r in rows])
    vote = np.array([r["vote_share"] or 0.0 for r in rows])
    print(f"{len(rows)} bursts (every rig normal): classifier misreads {int((logit > 0).sum())}, vote misreads "
          f"{int((vote > 0.5).sum())}, both {int(((logit > 0) & (vote > 0.5)).sum())}")
    for m in MOTIONS:
        sel = np.array([r["motion"] == m for r in rows])
        print(f"{m:30s} classifier {int((logit[sel] > 0).sum())} vote {int((vote[sel] > 0.5).sum())} of {int(sel.sum())}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("--bursts", type=int, default=1600)
    t.add_argument("--epochs", type=int, default=8)
    t.add_argument("--out", type=Path, required=True)
    t.add_argument("--torch-seed", type=int, default=0)
    e = sub.add_parser("eval")
    e.add_argument("--seed", type=int, required=True)
    e.add_argument("--weights", type=Path, required=True)
    e.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    torch.set_num_threads(2)
    (train if args.cmd == "train" else evaluate)(args)


if __name__ == "__main__":
    main()
