"""Measurement uncertainty by the substitution method, and whether it holds on gears it was not taken on.

A master gear with a certificate (the twin's truth) is measured ``--masters`` times, each a fresh mounting
(eccentricity turned, start angle and noise seed changed): ``gearscan verify`` turns the readings into each ISO
1328-1 quantity's bias, repeatability and expanded uncertainty U (:mod:`gearscan.recon.substitution`). Then
``--workpieces`` gears of the same type with OTHER known deviations are measured once each, and every reading is
checked against its truth: within U, or not. That check can fail; the statement is only worth what it passes.

    python benchmarks/substitution_bench.py [--masters 5] [--workpieces 3] [--report benchmarks/substitution_report]

Renders and inspections are cached under ``out/substitution/`` (delete to redo). Default rig, 512x512, z = 20,
m = 2 mm, 0.6 deg/frame (200 bursts, one revolution), patterns in alternating order, the shipped network.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from inspect_bench import commit, host  # noqa: E402

WORK = Path("out/substitution")
MASTER = {"profile_slope_um": 8.0, "profile_crown_um": 4.0, "pitch_errors_um": {"5": 15.0}}
WORKPIECES = [  # other deviations of the same gear type: none of them is the master's
    {"profile_slope_um": -6.0, "profile_crown_um": 2.0, "pitch_errors_um": {"2": 20.0, "11": -10.0},
     "eccentricity_um": 35.0, "eccentricity_deg": 40.0},
    {"profile_slope_um": 3.0, "profile_crown_um": -3.0, "pitch_errors_um": {"8": 25.0},
     "eccentricity_um": 10.0, "eccentricity_deg": 200.0},
    {"profile_slope_um": 12.0, "profile_crown_um": 0.0, "pitch_errors_um": {"15": -18.0, "16": 12.0},
     "eccentricity_um": 25.0, "eccentricity_deg": 290.0},
]


def mounting(i: int) -> dict:
    """The i-th mounting of the master: its eccentricity turned, as a re-clamped gear's would be."""
    return {"eccentricity_um": 20.0, "eccentricity_deg": (72.0 * i) % 360.0}


def measure(name: str, defects: dict, seed: int, start_deg: float) -> Path:
    """Render (cached) one revolution of a gear with ``defects`` and inspect it (cached); the report folder."""
    from gearscan.inference.decoder import Decoder
    from gearscan.inspect import run_inspection
    from gearscan.recon.measure import network_support_option
    from gearscan.twin.defects import GearDefects
    from gearscan.twin.recordings import render_recording

    rec, out = WORK / f"rec_{name}", WORK / f"report_{name}"
    if not (rec / "recording.json").exists():
        t = time.perf_counter()
        render_recording(rec, defects=GearDefects(**defects), motion="uniform:0.6", bursts=200, alternate_order=True,
                         seed=seed, start_deg=start_deg, overwrite=True)
        print(f"rendered {rec} in {time.perf_counter() - t:.0f} s", flush=True)
    if not (out / "report.json").exists():
        t = time.perf_counter()
        decoder = Decoder(None)  # the shipped network, as `gearscan inspect REC` decodes
        run_inspection(rec, out, decoder=decoder, network_support_px=network_support_option(
            None, frame_fit=True, model=decoder.network_support))
        print(f"inspected {rec} in {time.perf_counter() - t:.0f} s", flush=True)
    return out


def analyse(masters: list[Path], pieces: list[Path], report: Path, started: str, head: str) -> None:
    """The statement from the masters, and every workpiece reading checked against its truth (the rule:
    ``benchmarks/substitution_rule.md``); writes ``report``.md/.json and ``out/substitution/uncertainty.json``."""
    from gearscan.core.recording import RecordingReader
    from gearscan.recon.inspect import iso1328_tolerances
    from gearscan.recon.substitution import QUANTITIES, TOLERANCE_KEY
    from gearscan.verify import report_readings, twin_certificate, verify, write_statement

    def certificate(folder: Path):
        return twin_certificate(RecordingReader(WORK / folder.name.replace("report_", "rec_")).meta)

    certs = [certificate(m) for m in masters]
    if any(c.quantities_um != certs[0].quantities_um for c in certs):
        raise SystemExit("the master's certificate differs between mountings: a bug in the twin or the certificate")
    statement = verify(certs[0], masters)
    write_statement(statement, WORK / "uncertainty.json")
    tolerances = {g: iso1328_tolerances(2.0, 40.0, g) for g in (5, 6, 7, 8)}
    checks = []
    for p in pieces:
        truth = {k: v.value for k, v in certificate(p).quantities_um.items()}
        readings, rep = report_readings(p)
        for key, q in statement.quantities.items():
            err = readings[key] - truth[key]
            no_bias = q.k * math.sqrt(q.u_cal**2 + q.u_p**2 + q.u_w**2)
            checks.append({"workpiece": p.name, "quantity": key, "truth": truth[key], "reading": readings[key],
                           "error": err, "U": q.U, "within": abs(err) <= q.U, "U_without_bias": no_bias,
                           "within_without_bias": abs(err) <= no_bias})
    misses = [c for c in checks if not c["within"]]
    verdict = "holds" if len(misses) <= 1 else "does NOT hold"
    md = [
        "# Measurement uncertainty by the substitution method: stated on a master, tested on other gears", "",
        f"`python benchmarks/substitution_bench.py --masters {len(masters)} --workpieces {len(pieces)}` - commit {head}, "
        f"host: {started}. Rule (written before the analysis): `benchmarks/substitution_rule.md`.", "",
        "Gear type: z = 20, m = 2 mm, default rig 512 x 512, 0.6 deg/frame, 200 bursts, patterns alternating, the "
        "shipped network, `gearscan inspect` defaults (frame fit on). Master: slope +8, crown +4 um, tooth 5 +15 um, "
        f"measured {len(masters)} times, each remounted (eccentricity 20 um turned 72 deg, start angle +17 deg, new "
        "noise seed). Certificate: the twin's truth (U 0).", "",
        "## The statement (`gearscan verify`)", "",
        "| quantity | certified | readings | mean | bias | u_p | dof | k | **U** | U / T class 5 / 6 / 7 / 8 |",
        "|---|---|---|---|---|---|---|---|---|---|",
        *[f"| {k} | {q.certified:.2f} | {', '.join(f'{v:.1f}' for v in q.readings)} | {q.mean:.2f} | {q.bias:+.2f} | "
          f"{q.u_p:.2f} | {q.dof:.0f} | {q.k:.2f} | **{q.U:.2f}** | "
          + " / ".join(f"{q.U / tolerances[g][TOLERANCE_KEY[k]]:.2f}" for g in (5, 6, 7, 8)) + " |"
          for k, q in statement.quantities.items()], "",
        f"## Held-out workpieces: reading - truth against U ({len(checks) - len(misses)} of {len(checks)} within: "
        f"the statement **{verdict}**)", "",
        "| workpiece | quantity | truth | reading | error | U | within | U without the bias | within |",
        "|---|---|---|---|---|---|---|---|---|",
        *[f"| {c['workpiece'].replace('report_', '')} | {c['quantity']} | {c['truth']:.2f} | {c['reading']:.2f} | "
          f"{c['error']:+.2f} | {c['U']:.2f} | {'yes' if c['within'] else '**NO**'} | {c['U_without_bias']:.2f} | "
          f"{'yes' if c['within_without_bias'] else 'no'} |" for c in checks], "",
        f"Without the bias term {sum(c['within_without_bias'] for c in checks)} of {len(checks)} would be within.", ""]
    report.with_suffix(".md").write_text("\n".join(md))
    report.with_suffix(".json").write_text(json.dumps({
        "commit": head, "host": started, "python": platform.python_version(), "masters": [str(m) for m in masters],
        "workpieces": [str(p) for p in pieces], "statement": statement.to_json(), "checks": checks,
        "misses": len(misses), "verdict": verdict, "quantities": list(QUANTITIES)}, indent=2))
    print(f"{len(checks) - len(misses)} of {len(checks)} within U: the statement {verdict}; {report}.md")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--masters", type=int, default=5)
    ap.add_argument("--workpieces", type=int, default=len(WORKPIECES))
    ap.add_argument("--measure-only", action="store_true", help="render and inspect; no analysis")
    ap.add_argument("--report", type=Path, default=HERE / "substitution_report")
    args = ap.parse_args()
    started, head = host(), commit()
    masters = [measure(f"master_{i}", MASTER | mounting(i), seed=100 + i, start_deg=17.0 * i) for i in range(args.masters)]
    pieces = [measure(f"workpiece_{j}", WORKPIECES[j], seed=200 + j, start_deg=11.0 * j)
              for j in range(args.workpieces)]
    if args.measure_only:
        return
    analyse(masters, pieces, args.report, started, head)


if __name__ == "__main__":
    main()
