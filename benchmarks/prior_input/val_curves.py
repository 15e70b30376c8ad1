"""The val side of the prior-input experiment (issue 13, item 6): each run's val RMSE per epoch and how
much its first conv weighs the prior's channels.

    .venv/bin/python benchmarks/prior_input/val_curves.py

Reads the training logs copied beside this file (``<run>_metrics.csv``) and, where present, the runs'
weights under ``runs/``; writes ``val_report.md`` here. Val only (48 val bursts, the same for every run):
it applies the rule in ``choice_rule.md``; the test numbers are in ``benchmarks/prior_input_report.md``.
"""

from __future__ import annotations

import csv
import math
import subprocess
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
PAIRS = {  # pair: (prior run, control run, what each started from)
    "fine-tune of v6": ("finetune_prior", "finetune_control", "v6"),
    "from scratch": ("scratch_prior", "scratch_control", "random init"),
}
RUNS = {"finetune_prior": "runs/prior_input", "finetune_control": "runs/prior_control",
        "scratch_prior": "runs/prior_scratch", "scratch_control": "runs/control_scratch"}
FRAMES, PRIOR = slice(0, 3), slice(3, 10)  # first-conv input channels: frames, then the 7 prior channels


def curve(run: str) -> list[dict]:
    with open(HERE / f"{run}_metrics.csv") as f:
        return [{k: float(v) if v not in ("", "nan") else math.nan for k, v in row.items()} for row in csv.DictReader(f)]


def stem_weights(run: str) -> tuple[float, float] | None:
    """Mean |w| of the first conv over the frame channels and over the prior channels (best weights)."""
    path = REPO / RUNS[run] / "best.safetensors"
    if not path.is_file():
        return None
    from safetensors.torch import load_file

    w = load_file(str(path))["encoder.stem.0.weight"].abs().mean(dim=(0, 2, 3))
    return float(w[FRAMES].mean()), float(w[PRIOR].mean())


def main() -> None:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    lines = ["# The twin's prediction as network input: val (issue 13, item 6)", "",
             f"`python benchmarks/prior_input/val_curves.py`; commit `{commit}`. Val only: 48 bursts of "
             "`data/repro/val_radial` + `val_views` (the same for every run), the training logs' val RMSE (rad). "
             "Rule and commands: `choice_rule.md`.", ""]
    for pair, (p_run, c_run, start) in PAIRS.items():
        p, c = curve(p_run), curve(c_run)
        p_tr, c_tr = [r for r in p if r["epoch"] > 0], [r for r in c if r["epoch"] > 0]  # trained epochs
        n = min(len(p_tr), len(c_tr))
        p_best = min((r["val_rmse"], int(r["epoch"])) for r in p)
        c_best = min((r["val_rmse"], int(r["epoch"])) for r in c)
        p_run_best = min((r["val_rmse"], int(r["epoch"])) for r in p_tr[:n])
        c_run_best = min((r["val_rmse"], int(r["epoch"])) for r in c_tr[:n])
        ratio = p_best[0] / c_best[0]
        lines += [f"## {pair} (from {start})", "",
                  f"- Epochs trained: prior {len(p_tr)}, control {len(c_tr)} (100 steps of 8 each)"
                  + ("; epoch 0 is the starting point, validated before training." if len(p) > len(p_tr) else "."),
                  f"- Best val RMSE: prior {p_best[0]:.4f} (epoch {p_best[1]}), control {c_best[0]:.4f} "
                  f"(epoch {c_best[1]}): ratio **{ratio:.3f}**; the rule needs <= 0.9: "
                  f"**{'met' if ratio <= 0.9 else 'not met'}**.",
                  f"- Best over the first {n} trained epochs of both: prior {p_run_best[0]:.4f} "
                  f"(epoch {p_run_best[1]}), control {c_run_best[0]:.4f} (epoch {c_run_best[1]}); mean over them: "
                  f"prior {sum(r['val_rmse'] for r in p_tr[:n]) / n:.4f}, control {sum(r['val_rmse'] for r in c_tr[:n]) / n:.4f}."]
        w = stem_weights(p_run)
        if w is not None and p_best[1] > 0:
            lines.append(f"- First conv of the prior run's best weights, mean |w| per input channel: frames "
                         f"{w[0]:.4f}, prior channels {w[1]:.4f} ({w[1] / w[0]:.2f}x).")
        elif w is not None:
            lines.append("- The prior run's best weights are its starting point (the prior channels zero-weighted).")
        rows_p, rows_c = p[: len(p) - len(p_tr) + n : 5], c[: len(c) - len(c_tr) + n : 5]
        lines += ["", "| epoch | " + " | ".join(str(int(r["epoch"])) for r in rows_p) + " |",
                  "|---|" + "---|" * len(rows_p),
                  "| prior | " + " | ".join(f"{r['val_rmse']:.3f}" for r in rows_p) + " |",
                  "| control | " + " | ".join(f"{r['val_rmse']:.3f}" for r in rows_c) + " |", ""]
    (HERE / "val_report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
