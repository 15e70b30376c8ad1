"""Twin render throughput and dataset generation time; writes benchmarks/twin_report.{md,json}.

    .venv/bin/python benchmarks/twin_bench.py [--poses 10]

Images/s counts rendered camera images (18-step poses: one ray cast, 18 images each). The
process CPU time per pose is reported beside the wall time: on a machine shared with other jobs
it says what the renderer costs when the wall time does not.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from gearscan.core.gear import GearSpec
from gearscan.core.patterns import DEFAULT_PERIOD_PX, PatternSet
from gearscan.core.rig import default_rig
from gearscan.twin.dataset import DatasetSpec, generate_dataset
from gearscan.twin.render import Optics, TwinRenderer

HERE = Path(__file__).parent


def bench_render(size: int, poses: int) -> dict:
    gear = GearSpec()
    t0 = time.perf_counter()
    r = TwinRenderer(default_rig(size, size), gear, Optics())
    setup = time.perf_counter() - t0
    ps = PatternSet.n_step(18, DEFAULT_PERIOD_PX)
    rng = np.random.default_rng(0)
    r.render(0.0, ps, rng)  # warm-up
    times, cpu, geo = [], [], []
    for i in range(poses):
        a = np.radians(0.1 * i)
        t0 = time.perf_counter()
        r.surface(a)
        geo.append(time.perf_counter() - t0)
        t0, c0 = time.perf_counter(), time.process_time()
        r.render(a, ps, rng)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    best, med = min(times), float(np.median(times))
    return {
        "size": size,
        "setup_s": setup,
        "pose_median_s": med,
        "pose_best_s": best,
        "pose_cpu_median_s": float(np.median(cpu)),
        "raycast_geometry_median_s": float(np.median(geo)),
        "images_per_s_median": 18 / med,
        "images_per_s_best": 18 / best,
    }


def bench_dataset(size: int) -> dict:
    spec = DatasetSpec(gears=[GearSpec(teeth=20)], width=size, height=size, max_start_points=2)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        generate_dataset(tmp, spec)
        dt = time.perf_counter() - t0
    return {"size": size, "start_points": 2, "images": 2 * 18 * 18, "seconds": dt, "seconds_per_start_point": dt / 2}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--poses", type=int, default=10)
    args = ap.parse_args()
    load = os.getloadavg()[0]
    results = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "loadavg_1min_at_start": load},
        "render": [bench_render(512, args.poses), bench_render(800, args.poses)],
        "dataset": [bench_dataset(256), bench_dataset(512)],
    }
    results["machine"]["loadavg_1min_at_end"] = os.getloadavg()[0]
    (HERE / "twin_report.json").write_text(json.dumps(results, indent=2))
    lines = [
        "# Twin rendering benchmark",
        "",
        f"`python benchmarks/twin_bench.py --poses {args.poses}` on {os.cpu_count()} CPU cores, "
        f"1-min load average {load:.2f} at start, {results['machine']['loadavg_1min_at_end']:.2f} at end "
        "(other jobs inflate the wall times; CPU time is the process's, all its threads).",
        "",
        "Per pose: one camera ray cast, one shadow ray cast, then the 18-step images (noise on).",
        "",
        "| camera | images/s (median) | images/s (best) | s per 18-image pose | of which ray casting + geometry | CPU s per pose |",
        "|---|---|---|---|---|---|",
    ]
    for r in results["render"]:
        lines.append(
            f"| {r['size']}x{r['size']} | {r['images_per_s_median']:.0f} | {r['images_per_s_best']:.0f} | "
            f"{r['pose_median_s']:.3f} | {r['raycast_geometry_median_s']:.3f} | {r['pose_cpu_median_s']:.3f} |"
        )
    lines += ["", "Target: >= 200 images/s at 512x512 on 2 cores.", "", "| dataset | images | seconds | s per start point |", "|---|---|---|---|"]
    for d in results["dataset"]:
        lines.append(f"| {d['size']}x{d['size']}, 2 start points x 18 poses x 18 steps | {d['images']} | {d['seconds']:.1f} | {d['seconds_per_start_point']:.1f} |")
    (HERE / "twin_report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
