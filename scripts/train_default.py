"""Recipe of v5, the default until session 23 (CPU): data, network and schedule in one place; v6 (the
shipped default now) was trained by scripts/reproduce_model.py, which calls this script's training.

Data (randomised rigs, optics, fringe periods and gear sizes; tooth count 25 is never trained on):

    gearscan twin dataset data/train --teeth 12,16,20,30,36 --repeats 4 --max-start-points 2 \
        --width 256 --height 256 --randomize --seed 1
    T=11,13,14,15,17,18,19,21,22,23,24,26,27,28,29,31,33,34,38,40
    gearscan twin dataset data/train2 --teeth $T --repeats 10 --max-start-points 1 --width 256 --height 256 --randomize --seed 7
    gearscan twin dataset data/train3 --teeth $T --repeats 10 --max-start-points 1 --width 256 --height 256 --randomize --seed 11
    gearscan twin dataset data/val --teeth 25 --repeats 3 --max-start-points 2 --width 256 --height 256 \
        --randomize --seed 2

v5's weights (`inference/weights/v5.*`) are the end of five runs, each starting from the one
before (CPU, ~130 min in all; `inference/weights/V5_MODEL_CARD.md`). The last run's ``--ship``
copies its weights over the shipped default (`default.*`, now v6); to rebuild v5 beside it, drop
``--ship`` and copy ``runs/v5r/best.*`` to ``inference/weights/v5.*``:

    python scripts/train_default.py --train data/train --out runs/v1 --epochs-det 35 --epochs-drop 5 \
        --steps-per-epoch 100 --crop 128 --lr 2e-3 --val-items 32 --patience 25
    python scripts/train_default.py --train data/train data/train2 --out runs/v2 \
        --init runs/v1/stage1_best.safetensors --reset-dropout --dropout-init 0.02,0.1 \
        --epochs-det 80 --epochs-drop 10 --steps-per-epoch 100 --crop 128 --lr 1e-3 --val-items 48 --patience 30
    python scripts/train_default.py --train data/train data/train2 data/train3 --out runs/v3 \
        --init runs/v2/best.safetensors --dropout-init 0.02,0.1 \
        --epochs-det 50 --epochs-drop 8 --steps-per-epoch 100 --crop 128 --lr 5e-4 --val-items 48 --patience 30
    python scripts/train_default.py --train data/train data/train2 data/train3 --out runs/v4 \
        --init runs/v3/best.safetensors --dropout-init 0.02,0.1 --static-repeat 10 \
        --epochs-det 8 --epochs-drop 2 --steps-per-epoch 100 --crop 128 --lr 2e-4 --val-items 48 --patience 30
    python scripts/train_default.py --train data/train data/train2 data/train3 --out runs/v5r \
        --init runs/v4/best.safetensors --reverse --dropout-init 0.02,0.1 --static-repeat 20 \
        --epochs-det 40 --epochs-drop 4 --steps-per-epoch 100 --crop 128 --lr 3e-4 --val-items 48 --patience 30 --ship

Then v5's uncertainty calibration (sigma' = a sigma^b per mode, by Gaussian NLL; ~6 CPU minutes).
Today's `gearscan calibrate-uncertainty` fits the departure map by the event score instead; v5's JSON
keeps the map below, which every report before session 23 measured:

    gearscan calibrate-uncertainty data/val --items 64 --mc 20
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import ConcatDataset, Subset

from gearscan.inference.data import MotionInput, PriorInput
from gearscan.inference.losses import LossConfig
from gearscan.inference.models import PRIOR_CHANNELS, ModelConfig
from gearscan.inference.train import TrainConfig, train
from gearscan.twin.dataset import TwinBurstDataset

WEIGHTS = Path(__file__).resolve().parents[1] / "inference" / "weights"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--train", type=Path, nargs="+", default=[Path("data/train")], help="one or more dataset folders")
    ap.add_argument("--val", type=Path, nargs="+", default=[Path("data/val")], help="one or more dataset folders")
    ap.add_argument("--out", type=Path, default=Path("runs/default"))
    ap.add_argument("--name", default="cd-dcu-net", help="cd-dcu-net, unet, ts-unet or dr-unet")
    ap.add_argument("--width", type=int, default=8)
    ap.add_argument("--crop", type=int, default=160)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--steps-per-epoch", type=int, default=50)
    ap.add_argument("--epochs-det", type=int, default=30)
    ap.add_argument("--epochs-drop", type=int, default=6)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--val-items", type=int, default=48)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="auto", help="auto, cpu or cuda")
    ap.add_argument("--workers", type=int, default=0, help="DataLoader workers")
    ap.add_argument("--bank", action="store_true",
                    help="draw the training bursts on the training device (inference.burst_bank; a GPU's choice: "
                         "DataLoader workers then serve validation only, so --workers 0 suits it)")
    ap.add_argument("--compile", action="store_true",
                    help="torch.compile the training steps (inductor; eager again, with a message, if it fails)")
    ap.add_argument("--deadline", type=float, default=None,
                    help="stop training by this wall-clock time, Unix seconds (best-on-val weights kept; the dropout "
                         "stage keeps its share; a lent machine's command limit)")
    ap.add_argument("--no-calibrate", action="store_true", help="skip the sigma calibration at the end")
    ap.add_argument("--precision", default="auto", choices=["auto", "fp32", "bf16"],
                    help="autocast; auto = bf16 on CUDA and on CPUs with native bf16 (AVX512-BF16/AMX), else fp32")
    ap.add_argument("--mse-weighting", default="modulation")
    ap.add_argument("--outside-weight", type=float, default=0.0,
                    help="weight of the M, D error outside the truth mask (against the 18-step label); 0: none")
    ap.add_argument("--val-objective", default="inside", choices=["inside", "full"],
                    help="what early stopping reads: the inside-mask loss (every model so far) or the full objective "
                         "with the --outside-weight term")
    ap.add_argument("--no-residual", action="store_true")
    ap.add_argument("--motion-input", action="store_true",
                    help="feed the encoder's rotation within the burst (2 extra channels); with --init from a "
                         "model without them, they start zero-weighted")
    ap.add_argument("--prior-input", action="store_true",
                    help="feed the twin's per-pixel prediction of the burst (phase changes and shading ratios "
                         "from the CAD; 7 extra channels, built here from the renders' truth); with --init from "
                         "a model without them, they start zero-weighted")
    ap.add_argument("--prior-jitter", type=float, default=0.05,
                    help="with --prior-input: scale each training burst's predicted changes by 1 +- this "
                         "(an encoder or calibration a little off)")
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--init", type=Path, default=None, help="start from these weights (.safetensors)")
    ap.add_argument("--patience", type=int, default=12)
    ap.add_argument("--reverse", action="store_true", help="add every moving burst played backwards (the other rotation sense)")
    ap.add_argument("--static-repeat", type=int, default=1, help="oversample the motionless bursts this many times")
    ap.add_argument("--dropout-init", default="0.1,0.4", help="initial Concrete Dropout rate range MIN,MAX")
    ap.add_argument("--reset-dropout", action="store_true", help="re-draw the rates of the --init weights from --dropout-init")
    ap.add_argument("--ship", action="store_true", help="copy best model into inference/weights/default.*")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    parts = [TwinBurstDataset(root, crop=args.crop, static=True, static_repeat=args.static_repeat, seed=i,
                              reverse=args.reverse, prior=args.prior_input, prior_jitter=args.prior_jitter)
             for i, root in enumerate(args.train)]
    if args.motion_input:
        parts = [MotionInput(p) for p in parts]
    if args.prior_input:
        parts = [PriorInput(p) for p in parts]
    train_set = parts[0] if len(parts) == 1 else ConcatDataset(parts)
    p_min, p_max = (float(v) for v in args.dropout_init.split(","))
    val_parts = [TwinBurstDataset(root, crop=None, static=True, reverse=args.reverse, prior=args.prior_input)
                 for root in args.val]
    val_full = val_parts[0] if len(val_parts) == 1 else ConcatDataset(val_parts)
    if args.motion_input:
        val_full = MotionInput(val_full)
    if args.prior_input:
        val_full = PriorInput(val_full)
    rng = np.random.default_rng(0)
    val_set = Subset(val_full, sorted(rng.choice(len(val_full), args.val_items, replace=False).tolist()))
    residual = not args.no_residual
    config = TrainConfig(
        out_dir=str(args.out),
        model=ModelConfig(name=args.name, width=args.width, classical_input=residual, residual=residual,
                          in_channels=3 + 2 * args.motion_input + PRIOR_CHANNELS * args.prior_input,
                          motion_input=args.motion_input, prior_input=args.prior_input,
                          init_min=p_min, init_max=p_max),
        loss=LossConfig(alpha=1e-4, mse_weight=1.0, mse_weighting=args.mse_weighting, outside_weight=args.outside_weight),
        epochs_deterministic=args.epochs_det,
        epochs_dropout=args.epochs_drop,
        batch_size=args.batch,
        lr=args.lr,
        lr_dropout=args.lr / 10,
        schedule="cosine",
        patience=args.patience,
        init=str(args.init) if args.init else None,
        reset_dropout=args.reset_dropout,
        widen_inputs=args.motion_input or args.prior_input,
        steps_per_epoch=args.steps_per_epoch,
        val_objective=args.val_objective,
        precision=args.precision,
        device=args.device,
        num_workers=args.workers,
        bank=args.bank,
        compile=args.compile,
        deadline=args.deadline,
        calibrate=not args.no_calibrate,
        resume=args.resume,
        progress=sys.stdout.isatty(),  # a bar in a log file is only blank lines
    )
    t0 = time.time()
    result = train(config, train_set, val_set)
    info = {"train_seconds": time.time() - t0, "train_items": len(train_set), "val_items": len(val_set),
            "train_data": [str(r) for r in args.train], "val_data": [str(r) for r in args.val], "args": vars(args) | {"train": [str(r) for r in args.train], "val": [str(r) for r in args.val], "out": str(args.out)}}
    (args.out / "recipe.json").write_text(json.dumps(info, indent=2, default=str))
    print(result)
    if args.ship:
        WEIGHTS.mkdir(exist_ok=True)
        for ext in (".safetensors", ".json"):
            shutil.copy(args.out / f"best{ext}", WEIGHTS / f"default{ext}")


if __name__ == "__main__":
    main()
