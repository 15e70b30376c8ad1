"""Dev look: the profile error trace (read minus the master's true profile) per bin and flank side.

Reads the substitution benchmark's master reports (``out/substitution/``, made by ``benchmarks/substitution_bench.py``;
the certificate by ``gearscan twin certificate out/substitution/rec_master_0 -o out/substitution/cert_master.json``)
and prints the error's mean shape per side, its scatter per bin about that shape and its range per flank.

    python scripts/profile_error_look.py [--masters 5] [--reports out/substitution]
"""

from __future__ import annotations

import argparse

import numpy as np

from gearscan.verify import load_certificate, read_report

WORK = "out/substitution"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--masters", type=int, default=5)
    ap.add_argument("--reports", default=WORK, help="the inspections' folder (benchmarks/substitution_bench.py --reports)")
    args = ap.parse_args()
    cert = load_certificate(f"{WORK}/cert_master.json")
    rows: dict[str, list[np.ndarray]] = {"left": [], "right": []}
    for i in range(args.masters):
        r = read_report(f"{args.reports}/report_master_{i}")
        full = r.evaluation.centres_mm()
        for f in r.flanks:
            roll = np.asarray(f.roll_mm)
            err = np.asarray(f.trace_um) - cert.profile_um[f.side].offset(r.evaluation.xi(roll))
            per_bin = np.full(len(full), np.nan)
            per_bin[np.searchsorted(full, roll - 1e-9)] = err - np.nanmean(err)  # the datum's constant out
            rows[f.side].append(per_bin)
    for side, traces in rows.items():
        e = np.array(traces)
        shape = np.nanmean(e, 0)
        spread = np.nanstd(e, 0)
        span = np.nanmax(e, 1) - np.nanmin(e, 1)
        span_res = np.nanmax(e - shape, 1) - np.nanmin(e - shape, 1)
        print(f"{side}: {len(e)} flanks")
        print(f"  mean error per bin (um): {np.round(shape, 1)}")
        print(f"  scatter per bin (um):    {np.round(spread, 1)}")
        print(f"  range per flank: median {np.median(span):.1f}, p95 {np.percentile(span, 95):.1f}; without the side's "
              f"mean shape: median {np.median(span_res):.1f}, p95 {np.percentile(span_res, 95):.1f}")


if __name__ == "__main__":
    main()
