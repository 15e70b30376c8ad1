"""Figure of a training run (loss curves, validation RMSE per epoch), apart from the loop."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_history(history: list[dict], path: str | Path) -> Path:
    """Loss curves (train total, val loss) and val RMSE per epoch, stage boundaries dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    x = np.arange(1, len(history) + 1)
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.4), dpi=110)
    a.plot(x, [h["train_total"] for h in history], label="train loss")
    a.plot(x, [h["val_loss"] for h in history], label="val loss (no reg)")
    a.set_yscale("symlog", linthresh=1e-6)
    b.plot(x, [h["val_rmse"] for h in history], color="C2")
    b.set_ylabel("val wrapped RMSE (rad)")
    if all(h["val_rmse"] > 0 for h in history):
        b.set_yscale("log")
    for ax in (a, b):
        ax.set_xlabel("epoch")
        for i in range(1, len(history)):
            if history[i]["stage"] != history[i - 1]["stage"]:
                ax.axvline(i + 0.5, ls="--", color="grey")
    a.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
