"""Monte Carlo mode's phase, chosen on val: the deterministic pass's, or the mean of the passes (the paper's).

Per family, a seeded sample of moving (both senses) and still val bursts, decoded by the deterministic pass and by
several MC draws of the mean of the passes (one torch seed each), the network's own phase (still gates off, fringe
orientation normal); RMSE over the truth mask pooled by pixels. Two rules read the table:

- ``two-sided`` (``benchmarks/mc_phase_rule_v2.md``, every choice from session 41 on): the phase whose worst
  family x kind cell, against the other phase, is lower; when both are within :data:`COST` in every cell, the one
  with the lower pooled moving RMSE.
- ``one-sided`` (``benchmarks/mc_phase_rule.md``, the choices of sessions 38-39): the deterministic phase only when
  its pooled moving RMSE is at most the draws' mean and no cell is above :data:`COST` x it; kept to reproduce them.

``scripts/choose_mc_phase.py`` runs either on a model.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from gearscan.core.phase import phase_error
from gearscan.inference.predictor import Predictor
from gearscan.twin.dataset import TwinBurstDataset

COST = 1.03
DRAWS = (0, 1)  # torch seeds of the one-sided rule's two MC draws
DRAWS_V2 = (2, 3, 4, 5)  # the two-sided rule's four
KINDS = {"moving": {"reverse": True}, "still": {"static": True, "motion": "uniform", "max_span": 0}}
RULE = ("benchmarks/mc_phase_rule.md: the deterministic pass's phase when its pooled moving RMSE is at most the mean "
        "of two MC draws' and no family's moving or still RMSE is above 1.03 x it")
RULE_V2 = ("benchmarks/mc_phase_rule_v2.md: the phase whose worst family x kind cell against the other is lower; when "
           "both are within 1.03x in every cell, the one with the lower pooled moving RMSE (ties: deterministic)")
RULES = {"two-sided": (RULE_V2, DRAWS_V2), "one-sided": (RULE, DRAWS)}


def mc_phase_table(model: str | None, families: dict[str, Sequence[str]], *, seed: int = 11, moving: int = 96,
                   still: int = 48, passes: int = 20, rule: str = "two-sided",
                   progress: Callable[[str], None] | None = None) -> dict[str, dict]:
    """``table["family:kind"]`` = RMSE of the deterministic pass (``det``), of each MC draw (``mc<torch seed>``) and
    the draws' mean (``mc_mean_of_draws``); ``"pooled:moving"`` over every family; ``"rule"``: ``rule``'s verdict
    (``"one-sided"`` or ``"two-sided"``, :data:`RULES`; its draws too)."""
    if rule not in RULES:
        raise ValueError(f"rule: expected one of {sorted(RULES)}, got {rule!r}")
    draws = RULES[rule][1]
    # one predictor: mc = 0 is the deterministic pass whatever mc_phase says; mc > 0 the mean of the passes
    pred = Predictor.load(model, orientation="normal", still_burst_rad=0.0, still_gate_rad=0.0, mc_phase="mean")
    table: dict[str, dict] = {}
    sums: dict[str, dict[str, list[float]]] = {}
    for fam, folders in families.items():
        for kind, options in KINDS.items():
            count = moving if kind == "moving" else still
            acc = {k: [0.0, 0] for k in ("det", *(f"mc{s}" for s in draws))}
            for f, folder in enumerate(folders):
                ds = TwinBurstDataset(folder, **options)
                n = min(count // len(folders), len(ds))
                for i in sorted(np.random.default_rng([seed, f, kind == "still"]).choice(len(ds), n, replace=False)):
                    item = ds[int(i)]
                    x = torch.from_numpy(np.asarray(item["input"], np.float32))[None]
                    mask = np.asarray(item["mask"], bool)
                    results = {"det": pred.predict_tensor(x)}
                    for s in draws:
                        torch.manual_seed(s)
                        results[f"mc{s}"] = pred.predict_tensor(x, passes)
                    for k, r in results.items():
                        e = phase_error(r.phase, item["phase"])[mask].astype(np.float64)
                        acc[k][0] += float((e**2).sum())
                        acc[k][1] += e.size
            table[f"{fam}:{kind}"] = _rmse_row(acc)
            sums[f"{fam}:{kind}"] = acc
            if progress:
                progress(f"{fam} {kind}: " + ", ".join(f"{k} {v:.4f}" for k, v in table[f"{fam}:{kind}"].items()))
    pooled = {k: [sum(sums[f"{fam}:moving"][k][i] for fam in families) for i in (0, 1)]
              for k in ("det", *(f"mc{s}" for s in draws))}
    table["pooled:moving"] = _rmse_row(pooled)
    table["rule"] = verdict_two_sided(table) if rule == "two-sided" else verdict(table)
    return table


def _rmse_row(acc: dict[str, list[float]]) -> dict[str, float]:
    row = {k: float(np.sqrt(v[0] / v[1])) for k, v in acc.items()}
    row["mc_mean_of_draws"] = float(np.mean([v for k, v in row.items() if k != "det"]))
    return row


def verdict(table: dict[str, dict]) -> dict[str, bool]:
    """The rule on a table of :func:`mc_phase_table` (its ``"rule"`` entry ignored)."""
    rows = {k: v for k, v in table.items() if k not in ("rule", "pooled:moving")}
    pooled = table["pooled:moving"]
    c1 = pooled["det"] <= pooled["mc_mean_of_draws"]
    c2 = all(r["det"] <= COST * r["mc_mean_of_draws"] for r in rows.values())
    return {"1 pooled moving det <= MC": c1, "2 no family above 1.03x": c2, "adopt": c1 and c2}


def verdict_two_sided(table: dict[str, dict]) -> dict[str, object]:
    """``benchmarks/mc_phase_rule_v2.md`` on a table of :func:`mc_phase_table` (its ``"rule"`` entry ignored):
    ``phase`` is ``"deterministic"`` or ``"mean"``; ``adopt`` is True for the deterministic phase."""
    rows = {k: v for k, v in table.items() if k not in ("rule", "pooled:moving")}
    if not rows:
        raise ValueError("mc phase table: no family x kind cells to judge")
    worst_det = max(r["det"] / r["mc_mean_of_draws"] for r in rows.values())
    worst_mc = max(r["mc_mean_of_draws"] / r["det"] for r in rows.values())
    pooled = table["pooled:moving"]
    if worst_det <= COST and worst_mc <= COST:
        by = "1 both within 1.03x in every cell: the lower pooled moving RMSE"
        det = pooled["det"] <= pooled["mc_mean_of_draws"]
    else:
        by = "2 the lower worst cell"
        det = worst_det <= worst_mc
    return {"worst cell if deterministic": worst_det, "worst cell if mean": worst_mc, "decided by": by,
            "phase": "deterministic" if det else "mean", "adopt": det}
