"""A val look (chooses nothing): does averaging the network over a burst and its row-mirrored copy lower its error?

    .venv/bin/python scripts/tta_look.py [--items 48] [--out benchmarks/tta_look.json]

Mirroring a burst's rows (top to bottom) keeps the fringes' direction along the columns and the frames' order, so the
mirrored burst is a physical scene of the kind the network trained on (a mirror-image rig, the gear turning the other
way as seen). Decoding both and mapping the second back gives two estimates of one phase; their circular mean (plain,
or weighted by each pass's inverse variance) is test-time augmentation at twice the deterministic cost. Mirroring the
columns would reverse the fringe direction (the mirrored-rig case the orientation handles), and reversing the frames
would move the phase's pose to the last frame, so neither is a valid copy. Val only, rig orientation, no still-burst
gate (the network's own phase), the seeded sample of ``scripts/val_compare.py``.

Session 53 (``--items 24`` -> ``benchmarks/tta_look.json``, AMD host): the mirrored copy's phase is nearly the same
as the network's (v9 is close to equivariant to the row mirror), so its errors are too: the weighted mean lowers the
moving RMSE by 0.3-1.2 % per val set (val_radial 0.0930 -> 0.0919, the default rig's z62 0.1551 -> 0.1539) for twice the
decode. Not worth a sigma-map refit and the depth tables anew: nothing was built on it.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from gearscan.core.phase import phase_error, three_step
from gearscan.inference.predictor import Predictor
from gearscan.twin.dataset import TwinBurstDataset

SETS = ["data/repro/val_radial", "data/repro/val_views", *(f"data/default_rig/val/z{z}" for z in (25, 32, 46, 62))]


def rms(errs: list[np.ndarray]) -> float:
    return float(np.sqrt(np.mean(np.concatenate(errs).astype(np.float64) ** 2)))


def combine(p1: np.ndarray, p2: np.ndarray, w1: np.ndarray | float = 1.0, w2: np.ndarray | float = 1.0) -> np.ndarray:
    """The weighted circular mean of two wrapped phases."""
    return np.arctan2(w1 * np.sin(p1) + w2 * np.sin(p2), w1 * np.cos(p1) + w2 * np.cos(p2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--items", type=int, default=48, help="moving bursts per set (still: half)")
    ap.add_argument("--model", default=None)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    pred = Predictor.load(args.model, orientation="normal", still_burst_rad=0.0)
    t0 = time.perf_counter()
    out = {}
    for path in SETS:
        moving = TwinBurstDataset(path, reverse=True)
        still = TwinBurstDataset(path, static=True, motion="uniform", max_span=0)
        pick = np.random.default_rng(0).choice(len(moving), min(args.items, len(moving)), replace=False)
        still_pick = np.random.default_rng(1).choice(len(still), min(args.items // 2, len(still)), replace=False)
        for kind, items in (("moving", [moving[int(i)] for i in sorted(pick)]),
                            ("still", [still[int(i)] for i in sorted(still_pick)])):
            err: dict[str, list[np.ndarray]] = {k: [] for k in ("three-step", "net", "mirrored", "mean", "weighted")}
            for it in items:
                x = torch.from_numpy(np.asarray(it["input"], np.float32))[None]
                m, truth = it["mask"], it["phase"]
                a = pred.predict_tensor(x)
                b = pred.predict_tensor(torch.flip(x, dims=[-2]))
                pb, sb = np.flip(b.phase, -2), np.flip(b.sigma_total, -2)
                est = {"three-step": three_step(it["input"][:3], 1.0)[0], "net": a.phase, "mirrored": pb,
                       "mean": combine(a.phase, pb),
                       "weighted": combine(a.phase, pb, 1 / np.maximum(a.sigma_total, 1e-6) ** 2,
                                           1 / np.maximum(sb, 1e-6) ** 2)}
                for k, v in est.items():
                    err[k].append(phase_error(v, truth)[m])
            row = {k: rms(v) for k, v in err.items()} | {"bursts": len(items)}
            out[f"{path} {kind}"] = row
            print(f"{path} {kind}: " + ", ".join(f"{k} {v:.4f}" for k, v in row.items() if k != "bursts"), flush=True)
    out["seconds"] = time.perf_counter() - t0
    if args.out:
        args.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
