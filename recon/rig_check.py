"""What a calibration's error does to a measurement: a rig against another (the twin's truth, or a rig drawn from the
calibration's own uncertainty), read on a 20 mm cylinder turned once round as a fused revolution is.

``gearscan calibrate --twin`` compares the calibrated rig with the truth; a jointly adjusted calibration states its own
uncertainty by the same cylinder measured with rigs drawn from its covariance (:func:`calibration_uncertainty`; the
staged fit states none).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gearscan.core.rig import Rig
from gearscan.recon.unwrap import ray_depth_at_phase


def cylinder_check(estimate: Rig, truth: Rig, *, radius_mm: float = 20.0, half_height_mm: float = 10.0, points: int = 4000,
                   seed: int = 0) -> dict[str, float]:
    """What a calibration's error does to a measured revolution (twin checks): points all round a cylinder about the
    true turntable axis, each seen at an encoder angle that turns it towards the camera (+-34 deg), by the TRUE rig
    (camera pixel, projector column), are triangulated with the ESTIMATED rig and turned back about its axis, as a
    fused revolution is. Returns the radius's error about the estimated axis (bias and spread, um: what a size
    reading inherits) and the fused points' distance from the true ones after a rigid fit (RMS and 95th percentile,
    um: the smear and wobble a wrong axis puts into a revolution, size included)."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.0, 2 * np.pi, points)  # around the gear
    gear = np.stack([radius_mm * np.cos(theta), radius_mm * np.sin(theta),
                     rng.uniform(-half_height_mm, half_height_mm, points)], axis=1)
    c = truth.camera.center_world
    angle = np.arctan2(c[1], c[0]) - theta + rng.uniform(-0.6, 0.6, points)  # the encoder angle it is seen at
    cos, sin = np.cos(angle), np.sin(angle)
    world = np.stack([cos * gear[:, 0] - sin * gear[:, 1], sin * gear[:, 0] + cos * gear[:, 1], gear[:, 2]], axis=1)
    pix, lit = truth.camera.project(world), truth.projector.project(world)
    column = lit[:, 0]
    seen = truth.camera.in_frame(pix) & truth.projector.in_frame(lit)  # in both frames (a user's rig may cut some)
    cam = estimate.camera
    xy = cam.normalized(pix[seen])
    rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    z_axis = float((cam.T_from_world @ np.array([0.0, 0.0, 0.0, 1.0]))[2])
    z = ray_depth_at_phase(estimate, 1.0, rays, 2 * np.pi * column[seen], np.full(len(rays), z_axis))
    ok = np.isfinite(z)
    if not ok.any():
        raise ValueError(f"cylinder_check: the estimated rig triangulates none of the {int(seen.sum())} cylinder points "
                         "the true rig sees")
    p_world = (rays[ok] * z[ok, None]) @ cam.T_world_from[:3, :3].T + cam.T_world_from[:3, 3]  # the estimated frame
    back = -angle[seen][ok]  # turned back about the estimated axis by each point's encoder angle: the fused gear
    fused = np.stack([np.cos(back) * p_world[:, 0] - np.sin(back) * p_world[:, 1],
                      np.sin(back) * p_world[:, 0] + np.cos(back) * p_world[:, 1], p_world[:, 2]], axis=1)
    radius = 1e3 * (np.hypot(fused[:, 0], fused[:, 1]) - radius_mm)
    # its shape: the fused gear rigidly fitted to the true one (where each frame puts angle zero and its origin is a
    # convention); what is left is what the calibration does to a fused revolution, size included
    true = gear[seen][ok]
    a, b = fused - fused.mean(axis=0), true - true.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    rot = (u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt).T
    shape = 1e3 * np.linalg.norm(a @ rot.T - b, axis=1)
    return {"points": int(ok.sum()), "of": points, "radius_bias_um": float(radius.mean()),
            "radius_spread_um": float(radius.std()), "shape_rms_um": float(np.sqrt(np.mean(shape**2))),
            "shape_p95_um": float(np.percentile(shape, 95))}


def compare_rigs(estimate: Rig, truth: Rig) -> dict[str, float]:
    """Differences between a calibrated rig and the true one (twin checks).

    Axis error compares the turntable z axis seen from the camera (world z in camera frame).
    """
    za = estimate.camera.T_from_world[:3, :3] @ np.array([0.0, 0.0, 1.0])
    zb = truth.camera.T_from_world[:3, :3] @ np.array([0.0, 0.0, 1.0])
    axis = float(np.degrees(np.arccos(np.clip(za @ zb, -1.0, 1.0))))
    return {
        "baseline_rel_error": abs(estimate.baseline_mm - truth.baseline_mm) / truth.baseline_mm,
        "axis_error_deg": axis,
        "camera_center_error_mm": float(np.linalg.norm(estimate.camera.center_world - truth.camera.center_world)),
        "projector_center_error_mm": float(np.linalg.norm(estimate.projector.center_world - truth.projector.center_world)),
    }


def calibration_uncertainty(rig: Rig, draws: Sequence[Rig], variance_factor: float, *, factor: float = 1.0) -> dict:
    """The calibration's own contribution to a measurement, from rigs drawn from its fit's covariance: each draw
    measures the 20 mm cylinder of :func:`cylinder_check` as ``rig`` sees it. ``radius_um``: the draws' radius
    readings' standard deviation (k = 1); ``shape_rms_um_p95``: the 95th percentile of their fused-shape RMS; the
    spread of the baseline, focal lengths and axis direction beside. ``factor`` multiplies every spread (1: the
    covariance as fitted; its origin belongs in the caller's report); ``variance_factor`` (already in the draws) is
    recorded. Corner noise only, each corner's independent of the others': the encoder's angles are trusted, the lens
    model taken as right, and the projector's corners, sampled at the camera's, share the camera's detection error
    (``benchmarks/calibration_uncertainty_rule.md`` tests the statement as a whole). Refused (ValueError) where a
    draw triangulates under 90 % of the points ``rig`` does: a covariance that wide is beyond its linearisation."""
    if len(draws) < 2:
        raise ValueError(f"calibration_uncertainty: {len(draws)} drawn rigs; expected at least 2")
    own = cylinder_check(rig, rig)["points"]
    cyl = [cylinder_check(d, rig) for d in draws]
    lost = min(c["points"] for c in cyl)
    if lost < 0.9 * own:
        raise ValueError(f"a drawn calibration triangulates {lost} of the {own} cylinder points the calibration does: "
                         "its covariance is too wide to state (add views)")
    radius = np.array([c["radius_bias_um"] for c in cyl])
    shape = np.array([c["shape_rms_um"] for c in cyl])
    z = np.array([0.0, 0.0, 1.0])
    axis = [np.degrees(np.arccos(np.clip((d.camera.T_from_world[:3, :3] @ z) @ (rig.camera.T_from_world[:3, :3] @ z),
                                         -1.0, 1.0))) for d in draws]
    return {
        "draws": len(draws), "variance_factor": float(variance_factor), "factor": float(factor),
        "radius_um": float(factor * radius.std(ddof=1)),
        "shape_rms_um_median": float(factor * np.median(shape)),
        "shape_rms_um_p95": float(factor * np.percentile(shape, 95)),
        "baseline_mm": float(factor * np.std([d.baseline_mm for d in draws], ddof=1)),
        "camera_focal_pct": float(factor * 100 * np.std([d.camera.K[0, 0] for d in draws], ddof=1) / rig.camera.K[0, 0]),
        "projector_focal_pct": float(factor * 100 * np.std([d.projector.K[0, 0] for d in draws], ddof=1)
                                     / rig.projector.K[0, 0]),
        "axis_deg_rms": float(factor * np.sqrt(np.mean(np.square(axis)))),
    }
