"""Measurement uncertainty by the substitution method, and whether it holds on gears it was not taken on.

A master gear with a certificate (the twin's truth) is measured ``--masters`` times, each a fresh mounting
(eccentricity turned, start angle and noise seed changed): ``gearscan verify`` turns the readings into each ISO
1328-1 quantity's bias, repeatability and expanded uncertainty U (:mod:`gearscan.recon.substitution`). Then
``--workpieces`` gears of the same type with OTHER known deviations are measured once each, and every reading is
checked against its truth: within U, or not. That check can fail; the statement is only worth what it passes.

    python benchmarks/substitution_bench.py [--masters 5] [--workpieces 3] [--report benchmarks/substitution_report]
        [--reports out/substitution] [--shading quadratic] [--again-from out/substitution]

Renders are cached under ``out/substitution/``, inspections under ``--reports`` (default the same; delete to redo;
another folder re-inspects the same renders, e.g. after a change to the measurement). Default rig, 512x512, z = 20,
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
    # rendered after the rule's amendment, for the bound method alone
    {"profile_slope_um": -10.0, "profile_crown_um": -2.0, "pitch_errors_um": {"6": 12.0},
     "eccentricity_um": 15.0, "eccentricity_deg": 120.0},
    {"profile_slope_um": 5.0, "profile_crown_um": 6.0, "pitch_errors_um": {"1": -15.0, "13": 20.0},
     "eccentricity_um": 30.0, "eccentricity_deg": 330.0},
    {"profile_slope_um": 0.0, "profile_crown_um": 3.0, "pitch_errors_um": {"9": -25.0},
     "eccentricity_um": 40.0, "eccentricity_deg": 75.0},
]


def mounting(i: int) -> dict:
    """The i-th mounting of the master: its eccentricity turned, as a re-clamped gear's would be."""
    return {"eccentricity_um": 20.0, "eccentricity_deg": (72.0 * i) % 360.0}


def measure(name: str, defects: dict, seed: int, start_deg: float, reports: Path = WORK, shading: str | None = None,
            again_from: Path | None = None) -> Path:
    """Render (cached) one revolution of a gear with ``defects`` and inspect it (cached, under ``reports``); the report
    folder. With ``again_from`` the inspection reads that folder's report of the gear again, without a replay."""
    from gearscan.inference.decoder import Decoder
    from gearscan.inspect import run_inspection
    from gearscan.recon.measure import network_support_option
    from gearscan.twin.defects import GearDefects
    from gearscan.twin.recordings import render_recording

    rec, out = WORK / f"rec_{name}", reports / f"report_{name}"
    if not (rec / "recording.json").exists():
        t = time.perf_counter()
        render_recording(rec, defects=GearDefects(**defects), motion="uniform:0.6", bursts=200, alternate_order=True,
                         seed=seed, start_deg=start_deg, overwrite=True)
        print(f"rendered {rec} in {time.perf_counter() - t:.0f} s", flush=True)
    if not (out / "report.json").exists() and again_from is not None:
        run_inspection(rec, out, from_report=again_from / f"report_{name}")
        print(f"inspected {again_from / f'report_{name}'} again in {out}", flush=True)
    if not (out / "report.json").exists():
        t = time.perf_counter()
        decoder = Decoder(None)  # the shipped network, as `gearscan inspect REC` decodes
        run_inspection(rec, out, decoder=decoder, network_support_px=network_support_option(
            None, frame_fit=True, model=decoder.network_support), shading=shading)
        print(f"inspected {rec} in {time.perf_counter() - t:.0f} s", flush=True)
    return out


def analyse(masters: list[Path], pieces: list[Path], report: Path, started: str, head: str) -> None:
    """Both methods of ``benchmarks/substitution_rule.md`` on the masters, every workpiece reading checked against its
    truth; writes ``report``.md/.json and the shipped method's statement ``uncertainty.json`` beside the inspections."""
    from gearscan.recon.inspect import iso1328_tolerances
    from gearscan.recon.substitution import (
        BUDGETED,
        TOLERANCE_KEY,
        error_functionals,
        quantity_uncertainty,
    )
    from gearscan.verify import read_report, twin_certificate, verify, write_statement

    def certificate(folder: Path):
        return twin_certificate(json.loads((WORK / folder.name.replace("report_", "rec_") / "recording.json").read_text()))

    certs = [certificate(m) for m in masters]
    if any(c != certs[0] for c in certs):
        raise SystemExit("the master's certificate differs between mountings: a bug in the twin or the certificate")
    cert = certs[0]
    alpha = math.radians(cert.gear.pressure_angle_deg)
    master_reads = [read_report(m) for m in masters]
    # 1. the rule as first written: ISO 15530-3's form on the headline readings, judged on workpieces 1-3
    certified = cert.headline_um()
    iso = {k: quantity_uncertainty(k, certified[k], 0.0, [r.headline[k] for r in master_reads]) for k in BUDGETED}
    # 2. the amendment: the bound method (what `gearscan verify` ships), judged on all six workpieces
    statement = verify(cert, masters)
    write_statement(statement, masters[0].parent / "uncertainty.json")
    shadings = sorted({str(json.loads((f / "report.json").read_text())["fused"].get("frame_fit_shading"))
                       for f in [*masters, *pieces]})
    datums = sorted({str(json.loads((f / "report.json").read_text())["inspection"]["settings"].get("datum"))
                     for f in [*masters, *pieces]})
    again = sorted({str(json.loads((f / "report.json").read_text()).get("fused_from")) for f in [*masters, *pieces]})
    tolerances = {g: iso1328_tolerances(2.0, 40.0, g) for g in (5, 6, 7, 8)}
    checks = []
    for j, p in enumerate(pieces):
        truth_cert = certificate(p)
        r = read_report(p)
        truth = truth_cert.headline_um(r.evaluation.xi_start, r.evaluation.xi_end, r.evaluation.bins)
        if any(r.headline[k] is None for k in BUDGETED) or r.flanks_of[0] < r.flanks_of[1]:
            raise SystemExit(f"{p}: measured on {r.flanks_of[0]} of {r.flanks_of[1]} flanks, headlines "
                             f"{r.headline}: the rule's checks need every quantity of the whole gear")
        own = error_functionals(r.flanks, r.positions_um, r.evaluation,
                                lambda side, xi, c=truth_cert: c.profile_um[side].offset(xi), truth_cert.positions_um,
                                alpha)
        for key in BUDGETED:
            err = abs(r.headline[key]) - abs(truth[key])  # fH_alpha judged by magnitude, the others are magnitudes
            checks.append({"workpiece": j + 1, "bins_left_out": r.bins_left_out, "quantity": key, "truth": truth[key], "reading": r.headline[key],
                           "error": err, "U_bound": statement.quantities[key].U,
                           "within_bound": abs(err) <= statement.quantities[key].U, "own_error_bound": own[key],
                           "U_iso": iso[key].U, "within_iso": abs(r.headline[key] - truth[key]) <= iso[key].U,
                           "judged_iso": j < 3})
    iso_checks = [c for c in checks if c["judged_iso"]]
    iso_misses = [c for c in iso_checks if not c["within_iso"]]
    misses = [c for c in checks if not c["within_bound"]]
    iso_verdict = "holds" if len(iso_misses) <= 1 else "does NOT hold"
    verdict = "holds" if not misses else "does NOT hold"
    md = [
        "# Measurement uncertainty from a master gear: stated on the master, tested on other gears", "",
        f"`python benchmarks/substitution_bench.py {' '.join(sys.argv[1:])}` ({len(masters)} masters, {len(pieces)} "
        f"workpieces) - commit {head}, "
        f"host: {started}. Rule and its amendment (both written before the analysis): `benchmarks/substitution_rule.md`.",
        "",
        "Gear type: z = 20, m = 2 mm, default rig 512 x 512, 0.6 deg/frame, 200 bursts, patterns alternating, the "
        f"shipped network, `gearscan inspect` defaults (frame fit on; its shading model: {', '.join(shadings)}; 'None': "
        "an inspection from before the report named it, the drift model; datum: "
        f"{', '.join(datums)}, 'None': the flank fit of before session 59; clouds inspected again from: "
        f"{', '.join(again)}). Master: slope +8, crown +4 um, tooth 5 +15 um, "
        f"measured {len(masters)} times, each remounted (eccentricity 20 um turned 72 deg, start angle +17 deg, new "
        "noise seed). Certificate: the twin's truth (U 0). Workpieces: other slopes, crowns, pitch errors and "
        "mountings, measured once each (the rule lists them; 4-6 rendered after the amendment).", "",
        f"## 1. The rule as first written: ISO 15530-3's form on the headlines (workpieces 1-3): "
        f"{len(iso_checks) - len(iso_misses)} of {len(iso_checks)} within U, the statement **{iso_verdict}**", "",
        "| quantity | certified | headline readings of the master | bias | u_p | k | U |", "|---|---|---|---|---|---|---|",
        *[f"| {k} | {q.certified:.2f} | {', '.join(f'{v:.1f}' for v in q.readings)} | {q.bias:+.2f} | {q.u_p:.2f} | "
          f"{q.k:.2f} | {q.U:.2f} |" for k, q in iso.items()], "",
        "## 2. The amendment's bound method (what `gearscan verify` ships)", "",
        "Per mounting the largest error each headline could take from the errors of the traces and positions read; "
        "U = mean + k s over the mountings (95 % of mountings at 95 % confidence) + the certificate's U (0 here).", "",
        "| quantity | error bound per mounting | mean | s | k | **U** | U / T class 5 / 6 / 7 / 8 |",
        "|---|---|---|---|---|---|---|",
        *[f"| {k} | {', '.join(f'{v:.2f}' for v in q.samples)} | {q.mean:.2f} | {q.s:.2f} | {q.k:.2f} | **{q.U:.2f}** | "
          + (" / ".join(f"{q.U / tolerances[g][TOLERANCE_KEY[k]]:.2f}" for g in (5, 6, 7, 8)) if k in TOLERANCE_KEY
             else "(not ISO's Fr)") + " |" for k, q in statement.quantities.items()], "",
        f"## Held-out workpieces: {len(checks) - len(misses)} of {len(checks)} headline readings within the bound "
        f"method's U: it **{verdict}**", "",
        "Error: |reading| - |truth| (fH_alpha by magnitude). The workpiece's own error bound is the same functional of "
        "its own traces' and positions' errors that U bounds on 95 % of mountings.", "",
        "| workpiece | quantity | truth | reading | error | U (bound) | within | own error bound | U (ISO form) | "
        "within (ISO form) |", "|---|---|---|---|---|---|---|---|---|---|",
        *[f"| {c['workpiece']} | {c['quantity']} | {c['truth']:.2f} | {c['reading']:.2f} | {c['error']:+.2f} | "
          f"{c['U_bound']:.2f} | {'yes' if c['within_bound'] else '**NO**'} | {c['own_error_bound']:.2f} | "
          f"{c['U_iso']:.2f} | {('yes' if c['within_iso'] else '**NO**') + ('' if c['judged_iso'] else ' (not judged)')} |"
          for c in checks], "",
        "Profile bins left out per workpiece (of 800): " + ", ".join(
            f"{c['workpiece']}: {c['bins_left_out']}" for c in checks if c["quantity"] == "fp") + "; every flank and "
        "tooth measured on each (checked). "
        f"Own error bounds above U: {sum(c['own_error_bound'] > c['U_bound'] for c in checks)} of {len(checks)}. "
        f"Largest |error| / U (bound method): {max(abs(c['error']) / c['U_bound'] for c in checks):.2f}.", ""]
    report.with_suffix(".md").write_text("\n".join(md))
    report.with_suffix(".json").write_text(json.dumps({
        "commit": head, "host": started, "python": platform.python_version(), "frame_fit_shading": shadings,
        "datum": datums, "fused_from": again,
        "masters": [str(m) for m in masters],
        "workpieces": [str(p) for p in pieces], "statement": statement.to_json(),
        "iso_form": {k: {"U": q.U, "bias": q.bias, "u_p": q.u_p, "k": q.k, "readings": list(q.readings)}
                     for k, q in iso.items()},
        "checks": checks, "iso_verdict": iso_verdict, "iso_misses": len(iso_misses), "verdict": verdict,
        "misses": len(misses)}, indent=2))
    print(f"ISO form: {len(iso_checks) - len(iso_misses)} of {len(iso_checks)} within U ({iso_verdict}); bound method: "
          f"{len(checks) - len(misses)} of {len(checks)} ({verdict}); {report}.md")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--masters", type=int, default=5)
    ap.add_argument("--workpieces", type=int, default=len(WORKPIECES))  # 1-3 judge the rule, 4-6 its amendment
    ap.add_argument("--measure-only", action="store_true", help="render and inspect; no analysis")
    ap.add_argument("--report", type=Path, default=None, help="report path without suffix (default "
                    "benchmarks/substitution_report; required with another --reports, so a re-inspection never "
                    "overwrites the committed report)")
    ap.add_argument("--reports", type=Path, default=WORK, help="where the inspections are cached (renders: out/substitution)")
    ap.add_argument("--shading", default=None, help="the frame fit's shading model (default: the product's)")
    ap.add_argument("--again-from", type=Path, default=None, help="inspect again, without a replay, the fused clouds of "
                    "this folder's inspections (e.g. after a change to the inspection alone); needs its own --reports")
    args = ap.parse_args()
    if args.shading is not None and args.reports == WORK:
        ap.error("--shading needs its own --reports folder (the cached inspections there used the product's model)")
    if args.again_from is not None and (args.reports == WORK or args.shading is not None):
        ap.error("--again-from needs its own --reports folder and no --shading (the clouds' frame fit has run)")
    if args.report is None:
        if args.reports != WORK:
            ap.error("--reports elsewhere needs its own --report (the default is the committed report)")
        args.report = HERE / "substitution_report"
    started, head = host(), commit()
    masters = [measure(f"master_{i}", MASTER | mounting(i), seed=100 + i, start_deg=17.0 * i, reports=args.reports,
                       shading=args.shading, again_from=args.again_from)
               for i in range(args.masters)]
    pieces = [measure(f"workpiece_{j}", WORKPIECES[j], seed=200 + j, start_deg=11.0 * j, reports=args.reports,
                      shading=args.shading, again_from=args.again_from)
              for j in range(args.workpieces)]
    if args.measure_only:
        return
    analyse(masters, pieces, args.report, started, head)


if __name__ == "__main__":
    main()
