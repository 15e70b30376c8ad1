"""Dev look behind ``benchmarks/mixed_shading_rule.md``: the drift and the quadratic frame fit on one substitution
recording, combined per point at several sigma ratios R, each combination inspected and held to the twin's truth.

    python scripts/mixed_shading_look.py master_0 [--ratios 1,1.25,1.5,2,1e9] [--work out/mixed_look]

Replays ``out/substitution/rec_NAME`` once as ``gearscan inspect`` does (the shipped network, the drift fit), runs both
fits to convergence on its fused cloud (kept in ``WORK/fits_NAME.pkl``; a second call reuses it), then for each R takes
a point's quadratic fit where its sigma is at most R times drift's (or drift did not fit it), else drift's, drops what
the product drops, inspects the cloud (``run_inspection(from_report=...)``) and prints the per-mounting error bounds
that the substitution statement's U is built from (``recon.substitution.error_functionals``), um.
"""

from __future__ import annotations

import argparse
import json
import pickle
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def fits(rec: Path, work: Path, name: str) -> tuple[dict, Path]:
    """The fused cloud and both fits' per-point results (cached), and the product's report of the recording."""
    from gearscan.inference.decoder import Decoder
    from gearscan.inspect import run_inspection
    from gearscan.recon import track
    from gearscan.recon.measure import network_support_option

    dump, base = work / f"fits_{name}.pkl", work / f"drift_{name}"
    if dump.exists() and (base / "report.json").exists():
        return pickle.loads(dump.read_bytes()), base
    product = track.TrackRefiner.refine_fused

    def both_then_product(self, fused):
        res = {}
        for degree, shading in ((1, "drift"), (2, "quadratic")):
            self.shading = shading
            res[degree] = self.refine(fused.points)
        self.shading = "drift"
        dump.write_bytes(pickle.dumps({"fused": fused, "fits": res, "max_sigma_mm": self.max_sigma_mm,
                                       "rest_sigma_scale": self.rest_sigma_scale}))
        return product(self, fused)

    track.TrackRefiner.refine_fused = both_then_product
    try:
        decoder = Decoder(None)
        run_inspection(rec, base, decoder=decoder, network_support_px=network_support_option(
            None, frame_fit=True, model=decoder.network_support), shading="drift")
    finally:
        track.TrackRefiner.refine_fused = product
    return pickle.loads(dump.read_bytes()), base


def combined(d: dict, ratio: float, rig, period_px: float):
    """The fused cloud with each point from the quadratic fit where its sigma <= ratio x drift's, else drift's, through
    the product's ``TrackRefiner.refine_fused`` (its sigma for the rest, its drops); and the counts."""
    from gearscan.recon.track import TrackRefiner, TrackResult

    r1, r2 = d["fits"][1], d["fits"][2]
    with np.errstate(invalid="ignore"):
        quad = r2.refined & (~r1.refined | (r2.sigma <= ratio * r1.sigma))
    pick = lambda a, b: np.where(quad.reshape(-1, *[1] * (a.ndim - 1)), b, a)  # noqa: E731
    fit = TrackResult(pick(r1.points, r2.points), pick(r1.sigma, r2.sigma), r1.refined | quad,
                      pick(r1.frames, r2.frames), pick(r1.moved_mm, r2.moved_mm), pick(r1.rays, r2.rays), {})
    refiner = TrackRefiner(rig, period_px, rest_sigma_scale=d["rest_sigma_scale"], max_sigma_mm=d["max_sigma_mm"])
    cloud, _ = refiner.refine_fused(d["fused"], fit)
    return cloud, {"quadratic": int(quad.sum()), "drift": int((r1.refined & ~quad).sum())}


def bounds(report: Path, rec: Path) -> dict:
    """The inspection's per-mounting error bounds against the twin's certificate, um."""
    import math

    from gearscan.recon.substitution import error_functionals
    from gearscan.verify import read_report, twin_certificate

    r = read_report(report)
    cert = twin_certificate(json.loads((rec / "recording.json").read_text()))
    return error_functionals(r.flanks, r.positions_um, r.evaluation, lambda s, xi: cert.profile_um[s].offset(xi),
                             cert.positions_um, math.radians(cert.gear.pressure_angle_deg))


def main() -> None:
    from gearscan.inspect import run_inspection
    from gearscan.recon.fuse import save_fused

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("name", help="a substitution recording: master_0 ... workpiece_5")
    ap.add_argument("--ratios", default="1,1.25,1.5,2,1e9")
    ap.add_argument("--work", type=Path, default=ROOT / "out" / "mixed_look")
    ap.add_argument("--renders", type=Path, default=ROOT / "out" / "substitution")
    args = ap.parse_args()
    rec = args.renders / f"rec_{args.name}"
    if not (rec / "recording.json").exists():
        raise SystemExit(f"{rec}: no recording (render it: python benchmarks/substitution_bench.py --measure-only)")
    args.work.mkdir(parents=True, exist_ok=True)
    from gearscan.core.recording import RecordingReader

    d, base = fits(rec, args.work, args.name)
    reader = RecordingReader(rec)
    print(f"{args.name} drift (product): { {k: round(v, 2) for k, v in bounds(base, rec).items()} }")
    for ratio in (float(x) for x in args.ratios.split(",")):
        cloud, counts = combined(d, ratio, reader.rig, reader.patterns.periods[0])
        src, out = args.work / f"src_{args.name}_R{ratio:g}", args.work / f"comb_{args.name}_R{ratio:g}"
        for folder in (src, out):
            shutil.rmtree(folder, ignore_errors=True)
        shutil.copytree(base, src)  # the product's report with the combined cloud: what --from-report reads
        save_fused(cloud, src / "fused.ply")
        meta = json.loads((src / "report.json").read_text())
        meta["fused"]["points"] = len(cloud)
        (src / "report.json").write_text(json.dumps(meta))
        run_inspection(rec, out, from_report=src)
        share = counts["quadratic"] / max(counts["quadratic"] + counts["drift"], 1)
        print(f"{args.name} R={ratio:g} ({share:.0%} of the fitted points quadratic): "
              f"{ {k: round(v, 2) for k, v in bounds(out, rec).items()} }")


if __name__ == "__main__":
    main()
