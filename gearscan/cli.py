"""The ``gearscan`` command line (typer). Heavy imports happen inside the commands."""

from __future__ import annotations

import importlib
import logging
import math
from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(
    help="Fringe-projection measurement of rotating gears with CD-DCU-Net motion correction.",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
)
twin_app = typer.Typer(help="Digital twin: render recordings and training datasets.", no_args_is_help=True)


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            typer.echo(f"gearscan {version('gearscan')}")
        except PackageNotFoundError:  # run from a source tree that was never installed
            typer.echo("gearscan (version unknown: not installed; run `pip install -e .`)")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True, help="print the version and exit")] = False,
) -> None:
    """Fringe-projection measurement of rotating gears with CD-DCU-Net motion correction."""


app.add_typer(twin_app, name="twin")


def _fail(msg: str) -> typer.Exit:
    typer.secho(f"error: {msg}", fg=typer.colors.RED, err=True)
    return typer.Exit(code=2)


def _writable(path: Path | None, flag: str, *, folder: bool = False) -> None:
    """Fail now, naming ``flag``, where ``path`` (a file, or with ``folder`` a folder) cannot be written: its folder made
    and a file created and removed there. Checked before a run, not found after its work is done."""
    import tempfile

    if path is None:
        return
    where = path if folder else path.parent
    if (folder and path.exists() and not path.is_dir()) or (not folder and path.is_dir()):
        raise _fail(f"{flag}: {path} is {'not ' if folder else ''}a folder; expected a {'folder' if folder else 'file'}")
    try:
        where.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=where, prefix=".gearscan-write-check-"):
            pass
    except OSError as exc:
        raise _fail(f"{flag}: cannot write to {where} ({exc.strerror or exc})") from exc


def _connect_url(url: str | None, flag: str) -> str | None:
    """``url`` if the viewer can connect to it (None: no --connect), else exit 2 naming ``flag``."""
    if url is None:
        return None
    from gearscan.viewer.log import check_connect_url

    try:
        return check_connect_url(url)
    except ValueError as exc:
        raise _fail(f"{flag}: {exc}") from exc


def _require_recording(recording: Path) -> None:
    """Exit 2 where ``recording`` holds no recording: said before any output folder is made for it."""
    if not (recording / "recording.json").is_file():
        raise _fail(f"{recording} is not a recording: recording.json is missing")


def _progress(description: str):
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    return Progress(TextColumn(description), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(), transient=False)


def _gear_from_options(teeth: int, module: float, pressure_angle: float, face_width: float, bore: float):
    from pydantic import ValidationError

    from gearscan.core.gear import GearSpec

    try:
        return GearSpec(teeth=teeth, module=module, pressure_angle_deg=pressure_angle, face_width=face_width, bore=bore)
    except ValidationError as exc:
        raise _fail("invalid gear: " + "; ".join(f"{'.'.join(map(str, e['loc'])) or 'gear'}: {e['msg']}" for e in exc.errors())) from exc


@twin_app.command("render")
def twin_render(
    out: Annotated[Path, typer.Argument(help="recording folder to write")],
    motion: Annotated[str, typer.Option(help="uniform:DEG | nonuniform:D1,D2[,GAP] | angles:A,B,C,... | static")] = "uniform:0.6",
    bursts: Annotated[int, typer.Option(min=1, help="number of three-frame bursts")] = 4,
    teeth: Annotated[int, typer.Option(help="number of teeth (>= 6)")] = 20,
    module: Annotated[float, typer.Option(help="module, mm")] = 2.0,
    pressure_angle: Annotated[float, typer.Option(help="pressure angle, degrees")] = 20.0,
    face_width: Annotated[float, typer.Option(help="face width, mm")] = 20.0,
    bore: Annotated[float, typer.Option(help="bore diameter, mm")] = 10.0,
    rig: Annotated[Path | None, typer.Option(help="rig calibration JSON (default: the built-in rig)")] = None,
    width: Annotated[int | None, typer.Option(help="camera width, px (default 512; with --rig: the camera's; another rescales the rig)")] = None,
    height: Annotated[int | None, typer.Option(help="camera height, px (default 512; with --rig: the camera's)")] = None,
    period: Annotated[float, typer.Option(help="fringe period, projector px")] = 40.0,
    start: Annotated[float, typer.Option(help="start angle, degrees")] = 0.0,
    noise: Annotated[bool, typer.Option(help="camera shot + read noise")] = True,
    motion_blur: Annotated[bool, typer.Option(help="integrate motion during the exposure")] = False,
    seed: Annotated[int, typer.Option()] = 0,
    overwrite: Annotated[bool, typer.Option(help="replace an existing recording")] = False,
    defects: Annotated[Path | None, typer.Option(help="as-built defects JSON (GearDefects fields); the options below add to it")] = None,
    eccentricity_um: Annotated[float | None, typer.Option(help="defect: gear axis this far from the turntable axis, µm")] = None,
    pitch_error: Annotated[list[str] | None, typer.Option(help="defect TOOTH:UM: that tooth turned along the pitch circle (repeat)")] = None,
    chip: Annotated[list[str] | None, typer.Option(help="defect TOOTH:MM[:SIDE[:ZMIN:ZMAX]]: tip corner chipped (repeat)")] = None,
    wear: Annotated[list[str] | None, typer.Option(help="defect TOOTH:UM[:SIDE]: flank worn this deep mid-flank (repeat)")] = None,
    true_module: Annotated[float | None, typer.Option(help="defect: as-built module, mm (the recording states --module as CAD)")] = None,
    coarse_period: Annotated[float | None, typer.Option(help="also a coarse three-step burst at this period (projector px), first and then every --coarse-every bursts: CAD-free unwrapping (replay --unwrap coarse)")] = None,
    coarse_every: Annotated[int, typer.Option(min=1, help="with --coarse-period: bursts between coarse bursts")] = 4,
    alternate_order: Annotated[bool, typer.Option(help="every other burst shows its patterns as 0, 2, 1 (as live's projector.alternate_order): the fused model's frame fit then fits nearly every point")] = False,
) -> None:
    """Render a twin recording of a rotating gear (frames, encoder, ground truth), optionally with known defects."""
    from gearscan.core.recording import RecordingError
    from gearscan.core.rig import Rig, RigError, default_rig
    from gearscan.twin.defects import GearDefects
    from gearscan.twin.motion import MotionError
    from gearscan.twin.recordings import render_recording
    from gearscan.twin.render import Optics, RenderError

    gear = _gear_from_options(teeth, module, pressure_angle, face_width, bore)
    try:
        as_built = GearDefects.from_options(
            defects, eccentricity_um=eccentricity_um, pitch_errors=pitch_error, chips=chip, wear=wear, module=true_module
        )
        the_rig = Rig.load(rig) if rig else default_rig()
        size = (the_rig.camera.width, the_rig.camera.height) if rig else (512, 512)
        size = (width or size[0], height or size[1])
        if size != (the_rig.camera.width, the_rig.camera.height):
            if rig:  # a user's calibration rendered at another size: said, not silent
                typer.echo(f"note: --width/--height {size[0]}x{size[1]}: the rig's camera "
                           f"({the_rig.camera.width}x{the_rig.camera.height}, {rig}) rescaled to it", err=True)
            the_rig = the_rig.with_camera_resolution(*size)
        optics = Optics() if noise else Optics().noise_free()
        with _progress("rendering") as prog:
            frames = 3 * (bursts + (-(-bursts // coarse_every) if coarse_period else 0))  # coarse bursts too
            task = prog.add_task("render", total=frames)
            render_recording(
                out, rig=the_rig, gear=gear, defects=as_built, optics=optics, motion=motion, bursts=bursts, period_px=period,
                start_deg=start, motion_blur=motion_blur, seed=seed, overwrite=overwrite,
                coarse_period_px=coarse_period, coarse_every=coarse_every, alternate_order=alternate_order,
                progress=lambda i, n: prog.update(task, completed=i),
            )
    except (RigError, MotionError, RenderError, RecordingError, ValueError) as exc:
        raise _fail(str(exc)) from exc
    typer.echo(f"wrote {frames} frames to {out}")


@twin_app.command("certificate")
def twin_certificate_cmd(
    recording: Annotated[Path, typer.Argument(help="a twin recording rendered with defects (its truth is the certificate)")],
    out: Annotated[Path, typer.Option("--out", "-o", help="certificate JSON to write")] = Path("certificate.json"),
) -> None:
    """Write the certificate of a twin recording's gear (its exact ISO 1328-1 values, U 0) for `gearscan verify`."""
    from gearscan.core.recording import RecordingError, RecordingReader
    from gearscan.verify import VerifyError, twin_certificate

    _require_recording(recording)
    _writable(out, "--out")
    try:
        cert = twin_certificate(RecordingReader(recording).meta)
    except (RecordingError, VerifyError) as exc:
        raise _fail(f"{recording}: {exc}") from exc
    out.write_text(cert.model_dump_json(indent=2))
    typer.echo("; ".join(f"{k} {v:.2f}" for k, v in cert.headline_um().items()) + f" µm -> {out}")


@twin_app.command("dataset")
def twin_dataset(
    out: Annotated[Path, typer.Argument(help="dataset folder (resumes if it exists)")],
    teeth: Annotated[str, typer.Option(help="comma-separated tooth counts, one gear each (with --rig: your gear's one)")] = "12,20,30",
    module: Annotated[float, typer.Option(help="module, mm")] = 2.0,
    width: Annotated[int | None, typer.Option(help="image width, px (default 512; with --rig: the camera's)")] = None,
    height: Annotated[int | None, typer.Option(help="image height, px (default 512; with --rig: the camera's)")] = None,
    period: Annotated[float, typer.Option(help="fringe period, projector px (ignored with --randomize)")] = 40.0,
    randomize: Annotated[bool, typer.Option(help="randomise rig, optics, period and gear size per gear")] = False,
    views: Annotated[bool, typer.Option(help="with --randomize: any view (radial/side/oblique/face), module 0.5-5 mm, camera fringe period 5-60 px")] = False,
    repeats: Annotated[int, typer.Option(min=1, help="randomised scenes per tooth count")] = 1,
    max_start_points: Annotated[int | None, typer.Option(help="cap on start points per gear")] = None,
    start_step_deg: Annotated[float, typer.Option(help="start points every this many degrees within one tooth pitch")] = 2.0,
    seed: Annotated[int, typer.Option()] = 0,
    rig: Annotated[Path | None, typer.Option(help="your rig (rig.json from `gearscan calibrate`): an adaptation dataset of your rig and gear, for `gearscan train --init`")] = None,
    optics: Annotated[Path | None, typer.Option(help="with --rig: the twin's optics as JSON (fields of twin.render.Optics); default: the twin's defaults, projector power balanced for the rig")] = None,
    pressure_angle: Annotated[float, typer.Option(help="pressure angle, degrees")] = 20.0,
    face_width: Annotated[float, typer.Option(help="face width, mm")] = 20.0,
    bore: Annotated[float, typer.Option(help="bore diameter, mm")] = 10.0,
) -> None:
    """Render the paper's dataset protocol (start points x 18 poses x 18-step patterns).

    With --rig: your own rig and gear (an adaptation dataset, index.json purpose "adaptation"),
    which may have any tooth count; without it, the project's protocol datasets, which refuse the
    test split's tooth counts and seeds (twin/splits.py).
    """
    import json

    from pydantic import ValidationError

    from gearscan.twin.dataset import DatasetError, DatasetSpec, generate_dataset, start_points

    try:
        counts = [int(t) for t in teeth.split(",") if t.strip()]
    except ValueError as exc:
        raise _fail(f"--teeth: expected comma-separated integers, got {teeth!r}") from exc
    gears = [_gear_from_options(t, module, pressure_angle, face_width, bore) for t in counts for _ in range(repeats)]
    scene = None
    if rig is not None:
        from gearscan.core.rig import Rig, RigError
        from gearscan.twin.randomize import balance_projector_power
        from gearscan.twin.render import Optics

        if randomize or views or len(gears) != 1:
            raise _fail("--rig renders your one rig and gear: give one --teeth, without --randomize/--views/--repeats")
        try:
            user_rig = Rig.load(rig)
        except RigError as exc:
            raise _fail(str(exc)) from exc
        size = (user_rig.camera.width, user_rig.camera.height)
        if (width or size[0], height or size[1]) != size:
            raise _fail(f"--width/--height {width}x{height} differ from the rig's camera {size[0]}x{size[1]}; "
                        "leave them out with --rig")
        width, height = size
        try:
            twin_optics = (Optics(**json.loads(optics.read_text())) if optics is not None
                           else balance_projector_power(user_rig, Optics()))
        except (OSError, ValueError, TypeError) as exc:  # pydantic's ValidationError is a ValueError
            raise _fail(f"--optics {optics}: expected a JSON object of twin.render.Optics fields ({exc})") from exc
        scene = (user_rig, twin_optics, gears[0], period)
    elif optics is not None:
        raise _fail("--optics needs --rig")
    try:
        spec = DatasetSpec(gears=gears, width=width or 512, height=height or 512, period_px=period,
                           randomize=randomize, views=views, seed=seed, max_start_points=max_start_points,
                           start_step_deg=start_step_deg)
    except (ValueError, ValidationError) as exc:
        raise _fail(f"invalid dataset options: {exc}") from exc
    n = sum(len(start_points(g, spec.start_step_deg)[:max_start_points]) for g in gears)
    try:
        with _progress("start points") as prog:
            task = prog.add_task("dataset", total=n)
            generate_dataset(out, spec, progress=lambda i, total: prog.update(task, completed=i), scene=scene,
                             purpose="protocol" if scene is None else "adaptation")
    except DatasetError as exc:
        raise _fail(str(exc)) from exc
    kind = f"adaptation dataset of {rig} ({width}x{height})" if scene is not None else "dataset"
    typer.echo(f"{kind} ready in {out}: {n} start points x 816 three-step inputs")


def _speed(value: str) -> float | None:
    if value == "max":
        return None
    try:
        speed = float(value)
    except ValueError:
        raise _fail(f"--speed must be a positive number or 'max', got {value!r}") from None
    if not math.isfinite(speed) or speed <= 0:  # nan compares false with everything
        raise _fail(f"--speed must be a positive number or 'max', got {value!r}")
    return speed


def _decoder(classical: bool, mc: int, model: Path | None, **options):
    """The decoder, or a clear CLI error when the model cannot be loaded; ``options`` go to Decoder."""
    from gearscan.inference.decoder import Decoder

    if classical:
        return Decoder(classical=True)
    try:
        return Decoder(model, mc=mc, **options)
    except (ValueError, FileNotFoundError) as exc:  # ModelFileError is a ValueError
        raise _fail(f"cannot load the model: {exc}") from exc


def _serve(bind: str, grpc_port: int, web_port: int):
    """``--serve``: start the web viewer on fixed ports and say where it is; a taken port is exit 2."""
    from gearscan.viewer.serve import ViewerError, serve_web

    try:
        web = serve_web(bind, grpc_port=grpc_port, web_port=web_port)
    except ViewerError as exc:
        raise _fail(f"--serve: {exc}") from exc
    typer.echo(f"web viewer: {web.web_url}  (gRPC for --connect: {web.grpc_url})")
    return web


@app.command("replay")
def replay_cmd(
    recording: Annotated[Path, typer.Argument(help="recording folder")],
    save: Annotated[Path | None, typer.Option(help="write the rerun stream to this .rrd file (default without --connect or --serve: out/<recording>.rrd)")] = None,
    connect: Annotated[str | None, typer.Option(help="stream to a rerun viewer at this gRPC URL")] = None,
    serve: Annotated[bool, typer.Option(help="serve the web viewer (gRPC + web) from this machine")] = False,
    bind: Annotated[str, typer.Option(help="address --serve binds to")] = "127.0.0.1",
    grpc_port: Annotated[int, typer.Option(help="--serve: gRPC port the logging stream and the viewer use (0: any free port)")] = 9876,
    web_port: Annotated[int, typer.Option(help="--serve: port of the web viewer page (0: any free port)")] = 9090,
    metrics: Annotated[Path | None, typer.Option(help="write accuracy and pipeline metrics (JSON) here")] = None,
    speed: Annotated[str, typer.Option(help="replay speed: 1.0 = recorded timing, 'max' = as fast as possible")] = "max",
    classical: Annotated[bool, typer.Option(help="decode with three-step PS instead of the network")] = False,
    mc: Annotated[int, typer.Option(min=0, help="Monte Carlo passes (0: deterministic)")] = 0,
    model: Annotated[Path | None, typer.Option(help="model weights (.safetensors); default: the shipped model")] = None,
    truth: Annotated[bool, typer.Option(help="score against the recording's truth when it has one (--no-truth: what a live run does per burst)")] = True,
    workers: Annotated[int | None, typer.Option(min=1, help="bursts decoded at once (default: 2 on a CPU, 1 on a GPU)")] = None,
    still_span_deg: Annotated[float | None, typer.Option(min=0, help="bursts spanning less turntable angle go to three-step PS (0: never; default 0.0375, the val choice for v9)")] = None,
    orientation: Annotated[str, typer.Option(help="the rig's fringe phase along the camera columns: normal (rising, the twin's rigs), mirrored, or auto (from the rig calibration; 3 still bursts that agree against it win; without a usable calibration a vote per burst, which misreads fast bursts)")] = "auto",
    strict: Annotated[bool, typer.Option(help="exit 1 when the recording has damage (default: skip it, measure the rest, exit 0)")] = False,
    unwrap: Annotated[str, typer.Option(help="fringe orders from the gear's CAD ('cad'), or CAD-free from its envelope ('envelope') or from the recording's coarse bursts ('coarse')")] = "cad",
    fuse: Annotated[Path | None, typer.Option(help="fuse every burst's cloud in the gear frame and write it here (.ply/.pcd/.csv: x y z mm, sigma, deviation from CAD, bursts)")] = None,
    voxel_mm: Annotated[float, typer.Option(min=0.001, help="with --fuse: voxel edge of the fused model, mm")] = 0.1,
    min_bursts: Annotated[int, typer.Option(min=1, help="with --fuse: keep fused points seen by at least this many bursts")] = 3,
    refine: Annotated[bool, typer.Option(help="with --fuse: fit each fused point to every raw frame that saw it (keeps the recording's frames in memory)")] = True,
    ply: Annotated[Path | None, typer.Option(help="write every burst's cloud (gear frame: x y z mm, sigma) as DIR/burst_NNNNNN.ply")] = None,
    csv: Annotated[Path | None, typer.Option(help="write every burst's cloud as DIR/burst_NNNNNN.csv (x_mm,y_mm,z_mm,sigma_mm[,deviation_mm])")] = None,
    rig: Annotated[Path | None, typer.Option(help="rig calibration JSON for a recording made without one (replaces the recording's own)")] = None,
    network_support_px: Annotated[int | None, typer.Option(min=-1, max=16, help="a network's pixel needs fringes in its own frames within this many px (-1: no such test; default: the model's own, its JSON's network_support: per burst none for the shipped v9 and the default-rig option (v9's, inherited), 2 px for v6; with --fuse and its frame fit none for v9 and the option (since session 48), 0 px for v6; a fine-tune inherits its init's; a model naming none gets v9's)")] = None,
    max_sigma_rad: Annotated[float | None, typer.Option(min=0.01, help="report no point whose total phase sigma exceeds this, rad (the fringe orders are found on the pixels within it, recon.measure.UNWRAP_MAX_SIGMA; default: the product's val choice for the path, recon.measure.MAX_SIGMA_RAD per burst, FRAME_FIT_MAX_SIGMA_RAD with --fuse and its frame fit, then for every burst of the run, its per-burst metrics and exports too)")] = None,
    max_point_sigma_um: Annotated[float | None, typer.Option(min=0.1, help="with --fuse and its frame fit: report no point of the fitted cloud whose sigma exceeds this, µm: a fit must meet it to replace its fused point, an unfitted point above it is dropped and counted (default 30, recon.track.MAX_POINT_SIGMA_MM; needs the frame fit)")] = None,
    frame_fit_shading: Annotated[str | None, typer.Option(help="with --fuse and its frame fit: how the fit models the light a point gets as the gear turns: lambert (irradiance from the point's normal, for matt surfaces; the twin renders it) drift (mean and modulation linear in the turn angle, no surface model) quadratic (the same, quadratic in the turn angle) or mixed (quadratic per point where its samples carry it, drift elsewhere); default recon.track.SHADING")] = None,
) -> None:
    """Replay a recording through the live pipeline; print accuracy when it holds truth.

    Damaged frames and lines are skipped (each named once in a warning, all listed in the
    metrics' "damage" section); see also `gearscan check`.
    """
    from gearscan.core.recording import RecordingError
    from gearscan.pipeline import PipelineError
    from gearscan.replay import replay

    span = {} if still_span_deg is None else {"still_span_deg": still_span_deg}
    if orientation not in ("auto", "normal", "mirrored"):
        raise typer.BadParameter(f"expected auto, normal or mirrored, got {orientation!r}", param_hint="--orientation")
    point_sigma_mm = _point_sigma_mm(max_point_sigma_um, fitted=refine and fuse is not None,
                                     needs="give --fuse FILE and leave the frame fit on (no --no-refine)")
    _shading(frame_fit_shading, fitted=refine and fuse is not None,
             needs="give --fuse FILE and leave the frame fit on (no --no-refine)")
    decoder = _decoder(classical, mc, model, workers=workers, orientation=orientation, **span)
    web = None
    if serve:
        web = _serve(bind, grpc_port, web_port)
        connect = web.grpc_url
    _connect_url(connect, "--connect")
    if not (save or connect):
        save = Path("out") / f"{recording.name}.rrd"
    try:
        if unwrap not in ("cad", "envelope", "coarse"):
            raise typer.BadParameter(f"expected 'cad', 'envelope' or 'coarse', got {unwrap!r}", param_hint="--unwrap")
        if fuse is not None and fuse.suffix.lower() not in (".ply", ".pcd", ".csv"):
            raise typer.BadParameter(f"expected a .ply, .pcd or .csv file, got {fuse}", param_hint="--fuse")
        pace = _speed(speed)
        _require_recording(recording)
        for flag, target in (("--save", save), ("--metrics", metrics), ("--fuse", fuse)):
            _writable(target, flag)
        for flag, target in (("--ply", ply), ("--csv", csv)):
            _writable(target, flag, folder=True)
        export = None
        if ply is not None or csv is not None:
            from gearscan.replay import CloudExport

            try:
                export = CloudExport(ply=ply, csv=csv)
            except ValueError as exc:
                raise _fail(str(exc)) from exc
        fuser = None
        if fuse is not None:
            from gearscan.recon.fuse import CloudFuser

            fuser = CloudFuser(voxel_mm, min_bursts)
        from gearscan.recon.measure import network_support_option

        if max_sigma_rad is not None and not math.isfinite(max_sigma_rad):
            raise typer.BadParameter(f"expected a finite bound in rad, got {max_sigma_rad}", param_hint="--max-sigma-rad")
        result = replay(recording, decoder=decoder, save=save, connect=connect, metrics_path=metrics, speed=pace,
                        truth=truth, unwrap=unwrap, fuse=fuser, rig=rig, export=export, refine=refine and fuser is not None,
                        network_support_px=network_support_option(network_support_px,
                                                                  frame_fit=refine and fuser is not None,
                                                                  model=decoder.network_support),
                        max_sigma=max_sigma_rad, point_sigma_mm=point_sigma_mm, shading=frame_fit_shading)
        if fuse is not None:
            from gearscan.inspect import dropped_note
            from gearscan.recon.fuse import save_fused

            if result.fused is None or not len(result.fused):
                raise RecordingError(f"--fuse: no point was seen by {min_bursts} bursts; nothing written to {fuse}")
            save_fused(result.fused, fuse)
            fitted = ""
            if result.fused.refined is not None:
                fitted = f", {int(result.fused.refined.sum()):,} of them fitted to the raw frames"
                if bound := (result.refine or {}).get("sigma_bound_mm"):
                    fitted += f", every point's sigma within {1e3 * bound:g} µm"
            typer.echo(f"fused model: {len(result.fused):,} points from {result.fused.bursts_added} bursts{fitted} -> {fuse}")
            if note := dropped_note(result.refine).strip():  # on its own line: not read as part of the path
                typer.echo(note)
        if export is not None:
            typer.echo(f"burst clouds: {export.written} -> " + ", ".join(str(d) for d in (ply, csv) if d is not None))
    except (RecordingError, PipelineError) as exc:
        raise _fail(str(exc)) from exc
    finally:
        if web is not None and not serve:
            web.close()
    for k, v in result.summary().items():
        typer.echo(f"{k}: {v:.4f}" if isinstance(v, float) else f"{k}: {v}")
    from gearscan.recon.depth_sigma import (
        REST_STALE_NOTE,
        UNMEASURED_NOTES,
        turning_three_step_note,
    )

    if note := UNMEASURED_NOTES.get((result.recon or {}).get("depth_sigma_source")):
        typer.secho(f"sigma: {note}", fg=typer.colors.YELLOW)
    if (result.recon or {}).get("rest_sigma_source") == "stale":
        typer.secho(f"sigma: {REST_STALE_NOTE}", fg=typer.colors.YELLOW)
    if turning := (result.decoder or {}).get("turning_three_step", 0):
        typer.secho(f"sigma: {turning_three_step_note(turning)}", fg=typer.colors.YELLOW)
    if uncalibrated := (result.recon or {}).get("bursts_sigma_uncalibrated", 0):
        from gearscan.recon.depth_sigma import CALIBRATED_SPAN_DEG

        typer.secho(f"sigma: {uncalibrated} burst(s) spanned more than the depth sigma was calibrated for "
                    f"({CALIBRATED_SPAN_DEG:g} deg from frame 1 to 3, recon.depth_sigma); their points' sigma is not a "
                    "measured k = 2 bound",
                    fg=typer.colors.YELLOW)
    damage = result.damage.get("count", 0)
    if damage:
        kinds = ", ".join(f"{k} {n}" for k, n in result.damage["by_kind"].items())
        typer.secho(f"damage: {damage} part(s) skipped ({kinds}), named in the warnings above; a skipped frame "
                    "drops its burst", fg=typer.colors.YELLOW)
    if save:
        typer.echo(f"rerun stream saved to {save} (open with: rerun {save})")
    if strict and damage:
        typer.secho(f"error: --strict: {recording} has {damage} damaged part(s)", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=1)
    if web is not None:
        typer.echo(f"serving {web.web_url} — Ctrl-C to stop")
        try:
            web.process.wait()
        except KeyboardInterrupt:
            pass
        finally:
            web.close()


def _serial_ports() -> list[str]:
    from gearscan.acquisition.encoder import list_serial_ports

    return list_serial_ports()


def unambiguous_range_line(rig, period_px: float, gear, unwrap: str) -> str:
    """One line saying how far a surface may be off its CAD before its fringe order is lost."""
    from gearscan.recon.measure import Reconstructor, envelope_bounds
    from gearscan.recon.unwrap import min_unambiguous_period

    rc = Reconstructor.for_gear(rig, period_px, gear)
    try:
        r = rc.depth_range_mm()
    except ValueError as exc:
        return f"unambiguous depth range: not stated ({exc})"
    finally:
        rc.close()
    line = (f"unambiguous depth range at {period_px:g} px fringes: -{r['minus_median_mm']:.2f}/+{r['plus_median_mm']:.2f} mm "
            f"around the CAD (median over the gear; at least -{r['minus_min_mm']:.2f}/+{r['plus_min_mm']:.2f} mm)")
    if unwrap == "envelope":
        need = min_unambiguous_period(rig, envelope_bounds(rig, gear))
        line += (f"; CAD-free unwrapping resolves every pixel from {need:.0f} px fringes on"
                 + (" (finer fringes leave regions ambiguous: counted, not guessed)" if period_px < need else ""))
    return line


@app.command("check")
def check_cmd(
    recording: Annotated[Path, typer.Argument(help="recording folder")],
) -> None:
    """List a recording's damage without decoding images (PNG structure and CRCs, index and
    encoder lines, header). Exit 0: clean; 1: damaged (replay skips what is listed); 2: not a
    readable recording (recording.json missing or damaged, or its gear or pattern section, which replay needs; a damaged
    rig is 1: replay takes --rig)."""
    import warnings

    from gearscan.core.recording import RecordingError, RecordingReader

    with warnings.catch_warnings(record=True) as caught:  # an interrupted tail is a note, not damage
        warnings.simplefilter("always")
        try:
            reader = RecordingReader(recording, warn=False)
            notes = reader.check()
        except RecordingError as exc:
            raise _fail(str(exc)) from exc
    for d in reader.damage:
        typer.echo(f"damaged: {d} [{d.kind}]")
    for note in [str(w.message) for w in caught] + notes:
        typer.echo(f"note: {note}")
    sections = [d.what.split(":")[0] for d in reader.damage if d.kind == "header"]
    if [s for s in sections if s != "rig"]:  # replay cannot measure without its patterns or gear: not skippable
        typer.secho(f"{recording}: recording.json's {', '.join(sections)} damaged: replay refuses it until the header "
                    "is mended", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=2)
    if sections:  # a damaged rig: replay measures with --rig, as for a recording made without one
        typer.secho(f"{recording}: recording.json's rig damaged: replay it with --rig RIG.json", fg=typer.colors.YELLOW)
    if reader.damage:
        typer.secho(f"{recording}: {len(reader.damage)} damaged part(s); replay skips them and measures the rest",
                    fg=typer.colors.YELLOW)
        raise typer.Exit(code=1)
    typer.echo(f"{recording}: OK ({len(reader)} frames)")


config_app = typer.Typer(help="Live configuration files.", no_args_is_help=True)
app.add_typer(config_app, name="config")


@config_app.command("init")
def config_init(
    path: Annotated[Path, typer.Argument(help="where to write the commented template")] = Path("rig.toml"),
    force: Annotated[bool, typer.Option(help="overwrite an existing file")] = False,
) -> None:
    """Write a commented template of the live configuration."""
    from gearscan.config import TEMPLATE

    if path.exists() and not force:
        raise _fail(f"{path} exists (use --force to overwrite)")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(TEMPLATE)
    except OSError as exc:
        raise _fail(f"cannot write {path} ({exc.strerror or exc})") from exc
    typer.echo(f"wrote {path}; edit it, then run: gearscan live --config {path} --check")


@app.command("live")
def live_cmd(
    config: Annotated[Path | None, typer.Option(help="live configuration (TOML); see `gearscan config init` (optional with --simulate)")] = None,
    simulate: Annotated[bool, typer.Option(help="run on simulators: Aravis's GigE camera simulator (a test ramp, not a gear), the mock encoder (2.5 rpm) and a mock projector; a --config keeps its rig, gear and model")] = False,
    record: Annotated[Path | None, typer.Option(help="record every measured burst into this folder")] = None,
    overwrite: Annotated[bool, typer.Option(help="replace an existing recording")] = False,
    bursts: Annotated[int | None, typer.Option(min=1, help="stop after this many bursts")] = None,
    duration: Annotated[float | None, typer.Option(min=0.1, help="stop after this many seconds")] = None,
    save: Annotated[Path | None, typer.Option(help="write the rerun stream to this .rrd file")] = None,
    max_save_mb: Annotated[float | None, typer.Option(min=0, help="the .rrd file stops growing at this size, MB; the measurement goes on (0: no cap; default from config: 2000)")] = None,
    connect: Annotated[str | None, typer.Option(help="stream to a rerun viewer at this gRPC URL")] = None,
    serve: Annotated[bool | None, typer.Option(help="serve the web viewer from this machine")] = None,
    bind: Annotated[str | None, typer.Option(help="address --serve binds to (default from config: 127.0.0.1)")] = None,
    grpc_port: Annotated[int | None, typer.Option(help="--serve: gRPC port (default from config: 9876; 0: any free port)")] = None,
    web_port: Annotated[int | None, typer.Option(help="--serve: web viewer port (default from config: 9090; 0: any free port)")] = None,
    check: Annotated[bool, typer.Option(help="open the camera, encoder and projector the configuration names, check them and the rig file, then exit")] = False,
) -> None:
    """Measure live: camera + projector + encoder -> network -> point cloud -> rerun viewer.

    A one-line status shows bursts/s, drops by cause, the encoder rate and the .rrd file; the
    end summary says why the run stopped.
    """
    import contextlib

    from gearscan.acquisition.config import ConfigError
    from gearscan.config import LiveConfig
    from gearscan.simulated import SimulationError, simulated_devices

    if config is None and not simulate:
        raise _fail("--config: a live configuration is needed (write one with `gearscan config init rig.toml`), "
                    "or try the simulators with --simulate")
    with contextlib.ExitStack() as devices:
        try:
            cfg = LiveConfig.load(config) if config is not None else None
            for note in cfg.defaulted_sections() if cfg is not None else []:
                typer.secho(f"{config}: {note}", fg=typer.colors.YELLOW, err=True)
            if simulate:
                cfg = devices.enter_context(simulated_devices(cfg))
                typer.echo(f"simulated devices: camera {cfg.camera.id} (Aravis GigE simulator on 127.0.0.1, test ramp), "
                           f"encoder {cfg.encoder.port} ({cfg.encoder.counts_per_rev} counts/rev), mock projector")
            rig = cfg.load_rig()
        except (ConfigError, SimulationError) as exc:
            raise _fail(str(exc)) from exc
        if check:
            _live_check(cfg, rig, config or Path("--simulate"))
            return
        _writable(save, "--save")  # --record: the recording writer judges it as the session starts, before any frame
        _live_run(cfg, record=record, overwrite=overwrite, bursts=bursts, duration=duration, save=save,
                  max_save_mb=max_save_mb, connect=connect, serve=serve, bind=bind,
                  ports=(grpc_port, web_port))


def _live_check(cfg, rig, source: Path) -> None:
    """``live --check``: open each device the configuration names and say what was verified."""
    from gearscan.acquire import check_camera
    from gearscan.acquisition.camera import CameraError
    from gearscan.acquisition.config import ConfigError
    from gearscan.acquisition.probe import check_projector, probe_encoder

    lines = []
    try:
        lines.append("camera: " + check_camera(cfg, (rig.camera.width, rig.camera.height)))
        lines.append("projector: " + check_projector(cfg))
        seq = cfg.projector.patterns().cycle(cfg.projector.coarse_every, alternate=cfg.projector.alternate_order)
        lines.append("pattern sequence: " + ", ".join(map(str, seq)) + (
            " (the projector plays it by itself: program it so, from the camera's first frame; "
            f"camera.pattern_cycle = {len(seq)})" if cfg.camera.trigger != "software" else
            " (shown by software, one pattern per triggered frame)"))
    except (CameraError, ConfigError) as exc:
        raise _fail(str(exc)) from exc
    if cfg.encoder is None:
        lines.append("encoder: none (the gear is taken as standing still at angle 0)")
    else:  # a config that parses is not a device that answers
        enc = cfg.encoder
        found = probe_encoder(enc.port, enc.baudrate, timeout_s=2.0)
        if found.error is not None:
            raise _fail(f"encoder.port: cannot open {enc.port!r} ({found.error}); serial ports found: {_serial_ports()}")
        if not found.is_encoder:
            raise _fail(f"encoder.port: {enc.port!r} opened, but {found.describe()} within 2 s "
                        f"(encoder.baudrate = {enc.baudrate}; `gearscan devices` probes every port)")
        if found.banner is not None and found.banner.counts_per_rev != enc.counts_per_rev:
            raise _fail(f"encoder.counts_per_rev: {enc.counts_per_rev} in the config, but the encoder on {enc.port} "
                        f"reports {found.banner.counts_per_rev}")
        lines.append(f"encoder: {enc.port} answered: {found.describe()}")
    lines.append(f"rig: {rig.camera.width}x{rig.camera.height} px camera; gear z={cfg.gear.teeth}, m={cfg.gear.module:g}; "
                 + (rig.calibration.line() if rig.calibration is not None else
                    "its calibration states no uncertainty of its own (not from `gearscan calibrate`'s joint "
                    "adjustment: calibrate again to have one)"))
    typer.echo(f"{source}: OK\n  " + "\n  ".join(lines))
    typer.echo(unambiguous_range_line(rig, cfg.projector.period_px, cfg.gear, cfg.recon.unwrap))


def _live_run(cfg, *, record, overwrite, bursts, duration, save, max_save_mb, connect, serve, bind,
              ports=(None, None)) -> None:
    """``live`` proper: the sinks, the run with its status line, the end summary."""
    import os

    from gearscan.acquisition.camera import CameraError
    from gearscan.acquisition.config import ConfigError
    from gearscan.acquisition.encoder import EncoderError
    from gearscan.core.recording import RecordingError
    from gearscan.live import LiveError, StatusLine, run_live
    from gearscan.pipeline import PipelineError

    decoder = _decoder(False, cfg.model.mc, cfg.model.path, precision=cfg.model.precision,
                       workers=cfg.model.workers, still_span_deg=cfg.model.still_span_deg,
                       orientation=cfg.model.orientation)
    save = save or cfg.viewer.save
    connect = _connect_url(connect or cfg.viewer.connect, "--connect / viewer.connect")
    cap = cfg.viewer.max_save_mb if max_save_mb is None else max_save_mb
    web = None
    if serve if serve is not None else cfg.viewer.serve:
        grpc_port, web_port = ports
        web = _serve(bind or cfg.viewer.bind, cfg.viewer.grpc_port if grpc_port is None else grpc_port,
                     cfg.viewer.web_port if web_port is None else web_port)
        connect = web.grpc_url
    spawn = False
    if not (save or connect):  # default: the local viewer when there is a screen, else a file
        spawn = bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
        save = None if spawn else Path("out") / "live.rrd"
        typer.echo("viewer: the local rerun viewer" if spawn else
                   f"viewer: no screen and no --save/--connect/--serve, so the stream goes to {save}"
                   + (f" (up to {cap:g} MB)" if cap else ""))
    if cfg.encoder is None:
        typer.secho("no [encoder]: the gear is taken as standing still at angle 0 (three-step PS on every burst)",
                    fg=typer.colors.YELLOW)
    try:
        with StatusLine() as status:
            report = run_live(cfg, record=record, overwrite=overwrite, bursts=bursts, duration=duration,
                              decoder=decoder, save=save, connect=connect, spawn=spawn, on_status=status.update,
                              max_save_mb=cap)
    except LiveError as exc:
        if exc.live_report is not None:
            typer.echo(exc.live_report.summary())
        raise _fail(str(exc)) from exc
    except (ConfigError, CameraError, EncoderError, RecordingError, PipelineError) as exc:
        raise _fail(str(exc)) from exc
    finally:
        if web is not None:
            web.close()
    typer.echo(report.summary())
    if record:
        typer.echo(f"recording: {record} (replay with: gearscan replay {record})")


@app.command("evaluate")
def evaluate_cmd(
    out: Annotated[Path, typer.Argument(help="report folder (report.md, results.json, figures)")],
    model: Annotated[Path | None, typer.Option(help="model weights; default: the shipped model")] = None,
    data: Annotated[list[Path] | None, typer.Option(help="validation twin dataset(s) (unseen gears); default: built-in scenes")] = None,
    train_data: Annotated[Path | None, typer.Option(help="twin dataset for the loss-ablation runs")] = None,
    peers: Annotated[Path | None, typer.Option(help="folder with trained unet/, ts-unet/, dr-unet/ runs")] = None,
    per_motion: Annotated[int, typer.Option(min=1, help="bursts per motion per scene")] = 3,
    mc: Annotated[int, typer.Option(min=1, help="Monte Carlo passes")] = 20,
    quick: Annotated[bool, typer.Option(help="reduced version (small scenes, tiny training runs), minutes on 2 cores")] = False,
    seed: Annotated[int, typer.Option()] = 0,
) -> None:
    """Reproduce the paper's experiments (section 3) on twin gears the model never saw."""
    from gearscan.report import EvalOptions, run_evaluation

    opt = EvalOptions(model=model, data=list(data or []), out=out, quick=quick, peers=peers, mc=mc,
                      per_motion=per_motion, seed=seed, train_data=train_data)
    try:
        run_evaluation(opt, progress=lambda s: typer.echo(f"- {s}"))
    except (ValueError, FileNotFoundError) as exc:
        raise _fail(str(exc)) from exc
    typer.echo(f"report: {out / 'report.md'}")


def _shading(shading: str | None, *, fitted: bool, needs: str) -> None:
    """``--frame-fit-shading`` refused before anything runs: a name the fit does not know, or no fit to model."""
    from gearscan.recon.track import SHADINGS

    if shading is None:
        return
    if shading not in SHADINGS:
        raise typer.BadParameter(f"expected one of {', '.join(SHADINGS)}, got {shading!r}", param_hint="--frame-fit-shading")
    if not fitted:
        raise typer.BadParameter(f"the shading model is the frame fit's: {needs}", param_hint="--frame-fit-shading")


def _point_sigma_mm(um: float | None, *, fitted: bool, needs: str) -> float | None:
    """``--max-point-sigma-um`` as the frame fit's bound in mm, refused where no fit runs (``needs``: what the command
    asks for one) or the value is not finite."""
    if um is None:
        return None
    if not math.isfinite(um):
        raise typer.BadParameter(f"expected a finite sigma in µm, got {um}", param_hint="--max-point-sigma-um")
    if not fitted:
        raise typer.BadParameter(f"bounds the points of the cloud fitted to the raw frames: {needs}",
                                 param_hint="--max-point-sigma-um")
    return um / 1e3


@app.command("verify")
def verify_cmd(
    certificate: Annotated[Path, typer.Argument(help="the master gear's certificate (JSON; `gearscan twin certificate` writes one for a twin gear)")],
    reports: Annotated[list[Path], typer.Argument(help="`gearscan inspect` report folders of the master, each after a fresh mounting (at least 3; ISO 15530-3 asks for 20)")],
    out: Annotated[Path, typer.Option("--out", "-o", help="the statement to write (JSON, and Markdown beside it)")] = Path("uncertainty.json"),
) -> None:
    """Measurement uncertainty of each ISO 1328-1 quantity from a master gear measured after several mountings."""
    from gearscan.recon.substitution import RECOMMENDED_READINGS
    from gearscan.verify import VerifyError, verify, write_statement

    _writable(out, "--out")
    try:
        st = verify(certificate, reports)
    except VerifyError as exc:
        raise _fail(str(exc)) from exc
    for key, q in st.quantities.items():
        typer.echo(f"{key}: U = {q.U:.2f} µm (error bound per mounting {q.mean:.2f} ± {q.s:.2f}, k {q.k:.2f}, "
                   f"certificate {q.U_cal:.2f})")
    if len(reports) < RECOMMENDED_READINGS:
        typer.secho(f"{len(reports)} mountings: fewer than the {RECOMMENDED_READINGS} ISO 15530-3 asks for (k widens U "
                    "for it)", fg=typer.colors.YELLOW)
    json_path, md = write_statement(st, out)
    typer.echo(f"statement: {json_path} ({md})")


@app.command("inspect")
def inspect_cmd(
    recording: Annotated[Path, typer.Argument(help="recording folder of one revolution (or more) of the gear")],
    out: Annotated[Path, typer.Option("--out", "-o", help="report folder (report.md, report.json, plots, fused.ply)")] = Path("report"),
    grade: Annotated[int | None, typer.Option(min=1, max=11, help="ISO 1328-1:2013 tolerance class to check against")] = None,
    classical: Annotated[bool, typer.Option(help="decode with three-step PS instead of the network")] = False,
    model: Annotated[Path | None, typer.Option(help="model weights (.safetensors); default: the shipped model")] = None,
    voxel_mm: Annotated[float, typer.Option(min=0.001, help="voxel edge of the fused model, mm")] = 0.1,
    min_bursts: Annotated[int, typer.Option(min=1, help="keep fused points seen by at least this many bursts")] = 3,
    unwrap: Annotated[str, typer.Option(help="fringe orders from the CAD ('cad') or its envelope ('envelope')")] = "cad",
    save: Annotated[Path | None, typer.Option(help="also write the rerun stream (bursts + fused model) to this .rrd")] = None,
    refine: Annotated[bool, typer.Option(help="fit each fused point to every raw frame that saw it (keeps the recording's frames in memory)")] = True,
    network_support_px: Annotated[int | None, typer.Option(min=-1, max=16, help="a network's pixel needs fringes in its own frames within this many px (-1: no such test; default: the model's own, its JSON's network_support: with the frame fit none for the shipped v9 (since session 48) and the default-rig option (v9's, inherited), 0 px for v6; with --no-refine none for v9 and the option, 2 px for v6; a fine-tune inherits its init's; a model naming none gets v9's)")] = None,
    max_point_sigma_um: Annotated[float | None, typer.Option(min=0.1, help="report no point of the fitted cloud whose sigma exceeds this, µm: a fit must meet it to replace its fused point, an unfitted point above it is dropped and counted (default 30, recon.track.MAX_POINT_SIGMA_MM; needs the frame fit; not with --no-refine)")] = None,
    frame_fit_shading: Annotated[str | None, typer.Option(help="how the frame fit models the light a point gets as the gear turns: lambert (irradiance from the point's normal, for matt surfaces; the twin renders it) drift (mean and modulation linear in the turn angle, no surface model) quadratic (the same, quadratic in the turn angle) or mixed (quadratic per point where its samples carry it, drift elsewhere); default recon.track.SHADING; not with --no-refine")] = None,
    rig: Annotated[Path | None, typer.Option(help="rig calibration JSON to measure with (the file `gearscan calibrate` wrote; replaces the recording's own)")] = None,
    uncertainty: Annotated[Path | None, typer.Option(help="measurement uncertainty statement of this gear type (`gearscan verify` wrote it from a master gear): each reading gets its U and, with --grade, an ISO 14253-1 decision")] = None,
    datum: Annotated[str, typer.Option(help="the axis pitch and runout are read about: tip (the tip lands' circle; no pitch deviation moves it) or teeth (placed by the flanks' radial part: for a gear whose tip circle is not concentric with its teeth; 2.5-5x noisier on the twin)")] = "tip",
    from_report: Annotated[Path | None, typer.Option(help="inspect again the fused cloud of an earlier report folder of this recording, without replaying it (another --datum, --grade or --uncertainty in seconds); the replay's settings are that report's, so none of them may be given")] = None,
) -> None:
    """Inspect a gear (ISO 1328-1): fuse a revolution, then pitch fp/Fp, runout Fr, profile Fα/ffα/fHα, chipped teeth."""
    from gearscan.core.recording import RecordingError
    from gearscan.inspect import QUANTITIES, run_inspection
    from gearscan.pipeline import PipelineError
    from gearscan.recon.measure import network_support_option

    if unwrap not in ("cad", "envelope"):
        raise _fail(f"--unwrap: expected 'cad' or 'envelope', got {unwrap!r}")
    point_sigma_mm = _point_sigma_mm(max_point_sigma_um, fitted=refine, needs="leave the frame fit on (no --no-refine)")
    _shading(frame_fit_shading, fitted=refine, needs="leave the frame fit on (no --no-refine)")
    from gearscan.recon.inspect import DATUMS

    if datum not in DATUMS:
        raise typer.BadParameter(f"expected one of {', '.join(DATUMS)}, got {datum!r}", param_hint="--datum")
    if from_report is not None:
        replay_settings = {"--classical": classical, "--model": model is not None, "--save": save is not None,
                           "--frame-fit-shading": frame_fit_shading is not None, "--rig": rig is not None,
                           "--max-point-sigma-um": max_point_sigma_um is not None,
                           "--network-support-px": network_support_px is not None, "--voxel-mm": voxel_mm != 0.1,
                           "--min-bursts": min_bursts != 3, "--unwrap": unwrap != "cad", "--no-refine": not refine}
        given = [name for name, on in replay_settings.items() if on]
        if given:
            raise _fail(f"--from-report {from_report}: its fused cloud was measured with that report's replay settings; "
                        f"{', '.join(given)} would change the replay, which does not run: inspect the recording afresh")
        if out.resolve() == from_report.resolve():
            raise _fail(f"--from-report {from_report}: write the new report elsewhere (--out), so that the cloud it "
                        "reads stays beside the report that measured it")
    _require_recording(recording)
    _writable(out, "--out", folder=True)
    _writable(save, "--save")
    common = {"grade": grade, "progress": lambda s: typer.echo(f"- {s}"), "uncertainty": uncertainty, "datum": datum}
    try:
        if from_report is not None:  # no replay: no decoder to load
            report = run_inspection(recording, out, from_report=from_report, **common)
        else:
            decoder = _decoder(classical, 0, model)
            report = run_inspection(recording, out, decoder=decoder, voxel_mm=voxel_mm, min_bursts=min_bursts,
                                    unwrap=unwrap, save=save, refine=refine,
                                    network_support_px=network_support_option(network_support_px, frame_fit=refine,
                                                                              model=decoder.network_support),
                                    point_sigma_mm=point_sigma_mm, rig=rig, shading=frame_fit_shading, **common)
    except (RecordingError, PipelineError, ValueError) as exc:
        raise _fail(str(exc)) from exc
    from gearscan.inspect import chip_verdict, quantity_line, uncertainty_lines

    summary = report.inspection.summary()
    for key in QUANTITIES:
        tol = f" (class {grade}: {report.tolerances[key]:g})" if report.tolerances else ""
        typer.echo(quantity_line(report.inspection, key, summary[key], tol))

    typer.echo(f"chipped teeth: {chip_verdict(report.inspection)}")
    for line in uncertainty_lines(report.uncertainty):
        typer.secho(line, fg=typer.colors.YELLOW if line.startswith("warning") else None)
    from gearscan.inspect import spec_note, turning_note, unmeasured_sigma_note

    if note := unmeasured_sigma_note(report):
        typer.secho(note, fg=typer.colors.YELLOW)
    if note := turning_note(report):
        typer.secho(note, fg=typer.colors.YELLOW)
    if note := spec_note(report):
        typer.secho(f"warning: {note}", fg=typer.colors.YELLOW)
    typer.echo(f"report: {report.files['markdown']}")


@app.command("record")
def record(
    out: Path = typer.Argument(..., help="Recording folder to create."),
    config: Path = typer.Option(..., "--config", "-c", help="Live configuration TOML (`gearscan config init`): devices, rig, gear."),
    bursts: int = typer.Option(10, "--bursts", "-n", help="Number of valid three-frame bursts to record."),
    overwrite: bool = typer.Option(False, help="Replace an existing recording in OUT."),
) -> None:
    """Record BURSTS bursts from the configured camera, projector and encoder into OUT.

    Takes the configuration `gearscan live` takes and stores its rig, gear and pattern set in OUT as `live --record` does.
    """
    from rich.console import Console
    from rich.progress import Progress

    from gearscan.acquire import record_bursts
    from gearscan.acquisition.camera import CameraError
    from gearscan.acquisition.config import ConfigError
    from gearscan.acquisition.encoder import EncoderError
    from gearscan.config import LiveConfig
    from gearscan.core.recording import RecordingError

    console = Console()
    try:
        cfg = LiveConfig.load(config)
        for note in cfg.defaulted_sections():
            console.print(f"[yellow]{config}: {note}[/yellow]")
        meta = cfg.recording_meta(cfg.load_rig(), source="record")
        with Progress(console=console) as progress:
            task = progress.add_task("recording bursts", total=bursts)
            summary = record_bursts(cfg, out, bursts, overwrite=overwrite, extra_meta=meta,
                                    on_burst=lambda n: progress.update(task, completed=n))
    except (ConfigError, CameraError, EncoderError, RecordingError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    console.print(
        f"{summary.bursts} bursts ({summary.frames} frames, {summary.encoder_samples} encoder samples) "
        f"in {summary.seconds:.1f} s -> {summary.out} (replay with: gearscan replay {summary.out})"
    )
    console.print(f"assembler: {summary.assembler}")
    console.print(f"camera: {summary.camera}")
    if summary.encoder is not None:
        console.print(f"encoder: {summary.encoder}")


def _register(module: str, names: list[str], target: typer.Typer = app) -> None:
    """Register command functions that live in stage packages (light modules, lazy heavy imports)."""
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.startswith("gearscan"):
            return
        raise
    for name in names:
        fn = getattr(mod, name, None)
        if fn is not None:
            target.command(name.replace("_", "-"))(fn)


_register("gearscan.inference.commands", ["predict", "train", "calibrate_uncertainty", "still_gate"])
_register("gearscan.calibrate", ["calibrate"])
_register("gearscan.acquisition.commands", ["devices"])


def main() -> None:  # pragma: no cover - console entry
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
