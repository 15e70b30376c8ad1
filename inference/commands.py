"""CLI command functions of the network package (registered in gearscan/cli.py).

Only light imports at module level; torch and friends load inside the functions.
"""

from __future__ import annotations

import struct
import time
import zipfile
import zlib
from pathlib import Path
from typing import Annotated

import typer

from gearscan.inference.decoder import STILL_SPAN_DEG, turned_less_than


def _read_images(paths: list[Path]):
    import cv2
    import numpy as np

    imgs = []
    for p in paths:
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise typer.BadParameter(f"cannot read image {p}")
        if img.ndim == 3:
            raise typer.BadParameter(
                f"{p}: expected a single-channel (grey) image, got shape {img.shape}"
            )
        imgs.append(img)
    shapes = {i.shape for i in imgs}
    dtypes = {i.dtype for i in imgs}
    if len(shapes) != 1 or len(dtypes) != 1:
        raise typer.BadParameter(
            f"the three images differ in shape/dtype: {sorted(map(str, shapes))} {sorted(map(str, dtypes))}"
        )
    return np.stack(imgs)


# what numpy and zipfile raise on a damaged .npz (bad zip, CRC, npy header, truncated data)
_NPZ_ERRORS = (OSError, EOFError, ValueError, TypeError, KeyError, NotImplementedError, OverflowError,
               MemoryError, RecursionError, SyntaxError, zipfile.BadZipFile, zlib.error, struct.error)
_NPZ_EXPECTED = "an .npz from numpy.savez with 'frames' (3, H, W) uint8/uint16"


def _read_npz(path: Path) -> dict:
    """Every array of the .npz at ``path``, read whole, so damage fails here and names the file."""
    import numpy as np

    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ValueError(f"a {type(z).__name__}, not a zip of arrays")
        with z:
            return {k: z[k] for k in z.files}
    except _NPZ_ERRORS as exc:
        why = f"{type(exc).__name__}: {exc}"
        raise typer.BadParameter(f"{path}: not a readable .npz ({why[:200]}); expected {_NPZ_EXPECTED}") from exc


def _scalar(path: Path, arrays: dict, key: str, lo: float, hi: float, integer: bool = False) -> float | None:
    """``arrays[key]`` as one finite number in ``[lo, hi]`` (None when absent)."""
    import numpy as np

    if key not in arrays:
        return None
    a = arrays[key]
    kinds = "iu" if integer else "iuf"
    if a.size != 1 or a.dtype.kind not in kinds or not np.isfinite(a).all() or not lo <= float(a.item()) <= hi:
        what = "an integer" if integer else "a finite number"
        raise typer.BadParameter(f"{path}: '{key}' expected {what} in [{lo:g}, {hi:g}], got {a.dtype} {a.shape} "
                                 f"{np.array2string(a.ravel()[:3])}")
    return float(a.item())


def load_frames(inputs: list[Path]):
    """``(3, H, W)`` raw frames, full scale and angles (rad, or None) from an .npz (``frames``,
    optional ``full_scale``/``bit_depth``/``angles``) or three images; anything else, or a
    damaged file, is a :class:`typer.BadParameter` naming the file and what was expected."""
    import numpy as np

    angles = None
    if len(inputs) == 1 and inputs[0].suffix == ".npz":
        src = inputs[0]
        arrays = _read_npz(src)
        if "frames" not in arrays:
            raise typer.BadParameter(f"{src}: no array 'frames' (found {sorted(arrays)}); expected {_NPZ_EXPECTED}")
        frames = arrays["frames"]
        full_scale = _scalar(src, arrays, "full_scale", 1e-12, 1e12)
        bit_depth = _scalar(src, arrays, "bit_depth", 1, 16, integer=True)
        if full_scale is None and bit_depth is not None:
            full_scale = float((1 << int(bit_depth)) - 1)
        if "angles" in arrays:
            angles = arrays["angles"]
            if angles.shape != (3,) or angles.dtype.kind not in "iuf" or not np.isfinite(angles).all():
                raise typer.BadParameter(f"{src}: 'angles' expected three finite numbers (rad), "
                                         f"got {angles.dtype} {angles.shape}")
            angles = angles.astype(np.float64)
    elif len(inputs) == 3:
        src, frames, full_scale = "frames", _read_images(inputs), None
    else:
        raise typer.BadParameter(
            f"INPUT: expected one .npz with 'frames' or three image files, got {len(inputs)} path(s)"
        )
    if frames.ndim != 3 or frames.shape[0] != 3 or 0 in frames.shape:
        raise typer.BadParameter(f"{src}: 'frames' expected (3, H, W) with H, W > 0, got shape {frames.shape}")
    if frames.dtype not in (np.uint8, np.uint16):
        raise typer.BadParameter(f"{src}: 'frames' expected uint8 or uint16, got {frames.dtype}")
    return frames, full_scale, angles


def check_device(device: str, *, allow_auto: bool = False) -> str:
    """A torch device the user named: ``cpu``, ``cuda`` or ``cuda:N`` (and ``auto`` where allowed)."""
    import torch

    kinds = ("auto", "cpu", "cuda") if allow_auto else ("cpu", "cuda")
    kind, _, index = device.partition(":")
    if kind not in kinds or (index and (kind != "cuda" or not index.isdigit())):
        raise typer.BadParameter(f"expected {', '.join(kinds)} or cuda:N, got {device!r}", param_hint="--device")
    if kind == "cuda" and not torch.cuda.is_available():
        raise typer.BadParameter("cuda: no CUDA device is available on this machine (use --device cpu)",
                                 param_hint="--device")
    return device


def predict(
    inputs: Annotated[
        list[Path],
        typer.Argument(
            help="an .npz with 'frames' (3,H,W) uint8/uint16, or three image files",
            exists=True,
            dir_okay=False,
        ),
    ],
    output: Annotated[Path, typer.Option("--output", "-o", help="output .npz")] = Path("phase.npz"),
    mc: Annotated[
        int,
        typer.Option("--mc", min=0, help="Monte Carlo passes T (0 = single deterministic pass)"),
    ] = 0,
    model: Annotated[
        Path | None,
        typer.Option(
            "--model", help="model .safetensors (JSON config beside it); default: shipped model"
        ),
    ] = None,
    device: Annotated[str, typer.Option(help="cpu or cuda")] = "cpu",
    precision: Annotated[
        str,
        typer.Option(help="auto (bf16 where the CPU has native bf16 or on CUDA, else fp32), fp32 or bf16"),
    ] = "auto",
    angles_deg: Annotated[
        str | None,
        typer.Option(
            help="the three frames' turntable angles 'A,B,C' in degrees (models with motion "
            "input; an .npz may hold them as 'angles', rad)"
        ),
    ] = None,
    still_span_deg: Annotated[
        float,
        typer.Option(
            min=0.0,
            help="with angles: a burst that turned less than this (frame 1 to 3) is decoded by three-step PS, "
            "as live and replay do (no motion, no motion error; 0: always the network)",
        ),
    ] = STILL_SPAN_DEG,
    orientation: Annotated[
        str,
        typer.Option(help="the rig's fringe phase along the camera columns: normal (rising, as on the twin's rigs), "
                     "mirrored, or auto (from --rig's calibration; without one a vote on this burst, which misreads "
                     "fast bursts on large gears)"),
    ] = "auto",
    rig: Annotated[
        Path | None,
        typer.Option(help="the rig's calibration JSON (`gearscan calibrate`): with --orientation auto the fringe "
                     "orientation comes from its geometry, which no motion can fool, instead of a vote on the burst"),
    ] = None,
    still_burst_rad: Annotated[
        float | None,
        typer.Option(
            min=0.0, max=3.0,
            help="decode the burst by three-step PS when the network's median departure from it over the burst's "
            "interior is below this (rad): a still gear without angles. Default: the model's (chosen on val; "
            "0.03 in v9 and v6, none in the default-rig option); 0: off",
        ),
    ] = None,
    still_burst_motion: Annotated[
        float | None,
        typer.Option(
            help="and only when fewer than this share of the lit pixels swing more between the three frames than a "
            "still fringe can (an outline or shadow border crossing them): a burst whose frames show motion keeps "
            "the network. Default: the model's (chosen on val with --still-burst-rad); inf: no check",
        ),
    ] = None,
) -> None:
    """Predict wrapped phase and its uncertainty from one three-step burst.

    OUT.npz holds phase, M, D, sigma_model, sigma_data, sigma_total (float32, H x W, radians
    for phase and sigmas), the mode used and the fringe orientation the network decoded with.
    """
    import numpy as np

    from gearscan.core.phase import still_three_step_result
    from gearscan.inference.model_io import ModelFileError
    from gearscan.inference.models import classical_md
    from gearscan.inference.predictor import (
        BURST_GATE_MODULATION,
        ORIENTATIONS,
        PRECISIONS,
        Predictor,
        check_motion_limit,
        frames_to_tensor,
        fringe_phase_decreases_along_columns,
        resolve_full_scale,
    )

    if precision not in PRECISIONS:
        raise typer.BadParameter(f"expected one of {', '.join(PRECISIONS)}, got {precision!r}", param_hint="--precision")
    check_device(device)
    if orientation not in ORIENTATIONS:
        raise typer.BadParameter(f"expected one of {', '.join(ORIENTATIONS)}, got {orientation!r}", param_hint="--orientation")
    from_rig = False  # the orientation came from --rig's calibration
    if rig is not None:
        from gearscan.core.rig import Rig, RigError, fringe_orientation

        try:
            loaded = Rig.load(rig)
        except RigError as exc:
            raise typer.BadParameter(str(exc), param_hint="--rig") from exc
        try:
            calibrated, why = fringe_orientation(loaded), None
        except RigError as exc:
            calibrated, why = None, str(exc)
        side = calibrated.orientation if calibrated is not None else None
        if side is None:
            typer.secho(f"warning: --rig {rig}: {why or calibrated.describe()}", fg=typer.colors.YELLOW, err=True)
        elif orientation == "auto":
            orientation, from_rig = side, True
        elif orientation != side:
            typer.secho(f"warning: --orientation {orientation}, but --rig {rig} says {calibrated.describe()}: "
                        f"decoding as --orientation says", fg=typer.colors.YELLOW, err=True)
    frames, full_scale, npz_angles = load_frames(inputs)
    if np.array_equal(frames.min(axis=0), frames.max(axis=0)):  # no pixel changes between the three steps
        what = "all zero" if not frames.any() else "the same at every pixel"
        typer.secho(f"warning: {', '.join(map(str, inputs))}: the three frames are {what}: no fringe modulation, "
                    "so the phase is meaningless (projector off, lens cap on, or exposure far too short?)",
                    fg=typer.colors.YELLOW, err=True)
    if still_burst_motion is not None:
        try:
            check_motion_limit(still_burst_motion, "--still-burst-motion")
        except ValueError as exc:
            raise typer.BadParameter(str(exc), param_hint="--still-burst-motion") from exc
    try:
        predictor = Predictor.load(model, device=device, precision=precision, orientation=orientation,
                                   still_burst_rad=still_burst_rad, still_burst_motion=still_burst_motion)
    except ModelFileError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    angles = npz_angles
    if angles_deg is not None:
        try:
            angles = np.radians([float(v) for v in angles_deg.split(",")])
        except ValueError as exc:
            raise typer.BadParameter(f"--angles-deg: expected three numbers 'A,B,C', got {angles_deg!r}") from exc
    fringes = "not used (three-step PS)"
    # which way the burst went: the encoder's still rule, else the network behind its still-burst gate
    whose_gate = "set" if still_burst_rad is not None else "the model's"
    gate = (f"still-burst gate {predictor.still_burst_rad:g} rad ({whose_gate})" if predictor.still_burst_rad > 0
            else f"no still-burst gate ({whose_gate})")
    try:
        if angles is not None and turned_less_than(angles, still_span_deg):  # the pipeline's still rule
            result = still_three_step_result(frames, resolve_full_scale(frames, full_scale))
            route = f"the encoder's angles turned less than {still_span_deg:g} deg: three-step PS"
        else:
            # the orientation decided here, so that the output can say which one decoded the burst
            mirror = (fringe_phase_decreases_along_columns(frames_to_tensor(frames, full_scale))
                      if orientation == "auto" else orientation == "mirrored")
            result = predictor.predict(frames, mc=mc, full_scale=full_scale, angles=angles, mirror=mirror)
            if result.mode == "three-step":  # the still-burst gate took it: no orientation decoded it
                route = f"{gate} took it as still: three-step PS"
            else:
                how = " (voted on this burst)" if orientation == "auto" else " (rig calibration)" if from_rig else " (set)"
                fringes = ("mirrored" if mirror else "normal") + how
                route = f"the network, {gate}"
    except ValueError as exc:  # a motion-input model without angles, or bad angles
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    try:  # through a file object: numpy would append '.npz' to another name and write elsewhere
        output.parent.mkdir(parents=True, exist_ok=True)
        with open(output, "wb") as fh:
            fields = ("phase", "M", "D", "sigma_model", "sigma_data", "sigma_total")
            np.savez_compressed(fh, mode=np.array(result.mode), fringes=np.array(fringes),
                                **{k: getattr(result, k) for k in fields})
    except OSError as exc:
        typer.echo(f"error: --output: cannot write {output} ({exc.strerror or exc})", err=True)
        raise typer.Exit(2) from exc
    # the median over the pixels with fringes (three-step modulation 2B/S >= 0.05, the reconstructor's keep floor):
    # over the whole image the background's sigma swamps it (a gear filling 8 % of a frame read 0.22 rad, 0.065 on it)
    m3, d3 = classical_md(frames_to_tensor(frames, full_scale))[0].numpy()
    lit = np.hypot(m3, d3) >= BURST_GATE_MODULATION
    sigma_text = (f"median sigma_total {float(np.median(result.sigma_total[lit])):.4f} rad over the {100 * lit.mean():.0f} % "
                  "of pixels with fringes (modulation >= 0.05)" if lit.any() else "no pixel with fringes (modulation >= 0.05)")
    typer.echo(
        f"{output}: {frames.shape[2]}x{frames.shape[1]} phase, mode {result.mode}, fringes {fringes}, {sigma_text}; "
        f"route: {route}"
    )
    if fringes.endswith("(voted on this burst)"):
        typer.secho("note: the fringe orientation was voted on this burst (--orientation auto); the vote "
                    "misreads fast bursts (fringes drifting about a third of a period per frame; on val 13 of 36 "
                    "bursts at 2 deg/frame, 16 of 36 at 2+3 deg: benchmarks/orientation_look.json), and a "
                    "misread burst decodes about 1.9 rad off: "
                    + ("set --orientation normal|mirrored" if rig is not None else
                       "pass --rig rig.json or set --orientation normal|mirrored"),
                    fg=typer.colors.YELLOW, err=True)


def _load_dataset(spec: str, max_items: int | None = None, motion_input: bool = False,
                  reverse: bool = False, flag: str = "--data"):
    """A twin dataset folder (``gearscan twin dataset``), a folder of .npz items, or
    ``package.module:function`` returning a dataset or (train, val); ``flag`` names the option in an error."""
    import importlib

    from gearscan.inference.data import MotionInput, NpzBurstDataset

    if (Path(spec) / "index.json").is_file():
        import numpy as np
        from torch.utils.data import Subset

        from gearscan.twin.dataset import TwinBurstDataset

        ds = TwinBurstDataset(spec, static=True, reverse=reverse)
        if motion_input:
            ds = MotionInput(ds)
        if max_items is not None and len(ds) > max_items:  # a validation sample, seeded
            pick = np.random.default_rng(0).choice(len(ds), max_items, replace=False)
            return Subset(ds, sorted(pick.tolist()))
        return ds
    if Path(spec).is_dir():
        return NpzBurstDataset(spec)
    if ":" in spec:
        mod, fn = spec.split(":", 1)
        return getattr(importlib.import_module(mod), fn)()
    raise typer.BadParameter(
        f"{flag}: expected a twin dataset folder, a folder of .npz items or 'module:function', got {spec!r}"
    )


def train(
    data: Annotated[
        str,
        typer.Option(
            help="twin dataset folder (gearscan twin dataset), folder of .npz items (input/target/mask/phase/group) or 'module:function' returning a Dataset or (train, val)"
        ),
    ],
    out: Annotated[
        Path, typer.Option(help="output folder (checkpoints, metrics, plots, best.safetensors)")
    ] = Path("runs/cd-dcu-net"),
    val_data: Annotated[
        str | None,
        typer.Option(
            help="separate validation data (same forms as --data); default: split --data by group"
        ),
    ] = None,
    model: Annotated[str, typer.Option(help="cd-dcu-net, unet, ts-unet or dr-unet (with --init: the init's)")] = "cd-dcu-net",
    width: Annotated[int, typer.Option(min=1, help="base width w (paper 64; with --init: the init's)")] = 16,
    classical_input: Annotated[
        bool, typer.Option(help="feed the classical three-step M, D as two extra input channels")
    ] = False,
    residual: Annotated[
        bool, typer.Option(help="predict a correction to the classical three-step M, D")
    ] = False,
    reverse: Annotated[
        bool,
        typer.Option(help="twin datasets: add every moving burst played backwards (the other rotation sense)"),
    ] = False,
    motion_input: Annotated[
        bool,
        typer.Option(help="feed the encoder's rotation within the burst (twin datasets); "
                     "with --init from a model without it, the new inputs start zero-weighted"),
    ] = False,
    epochs_deterministic: Annotated[
        int, typer.Option(min=0, help="stage 1 epochs (no dropout)")
    ] = 50,
    epochs_dropout: Annotated[
        int, typer.Option(min=0, help="stage 2 epochs (Concrete Dropout)")
    ] = 50,
    batch_size: Annotated[int, typer.Option(min=1)] = 16,
    lr: Annotated[float, typer.Option(min=0.0)] = 1e-3,
    schedule: Annotated[str, typer.Option(
        help="step, cosine, constant, or cosine-time (annealed to 0 over the --budget-cpu-min or --wall-minutes "
             "the stage has, whatever number of epochs that is)")] = "step",
    step_every: Annotated[
        int, typer.Option(min=1, help="epochs between x gamma decays (step schedule)")
    ] = 20,
    gamma: Annotated[float, typer.Option(help="decay factor of the step schedule")] = 0.9,
    patience: Annotated[
        int, typer.Option(min=1, help="early stop after this many epochs without val improvement")
    ] = 10,
    crop: Annotated[int | None, typer.Option(help="random square crop size per batch")] = None,
    steps_per_epoch: Annotated[int | None, typer.Option(help="cap on batches per epoch")] = None,
    alpha: Annotated[float, typer.Option(help="temperature of the Gaussian NLL term")] = 1e-4,
    mse_weight: Annotated[float, typer.Option(help="weight of the MSE term")] = 1.0,
    mse_weighting: Annotated[
        str | None, typer.Option(help="uniform or modulation (1/m^2, phase-like); default: the --init model's, else uniform")
    ] = None,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda")] = "auto",
    precision: Annotated[
        str, typer.Option(help="autocast: auto (bf16 on CUDA and on CPUs with native bf16, else fp32), fp32 or bf16")
    ] = "auto",
    workers: Annotated[int, typer.Option(min=0, help="DataLoader workers")] = 0,
    seed: Annotated[int, typer.Option()] = 0,
    init: Annotated[
        Path | None,
        typer.Option("--init", help="start from these weights (.safetensors): fine-tuning; the network "
                     "(name, width, inputs, dropout) is the one in their JSON"),
    ] = None,
    budget_cpu_min: Annotated[
        float | None,
        typer.Option(min=0.01, help="stop at this many CPU minutes of this process (all threads, and the compiler a "
                     "--compile step waits for; other load on shared cores does not count), keeping the best-on-val "
                     "weights"),
    ] = None,
    checkpoints_cpu_min: Annotated[
        str | None,
        typer.Option(help="'5,10,20': also save the best-on-val weights so far as OUT/cpu_<m>min.safetensors "
                     "at these CPU minutes"),
    ] = None,
    bank: Annotated[bool, typer.Option(
        help="draw the training bursts on the training device (twin dataset folders only), so a GPU step waits "
             "on no DataLoader worker and no per-item copy")] = False,
    compile: Annotated[bool, typer.Option(
        "--compile", help="torch.compile the training steps (fused kernels; a compile of tens of seconds per stage, "
                          "which a CPU budget counts; eager again, with a message, if it fails). On an AMX CPU a real "
                          "fine-tune made only 1.07x the steps in 30 CPU min (benchmarks/adaptation_compile_rule.md); "
                          "the GPU lease measures it there")] = False,
    average_from: Annotated[float | None, typer.Option(
        min=0.0, max=0.99,
        help="average the weights of every epoch from this share of a stage on (of --budget-cpu-min or "
             "--wall-minutes when given, else of its epochs; stochastic weight averaging); the average is kept only "
             "if it beats the stage's best epoch on val")] = None,
    wall_minutes: Annotated[float | None, typer.Option(
        min=0.01, help="stop by this many wall-clock minutes from now, best-on-val weights kept (the dropout "
                       "stage keeps its share)")] = None,
    resume: Annotated[bool, typer.Option(help="resume from OUT/last.* if present")] = False,
    progress: Annotated[bool, typer.Option(help="show a progress bar")] = True,
    calibrate_mc: Annotated[
        int, typer.Option(min=0, help="MC passes for the MC-mode sigma calibration at the end (0: skip)")
    ] = 20,
) -> None:
    """Train a phase network (two stages: deterministic, then Concrete Dropout); DDP via torchrun.

    Fine-tuning the shipped model on your rig (the paper's digital-twin workflow)::

        gearscan twin dataset adapt --rig rig.json --teeth 35 --module 2 --period 40 --seed 1 --max-start-points 8
        gearscan twin dataset adapt_val --rig rig.json --teeth 35 --module 2 --period 40 --seed 2 \
            --start-step-deg 3.3 --max-start-points 2
        gearscan train --init inference/weights/default.safetensors --data adapt --val-data adapt_val \
            --budget-cpu-min 30 --epochs-dropout 0 --schedule constant --lr 3e-4 --crop 128 --batch-size 8 \
            --steps-per-epoch 40 --epochs-deterministic 100000 --out runs/my-rig

    (the README's recipe, as ``benchmarks/adaptation.py`` measures it); then the README's calibration steps.
    """
    import dataclasses

    from gearscan.inference.losses import LossConfig
    from gearscan.inference.model_io import ModelFileError, read_config
    from gearscan.inference.models import ModelConfig
    from gearscan.inference.predictor import model_network_support
    from gearscan.inference.train import TrainConfig
    from gearscan.inference.train import train as run_training
    from gearscan.twin.dataset import DatasetError

    check_device(device, allow_auto=True)
    marks: tuple[float, ...] = ()
    if checkpoints_cpu_min:
        try:
            marks = tuple(float(v) for v in checkpoints_cpu_min.split(",") if v.strip())
        except ValueError as exc:
            raise typer.BadParameter(f"expected CPU minutes 'A,B,...', got {checkpoints_cpu_min!r}",
                                     param_hint="--checkpoints-cpu-min") from exc
    init_loss: dict = {}
    if init is not None:  # fine-tuning: the network is the init's own
        try:
            meta = read_config(init)
            net_config = ModelConfig.from_json(meta["model"], str(init))
            model_network_support(meta)  # a bad entry is refused here, before any training
        except (ModelFileError, ValueError, TypeError) as exc:
            typer.echo(f"error: --init: {exc}", err=True)
            raise typer.Exit(2) from exc
        if motion_input and not net_config.motion_input:
            net_config = dataclasses.replace(net_config, in_channels=net_config.in_channels + 2, motion_input=True)
        motion_input = net_config.motion_input
        init_loss = (meta.get("training") or {}).get("loss") or {}
    else:
        net_config = ModelConfig(
            name=model,
            width=width,
            classical_input=classical_input,
            residual=residual,
            in_channels=3 + 2 * motion_input,
            motion_input=motion_input,
        )
    weighting = mse_weighting or init_loss.get("mse_weighting", "uniform")
    config = TrainConfig(
        out_dir=str(out),
        model=net_config,
        loss=LossConfig(alpha=alpha, mse_weight=mse_weight, mse_weighting=weighting),
        epochs_deterministic=epochs_deterministic,
        epochs_dropout=epochs_dropout,
        batch_size=batch_size,
        lr=lr,
        schedule=schedule,
        step_every=step_every,
        gamma=gamma,
        patience=patience,
        crop=crop,
        steps_per_epoch=steps_per_epoch,
        device=device,
        precision=precision,
        num_workers=workers,
        seed=seed,
        init=str(init) if init else None,
        widen_inputs=motion_input and init is not None and not read_config(init)["model"].get("motion_input", False),
        resume=resume,
        progress=progress,
        calibrate_mc=calibrate_mc,
        budget_cpu_min=budget_cpu_min,
        checkpoints_cpu_min=marks,
        bank=bank,
        compile=compile,
        average_from=average_from,
        deadline=None if wall_minutes is None else time.time() + 60.0 * wall_minutes,
    )
    train_set = _load_dataset(data, motion_input=motion_input, reverse=reverse)
    val_set = (_load_dataset(val_data, max_items=64, motion_input=motion_input, reverse=reverse, flag="--val-data")
               if val_data else None)
    if isinstance(train_set, tuple):
        train_set, val_set = train_set
    try:
        result = run_training(config, train_set, val_set)
    except DatasetError as exc:  # e.g. --bank on data that are not twin dataset folders
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    if result.best_path is not None:
        budgets = ([f"CPU budget {budget_cpu_min:g} min"] if budget_cpu_min is not None else []) + (
            [f"wall-clock budget {wall_minutes:g} min"] if wall_minutes is not None else [])
        budget = f", {' or '.join(budgets)} reached" if result.budget_hit else ""
        typer.echo(
            f"best model: {result.best_path} (val loss {result.best_val:.4g}, var scale {result.var_scale:.3g}, "
            f"{result.seconds:.0f} s, {result.cpu_seconds / 60:.1f} CPU min{budget})"
        )


def calibrate_uncertainty(
    val: Annotated[
        list[str],
        typer.Argument(help="twin validation dataset folders (`gearscan twin dataset`), gears not trained on; "
                       "comma-joined folders are one family (e.g. one rig's gears), held out together"),
    ],
    model: Annotated[
        Path | None,
        typer.Option("--model", help="model .safetensors to calibrate; default: the shipped model"),
    ] = None,
    items: Annotated[int, typer.Option(min=2, help="moving validation bursts per family (whole images; shared out "
                                                   "over a family's folders); half as many still ones")] = 64,
    mc: Annotated[int, typer.Option(min=0, help="Monte Carlo passes for the MC-mode map (0: deterministic only)")] = 20,
    seed: Annotated[int, typer.Option(help="seed of the burst sample")] = 0,
    output: Annotated[
        Path | None,
        typer.Option("--output", "-o", help="write a calibrated copy here (.safetensors) instead of in place"),
    ] = None,
    orientation: Annotated[
        str,
        typer.Option(help="the val bursts' fringe orientation (normal: every twin rig's; auto: the per-burst vote, "
                     "which misreads some fast bursts)"),
    ] = "normal",
    form: Annotated[
        str | None,
        typer.Option(help="the map's form: power (sigma' = a sigma^b (departure + d0)^c), additive (hinges in log "
                     "sigma, departure and the network's fringe density), additive-local (also the phase's "
                     "curvature and the departure's 7x7 RMS) or additive-local-data (also the aleatoric part of "
                     "the sigma apart: MC mode only, with --modes mc); default: the form of the model's map"),
    ] = None,
    modes: Annotated[
        str,
        typer.Option(help="which maps to refit, comma-joined: deterministic, mc (the others are kept as stored)"),
    ] = "deterministic,mc",
) -> None:
    """Fit the uncertainty calibration per mode (by the log score of the ECE's event) and store it in the
    model's JSON; prints the ECE before and after on held-out data (each family scored by a map fitted on the
    others; one family: half its start points)."""
    from gearscan.inference.calibrate import calibrate_model
    from gearscan.inference.model_io import ModelFileError
    from gearscan.inference.predictor import model_path
    from gearscan.twin.dataset import DatasetError

    mode_list = tuple(m.strip() for m in modes.split(",") if m.strip())
    missing = [repr(f) for v in val for f in v.split(",") if not f.strip() or not Path(f).is_dir()]
    if missing:
        typer.echo(f"error: validation folder(s) {', '.join(missing)}: expected existing twin dataset folders", err=True)
        raise typer.Exit(2)
    try:
        report = calibrate_model(model, val, items=items, mc=mc, seed=seed, output=output,
                                 progress=lambda s: typer.echo(f"- {s}"), orientation=orientation, form=form,
                                 modes=mode_list)
    except (ModelFileError, DatasetError, ValueError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    for mode in report["fitted"]:  # a mode not fitted (e.g. MC with --mc 0) kept its map and is not printed
        r = report[mode]
        m = r["map"]
        if m.get("form") == "additive":
            terms = ", ".join(f"{t['feature']} ({len(t['knots'])} knots)" for t in m["terms"])
            line = f"{mode}: additive map in log {terms}"
        else:
            line = f"{mode}: sigma' = {m['a']:.4g} * sigma^{m['b']:.3f}"
            if "c" in m:
                line += f" * (departure + {m['d0']:g})^{m['c']:.3f}"
        typer.echo(line)
        worse = []
        for piece in r["held_out"]:
            b, a = piece["before"], piece["after"]
            parts = [f"ECE {b['ece']:.3f} -> {a['ece']:.3f}"]
            parts += [f"{k} {b[f'ece_{k}']:.3f} -> {a[f'ece_{k}']:.3f}" for k in ("moving", "still") if f"ece_{k}" in a]
            typer.echo(f"  held-out {piece['scored']}: " + ", ".join(parts) + f" (RMSE {a['rmse']:.4f} rad)")
            if a["ece"] > b["ece"]:
                worse.append(piece["scored"])
        if worse:  # stored as asked, but a map that scores worse than no map where it was not fitted is said
            typer.secho(f"warning: {mode}: on {', '.join(worse)} the map fitted without it is less calibrated than the "
                        f"uncalibrated sigma (ECE above): the sample ({report['items']['moving']} moving, "
                        f"{report['items']['still']} still bursts) may be too small or unlike that data; more --items "
                        "or more val folders (to compare a refit before it replaces a map, write a copy with -o)",
                        fg=typer.colors.YELLOW, err=True)
    written = (output if output is not None else model_path(model)).with_suffix(".json")
    typer.echo(f"wrote the sigma maps ({', '.join(report['fitted'])}) to {written}")


def still_gate(
    data: Annotated[
        list[Path],
        typer.Argument(help="twin datasets of your rig and gear (`gearscan twin dataset --rig`), pooled as one rig",
                       exists=True, file_okay=False),
    ],
    model: Annotated[
        Path | None,
        typer.Option("--model", help="model .safetensors whose gate to choose; default: the shipped model (a shipped "
                                     "model needs --output: its own gate stays)"),
    ] = None,
    output: Annotated[
        Path | None,
        typer.Option("--output", "-o", help="write a copy with the rig's gate here (.safetensors) instead of in place"),
    ] = None,
    orientation: Annotated[str, typer.Option(help="your rig's fringe orientation (normal: every twin rig's)")] = "normal",
    seed: Annotated[int, typer.Option(help="seed of the burst draws")] = 29,
) -> None:
    """Choose the still-burst gate on your rig's twin data (the shipped rule, your rig as its only family:
    benchmarks/rig_still_gate_rule.md) and store it in the model's JSON. A burst the gate takes is decoded by
    three-step PS when no encoder says the gear stood still (`gearscan predict` without angles)."""
    import math

    from gearscan.inference.model_io import ModelFileError
    from gearscan.inference.still_gate_choice import choose_rig_gate, setting_key
    from gearscan.twin.dataset import DatasetError

    def show(fam: str, rows: dict) -> None:
        base = rows["0"]
        typer.echo(f"- {fam}: ungated network " + ", ".join(
            f"{k} {v['rmse']:.4f} rad (three-step {v['three_step']:.4f})" for k, v in base.items()))

    try:
        choice, written = choose_rig_gate(data, model, output, seed=seed, orientation=orientation, progress=show)
    except (ModelFileError, DatasetError, ValueError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    rad, motion = choice["rad"], choice.get("max_motion_share", math.inf)
    if rad == 0:
        typer.echo("no gate: no setting beat the ungated network within the rule's costs on this rig")
    else:
        rows = next(iter(choice["val"].values()))[setting_key(rad, motion)]
        typer.echo(f"gate {rad:g} rad" + ("" if motion == math.inf else f", motion share < {motion:g}") + ": "
                   + ", ".join(f"{k} {v['rmse']:.4f} rad, {v['taken']}/{v['bursts']} taken" for k, v in rows.items()))
    typer.echo(f"wrote still_burst_gate to {written}")
