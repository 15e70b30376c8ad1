"""How much of each board corner's residual is fixed by its pose (a look; chooses nothing).

    .venv/bin/python scripts/calibration_residual_split.py [--views narrow] [--seeds 1,2,3]

Calibrates the twin's default rig from the same board poses rendered with several sensor-noise seeds (the product fit)
and splits each device's residual per coordinate into its whole RMS and the part that differs between two seeds
(pairwise differences over sqrt 2). What the seeds share is fixed by the poses: a test over render seeds with repeated
poses samples only the rest (benchmarks/calibration_uncertainty_rule.md, amendment).

Session 56, ``--views narrow --seeds 1,2,3`` (the 16 views then shipped), AMD EPYC host: camera 0.0207 / 0.0199 /
0.0204 px in all, 0.0092-0.0095 px differing; projector 0.0378 / 0.0360 / 0.0368 px in all, 0.0171-0.0175 px differing.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from calibration_accuracy import SHIPPED_VIEWS, VIEW_SETS, seed_list  # noqa: E402

from gearscan.core.rig import default_rig  # noqa: E402
from gearscan.recon.calibration import Checkerboard, calibrate_rig, decode_capture  # noqa: E402
from gearscan.twin.board import calibration_poses, render_calibration_set  # noqa: E402
from gearscan.twin.render import Optics  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", choices=list(VIEW_SETS), default=SHIPPED_VIEWS)
    ap.add_argument("--seeds", type=seed_list, default=[1, 2, 3])
    args = ap.parse_args()
    rig, board = default_rig(), Checkerboard()
    proj = (rig.projector.width, rig.projector.height)
    poses = calibration_poses(rig, board, turntable_angles_deg=VIEW_SETS[args.views])
    res = {}
    for seed in args.seeds:
        views = [decode_capture(c, proj) for c in render_calibration_set(rig, board, Optics(), steps=12, seed=seed,
                                                                          poses=poses)]
        fit = calibrate_rig(views, board, (rig.camera.width, rig.camera.height), proj)
        res[seed] = (np.concatenate(fit.residuals_camera), np.concatenate(fit.residuals_projector))
    for d, name in enumerate(("camera", "projector")):
        whole = [float(np.sqrt(np.mean(res[s][d] ** 2))) for s in args.seeds]
        apart = [float(np.sqrt(np.mean((res[a][d] - res[b][d]) ** 2) / 2))
                 for a, b in itertools.combinations(args.seeds, 2)]
        print(f"{name}: per coordinate {np.round(whole, 4).tolist()} px in all, {np.round(apart, 4).tolist()} px "
              "differing between seeds")


if __name__ == "__main__":
    main()
