"""Soak: `gearscan live` for a long time on the simulators, recording every burst.

The counterparts of tests/test_live.py: the replay camera fed by a small twin recording (looped),
the mock projector and the mock encoder process on a pty (1 kHz). ``run_live`` decodes with the
shipped network and writes the recording and the rerun stream; a thread samples the process's
resident memory (VmRSS). Afterwards the recording is read back and checked (every frame's PNG
structure and format, every encoder line) without decoding.

Reported: duration, bursts, RSS at the first burst / after warm-up / at the end / max and the
growth after warm-up (with its slope, MB/h), frames lost (frame-id gaps, discarded frames,
encoder gaps), encoder lines lost, bursts dropped before decoding (a slow decoder drops the
oldest burst: measured, still recorded), and whether every acquired burst is in the recording.

    nice -n 19 .venv/bin/python benchmarks/soak_bench.py --minutes 30

Writes benchmarks/soak_report.md and benchmarks/soak_report.json (``--no-report``: only
``--json``). ``--settle-ms`` paces the projector (and so the frame rate) to keep the CPU use modest.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from gearscan.provenance import code_edits

HERE = Path(__file__).parent

CONFIG = """
[camera]
driver = "replay"
id = "{rec}"
trigger = "software"
loop = true

[projector]
backend = "mock"
width = 1280
height = 800
period_px = 40.0
settle_ms = {settle_ms}

[encoder]
port = "{port}"
counts_per_rev = 10000

[rig]
calibration = "{rig}"

[gear]
teeth = 20

[model]
mc = 0
"""


def rss_mb() -> float:
    """Resident memory of this process (VmRSS), MB."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def host() -> dict:
    model = platform.processor() or "?"
    try:
        with open("/proc/cpuinfo") as fh:
            model = next(line.split(":", 1)[1].strip() for line in fh if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, capture_output=True, text=True).stdout.strip()
    dirty = code_edits(HERE.parent)
    return {"cpu": model, "cores": os.cpu_count(), "commit": commit + (" + uncommitted changes" if dirty else ""),
            "python": platform.python_version()}


def rss_summary(samples: list, before: float, first_burst: float | None) -> dict:
    """RSS figures from ``samples`` ``[seconds, bursts, MB]`` taken while live ran, the last one
    after it closed (viewer stream flushed and released)."""
    t = np.array([s[0] for s in samples[:-1]])
    rss = np.array([s[2] for s in samples[:-1]])
    warm = t >= min(60.0, 0.2 * t[-1])  # after the first minute (model, pools, caches warmed)
    slope = float(np.polyfit(t[warm], rss[warm], 1)[0] * 3600) if warm.sum() >= 3 else float("nan")
    return {
        "before": round(before, 1),
        "first_burst": None if first_burst is None else round(first_burst, 1),
        "after_warmup": round(float(rss[warm][0]), 1),
        "end_of_run": round(float(rss[-1]), 1),
        "max_in_run": round(float(rss.max()), 1),
        "after_close": round(float(samples[-1][2]), 1),
        "growth_after_warmup": round(float(rss[-1] - rss[warm][0]), 1),
        "slope_mb_per_h_after_warmup": round(slope, 1),
        "growth_per_burst_kb": round(float(rss[-1] - rss[warm][0]) * 1024 / max(1, samples[-2][1] - samples[
            int(np.argmax(warm))][1]), 2),
    }


def soak(minutes: float, work: Path, *, size: int = 96, settle_ms: float = 100.0, sample_s: float = 5.0,
         viewer: bool = True) -> dict:
    """Run live for ``minutes`` in ``work``; return the figures (see the module docstring).
    ``viewer=False``: no rerun stream (tells the viewer's memory from the pipeline's)."""
    from gearscan.config import LiveConfig
    from gearscan.core.recording import RecordingReader
    from gearscan.core.rig import default_rig
    from gearscan.live import run_live
    from gearscan.mocks.encoder_device import MockEncoderProcess
    from gearscan.twin.recordings import render_recording

    rig = default_rig(size, size)
    twin = render_recording(work / "twin", rig=rig, motion="uniform:0.6", bursts=4, seed=2)
    rig.save(work / "rig.json")
    link = str(work / "enc")
    cfg_path = work / "live.toml"
    cfg_path.write_text(CONFIG.format(rec=twin, settle_ms=settle_ms, port=link, rig=work / "rig.json"))
    duration = minutes * 60.0
    samples: list[tuple[float, int, float]] = []  # (seconds, bursts decoded, RSS MB)
    decoded = [0]
    first_burst_rss: list[float] = []
    stop = threading.Event()
    t0 = time.monotonic()

    def sampler() -> None:
        while not stop.wait(sample_s):
            samples.append((time.monotonic() - t0, decoded[0], rss_mb()))

    def on_burst(m, row) -> None:
        decoded[0] += 1
        if decoded[0] == 1:
            first_burst_rss.append(rss_mb())

    rss_before = rss_mb()
    machine = host()  # the commit measured: before anything else is committed meanwhile
    with MockEncoderProcess(link, rate=1000, cpr=10000, rpm=6.0, duration=duration + 120, linger=0) as dev:
        cfg = LiveConfig.load(cfg_path)
        thread = threading.Thread(target=sampler, daemon=True)
        thread.start()
        try:
            report = run_live(cfg, record=work / "rec", duration=duration, save=work / "live.rrd" if viewer else None,
                              on_burst=on_burst, handle_signals=False)
        finally:
            stop.set()
            thread.join()
            dev.kill()
    wall = time.monotonic() - t0
    samples.append((wall, decoded[0], rss_mb()))

    # read the recording back: every acquired burst in it, nothing damaged
    reader = RecordingReader(work / "rec", warn=False)
    notes = reader.check()
    recorded_frames = len(reader)
    encoder_lines = len(reader.encoder_samples())
    meta = reader.meta
    stages = report.pipeline.stages
    return {
        "host": machine,
        "minutes_requested": minutes,
        "wall_s": round(wall, 1),
        "live_s": round(report.pipeline.wall_s, 1),
        "image": f"{size}x{size}",
        "viewer": viewer,
        "settle_ms": settle_ms,
        "bursts_acquired": report.bursts,
        "bursts_decoded": decoded[0],
        "bursts_recorded": recorded_frames // 3,
        "frames_recorded": recorded_frames,
        "every_burst_recorded": recorded_frames == 3 * report.bursts and reader.finished,
        "recording_damage": len(reader.damage),
        "recording_notes": notes,
        "encoder_lines_recorded": encoder_lines,
        "assembler": meta.get("assembler", {}),
        "camera": meta.get("camera_stats", {}),
        "encoder": meta.get("encoder_stats", {}),
        "dropped_before_stage": {name: int(s["dropped_in"]) for name, s in stages.items()},
        "stopped_by": report.pipeline.stopped_by,
        "rss_mb": rss_summary(samples, rss_before, first_burst_rss[0] if first_burst_rss else None),
        "rss_samples": [[round(a, 1), b, round(c, 1)] for a, b, c in samples],
        "rrd_mb": round((work / "live.rrd").stat().st_size / 2**20, 1) if (work / "live.rrd").exists() else 0.0,
        "recording_mb": round(sum(p.stat().st_size for p in (work / "rec").rglob("*") if p.is_file()) / 2**20, 1),
    }


def lost_frames(r: dict) -> int:
    a, e = r["assembler"], r["encoder"]
    return int(a.get("dropped_frames", 0) + a.get("discarded_frames", 0) + a.get("encoder_gaps", 0)
               + e.get("lost", 0) + e.get("out_of_order", 0))


def markdown(r: dict) -> str:
    m, a, e, h = r["rss_mb"], r["assembler"], r["encoder"], r["host"]
    drops = ", ".join(f"{k} {v}" for k, v in r["dropped_before_stage"].items())
    return f"""# Soak report

`nice -n 19 .venv/bin/python benchmarks/soak_bench.py --minutes {r['minutes_requested']:g} --size {r['image'].split('x')[0]} --settle-ms {r['settle_ms']:g}{'' if r.get('viewer', True) else ' --no-viewer'}`:
`run_live` on the simulators of tests/test_live.py (replay camera looping a {r['image']} twin recording, mock
projector with {r['settle_ms']:g} ms settle, mock encoder on a pty at 1 kHz), decoding with the shipped network,
recording every burst and writing the rerun stream; VmRSS sampled every 5 s.

Host: {h['cpu']}, {h['cores']} cores (shared with other work), Python {h['python']}, commit {h['commit']}.

| | |
|---|---|
| duration | {r['live_s'] / 60:.1f} min of live ({r['wall_s']:.0f} s with setup) |
| bursts acquired / decoded / recorded | {r['bursts_acquired']} / {r['bursts_decoded']} / {r['bursts_recorded']} |
| every acquired burst in the recording | {'yes' if r['every_burst_recorded'] else 'NO'} ({r['frames_recorded']} frames; `check`: {r['recording_damage']} damage) |
| frames lost (id gaps / discarded / encoder gaps) | {a.get('dropped_frames', 0)} / {a.get('discarded_frames', 0)} / {a.get('encoder_gaps', 0)} |
| encoder lines lost / out of order / corrupt | {e.get('lost', 0)} / {e.get('out_of_order', 0)} / {e.get('corrupt', 0)} ({r['encoder_lines_recorded']} recorded) |
| bursts dropped before a stage (slow decoder; still recorded) | {drops} |
| RSS before / first burst / after warm-up (1 min) / end of run / max in run / after close | {m['before']} / {m['first_burst']} / {m['after_warmup']} / {m['end_of_run']} / {m['max_in_run']} / {m['after_close']} MB |
| RSS growth after warm-up | {m['growth_after_warmup']} MB ({m['slope_mb_per_h_after_warmup']} MB/h fitted; {m['growth_per_burst_kb']} KB per burst) |
| rerun stream | {'written to a file, as live' if r.get('viewer', True) else 'off (--no-viewer)'} |
| recording / rerun stream on disk | {r['recording_mb']} MB / {r['rrd_mb']} MB |

Stopped by: {r['stopped_by']}. Lost frames in all: {lost_frames(r)}.
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--size", type=int, default=96, help="image width and height, px")
    ap.add_argument("--settle-ms", type=float, default=100.0, help="projector settle per frame: paces the frame rate")
    ap.add_argument("--no-viewer", action="store_true", help="no rerun stream (default: written to a file, as live)")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    ap.add_argument("--no-report", action="store_true", help="do not write benchmarks/soak_report.{md,json}")
    ap.add_argument("--render", type=Path, default=None, help="only re-render the report from this JSON")
    ap.add_argument("--keep", type=Path, default=None, help="work in this folder and keep it (default: a temporary one)")
    args = ap.parse_args()
    if args.render is not None:
        r = json.loads(args.render.read_text())
        s = r["rss_samples"]
        r["rss_mb"] = rss_summary(s, r["rss_mb"]["before"], r["rss_mb"]["first_burst"])
        print(markdown(r))
        return
    work = args.keep or Path(tempfile.mkdtemp(prefix="soak-"))
    work.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("HOME", str(work))  # rerun and friends keep their files away from the user's
    try:
        r = soak(args.minutes, work, size=args.size, settle_ms=args.settle_ms, viewer=not args.no_viewer)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    text = json.dumps(r, indent=2)
    if args.json:
        args.json.write_text(text)
    if not args.no_report:
        (HERE / "soak_report.json").write_text(text)
        (HERE / "soak_report.md").write_text(markdown(r))
    print(markdown(r))


if __name__ == "__main__":
    main()
