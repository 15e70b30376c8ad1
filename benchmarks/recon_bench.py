"""Reconstruction speed per 2048x2448 burst on CPU: geometric unwrapping + triangulation.

Run: ``.venv/bin/python benchmarks/recon_bench.py`` (writes benchmarks/recon_report.md).
The wrapped phase is synthetic (timing does not depend on content); the rig is the default
rig at 2448x2048 with the gear's tip/root depth bounds and a 110 px fringe period.
"""

from __future__ import annotations

import math
import os
import platform
import time
from pathlib import Path

import cv2
import numpy as np

from gearscan.core.gear import GearSpec
from gearscan.core.phase import frame_swing, fringe_support
from gearscan.core.rig import default_rig
from gearscan.recon.reconstruct import SingleFrequencyReconstructor
from gearscan.recon.triangulate import Triangulator
from gearscan.recon.unwrap import gear_depth_bounds, geometric_unwrap, phase_bounds, temporal_unwrap

WIDTH, HEIGHT = 2448, 2048
PERIOD = 110.0
REPEATS = 15


def _time(fn, repeats: int = REPEATS) -> dict[str, float]:
    fn()  # warm-up (page faults, thread start)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    ts = np.array(ts) * 1e3
    return {"median": float(np.median(ts)), "p10": float(np.percentile(ts, 10)), "p90": float(np.percentile(ts, 90))}


def main() -> None:
    rig = default_rig(WIDTH, HEIGHT)
    gear = GearSpec()
    t0 = time.perf_counter()
    bounds = gear_depth_bounds(rig, gear.tip_radius, gear.root_radius, gear.face_width)
    t_bounds = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    phase = rng.uniform(-math.pi, math.pi, (HEIGHT, WIDTH)).astype(np.float32)
    sigma = np.full((HEIGHT, WIDTH), 0.02, np.float32)
    rows = []

    t0 = time.perf_counter()
    fused = SingleFrequencyReconstructor(rig, PERIOD, bounds)
    t_setup = time.perf_counter() - t0
    buf = fused.allocate()
    rows.append(("fused unwrap + triangulate + sigma, reused buffers (live path)", _time(lambda: fused(phase, sigma, out=buf))))
    rows.append(("fused, fresh output arrays per burst", _time(lambda: fused(phase, sigma))))
    fused.close()
    single = SingleFrequencyReconstructor(rig, PERIOD, bounds, threads=1)
    buf1 = single.allocate()
    rows.append(("fused, reused buffers, 1 thread", _time(lambda: single(phase, sigma, out=buf1))))
    single.close()

    # the keep test's fringe support for a network's burst (recon.measure.keep_candidates, E = 2 px)
    frames8 = rng.integers(0, 256, (3, HEIGHT, WIDTH)).astype(np.uint8)
    frames12 = (frames8.astype(np.uint16) * 16)

    def support_session32() -> None:  # the first form (session 32): float copies, sqrt, division
        lit = (2.0 * frame_swing(frames8.astype(np.float32) / np.float32(255.0)) >= 0.05).astype(np.uint8)
        cv2.erode(lit, np.ones((5, 5), np.uint8), borderType=cv2.BORDER_REPLICATE).astype(bool)

    rows.append(("network fringe support, 8-bit frames, 2 px (v6's live path)", _time(lambda: fringe_support(frames8, 255.0, 0.05, 2))))
    rows.append(("network fringe support, 12-bit frames, 2 px", _time(lambda: fringe_support(frames12, 4095.0, 0.05, 2))))
    rows.append(("reference: the same support, session 32's form", _time(support_session32)))

    lo, hi = phase_bounds(rig, bounds, PERIOD)
    tri = Triangulator(rig, PERIOD)

    def reference() -> None:
        res = geometric_unwrap(phase, lo, hi, PERIOD, margin=0.2)
        tri(res.phase_abs, sigma)

    rows.append(("reference: geometric_unwrap then Triangulator (numpy, unfused)", _time(reference, 5)))
    periods = [20.0, 160.0, 1408.0]
    wrapped = [phase, phase, phase]
    rows.append(("temporal_unwrap, 3 frequencies (static reference scans)", _time(lambda: temporal_unwrap(wrapped, periods, 1280), 5)))

    lines = [
        "# Reconstruction benchmark",
        "",
        f"Per burst of {WIDTH}x{HEIGHT} camera pixels, float32, CPU only; default rig, gear tip/root",
        f"depth bounds, fringe period {PERIOD:g} projector px. Target: < 50 ms for unwrapping +",
        "triangulation (with per-point depth sigma).",
        "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, shared with other jobs",
        f"(1-min load average at the end of the run: {os.getloadavg()[0]:.1f}; on a loaded machine timings",
        "grow by 2-3x), numpy " + np.__version__ + ".",
        "",
        "| step | median ms | p10 ms | p90 ms |",
        "|---|---|---|---|",
    ]
    for name, t in rows:
        lines.append(f"| {name} | {t['median']:.1f} | {t['p10']:.1f} | {t['p90']:.1f} |")
    lines += [
        "",
        f"One-time setup per rig: depth bounds {t_bounds:.1f} s, fused reconstructor {t_setup:.1f} s",
        "(undistorting 5 M camera rays and projecting the bounds; cache it for the session).",
        "",
        "A network's burst adds the fringe-support test of its keep test (`core.phase.fringe_support`:",
        "the frames' own modulation 2B'/S >= 0.05 on every pixel within 2 px), read off the three frames",
        "before the fused step; three-step PS and the other classical decoders skip it.",
        "",
        "The live path is `SingleFrequencyReconstructor(rig, period, bounds)(phase, sigma, out=buffers)`:",
        "row blocks of 64 rows that stay in cache, on a thread pool; reusing the output buffers",
        "avoids ~100 MB of page faults per burst.",
        "",
        "Observed on this shared 2-core machine: 36 ms median for the live path when the load",
        "average was low (~1-2), 63-70 ms at load 3-4 (other engineers' jobs). The step is",
        "memory-bound (~300 MB of float32 traffic per burst: phase, sigma, 6 per-pixel rig maps in;",
        "points, depth, sigma, order, mask out), so it meets the 50 ms target only on an unloaded",
        "machine. Next lever if needed: derive the per-pixel triangulation constants from the ray",
        "map on the fly and skip the order map (about -25 % traffic).",
        "",
    ]
    out = Path(__file__).with_name("recon_report.md")
    out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
