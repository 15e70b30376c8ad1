"""How far the fringes move per degree of rotation, per radial scene of a training plan or test family.

    python scripts/fringe_drift_stats.py                # v6's radial train sets, the dense sets, val, default family

Three-step PS fails, and the network has to decode, where the fringe phase seen at a pixel moves a
large part of a period across the burst (``benchmarks/generalization_report.md``, fringe phase
change strata). For a radial view that drift is the rim's motion in camera pixels over the camera
fringe period: ``r * dtheta`` in mm, times pixels per mm, over the period. This script computes it
at the pitch circle for every scene, from the scene's rig and gear alone (nothing is rendered for
the radial randomiser; the test family's scenes are drawn, never decoded or scored), so a training
set can be compared with the rigs it must serve before anything is trained.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from gearscan.core.gear import GearSpec
from gearscan.core.rig import Rig
from gearscan.twin.dataset import DatasetSpec, scene_for
from gearscan.twin.randomize import projector_period_for

sys.path.insert(0, str(Path(__file__).resolve().parent))
from reproduce_model import plan  # noqa: E402


def periods_per_degree(rig: Rig, gear: GearSpec, period_px: float) -> tuple[float, float]:
    """(fringe periods crossed per degree at the pitch circle, camera fringe period there in px)."""
    r = gear.pitch_radius
    a = math.radians(1.0)
    p = np.array([[r, 0.0, 0.0]])
    q = np.array([[r * math.cos(a), r * math.sin(a), 0.0]])
    moved_px = float(np.linalg.norm(rig.camera.project(q) - rig.camera.project(p)))
    camera_period = period_px / projector_period_for(rig, 1.0, r)
    return moved_px / camera_period, camera_period


def job_rows(job: tuple, size: int = 256) -> list[tuple[float, float]]:
    """One row per gear of a radial render job of ``scripts/reproduce_model.plan``."""
    _name, teeth, repeats, points, views, seed, period_range = job
    if views:
        raise ValueError(f"job {_name}: any-view sets have no single radial geometry")
    gears = [GearSpec(teeth=t) for t in teeth for _ in range(repeats)]
    spec = DatasetSpec(gears=gears, width=size, height=size, randomize=True, seed=seed, max_start_points=points,
                       radial_period_px=period_range)
    rows = []
    for i in range(len(gears)):
        rig, _optics, gear, period = scene_for(spec, i)
        rows.append(periods_per_degree(rig, gear, period))
    return rows


def summary(rows: list[tuple[float, float]]) -> dict:
    d = np.array([r[0] for r in rows])
    c = np.array([r[1] for r in rows])
    return {"scenes": len(rows), "median_periods_per_deg": float(np.median(d)),
            "p90_periods_per_deg": float(np.percentile(d, 90)), "share_ge_0.5": float(np.mean(d >= 0.5)),
            "share_ge_1": float(np.mean(d >= 1.0)), "median_camera_period_px": float(np.median(c)),
            "min_camera_period_px": float(c.min())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--default-scenes", type=int, default=16, help="scenes of the default test family")
    args = ap.parse_args()
    from gearscan.twin.families import family_scenes

    v6_train, v6_val = plan(0.7)  # v6's data (scale 0.7)
    dense_train, dense_val = plan(0.3, 3)
    sets = {
        "v6 radial train sets": [r for j in v6_train if not j[4] for r in job_rows(j)],
        "dense radial train sets": [r for j in dense_train if j[6] for r in job_rows(j)],
        "val_radial": [r for j in v6_val if not j[4] for r in job_rows(j)],
        "val_radial_dense": [r for j in dense_val if j[6] for r in job_rows(j)],
        f"default test family ({args.default_scenes} scenes)": [
            periods_per_degree(s.rig, s.gear, s.period_px) for s in family_scenes("default", args.default_scenes)],
    }
    print(json.dumps({k: summary(v) for k, v in sets.items()}, indent=1))


if __name__ == "__main__":
    main()
