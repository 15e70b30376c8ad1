"""The still-burst gate's choice: draw a family's twin bursts, score every gate setting, apply the rule.

The gate (:func:`gearscan.inference.predictor.still_burst_gate`) decodes a whole burst by three-step PS when
the network's median departure from it over the burst's interior is below ``rad`` and the share of lit pixels
whose frames swing more than a still fringe can (:func:`~gearscan.inference.predictor.frame_motion_share`) is
below ``max_motion``. The rules are written in ``benchmarks/still_burst_gate_rule.md`` (``rad`` alone) and
``benchmarks/still_burst_motion_rule.md`` (both; the shipped one). ``scripts/choose_still_burst_gate.py`` runs them
on the val split for a shipped model; :func:`choose_rig_gate` (``gearscan still-gate``) on one rig's own twin data
(``benchmarks/rig_still_gate_rule.md``).
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import torch

from gearscan.core.phase import phase_error
from gearscan.inference.model_io import read_config, write_config
from gearscan.inference.models import classical_md
from gearscan.inference.predictor import (
    THREE_STEP_NOISE,
    WEIGHTS_DIR,
    BurstSigma,
    Predictor,
    burst_departure,
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


def scores(rows: list[dict], rad: float, max_motion: float = math.inf) -> dict[str, float | None]:
    """RMSE and ECE of the gated outputs at ``rad`` (0: ungated) and ``max_motion``, three-step RMSE, bursts taken,
    and the ECE of the taken bursts alone, gated and ungated (None when none is taken)."""
    take = [taken(r, rad, max_motion) for r in rows]
    err = np.concatenate([r["e_3"] if t else r["e_net"] for r, t in zip(rows, take, strict=True)])
    sig = np.concatenate([r["s_3"] if t else r["s_net"] for r, t in zip(rows, take, strict=True)])
    e3 = np.concatenate([r["e_3"] for r in rows]).astype(np.float64)
    chosen = [r for r, t in zip(rows, take, strict=True) if t]

    def ece_of(e: str, s: str) -> float | None:
        if not chosen:
            return None
        return float(reliability(np.concatenate([r[e] for r in chosen]), np.concatenate([r[s] for r in chosen])).ece)

    return {"rmse": float(np.sqrt(np.mean(err.astype(np.float64) ** 2))), "ece": float(reliability(err, sig).ece),
            "three_step": float(np.sqrt(np.mean(e3**2))), "taken": int(sum(take)), "bursts": len(rows),
            "ece_taken": ece_of("e_3", "s_3"), "ece_taken_ungated": ece_of("e_net", "s_net")}


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

    ok = [r for r in GRID if within_cost(table, f"{r:g}", ece_scope="family")]
    reaching = [r for r in ok if still_ok(r)]
    return min(reaching) if reaching else (max(ok) if ok else 0.0)


ECE_SCOPES = ("family", "taken")


def within_cost(table: dict, key: str, ece_scope: str = "taken") -> bool:
    """Moving and slow RMSE <= 1.03 x the ungated network's, and the ECE bound, in every family.

    The ECE bound, on moving and on still bursts: ``"taken"`` (``benchmarks/still_gate_taken_ece_rule.md``, the
    shipped rule) bounds the ECE of the bursts the setting takes by the same bursts' ECE ungated, since the gate
    changes nothing else; ``"family"`` (the rules before it) bounds the family's pooled ECE by its ungated one.
    """
    if ece_scope not in ECE_SCOPES:
        raise ValueError(f"ece_scope: expected one of {ECE_SCOPES}, got {ece_scope!r}")
    for fam in table.values():
        base, cur = fam["0"], fam[key]
        if any(cur[k]["rmse"] > COST * base[k]["rmse"] for k in ("moving", "slow")):
            return False
        for k in ("moving", "still"):
            if ece_scope == "family":
                gated, ungated = cur[k]["ece"], base[k]["ece"]
            elif "ece_taken" not in cur[k]:
                raise ValueError(f"gate table, setting {key}: no ECE of the taken bursts (a table scored before "
                                 "benchmarks/still_gate_taken_ece_rule.md); read it with ece_scope='family'")
            elif cur[k]["ece_taken"] is None:
                continue  # nothing taken: the gate changed nothing of this kind
            else:
                gated, ungated = cur[k]["ece_taken"], cur[k]["ece_taken_ungated"]
            if gated > max(ungated + ECE_SLACK, ECE_TARGET):
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


def choose_with_motion(table: dict, ece_scope: str = "taken") -> tuple[float, float]:
    """``(rad, max_motion)`` by ``benchmarks/still_burst_motion_rule.md`` over ``table[family][key][kind]``
    (keys by :func:`setting_key`, "0" ungated): among the settings within cost (:func:`within_cost`; its ECE
    bound on the taken bursts since ``still_gate_taken_ece_rule.md``, ``"family"`` before), the lowest
    :func:`still_objective`, ties to the smaller rad, then the smaller max_motion (the stricter check);
    (0, inf) when no setting beats the ungated network's objective."""
    best, best_obj = (0.0, math.inf), still_objective(table, "0")
    for rad in GRID:
        for mm in MOTION_GRID:
            key = setting_key(rad, mm)
            if not within_cost(table, key, ece_scope):
                continue
            obj = still_objective(table, key)
            if obj < best_obj:  # strict: an earlier (smaller rad, stricter check) setting keeps a tie
                best, best_obj = (rad, mm), obj
    return best



MOTION_RULE = ("benchmarks/still_burst_motion_rule.md with the ECE bound of benchmarks/still_gate_taken_ece_rule.md: "
               "among the (rad, max_motion) settings within moving and slow RMSE <= 1.03 x ungated and, for moving "
               "and still bursts, the taken bursts' ECE <= max(their ungated ECE + 0.005, 0.05) in every family, "
               "the fewest families with still RMSE > 1.05 x three-step, then the lowest mean still ratio (floored "
               "at 1.05) where the network is above it; ties: the smaller rad, then the stricter check; none better "
               "than ungated: 0")
STATISTIC = "median |network - three-step| phase over modulation >= 0.05, eroded 7x7, >= 256 px"
MOTION_STATISTIC = ("share of the lit pixels (three-step modulation 2B' >= 0.05, >= 256 px) whose three-step "
                    "amplitude B' exceeds the frames' mean A'")
NOISE_SIGMA = {"kind": THREE_STEP_NOISE, "form": "sqrt(2/3) * s_n / B', s_n measured on the burst's frame sum "
               "(gearscan.core.phase.still_frame_noise), B' = three-step modulation / 2 floored at 0.005; "
               "no fitted parameter"}


def gate_table(predictor: Predictor, families: dict[str, Folders], seed: int, sigma_map: BurstSigma | None,
               motion: bool = True, progress=None) -> dict:
    """``table[family][setting][kind]``: every gate setting's scores (:func:`scores`) on each family's drawn bursts
    (``predictor`` with its gates off); "0" is the ungated network."""
    settings = [(0.0, math.inf)] + [(r, m) for r in GRID for m in (MOTION_GRID if motion else (math.inf,))]
    table = {}
    for fam, folders in families.items():
        rows = family_bursts(predictor, folders, seed, sigma_map)
        table[fam] = {setting_key(r, m): {k: scores(v, r, m) for k, v in rows.items()} for r, m in settings}
        if progress is not None:
            progress(fam, table[fam])
    return table


def motion_choice(table: dict, families: list[str], seed: int, orientation: str, by_view: bool,
                  sigma_entry: dict | None) -> dict:
    """The JSON record of :func:`choose_with_motion` on ``table``: the setting, what it was chosen on, the rule,
    the statistics, the gated bursts' sigma and the table itself (``still_burst_gate`` in the model's JSON)."""
    rad, max_motion = choose_with_motion(table)
    choice = {"rad": rad, "chosen_on": f"{data_kind(families)}: " + "; ".join(table), "grid": list(GRID),
              "rule": MOTION_RULE, "statistic": STATISTIC, "orientation": orientation, "mode": "deterministic",
              "seed": seed, "by_view": by_view, "ece_bound": "taken", "val": table,
              "motion_grid": [m for m in MOTION_GRID if m != math.inf] + ["none"], "motion_statistic": MOTION_STATISTIC}
    if rad > 0 and max_motion != math.inf:
        choice["max_motion_share"] = max_motion
    if sigma_entry is not None:
        choice["sigma"] = sigma_entry
    return choice


def choose_rig_gate(folders: list[Path], model: Path | None = None, output: Path | None = None, *,
                    seed: int = 29, orientation: str = "normal", progress=None) -> tuple[dict, Path]:
    """Choose the gate on one rig's own twin data (``folders`` pooled into one family: ``gearscan twin dataset
    --rig``) by the shipped rule with the shipped gated-burst sigma, and store it in the model's JSON (a copy at
    ``output`` when given, else in place); returns the record and the JSON written."""
    for folder in folders:  # each a twin dataset, before anything is copied or written
        TwinBurstDataset(folder)
    weights = model_path(model)
    Predictor.load(weights)  # the model loads (weights and the JSON beside them) before anything is copied or written
    if output is None and weights.resolve().parent == WEIGHTS_DIR.resolve():
        raise ValueError(f"{weights.name} is a shipped model: a gate chosen on one rig would replace the one chosen "
                         "for every rig; write a copy with --output MY_RIG.safetensors (or pass your own --model)")
    if output is not None:
        output = Path(output).with_suffix(".safetensors")
        if output.resolve() != weights.resolve():
            shutil.copy(weights, output)
            shutil.copy(weights.with_suffix(".json"), output.with_suffix(".json"))
        weights = output
    predictor = Predictor.load(weights, orientation=orientation, still_gate_rad=0.0, still_burst_rad=0.0)
    name = ",".join(str(f) for f in folders)
    table = gate_table(predictor, {name: [(str(f), None) for f in folders]}, seed, THREE_STEP_NOISE,
                       progress=progress)
    choice = motion_choice(table, [name], seed, orientation, False, NOISE_SIGMA)
    meta = read_config(weights)
    meta["still_burst_gate"] = choice
    return choice, write_config(weights, meta)
