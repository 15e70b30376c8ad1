"""CPU inference time of CD-DCU-Net per burst: fp32 vs bf16 autocast + channels_last.

Untrained weights (timing does not depend on them). Writes ``inference_speed.md`` and
``inference_speed.json`` beside this script.

    .venv/bin/python benchmarks/inference_speed.py [--width 16] [--size 512] [--threads 2] [--mc 20]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from gearscan.inference.models import build_model
from gearscan.inference.predictor import Predictor, cpu_has_fast_bf16


def time_call(fn, repeats: int, warmup: int = 2) -> list[float]:
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--width", type=int, default=16)
    ap.add_argument("--size", type=int, nargs="+", default=[512])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--mc", type=int, default=20)
    ap.add_argument("--mc-repeats", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    rows = []
    for size in args.size:
        frames = np.random.default_rng(0).integers(0, 256, size=(3, size, size)).astype(np.uint8)
        variants = {
            "fp32 (contiguous)": dict(precision="fp32", head_fp32=True, channels_last=False),
            "fp32+channels_last": dict(precision="fp32", head_fp32=True),
            "bf16+channels_last (fp32 head)": dict(precision="bf16", head_fp32=True),
            "bf16+channels_last (bf16 head)": dict(precision="bf16", head_fp32=False),
        }
        for label, v in variants.items():
            model = build_model("cd-dcu-net", width=args.width, head_fp32=v["head_fp32"])
            pred = Predictor(model, precision=v["precision"], channels_last=v.get("channels_last"))
            slow = v["precision"] == "bf16" and not cpu_has_fast_bf16()
            det = time_call(
                lambda pred=pred, frames=frames: pred.predict(frames),
                2 if slow else args.repeats,
                warmup=1,
            )
            row = {
                "size": size,
                "variant": label,
                "deterministic_s_median": statistics.median(det),
                "deterministic_s_min": min(det),
            }
            if args.mc and not slow:
                mc = time_call(
                    lambda pred=pred, frames=frames: pred.predict(frames, mc=args.mc),
                    args.mc_repeats,
                    warmup=1,
                )
                row[f"mc{args.mc}_s_median"] = statistics.median(mc)
            rows.append(row)
            print(row, flush=True)
    info = {
        "width": args.width,
        "threads": args.threads,
        "torch": torch.__version__,
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "cpu_native_bf16": cpu_has_fast_bf16(),
        "load_average_1min_at_end": os.getloadavg()[0],
        "note": "shared 2-core machine; other jobs were running",
        "rows": rows,
    }
    here = Path(__file__).resolve().parent
    (here / "inference_speed.json").write_text(json.dumps(info, indent=2))
    lines = [
        f"# CD-DCU-Net CPU inference time (w={args.width}, {args.threads} threads, torch {torch.__version__})",
        "",
        "Per burst through `Predictor.predict` (uint8 frames in, PhaseResult out; includes conversion and",
        "phase/sigma propagation). Untrained weights; median of repeats.",
        f"CPU native bf16 (AVX512-BF16/AMX): {cpu_has_fast_bf16()}; 1-min load average "
        f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (other engineers' jobs were running, so",
        "absolute times are pessimistic; the ratios between variants are the useful part).",
        "",
        f"| size | variant | deterministic median (s) | deterministic min (s) | MC T={args.mc} (s) |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        mc = r.get(f"mc{args.mc}_s_median")
        lines.append(
            f"| {r['size']}² | {r['variant']} | {r['deterministic_s_median']:.3f} | {r['deterministic_s_min']:.3f} | "
            + (f"{mc:.2f}" if mc is not None else "-")
            + " |"
        )
    (here / "inference_speed.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
