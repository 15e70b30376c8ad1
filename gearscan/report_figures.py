"""The figures of ``gearscan evaluate`` (paper figure numbers in the file names).

Each function draws one figure from numbers the report's parts computed, writes it into the
report folder and returns its file name: the part lists it under ``figures``, the only images
the Markdown embeds (so it never points at a figure that was not written).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gearscan.core.phase import phase_error
from gearscan.evaluate import PAPER_MOTIONS, BurstCase


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, out: Path, name: str, **kwargs) -> str:
    """Write ``fig`` to ``out/name``, close it and return ``name``."""
    fig.savefig(out / name, **kwargs)
    pyplot().close(fig)
    return name


def masked_error(method, case: BurstCase) -> np.ndarray:
    """Phase error of ``method`` on ``case`` inside the truth mask (NaN outside)."""
    res = method(case.frames, case.full_scale, case.angles_rad)
    return np.where(case.truth.mask, phase_error(res.phase, case.truth.phase), np.nan)


def error_maps(out: Path, name: str, methods: dict, cases: list[BurstCase], scores: list) -> str:
    """|phase error| of one burst per paper motion (columns) and method (rows). Each panel's title
    carries the method's RMSE for that motion from the section's table (all its bursts), so the
    figure and the table say the same number; the map shows the first of those bursts."""
    motions = list(PAPER_MOTIONS)
    one = {m: next(c for c in cases if c.motion == m) for m in motions}
    table = {(s.method, s.motion): s for s in scores}
    plt = pyplot()
    fig, axes = plt.subplots(len(methods), len(motions), figsize=(2.6 * len(motions), 2.4 * len(methods)), dpi=100,
                             squeeze=False)
    for r, (method, fn) in enumerate(methods.items()):
        for c, motion in enumerate(motions):
            ax = axes[r][c]
            im = ax.imshow(np.abs(masked_error(fn, one[motion])), cmap="magma", vmin=0, vmax=0.5)
            ax.set_title(f"{method}\n{motion}: {table[(method, motion)].rmse_rad:.4f} rad", fontsize=8)
            ax.axis("off")
    fig.colorbar(im, ax=axes, shrink=0.6, label="|phase error| (rad)")
    n = table[(next(iter(methods)), motions[0])].bursts
    fig.suptitle(f"|phase error| of one burst ({one[motions[0]].scene.name});\n"
                 f"titles: phase RMSE (rad) over the motion's {n} burst{'s' * (n != 1)}, as in the table", fontsize=9)
    return save(fig, out, name, bbox_inches="tight")


def validation_curves(out: Path, name: str, curves: dict[str, list[float]], *, xlabel: str,
                      title: str | None = None, legend_fontsize: float | None = None) -> str:
    """Validation RMSE per epoch of small training runs (one line per run, log scale)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=100)
    for label, c in curves.items():
        ax.plot(range(1, len(c) + 1), c, marker="o", label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("validation RMSE (rad)")
    if title:
        ax.set_title(title, fontsize=9)
    ax.set_yscale("log")
    ax.legend(fontsize=legend_fontsize)
    fig.tight_layout()
    return save(fig, out, name)


def loss_curves(out: Path, name: str, histories: dict) -> str:
    """Training MSE and validation RMSE per epoch of the peer networks' runs (their metrics.json)."""
    plt = pyplot()
    fig, (a, b2) = plt.subplots(1, 2, figsize=(9, 3.2), dpi=100)
    for label, hist in histories.items():
        h = hist["history"] if isinstance(hist, dict) and "history" in hist else hist
        a.plot([x["train_mse"] for x in h], label=label)
        b2.plot([x["val_rmse"] for x in h], label=label)
    a.set_title("training MSE")
    b2.set_title("validation RMSE (rad)")
    for ax in (a, b2):
        ax.set_xlabel("epoch")
        ax.set_yscale("log")
        ax.legend(fontsize=7)
    fig.tight_layout()
    return save(fig, out, name)


def sparsification(out: Path, name: str, fractions: np.ndarray, model: list[float], oracle: list[float],
                   title: str) -> str:
    """RMSE of the remaining pixels as the most uncertain are removed, vs the oracle."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=100)
    ax.plot(fractions, model, marker="o", label="remove by predicted sigma")
    ax.plot(fractions, oracle, ls="--", label="oracle (remove by true error)")
    ax.set_xlabel("fraction of pixels removed")
    ax.set_ylabel("RMSE of the rest (rad)")
    ax.set_title(title, fontsize=9)
    ax.legend()
    fig.tight_layout()
    return save(fig, out, name)


def uncertainty_maps(out: Path, name: str, case: BurstCase, res, error: np.ndarray, title: str) -> str:
    """One burst: frame 1, mean M and D, model/data/total sigma and |error| side by side."""
    c, e = case, error
    panels = [("frame 1", c.frames[0], "gray", None), ("mean M", res.M, "coolwarm", None), ("mean D", res.D, "coolwarm", None),
              ("model sigma (rad)", res.sigma_model, "viridis", 0.2), ("data sigma (rad)", res.sigma_data, "viridis", 0.2),
              ("total sigma (rad)", res.sigma_total, "viridis", 0.2), ("|error| (rad)", np.where(c.truth.mask, np.abs(e), np.nan), "magma", 0.2)]
    plt = pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(2.4 * len(panels), 2.6), dpi=100)
    for ax, (t, img, cmap, vmax) in zip(axes, panels, strict=True):
        ax.imshow(np.where(c.truth.mask, img, np.nan) if img.dtype != np.uint8 else img, cmap=cmap, vmin=0 if vmax else None, vmax=vmax)
        ax.set_title(t, fontsize=8)
        ax.axis("off")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return save(fig, out, name)


def generalisation(out: Path, name: str, methods, scores: list, spans: dict[str, float]) -> str:
    """Phase RMSE and cloud RMS per method against the frame 1-3 span of each motion."""
    plt = pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.2), dpi=100)
    for method in methods:
        pts = sorted((spans[s.motion], s.rmse_rad, s.cloud_rms_mm or np.nan) for s in scores if s.method == method)
        a.plot([p[0] for p in pts], [p[1] for p in pts], marker="o", label=method)
        b.plot([p[0] for p in pts], [p[2] for p in pts], marker="o", label=method)
    a.set_ylabel("phase RMSE (rad)")  # the table's column names
    b.set_ylabel("cloud RMS vs truth (mm)")
    paper_span = max(d1 + d2 for d1, d2 in PAPER_MOTIONS.values())
    ticks = sorted(spans.values())
    for ax in (a, b):  # each point named by its motion, as the table's rows are
        ax.set_xticks(ticks, [f"{next(k for k, v in spans.items() if v == t)} ({t:g})" for t in ticks], fontsize=7,
                      rotation=35, ha="right")
        ax.set_xlabel("span frame 1 to 3 (deg) and motion")
        ax.axvline(paper_span, ls="--", color="grey", label=f"paper's largest span ({paper_span:g} deg)")
        ax.set_yscale("log")
    b.axhline(0.05, ls=":", color="red", label="target 0.05 mm")
    for ax in (a, b):
        ax.legend(fontsize=7)
    fig.tight_layout()
    return save(fig, out, name)

