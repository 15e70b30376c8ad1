"""Val only: moving-burst RMSE per scene (start point) of radial val folders, beside the scene's fringe drift.

    python scripts/val_per_scene.py runs/v7/best.safetensors --val data/repro/val_radial_dense data/repro/val_radial

Says which val scenes carry a model's error and whether that follows the fringe drift per degree
(``scripts/fringe_drift_stats.py``). 16 moving bursts per scene (both senses, seeded by the scene),
three-step PS beside. Chooses nothing by itself; its numbers are val numbers, never test ones.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from gearscan.core.gear import GearSpec
from gearscan.core.phase import phase_error, three_step
from gearscan.core.rig import Rig
from gearscan.inference.predictor import Predictor, fringe_phase_decreases_along_columns
from gearscan.twin.dataset import TwinBurstDataset

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fringe_drift_stats import periods_per_degree  # noqa: E402


def _rms(errors: list[np.ndarray]) -> float:
    return float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))


def scene_rows(pred: Predictor, rig_pred: Predictor, folder: Path, bursts: int) -> list[dict]:
    """Per start point: RMSE with the per-burst orientation vote (``pred``) and with the orientation
    set from the start point's still burst (``rig_pred``, as a user sets it once), and the bursts the vote misreads."""
    index = json.loads((folder / "index.json").read_text())
    rows = []
    for g, entry in enumerate(index["entries"]):
        gear = GearSpec(**entry["gear"])
        drift, cam_period = periods_per_degree(Rig.from_json(entry["rig"]), gear, entry["period_px"])
        still = TwinBurstDataset(folder, groups=[g], static=True, motion="uniform", max_span=0)[0]
        rig_mirrored = fringe_phase_decreases_along_columns(torch.from_numpy(np.asarray(still["input"], np.float32))[None])
        rig_pred.orientation = "mirrored" if rig_mirrored else "normal"
        ds = TwinBurstDataset(folder, groups=[g], reverse=True)
        pick = np.random.default_rng(g).choice(len(ds), min(bursts, len(ds)), replace=False)
        net, net_rig, ps, misread_spans = [], [], [], []
        for i in pick:
            it = ds[int(i)]
            x = torch.from_numpy(np.asarray(it["input"], np.float32))[None]
            if fringe_phase_decreases_along_columns(x) != rig_mirrored:
                misread_spans.append(round(float(it["span_deg"]), 2))
            net.append(phase_error(pred.predict_tensor(x).phase, it["phase"])[it["mask"]])
            net_rig.append(phase_error(rig_pred.predict_tensor(x).phase, it["phase"])[it["mask"]])
            ps.append(phase_error(three_step(it["input"][:3], 1.0)[0], it["phase"])[it["mask"]])
        rows.append({"folder": folder.name, "start_point": entry["id"], "teeth": gear.teeth,
                     "module": gear.module, "periods_per_deg": drift, "camera_period_px": cam_period,
                     "net": _rms(net), "net_rig_orientation": _rms(net_rig), "three_step": _rms(ps),
                     "rig_orientation": rig_pred.orientation, "bursts": len(pick), "misread_spans_deg": misread_spans})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("model", nargs="?", default=None, help="weights (.safetensors); default: the shipped model")
    ap.add_argument("--val", type=Path, nargs="+",
                    default=[Path("data/repro/val_radial_dense"), Path("data/repro/val_radial")])
    ap.add_argument("--bursts", type=int, default=16, help="moving bursts per scene")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    pred = Predictor.load(args.model, still_burst_rad=0.0)
    rig_pred = Predictor.load(args.model, orientation="normal", still_burst_rad=0.0)
    rows = [r for folder in args.val for r in scene_rows(pred, rig_pred, folder, args.bursts)]
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
