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

    Writes the rig file (with a "calibration_report" of per-view reprojection errors and the
    calibration's own uncertainty), a residual plot <output>.residuals.png and the Unity twin
    parameters <output>.unity.json (paper Table 1). With --twin, the board is rendered by the
    digital twin of that rig first, so the whole workflow can be tried without hardware and
    checked against it.

    Views: the twin's set, measured best of three on hand-placed boards, is 11 free-hand views
    across the field (tilted up to 18 deg, reaching the image edges) and 13 on the turntable,
    the board through the axis facing the camera, turned -45 to +45 deg every 7.5 deg.
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
    console.print(uncertainty_line(rep["uncertainty"]))
    if "angle_error_deg_rms" in rep.get("turntable_axis", {}):
        scale = joint.get("encoder_scale")
        console.print(f"turntable: the board's rotations agree with the encoder angles within "
                      f"{rep['turntable_axis']['angle_error_deg_rms']:.3f} deg RMS (staged fit)"
                      + ("" if scale is None else f"; their scale, fitted jointly: {scale:.5f}"))
    if joint.get("encoder_warning"):
        console.print(f"[yellow]warning:[/yellow] {joint['encoder_warning']}")
    if len(rep["views_used"]) < FEW_VIEWS:
        console.print(f"[yellow]warning:[/yellow] only {len(rep['views_used'])} usable views: the RMS above says "
                      "nothing about what so few leave unconstrained, the uncertainty above does (on the twin, OpenCV's "
                      "staged fit put the turntable axis 0.33 and 1.58 deg off with two choices of 3 views where 16 put "
                      f"it 0.035-0.077 deg); use {FEW_VIEWS} or more, spread over the image and the turntable (the twin's "
                      "set: 11 free-hand, 13 on the turntable over +-45 deg)")
    if truth is not None:
        console.print(truth_line(result.rig, truth))
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


def uncertainty_line(unc: dict) -> str:
    """The calibration's own uncertainty (the report's ``uncertainty``, :func:`gearscan.recon.rig_check.
    calibration_uncertainty`) as one console line, or why it is not stated."""
    if not unc.get("stated"):
        return f"calibration uncertainty: not stated ({unc.get('why', 'unknown')})"
    return (f"calibration uncertainty (corner noise through the joint adjustment, {unc['draws']} drawn calibrations): a "
            f"20 mm radius +-{2 * unc['radius_um']:.1f} um (k = 2), fused shape up to {unc['shape_rms_um_p95']:.1f} um "
            f"RMS (95 %), baseline +-{2e3 * unc['baseline_mm']:.1f} um (k = 2), axis direction "
            f"{unc['axis_deg_rms']:.3f} deg RMS; lens-model errors and the encoder's not included")


def truth_line(rig, truth) -> str:
    """``calibrate --twin``: the calibrated rig against the twin's truth, by the rigs' differences and by a 20 mm
    cylinder turned once round (:func:`gearscan.recon.rig_check.cylinder_check`), as one console line."""
    from gearscan.recon.rig_check import compare_rigs, cylinder_check

    cmp = compare_rigs(rig, truth)
    head = f"vs twin truth: baseline error {cmp['baseline_rel_error'] * 100:.4f} %, axis error {cmp['axis_error_deg']:.4f} deg"
    try:
        cyl = cylinder_check(rig, truth)
    except ValueError as exc:  # a rig so far off it triangulates none of the cylinder: said, the files stand
        return f"{head}; {exc}"
    return (f"{head}; a 20 mm cylinder turned once round, seen by the true rig and measured with this one: radius "
            f"{cyl['radius_bias_um']:+.1f} um (spread {cyl['radius_spread_um']:.1f} um), shape {cyl['shape_rms_um']:.1f} "
            f"um RMS after a rigid fit (p95 {cyl['shape_p95_um']:.1f} um)")
