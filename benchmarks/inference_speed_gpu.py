"""Inference time of the shipped CD-DCU-Net per burst on a GPU: deterministic, Monte Carlo T passes, the shipped path.

What a shop floor with a GPU would get from ``Predictor.load(device="cuda")`` through ``Predictor.predict`` (uint8
frames in on the host, PhaseResult out on the host, so every time includes the copies and ends synchronised), on
the synthetic fringe frames of ``inference_speed.py``:

- "network": the still-burst gate off, deterministic and MC T passes (chunks: the CPU's choice, all T passes in one
  batch, and the Predictor's automatic choice on this device);
- "shipped path": the model's own settings (its still-burst gate on: these still frames are a burst it takes, so
  the time includes the deterministic pass the gate reads and the three-step decode it reports);
- bf16 (``auto`` on CUDA) beside fp32, and the peak GPU memory of the MC run.

Writes ``inference_speed_gpu.md`` and ``.json`` into ``--out`` (default: beside this script). Run on a lent GPU
machine by ``scripts/lease_bench.sh``.

    python benchmarks/inference_speed_gpu.py [--device cuda] [--sizes 512 800 1232x1360] [--mc 20]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from functools import partial
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from inference_speed import fringe_frames, host_info, parse_size, time_call  # noqa: E402

from gearscan.inference.predictor import Predictor, auto_mc_chunk  # noqa: E402

HERE = Path(__file__).resolve().parent


def median_ms(seconds: list[float]) -> float:
    return 1000 * statistics.median(seconds)


def measure(device: str, sizes: list[str], passes: int, repeats: int, model: str | None) -> list[dict]:
    """One row per (size, precision, path): median ms over ``repeats`` after a warm-up call."""
    rows = []
    for precision in ("auto", "fp32"):
        net = Predictor.load(model, device=device, precision=precision, still_burst_rad=0.0)
        shipped = Predictor.load(model, device=device, precision=precision)
        for size in sizes:
            h, w = parse_size(size)
            first = len(rows)
            frames = fringe_frames(h, w)
            base = {"size": f"{h}x{w}", "precision": net.precision}
            rows.append(base | {"path": "network, deterministic",
                                "ms": median_ms(time_call(partial(net.predict, frames), repeats, warmup=2))})
            for chunk in dict.fromkeys((auto_mc_chunk(h, w, passes), passes, auto_mc_chunk(h, w, passes, device))):
                net.mc_chunk = chunk
                if device == "cuda":
                    torch.cuda.reset_peak_memory_stats()
                ms = median_ms(time_call(partial(net.predict, frames, mc=passes), repeats, warmup=1))
                peak = torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else None
                rows.append(base | {"path": f"network, MC T={passes}, chunk {chunk}", "ms": ms, "peak_mib": peak})
            net.mc_chunk = None
            rows.append(base | {"path": "shipped path (gate on; it takes this still burst)",
                                "ms": median_ms(time_call(partial(shipped.predict, frames), repeats, warmup=2))})
            print(rows[first:], flush=True)
    return rows


def write_report(rows: list[dict], info: dict, args: argparse.Namespace, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "inference_speed_gpu.json").write_text(json.dumps({"host": info, "rows": rows}, indent=1) + "\n")
    lines = [
        f"# Inference time per burst on {info['gpu']} (`benchmarks/inference_speed_gpu.py`)",
        "",
        f"`python benchmarks/inference_speed_gpu.py --device {args.device} --sizes {' '.join(args.sizes)} "
        f"--mc {args.mc} --repeats {args.repeats}`; commit `{info['commit']}`; torch {info['torch']}; host CPU "
        f"{info['cpu']} ({info['cores']} cores). `Predictor.predict` from uint8 frames on the host to a PhaseResult "
        f"on the host (copies included); median of {args.repeats} calls after a warm-up; synthetic still fringe "
        "frames (`inference_speed.fringe_frames`). Peak: GPU memory allocated during the MC calls.",
        "",
        "| size | precision | path | ms per burst | peak GPU MiB |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        peak = f"{r['peak_mib']:.0f}" if r.get("peak_mib") is not None else ""
        lines.append(f"| {r['size']} | {r['precision']} | {r['path']} | {r['ms']:.1f} | {peak} |")
    (out / "inference_speed_gpu.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--sizes", nargs="+", default=["512", "800", "1232x1360"], help="HxW or N (square)")
    ap.add_argument("--mc", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--model", default=None, help="weights (default: the shipped model)")
    ap.add_argument("--out", type=Path, default=HERE)
    args = ap.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: torch sees no GPU")
    info = host_info(torch.get_num_threads()) | {
        "gpu": torch.cuda.get_device_name() if args.device == "cuda" else "cpu (a dry run of the GPU benchmark)"}
    rows = measure(args.device, args.sizes, args.mc, args.repeats, args.model)
    write_report(rows, info, args, args.out)
    print((args.out / "inference_speed_gpu.md").read_text())


if __name__ == "__main__":
    main()
