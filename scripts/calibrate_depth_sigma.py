"""Calibrate the per-burst depth sigma by distance to the cloud's edge and motion class, on VAL (benchmarks/depth_sigma_rule.md).

    python scripts/calibrate_depth_sigma.py [--out benchmarks/depth_sigma_val.json] [--fit-seed 2000] [--check-seed 2800] [--per-motion 5]

The val scenes of the reconstruction's per-burst choices (``evaluate.VAL_CLOUD_SETS``), one burst per motion of
``VAL_MOTIONS["wide"]`` (``--per-motion``: 5 since the fifth amendment), decoded as the app decodes them (a burst spanning less than the decoder's still span by
three-step PS, the rest by the shipped network, deterministic, the twin rigs' orientation, its still-burst gate on)
through the product's reconstructor with the raw propagated sigma (all scales 1). Per point |depth error along its
ray| / sigma (``evaluate.depth_z``), its band, its burst's motion class (``recon.depth_sigma.motion_class``) and its
val family (the twin's radial set, its any-view set, the default rig's gears). Per class and band the scale is the
largest need of the families (the rule's fourth and fifth amendments). The scales come from the fit seed set, the check from the
other (every family's cell judged); z scales as 1 / s, so both read one raw pass each.
Writes the choice and both tables (and the check per motion) to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
CHECK_BEYOND_2 = 0.055  # the check's bound on the share beyond 2 sigma per (band, class) cell
CHECK_MIN_POINTS = 1000  # smaller cells are reported, not judged


def collect(seed: int, motions: str, per_motion: int, model: Path | None = None,
            sets: tuple[str, ...] | None = None, mc: int = 0) -> dict[tuple[str, int, str, str], np.ndarray]:
    """z = |depth error along the ray| / raw sigma per (motion class, band, motion, val folder), over the val scenes
    rendered from ``seed`` (scene i from ``seed + i``, in the order of ``sets``); ``mc`` > 0: the network's bursts
    decoded in Monte Carlo mode with that many passes (the dropout masks seeded, torch seed 0, at the start)."""
    import torch

    from gearscan.core.phase import still_result
    from gearscan.core.types import Burst, Frame
    from gearscan.evaluate import (
        VAL_CLOUD_SETS,
        VAL_MOTIONS,
        depth_z,
        render_cases,
        scenes_from_dataset,
    )
    from gearscan.inference.decoder import STILL_SPAN_DEG, turned_less_than
    from gearscan.inference.predictor import Predictor
    from gearscan.recon.depth_sigma import NO_SCALES, band_index, edge_distance, motion_class
    from gearscan.recon.measure import Reconstructor

    predictor = Predictor.load(model, orientation="normal")  # every twin rig is normal by its geometry
    torch.manual_seed(0)
    scenes = [(root, s) for root in (sets or VAL_CLOUD_SETS) for s in scenes_from_dataset(ROOT / root)]
    zs: dict[tuple[str, int, str, str], list[np.ndarray]] = {}
    for i, (root, scene) in enumerate(scenes):
        rc = Reconstructor.for_gear(scene.rig, scene.period_px, scene.gear, depth_sigma_scales=NO_SCALES)
        try:
            for case in render_cases(scene, VAL_MOTIONS[motions], per_motion, seed=seed + i):
                fr = tuple(Frame(f, j, 0, j, bit_depth=int(case.full_scale).bit_length())
                           for j, f in enumerate(case.frames))
                burst = Burst(fr, tuple(math.radians(a) for a in case.angles_deg))
                if turned_less_than(burst.angles, STILL_SPAN_DEG):  # as inference.decoder.Decoder routes it
                    result = still_result(burst)
                else:
                    result = replace(predictor.predict(case.frames, mc, full_scale=case.full_scale),
                                     angle=burst.angles[0])
                m = rc(burst, result)
                if m.cloud is None or not len(m.cloud):
                    continue
                z = depth_z(scene.cad[1], scene.rig, burst.angles[0], m.cloud.points, m.cloud.sigma)
                keep = np.zeros(case.truth.mask.shape, bool)
                keep[m.cloud.pixels[:, 0], m.cloud.pixels[:, 1]] = True
                band = band_index(edge_distance(keep)[m.cloud.pixels[:, 0], m.cloud.pixels[:, 1]])
                cls = motion_class(burst.angles, result.from_network)
                ok = np.isfinite(z)
                for b in np.unique(band):
                    zs.setdefault((cls, int(b), case.motion, root), []).append(z[ok & (band == b)])
        finally:
            rc.close()
        print(f"seed {seed}: {i + 1}/{len(scenes)} {scene.name}", flush=True)
    return {k: np.concatenate(v) for k, v in zs.items()}


Zs = dict[tuple[str, int, str, str], np.ndarray]  # (motion class, band, motion, val folder) -> z


def family(root: str) -> str:
    """The val family of a val folder (the fourth amendment): the default rig's gears, or the twin's set by name."""
    return "default_rig" if root.startswith("data/default_rig/") else root.rstrip("/").split("/")[-1]


def _pool(zs: Zs, key) -> dict:
    """The z of ``zs`` pooled by ``key(cls, band, motion, root)``."""
    groups: dict = {}
    for k, z in zs.items():
        groups.setdefault(key(*k), []).append(z)
    return {k: np.concatenate(v) for k, v in groups.items()}


def by_cell(zs: Zs) -> dict[tuple[str, int], np.ndarray]:
    """The z of each (class, band) cell, pooled over motions and val folders."""
    return _pool(zs, lambda cls, b, motion, root: (cls, b))


def by_family_cell(zs: Zs) -> dict[tuple[str, int], np.ndarray]:
    """The z of each (family/class, band) cell, pooled over motions and the family's folders."""
    return _pool(zs, lambda cls, b, motion, root: (f"{family(root)}/{cls}", b))


def family_scales(table_: dict, chosen: dict[str, tuple[float, ...]]) -> dict[str, tuple[float, ...]]:
    """Each family/class kind of a per-family table with its class's scales."""
    return {kind: chosen[kind.split("/", 1)[1]] for kind in table_}


def _shares(zs: Zs, scales: dict[str, tuple[float, ...]], key) -> dict:
    """Points, median z and share beyond 2 sigma per ``key(cls, band, motion, root)``, each z divided by its class's
    band scale (a report of where the tail sits; the check judges cells)."""
    from gearscan.evaluate import z_summary

    scaled = {k: z / scales[k[0]][k[1]] for k, z in zs.items()}
    out = {}
    for k, z in sorted(_pool(scaled, key).items()):
        s = z_summary(z)
        out[k] = {"points": int(z.size), "median": s["median_z"], "beyond_2sigma": s["beyond_2sigma"]}
    return out


def by_motion(zs: Zs, scales: dict[str, tuple[float, ...]]) -> dict:
    """Per motion, pooled over its bands, classes and folders, with each band's scale."""
    return _shares(zs, scales, lambda cls, b, motion, root: motion)


def by_family_motion(zs: Zs, scales: dict[str, tuple[float, ...]]) -> dict:
    """Per family and motion, pooled over bands and classes, with each band's scale (a report; judged by nothing)."""
    out: dict = {}
    for (fam, motion), cell in _shares(zs, scales, lambda cls, b, motion, root: (family(root), motion)).items():
        out.setdefault(fam, {})[motion] = cell
    return out


def _per_kind(scales, kind: str) -> tuple[float, ...]:
    """One kind's scales from a flat tuple (every kind alike) or a mapping kind -> scales."""
    return tuple(scales[kind]) if isinstance(scales, dict) else tuple(scales)


def table(zs: dict[tuple[str, int], np.ndarray], scales=None, at=()) -> dict:
    """Per kind (motion class) and band: points, median z, share beyond 2 sigma, the scale needed (z divided by
    ``scales``: flat or per kind); a raw table (no ``scales``) also holds the share beyond 2 x s for each s in ``at``
    (flat, or per kind: the scales a check reads)."""
    from gearscan.evaluate import z_summary
    from gearscan.recon.depth_sigma import band_labels

    out: dict = {}
    for kind in sorted({k for k, _ in zs}):
        out[kind] = {}
        grid = sorted(set(_per_kind(at, kind))) if at else []
        for b, label in enumerate(band_labels()):
            z = zs.get((kind, b), np.zeros(0))
            if scales is not None:
                z = z / _per_kind(scales, kind)[b]
            if not z.size:
                out[kind][label] = {"points": 0}
                continue
            s = z_summary(z)
            out[kind][label] = {"points": int(z.size), "median": s["median_z"], "beyond_2sigma": s["beyond_2sigma"],
                                "z_q9545": s["z_q9545"], "needed_scale": s["needed_scale"]}
            if scales is None and grid:  # the raw share beyond 2 x s, so that the check recomputes from the raw table
                out[kind][label]["beyond_2x_scale"] = {f"{c:.2f}": float(np.mean(z > 2 * c)) for c in grid}
    return out


def recheck(raw: dict, scales) -> dict:
    """The check's scaled shares beyond 2 sigma, read from a raw table's shares beyond 2 x s at these scales (flat,
    or per kind)."""
    from gearscan.recon.depth_sigma import band_labels

    return {kind: {label: {"points": cells[label].get("points", 0),
                           "beyond_2sigma": cells[label]["beyond_2x_scale"][f"{sc:.2f}"] if cells[label].get("points")
                           else None}
                   for label, sc in zip(band_labels(), _per_kind(scales, kind), strict=True)}
            for kind, cells in raw.items()}


def _round_up(need: float) -> float:
    return round(max(1.0, math.ceil(round(need / 0.05, 6)) * 0.05), 2)


def choose_pooled(fit: dict) -> tuple[float, ...]:
    """The rule as first written (session 50, kinds still and moving): per band the larger need of the kinds on the
    fit set, rounded up to 0.05, at least 1; one set for every burst."""
    from gearscan.recon.depth_sigma import band_labels

    return tuple(_round_up(max(fit[k][label].get("needed_scale", 1.0) for k in fit)) for label in band_labels())


def choose(fit: dict, classes: tuple[str, ...] | None = None) -> dict[str, tuple[float, ...]]:
    """The second and third amendments: per motion class and band, that class's need on the fit set, rounded up to
    0.05, at least 1. ``classes``: those to choose for (default ``MOTION_CLASSES``; the second amendment had three).
    Every class must have points in every band (else a ValueError: the rule cannot choose for it)."""
    from gearscan.recon.depth_sigma import MOTION_CLASSES, band_labels

    out = {}
    for cls in classes or MOTION_CLASSES:
        cells = fit.get(cls, {})
        missing = [label for label in band_labels() if not cells.get(label, {}).get("points")]
        if missing:
            raise ValueError(f"fit set: motion class {cls!r} has no points in {', '.join(missing)}")
        out[cls] = tuple(_round_up(cells[label]["needed_scale"]) for label in band_labels())
    return out


def choose_worst_family(fit: dict) -> dict[str, tuple[float, ...]]:
    """The fourth amendment: per motion class and band, the largest need over the val families (kinds
    "family/class" of a per-family fit table) whose cell holds at least CHECK_MIN_POINTS points, rounded up to 0.05,
    at least 1. A class with no counted family in some band: a ValueError (the rule cannot choose for it)."""
    from gearscan.recon.depth_sigma import MOTION_CLASSES, band_labels

    out = {}
    for cls in MOTION_CLASSES:
        kinds = [k for k in fit if k.split("/", 1)[1] == cls]
        scales = []
        for label in band_labels():
            needs = [fit[k][label]["needed_scale"] for k in kinds
                     if fit[k].get(label, {}).get("points", 0) >= CHECK_MIN_POINTS]
            if not needs:
                raise ValueError(f"fit set: motion class {cls!r} has no family with {CHECK_MIN_POINTS} points in {label}")
            scales.append(_round_up(max(needs)))
        out[cls] = tuple(scales)
    return out


def check(scaled: dict) -> list[str]:
    """The check set's cells that miss the bound (empty: the check passes)."""
    return [f"{kind} {label}: {cell['beyond_2sigma']:.1%} beyond 2 sigma"
            for kind, cells in scaled.items() for label, cell in cells.items()
            if cell.get("points", 0) >= CHECK_MIN_POINTS and cell["beyond_2sigma"] > CHECK_BEYOND_2]


def val_sets(arg: str | None, ap: argparse.ArgumentParser) -> tuple[str, ...] | None:
    """``--sets`` as folders: relative to the working directory (the repository's own, ``data/...``, as its rule runs
    name them), each a twin dataset (its ``index.json``); None: the product's val scenes. A folder outside the
    repository, or not named ``data/default_rig/...``, is a val family of its own (:func:`family`)."""
    if arg is None:
        return None
    out = []
    for name in (n.strip() for n in arg.split(",")):
        path = Path(name).resolve()
        if not name or not (path / "index.json").is_file():
            ap.error(f"--sets: {name!r} is not a twin dataset folder (expected a folder with index.json, e.g. from "
                     f"`gearscan twin dataset`)")
        out.append(str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path))
    return tuple(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "depth_sigma_val.json")
    ap.add_argument("--motions", default="wide")
    ap.add_argument("--per-motion", type=int, default=5)  # 1 until the fifth amendment
    ap.add_argument("--fit-seed", type=int, default=2000)
    ap.add_argument("--check-seed", type=int, default=2800)  # 2200: the first choice and the second amendment; 2400 the third; 2600 the fourth
    ap.add_argument("--check-model", type=Path, default=None,
                    help="check the shipped scales on this model's bursts (check seed set only; chooses nothing) "
                         "and write that check to --out")
    ap.add_argument("--model", type=Path, default=None,
                    help="choose this model's own scales (the rule's amendment: a model fine-tuned on one rig, on "
                         "that rig's val scenes given by --sets); default: the shipped model, the product's scales")
    ap.add_argument("--sets", default=None,
                    help="with --model or --check-model: comma-separated val folders (default: "
                         "evaluate.VAL_CLOUD_SETS), e.g. the default rig's val gears for a model fine-tuned on that rig")
    ap.add_argument("--mc", type=int, default=0,
                    help="Monte Carlo passes of the network's decode (the ninth amendment; 0: deterministic); with "
                         "it the deterministic table's check on the same MC decodes is recorded too")
    ap.add_argument("--write", action="store_true",
                    help="with --model: store the scales in the model's JSON (depth_sigma) if the check passes")
    args = ap.parse_args()
    if args.sets is not None and args.check_model is None and args.model is None:
        ap.error("--sets: only with --model or --check-model (the product's choice reads evaluate.VAL_CLOUD_SETS)")
    if args.write and args.model is None:
        ap.error("--write: only with --model (the product's scales are recon.depth_sigma.DEPTH_SIGMA_SCALES)")
    if args.model is not None and args.check_model is not None:
        ap.error("--model and --check-model: give one")
    from gearscan.inference.model_io import ModelFileError, read_config

    for flag, path in (("--model", args.model), ("--check-model", args.check_model)):
        if path is None:
            continue
        if not path.is_file():
            ap.error(f"{flag}: expected a model's .safetensors file, got {path}")
        try:  # its JSON (config, sigma maps) beside it: a clear error here, not a traceback after the decodes
            read_config(path)
        except ModelFileError as exc:
            ap.error(f"{flag}: {exc}")
    if args.model is not None and args.out == ROOT / "benchmarks" / "depth_sigma_val.json":
        ap.error("--model: give its own --out (benchmarks/depth_sigma_val.json is the product's choice)")
    if args.mc and (args.model is not None or args.check_model is not None or args.write):
        ap.error("--mc: only for the product's choice (a model's own scales are chosen deterministic)")
    if args.mc and args.out == ROOT / "benchmarks" / "depth_sigma_val.json":
        ap.error("--mc: give its own --out (benchmarks/depth_sigma_val.json is the deterministic choice)")
    if args.fit_seed == args.check_seed:
        ap.error(f"--check-seed: expected another seed set than --fit-seed ({args.fit_seed})")
    if args.check_model is not None:
        if args.out == ROOT / "benchmarks" / "depth_sigma_val.json":
            ap.error("--check-model: give its own --out (benchmarks/depth_sigma_val.json is the rule's choice)")

    from inspect_bench import commit, host

    from gearscan.evaluate import VAL_CLOUD_SETS
    from gearscan.inference.model_io import model_fingerprint
    from gearscan.inference.predictor import DEFAULT_MODEL
    from gearscan.recon.depth_sigma import (
        DEPTH_SIGMA_SCALES,
        EDGE_BANDS_PX,
        MOTION_CLASSES,
        TRAINED_SPAN_DEG,
    )

    shipped = {c: tuple(v) for c, v in DEPTH_SIGMA_SCALES.by_class.items()}
    if args.check_model is not None:  # the shipped scales on another model's bursts: a report, no choice
        sets = val_sets(args.sets, ap)
        check_z = collect(args.check_seed, args.motions, args.per_motion, args.check_model, sets)
        check_kinds = family_scales(table(by_family_cell(check_z)), shipped)  # judged per family, as the rule does
        check_raw = table(by_family_cell(check_z), at=check_kinds)
        misses = check(recheck(check_raw, check_kinds))
        out = {"split": "val", "rule": "benchmarks/depth_sigma_rule.md (its check, on another model; chooses nothing)",
               "commit": commit(), "host": host(), "model": str(args.check_model),
               "model_fingerprint": model_fingerprint(args.check_model), "sets": list(sets or VAL_CLOUD_SETS),
               "motions": args.motions,
               "per_motion": args.per_motion, "check_seed": args.check_seed, "edge_bands_px": list(EDGE_BANDS_PX),
               "scales": DEPTH_SIGMA_SCALES.as_dict(), "check_bound_beyond_2sigma": CHECK_BEYOND_2,
               "check_min_points": CHECK_MIN_POINTS, "check_passed": not misses, "check_misses": misses,
               "check_raw": check_raw, "check_scaled": table(by_family_cell(check_z), check_kinds),
               "check_by_motion": by_motion(check_z, shipped)}
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1) + "\n")
        print(f"{args.check_model}: check {'passed' if not misses else 'MISSED: ' + '; '.join(misses)}")
        return

    sets = val_sets(args.sets, ap)
    fit_z = collect(args.fit_seed, args.motions, args.per_motion, args.model, sets, args.mc)
    fit = table(by_family_cell(fit_z))
    try:
        scales = choose_worst_family(fit)
    except ValueError as exc:  # too few points for the rule to choose in some class and band: no scales, said why
        raise SystemExit(f"error: {exc}: the val scenes are too small for a measured choice (the rule needs "
                         f"{CHECK_MIN_POINTS} points per class and edge band in some family); render more start points "
                         "or larger images, or raise --per-motion. Nothing chosen, nothing written.") from exc
    check_z = collect(args.check_seed, args.motions, args.per_motion, args.model, sets, args.mc)
    per_kind = family_scales(table(by_family_cell(check_z)), scales)
    check_raw = table(by_family_cell(check_z), at=per_kind)
    misses = check(recheck(check_raw, per_kind))
    model = args.model or DEFAULT_MODEL
    out = {
        "split": "val", "rule": "benchmarks/depth_sigma_rule.md (fifth amendment: per motion class, the worst val family, "
                                f"{args.per_motion} bursts per motion)"
                + (" (its amendment: a model's own)" if args.model else "")
                + (f" (ninth amendment: Monte Carlo mode, T = {args.mc})" if args.mc else ""),
        "commit": commit(), "host": host(), "model": str(model.relative_to(ROOT) if model.is_relative_to(ROOT) else model),
        "model_fingerprint": model_fingerprint(model),  # the decode it was chosen for (weights, sigma maps)
        "sets": list(sets or VAL_CLOUD_SETS),
        "motions": args.motions, "per_motion": args.per_motion, "mc": args.mc, "fit_seed": args.fit_seed,
        "check_seed": args.check_seed, "edge_bands_px": list(EDGE_BANDS_PX),
        "motion_classes": {"classes": list(MOTION_CLASSES), "trained_span_deg": TRAINED_SPAN_DEG},
        "scales": {c: list(v) for c, v in scales.items()},
        "check_bound_beyond_2sigma": CHECK_BEYOND_2, "check_min_points": CHECK_MIN_POINTS,
        "check_passed": not misses, "check_misses": misses,
        "fit_raw": fit, "fit_scaled": table(by_family_cell(fit_z), family_scales(fit, scales)),
        "check_raw": check_raw, "check_scaled": table(by_family_cell(check_z), per_kind),
        "check_pooled_scaled": table(by_cell(check_z), scales),  # the classes pooled over families, for comparison
        "check_by_family_motion": by_family_motion(check_z, scales),
        "check_by_family_motion_shipped_before": by_family_motion(check_z, shipped),
    }
    if args.mc:  # the deterministic table on the same MC decodes, judged per family cell as the check is
        det_kinds = family_scales(check_raw, shipped)
        out["check_deterministic_scales_scaled"] = table(by_family_cell(check_z), det_kinds)
        out["check_deterministic_scales_misses"] = check(out["check_deterministic_scales_scaled"])
    if args.model is not None:  # what the model carries now (its own scales, else the product's), on the check set
        from gearscan.inference.model_io import read_config
        from gearscan.inference.predictor import model_depth_sigma_scales
        from gearscan.recon.depth_sigma import run_depth_sigma_scales

        before = run_depth_sigma_scales(model_depth_sigma_scales(read_config(args.model)), network=True) \
            or DEPTH_SIGMA_SCALES
        before_kinds = family_scales(check_raw, {c: tuple(v) for c, v in before.by_class.items()})
        out["model_scales_before"] = before.as_dict()
        out["check_model_before_scaled"] = table(by_family_cell(check_z), before_kinds)
        out["check_model_before_misses"] = check(out["check_model_before_scaled"])
    if args.write and not misses:
        from gearscan.inference.model_io import read_config, write_config
        from gearscan.inference.predictor import DEPTH_SIGMA_KEY

        meta = read_config(args.model)
        meta[DEPTH_SIGMA_KEY] = {"scales": {c: list(v) for c, v in scales.items()}, "edge_bands_px": list(EDGE_BANDS_PX),
                                 "model_fingerprint": out["model_fingerprint"],  # the decode they were chosen for
                                 "chosen_by": f"benchmarks/depth_sigma_rule.md (amendment), {args.out.name}, "
                                              f"commit {out['commit']}"}
        out["written"] = write_config(args.model, meta).name
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(f"scales {scales}; check {'passed' if not misses else 'MISSED: ' + '; '.join(misses)}"
          + (f"; written to {out['written']}" if out.get("written") else ""))
    if args.write and misses:  # a choice that missed its check is no measured bound: the model keeps what it had
        raise SystemExit(f"error: the check missed, so nothing was written to {args.model}'s JSON (record: {args.out}); "
                         "its points keep the scales they had (`depth_sigma_source` says whether those were measured)")


if __name__ == "__main__":
    main()
