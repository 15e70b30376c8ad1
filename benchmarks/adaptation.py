"""Per-rig adaptation (the paper's digital-twin workflow) on test scenes: zero-shot vs fine-tuned.

    nice -n 10 .venv/bin/python benchmarks/adaptation.py --family side          # one scene, ~35 CPU min
    nice -n 10 .venv/bin/python benchmarks/adaptation.py --family radial-wide
    .venv/bin/python benchmarks/adaptation.py --report                           # writes the report

Per family, its first test scene (:func:`gearscan.twin.families.family_scenes`): the twin renders
an **adaptation dataset** of that scene's rig and gear (what ``gearscan twin dataset --rig`` does
for a user: ``purpose: adaptation``), with a non-test seed and start angles on a grid the test
bursts' random angles do not hit (both enforced below). Its start points are split into train and
val (val: every ``--val-every``-th start point, never the test bursts). The shipped model (or ``--init``) is
fine-tuned on it under a CPU budget of this process (``time.process_time()``: robust to other
load on the shared cores), keeping the best-on-val weights. With the constant learning rate (``--schedule
constant``) the weights that were best on val at 5, 10 and 20 CPU minutes are saved on the way (a 10-minute
budget run stops on the same trajectory); with ``--schedule cosine-time`` (annealed to 0 over the budget) or
``--average-from`` (the last epochs' weights averaged) a run's own budget is its only mark, and a shorter budget is
another run (``--budget 10 --tag=-cosine10``). Each checkpoint is then scored on the
scene's **test** bursts (test seed, rendered on the fly: the paper's three motions both ways and
still bursts, ``--reps`` bursts each) against three-step PS, as ``benchmarks/generalization.py``
scores them. Writes ``runs/adaptation/<family>[-span<deg>]/result.json``; ``--report`` gathers them into
``benchmarks/adaptation_report.{md,json,png}``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Subset

from gearscan.core.phase import phase_error
from gearscan.evaluate import Scene, classical_method, network_method, render_cases
from gearscan.generalization import MOVING, STILL, rig_orientation, scene_motions
from gearscan.inference.losses import LossConfig
from gearscan.inference.model_io import read_config
from gearscan.inference.models import ModelConfig
from gearscan.inference.predictor import DEFAULT_MODEL, Predictor, resolve_precision
from gearscan.inference.train import TrainConfig, TrainResult, train
from gearscan.provenance import code_edits
from gearscan.twin.dataset import DatasetSpec, TwinBurstDataset, generate_dataset
from gearscan.twin.families import family_scenes
from gearscan.twin.splits import SPLITS, describe, refuse_test

HERE = Path(__file__).parent
REPO = HERE.parent
RUNS = REPO / "runs" / "adaptation"
GEN_RIG = "CD-DCU-Net, rig orientation from a still burst"  # generalization_report.json's column scored as here
TARGET_RAD = 0.035  # issue 13: fine-tuned 30 CPU min on the target rig, moving bursts


def host() -> dict[str, object]:
    """CPU model, the AVX-512/bf16/AMX flags, cores and load."""
    cpu, flags = platform.processor() or "unknown", set()
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name") and cpu in ("unknown", "x86_64", ""):
            cpu = line.split(":", 1)[1].strip()
        elif line.startswith("flags"):
            flags = set(line.split(":", 1)[1].split())
    return {"cpu": cpu, "cores": os.cpu_count(), "avx512f": "avx512f" in flags,
            "avx512_bf16": "avx512_bf16" in flags, "amx_bf16": "amx_bf16" in flags,
            "loadavg_start": os.getloadavg()}


def file_sha256(path: Path) -> str:
    """Which weights a run fine-tuned (the shipped default changes between sessions)."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True).stdout.strip()


def pose_angles(spec: DatasetSpec, starts: list[float]) -> np.ndarray:
    """Every rendered pose angle (deg) of an adaptation dataset."""
    return np.array([s + p * spec.pose_step_deg for s in starts for p in range(spec.poses)])


def angle_gap_deg(a: np.ndarray, b: np.ndarray, pitch: float) -> float:
    """Smallest distance (deg, modulo one tooth pitch) between any angle of ``a`` and of ``b``."""
    d = np.abs(np.remainder(a[:, None] - b[None, :] + pitch / 2, pitch) - pitch / 2)
    return float(d.min())


def score(predictor: Predictor | None, cases, motions) -> dict[str, float]:
    """Pooled RMSE (rad) over the truth masks of the moving and of the still bursts."""
    method = classical_method if predictor is None else network_method(predictor)
    sums = {MOVING: [0.0, 0], STILL: [0.0, 0]}
    for motion, case in zip(motions, cases, strict=True):
        res = method(case.frames, case.full_scale, case.angles_rad)
        err = phase_error(res.phase, case.truth.phase)[case.truth.mask].astype(np.float64)
        s = sums[motion.kind]
        s[0] += float(np.sum(err**2))
        s[1] += err.size
    return {k: math.sqrt(v[0] / v[1]) for k, v in sums.items()}


def shorter_runs_on_the_way(args) -> bool:
    """Whether a run's best-on-val weights at a mark are what a run of that budget keeps: only at a constant rate
    and without a weight average (an annealed or averaging run's mark is the middle of its own schedule)."""
    return args.schedule == "constant" and args.average_from is None


def run_family(args) -> None:
    torch.set_num_threads(args.threads)
    machine = host()
    scene = family_scenes(args.family, args.scene + 1)[args.scene]
    init = args.init.resolve()
    start = "" if init == DEFAULT_MODEL.resolve() else f"-from-{init.stem}"  # another start than the shipped default
    out = args.runs / ((args.family if args.min_span_deg is None else f"{args.family}-span{args.min_span_deg:g}") + start
                       + args.tag)
    gear, pitch = scene.gear, 360.0 / scene.gear.teeth
    w, h = scene.rig.camera.width, scene.rig.camera.height
    # adaptation data: the scene's rig and gear, a non-test seed, start points on a grid within one pitch
    spec = DatasetSpec(gears=[gear], width=w, height=h, period_px=scene.period_px, seed=args.seed,
                       start_step_deg=pitch / args.start_points, max_start_points=args.start_points)
    refuse_test(seed=spec.seed, what="adaptation data of the benchmark")
    starts = [k * spec.start_step_deg for k in range(args.start_points)]
    data = out / "data"
    t0 = time.perf_counter()
    generate_dataset(data, spec, scene=(scene.rig, scene.optics, gear, scene.period_px), purpose="adaptation")
    render_s = None if args.score_only else time.perf_counter() - t0  # a resumed render says nothing
    # test bursts: the scene's test seed, rendered on the fly (never stored)
    rng = np.random.default_rng([scene.seed, 1])
    base = scene_motions(rng, sweeps=0, stills=2)
    motions = [m for m in base for _ in range(args.reps)]  # render_cases' order: per motion, reps bursts
    sc = Scene(scene.name, scene.rig, scene.optics, scene.gear, scene.period_px, _renderer=scene.renderer)
    cases = render_cases(sc, {m.name: m.steps_deg for m in base}, args.reps, seed=scene.seed)
    test_angles = np.array([a for c in cases for a in c.angles_deg])
    gap = angle_gap_deg(test_angles, pose_angles(spec, starts), pitch)
    if gap < 1e-4:  # the same angle: a test frame's pose would be in the adaptation data (noise aside)
        raise SystemExit(f"a test burst angle lies on an adaptation pose (gap {gap:.2g} deg): change --start-points")
    val_groups = [k for k in range(args.start_points) if k % args.val_every == args.val_every - 1]
    train_groups = [k for k in range(args.start_points) if k not in val_groups]
    # the user's speed (optional): only bursts spanning at least --min-span-deg, as the turntable turns in use
    min_span = None if args.min_span_deg is None else math.ceil(args.min_span_deg / spec.pose_step_deg - 1e-9)
    train_set = TwinBurstDataset(data, groups=train_groups, static=True, static_repeat=20, reverse=True,
                                 crop=args.crop, seed=0, min_span=min_span)
    val_full = TwinBurstDataset(data, groups=val_groups, static=True, reverse=True, min_span=min_span)
    pick = np.random.default_rng(0).choice(len(val_full), args.val_items, replace=False)
    val_set = Subset(val_full, sorted(pick.tolist()))
    meta = read_config(init)
    budget = args.budget
    marks = tuple(m for m in args.marks if m < budget) if shorter_runs_on_the_way(args) else ()
    run = out / "run"
    if run.exists() and not args.resume and not args.score_only:
        shutil.rmtree(run)
    config = TrainConfig(
        out_dir=str(run), model=ModelConfig.from_json(meta["model"]), loss=LossConfig(**meta["training"]["loss"]),
        epochs_deterministic=1_000_000, epochs_dropout=0, batch_size=args.batch, lr=args.lr, schedule=args.schedule,
        patience=1_000_000, steps_per_epoch=args.steps_per_epoch, init=str(init), progress=False,
        calibrate=True, calibrate_mc=0, budget_cpu_min=budget, checkpoints_cpu_min=marks, seed=0,
        resume=args.resume, precision=args.precision, compile=args.compile, average_from=args.average_from,
    )
    t0 = time.perf_counter()
    if args.score_only:  # a finished run (e.g. one whose scoring failed): read what it wrote
        best = read_config(run / "best.safetensors")
        history = json.loads((run / "metrics.json").read_text())
        result = TrainResult(run / "best.safetensors", history, math.nan, best["var_scale"], math.nan,
                             60.0 * best["train_cpu_min"], best["budget_hit"])
        train_wall = float(sum(h["seconds"] for h in history))
    else:
        result = train(config, train_set, val_set)
        train_wall = time.perf_counter() - t0
    # score every checkpoint on the test bursts
    points = [("0", init, 0.0)]
    for m in marks:
        p = run / f"cpu_{m:g}min.safetensors"
        if p.is_file():
            points.append((f"{m:g}", p, float(read_config(p)["cpu_min"])))
    points.append((f"{budget:g}", run / "best.safetensors", result.cpu_seconds / 60.0))
    baseline = score(None, cases, motions)
    # the fringe orientation as the user sets it for the rig (from a still burst), or the per-burst vote
    orientation = rig_orientation(motions, cases) if args.orientation == "rig" else "auto"
    curve = []
    for label, path, cpu_min in points:
        net = score(Predictor.load(path, orientation=orientation, still_burst_rad=0.0), cases, motions)
        curve.append({"mark_cpu_min": float(label), "cpu_min": cpu_min, "weights": str(path.relative_to(REPO) if path.is_relative_to(REPO) else path),
                      "rmse": net, "ratio_to_three_step": {k: net[k] / baseline[k] for k in net}})
        print(f"{args.family} {label:>3} CPU min (at {cpu_min:.1f}): moving {net[MOVING]:.4f} still {net[STILL]:.4f} "
              f"rad (three-step {baseline[MOVING]:.4f} / {baseline[STILL]:.4f})", flush=True)
    machine["loadavg_end"] = os.getloadavg()
    # how the weights were trained: this call's settings, or a rescored run's own (its best.json)
    trained = read_config(run / "best.safetensors")["training"] if args.score_only else config.to_json()
    # a rescore keeps the commit its weights were trained at
    before = json.loads((out / "result.json").read_text()) if args.score_only and (out / "result.json").is_file() else {}
    trained_at = before.get("training_commit", before.get("commit")) if args.score_only else None
    res = {
        "family": args.family, "scene_seed": scene.seed, "params": dict(scene.params),
        "scene": scene.name + ("" if args.min_span_deg is None else f", adapted on spans >= {args.min_span_deg:g} deg")
        + ("" if not start else f", from {init.stem}"),
        "period_px": scene.period_px, "resolution": f"{w}x{h}", "commit": git("rev-parse", "--short", "HEAD"),
        "training_commit": trained_at or git("rev-parse", "--short", "HEAD"),
        "working_tree_dirty": bool(code_edits(REPO)), "host": machine,
        "torch_threads": args.threads, "precision": Predictor.load(init).precision,
        "orientation": {"mode": args.orientation, "set": orientation},
        "model": {"path": str(init.relative_to(REPO) if init.is_relative_to(REPO) else init),
                  "sha256": file_sha256(init)[:12]},
        "adaptation": {"seed": spec.seed, "seed_split": "train" if SPLITS["train"].has_seed(spec.seed) else "val",
                       "start_points": args.start_points, "min_span_deg": args.min_span_deg,
                       "moving_train_bursts_per_start_point": sum(1 for c in train_set.combos if c[0] != c[2]),
                       "still_share": sum(1 for c in train_set.combos if c[0] == c[2]) / len(train_set.combos), "start_step_deg": spec.start_step_deg,
                       "poses": spec.poses, "pose_step_deg": spec.pose_step_deg, "steps": spec.steps,
                       "train_start_points": train_groups, "val_start_points": val_groups,
                       "train_items": len(train_set), "val_items": len(val_set), "render_s": render_s,
                       "min_gap_to_test_angles_deg": gap},
        "training": {"budget_cpu_min": budget, "marks": list(trained.get("checkpoints_cpu_min", marks)), "lr": trained["lr"], "schedule": trained["schedule"],
                     "batch": args.batch, "crop": args.crop, "steps_per_epoch": args.steps_per_epoch,
                     "average_from": trained.get("average_from"),
                     "cpu_min": result.cpu_seconds / 60.0, "wall_s": train_wall, "precision": trained["precision"], "budget_hit": result.budget_hit,
                     "autocast": resolve_precision(trained["precision"], torch.device("cpu"), training=True),  # what "auto" chose
                     "compile": trained.get("compile", False),
                     "steps": int(sum(r.get("steps", 0) for r in result.history)),
                     "history": [{k: r[k] for k in ("epoch", "cpu_min", "val_rmse", "val_loss", "steps")}
                                 for r in result.history]},
        "test": {"bursts": len(cases), "moving": sum(m.kind == MOVING for m in motions),
                 "still": sum(m.kind == STILL for m in motions), "reps": args.reps,
                 "motions": sorted({m.name for m in motions})},
        "three_step": baseline, "curve": curve,
    }
    (out / "result.json").write_text(json.dumps(res, indent=1, default=str))
    print(f"wrote {out / 'result.json'}")


def _f(v: float) -> str:
    return f"{v:.4f}"


def power_fit(curve: list[dict], kind: str = MOVING) -> tuple[float, float] | None:
    """``rmse = a * cpu_min**b`` fitted (log-log least squares) to the fine-tuned points (cpu_min > 0)."""
    pts = [(c["cpu_min"], c["rmse"][kind]) for c in curve if c["cpu_min"] > 0 and c["mark_cpu_min"] > 0]
    if len(pts) < 2:
        return None
    x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    b, log_a = np.polyfit(x, y, 1)
    return float(math.exp(log_a)), float(b)


def steps_at(r: dict, cpu_min: float) -> int:
    """Training steps taken by the time the run had used ``cpu_min`` CPU minutes."""
    return int(sum(h["steps"] for h in r["training"]["history"] if h["cpu_min"] <= cpu_min + 1e-9))


def label_floor(data: Path, groups: list[int]) -> float | None:
    """RMSE (rad) of the 18-step PS training label against the analytic phase on the val start points:
    what a network trained on these labels is taught, so roughly the floor fine-tuning can reach."""
    index = json.loads((data / "index.json").read_text()) if (data / "index.json").is_file() else None
    if index is None:
        return None
    se = n = 0.0
    for g in groups:
        d = data / index["entries"][g]["id"]
        lab, ph, m = (np.load(d / f"{k}.npy", mmap_mode="r") for k in ("label", "phase", "mask"))
        for p in range(0, lab.shape[0], 3):
            e = phase_error(np.arctan2(lab[p, 0], lab[p, 1]), ph[p])[m[p]].astype(np.float64)
            se, n = se + float(np.sum(e**2)), n + e.size
    return math.sqrt(se / n) if n else None


def _extrapolation(r: dict) -> str:
    fit = power_fit(r["curve"])
    if fit is None:
        return (f"- {r['scene']}: one budget ({r['training']['budget_cpu_min']:g} CPU min), no curve: a point at another "
                "budget is a run of its own, and none was made.")
    a, b = fit
    cpu = r["training"]["cpu_min"]
    step_cpu_s = 60.0 * cpu / max(r["training"]["steps"], 1)
    floors = (f" Floors on this scene: the 18-step training label is {r['label_floor']:.4f} rad from the truth "
              f"(val start points), three-step PS on still bursts {r['three_step'][STILL]:.4f} rad."
              if r.get("label_floor") else "")
    if b >= -1e-6:  # flat (every mark kept the same weights: b is 0 up to rounding) or rising
        return (f"- {r['scene']}: rmse = {a:.3f} t^{b:.3f}: no longer falling with CPU time; more of the same will "
                f"not reach it.{floors}")
    log_need = math.log(TARGET_RAD / a) / b  # in logs: a nearly flat curve needs more minutes than a float holds
    verdict = ("out of reach of more CPU time with this network and data" if log_need > math.log(100 * cpu)
               else "if the trend held")
    if log_need > math.log(1e9):
        return f"- {r['scene']}: rmse = {a:.3f} t^{b:.3f}; {TARGET_RAD} rad beyond 1e9 CPU min: {verdict}.{floors}"
    need = math.exp(log_need)
    return (f"- {r['scene']}: rmse = {a:.3f} t^{b:.3f}; {TARGET_RAD} rad at about {need:.3g} CPU min "
            f"(~{need * 60 / step_cpu_s:.3g} steps of batch {r['training']['batch']} at {step_cpu_s:.2f} CPU s per step "
            f"on this host, {r['training'].get('autocast', r['training']['precision'])}): {verdict}.{floors}")


def budget_curves(results: list[dict]) -> list[dict]:
    """What to extrapolate: a constant-rate run's own marks, or, for runs annealed over their budgets
    (``cosine-time``) or averaging their last epochs, one curve through the budget-end points of the runs of one scene
    and recipe (each point is what that budget gives; a run's other points would be the middle of its schedule, so it
    is never fitted alone)."""
    curves = [r for r in results
              if r["training"].get("schedule", "constant") == "constant" and r["training"].get("average_from") is None]
    groups: dict[tuple, list[dict]] = {}
    for r in results:
        if r["training"].get("schedule") == "cosine-time" or r["training"].get("average_from") is not None:
            t, a = r["training"], r["adaptation"]
            key = (r["family"], r["scene_seed"], a.get("min_span_deg"), r.get("model", {}).get("sha256"), a["seed"],
                   a["start_points"], *(t.get(k) for k in ("schedule", "average_from", "lr", "batch", "crop",
                                                          "steps_per_epoch", "autocast", "compile")))
            groups.setdefault(key, []).append(r)
    for runs in groups.values():
        runs = sorted(runs, key=lambda r: r["training"]["budget_cpu_min"])
        last = runs[-1]
        how = "annealed" if last["training"].get("schedule") == "cosine-time" else "averaged"
        curves.append({**last, "scene": f"{last['scene'].split(' [')[0]} [{how}: {', '.join(r['run'] for r in runs)}]",
                       "curve": [last["curve"][0]] + [r["curve"][-1] for r in runs]})
    return curves


def training_mode(results: list[dict]) -> str:
    """How the runs trained: autocast and compiled steps, per run where they differ."""
    def mode(r: dict) -> str:
        t = r["training"]
        cast = t.get("autocast", t["precision"])
        why = (" (the AMD host's choice in session 21: 1.2 CPU s per w8 step in fp32, 1.7 in bf16 without AMX)"
               if t["precision"] == "fp32" else f" (`--precision {t['precision']}`)")
        sched = ("learning rate **annealed to 0 over the budget** (`--schedule cosine-time`)"
                 if t.get("schedule") == "cosine-time" else "constant learning rate")
        avg = (f", the weights of every epoch from {t['average_from']:g} of the budget on averaged (`--average-from`; "
               "the average kept only if better on val)" if t.get("average_from") is not None else "")
        return (f"autocast **{cast}**{why}, {'**compiled** steps (`--compile`)' if t.get('compile') else 'eager steps'}, "
                f"{sched} {t['lr']:g}{avg}")

    modes = {r["run"]: mode(r) for r in results}
    if len(set(modes.values())) == 1:
        return next(iter(modes.values()))
    return "; ".join(f"{run}: {m}" for run, m in modes.items())


def write_report(prefix: Path, runs: Path = RUNS) -> None:
    paths = sorted(runs.glob("*/result.json"))
    results = [json.loads(p.read_text()) for p in paths]
    if not results:
        raise SystemExit(f"no results under {runs}: run with --family first")
    for p, r in zip(paths, results, strict=True):
        r["run"] = p.parent.name  # the family, or family-spanX: two runs of one family stay apart
        r["label_floor"] = label_floor(p.parent / "data", r["adaptation"]["val_start_points"])
    scenes = [r["scene"] for r in results]
    for r in results:  # runs of one scene that differ only in how they trained (--tag) are told apart by folder
        if scenes.count(r["scene"]) > 1:
            r["scene"] += f" [{r['run']}]"
    gen = json.loads((HERE / "generalization_report.json").read_text())
    fam_zero = {(c["family"], c["group"]): c for c in gen["cells"]}
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # left: the test bursts at each scored point (moving solid, still dashed); right: val per epoch; one colour per run
    fig, (ax, av) = plt.subplots(1, 2, figsize=(11.0, 5.4), dpi=100, sharey=True)
    for k, r in enumerate(results):
        xs = [c["cpu_min"] for c in r["curve"]]
        col = f"C{k % 10}"
        mark = "os^vD"[k // 10 % 5]
        ax.plot(xs, [c["rmse"][MOVING] for c in r["curve"]], "-" + mark, color=col, label=r["scene"])
        ax.plot(xs, [c["rmse"][STILL] for c in r["curve"]], "--" + mark, color=col, ms=3, lw=0.8)
        hist = [x for x in r["training"]["history"] if math.isfinite(x["val_rmse"])]
        av.plot([x["cpu_min"] for x in hist], [x["val_rmse"] for x in hist], color=col, lw=0.6, alpha=0.7)
    for scene_ts in {round(r["three_step"][MOVING], 6) for r in results}:
        ax.axhline(scene_ts, color="0.5", lw=0.6, ls=":")
    for a in (ax, av):
        a.axhline(TARGET_RAD, color="k", lw=1, ls="-.")
        a.set_yscale("log")
        a.set_xlabel("fine-tuning, CPU minutes of the training process")
    ax.set_ylabel("RMSE (rad)")
    ax.set_title("test bursts: moving (solid), still (dashed); dotted: three-step moving; dash-dot: target",
                 fontsize=8)
    av.set_title("val RMSE per epoch (the adaptation data's val start points; it chose the weights)", fontsize=8)
    fig.legend(*ax.get_legend_handles_labels(), loc="lower center", ncol=2, fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0.03 + 0.026 * math.ceil(len(results) / 2), 1, 1))  # room for the legend's rows
    png = prefix.with_suffix(".png")
    fig.savefig(png)
    plt.close(fig)

    r0 = results[0]
    h = r0["host"]
    lines = [
        "# Per-rig adaptation on test scenes: zero-shot vs 10 and 30 CPU minutes of fine-tuning",
        "",
        "`nice -n 10 python benchmarks/adaptation.py --family F` per family, then `--report`; "
        + "; ".join(f"{r['run']}: commit `{r['commit']}`{' (uncommitted edits in the tree)' if r['working_tree_dirty'] else ''}"
                    + (f", fine-tuned at `{r['training_commit']}` and rescored (`--score-only`)"
                       if r.get("training_commit", r["commit"]) != r["commit"] else "")
                    for r in results) + ".",
        "",
        f"- **Host**: {h['cpu']}, {h['cores']} cores shared with other work, AVX-512 {'yes' if h['avx512f'] else 'no'}, "
        f"AVX512-BF16 {'yes' if h['avx512_bf16'] else 'no'}, AMX-BF16 {'yes' if h['amx_bf16'] else 'no'}; load average "
        + "; ".join(f"{r['run']} {r['host']['loadavg_start'][0]:.1f} at start, {r['host']['loadavg_end'][0]:.1f} at the end"
                    for r in results)
        + f"; {r0['torch_threads']} torch threads. Training: {training_mode(results)}; the test "
        f"scoring in **{r0['precision']}**, the Predictor's automatic choice, as in `generalization_report.md`.",
        "- **Model** fine-tuned and scored at 0 minutes: "
        + "; ".join(f"{r['run']}: `{r['model']['path']}` sha256 `{r['model']['sha256']}`" if "model" in r
                    else f"{r['run']}: not recorded" for r in results)
        + " (the shipped default when the run was made, unless the scene says `from` another; `--init`).",
        "- **Fringe orientation** in the test scoring: "
        + "; ".join(f"{r['run']}: " + (f"set once for the rig, `{r['orientation']['set']}` (the vote on the scene's "
                                       "first still test burst, as a user sets it per rig)"
                                       if r.get("orientation", {}).get("mode") == "rig"
                                       else "the Predictor's per-burst vote (`auto`)") for r in results) + ".",
        "- **CPU minutes** are `time.process_time()` of the training process (all its threads; since session 36 plus "
        "the child processes it waited for, such as a compiled run's C++ compiler), counted from the "
        "start of fine-tuning: validation and a compiled run's compiling included, rendering and the closing sigma "
        "calibration not. Other load on "
        "the shared cores does not eat the budget directly, but it is not neutral either: the same step (w8, batch 8, "
        "128^2 crops) cost "
        + ", ".join(f"{60 * r['training']['cpu_min'] / max(r['training']['steps'], 1):.2f} CPU s in the {r['run']} run"
                    for r in results)
        + " (load averages under Host; torch's threads burn CPU time waiting for a descheduled peer), so a busy host "
        "buys fewer steps per CPU minute. Wall time is stated per run.",
        "- **What chose what**: the adaptation data's own held-out start points (val) chose the weights at every "
        "mark (best-on-val so far, the shipped weights included: the 0-minute row); nothing was chosen on the test "
        "bursts. Learning rate, batch, crop and the mix (static bursts x20, both rotation senses) are the shipped "
        "CPU recipe's (`scripts/train_default.py`: batch 8, 128^2 crops), set before any run. With a constant learning "
        "rate the 10-minute mark is where a `--budget-cpu-min 10` run stops; a run annealed over its budget or averaging "
        "its last epochs (under Host) has its budget as its only mark, and a shorter budget is a run of its own.",
        f"- **Split**: the scenes are the first scene of each test family run (`twin/families.py`, test seeds: the "
        "product's default rig with a test gear, or a rig never trained on; "
        f"test split: {describe('test')}). The adaptation data are the user's workflow on that rig and gear: "
        "`purpose: adaptation` (a test tooth count is the user's gear, allowed there), a **non-test seed** and start "
        "angles on a grid that the test bursts' random angles miss (the smallest gap, modulo a pitch, is stated; "
        "enforced > 1e-4 deg: no test frame at an adaptation pose): the test bursts (test seed, noise and angles) are never rendered into it.",
        "- **Test bursts**: per scene the paper's motions (uniform 0.6/0.6, non-uniform 0.1/1.6 and 0.5/1.0 deg) "
        "both ways and still bursts, each several times (`reps`), rendered on the fly from the scene's test seed; RMSE "
        "over the truth masks against the analytic phase at the first frame (as `benchmarks/generalization.py`).",
        "",
        "## Zero-shot vs fine-tuned (test bursts)",
        "",
        "| scene | CPU min (mark / actual) | steps | moving RMSE (rad) | still RMSE (rad) | moving / three-step | still / three-step | val RMSE of the kept weights (chosen by val loss) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        hist = r["training"]["history"]
        for c in r["curve"]:
            val = min((x for x in hist if x["cpu_min"] <= c["cpu_min"] + 1e-9), key=lambda x: x["val_loss"], default=None)
            lines.append(
                f"| {r['scene']} | {c['mark_cpu_min']:g} / {c['cpu_min']:.1f} | {steps_at(r, c['cpu_min'])} | {_f(c['rmse'][MOVING])} | "
                f"{_f(c['rmse'][STILL])} | {c['ratio_to_three_step'][MOVING]:.2f}x | {c['ratio_to_three_step'][STILL]:.2f}x | "
                f"{_f(val['val_rmse']) if val else ''} |")
        lines.append(f"| {r['scene']} | three-step PS | | {_f(r['three_step'][MOVING])} | {_f(r['three_step'][STILL])} | 1 | 1 | |")
    lines += ["", f"Figure: `{png.name}` (test RMSE vs CPU minutes; the dashed-dotted line is the {TARGET_RAD} rad target).", ""]
    met = [r for r in results if r["curve"][-1]["rmse"][MOVING] <= TARGET_RAD]
    lines += [
        "## The target: fine-tuned 30 CPU min on the target rig <= 0.035 rad",
        "",
        (f"Met on {', '.join(r['scene'] for r in met)}. " if met else "**Not met** on any scene. ")
        + "Moving bursts after the full budget: "
        + "; ".join(f"{r['scene']} {_f(r['curve'][-1]['rmse'][MOVING])} rad (zero-shot {_f(r['curve'][0]['rmse'][MOVING])})"
                    for r in results) + ".",
        "",
        "What would meet it, read off the curve (a power law `rmse = a * (CPU min)^b` fitted to the fine-tuned "
        "moving-burst points: a constant-rate run's marks, or the budget ends of the runs that anneal or average over their "
        "budgets; an extrapolation, not a measurement):",
        "",
        *[_extrapolation(r) for r in budget_curves(results)],
        "",
        "## Runs",
        "",
        "| scene | resolution | projector period (px) | adaptation data | train / val items | render (s) | steps | CPU min | wall (min) | budget hit | min angle gap to test (deg) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        a, t = r["adaptation"], r["training"]
        lines.append(
            f"| {r['scene']} | {r['resolution']} | {r['period_px']:.1f} | seed {a['seed']} ({a['seed_split']} split), "
            f"{a['start_points']} start points {a['start_step_deg']:.3f} deg apart x {a['poses']} poses x {a['steps']} steps, "
            f"val start points {a['val_start_points']} | {a['train_items']} / {a['val_items']} | "
            f"{'n/a' if a['render_s'] is None else format(a['render_s'], '.0f')} | "
            f"{t['steps']} x batch {t['batch']} crop {t['crop']} | {t['cpu_min']:.1f} | {t['wall_s'] / 60:.1f} | "
            f"{'yes' if t['budget_hit'] else 'no'} | {a['min_gap_to_test_angles_deg']:.4f} |")
    lines += ["", "Zero-shot numbers of the whole family (16 scenes, `generalization_report.md`, same model, the fringe "
              "orientation set for the rig as here) for scale:", "",
              "| family | moving net / three-step (rad) | still net / three-step (rad) |", "|---|---|---|"]
    for fam in dict.fromkeys(r["family"] for r in results):
        mv, st = fam_zero.get((fam, MOVING)), fam_zero.get((fam, STILL))
        if mv and st:
            lines.append(f"| {fam} | {mv['rmse'][GEN_RIG]:.4f} / {mv['rmse']['three-step PS']:.4f} | "
                         f"{st['rmse'][GEN_RIG]:.4f} / {st['rmse']['three-step PS']:.4f} |")
    lines += ["", "Scene parameters:", ""]
    lines += [f"- {r['scene']}: " + ", ".join(f"{k} {v}" for k, v in r["params"].items()) for r in results]
    prefix.with_suffix(".md").write_text("\n".join(lines) + "\n")
    prefix.with_suffix(".json").write_text(json.dumps({"target_rad": TARGET_RAD, "results": results}, indent=1))
    print("\n".join(lines))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--family", help="test family to adapt to (default, radial-wide, side, oblique, face)")
    ap.add_argument("--scene", type=int, default=0, help="which scene of the family (0: the first)")
    ap.add_argument("--budget", type=float, default=30.0, help="CPU minutes of fine-tuning")
    ap.add_argument("--init", type=Path, default=DEFAULT_MODEL,
                    help="the weights fine-tuned and scored at 0 minutes (default: the shipped default; "
                         "e.g. inference/weights/default_rig.safetensors, the default-rig option)")
    ap.add_argument("--marks", type=lambda s: [float(v) for v in s.split(",")], default=None,
                    help="CPU minutes at which the best-on-val weights so far are scored too (constant schedule "
                         "only; default 5,10,20)")
    ap.add_argument("--schedule", choices=("constant", "cosine-time"), default="constant",
                    help="learning rate: constant (the marks are shorter budgets' results) or cosine-time (annealed "
                         "to 0 over --budget: a shorter budget is a run of its own)")
    ap.add_argument("--average-from", type=float, default=None,
                    help="average every epoch's weights from this share of the budget on (TrainConfig.average_from; "
                         "the average kept only if better on val); marks are then runs of their own")
    ap.add_argument("--start-points", type=int, default=10)
    ap.add_argument("--val-every", type=int, default=5, help="every N-th start point is val")
    ap.add_argument("--val-items", type=int, default=32)
    ap.add_argument("--seed", type=int, default=1, help="adaptation data seed (train or val split; never test)")
    ap.add_argument("--reps", type=int, default=3, help="test bursts per motion")
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--steps-per-epoch", type=int, default=40)
    ap.add_argument("--min-span-deg", type=float, default=None,
                    help="adaptation bursts spanning at least this (frame 1 to 3): the user's turntable speed; "
                         "default: every span the poses give (0.2-1.7 deg)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--precision", default="auto", choices=["auto", "fp32", "bf16"],
                    help="training autocast; auto: bf16 on a CPU with AMX, else fp32 (reports before session 36 ran "
                         "fp32 on an AVX512-BF16 host without AMX; benchmarks/adaptation_precision_rule.md)")
    ap.add_argument("--compile", action="store_true",
                    help="torch.compile the training steps (TrainConfig.compile; the compile counts in the budget)")
    ap.add_argument("--tag", default="", help="appended to the run's folder name (spelled --tag=-compiled: a value starting with '-')")
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--score-only", action="store_true", help="score a finished run's checkpoints (no training)")
    ap.add_argument("--orientation", choices=("rig", "auto"), default="rig",
                    help="scoring: rig = set once from the scene's first still test burst, as a user sets it per rig; "
                         "auto = the Predictor's per-burst vote (reports before session 26)")
    ap.add_argument("--report", action="store_true", help="gather runs/adaptation/*/result.json into the report")
    ap.add_argument("--out", type=Path, default=HERE / "adaptation_report")
    ap.add_argument("--runs", type=Path, default=RUNS, help="folder of the per-family runs (data, weights, result.json)")
    args = ap.parse_args()
    if args.marks is not None and not shorter_runs_on_the_way(args):
        ap.error("--marks: only with --schedule constant and no --average-from (such a run's mark is not what a "
                 "shorter budget gives)")
    if args.marks is None:
        args.marks = [5.0, 10.0, 20.0]
    if args.min_span_deg is not None and not args.min_span_deg > 0:
        ap.error(f"--min-span-deg: expected > 0 degrees, got {args.min_span_deg}")
    if not args.init.is_file():
        ap.error(f"--init {args.init}: no such weights file (expected a .safetensors with its .json)")
    if args.report:
        write_report(args.out, args.runs)
    elif args.family:
        run_family(args)
    else:
        ap.error("give --family or --report")


if __name__ == "__main__":
    main()
