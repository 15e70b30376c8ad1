"""Reproduce a CD-DCU-Net from nothing in one command: render the twin data, train, calibrate.

The same command runs on a 2-core CPU or on a lent GPU machine (``--device cuda``); only the
budget and the number of render processes change::

    python scripts/reproduce_model.py --out runs/repro --device cpu --jobs 2 --train-minutes 120
    python scripts/reproduce_model.py --out runs/repro --device cuda --jobs 16 --total-minutes 9 --batch 128

(a lent machine's command runs at most 10 minutes: ``--total-minutes`` bounds render, probe and training
together; ``scripts/lease_train.sh`` below wraps it.)

Data (twin/splits.py: train gears and seeds only; val gears and seeds only for the validation
set that does early stopping and the sigma calibration; nothing from the test split):

- ``radial``: the shipped model's family (``--randomize``: radial view, module 1.5-3 mm, camera
  period 12-40 px), train tooth counts 11-40;
- ``views``: any view (radial/side/oblique/face), module 0.5-5 mm, camera period 5-60 px, train
  tooth counts 11-76;
- ``val``: the same two randomisers on val tooth counts and seeds.
- ``--dense-radial`` adds ``radial_dense``: the radial randomiser with train tooth counts 11-80 and
  camera periods 5-40 px (log-uniform), where large gears move their fringes a period and more
  per degree (the default rig's test family lives there: 11 px fringes at 256 px, gears to 80
  teeth), and its val twin ``val_radial_dense`` (val tooth counts 25-78, seed 10003).

The next model should add ``--outside-weight 0.05 --val-objective full``: the network is then taught what to output
outside the twin's truth mask and stopped on that objective (val, session 33: its unguarded per-burst cloud 124 -> 51
um on still bursts, 158 -> 96 um on moving ones at slightly higher coverage, at +2.3 % moving RMSE inside the mask; ``benchmarks/outside_loss_val.md``).
Without them the command is the one that trained v6.

Every item set is a folder of its own (one render process each), so the render runs in parallel
and resumes where it stopped. Training is ``scripts/train_default.py`` (deterministic stage,
then Concrete Dropout, cosine schedules, best-on-val weights, sigma calibration on val) with the
number of epochs sized to ``--train-minutes`` by a short timed probe on this machine.

On a lent GPU machine run it through ``scripts/lease_train.sh`` (one command of at most 600 s, with ``.lease`` from
``scripts/lease_carry.sh`` carried: open3d's CPU build for the machine's Python, pydantic, triangle and the
libraries open3d links against), which gives this command ``--total-minutes`` for what is left after its
install, draws the training bursts on the GPU (``--bank``) and copies what comes back into ``$OUT``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from gearscan.twin.splits import SplitError, split_of_seed, split_of_teeth

ROOT = Path(__file__).resolve().parents[1]
TRAIN = ROOT / "scripts" / "train_default.py"
CLOSE_S = 20.0  # kept free at the end of --total-minutes after the training's deadline: its last saves and exit


def _teeth(split: str, lo: int, hi: int) -> list[int]:
    """The tooth counts in ``[lo, hi]`` that ``split`` owns (twin/splits.py decides, not this script)."""
    return [t for t in range(lo, hi + 1) if split_of_teeth(t) == split]


# a render job: (folder name, teeth, repeats, max start points, any view?, seed, radial camera period
# range or None); one seed per folder so no two folders share a scene, each checked against its split in plan()
_RADIAL_TEETH = _teeth("train", 11, 40)  # the default's family: the shipped model's tooth range
_VIEW_TEETH = _teeth("train", 11, 76)
_DENSE_TEETH = _teeth("train", 11, 80)
DENSE_PERIOD_PX = (5.0, 40.0)
_VAL_SETS = [("val_radial", _teeth("val", 11, 40), 2, 2, False, 10002, None),
             ("val_views", _teeth("val", 41, 78), 1, 2, True, 10001, None)]
_VAL_DENSE = ("val_radial_dense", _teeth("val", 11, 80), 1, 2, False, 10003, DENSE_PERIOD_PX)


def _chunks(values: list[int], n: int) -> list[list[int]]:
    return [values[i::n] for i in range(n) if values[i::n]]


def plan(scale: float, dense: int = 0, gears_per_set: int | None = None) -> tuple[list[tuple], list[tuple]]:
    """The render jobs (train, val) for a data ``scale`` (1.0: about 420 train start points, 18 GB at 256x256; 0.7: 300).

    ``dense`` > 0 adds that many repeats of the dense radial set (34 train gears each) and its val set.
    ``gears_per_set`` keeps only that many tooth counts per folder (a quick run of the whole command).
    """
    repeats_radial = max(1, round(6 * scale))
    repeats_views = max(1, round(4 * scale))
    train = []
    for i, teeth in enumerate(_chunks(_RADIAL_TEETH, 6)):
        train.append((f"radial_{i}", teeth, repeats_radial, 1, False, 3001 + i, None))
    for i, teeth in enumerate(_chunks(_VIEW_TEETH, 10)):
        train.append((f"views_{i}", teeth, repeats_views, 2, True, 4001 + i, None))
    if dense:
        for i, teeth in enumerate(_chunks(_DENSE_TEETH, 4)):
            train.append((f"radial_dense_{i}", teeth, dense, 1, False, 3101 + i, DENSE_PERIOD_PX))
    val = [*_VAL_SETS, *([_VAL_DENSE] if dense else [])]
    if gears_per_set is not None:
        train, val = ([(j[0], j[1][:gears_per_set], *j[2:]) for j in jobs] for jobs in (train, val))
    for name, jobs in (("train", train), ("val", val)):
        wrong = [j[0] for j in jobs if split_of_seed(j[5]) != name]
        if wrong:
            raise SplitError(f"render jobs {wrong}: seed outside the {name} split")
    return train, val


def _render(job: tuple, root: Path, size: int) -> str:
    """One folder of twin data (resumes a partial one); runs in its own process."""
    from gearscan.core.gear import GearSpec
    from gearscan.twin.dataset import DatasetSpec, generate_dataset

    name, teeth, repeats, points, views, seed, period = job
    gears = [GearSpec(teeth=t) for t in teeth for _ in range(repeats)]
    spec = DatasetSpec(gears=gears, width=size, height=size, randomize=True, views=views, seed=seed,
                       max_start_points=points, radial_period_px=period)
    t0 = time.time()
    generate_dataset(root / name, spec)
    return f"{name}: {len(gears)} scenes, {time.time() - t0:.0f} s"


def render(jobs: list[tuple], root: Path, size: int, processes: int) -> None:
    """Render every job's folder, ``processes`` at a time (one render thread pair each)."""
    root.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    with ProcessPoolExecutor(processes) as pool:
        for line in pool.map(_render, jobs, [root] * len(jobs), [size] * len(jobs)):
            print("rendered", line, flush=True)


def _train_cmd(args, train_dirs: list[Path], val_dirs: list[Path], out: Path, epochs_det: int, epochs_drop: int,
               steps: int, val_items: int) -> list[str]:
    return [sys.executable, str(TRAIN), "--train", *map(str, train_dirs), "--val", *map(str, val_dirs),
            "--out", str(out), "--width", str(args.width), "--crop", str(args.crop), "--batch", str(args.batch),
            "--steps-per-epoch", str(steps), "--epochs-det", str(epochs_det), "--epochs-drop", str(epochs_drop),
            "--lr", str(args.lr), "--val-items", str(val_items), "--patience", "1000", "--reverse",
            "--static-repeat", str(args.static_repeat), "--dropout-init", "0.02,0.1", "--device", args.device,
            "--workers", str(args.workers), "--threads", str(args.threads),
            *(["--bank"] if args.bank else []),
            *(["--compile"] if args.compile else []),
            *(["--init", str(args.init)] if args.init else []),
            *(["--prior-input", "--prior-jitter", str(args.prior_jitter)] if args.prior_input else []),
            *(["--outside-weight", str(args.outside_weight)] if args.outside_weight else []),
            *(["--val-objective", args.val_objective] if args.val_objective != "inside" else [])]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("runs/repro"))
    ap.add_argument("--data", type=Path, default=Path("data/repro"), help="where the renders go (resumed)")
    ap.add_argument("--device", default="auto", help="auto, cpu or cuda")
    ap.add_argument("--jobs", type=int, default=2, help="render processes")
    ap.add_argument("--scale", type=float, default=1.0, help="data size (1.0: about 420 train start points, 18 GB)")
    ap.add_argument("--size", type=int, default=256, help="rendered image size, px")
    ap.add_argument("--gears-per-set", type=int, default=None, metavar="N",
                    help="render only N tooth counts per folder (a quick run of the whole command)")
    ap.add_argument("--width", type=int, default=8, help="network base width w")
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--static-repeat", type=int, default=20, help="oversample the still bursts")
    ap.add_argument("--outside-weight", type=float, default=0.0,
                    help="weight of the M, D error outside the truth mask (inference.losses.LossConfig.outside_weight)")
    ap.add_argument("--val-objective", default="inside", choices=["inside", "full"],
                    help="what early stopping reads (scripts/train_default.py)")
    ap.add_argument("--steps-per-epoch", type=int, default=200)
    ap.add_argument("--val-items", type=int, default=96)
    ap.add_argument("--train-minutes", type=float, default=120.0, help="wall-clock training budget")
    ap.add_argument("--workers", type=int, default=0, help="DataLoader workers")
    ap.add_argument("--bank", action=argparse.BooleanOptionalAction, default=None,
                    help="draw training bursts on the device (inference.burst_bank); default: on with --device cuda")
    ap.add_argument("--compile", action="store_true",
                    help="torch.compile the training steps (the probe's second epoch times the compiled step)")
    ap.add_argument("--total-minutes", type=float, default=None,
                    help="wall-clock budget of the whole command (render, probe, training); the training gets "
                         "what is left and stops itself before it (a lent machine's command limit); "
                         "replaces --train-minutes")
    ap.add_argument("--probe-steps", type=int, default=100, help="steps per epoch of the timing probe (2 epochs)")
    ap.add_argument("--no-calibrate", action="store_true",
                    help="skip the trainer's sigma calibration (refit later with gearscan calibrate-uncertainty)")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--dense-radial", type=int, default=0, metavar="N",
                    help="add N repeats of the dense radial set (train gears 11-80, camera period 5-40 px) and its val set")
    ap.add_argument("--init", type=Path, default=None, help="fine-tune from these weights (.safetensors)")
    ap.add_argument("--prior-input", action="store_true",
                    help="train a network fed the twin's prediction of each burst (phase changes and shading ratios "
                         "from the CAD: benchmarks/prior_input_report.md); with --init from a plain one, widened")
    ap.add_argument("--prior-jitter", type=float, default=0.05, help="with --prior-input: see train_default.py")
    ap.add_argument("--skip-render", action="store_true", help="the renders are already in --data")
    ap.add_argument("--render-only", action="store_true", help="stop after rendering")
    args = ap.parse_args()
    t_start = time.time()
    if args.bank is None:
        args.bank = args.device == "cuda"

    if args.init is not None and not args.init.is_file():
        raise SystemExit(f"--init {args.init}: no such weights file")
    train_jobs, val_jobs = plan(args.scale, args.dense_radial, args.gears_per_set)
    t0 = time.time()
    if not args.skip_render:
        render(train_jobs + val_jobs, args.data, args.size, args.jobs)
    render_s = time.time() - t0
    if args.render_only:
        print(f"rendered in {render_s:.0f} s", flush=True)
        return
    train_dirs = [args.data / j[0] for j in train_jobs]
    val_dirs = [args.data / j[0] for j in val_jobs]

    # probe: seconds per training step on this machine with these settings (the second, warm epoch's)
    probe = args.out / "probe"
    # validated on as many items as the run (validation is part of an epoch's time)
    subprocess.run(_train_cmd(args, train_dirs, val_dirs, probe, 2, 0, args.probe_steps, args.val_items)
                   + ["--no-calibrate"], check=True)
    last = json.loads((probe / "metrics.json").read_text())[-1]
    per_step = last["seconds"] / last["steps"]
    budget_s = args.train_minutes * 60
    extra = ["--no-calibrate"] if args.no_calibrate else []
    if args.total_minutes is not None:  # the training stops itself by a deadline that leaves its close
        deadline = t_start + args.total_minutes * 60 - CLOSE_S
        budget_s = deadline - time.time()
        if budget_s < 60:
            raise SystemExit(f"--total-minutes {args.total_minutes}: {budget_s + CLOSE_S:.0f} s left after the "
                             f"render and the probe, not enough to train (expected >= {60 + CLOSE_S:.0f} s)")
        extra += ["--deadline", f"{deadline:.1f}"]
    # sized to 85 % of a CPU budget; 95 % of a wall budget, which stops the run itself if the probe was optimistic
    fill = 0.95 if args.total_minutes is not None else 0.85
    total_epochs = max(2, int(budget_s * fill / (per_step * args.steps_per_epoch)))
    epochs_drop = max(1, total_epochs // 10)
    epochs_det = total_epochs - epochs_drop
    # how much of a step waited on the loader: a large share means more workers (or GPU-side bursts), not a
    # wider or faster network, would buy steps (the session-22 lease had 58 ms/step at w8 and at w32 alike)
    wait = last.get("data_wait_s", float("nan")) / last["steps"]
    print(f"probe: {per_step * 1000:.0f} ms/step ({wait * 1000:.0f} ms of it waiting on the loader, "
          f"{last.get('train_s', float('nan')) / last['steps'] * 1000:.0f} ms training) -> {epochs_det} + {epochs_drop} "
          f"epochs of {args.steps_per_epoch}", flush=True)
    t2 = time.time()
    subprocess.run(_train_cmd(args, train_dirs, val_dirs, args.out, epochs_det, epochs_drop, args.steps_per_epoch,
                              args.val_items) + extra, check=True)
    rows = json.loads((args.out / "metrics.json").read_text()) if (args.out / "metrics.json").is_file() else []
    info = {"render_seconds": render_s, "train_seconds": time.time() - t2, "probe_ms_per_step": per_step * 1000,
            "stages_run": sorted({int(r["stage"]) for r in rows if r.get("steps")}),
            "probe_ms_data_wait_per_step": wait * 1000,
            "epochs": [epochs_det, epochs_drop], "args": {k: str(v) for k, v in vars(args).items()},
            "train_sets": train_jobs, "val_sets": val_jobs}
    (args.out / "reproduce.json").write_text(json.dumps(info, indent=2))
    print(json.dumps({k: info[k] for k in ("render_seconds", "train_seconds", "epochs")}), flush=True)


if __name__ == "__main__":
    main()
