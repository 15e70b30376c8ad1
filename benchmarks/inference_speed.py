"""CPU inference time of the shipped CD-DCU-Net per burst: deterministic and Monte Carlo (T passes).

Measures ``Predictor.load()`` (inference/weights/default.safetensors, precision chosen by the CPU)
through ``Predictor.predict`` (uint8 frames in, PhaseResult out), on synthetic fringe frames:

- deterministic pass, per image size;
- MC T=20 before/after: "plain" runs the whole network once per pass on ``x.repeat(chunk)``
  in chunks of 2 (the previous default); "reuse" computes the deterministic prefix (classical
  M, D, padding, stem) once per burst, the first dropout layer's passes as one convolution, and
  chunks by image size (``auto_mc_chunk``);
- at the first size: the reuse path by chunk size, fp32 beside the chosen precision, and where
  the time goes (one profiled MC run: share of op time by feature-map resolution, and the
  per-pass multiply-accumulates by resolution), so the report can say what bounds it.

Writes ``inference_speed.md`` and ``inference_speed.json`` beside this script.

    .venv/bin/python benchmarks/inference_speed.py [--sizes 512 800 1232x1360] [--threads 2] [--mc 20]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import time
from functools import partial
from pathlib import Path

import numpy as np
import torch

from gearscan.inference import predictor as predictor_module
from gearscan.inference.predictor import Predictor, auto_mc_chunk
from gearscan.inference.uncertainty import mc_moments

HERE = Path(__file__).resolve().parent
REPO = HERE.parent


def host_info(threads: int) -> dict:
    flags = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").is_file() else ""
    model = next(
        (ln.split(":", 1)[1].strip() for ln in flags.splitlines() if ln.startswith("model name")),
        "",
    )

    def git(*args: str) -> str:
        try:
            return subprocess.run(
                ["git", *args], cwd=REPO, capture_output=True, text=True, check=True
            ).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return ""

    dirty = git("status", "--porcelain", "--", "inference", "benchmarks/inference_speed.py")
    return {
        "cpu": model or platform.processor() or platform.machine(),
        "avx512_bf16": "avx512_bf16" in flags,
        "amx_bf16": "amx_bf16" in flags,
        "cores": os.cpu_count(),
        "threads": threads,
        "torch": torch.__version__,
        "commit": git("rev-parse", "--short", "HEAD")
        + (" + uncommitted inference changes" if dirty else ""),
    }


def fringe_frames(h: int, w: int) -> np.ndarray:
    """Three 8-bit phase-shifted frames, phase increasing along the columns (as the twin's)."""
    yy, xx = np.mgrid[0:h, 0:w]
    phase = 2 * np.pi * xx / 24 + 0.002 * yy
    return np.stack([128 + 90 * np.cos(phase + 2 * np.pi * n / 3) for n in range(3)]).astype(
        np.uint8
    )


def time_call(fn, repeats: int, warmup: int = 1) -> list[float]:
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return out


def parse_size(text: str) -> tuple[int, int]:
    h, _, w = text.partition("x")
    return int(h), int(w or h)


def mc_time(
    pred: Predictor,
    frames: np.ndarray,
    passes: int,
    repeats: int,
    *,
    plain: bool,
    chunk: int | None,
) -> list[float]:
    """Seconds per ``pred.predict(frames, mc=passes)`` with the plain or the prefix-reusing path."""
    saved_fn, saved_chunk = predictor_module.mc_moments, pred.mc_chunk
    predictor_module.mc_moments = partial(mc_moments, reuse_prefix=not plain)
    pred.mc_chunk = chunk
    try:
        return time_call(lambda: pred.predict(frames, mc=passes), repeats)
    finally:
        predictor_module.mc_moments, pred.mc_chunk = saved_fn, saved_chunk


def macs_by_resolution(model: torch.nn.Module, h: int, w: int) -> dict[str, float]:
    """Multiply-accumulates of one pass by output resolution (convs and transposed convs), and the stem's."""
    out: dict[str, float] = {}
    hooks = []

    def hook(mod, inp, res):
        if isinstance(mod, torch.nn.ConvTranspose2d):
            macs = inp[0].numel() * mod.weight.shape[1] * mod.weight.shape[2] * mod.weight.shape[3]
        else:
            macs = res.numel() * mod.weight[0].numel()
        key = f"{res.shape[-2]}x{res.shape[-1]}"
        out[key] = out.get(key, 0.0) + macs

    for m in model.modules():
        if isinstance(m, (torch.nn.Conv2d, torch.nn.ConvTranspose2d)):
            hooks.append(m.register_forward_hook(hook))
    with torch.no_grad():
        model(torch.rand(1, model.config.in_channels, h, w))
    for hk in hooks:
        hk.remove()
    stem = sum(
        m.weight[0].numel() * m.weight.shape[0] * h * w
        for m in model.encoder.stem.modules()
        if isinstance(m, torch.nn.Conv2d)
    )
    return {**out, "stem (once per burst)": float(stem)}


def time_by_resolution(pred: Predictor, frames: np.ndarray, passes: int) -> dict[str, float]:
    """Share of op self-time by the largest feature map an op reads (full resolution, 1/2, ...,
    1/16 of the rows), over one profiled MC run; "other": ops without a 4-D input."""
    from torch.profiler import ProfilerActivity, profile

    pred.predict(frames, mc=passes)
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        pred.predict(frames, mc=passes)
    shares: dict[str, float] = {}
    for ev in prof.key_averages(group_by_input_shape=True):
        shapes = [s for s in (ev.input_shapes or []) if isinstance(s, list) and len(s) == 4]
        rows = max((s[2] for s in shapes), default=0)
        ratio = round(frames.shape[1] / rows) if rows else 0
        key = (
            "other" if not 1 <= ratio <= 16 else ("full resolution" if ratio == 1 else f"1/{ratio}")
        )
        shares[key] = shares.get(key, 0.0) + ev.self_cpu_time_total
    total = sum(shares.values()) or 1.0
    return {k: v / total for k, v in sorted(shares.items(), key=lambda kv: -kv[1])}


def conv_throughput(precision: str, h: int, w: int) -> dict[str, float]:
    """GMAC/s of single 3x3 convs, channels_last, in ``precision``: the same work with 8 or 16 outputs."""
    import torch.nn.functional as F

    dt = torch.bfloat16 if precision == "bf16" else torch.float32
    cl = torch.channels_last
    cases = {
        f"8->8 at {h}x{w}, batch 2": (2, 8, 8, h, w),
        f"8->16 at {h}x{w}, batch 1": (1, 8, 16, h, w),
        f"8->4 at {h}x{w}, batch 2 (fp32: the head)": (2, 8, 4, h, w),
        f"32->32 at {h // 4}x{w // 4}, batch 2": (2, 32, 32, h // 4, w // 4),
    }
    out = {}
    with torch.inference_mode():
        for name, (b, cin, cout, hh, ww) in cases.items():
            d = torch.float32 if "fp32" in name else dt
            x = torch.randn(b, cin, hh, ww).to(d).contiguous(memory_format=cl)
            wt = torch.randn(cout, cin, 3, 3).to(d).contiguous(memory_format=cl)
            t = min(time_call(lambda x=x, wt=wt: F.conv2d(x, wt, padding=1), 5, warmup=2))
            out[name] = b * hh * ww * cin * cout * 9 / t / 1e9
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--sizes", nargs="+", default=["512", "800", "1232x1360"], help="HxW or N (square)"
    )
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--mc", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=5, help="deterministic repeats")
    ap.add_argument(
        "--mc-repeats", type=int, default=3, help="MC repeats at the first size (1 beyond 800x800)"
    )
    ap.add_argument("--chunks", type=int, nargs="*", default=[1, 2, 4, 5, 10, 20])
    ap.add_argument(
        "--render-only", action="store_true", help="rewrite the .md from the .json, measure nothing"
    )
    ap.add_argument(
        "--out", default="inference_speed",
        help="report name beside this script (.md, .json); hosts differ, so a second host gets its own",
    )
    args = ap.parse_args()
    md, js = HERE / f"{args.out}.md", HERE / f"{args.out}.json"
    if args.render_only:
        md.write_text(report(json.loads(js.read_text())))
        return
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    load_start = os.getloadavg()
    info = host_info(args.threads)
    # the network's own cost: these frames stand still, so the shipped still-burst gate would decode them
    # by three-step PS and skip the MC passes (measured apart below, "the still-burst gate's path")
    pred = Predictor.load(still_burst_rad=0.0)
    info["precision"] = pred.precision
    info["channels_last"] = pred.channels_last
    info["model"] = {
        k: pred.model.config.to_json()[k] for k in ("name", "width", "classical_input", "residual")
    }
    print(info, flush=True)
    rows, chunk_rows, extra = [], [], {}
    for i, text in enumerate(args.sizes):
        h, w = parse_size(text)
        frames = fringe_frames(h, w)
        big = h * w > 800 * 800
        reps = 1 if big else (args.mc_repeats if i == 0 else 2)
        det = time_call(lambda frames=frames: pred.predict(frames), 2 if big else args.repeats)
        row = {
            "size": f"{h}x{w}",
            "precision": pred.precision,
            "deterministic_s": min(det),
            "deterministic_s_median": statistics.median(det),
            "mc_chunk": auto_mc_chunk(h, w, args.mc),
        }
        if not big:
            before = mc_time(pred, frames, args.mc, reps, plain=True, chunk=2)
            row.update(mc_plain_s=min(before), mc_plain_s_median=statistics.median(before))
        after = mc_time(pred, frames, args.mc, reps, plain=False, chunk=None)
        row.update(mc_reuse_s=min(after), mc_reuse_s_median=statistics.median(after))
        rows.append(row)
        print(row, flush=True)
        if i == 0:
            for c in args.chunks:
                t = mc_time(pred, frames, args.mc, 2, plain=False, chunk=c)
                chunk_rows.append({"size": f"{h}x{w}", "chunk": c, "mc_reuse_s": min(t)})
                print(chunk_rows[-1], flush=True)
            shipped = Predictor.load()  # the shipped still-burst gate: takes these still frames
            taken = shipped.predict(frames, mc=args.mc).mode == "three-step"
            g_det = time_call(partial(shipped.predict, frames), args.repeats)
            g_mc = time_call(partial(shipped.predict, frames, mc=args.mc), 2)
            extra["still_gate"] = {"size": f"{h}x{w}", "rad": shipped.still_burst_rad, "taken": taken,
                                   "deterministic_s": min(g_det), "mc_s": min(g_mc)}
            print(extra["still_gate"], flush=True)
            if pred.precision != "fp32":
                fp32 = Predictor.load(precision="fp32", still_burst_rad=0.0)
                d = time_call(partial(fp32.predict, frames), args.repeats)
                m = mc_time(fp32, frames, args.mc, 2, plain=False, chunk=None)
                extra["fp32"] = {
                    "size": f"{h}x{w}",
                    "deterministic_s": min(d),
                    "mc_reuse_s": min(m),
                }
                print(extra["fp32"], flush=True)
            macs = macs_by_resolution(pred.model, h, w)
            extra["macs_per_pass"] = macs
            extra["time_share_by_resolution"] = time_by_resolution(pred, frames, args.mc)
            extra["conv_gmac_per_s"] = conv_throughput(pred.precision, h, w)
            print(extra["conv_gmac_per_s"], flush=True)
            print(extra["time_share_by_resolution"], flush=True)
    info.update(
        load_average_at_start=load_start,
        load_average_at_end=os.getloadavg(),
        passes=args.mc,
        rows=rows,
        chunks=chunk_rows,
        **extra,
    )
    js.write_text(json.dumps(info, indent=2) + "\n")
    md.write_text(report(info))


def report(info: dict) -> str:
    T = info["passes"]
    la0, la1 = info["load_average_at_start"], info["load_average_at_end"]
    lines = [
        f"# Shipped CD-DCU-Net: CPU inference time per burst (deterministic and MC T={T})",
        "",
        f"Host: {info['cpu']}, {info['cores']} cores, AVX512-BF16 {'yes' if info['avx512_bf16'] else 'no'}, "
        f"AMX {'yes' if info['amx_bf16'] else 'no'}; {info['threads']} threads; torch {info['torch']}; "
        f"commit {info['commit']}.",
        f"Load average (1/5/15 min) at start {la0[0]:.1f}/{la0[1]:.1f}/{la0[2]:.1f}, at end "
        f"{la1[0]:.1f}/{la1[1]:.1f}/{la1[2]:.1f}; this benchmark's own {info['threads']} threads count in it "
        "(a shared machine: other jobs may run beside; repeated runs differ by about 20 %).",
        f"Model: inference/weights/default ({info['model']}); precision chosen by the CPU: "
        f"{info['precision']}, channels_last {info['channels_last']}.",
        "Through `Predictor.predict` (uint8 fringe frames in, PhaseResult out, propagation included); "
        "min of repeats (median in the JSON); MC repeated 3 times at the first size, twice at the others, "
        "once above 800x800. The frames stand still, so the network is timed with the still-burst gate off "
        "(`still_burst_rad=0`): the shipped gate would decode them by three-step PS and skip the MC passes "
        "(its own path below). Since session 38 MC mode also runs the deterministic pass, whose phase it reports "
        "(`mc_phase`, benchmarks/mc_phase_rule.md): one pass more, about the deterministic column's "
        "time (with the gate on it runs anyway).",
        "",
        f"MC before = whole network per pass, chunks of 2, float64 moments (the previous path, "
        f"`mc_moments(..., reuse_prefix=False)`); after = classical M/D, padding and stem once per burst, "
        f"the first dropout layer's {T} passes as convolutions with stacked mask-scaled weights, the rest "
        f"per pass in chunks by image size (`auto_mc_chunk`), float32 moments around the first pass.",
        "",
        f"| size | deterministic (s) | MC T={T} before (s) | MC T={T} after (s) | chunk | after / pass (ms) |",
        "|---|---|---|---|---|---|",
    ]
    for r in info["rows"]:
        before = f"{r['mc_plain_s']:.2f}" if "mc_plain_s" in r else "-"
        lines.append(
            f"| {r['size']} | {r['deterministic_s']:.3f} | {before} | {r['mc_reuse_s']:.2f} | {r['mc_chunk']} | "
            f"{1000 * r['mc_reuse_s'] / T:.0f} |"
        )
    if info.get("chunks"):
        lines += [
            "",
            f"MC T={T} after, by chunk (passes per batched forward), {info['chunks'][0]['size']}:",
            "",
            "| chunk | " + " | ".join(str(c["chunk"]) for c in info["chunks"]) + " |",
            "|---|" + "---|" * len(info["chunks"]),
            "| s | " + " | ".join(f"{c['mc_reuse_s']:.2f}" for c in info["chunks"]) + " |",
        ]
    if "fp32" in info:
        f = info["fp32"]
        lines += [
            "",
            f"fp32 instead ({f['size']}): deterministic {f['deterministic_s']:.3f} s, "
            f"MC T={T} after {f['mc_reuse_s']:.2f} s.",
        ]
    if "still_gate" in info:
        g = info["still_gate"]
        lines += [
            "",
            f"The still-burst gate's path ({g['size']}, the shipped gate at {g['rad']:g} rad, these still frames "
            f"{'taken' if g['taken'] else 'NOT taken'}): deterministic {g['deterministic_s']:.3f} s, "
            f"MC T={T} {g['mc_s']:.3f} s (one deterministic pass decides; a taken burst skips the MC passes, "
            "a moving one pays that pass on top of the MC passes).",
        ]
    if "macs_per_pass" in info:
        macs = info["macs_per_pass"]
        per_pass = (
            sum(v for k, v in macs.items() if not k.startswith("stem"))
            - macs["stem (once per burst)"]
        )
        first = info["rows"][0]
        full = macs.get(first["size"], 0.0) - macs["stem (once per burst)"]
        lines += [
            "",
            "## What bounds it",
            "",
            "Multiply-accumulates of one pass by output resolution (G): "
            + ", ".join(f"{k} {v / 1e9:.3f}" for k, v in macs.items())
            + f". Per MC pass (without the stem): {per_pass / 1e9:.2f} GMAC, so T={T} is "
            f"{T * per_pass / 1e9:.0f} GMAC; after, that ran at "
            f"{T * per_pass / first['mc_reuse_s'] / 1e9:.0f} GMAC/s on {info['threads']} threads.",
            "Share of op time by the largest map an op reads (one profiled MC run, "
            f"{first['size']}): "
            + ", ".join(f"{k} {100 * v:.0f} %" for k, v in info["time_share_by_resolution"].items())
            + ".",
            f"Single convs in {info['precision']} ({info['threads']} threads), GMAC/s: "
            + ", ".join(f"{k}: {v:.0f}" for k, v in info["conv_gmac_per_s"].items())
            + ".",
            "",
            f"So: only the stem ({macs['stem (once per burst)'] / 1e9:.2f} GMAC) and the input of the first "
            "dropout conv are shared by all passes; every later layer sees masked features, so "
            "T x one pass of the rest is the floor of this estimator. In that pass the full-resolution maps "
            f"hold {100 * full / per_pass:.0f} % of the MACs but take "
            f"{100 * info['time_share_by_resolution'].get('full resolution', 0.0):.0f} % of the op time: "
            "oneDNN computes 16 output channels per vector, so the w=8 layers (8 outputs) run at half the "
            "rate of a 16-output conv, the head's last conv (4 outputs, kept in fp32 by the model config) "
            "far below it, and the elementwise work there (skip concat, max pool, masks, ReLU, "
            "the fp32 copy for the head) is memory-bound. Going faster means changing the estimator or the "
            "model (fewer passes, a bf16 head, fewer or wider full-resolution layers); grouped convs over "
            "the passes (tried: faster for some 8-channel convs at 2 passes, slower at 4 and for 16->8) "
            "gave no robust gain.",
        ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
