"""What bounds a training step: time per step by network width and batch size, and operator calls per step.

A step whose time hardly grows with the batch is bound by per-operator overhead (Python dispatch, kernel
launches), not by arithmetic: larger batches are then nearly free. Session 22's lease saw 58 ms per step at
w = 8 and at w = 32 alike (batch 32) and read it as a starved loader; this benchmark measures the step without
any loader (synthetic tensors on the device), and with ``--data`` also a twin dataset item's and a
:class:`~gearscan.inference.burst_bank.BurstBank` batch's cost, so the two causes can be told apart. ``--compiled``
times the same steps through ``torch.compile`` (fused kernels: fewer operator calls), which the GPU lease reads to
choose whether to train compiled (``scripts/lease_train.sh``).

    python benchmarks/train_step_profile.py --device cpu --batches 2,8 --widths 8,32
    python benchmarks/train_step_profile.py --device cuda --batches 32,128,512 --compiled 8x128 --out OUT/train_step_profile
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch
from inference_speed import host_info  # benchmarks/ is this script's folder

from gearscan.inference.losses import LossConfig, PhaseLoss
from gearscan.inference.models import ModelConfig, build_model
from gearscan.inference.predictor import resolve_precision

REPO = Path(__file__).resolve().parents[1]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def step_fn(width: int, batch: int, crop: int, device: torch.device, bf16: bool, compiled: bool = False):
    """One training step of the shipped architecture (Adam, the lease's loss) on fixed synthetic tensors; with
    ``compiled`` the network runs through ``torch.compile``, as ``TrainConfig.compile`` runs it."""
    net = build_model(ModelConfig(name="cd-dcu-net", width=width, classical_input=True, residual=True)).to(device)
    run = torch.compile(net) if compiled else net
    crit = PhaseLoss(LossConfig(alpha=1e-4, mse_weight=1.0, mse_weighting="modulation", outside_weight=0.05))
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    g = torch.Generator(device="cpu").manual_seed(0)
    x = torch.rand(batch, 3, crop, crop, generator=g).to(device)
    t = (torch.rand(batch, 2, crop, crop, generator=g) * 2 - 1).to(device)
    m = (torch.rand(batch, crop, crop, generator=g) > 0.3).to(device)

    def step() -> None:
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            pred = run(x)
        loss = crit(pred, t, m, net, include_regularization=False)["total"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return step


def time_steps(step, device: torch.device, warmup: int, steps: int) -> float:
    """Median seconds per step over ``steps`` timed steps, each synchronised."""
    for _ in range(warmup):
        step()
    _sync(device)
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        step()
        _sync(device)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def count_ops(step) -> int:
    """Operator calls the host dispatches in one step (top-level torch ops under the profiler)."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        step()
    return sum(1 for e in prof.events() if e.cpu_parent is None)


def loader_costs(folders: list[Path], batch: int, crop: int, device: torch.device) -> dict:
    """A warm twin dataset item (DataLoader path) and a BurstBank batch (device path), in ms."""
    from gearscan.inference.burst_bank import BurstBank
    from gearscan.twin.dataset import TwinBurstDataset

    parts = [TwinBurstDataset(f, crop=crop, static=True, static_repeat=20, reverse=True) for f in folders]
    rng = np.random.default_rng(0)
    idx = [(p, int(i)) for p in parts for i in rng.integers(0, len(p), 200)]
    for p, i in idx:
        p[i]
    t0 = time.perf_counter()
    for p, i in idx:
        p[i]
    item_ms = (time.perf_counter() - t0) / len(idx) * 1000
    t0 = time.perf_counter()
    bank = BurstBank(parts, device)
    build_s = time.perf_counter() - t0
    gen = torch.Generator(device=device).manual_seed(0)
    for _ in range(3):
        bank.draw(batch, gen)
    _sync(device)
    t0 = time.perf_counter()
    for _ in range(20):
        bank.draw(batch, gen)
    _sync(device)
    return {"item_ms": item_ms, "bank_batch_ms": (time.perf_counter() - t0) / 20 * 1000, "bank_build_s": build_s,
            "bank_mb": bank.nbytes / 2**20, "start_points": int(bank.frames.shape[0]), "batch": batch}


def write(info: dict, args: argparse.Namespace) -> None:
    """The JSON and the markdown table, rewritten after every row: a profile stopped by a timeout still reports."""
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(info, indent=2))
    loader = info["loader"]
    lines = [f"# Training step: what bounds it ({info['device']}, {info['host']})", "",
             f"`python benchmarks/train_step_profile.py --device {args.device} --widths {args.widths} --batches "
             f"{args.batches}{' --compiled ' + args.compiled if args.compiled else ''}"
             f"{''.join(' --data ' + str(f) for f in args.data[:1])}{' ...' if len(args.data) > 1 else ''}`; commit "
             f"`{info['commit']}`; load average {info['load_average'][0]:.2f}; torch {torch.__version__}, "
             f"{info['precision']} autocast, {args.threads} threads, {args.crop}x{args.crop} crops, synthetic tensors "
             f"already on the device (no loader), Adam, median of {args.steps} synchronised steps after "
             f"{args.warmup} warm-up. Compiled: the network through `torch.compile` (default mode), as "
             "`TrainConfig.compile` runs it; its first step, which compiles, is timed apart.", "",
             "| width | batch | step | ms per step | crops per s | operator calls per step | first step (s) |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['width']} | {r['batch']} | {'compiled' if r['compiled'] else 'eager'} | {r['ms_per_step']:.1f} | "
              f"{r['crops_per_s']:.0f} | {r['ops_per_step']} | {r['first_step_s']:.1f} |" for r in info["rows"]]
    if loader:
        lines += ["", f"Loader costs ({len(args.data)} twin folders, {loader['start_points']} start points): a warm "
                  f"dataset item (what a DataLoader worker builds) {loader['item_ms']:.2f} ms; a BurstBank batch of "
                  f"{loader['batch']} drawn on the device {loader['bank_batch_ms']:.1f} ms (bank {loader['bank_mb']:.0f} "
                  f"MB, built in {loader['bank_build_s']:.1f} s)."]
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n")


COMPILE_MIN_SPEEDUP = 1.25  # a compiled step at least this much faster than the eager one ...
COMPILES = 3  # ... and what it saves over the training pays for this many compiles (the lease's probe, stage 1, stage 2)


def worth_compiling(info: dict, width: int, batch: int, train_s: float) -> bool:
    """Whether a profile says to train compiled at ``width`` x ``batch`` for about ``train_s`` seconds: both rows
    measured, the compiled step at least ``COMPILE_MIN_SPEEDUP`` faster, and the time it saves over ``train_s``
    at least ``COMPILES`` compiles (the compiled row's first step)."""
    rows = {r["compiled"]: r for r in info["rows"] if (r["width"], r["batch"]) == (width, batch)}
    if len(rows) != 2:
        return False
    speedup = rows[False]["ms_per_step"] / rows[True]["ms_per_step"]
    return speedup >= COMPILE_MIN_SPEEDUP and COMPILES * rows[True]["first_step_s"] <= train_s * (1 - 1 / speedup)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--widths", default="8,32")
    ap.add_argument("--batches", default="2,8")
    ap.add_argument("--compiled", default="", metavar="WxB,...",
                    help="also time these width x batch steps compiled (e.g. 8x128), after the eager rows (and eager, "
                         "if the widths and batches leave them out)")
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--data", type=Path, nargs="*", default=[], help="twin dataset folders for the loader costs")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "train_step_profile")
    ap.add_argument("--worth-compiling", type=Path, metavar="JSON",
                    help="only print 1 or 0: whether this profile's rows say to train compiled at the one --compiled "
                         "width x batch for --train-seconds")
    ap.add_argument("--train-seconds", type=float, default=None, help="with --worth-compiling: the training's length")
    args = ap.parse_args()
    if args.worth_compiling:
        wanted = [c for c in args.compiled.split(",") if c]
        if len(wanted) != 1 or args.train_seconds is None:
            ap.error("--worth-compiling: expected one --compiled WxB and --train-seconds S")
        w, b = map(int, wanted[0].split("x"))
        print(int(worth_compiling(json.loads(args.worth_compiling.read_text()), w, b, args.train_seconds)))
        return
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    bf16 = resolve_precision("auto", device, training=True) == "bf16"
    h = host_info(args.threads)
    host = (f"{h['cpu']}, {h['cores']} cores, AVX512-BF16 {'yes' if h['avx512_bf16'] else 'no'}, AMX-BF16 "
            f"{'yes' if h['amx_bf16'] else 'no'}")
    if device.type == "cuda":
        host = f"{torch.cuda.get_device_name(device)}; host {host}"
    info = {"device": str(device), "host": host, "precision": "bf16" if bf16 else "fp32", "threads": args.threads,
            "crop": args.crop, "torch": torch.__version__, "commit": h["commit"], "rows": [], "loader": None,
            "load_average": list(os.getloadavg())}
    plan = [(int(w), int(b), False) for w in args.widths.split(",") for b in args.batches.split(",")]
    compiled = [(int(w), int(b)) for w, b in (c.split("x") for c in args.compiled.split(",") if c)]
    plan += [(w, b, False) for w, b in compiled if (w, b, False) not in plan]  # each compiled row's eager twin
    plan += [(w, b, True) for w, b in compiled]
    for w, b, compiled in plan:
        step = step_fn(w, b, args.crop, device, bf16, compiled)
        t0 = time.perf_counter()
        step()  # compiles, if compiled
        _sync(device)
        first = time.perf_counter() - t0
        sec = time_steps(step, device, args.warmup, args.steps)
        info["rows"].append({"width": w, "batch": b, "compiled": compiled, "ms_per_step": sec * 1000,
                             "crops_per_s": b / sec, "ops_per_step": count_ops(step), "first_step_s": first})
        print(info["rows"][-1], flush=True)
        write(info, args)
    if args.data:
        info["loader"] = loader_costs(args.data, int(args.batches.split(",")[-1]), args.crop, device)
    info["load_average_end"] = list(os.getloadavg())
    write(info, args)


if __name__ == "__main__":
    main()
