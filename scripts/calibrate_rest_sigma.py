"""Calibrate the sigma of the fused points the frame fit cannot take, on VAL stretches.

    python scripts/calibrate_rest_sigma.py [--out benchmarks/rest_sigma_val.json]

Rule, written before this ran: ``benchmarks/rest_sigma_rule.md``. The 8 val cells of
``scripts/choose_fused_support.py`` (two seeds, both pattern orders, the shipped model and the default-rig option),
each replayed with fusion and the frame-fit path's fringe-support test; the frame fit then runs on the fused cloud
and, for the points it cannot take that the off-surface test keeps (before the sigma bound), their distance to the
true surface and their sigma without credit for averaging (sigma * sqrt(bursts)). The scale (amended rule): the
smallest c in steps of 0.5 from 1 for which, in every cell, the points that c * sigma keeps under the 30 um bound have
a median |error| / (c * sigma) of at most 0.6745. Each cell's arrays are kept in ``--recordings`` (``rest_*.npz``).
Since rerun 6 (the rule's per-model amendment) the scale is chosen per model on its own cells: the shipped model's is
the product's (``recon.track.REST_SIGMA_SCALE``), the option's goes into its JSON (``rest_sigma``) with ``--write``.
Each cell records the decode it ran (``model_fingerprint``): a resume with another decode of a model (or with cells
that recorded none) is refused, and
``--write`` stamps the option's scale with the decode its cells ran, refusing cells of another (or of none recorded,
as before session 55: rerun them into a new ``--out``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "scripts"))
from choose_fused_support import load_or_start, val_cells  # noqa: E402  (the same val cells)

HONEST_MEDIAN_Z = 0.6745  # median |e| / sigma of a Gaussian error with that sigma
HONEST_BEYOND_2 = 0.0455  # ... and its share beyond 2 sigma (the amendment of session 50: the tail too)


def rest_z(rec: Path, decoder, keep: Path) -> dict:
    """Replay ``rec`` fused, fit, and return the unfitted on-surface points' z and errors (arrays saved in ``keep``)."""
    import open3d as o3d

    from gearscan.core.recording import RecordingReader
    from gearscan.recon.fuse import CloudFuser
    from gearscan.recon.measure import keep_bound_option, network_support_option
    from gearscan.recon.track import TrackRefiner
    from gearscan.replay import recording_rig, replay
    from gearscan.twin.defects import GearDefects, true_mesh

    reader = RecordingReader(rec)
    refiner = TrackRefiner(recording_rig(reader, None), reader.patterns.periods[0], rest_sigma_scale=1.0)  # unscaled
    m = replay(rec, decoder=decoder, fuse=CloudFuser(0.1, 3), truth=False, refine=False,
               network_support_px=network_support_option(None, frame_fit=True,  # as `inspect` runs this model
                                                         model=getattr(decoder, "network_support", None)),
               max_sigma=keep_bound_option(None, frame_fit=True), on_burst=lambda meas, row: refiner.add(meas))
    fused = m.fused
    fit, off, _ = refiner.fit_fused(fused)  # the product's fit, before its bound drops anything
    r = fit.refined
    rest = ~r & ~off
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(true_mesh(reader.gear, GearDefects.from_meta(reader.meta))))
    err = np.abs(scene.compute_signed_distance(o3d.core.Tensor(fused.points[rest].astype(np.float32))).numpy())
    sigma = fit.sigma[rest]  # the bursts' sigma without credit for averaging (scale 1)
    z = err / sigma
    np.savez(keep, error_mm=err, sigma_mm=sigma)
    return {"points": len(fused), "fitted": int(r.sum()), "rest": int(rest.sum()),
            "rest_rms_um": float(1e3 * np.sqrt(np.mean(err**2))) if err.size else None,
            "median_z": float(np.median(z)) if z.size else None,
            "z_quantiles": {q: float(np.quantile(z, q / 100)) for q in (25, 75, 90, 95)} if z.size else {},
            "median_sigma_um": float(1e3 * np.median(sigma)) if sigma.size else None}


def at_scale(arrays: list, c: float, bound_mm: float) -> list[dict]:
    """Per cell (``rest_z``'s saved arrays): the unfitted points ``c * sigma`` keeps under ``bound_mm``, their median z,
    share beyond 2 sigma and RMS (None where none is kept)."""
    per_cell = []
    for a in arrays:
        sig = c * a["sigma_mm"]
        kept = sig <= bound_mm
        z = a["error_mm"][kept] / sig[kept]
        per_cell.append({"kept": int(kept.sum()), "median_z": float(np.median(z)) if z.size else None,
                         "beyond_2sigma": float(np.mean(z > 2)) if z.size else None,
                         "kept_rms_um": float(1e3 * np.sqrt(np.mean(a["error_mm"][kept] ** 2))) if z.size else None})
    return per_cell


def honest(per_cell: list[dict]) -> bool:
    """The rule at one scale: every cell's kept points honest in body and tail (the amendment of session 50,
    rest_sigma_rule.md, "Rerun 2 and an amendment"); a cell with none kept passes."""
    return all(p["median_z"] is None or (p["median_z"] <= HONEST_MEDIAN_Z and p["beyond_2sigma"] <= HONEST_BEYOND_2)
               for p in per_cell)


def depth_scales_read() -> dict[str, dict[str, list[float]]]:
    """The per-burst depth-sigma scales the cells' reconstructors read: the product's (the shipped model's cells) and
    the default-rig option's own (its JSON), as ``{class: scales}``."""
    from gearscan.inference.model_io import read_config
    from gearscan.inference.predictor import model_depth_sigma_scales
    from gearscan.recon.depth_sigma import DEPTH_SIGMA_SCALES, run_depth_sigma_scales

    option = model_depth_sigma_scales(read_config(ROOT / "inference" / "weights" / "default_rig.safetensors"))
    return {"depth_sigma_scales": DEPTH_SIGMA_SCALES.as_dict(),
            "option_depth_sigma_scales": (run_depth_sigma_scales(option, network=True) or DEPTH_SIGMA_SCALES).as_dict()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "rest_sigma_val.json")
    ap.add_argument("--recordings", type=Path, default=ROOT / "out" / "fused_support_val")
    ap.add_argument("--bursts", type=int, default=60)
    ap.add_argument("--write", action="store_true",
                    help="store the default-rig option's own scale in its JSON (rest_sigma) with the decode it was chosen for")
    args = ap.parse_args()

    done = load_or_start(args.out)  # refuses a json scored with other shipped weights
    scales = depth_scales_read()
    if done["cells"] and {k: done.get(k) for k in scales} != scales:  # the cells' unfitted sigma reads them
        raise SystemExit(f"{args.out}: its cells were scored with other depth-sigma scales "
                         f"({ {k: done.get(k) for k in scales} }, now {scales}); write to another --out")
    done |= scales  # the product's, which its v9 cells read, and the option's own (before any cell is written)
    cells = done["cells"]
    for model, decoder, seed, order, rec in val_cells(args.recordings, args.bursts):
        fingerprint = decoder.model_fingerprint  # the decode this cell is scored with (None: none recorded before)
        stale = [c for c in cells if c["model"] == model and c.get("model_fingerprint") != fingerprint]
        if stale:  # another decode, or none recorded (cells from before session 55): not resumed into
            raise SystemExit(f"{args.out}: the {model}'s cells were scored with another decode "
                             f"({stale[0].get('model_fingerprint', 'not recorded')}, now {fingerprint}); write to another "
                             "--out")
        if any((c["model"], c["seed"], c["order"]) == (model, seed, order) for c in cells):
            continue
        short = model.split()[0] if model.endswith("(shipped)") else "default_rig"  # v6 / v9 / the option
        keep = args.recordings / f"rest_{short}_{seed}_{order}.npz"
        cells.append({"model": model, "model_fingerprint": fingerprint, "seed": seed, "order": order,
                      "arrays": str(keep.resolve()), **rest_z(rec, decoder, keep)})
        print({k: cells[-1][k] for k in ("model", "seed", "order", "rest", "rest_rms_um", "median_z")}, flush=True)
        args.out.write_text(json.dumps(done, indent=1))
    medians = [c["median_z"] for c in cells if c["median_z"] is not None]  # a cell with no unfitted point has none
    done["worst_median_z_before_the_bound"] = max(medians, default=0.0)  # the rule's first form
    done["scale_first_form"] = max(1.0, math.ceil(2 * done["worst_median_z_before_the_bound"] / HONEST_MEDIAN_Z) / 2)
    from gearscan.recon.track import TrackRefiner

    bound = TrackRefiner.__init__.__kwdefaults__["max_sigma_mm"]  # the bound every point of the refined cloud meets
    arrays = [np.load(ROOT / c["arrays"]) for c in cells]  # relative paths in runs before this form: under ROOT
    done["scan"], done["scale_all_cells"] = scan(arrays, bound)  # every cell together: the rule's form until rerun 5
    # the per-model amendment (rerun 6): each model's scale on its own cells; the shipped model's is the product's
    done["scale_by_model"] = {}
    for model in dict.fromkeys(c["model"] for c in cells):
        own = [a for a, c in zip(arrays, cells, strict=True) if c["model"] == model]
        rows, c = scan(own, bound)
        done["scale_by_model"][model] = {"scale": c, "keeps_no_unfitted_point": keeps_none(rows), "scan": rows}
    shipped = next(m for m in done["scale_by_model"] if m.endswith("(shipped)"))
    done["scale"] = done["scale_by_model"][shipped]["scale"]  # the product's (recon.track.REST_SIGMA_SCALE)
    # said apart: a scale that passes because no unfitted point is left drops them all, it does not calibrate them
    done["scale_keeps_no_unfitted_point"] = done["scale_by_model"][shipped]["keeps_no_unfitted_point"]
    args.out.write_text(json.dumps(done, indent=1))
    for model, row in done["scale_by_model"].items():
        print(f"{model}: scale {row['scale']}; keeps no unfitted point on val: {row['keeps_no_unfitted_point']}")
    print(f"every cell together (the rule's form until rerun 5): {done['scale_all_cells']} (first form "
          f"{done['scale_first_form']})")
    if args.write:
        write_option_scale(done, args.out)


def scan(arrays: list, bound: float) -> tuple[list[dict], float | None]:
    """The scale rows from 1 in steps of 0.5 up to the first honest one (:func:`honest`), and that scale."""
    rows = []
    for c in np.arange(1.0, 20.5, 0.5):
        per_cell = at_scale(arrays, float(c), bound)
        rows.append({"scale": float(c), "cells": per_cell})
        if honest(per_cell):
            return rows, float(c)
    return rows, None


def keeps_none(rows: list[dict]) -> bool:
    """Whether the chosen (last) row passed only because it kept no unfitted point in any cell."""
    return bool(rows) and all(p["median_z"] is None for p in rows[-1]["cells"])


def write_option_scale(done: dict, out: Path) -> None:
    """The option's own scale into its JSON (``rest_sigma``), with the decode its cells were scored on."""
    from gearscan.inference.model_io import model_fingerprint, read_config, write_config

    weights = ROOT / "inference" / "weights" / "default_rig.safetensors"
    row = done["scale_by_model"].get("default-rig option")
    if row is None or row["scale"] is None:
        raise SystemExit(f"{out}: no scale for the default-rig option's cells; nothing written")
    now = model_fingerprint(weights)
    scored = {c.get("model_fingerprint") for c in done["cells"] if c["model"] == "default-rig option"}
    if scored != {now}:  # the scale is stamped with the decode its cells ran, never with whatever is there at write time
        raise SystemExit(f"{out}: the default-rig option's cells were scored with decode(s) {sorted(map(str, scored))}, "
                         f"the option is now {now}; rerun its cells (another --out) before --write; nothing written")
    meta = read_config(weights)
    meta["rest_sigma"] = {"scale": row["scale"], "model_fingerprint": now,
                          "chosen_by": f"benchmarks/rest_sigma_rule.md (rerun 6, the per-model amendment), "
                                       f"{out.relative_to(ROOT) if out.is_relative_to(ROOT) else out}: the option's "
                                       "four val cells"}
    print(f"wrote rest_sigma {row['scale']} to {write_config(weights, meta)}")


if __name__ == "__main__":
    main()
