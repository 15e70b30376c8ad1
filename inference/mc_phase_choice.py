"""Monte Carlo mode's phase, chosen on val: the deterministic pass's, or the mean of the passes (the paper's).

The rule (``benchmarks/mc_phase_rule.md``, written before its first run): per family, a seeded sample of moving
(both senses) and still val bursts, decoded by the deterministic pass and by two MC draws of the mean of the passes
(torch seeds 0 and 1), the network's own phase (still gates off, fringe orientation normal); RMSE over the truth mask
pooled by pixels. The deterministic phase is adopted when its pooled moving RMSE is at most the two draws' mean and
no family's moving or still RMSE is above :data:`COST` x it. ``scripts/choose_mc_phase.py`` runs it on a model.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from gearscan.core.phase import phase_error
from gearscan.inference.predictor import Predictor
from gearscan.twin.dataset import TwinBurstDataset

COST = 1.03
DRAWS = (0, 1)  # torch seeds of the two MC draws
KINDS = {"moving": {"reverse": True}, "still": {"static": True, "motion": "uniform", "max_span": 0}}
RULE = ("benchmarks/mc_phase_rule.md: the deterministic pass's phase when its pooled moving RMSE is at most the mean "
        "of two MC draws' and no family's moving or still RMSE is above 1.03 x it")


def mc_phase_table(model: str | None, families: dict[str, Sequence[str]], *, seed: int = 9, moving: int = 48,
                   still: int = 24, passes: int = 20,
                   progress: Callable[[str], None] | None = None) -> dict[str, dict]:
    """``table["family:kind"]`` = RMSE of the deterministic pass (``det``), of each MC draw (``mc0``, ``mc1``) and
    the draws' mean (``mc_mean_of_draws``); ``"pooled:moving"`` over every family; ``"rule"``: the verdict."""
    # one predictor: mc = 0 is the deterministic pass whatever mc_phase says; mc > 0 the mean of the passes
    pred = Predictor.load(model, orientation="normal", still_burst_rad=0.0, still_gate_rad=0.0, mc_phase="mean")
    table: dict[str, dict] = {}
    sums: dict[str, dict[str, list[float]]] = {}
    for fam, folders in families.items():
        for kind, options in KINDS.items():
            count = moving if kind == "moving" else still
            acc = {k: [0.0, 0] for k in ("det", *(f"mc{s}" for s in DRAWS))}
            for f, folder in enumerate(folders):
                ds = TwinBurstDataset(folder, **options)
                n = min(count // len(folders), len(ds))
                for i in sorted(np.random.default_rng([seed, f, kind == "still"]).choice(len(ds), n, replace=False)):
                    item = ds[int(i)]
                    x = torch.from_numpy(np.asarray(item["input"], np.float32))[None]
                    mask = np.asarray(item["mask"], bool)
                    results = {"det": pred.predict_tensor(x)}
                    for s in DRAWS:
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
              for k in ("det", *(f"mc{s}" for s in DRAWS))}
    table["pooled:moving"] = _rmse_row(pooled)
    table["rule"] = verdict(table)
    return table


def _rmse_row(acc: dict[str, list[float]]) -> dict[str, float]:
    row = {k: float(np.sqrt(v[0] / v[1])) for k, v in acc.items()}
    row["mc_mean_of_draws"] = float(np.mean([row[f"mc{s}"] for s in DRAWS]))
    return row


def verdict(table: dict[str, dict]) -> dict[str, bool]:
    """The rule on a table of :func:`mc_phase_table` (its ``"rule"`` entry ignored)."""
    rows = {k: v for k, v in table.items() if k not in ("rule", "pooled:moving")}
    pooled = table["pooled:moving"]
    c1 = pooled["det"] <= pooled["mc_mean_of_draws"]
    c2 = all(r["det"] <= COST * r["mc_mean_of_draws"] for r in rows.values())
    return {"1 pooled moving det <= MC": c1, "2 no family above 1.03x": c2, "adopt": c1 and c2}
