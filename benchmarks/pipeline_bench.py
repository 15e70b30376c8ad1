"""End-to-end replay throughput and per-stage latency; writes benchmarks/pipeline_report.{md,json}.

    .venv/bin/python benchmarks/pipeline_bench.py [--bursts 12] [--mc 20]

Renders twin recordings (512x512 and the paper's 1232x1360 crop of a 2048x2448 camera),
replays each as fast as possible through camera -> assembler -> CD-DCU-Net -> unwrap +
triangulate -> rerun (file sink, viewer on), deterministic and Monte Carlo.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import torch
from inspect_bench import commit, host  # same folder: the host and commit lines of every report

from gearscan.core.rig import default_rig
from gearscan.inference.decoder import Decoder
from gearscan.replay import replay
from gearscan.twin.recordings import render_recording

HERE = Path(__file__).parent


def run(rec: Path, decoder: Decoder, out: Path, truth: bool = False) -> dict:
    done: list[float] = []
    t0 = time.perf_counter()
    m = replay(rec, decoder=decoder, save=out, truth=truth, on_burst=lambda *_: done.append(time.perf_counter()))
    wall = time.perf_counter() - t0
    # steady state: bursts out per second between the first and the last, without start-up
    steady = (len(done) - 1) / (done[-1] - done[0]) if len(done) > 1 else float("nan")
    stages = {k: {"latency_ms_mean": v["latency_ms_mean"], "latency_ms_p95": v["latency_ms_p95"],
                  "dropped_in": v["dropped_in"]} for k, v in m.pipeline.items()}
    return {"bursts": m.bursts, "wall_s": wall, "bursts_per_s": m.bursts / wall, "steady_bursts_per_s": steady,
            "stages": stages, "truth": truth}


def reference_forward_s(repeats: int = 10) -> float:
    """Median bare forward pass of the shipped model at 512x512: the host's speed during this run
    (the machines here are shared; this moved from 0.10 to 0.14 s within one session)."""
    import numpy as np
    import torch

    from gearscan.inference.predictor import Predictor

    model = Predictor.load().model
    x = torch.rand(1, 3, 512, 512).contiguous(memory_format=torch.channels_last)
    times = []
    with torch.inference_mode():
        model(x)
        for _ in range(repeats):
            t0 = time.perf_counter()
            model(x)
            times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--bursts", type=int, default=12)
    ap.add_argument("--mc", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3, help="runs of the 512x512 deterministic row (median reported)")
    args = ap.parse_args()
    stamp, started = commit(), host()  # before this run writes its report: a tree dirty with it is not an edit
    os.environ.setdefault("HOME", tempfile.mkdtemp())
    results = []
    forward_s = reference_forward_s()
    print(f"reference forward pass: {forward_s:.3f} s")

    def row(runs: list[dict], **info) -> None:
        runs.sort(key=lambda r: r["steady_bursts_per_s"])
        r = runs[len(runs) // 2]  # the median run
        r.update(info, steady_all_runs=[x["steady_bursts_per_s"] for x in runs])
        results.append(r)
        print(r)

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for w, h in ((512, 512), (1360, 1232)):
            size = f"{w}x{h}"
            rec = render_recording(tmp / f"rec{w}", rig=default_rig(w, h), bursts=args.bursts, motion="nonuniform:0.1,1.6")
            det = Decoder()  # the default: 2 workers on a CPU
            if w == 512:
                # the target row (live cost), against one worker; runs alternate (the host is shared)
                one = Decoder(workers=1)
                decoders = (det, one) if det.workers != 1 else (det,)  # a GPU decodes with one worker anyway
                paired: dict[int, list[dict]] = {dec.workers: [] for dec in decoders}
                for _ in range(args.repeats):
                    for dec in decoders:
                        Decoder.use_threads(dec.workers)
                        paired[dec.workers].append(run(rec, dec, tmp / "o.rrd"))
                for workers, runs in paired.items():
                    row(runs, size=size, mode="deterministic", workers=workers)
                Decoder.use_threads(det.workers)
                # the replay default also scores against truth
                row([run(rec, det, tmp / "o.rrd", truth=True)], size=size, mode="deterministic", workers=det.workers)
            else:
                Decoder.use_threads(det.workers)
                row([run(rec, det, tmp / "o.rrd")], size=size, mode="deterministic", workers=det.workers)
            mc = Decoder(mc=args.mc)
            n = max(2, args.bursts // 6)  # MC is slow: a shorter recording
            rec_mc = render_recording(tmp / f"rec{w}mc", rig=default_rig(w, h), bursts=n, motion="nonuniform:0.1,1.6")
            row([run(rec_mc, mc, tmp / "o.rrd")], size=size, mode=f"MC T={args.mc}", workers=mc.workers)
    (HERE / "pipeline_report.json").write_text(json.dumps(
        {"results": results, "loadavg": os.getloadavg(), "reference_forward_s": forward_s}, indent=2))
    one, two = ({r["workers"]: r["steady_bursts_per_s"] for r in results
                 if r["size"] == "512x512" and r["mode"] == "deterministic" and not r["truth"]}.get(k) for k in (1, 2))
    lines = [
        "# End-to-end replay benchmark (CPU)",
        "",
        f"`python benchmarks/pipeline_bench.py --bursts {args.bursts} --mc {args.mc} --repeats {args.repeats}` "
        f"on {os.cpu_count()} cores, torch threads = cores / decode workers, "
        f"load average {os.getloadavg()[0]:.1f} at the end. Replay at maximum speed with the rerun file sink on; "
        "stage latency is the time inside each stage's function. Steady state counts bursts out per second between "
        "the first and the last output; the other rate divides by the whole run, start-up included (model "
        "load, CAD scene, viewer stream). The 512x512 deterministic rows without truth scoring are the median of "
        "the repeated runs, one and two decode workers alternating.",
        "",
        f"Commit `{stamp}`; host: {started}. Host speed during this "
        f"run: the shipped network's bare forward pass at 512x512 took {forward_s:.3f} s (median of 10, before the "
        "runs); rates here scale with it (earlier reports, other hosts: 0.10-0.16 s when quiet).",
        "",
        "| camera | decoder | decode workers | truth scoring | bursts | bursts/s steady | bursts/s incl. start-up | assemble ms | infer ms | reconstruct ms | output ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        st = r["stages"]
        steady = f"{r['steady_bursts_per_s']:.2f}"
        if len(r["steady_all_runs"]) > 1:
            steady += f" (runs: {', '.join(f'{v:.2f}' for v in r['steady_all_runs'])})"
        lines.append(f"| {r['size']} | {r['mode']} | {r['workers']} | {'yes' if r['truth'] else 'no'} | {r['bursts']} | "
                     f"{steady} | {r['bursts_per_s']:.2f} | "
                     f"{st['assemble']['latency_ms_mean']:.1f} | {st['infer']['latency_ms_mean']:.0f} | "
                     f"{st['reconstruct']['latency_ms_mean']:.0f} | {st['output']['latency_ms_mean']:.0f} |")
    lines += ["", "Target on 2 CPU cores at 512x512 deterministic: >= 5 bursts/s end to end with the viewer on.",
              "Reading: the stages overlap in threads but share the cores, so a burst costs roughly the sum of",
              "the heavy stages. Rows without truth scoring cost what a live run costs (`gearscan replay",
              "--no-truth`); the scored row adds the replay's CAD distance of every point and a three-step",
              "baseline to `output`. `reconstruct` runs the keep test (with a network's fringe-support test),",
              "casts the CAD gear's rays (only where the modulation and sigma pass) for the fringe-order",
              "prior, carries orders in at its silhouettes, runs the fused unwrap + triangulation and drops",
              "mixed pixels.",
              "The pipeline runs numpy's BLAS single-threaded (`Pipeline(blas_threads=1)`): its own spinning",
              "pool competed with torch's and the other stages for the 2 cores: on a quiet host (forward 0.10 s) that",
              "took this row from 4.05 to 5.10 bursts/s (median of 3 runs: 4.66, 5.10, 5.13; report at commit 9766d02).",
              "Two decode workers (`model.workers`, the CPU default) run two bursts through two copies of the",
              "network with one torch thread each: one pass spread over both cores stalls at every parallel",
              "region whenever another stage holds a core; two single-threaded passes do not wait for each",
              "other. Per-burst infer latency grows (each pass has one core)"
              + (f"; in this run two workers gave {two:.2f} bursts/s against one worker's {one:.2f} (the medians "
                 "above)." if one is not None and two is not None else "; this device decodes with one worker."),
              f"Device: {'CUDA' if torch.cuda.is_available() else 'CPU only'}."]
    (HERE / "pipeline_report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
