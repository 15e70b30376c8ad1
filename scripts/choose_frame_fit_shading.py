"""Choose the frame fit's shading model on VAL stretches.

    python scripts/choose_frame_fit_shading.py [--out benchmarks/frame_fit_shading_val.json]

Rule, written before this ran: ``benchmarks/frame_fit_shading_rule.md``. The 16 cells of the settle rule
(``scripts/choose_frame_fit_settle.py``: four seeds, both pattern orders, two models), each replayed once at the path's
shipped settings; every candidate refits the same fused cloud and is scored against the twin's true surface as
``benchmarks/frame_fit_heldout.py`` scores, plus the error the profile reads: each flank's error against the true
surface averaged in the inspection's roll-length bins (:func:`flank_bin_error`). Cells already in ``--out`` are kept.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "scripts"))
from choose_frame_fit_settle import _KeepingRefiner, run_rule  # noqa: E402
from choose_fused_support import rest_scales  # noqa: E402
from frame_fit_heldout import score_fused, truth_scene  # noqa: E402

FIELD = "shading"
# "drift": the incumbent; "lambert": the irradiance model with samples lit at cos(incidence) >= 0.25 (the dev look's
# value on one substitution-benchmark master revolution, rule file)
CANDIDATES = ("drift", "lambert")
INCUMBENT = "drift"


def flank_bin_error(reader, points: np.ndarray, bins: int = 20, section: float = 0.6, min_points: int = 20) -> dict:
    """What a profile trace reads of the error: per flank, the points' signed distance to the true surface averaged in
    ``bins`` roll-length bins over the inspection's evaluation range (0.1-0.95 of the involute), in the mid-face
    ``section``; each flank's own mean removed (the trace's datum). The spread of those bin means (um) and the median
    and 95th percentile of their range per flank (flanks with at least half their bins)."""
    from gearscan.recon.deviation import SurfaceDistance
    from gearscan.recon.inspect import _flank_deviation
    from gearscan.twin.defects import GearDefects, true_mesh

    gear = reader.gear
    defects = GearDefects.from_meta(reader.meta)
    err = 1e3 * SurfaceDistance(true_mesh(gear, defects, flank_points=400)).distances(points)
    centre = defects.center if defects is not None else np.zeros(2)
    k, s, f, roll = _flank_deviation(points, np.array([*centre, 0.0]), gear)
    rb, ra = gear.base_radius, gear.tip_radius
    l0 = math.sqrt(max(max(rb, gear.root_radius) ** 2 - rb**2, 0.0))
    l1 = math.sqrt(ra**2 - rb**2)
    la, lb = l0 + 0.1 * (l1 - l0), l0 + 0.95 * (l1 - l0)
    band = (np.abs(points[:, 2]) <= 0.5 * section * gear.face_width) & (roll >= la) & (roll <= lb) & (np.abs(f) < 0.25 * gear.module)
    flank = (k[band] * 2 + (s[band] > 0)).astype(np.int64)
    b = np.clip(((roll[band] - la) / (lb - la) * bins).astype(np.int64), 0, bins - 1)
    key = flank * bins + b
    n = np.bincount(key, minlength=2 * gear.teeth * bins).reshape(-1, bins)
    total = np.bincount(key, err[band], minlength=2 * gear.teeth * bins).reshape(-1, bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n >= min_points, total / n, np.nan)
    mean = mean[np.isfinite(mean).sum(1) >= bins // 2]
    mean = mean - np.nanmean(mean, 1, keepdims=True)
    span = np.nanmax(mean, 1) - np.nanmin(mean, 1) if len(mean) else np.array([math.nan])
    return {"flank_bin_sd_um": float(np.nanstd(mean)) if len(mean) else math.nan, "flanks_binned": int(len(mean)),
            "flank_range_median_um": float(np.median(span)), "flank_range_p95_um": float(np.percentile(span, 95))}


def score_cell(rec: Path, decoder) -> list[dict]:
    """One replay of ``rec`` at the path's shipped settings, then a refit of its fused cloud per candidate."""
    from gearscan.core.recording import RecordingReader
    from gearscan.recon.fuse import CloudFuser
    from gearscan.replay import replay

    kept: list[_KeepingRefiner] = []

    def factory(rig, period_px, rest_sigma_scale):
        kept.append(_KeepingRefiner(rig, period_px, rest_sigma_scale=rest_sigma_scale))
        return kept[-1]

    m = replay(rec, decoder=decoder, fuse=CloudFuser(0.1, 3), truth=False, refine=True, refiner_factory=factory)
    ran = {"support_px_run": m.recon["network_support_px"], "max_sigma_rad_run": m.recon["max_sigma_rad"],
           "rest_sigma_scale_run": m.recon["rest_sigma_scale"]}
    refiner, reader = kept[0], RecordingReader(rec)
    scene = truth_scene(reader)
    rows = []
    for c in CANDIDATES:
        refiner.shading = c
        t = time.perf_counter()
        fused, stats = refiner.refine_fused(refiner.fused)
        seconds = time.perf_counter() - t
        rows.append({FIELD: c, **ran, **score_fused(reader, scene, fused, stats, seconds),
                     **flank_bin_error(reader, fused.points)})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "frame_fit_shading_val.json")
    ap.add_argument("--recordings", type=Path, default=ROOT / "out" / "fused_support_val")
    ap.add_argument("--bursts", type=int, default=60)
    args = ap.parse_args()

    from gearscan.recon.measure import FRAME_FIT_MAX_SIGMA_RAD, FRAME_FIT_NETWORK_SUPPORT_PX
    from gearscan.recon.track import (
        MIN_INCIDENCE_COS,
        MODULATION_RATIO,
        REST_SIGMA_SCALE,
        SETTLE_RAD,
        TrackRefiner,
    )

    settings = {"max_sigma_rad": FRAME_FIT_MAX_SIGMA_RAD, "rest_sigma_scale": REST_SIGMA_SCALE,
                "rest_sigma_scale_by_model": rest_scales(), "product_support_px": FRAME_FIT_NETWORK_SUPPORT_PX,
                "settle_rad": SETTLE_RAD, "modulation_ratio": MODULATION_RATIO, "min_incidence_cos": MIN_INCIDENCE_COS,
                "normal_radius_mm": TrackRefiner.__init__.__kwdefaults__["normal_radius_mm"]}
    done = run_rule(args.out, args.recordings, args.bursts, "benchmarks/frame_fit_shading_rule.md", FIELD, CANDIDATES,
                    None, settings, "flank_bin_sd_um", scorer=score_cell, incumbent=INCUMBENT, reference=INCUMBENT,
                    metric="flank_bin_sd_um")
    print(json.dumps(done["choice"], indent=1))


if __name__ == "__main__":
    main()
