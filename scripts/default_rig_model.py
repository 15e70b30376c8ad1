"""Fine-tune the shipped network on the product's default rig: the twin renders that rig with train gears.

    python scripts/default_rig_model.py --out runs/default_rig [--budget 40] [--gears 16]
    python scripts/default_rig_model.py --device cuda --bank --jobs 16 --batch 128 --lr 1e-3 \
        --schedule cosine-time --deadline-minutes 8 ...         # on a lent GPU (scripts/lease_train.sh)

The paper's digital-twin workflow (per-rig adaptation, `benchmarks/adaptation.py`) applied to the rig the
product ships with, over many gears instead of one: the default rig (`twin.families.default_rig_scene`)
aimed at train-split gears (module 2, random pressure angle and face width as the test family draws them,
train seeds), ``--init`` (v6 by default, as the first option; the option since session 54 from v9) fine-tuned under a CPU budget (batch 8, 128^2 crops, lr 3e-4 constant,
or annealed to 0 over ``--epochs`` with ``--schedule cosine``, or over the time left with ``cosine-time``; still
bursts x20, both senses; the weights best on the val folders are kept). On a GPU the same script takes
``--device cuda --bank`` and a wall-clock ``--deadline-minutes`` instead of the CPU budget. Val: the same rig with
val-split gears and a val seed. Test gears and seeds are refused by the dataset writer. Writes the
datasets under ``--data`` and the run (weights, metrics, ``default_rig.json``) under ``--out``.
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import ConcatDataset, Dataset, Subset

from gearscan.inference.losses import LossConfig
from gearscan.inference.model_io import read_config
from gearscan.inference.models import ModelConfig
from gearscan.inference.predictor import DEFAULT_MODEL
from gearscan.inference.train import TrainConfig, train
from gearscan.twin.dataset import DatasetSpec, TwinBurstDataset, generate_dataset
from gearscan.twin.families import (
    DEFAULT_RIG_MODULE,
    DEFAULT_RIG_PERIOD_PX,
    default_rig_scene,
    draw_gear,
)
from gearscan.twin.splits import SPLITS

VAL_TEETH = (25, 32, 46, 62)  # val-split tooth counts from small to large
TEETH = (10, 80)  # the test families' tooth range (twin/splits.py)


class CenterCrop(Dataset):
    """A val dataset's items cut to their central ``size`` x ``size``: val batches of several resolutions."""

    def __init__(self, dataset: Dataset, size: int) -> None:
        self.dataset, self.size = dataset, size

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, i: int) -> dict:
        item = dict(self.dataset[i])
        for key, value in item.items():
            if isinstance(value, np.ndarray) and value.ndim >= 2:
                h, w = value.shape[-2:]
                y, x = (h - self.size) // 2, (w - self.size) // 2
                item[key] = np.ascontiguousarray(value[..., y:y + self.size, x:x + self.size])
        return item


def _render_one(folder: Path, z: int, k: int, seed: int, start_points: int, size: int) -> Path:
    gear = draw_gear(np.random.default_rng([seed, k]), module=DEFAULT_RIG_MODULE, teeth=z)
    rig, optics = default_rig_scene(gear, (size, size))
    spec = DatasetSpec(gears=[gear], width=size, height=size, period_px=DEFAULT_RIG_PERIOD_PX, seed=seed + k,
                       max_start_points=start_points)
    t0 = time.perf_counter()
    generate_dataset(folder, spec, scene=(rig, optics, gear, DEFAULT_RIG_PERIOD_PX))
    print(f"{folder}: {time.perf_counter() - t0:.0f} s", flush=True)
    return folder


def render(root: Path, teeth: list[int], seed: int, start_points: int, size: int, jobs: int = 1) -> list[Path]:
    """One dataset folder per gear: the default rig aimed at it, ``start_points`` start angles each; ``jobs``
    gears rendered at once (each folder is the same whatever the number)."""
    tasks = [(root / f"z{z:02d}", z, k, seed, start_points, size) for k, z in enumerate(teeth)]
    if jobs <= 1:
        return [_render_one(*t) for t in tasks]
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        return list(pool.map(_render_one, *zip(*tasks, strict=True)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("runs/default_rig"))
    ap.add_argument("--data", type=Path, default=Path("data/default_rig"))
    ap.add_argument("--gears", type=int, default=16, help="train gears, spread over the train tooth counts")
    ap.add_argument("--start-points", type=int, default=4, help="start angles per train gear")
    ap.add_argument("--val-start-points", type=int, default=2)
    ap.add_argument("--seed", type=int, default=3201, help="first train seed (one per gear)")
    ap.add_argument("--val-seed", type=int, default=10005)
    ap.add_argument("--sizes", type=lambda v: [int(x) for x in v.split(",")], default=[256],
                    help="camera resolutions (square) to render the rig at, e.g. 256,512: the same gears and seeds at each")
    ap.add_argument("--budget", type=float, default=None,
                    help="CPU minutes of fine-tuning (default 40; none with --deadline-minutes)")
    ap.add_argument("--deadline-minutes", type=float, default=None,
                    help="wall-clock minutes from this script's start by which training ends (a GPU lease's limit)")
    ap.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    ap.add_argument("--bank", action="store_true", help="draw the training bursts on the device (inference/burst_bank.py)")
    ap.add_argument("--jobs", type=int, default=1, help="gears rendered at once (processes)")
    ap.add_argument("--steps-per-epoch", type=int, default=40, help="steps between val reads")
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--schedule", choices=("constant", "cosine", "cosine-time"), default="constant",
                    help="constant lr until the budget, cosine from lr to 0 over --epochs, or cosine-time over the "
                         "time left (budget or deadline)")
    ap.add_argument("--epochs", type=int, default=None,
                    help="epochs of --steps-per-epoch steps (cosine: the schedule's length; the budget still caps the run)")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--val-items", type=int, default=48)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--precision", default="fp32", choices=["auto", "fp32", "bf16"])
    ap.add_argument("--init", type=Path, default=DEFAULT_MODEL.with_name("v6.safetensors"),
                    help="the weights fine-tuned (default: v6, which the option's predecessor was fine-tuned from; the "
                         "option since session 54 was fine-tuned from v9, inference/weights/default.safetensors; the "
                         "option itself to continue it)")
    args = ap.parse_args()
    t_start = time.time()
    if args.deadline_minutes is not None:
        if not args.deadline_minutes > 0:
            ap.error(f"--deadline-minutes: expected > 0, got {args.deadline_minutes}")
        if args.budget is not None:
            ap.error("--budget and --deadline-minutes: expected one (CPU minutes here, wall minutes on a GPU)")
    elif args.budget is None:
        args.budget = 40.0
    if args.jobs < 1 or args.steps_per_epoch < 1:
        ap.error(f"--jobs, --steps-per-epoch: expected >= 1, got {args.jobs}, {args.steps_per_epoch}")
    if not SPLITS["train"].has_seed(args.seed) or not SPLITS["train"].has_seed(args.seed + args.gears - 1):
        ap.error(f"--seed: expected train seeds for all {args.gears} gears, got {args.seed}")
    if not SPLITS["val"].has_seed(args.val_seed) or not SPLITS["val"].has_seed(args.val_seed + len(VAL_TEETH) - 1):
        ap.error(f"--val-seed: expected val seeds, got {args.val_seed}")
    if args.schedule == "cosine" and args.epochs is None:
        ap.error("--schedule cosine: expected --epochs (the length the learning rate anneals over)")
    if args.epochs is not None and args.epochs < 1:
        ap.error(f"--epochs: expected >= 1, got {args.epochs}")
    torch.set_num_threads(args.threads)
    # the tooth counts users bring to this rig: the families' range (10-80), train split only
    pool = sorted(z for z in SPLITS["train"].teeth if TEETH[0] <= z <= TEETH[1])
    # spread evenly in tooth count (the pool is dense among small gears, the test family is not)
    train_teeth = sorted({min(pool, key=lambda z: abs(z - t)) for t in np.linspace(pool[0], pool[-1], args.gears)})
    if len(train_teeth) < args.gears:  # two spread points fell on the same train tooth count
        print(f"--gears {args.gears}: {len(train_teeth)} distinct train-split tooth counts in {TEETH[0]}-{TEETH[1]} "
              f"at that spread: {train_teeth}", flush=True)
    t0 = time.perf_counter()
    train_dirs, val_dirs = [], []
    for size in args.sizes:  # one size keeps the flat layout of the first run (data/default_rig/train/zNN)
        sub = "" if len(args.sizes) == 1 else f"{size}"
        train_dirs += render(args.data / "train" / sub, train_teeth, args.seed, args.start_points, size, args.jobs)
        val_dirs += render(args.data / "val" / sub, list(VAL_TEETH), args.val_seed, args.val_start_points, size,
                           args.jobs)
    render_s = time.perf_counter() - t0
    train_set = ConcatDataset([TwinBurstDataset(d, static=True, static_repeat=20, reverse=True, crop=args.crop, seed=i)
                               for i, d in enumerate(train_dirs)])
    val_full = ConcatDataset([CenterCrop(TwinBurstDataset(d, static=True, reverse=True), min(args.sizes))
                              for d in val_dirs])
    pick = np.random.default_rng(0).choice(len(val_full), min(args.val_items, len(val_full)), replace=False)
    val_set = Subset(val_full, sorted(pick.tolist()))
    if not args.init.is_file():
        ap.error(f"--init {args.init}: no such weights file")
    meta = read_config(args.init)
    config = TrainConfig(
        out_dir=str(args.out), model=ModelConfig.from_json(meta["model"]), loss=LossConfig(**meta["training"]["loss"]),
        epochs_deterministic=args.epochs or 1_000_000, epochs_dropout=0, batch_size=args.batch, lr=args.lr,
        schedule=args.schedule,
        patience=1_000_000, steps_per_epoch=args.steps_per_epoch, init=str(args.init), progress=False,
        calibrate=False, budget_cpu_min=args.budget,
        checkpoints_cpu_min=tuple(m for m in (10.0, 20.0, 30.0) if args.budget and m < args.budget),
        deadline=None if args.deadline_minutes is None else t_start + 60.0 * args.deadline_minutes,
        device=args.device, bank=args.bank, seed=0, precision=args.precision,
    )
    t1 = time.perf_counter()
    result = train(config, train_set, val_set)
    shown = {k: ",".join(map(str, v)) if isinstance(v, list) else v for k, v in vars(args).items()
             if v is not None and v is not False}
    words = [f"--{k.replace('_', '-')}" + ("" if v is True else f" {v}") for k, v in shown.items()]
    info = {"command": "python scripts/default_rig_model.py " + " ".join(words),
            "train_teeth": train_teeth, "val_teeth": list(VAL_TEETH), "train_dirs": [str(d) for d in train_dirs],
            "val_dirs": [str(d) for d in val_dirs], "render_s": render_s, "train_wall_s": time.perf_counter() - t1,
            "cpu_min": result.cpu_seconds / 60.0, "budget_hit": result.budget_hit, "best": str(result.best_path),
            "steps": int(sum(r.get("steps", 0) for r in result.history)), "train_items": len(train_set),
            "val_items": len(val_set)}
    (args.out / "default_rig.json").write_text(json.dumps(info, indent=1))
    print(json.dumps(info, indent=1))


if __name__ == "__main__":
    main()
