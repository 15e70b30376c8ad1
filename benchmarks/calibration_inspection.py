"""What a user's own calibration does to a gear's inspected quantities (twin): the inspection revolution of
``inspect_bench.py`` measured with the twin's true rig and with hand-placed calibrations of it, per ISO 1328-1 quantity.

    .venv/bin/python benchmarks/calibration_inspection.py [--seeds 51-55]        # ~5 min per rig on 2 cores

Per seed the twin's default rig is calibrated as a user would (the shipped board views placed by hand:
``calibration_accuracy.jittered_poses``; the product fit, which states its own uncertainty), written to a rig file, and
``inspect_bench.py --orientation normal --rig`` measures the same recording with it; once more with the true rig. The
differences from the true rig's inspection are the calibration's share of each quantity's error (the recording, decoder
and settings are the same). Nothing is chosen here. Writes ``benchmarks/calibration_inspection_report.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from calibration_accuracy import seed_list, write_hand_placed_rig

from gearscan.provenance import run_stamp

HERE = Path(__file__).resolve().parent
QUANTITIES = ("eccentricity", "fp", "Fp", "Fr", "F_alpha", "ff_alpha", "fH_alpha")  # um


def inspect_with(rig_path: Path | None, work: Path) -> dict:
    """``inspect_bench.py`` on its recording with ``rig_path`` (None: the twin's true rig); the quantities (um), the
    cloud's RMS (um) and coverage, the chip verdict."""
    cmd = [sys.executable, str(HERE / "inspect_bench.py"), "--orientation", "normal", "--out", str(work / "inspection"),
           "--report", str(work / "bench")]
    if rig_path is not None:
        cmd += ["--rig", str(rig_path)]
    subprocess.run(cmd, check=True, cwd=HERE.parent, stdout=subprocess.DEVNULL)
    rep = json.loads((work / "inspection" / "report.json").read_text())
    bench = json.loads((work / "bench.json").read_text())
    return {**{q: float("nan") if rep["summary_um"].get(q) is None else float(rep["summary_um"][q])
               for q in QUANTITIES if q != "eccentricity"},
            "eccentricity": float(rep["inspection"]["eccentricity_um"]), "cloud_rms_um": 1e3 * bench["fused_rms_mm"],
            "coverage": bench["coverage"], "chipped": bench["chipped"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=seed_list, default=list(range(51, 56)), help="e.g. 51-55")
    ap.add_argument("--work", type=Path, default=Path("out/calibration_inspection"))
    ap.add_argument("--report", type=Path, default=HERE / "calibration_inspection_report")
    args = ap.parse_args()
    work = args.work.resolve()  # the inspections run from the repository root
    stamp = run_stamp()
    truth = inspect_with(None, work / "truth")
    print("true rig:", truth, flush=True)
    runs = []
    for seed in args.seeds:
        path = work / f"rig_{seed}.json"
        cal = write_hand_placed_rig(seed, path)
        runs.append({"seed": seed, **cal, "inspection": inspect_with(path, work / f"seed_{seed}")})
        print(f"seed {seed}:", runs[-1], flush=True)
        (work / "progress.json").write_text(json.dumps({**stamp, "truth": truth, "runs": runs}, indent=1))
    keys = (*QUANTITIES, "cloud_rms_um")

    def cells(values: dict) -> str:
        return " | ".join(f"{values[q]:.2f}" for q in keys)

    delta = {q: np.array([r["inspection"][q] - truth[q] for r in runs]) for q in keys}
    lines = [
        "# What a user's calibration does to the inspected quantities (twin)",
        "",
        f"`python benchmarks/calibration_inspection.py --seeds {','.join(map(str, args.seeds))}` — commit "
        f"{stamp['commit']}{' + uncommitted edits' if stamp['uncommitted_edits'] else ''}, host: {stamp['host']}.",
        "",
        "The inspection revolution of `inspect_bench.py` (default rig, 20 teeth, module 2, 0.6 deg/frame, 200 bursts, "
        "eccentricity 50 um, tooth 3 +30 um, tooth 7 chipped; shipped v9, fringe orientation normal) measured with the "
        "twin's true rig and with the rig of each hand-placed calibration (the shipped board views, each seed's poses "
        "jittered as a hand places them; the product fit). The same recording, decoder and settings: a difference is "
        "the calibration's.",
        "",
        "| rig | cylinder radius / shape (um) | stated radius u (um) | eccentricity | fp | Fp | Fr | F_alpha | ff_alpha | "
        "fH_alpha | cloud RMS (um) | coverage | chip |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        f"| true rig | - | - | {cells(truth)} | {100 * truth['coverage']:.1f} % | "
        f"{truth['chipped']} |",
        *[f"| seed {r['seed']} | {r['cylinder']['radius_bias_um']:+.1f} / {r['cylinder']['shape_rms_um']:.1f} | "
          f"{r['stated_radius_um'] or float('nan'):.2f} | {cells(r['inspection'])} | "
          f"{100 * r['inspection']['coverage']:.1f} % | {r['inspection']['chipped']} |" for r in runs],
        f"| largest difference from the true rig | | | {cells({q: np.abs(d).max() for q, d in delta.items()})} | | |",
        f"| RMS difference | | | {cells({q: np.sqrt(np.mean(d**2)) for q, d in delta.items()})} | | |",
        "",
        "Quantities in um (ISO 1328-1: fp the largest single pitch deviation, Fp the total cumulative, Fr the ball-probe "
        "runout, F_alpha / ff_alpha / fH_alpha the worst flank's profile deviations).",
        "",
    ]
    args.report.with_suffix(".md").write_text("\n".join(lines))
    args.report.with_suffix(".json").write_text(json.dumps({**stamp, "seeds": args.seeds, "truth": truth, "runs": runs},
                                                           indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
