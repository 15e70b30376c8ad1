"""Choose a model's still-burst gate on the VAL split (or on one rig's own twin data) and store it in the model's JSON.

    python scripts/choose_still_burst_gate.py data/repro/val_radial data/repro/val_views \\
        data/default_rig/val/z25,data/default_rig/val/z32,data/default_rig/val/z46,data/default_rig/val/z62 \\
        [--model inference/weights/default.safetensors] [--write]

Each argument is a val family (comma-joined folders are pooled into one). The gate
(:func:`gearscan.inference.predictor.still_burst_gate`) decodes a whole burst by three-step PS when
the network's median departure from it over the burst's interior is below ``rad`` and, with a motion
check, the share of lit pixels whose frames swing more than a still fringe can
(:func:`~gearscan.inference.predictor.frame_motion_share`) is below ``max_motion``.

Rules (written before their runs): ``benchmarks/still_burst_gate_rule.md`` (``rad`` alone; within a
moving and a slow cost of 3 % and an ECE bound in every family, the smallest ``rad`` that brings the
still bursts to 1.05 x three-step PS wherever the network is above that; none reaches it: the largest
within cost; none within cost: 0) and, with ``--motion``, ``benchmarks/still_burst_motion_rule.md``
(``rad`` and ``max_motion`` together). Val only: the test split reports it
(``benchmarks/generalization.py``).

The twin workflow runs the same rule on a user's rig, that rig as its only family, into a copy of the model
(``benchmarks/rig_still_gate_rule.md``)::

    python scripts/choose_still_burst_gate.py ADAPT/ --model my_rig.safetensors --motion --noise-sigma --write
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

from gearscan.core.phase import phase_error
from gearscan.inference.model_io import read_config, write_config
from gearscan.inference.models import classical_md
from gearscan.inference.predictor import (
    THREE_STEP_NOISE,
    BurstSigma,
    Predictor,
    burst_departure,
    burst_sigma_map,
    frame_motion_share,
    model_path,
    still_burst_gate,
)
from gearscan.inference.uncertainty import event_log_score, reliability
from gearscan.twin.dataset import TwinBurstDataset

GRID = (0.015, 0.02, 0.025, 0.03, 0.035, 0.04)
MOTION_GRID = (0.001, 0.002, 0.005, math.inf)  # max_motion; inf: no motion check
COST = 1.03
STILL_TOLERANCE = 1.05
ECE_SLACK, ECE_TARGET = 0.005, 0.05
SETS = {"moving": (96, {"reverse": True}), "slow": (48, {"reverse": True, "max_span": 2}),
        "still": (48, {"static": True, "motion": "uniform", "max_span": 0})}


Folders = list[tuple[str, list[int] | None]]  # (dataset folder, its start points; None: all)


def by_view(folders: Folders) -> dict[str, Folders]:
    """The same folders split by the rig's name of each start point ("face view", ...): one family each."""
    views: dict[str, Folders] = {}
    for folder, groups in folders:
        entries = json.loads((Path(folder) / "index.json").read_text())["entries"]
        names: dict[str, list[int]] = {}
        for g in (range(len(entries)) if groups is None else groups):
            names.setdefault(entries[g]["rig"].get("name", "unnamed rig"), []).append(g)
        for name, gs in names.items():
            views.setdefault(name, []).append((folder, gs))
    return views


def sampled_bursts(folders: Folders, kind: str, seed: int):
    """The val bursts of one kind (:data:`SETS`) the rule scores: per folder a seeded sample, in item order."""
    s = list(SETS).index(kind)
    count, options = SETS[kind]
    for f, (folder, groups) in enumerate(folders):
        ds = TwinBurstDataset(folder, groups=groups, **options)
        n = min(count // len(folders), len(ds))
        for i in sorted(np.random.default_rng([seed, s, f]).choice(len(ds), n, replace=False)):
            yield ds[int(i)]


def family_bursts(predictor: Predictor, folders: Folders, seed: int, sigma_map: BurstSigma | None,
                  kinds: tuple[str, ...] = tuple(SETS)) -> dict[str, list[dict]]:
    """Per burst kind: the ungated network's and three-step PS's errors over the truth mask, the
    network's sigma and the gated sigma there, the three-step modulation, and the burst's interior
    departure."""
    out: dict[str, list[dict]] = {}
    for name in SETS:
        if name not in kinds:
            continue
        rows = []
        for it in sampled_bursts(folders, name, seed):
            x = torch.from_numpy(np.asarray(it["input"], np.float32))[None]
            net = predictor.predict_tensor(x)
            classical = classical_md(x[:, :3])[0].numpy()
            frames = x[0, :3].numpy()
            gated, _ = still_burst_gate(net, classical, np.inf, predictor.calibration.get("deterministic"), sigma_map,
                                        frames=frames)
            m = np.asarray(it["mask"], bool)
            rows.append({"score": burst_departure(net.phase, classical), "motion": frame_motion_share(frames),
                         "e_net": phase_error(net.phase, it["phase"])[m].astype(np.float32),
                         "e_3": phase_error(gated.phase, it["phase"])[m].astype(np.float32),
                         "s_net": net.sigma_total[m], "s_3": gated.sigma_total[m],
                         "mod": np.hypot(*classical)[m].astype(np.float32)})
        out[name] = rows
    return out


def data_kind(families: list[str]) -> str:
    """What the gate is chosen on: a rig's own twin data (every folder an adaptation dataset) or the val split."""
    folders = [Path(f) for fam in families for f in fam.split(",")]
    purposes = {json.loads((f / "index.json").read_text()).get("purpose", "protocol") for f in folders}
    return "the rig's own twin data" if purposes == {"adaptation"} else "val split"


def setting_key(rad: float, max_motion: float = math.inf) -> str:
    """A gate setting's key in the val table: ``"0.025"`` (no motion check), ``"0.025@0.002"``."""
    return f"{rad:g}" if max_motion == math.inf else f"{rad:g}@{max_motion:g}"


def taken(row: dict, rad: float, max_motion: float = math.inf) -> bool:
    """Whether the gate at ``rad`` and ``max_motion`` takes this burst (as ``still_burst_gate`` decides)."""
    if row["score"] is None or not row["score"] < rad:
        return False
    return max_motion == math.inf or (row["motion"] is not None and row["motion"] < max_motion)


def scores(rows: list[dict], rad: float, max_motion: float = math.inf) -> dict[str, float]:
    """RMSE and ECE of the gated outputs at ``rad`` (0: ungated) and ``max_motion``, three-step RMSE, bursts taken."""
    take = [taken(r, rad, max_motion) for r in rows]
    err = np.concatenate([r["e_3"] if t else r["e_net"] for r, t in zip(rows, take, strict=True)])
    sig = np.concatenate([r["s_3"] if t else r["s_net"] for r, t in zip(rows, take, strict=True)])
    e3 = np.concatenate([r["e_3"] for r in rows]).astype(np.float64)
    return {"rmse": float(np.sqrt(np.mean(err.astype(np.float64) ** 2))), "ece": float(reliability(err, sig).ece),
            "three_step": float(np.sqrt(np.mean(e3**2))), "taken": int(sum(take)), "bursts": len(rows)}


def fit_gated_sigma(rows: list[dict]) -> tuple[float, float, float]:
    """``(a, b, c)`` of ``sigma = a * sigma_net**b * max(2B/S, 0.01)**c`` for bursts decoded by
    three-step PS, by the event score (the ECE's event) on still val bursts' three-step errors."""
    from scipy.optimize import minimize

    err = np.concatenate([r["e_3"] for r in rows]).astype(np.float64)
    sig = np.maximum(np.concatenate([r["s_net"] for r in rows]).astype(np.float64), 1e-6)
    mod = np.maximum(np.concatenate([r["mod"] for r in rows]).astype(np.float64), 0.01)

    def loss(v: np.ndarray) -> float:
        return event_log_score(err, np.exp(v[0]) * sig ** v[1] * mod ** v[2])

    res = minimize(loss, x0=np.array([np.log(0.5), 1.0, 0.0]), method="L-BFGS-B",
                   bounds=[(-10.0, 5.0), (-3.0, 3.0), (-3.0, 3.0)])
    return float(np.exp(res.x[0])), float(res.x[1]), float(res.x[2])


def choose(table: dict[str, dict[str, dict[str, dict[str, float]]]]) -> float:
    """The rule over ``table[family][rad][kind]`` (rad keys as ``f"{rad:g}"``, "0" ungated)."""
    def still_ok(rad: float) -> bool:
        return all(fam[f"{rad:g}"]["still"]["rmse"] <= STILL_TOLERANCE * fam["0"]["still"]["three_step"]
                   for fam in table.values()
                   if fam["0"]["still"]["rmse"] > STILL_TOLERANCE * fam["0"]["still"]["three_step"])

    ok = [r for r in GRID if within_cost(table, f"{r:g}")]
    reaching = [r for r in ok if still_ok(r)]
    return min(reaching) if reaching else (max(ok) if ok else 0.0)


def within_cost(table: dict, key: str) -> bool:
    """Moving and slow RMSE <= 1.03 x the ungated network's, and the ECE bound, in every family."""
    for fam in table.values():
        base, cur = fam["0"], fam[key]
        if any(cur[k]["rmse"] > COST * base[k]["rmse"] for k in ("moving", "slow")):
            return False
        if any(cur[k]["ece"] > max(base[k]["ece"] + ECE_SLACK, ECE_TARGET) for k in ("moving", "still")):
            return False
    return True


def still_objective(table: dict, key: str) -> tuple[int, float]:
    """(families whose still RMSE is above 1.05 x three-step PS, the mean of max(ratio, 1.05) over the families
    where the ungated network is above it): lower is better; every setting that reaches the target ties."""
    needing = [fam for fam in table.values()
               if fam["0"]["still"]["rmse"] > STILL_TOLERANCE * fam["0"]["still"]["three_step"]]
    ratios = [fam[key]["still"]["rmse"] / fam[key]["still"]["three_step"] for fam in table.values()]
    above = sum(r > STILL_TOLERANCE for r in ratios)
    mean = float(np.mean([max(fam[key]["still"]["rmse"] / fam[key]["still"]["three_step"], STILL_TOLERANCE)
                          for fam in needing])) if needing else STILL_TOLERANCE
    return above, mean


def choose_with_motion(table: dict) -> tuple[float, float]:
    """``(rad, max_motion)`` by ``benchmarks/still_burst_motion_rule.md`` over ``table[family][key][kind]``
    (keys by :func:`setting_key`, "0" ungated): among the settings within cost, the lowest
    :func:`still_objective`, ties to the smaller rad, then the smaller max_motion (the stricter check);
    (0, inf) when no setting beats the ungated network's objective."""
    best, best_obj = (0.0, math.inf), still_objective(table, "0")
    for rad in GRID:
        for mm in MOTION_GRID:
            key = setting_key(rad, mm)
            if not within_cost(table, key):
                continue
            obj = still_objective(table, key)
            if obj < best_obj:  # strict: an earlier (smaller rad, stricter check) setting keeps a tie
                best, best_obj = (rad, mm), obj
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("families", nargs="+", help="val folders; comma-joined folders pool into one family")
    ap.add_argument("--model", default=None)
    ap.add_argument("--seed", type=int, default=29)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--fit-sigma", action="store_true",
                    help="fit the gated bursts' sigma map on still val bursts drawn with seed + 1 (else: the model's, "
                         "or none: the model's departure map at departure 0)")
    ap.add_argument("--noise-sigma", action="store_true",
                    help="gated bursts get three-step's own noise propagation of the frames' measured noise "
                         "(no fitted parameter; the amendment in benchmarks/still_burst_motion_rule.md)")
    ap.add_argument("--by-view", action="store_true",
                    help="score each family's rig views (the rig name of each start point) as families of their own: "
                         "a cost in one view cannot hide in a pooled number")
    ap.add_argument("--motion", action="store_true",
                    help="choose rad and the frames' motion check together (benchmarks/still_burst_motion_rule.md)")
    ap.add_argument("--write", action="store_true", help="store the choice in the model's JSON")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    predictor = Predictor.load(args.model, orientation="normal", still_gate_rad=0.0, still_burst_rad=0.0)
    sigma_map, sigma_entry = burst_sigma_map(predictor.meta), (predictor.meta.get("still_burst_gate") or {}).get("sigma")
    families: dict[str, Folders] = {}
    for fam in args.families:
        folders: Folders = [(f, None) for f in fam.split(",")]
        if args.by_view:
            families |= {f"{fam} [{view}]": part for view, part in by_view(folders).items()}
        else:
            families[fam] = folders
    if args.noise_sigma and args.fit_sigma:
        ap.error("--noise-sigma and --fit-sigma: choose one sigma for the gated bursts")
    if args.noise_sigma:
        sigma_map = THREE_STEP_NOISE
        sigma_entry = {"kind": THREE_STEP_NOISE, "form": "sqrt(2/3) * s_n / B', s_n measured on the burst's frame sum "
                       "(gearscan.core.phase.still_frame_noise), B' = three-step modulation / 2 floored at 0.005; "
                       "no fitted parameter"}
    if args.fit_sigma:
        fit_rows = [r for folders in families.values()
                    for r in family_bursts(predictor, folders, args.seed + 1, None, ("still",))["still"]]
        sigma_map = fit_gated_sigma(fit_rows)
        sigma_entry = dict(zip("abc", sigma_map, strict=True)) | {
            "fitted_on": f"val still bursts, seed {args.seed + 1}, the families below pooled", "score": "event"}
        print(f"gated bursts' sigma map: a {sigma_map[0]:.4g}, b {sigma_map[1]:.4g}, c {sigma_map[2]:.4g}", flush=True)
    settings = [(0.0, math.inf)] + [(r, m) for r in GRID for m in (MOTION_GRID if args.motion else (math.inf,))]
    table = {}
    for fam, folders in families.items():
        rows = family_bursts(predictor, folders, args.seed, sigma_map)
        table[fam] = {setting_key(r, m): {k: scores(v, r, m) for k, v in rows.items()} for r, m in settings}
        print(f"{fam}: " + "; ".join(f"rad {r}: " + ", ".join(f"{k} {v['rmse']:.4f} (3-step {v['three_step']:.4f}, "
                                                               f"ECE {v['ece']:.3f}, taken {v['taken']}/{v['bursts']})"
                                                               for k, v in row.items())
                                     for r, row in table[fam].items()), flush=True)
    if args.motion:
        chosen, max_motion = choose_with_motion(table)
        rule = ("benchmarks/still_burst_motion_rule.md: among the (rad, max_motion) settings within moving and slow "
                "RMSE <= 1.03 x ungated and ECE <= max(ungated + 0.005, 0.05) in every family, the fewest families "
                "with still RMSE > 1.05 x three-step, then the lowest mean still ratio (floored at 1.05) where the "
                "network is above it; ties: the smaller rad, then the stricter check; none better than ungated: 0")
    else:
        chosen, max_motion = choose(table), math.inf
        rule = ("benchmarks/still_burst_gate_rule.md: within moving and slow RMSE <= 1.03 x ungated and ECE "
                "<= max(ungated + 0.005, 0.05) in every family, the smallest rad with still RMSE <= 1.05 x "
                "three-step where the network is above it; else the largest within cost; else 0")
    choice = {
        "rad": chosen, "chosen_on": f"{data_kind(args.families)}: " + "; ".join(families), "grid": list(GRID), "rule": rule,
        "statistic": "median |network - three-step| phase over modulation >= 0.05, eroded 7x7, >= 256 px",
        "orientation": "normal", "mode": "deterministic", "seed": args.seed, "by_view": args.by_view, "val": table,
    }
    if args.motion:
        choice["motion_grid"] = [m for m in MOTION_GRID if m != math.inf] + ["none"]
        choice["motion_statistic"] = ("share of the lit pixels (three-step modulation 2B' >= 0.05, >= 256 px) whose "
                                      "three-step amplitude B' exceeds the frames' mean A'")
        if chosen > 0 and max_motion != math.inf:
            choice["max_motion_share"] = max_motion
    if sigma_entry is not None:
        choice["sigma"] = sigma_entry
    print(json.dumps({k: v for k, v in choice.items() if k != "val"}, indent=1))
    if args.write:
        weights = model_path(args.model)
        meta = read_config(weights)
        meta["still_burst_gate"] = choice
        print(f"wrote still_burst_gate to {write_config(weights, meta)}")


if __name__ == "__main__":
    main()
