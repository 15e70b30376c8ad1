"""`gearscan calibrate`: camera-projector-turntable calibration from captures, or from the twin's rendering of a rig.

An app command because ``--twin`` joins two stages (the twin renders the board, recon calibrates it).
Only light imports at module level; numpy, OpenCV, open3d and the twin load inside.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def calibrate(
    captures: Annotated[
        Path | None,
        typer.Argument(help="Folder of board captures (format: gearscan.recon.board_io). With --twin, where to write the synthetic set."),
    ] = None,
    output: Annotated[Path, typer.Option("--output", "-o", help="Rig calibration file to write (JSON).")] = Path("rig.json"),
    twin: Annotated[
        Path | None,
        typer.Option("--twin", help="Render a synthetic calibration set from this rig file (or 'default') and calibrate it."),
    ] = None,
    noise_free: Annotated[bool, typer.Option(help="With --twin: render without sensor noise.")] = False,
    steps: Annotated[int, typer.Option(min=3, help="With --twin: phase steps per fringe period.")] = 12,
    camera_pixel_um: Annotated[float, typer.Option(help="Camera pixel pitch for the Unity export, micrometres.")] = 3.45,
    projector_pixel_um: Annotated[float, typer.Option(help="Projector pixel pitch for the Unity export, micrometres.")] = 7.6,
    period: Annotated[float, typer.Option(min=1.0, help="Fringe period (projector px) the rig will measure with: states its unambiguous depth range.")] = 40.0,
) -> None:
    """Calibrate camera, projector and turntable axis from checkerboard captures.

    Writes the rig file (with a "calibration_report" of per-view reprojection errors), a
    residual plot <output>.residuals.png and the Unity twin parameters <output>.unity.json
    (paper Table 1). With --twin, the board is rendered by the digital twin of that rig
    first, so the whole workflow can be tried without hardware and checked against it.
    """
    import json
    import tempfile

    from rich.console import Console

    from gearscan.core.rig import Rig, RigError, default_rig
    from gearscan.recon.board_io import load_captures, save_captures
    from gearscan.recon.calibration import (
        FEW_VIEWS,
        CalibrationError,
        calibrate_rig,
        decode_capture,
        plot_residuals,
        save_calibration,
    )
    from gearscan.recon.unity import unity_parameters

    console = Console()
    if output.is_dir():  # before any work: the rig file is written there at the end
        raise typer.BadParameter(f"{output} is a folder; expected the rig JSON file to write", param_hint="--output")
    truth = None
    if twin is not None:
        from gearscan.twin.board import render_calibration_set
        from gearscan.twin.render import Optics

        try:
            truth = default_rig() if str(twin) == "default" else Rig.load(twin)
        except RigError as exc:
            raise typer.BadParameter(str(exc), param_hint="--twin") from exc
        optics = Optics().noise_free() if noise_free else Optics()
        folder = captures or Path(tempfile.mkdtemp(prefix="gearscan-board-"))
        with console.status("rendering the calibration board in the twin"):
            caps = render_calibration_set(truth, optics=optics, steps=steps)
            from gearscan.recon.calibration import Checkerboard

            save_captures(folder, caps, Checkerboard(), (truth.projector.width, truth.projector.height), optics.bit_depth)
        console.print(f"twin captures written to {folder}")
        captures = folder
    if captures is None:
        raise typer.BadParameter("give a captures folder, or --twin RIG to render one", param_hint="CAPTURES")
    try:
        caps, board, cam_size, proj_size = load_captures(captures)
    except (FileNotFoundError, ValueError) as exc:
        raise typer.BadParameter(str(exc), param_hint="CAPTURES") from exc
    with console.status(f"decoding {len(caps)} board views"):
        try:
            views = [decode_capture(c, proj_size) for c in caps]
        except (ValueError, CalibrationError) as exc:  # periods_u/periods_v none of which covers the projector
            raise typer.BadParameter(f"{captures / 'board.json'}: {exc}", param_hint="CAPTURES") from exc
    try:
        result = calibrate_rig(views, board, cam_size, proj_size)
    except CalibrationError as exc:
        console.print(f"[red]calibration failed:[/red] {exc}")
        raise typer.Exit(1) from exc
    output.parent.mkdir(parents=True, exist_ok=True)
    save_calibration(result, output)
    plot_path = output.with_suffix(".residuals.png")
    plot_residuals(result, plot_path)
    unity_path = output.with_suffix(".unity.json")
    unity_path.write_text(json.dumps(unity_parameters(result.rig, camera_pixel_um / 1000, projector_pixel_um / 1000), indent=2))
    rep = result.report
    joint = rep.get("joint_adjustment", {})
    how = ("adjusted jointly" if joint.get("run") and "why" not in joint
           else f"staged fit: {joint.get('why', 'no joint adjustment')}")
    console.print(
        f"camera RMS {rep['camera_rms_px']:.3f} px, projector RMS {rep['projector_rms_px']:.3f} px ({how}; staged "
        f"stereo RMS {rep['staged']['stereo_rms_px']:.3f} px), baseline {rep['baseline_mm']:.3f} mm, "
        f"{len(rep['views_used'])} views used, {len(rep['views_skipped'])} skipped"
    )
    lens = rep.get("lens_model", {})
    if lens:
        console.print("lens models (chosen on held-out views): " + ", ".join(
            f"{dev} {m['chosen']}" + (f" ({m['why']})" if m["chosen"] != "given" and "heldout_rms_px" not in m else "")
            for dev, m in lens.items()))
    if "angle_error_deg_rms" in rep.get("turntable_axis", {}):
        scale = joint.get("encoder_scale")
        console.print(f"turntable: the board's rotations agree with the encoder angles within "
                      f"{rep['turntable_axis']['angle_error_deg_rms']:.3f} deg RMS (staged fit)"
                      + ("" if scale is None else f"; their scale, fitted jointly: {scale:.5f}"))
    if joint.get("encoder_warning"):
        console.print(f"[yellow]warning:[/yellow] {joint['encoder_warning']}")
    if len(rep["views_used"]) < FEW_VIEWS:
        console.print(f"[yellow]warning:[/yellow] only {len(rep['views_used'])} usable views: the RMS above says "
                      "nothing about what so few leave unconstrained (on the twin, OpenCV's staged fit put the turntable "
                      f"axis 0.33 and 1.58 deg off with two choices of 3 views where 16 put it 0.035-0.077 deg); use {FEW_VIEWS} or more, "
                      "spread over the image and "
                      "the turntable")
    if truth is not None:
        cmp = compare_rigs(result.rig, truth)
        cyl = cylinder_check(result.rig, truth)
        console.print(
            f"vs twin truth: baseline error {cmp['baseline_rel_error'] * 100:.4f} %, "
            f"axis error {cmp['axis_error_deg']:.4f} deg; a 20 mm cylinder turned once round, seen by the true rig and "
            f"measured with this one: radius {cyl['radius_bias_um']:+.1f} um (spread {cyl['radius_spread_um']:.1f} um), "
            f"shape {cyl['shape_rms_um']:.1f} um RMS after a rigid fit (p95 {cyl['shape_p95_um']:.1f} um)"
        )
    console.print(depth_range_line(result.rig, period))
    console.print(f"wrote {output}, {plot_path}, {unity_path}")


def depth_range_line(rig, period_px: float) -> str:
    """How far along the camera rays one fringe order reaches, at the turntable axis's depth:
    the depth a surface may stray from its prior (CAD or coarse burst) and keep its fringe order
    (the projector's lens distortion included)."""
    import numpy as np

    from gearscan.recon.unwrap import unambiguous_depth_window

    z_axis = float((rig.camera.T_from_world @ np.array([0.0, 0.0, 0.0, 1.0]))[2])
    depth = np.full((rig.camera.height, rig.camera.width), z_axis)
    lo, hi = unambiguous_depth_window(rig, period_px, depth)
    ok = np.isfinite(lo) & np.isfinite(hi)
    if not ok.any():
        return f"unambiguous depth range: not stated (no projector fringe reaches the image at the axis depth {z_axis:.0f} mm)"
    minus, plus = (depth - lo)[ok], (hi - depth)[ok]
    return (f"unambiguous depth range at {period_px:g} px fringes, {z_axis:.0f} mm from the camera (the turntable axis): "
            f"-{np.median(minus):.2f}/+{np.median(plus):.2f} mm (median over the image; at least "
            f"-{minus.min():.2f}/+{plus.min():.2f} mm); wider fringes widen it in proportion")


def cylinder_check(estimate, truth, *, radius_mm: float = 20.0, half_height_mm: float = 10.0, points: int = 4000,
                   seed: int = 0) -> dict[str, float]:
    """What a calibration's error does to a measured revolution (twin checks): points all round a cylinder about the
    true turntable axis, each seen at an encoder angle that turns it towards the camera (+-34 deg), by the TRUE rig
    (camera pixel, projector column), are triangulated with the ESTIMATED rig and turned back about its axis, as a
    fused revolution is. Returns the radius's error about the estimated axis (bias and spread, um: what a size
    reading inherits) and the fused points' distance from the true ones after a rigid fit (RMS and 95th percentile,
    um: the smear and wobble a wrong axis puts into a revolution, size included)."""
    import numpy as np

    from gearscan.recon.unwrap import ray_depth_at_phase

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


def compare_rigs(estimate, truth) -> dict[str, float]:
    """Differences between a calibrated rig and the true one (twin checks).

    Axis error compares the turntable z axis seen from the camera (world z in camera frame).
    """
    import numpy as np

    za = estimate.camera.T_from_world[:3, :3] @ np.array([0.0, 0.0, 1.0])
    zb = truth.camera.T_from_world[:3, :3] @ np.array([0.0, 0.0, 1.0])
    axis = float(np.degrees(np.arccos(np.clip(za @ zb, -1.0, 1.0))))
    return {
        "baseline_rel_error": abs(estimate.baseline_mm - truth.baseline_mm) / truth.baseline_mm,
        "axis_error_deg": axis,
        "camera_center_error_mm": float(np.linalg.norm(estimate.camera.center_world - truth.camera.center_world)),
        "projector_center_error_mm": float(np.linalg.norm(estimate.projector.center_world - truth.projector.center_world)),
    }
