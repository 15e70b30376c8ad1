"""Predictor: raw three-frame bursts in, wrapped phase with uncertainty out.

>>> pred = Predictor.load()                       # inference/weights/default.safetensors
>>> result = pred.predict(frames)                 # (3, H, W) uint8 -> PhaseResult
>>> result = pred.predict(frames, mc=20)          # Monte Carlo, T = 20 passes

Weights are read from safetensors with a JSON config beside them (never unpickled).
Raw frames are converted to float32 in [0, 1] with their full scale S (255 for uint8,
65535 for uint16 unless the camera's bit depth says otherwise).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
from pathlib import Path

import cv2
import numpy as np
import torch

from gearscan.core.phase import (
    frame_swing,
    in_capture_order,
    noise_sigma,
    still_frame_noise,
    still_phase,
)
from gearscan.core.types import Burst, PhaseResult
from gearscan.inference.blocks import fold_batchnorm
from gearscan.inference.model_io import ModelFileError, load_model, model_fingerprint
from gearscan.inference.models import PRIOR_CHANNELS, classical_md, motion_channels
from gearscan.inference.uncertainty import (
    MomentStats,
    SigmaMap,
    departure,
    deterministic_moments,
    local_departure,
    mc_moments,
    moments_about,
    sigma_map_from_json,
    to_phase_result,
)

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
DEFAULT_MODEL = WEIGHTS_DIR / "default.safetensors"
PRECISIONS = ("auto", "fp32", "bf16")
MC_PHASES = ("mean", "deterministic")
CALIBRATION_MODES = ("deterministic", "mc")
CPUINFO = Path("/proc/cpuinfo")
# MC passes per batched forward: as many as fit in this many pixels, at least 1. Measured with the
# shipped w=8 model, bf16 + channels_last on 2 cores (AVX512-BF16): chunk 2 fastest at 512x512, 1
# to 20 in benchmarks/inference_speed.md; chunk 1 at 800x800 (2.65 s vs 2.73 for 2, 3.26 for 4)
# and 1232x1360 (7.2 s vs 7.9 for 2, 12.9 for 4): bigger batches fall out of cache.
MC_CHUNK_PIXELS = 2 * 512 * 512
# The still-burst gate's interior: three-step modulation 2B/S at least this (the keep test's), this many
# px from any pixel below it (a 7x7 erosion: a one-off val check in session 29 preferred it to 3x3 and 11x11), and at least
# this many such pixels for a verdict (fewer: the network's result stands).
BURST_GATE_MODULATION = 0.05
BURST_GATE_ERODE_PX = 3
BURST_GATE_MIN_PIXELS = 256
# no motion check on the frames: a model whose JSON names no ``still_burst_gate.max_motion_share``
NO_MOTION_CHECK = math.inf


# On a GPU every pass in one batch where memory allows: on an H100 (benchmarks/inference_speed_gpu.md) T = 20 in one
# batch took 54 ms at 512x512 against 105 ms in the CPU's chunks of 2, and 291 ms at 1232x1360 against 364 ms in
# chunks of 1. Its peak memory was at most 274 bytes per pixel and pass (fp32; bf16 138): a chunk may take this
# many bytes per pixel and pass out of half the memory free.
CUDA_MC_BYTES_PER_PIXEL_PASS = 300


def auto_mc_chunk(height: int, width: int, passes: int, device: str | torch.device = "cpu", model_width: int = 8) -> int:
    """Passes per batched forward for MC sampling of an ``height x width`` image: on a CPU by cache
    (``MC_CHUNK_PIXELS``), on CUDA by the memory free (``CUDA_MC_BYTES_PER_PIXEL_PASS``, measured at w = 8 and
    scaled with the network's width). On CUDA the chunk follows the memory free, so seeded MC draws repeat
    exactly only with a fixed ``Predictor(mc_chunk=...)``."""
    pixels = max(1, height * width)
    device = torch.device(device)
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        free += torch.cuda.memory_reserved(device) - torch.cuda.memory_allocated(device)  # torch's cache is free too
        per_pass = CUDA_MC_BYTES_PER_PIXEL_PASS * pixels * max(1.0, model_width / 8)
        return max(1, min(passes, int(free // 2 // per_pass)))
    return max(1, min(passes, MC_CHUNK_PIXELS // pixels))


def cpu_has_fast_bf16() -> bool:
    """True if the CPU has native bf16 matrix instructions (AVX512-BF16 or AMX).

    Without them (e.g. AVX2-only hosts) bf16 autocast is emulated and measured 4-7x SLOWER
    than fp32 for CD-DCU-Net w=16 at 512x512 (benchmarks/inference_speed.md as of commit
    befe6f9; the current report is from an AVX512-BF16 host, where bf16 is the faster one).
    """
    flags = _cpu_flags()
    return "avx512_bf16" in flags or "amx_bf16" in flags


def cpu_has_amx_bf16() -> bool:
    """True if the CPU has AMX bf16 tiles: only with them did a bf16 training step beat fp32 (below)."""
    return "amx_bf16" in _cpu_flags()


def _cpu_flags() -> set[str]:
    try:
        text = CPUINFO.read_text()
    except OSError:
        return set()
    return {f for line in text.splitlines() if line.startswith("flags") for f in line.split(":", 1)[-1].split()}


def resolve_precision(precision: str, device: str | torch.device, *, training: bool = False) -> str:
    """``auto``: bf16 on CUDA; on a CPU, bf16 where it was measured faster than fp32, fp32 otherwise.

    Inference: with native bf16 (AVX512-BF16 or AMX; on an AMD host with AVX512-BF16 and no AMX a 512x512 burst
    took 0.059 s in bf16 against 0.080 in fp32, ``benchmarks/inference_speed.md``). Training (``training=True``):
    only with AMX. On that AMD host a w = 8 training step cost 1.7 CPU s in bf16 against 1.2 in fp32 (session 21),
    while on an AMX host a 30-CPU-minute fine-tune made 1.66x the steps in bf16
    (``benchmarks/adaptation_precision_rule.md``).
    """
    if precision not in PRECISIONS:
        raise ValueError(f"precision: expected one of {PRECISIONS}, got {precision!r}")
    if precision != "auto":
        return precision
    kind = torch.device(device).type
    if kind == "cuda":
        return "bf16"
    fast = cpu_has_amx_bf16() if training else cpu_has_fast_bf16()
    return "bf16" if fast else "fp32"


def model_path(path: str | Path | None) -> Path:
    """The weights file a model argument names: ``None`` -> the shipped model, ``X.json`` -> ``X.safetensors``."""
    path = Path(path) if path is not None else DEFAULT_MODEL
    return path.with_suffix(".safetensors") if path.suffix == ".json" else path


def resolve_full_scale(frames: np.ndarray, full_scale: float | None) -> float:
    """``full_scale``, or the raw dtype's maximum (255, 65535) when None; floats need it given."""
    if full_scale is not None:
        return full_scale
    if frames.dtype == np.uint8:
        return 255.0
    if frames.dtype == np.uint16:
        return 65535.0
    raise ValueError(f"frames: expected uint8 or uint16 raw frames (or pass full_scale), got dtype {frames.dtype}")


def frames_to_tensor(frames: np.ndarray, full_scale: float | None = None) -> torch.Tensor:
    """``(3, H, W)`` (or ``(C, H, W)``) raw frames -> ``(1, C, H, W)`` float32 in [0, 1].

    ``full_scale`` defaults to the dtype's maximum (255, 65535); floats need it explicitly.
    """
    frames = np.asarray(frames)
    if frames.ndim != 3 or frames.shape[0] < 3:
        raise ValueError(f"frames: expected (3, H, W), got shape {frames.shape}")
    full_scale = resolve_full_scale(frames, full_scale)
    if not full_scale > 0:
        raise ValueError(f"full_scale: expected > 0, got {full_scale}")
    x = torch.from_numpy(np.ascontiguousarray(frames, dtype=np.float32)) / float(full_scale)
    return x.unsqueeze(0)


ORIENTATIONS = ("auto", "normal", "mirrored")


def fringe_phase_decreases_along_columns(x: torch.Tensor, min_modulation: float = 0.05) -> bool:
    """True when more than half of the modulation-weighted column steps of the three-step phase of
    ``x`` (1, C, H, W: one burst; a batch would be decided as one) decrease.

    The twin rigs (and so the training data) have the projector's phase increasing along the
    camera's columns; a camera or projector mounted mirrored reverses it, and the network, which
    never saw that, then corrects in the wrong direction (about 1.9 rad RMSE, static bursts
    included). The wrapped phase steps between neighbouring columns over modulated pixels vote,
    each weighted by the smaller modulation of its pair: more than half of the weight on negative
    steps means the fringes run the other way. Unweighted, the vote flipped 3 of 60 bursts of the
    default rig with a 69-tooth gear (the adaptation data of benchmarks/adaptation.py: large gear,
    5-12 px fringes, steep dim flanks whose steps reverse) into errors of about 1.9 rad; weighted,
    none. On val (72 bursts per folder, and the same mirrored) the two votes differ by one burst per set:
    val_radial 0/72 misread and 72/72 mirrored found by both; val_views 2/72 misread and 70/72 found
    weighted, 1/72 and 71/72 unweighted.
    """
    share = falling_phase_share(x, min_modulation)
    return share is not None and share > 0.5


def falling_phase_share(x: torch.Tensor, min_modulation: float = 0.05) -> float | None:
    """The modulation-weighted share of falling column steps of the three-step phase of ``x``
    (:func:`fringe_phase_decreases_along_columns`); None where no pixel pair is modulated."""
    md = classical_md(x[:, :3].float())
    return falling_step_share(torch.atan2(md[:, 0], md[:, 1]), torch.hypot(md[:, 0], md[:, 1]), min_modulation)


def falling_step_share(phase: torch.Tensor, mod: torch.Tensor, min_modulation: float = 0.05) -> float | None:
    """The share of falling column steps of a wrapped ``phase``, each weighted by the smaller ``mod`` of its pair
    (pairs below ``min_modulation`` weigh nothing); None where no pair is modulated."""
    step = torch.remainder(phase[..., 1:] - phase[..., :-1] + math.pi, 2 * math.pi) - math.pi
    weight = torch.minimum(mod[..., 1:], mod[..., :-1])
    weight = torch.where(weight >= min_modulation, weight, torch.zeros_like(weight))
    total = float(weight.sum())
    return float(weight[step < 0].sum()) / total if total > 0 else None


class Predictor:
    """A loaded network with its calibration and the chosen execution settings.

    Parameters
    ----------
    model : the network (any :class:`~gearscan.inference.models.PhaseNet`)
    var_scale : variance calibration factor stored with the model (1 = none)
    calibration : sigma calibration per mode (``"deterministic"``, ``"mc"``), applied after
        propagation (:class:`~gearscan.inference.uncertainty.SigmaCalibration` or ``AdditiveSigmaMap``); none: identity
    device : ``"cpu"`` or ``"cuda"``
    precision : ``"auto"``, ``"fp32"`` or ``"bf16"`` (autocast); see :func:`resolve_precision`
    channels_last : channels_last memory format (default: on CPU, where it was faster in fp32
        and bf16 alike)
    mc_chunk : passes per batched forward in MC mode; None: :func:`auto_mc_chunk` by image size
    still_gate_rad : per pixel, a network phase within this of three-step PS's is replaced by
        three-step PS's (0: off). A correction that small is what the network invents on a still
        gear (where three-step has no motion error and beats it); a real motion correction is larger.
        Chosen per model on the val split and stored in its JSON (``still_gate``); None: the model's.
    still_burst_rad : a whole burst is decoded by three-step PS when the network's median departure
        from it over the burst's interior (:func:`burst_departure`) is below this (0: off). On a still
        gear the network invents corrections in patches and at edges, but most of the interior stays
        within the noise of three-step PS; on a moving one the interior moves too. Chosen per model on
        the val split and stored in its JSON (``still_burst_gate``); None: the model's.
    mc_phase : the phase Monte Carlo mode reports: ``"deterministic"``, the deterministic pass's, with the passes'
        spread about it as the model variance (:func:`~gearscan.inference.uncertainty.moments_about`); ``"mean"``,
        the mean M, D of the passes (the paper's). Chosen per model on val and stored in its JSON (``mc_phase``;
        ``benchmarks/mc_phase_rule.md``); None: the model's (no entry: ``"mean"``). The model's MC sigma map is
        fitted for its own choice: v6's and the option's for the deterministic phase, the shipped v9's for the mean;
        with the other phase a model's MC sigma is not calibrated.
    still_burst_motion : and only when the frames themselves show less motion than this:
        :func:`frame_motion_share` below it (``inf``: no check). Where only part of the image moves
        (a face view: the teeth's outlines sweep, the flat face does not) the interior median stays at
        the noise although the network's correction at the outlines is real; the frames show those
        outlines moving. Chosen with ``still_burst_rad``; None: the model's (no entry: ``inf``).
    orientation : which way the fringe phase runs along the camera's columns: ``"auto"`` votes per
        burst (:func:`fringe_phase_decreases_along_columns`); ``"normal"`` (rising, as on every twin
        rig) or ``"mirrored"`` fix it, a property of the rig that a user sets once. The vote misreads
        fast bursts (val, large radial gears, spans of 1.1 deg and more:
        ``benchmarks/dense_finetune_report.md``; test: ``generalization_report.md``); the likely cause: fringes drifting a third of a period
        per frame turn the three frames into the reversed three-step set, whose phase is mirrored.

    ``network_support`` (read from the JSON, :func:`model_network_support`): the reconstructor's fringe-support
    tests chosen on val for this model, which the app passes on where the user sets none; None: the product's.
    ``depth_sigma_scales`` (read from the JSON, :func:`model_depth_sigma_scales`): the reconstructor's depth-sigma
    scales by edge band chosen on val for this model (``benchmarks/depth_sigma_rule.md``); None: the product's.
    """

    def __init__(
        self,
        model: torch.nn.Module,
        *,
        var_scale: float = 1.0,
        device: str = "cpu",
        precision: str = "auto",
        mc_chunk: int | None = None,
        meta: dict | None = None,
        channels_last: bool | None = None,
        calibration: dict[str, SigmaMap] | None = None,
        still_gate_rad: float | None = None,
        orientation: str = "auto",
        still_burst_rad: float | None = None,
        still_burst_motion: float | None = None,
        mc_phase: str | None = None,
    ) -> None:
        if orientation not in ORIENTATIONS:
            raise ValueError(f"orientation: expected one of {', '.join(ORIENTATIONS)}, got {orientation!r}")
        self.orientation = orientation
        self.device = torch.device(device)
        self.calibration = dict(calibration or {})
        unknown = set(self.calibration) - set(CALIBRATION_MODES)
        if unknown:
            raise ValueError(f"calibration: unknown modes {sorted(unknown)} (known: {list(CALIBRATION_MODES)})")
        self.precision = resolve_precision(precision, self.device)
        self.channels_last = (
            self.device.type == "cpu" if channels_last is None else bool(channels_last)
        )
        self.var_scale = float(var_scale)
        if mc_chunk is not None and int(mc_chunk) < 1:
            raise ValueError(f"mc_chunk: expected >= 1 or None (by image size), got {mc_chunk}")
        self.mc_chunk = None if mc_chunk is None else int(mc_chunk)
        self.meta = meta or {}
        self.mc_phase = model_mc_phase(self.meta) if mc_phase is None else check_mc_phase(mc_phase, "mc_phase")
        if still_gate_rad is None:
            still_gate_rad = float((self.meta.get("still_gate") or {}).get("rad", 0.0))
        if not 0.0 <= still_gate_rad < math.pi:
            raise ValueError(f"still_gate_rad: expected 0 <= rad < pi, got {still_gate_rad}")
        self.still_gate_rad = float(still_gate_rad)
        if still_burst_rad is None:
            still_burst_rad = float((self.meta.get("still_burst_gate") or {}).get("rad", 0.0))
        if not 0.0 <= still_burst_rad < math.pi:
            raise ValueError(f"still_burst_rad: expected 0 <= rad < pi, got {still_burst_rad}")
        self.still_burst_rad = float(still_burst_rad)
        self.still_burst_sigma = burst_sigma_map(self.meta)
        self.still_burst_motion = (burst_motion_limit(self.meta) if still_burst_motion is None
                                   else check_motion_limit(still_burst_motion, "still_burst_motion"))
        self.network_support = model_network_support(self.meta)
        self.depth_sigma_scales = model_depth_sigma_scales(self.meta)
        # the decode its own scales were chosen for (model_fingerprint), where the JSON names it
        self.depth_sigma_chosen_for = (self.meta.get(DEPTH_SIGMA_KEY) or {}).get("model_fingerprint")
        self.rest_sigma_scale = model_rest_sigma_scale(self.meta)
        self.rest_sigma_chosen_for = (self.meta.get(REST_SIGMA_KEY) or {}).get("model_fingerprint")
        self.fingerprint: str | None = None  # the decode's model_fingerprint, known when loaded from files
        self.path: Path | None = None  # the weights it was loaded from, where loaded from files
        # a private copy with BatchNorm folded into the convs: exact, and a pass less per block
        self.model = fold_batchnorm(copy.deepcopy(model).to(self.device).eval())
        if self.channels_last:
            self.model = self.model.to(memory_format=torch.channels_last)

    @classmethod
    def load(
        cls,
        path: str | Path | None = None,
        *,
        device: str = "cpu",
        precision: str = "auto",
        mc_chunk: int | None = None,
        still_gate_rad: float | None = None,
        orientation: str = "auto",
        still_burst_rad: float | None = None,
        still_burst_motion: float | None = None,
        mc_phase: str | None = None,
    ) -> Predictor:
        """Load ``path`` (.safetensors + .json); default: the shipped model."""
        path = model_path(path)
        if not path.is_file():
            hint = (
                " (the shipped default model has not been trained yet: run `gearscan train` and copy best.safetensors/.json there, or pass --model)"
                if path == DEFAULT_MODEL
                else ""
            )
            raise ModelFileError(f"model weights not found: {path}{hint}")
        model, meta = load_model(path, map_location=device)
        calibration = {}
        raw = meta.get("sigma_calibration", {})
        if not isinstance(raw, dict) or set(raw) - set(CALIBRATION_MODES):
            raise ModelFileError(
                f"{path.with_suffix('.json')}: sigma_calibration: expected an object with keys "
                f"{list(CALIBRATION_MODES)}, got {raw!r}"
            )
        for mode, entry in raw.items():
            try:
                calibration[mode] = sigma_map_from_json(entry, f"sigma_calibration.{mode}")
            except ValueError as exc:
                raise ModelFileError(f"{path.with_suffix('.json')}: {exc}") from exc
            if mode == "deterministic" and calibration[mode].needs_sigma_data:
                raise ModelFileError(f"{path.with_suffix('.json')}: sigma_calibration.deterministic reads the "
                                     f"aleatoric sigma apart (sigma_data), which the deterministic pass does not "
                                     f"have apart; expected a map without it (an MC map only)")
        predictor = cls(
            model,
            var_scale=float(meta.get("var_scale", 1.0)),
            device=device,
            precision=precision,
            mc_chunk=mc_chunk,
            meta=meta,
            calibration=calibration,
            still_gate_rad=still_gate_rad,
            orientation=orientation,
            still_burst_rad=still_burst_rad,
            still_burst_motion=still_burst_motion,
            mc_phase=mc_phase,
        )
        # the decode its files define (weights, both sigma maps, gates; not the overrides above): what a val choice
        # made for one decode (depth-sigma scales) is checked against
        predictor.fingerprint = model_fingerprint(path)
        predictor.path = path
        return predictor

    def replica(self) -> Predictor:
        """The same predictor on its own copy of the network, for a second thread."""
        twin = copy.copy(self)
        twin.model = copy.deepcopy(self.model)
        twin.calibration = dict(self.calibration)
        return twin

    @property
    def has_dropout(self) -> bool:
        return bool(getattr(self.model, "config", None) and self.model.config.dropout)

    def _autocast(self):
        if self.precision == "bf16":
            return torch.autocast(device_type=self.device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    @torch.inference_mode()
    def predict_tensor(self, x: torch.Tensor, mc: int = 0, *, mirror: bool | None = None) -> PhaseResult:
        """``(1, C, H, W)`` float32 in [0, 1] -> :class:`PhaseResult` (deterministic if ``mc == 0``).

        ``mirror``: decode the burst mirrored along the columns (its phase falls along them); None:
        as :attr:`orientation` says (a vote on this burst for ``"auto"``).
        """
        if mc < 0:
            raise ValueError(f"mc: expected >= 0 passes, got {mc}")
        if mc > 0 and not self.has_dropout:
            raise ValueError(
                f"mc={mc}: this model ({self.model.config.name}) has no Concrete Dropout layers; use mc=0"
            )
        if x.ndim != 4 or x.shape[0] != 1:
            raise ValueError(f"x: expected one burst (1, C, H, W), got shape {tuple(x.shape)}")
        x = x.to(self.device)
        calibration = self.calibration.get("mc" if mc > 0 else "deterministic")
        needs_classical = (self.still_gate_rad > 0 or self.still_burst_rad > 0
                           or (calibration is not None and calibration.needs_classical))
        classical = classical_md(x[:, :3].float())[0].cpu().numpy() if needs_classical else None
        frames = x[0, :3].float().cpu().numpy() if self.still_burst_rad > 0 else None
        if mirror is None:
            mirror = fringe_phase_decreases_along_columns(x) if self.orientation == "auto" else self.orientation == "mirrored"
        if mirror:  # the nets were trained on phase increasing along the columns: mirror in and out
            x = torch.flip(x, dims=[-1])
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        # the deterministic pass, once: it decides the burst gate in MC mode and is MC mode's phase
        det_stats = self._moments(x, 0) if mc == 0 or self.still_burst_rad > 0 or self.mc_phase == "deterministic" \
            else None
        if mc > 0 and self.still_burst_rad > 0:
            # the burst gate decides on the deterministic phase, as it was chosen on val; a burst it takes
            # needs no Monte Carlo passes (its phase is three-step PS's, its sigma the gate's map)
            det_cal = self.calibration.get("deterministic")
            det = self._result(det_stats, 0, mirror, det_cal, classical)
            gated, taken = still_burst_gate(det, classical, self.still_burst_rad, det_cal, self.still_burst_sigma,
                                            frames=frames, max_motion=self.still_burst_motion)
            if taken:
                return gated
        stats = det_stats
        if mc > 0:
            stats = self._moments(x, mc)
            if self.mc_phase == "deterministic":
                stats = moments_about(stats, det_stats)
        result = self._result(stats, mc, mirror, calibration, classical)
        burst_rad = self.still_burst_rad if mc == 0 else 0.0  # with mc > 0 the burst gate has spoken above
        return apply_still_gates(result, classical, pixel_rad=self.still_gate_rad, burst_rad=burst_rad,
                                 calibration=calibration, burst_sigma=self.still_burst_sigma,
                                 frames=frames, max_motion=self.still_burst_motion)[0]

    def _moments(self, x: torch.Tensor, mc: int) -> MomentStats:
        """The network's moments of the prepared input (``mc`` passes; 0: the deterministic pass)."""
        with self._autocast():
            if mc > 0:
                chunk = self.mc_chunk or auto_mc_chunk(*x.shape[-2:], mc, self.device, self.model.config.width)
                return mc_moments(self.model, x, mc, chunk)
            return deterministic_moments(self.model, x)

    def _result(self, stats: MomentStats, mc: int, mirror: bool, calibration: SigmaMap | None,
                classical: np.ndarray | None) -> PhaseResult:
        """The network's own :class:`PhaseResult` from its moments (``mc`` passes; 0: deterministic)."""
        if mirror:
            stats = MomentStats(*(torch.flip(getattr(stats, f.name), dims=[-1]) for f in dataclasses.fields(stats)))
        mode = f"mc{mc}" if mc > 0 else "deterministic"
        return to_phase_result(stats, 0, mode=mode, var_scale=self.var_scale, calibration=calibration,
                               classical_phase=None if classical is None else np.arctan2(*classical))

    @property
    def needs_angles(self) -> bool:
        """The network takes the encoder's rotation within the burst (``motion_input``)."""
        return bool(getattr(getattr(self.model, "config", None), "motion_input", False))

    def predict(
        self,
        frames: np.ndarray,
        mc: int = 0,
        *,
        full_scale: float | None = None,
        angles: np.ndarray | None = None,
        mirror: bool | None = None,
        prior: np.ndarray | None = None,
    ) -> PhaseResult:
        """Raw frames ``(3, H, W)`` uint8/uint16 -> :class:`PhaseResult` at the input size.

        ``angles``: the three frames' turntable angles (rad); required by a ``motion_input``
        network, ignored otherwise. ``prior``: :func:`~gearscan.inference.models.prior_channels` of
        the burst (the twin's prediction from the CAD at these angles, in the frames' pixel grid);
        required by a ``prior_input`` network, ignored otherwise. ``mirror``: as in :meth:`predict_tensor`.
        """
        x = frames_to_tensor(frames, full_scale)
        if self.needs_angles:
            if angles is None:
                raise ValueError(
                    "angles: this model takes the turntable's rotation within the burst "
                    "(motion_input); pass the three frames' encoder angles (rad)"
                )
            motion = motion_channels(angles, *x.shape[-2:])
            x = torch.cat([x, torch.from_numpy(motion)[None]], dim=1)
        if self.needs_prior:
            expected = (PRIOR_CHANNELS, *x.shape[-2:])
            if prior is None or tuple(np.shape(prior)) != expected:
                got = "none" if prior is None else f"shape {tuple(np.shape(prior))}"
                raise ValueError(
                    f"prior: this model takes the twin's per-pixel prediction (prior_input); expected "
                    f"prior_channels() of shape {expected}, got {got} (from gearscan.twin.prior.TwinPrior.maps)"
                )
            x = torch.cat([x, torch.from_numpy(np.asarray(prior, np.float32))[None]], dim=1)
        return self.predict_tensor(x, mc, mirror=mirror)

    @property
    def needs_prior(self) -> bool:
        """The network takes the twin's per-pixel prediction of the burst (``prior_input``)."""
        return bool(getattr(getattr(self.model, "config", None), "prior_input", False))

    def predict_burst(self, burst: Burst, mc: int = 0) -> PhaseResult:
        """Predict a :class:`Burst` (full scale from its bit depth; angle = first frame's).

        A burst shown in reversed order (shifts 0, 4pi/3, 2pi/3) is a forward burst of the negated
        phase: the network decodes it as such and the result is turned back (:func:`in_capture_order`).
        """
        # a set orientation is the rig's; a reversed-order burst shows the negated phase, which runs the other way
        mirror = None if self.orientation == "auto" else (self.orientation == "mirrored") != burst.reversed_order
        result = self.predict(burst.images, mc, full_scale=burst.full_scale, angles=np.asarray(burst.angles),
                              mirror=mirror)
        result = in_capture_order(result, burst)
        return dataclasses.replace(result, burst_index=burst.index, angle=float(burst.angles[0]))


def still_gate(result: PhaseResult, classical: np.ndarray, rad: float) -> PhaseResult:
    """``result`` with three-step PS's phase, M and D wherever the two phases differ by less than
    ``rad`` (sigma stays the network's). ``classical``: three-step M, D ``(2, H, W)`` of the burst."""
    m3, d3 = classical
    phase3 = np.arctan2(m3, d3)
    small = np.abs(np.angle(np.exp(1j * (result.phase - phase3)))) < rad

    def pick(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.where(small, b, a).astype(np.float32)

    return dataclasses.replace(result, phase=pick(result.phase, phase3), M=pick(result.M, m3), D=pick(result.D, d3))


THREE_STEP_NOISE = "three-step noise"
BurstSigma = tuple[float, float, float] | str  # a fitted map (a, b, c), or THREE_STEP_NOISE


def burst_sigma_map(meta: dict) -> BurstSigma | None:
    """The gated bursts' sigma from a model's JSON (``still_burst_gate.sigma``), if any: a fitted map
    ``(a, b, c)``, or :data:`THREE_STEP_NOISE` (``{"kind": "three-step noise"}``)."""
    raw = (meta.get("still_burst_gate") or {}).get("sigma")
    if raw is None:
        return None
    if isinstance(raw, dict) and "kind" in raw:
        if raw["kind"] != THREE_STEP_NOISE:
            raise ModelFileError(f"still_burst_gate.sigma.kind: expected {THREE_STEP_NOISE!r}, got {raw['kind']!r}")
        return THREE_STEP_NOISE
    try:
        a, b, c = (float(raw[k]) for k in ("a", "b", "c"))
    except (TypeError, KeyError, ValueError) as exc:
        raise ModelFileError(f"still_burst_gate.sigma: expected {{'a', 'b', 'c'}} numbers, got {raw!r}") from exc
    if not (math.isfinite(a) and a > 0 and all(math.isfinite(v) and abs(v) <= 3 for v in (b, c))):
        raise ModelFileError(f"still_burst_gate.sigma: expected a > 0 and |b|, |c| <= 3, got {raw!r}")
    return a, b, c


def check_mc_phase(value: object, name: str) -> str:
    """``value`` as an MC phase (:data:`MC_PHASES`), or a ValueError naming ``name``."""
    if value not in MC_PHASES:
        raise ValueError(f"{name}: expected one of {', '.join(MC_PHASES)}, got {value!r}")
    return str(value)


def model_mc_phase(meta: dict) -> str:
    """The phase a model's JSON chose for Monte Carlo mode (``mc_phase.phase``); no entry: ``"mean"``."""
    raw = meta.get("mc_phase")
    if raw is None:
        return "mean"
    try:
        return check_mc_phase(raw.get("phase") if isinstance(raw, dict) else None, "mc_phase.phase")
    except ValueError as exc:
        raise ModelFileError(str(exc)) from exc


def check_motion_limit(value: float, name: str) -> float:
    """``value`` as a limit on :func:`frame_motion_share` (> 0; ``inf``: no check), or a ValueError naming ``name``."""
    try:
        limit = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected a share > 0 (inf: no check), got {value!r}") from exc
    if not limit > 0:  # also rejects nan
        raise ValueError(f"{name}: expected a share > 0 (inf: no check), got {value!r}")
    return limit


def burst_motion_limit(meta: dict) -> float:
    """The burst gate's limit on :func:`frame_motion_share` from a model's JSON
    (``still_burst_gate.max_motion_share``); none there: :data:`NO_MOTION_CHECK`."""
    raw = (meta.get("still_burst_gate") or {}).get("max_motion_share")
    if raw is None:
        return NO_MOTION_CHECK
    try:
        return check_motion_limit(raw, "still_burst_gate.max_motion_share")
    except ValueError as exc:
        raise ModelFileError(str(exc)) from exc


NETWORK_SUPPORT_KEY = "network_support"
MAX_SUPPORT_PX = 16  # as the CLI's --network-support-px


@dataclasses.dataclass(frozen=True, slots=True)
class NetworkSupport:
    """The reconstructor's fringe-support tests chosen on val for one model (``network_support`` in its JSON): a
    network pixel is kept only where its burst's own frames show fringes on every pixel within this many px (None:
    no test). ``per_burst_px`` for each burst's cloud; ``frame_fit_px`` where the fused points are then fitted to the
    raw frames (``inspect``, ``replay --fuse``). A property of the model: v6 invents phase at shadow borders that v9
    does not (``benchmarks/network_support_rule.md``)."""

    per_burst_px: int | None
    frame_fit_px: int | None

    def to_json(self, chosen_by: str) -> dict:
        """The JSON entry (:func:`model_network_support` reads it back), with what chose it."""
        return {"per_burst_px": self.per_burst_px, "frame_fit_px": self.frame_fit_px, "chosen_by": chosen_by}


def _support_px(raw: object, name: str) -> int | None:
    if raw is None:
        return None
    if isinstance(raw, bool) or not isinstance(raw, int) or not 0 <= raw <= MAX_SUPPORT_PX:
        raise ModelFileError(f"{name}: expected null (no test) or a whole number of px in 0..{MAX_SUPPORT_PX}, "
                             f"got {raw!r}")
    return raw


def model_network_support(meta: dict) -> NetworkSupport | None:
    """A model's own fringe-support tests from its JSON (:class:`NetworkSupport`); None where the JSON names none
    (the reconstructor then uses the product's, ``recon.measure``)."""
    raw = meta.get(NETWORK_SUPPORT_KEY)
    if raw is None:
        return None
    if not isinstance(raw, dict) or not {"per_burst_px", "frame_fit_px"} <= set(raw):
        raise ModelFileError(f"{NETWORK_SUPPORT_KEY}: expected {{'per_burst_px': px or null, 'frame_fit_px': px or "
                             f"null}}, got {raw!r}")
    return NetworkSupport(_support_px(raw["per_burst_px"], f"{NETWORK_SUPPORT_KEY}.per_burst_px"),
                          _support_px(raw["frame_fit_px"], f"{NETWORK_SUPPORT_KEY}.frame_fit_px"))


DEPTH_SIGMA_KEY = "depth_sigma"


def model_depth_sigma_scales(meta: dict) -> tuple[float, ...] | dict[str, tuple[float, ...]] | None:
    """A model's own depth-sigma scales by edge band (``depth_sigma`` in its JSON: ``{"scales": ..., "edge_bands_px":
    [...], "chosen_by": ...}``, nearest the edge first; ``scales`` one list for every motion class, or one list per
    motion class of ``recon.depth_sigma.MOTION_CLASSES`` (``{"three_step": [...], "network": [...], ...}``); None where the JSON names none
    (the reconstructor then uses the product's; ``recon.depth_sigma.check_scales`` checks the counts and classes)."""
    raw = meta.get(DEPTH_SIGMA_KEY)
    if raw is None:
        return None
    scales = raw.get("scales") if isinstance(raw, dict) else None

    def factors(xs) -> tuple[float, ...] | None:
        ok = (isinstance(xs, list) and xs and all(isinstance(x, int | float) and not isinstance(x, bool)
                                                   and math.isfinite(x) and x >= 1 for x in xs))
        return tuple(float(x) for x in xs) if ok else None

    if (flat := factors(scales)) is not None:
        return flat
    if isinstance(scales, dict) and scales and all(factors(v) is not None for v in scales.values()):
        return {str(k): factors(v) for k, v in scales.items()}
    raise ModelFileError(f"{DEPTH_SIGMA_KEY}: expected {{'scales': [factors >= 1, nearest the edge first] or "
                         f"{{motion class: [factors >= 1]}}, ...}}, got {raw!r}")


REST_SIGMA_KEY = "rest_sigma"


def model_rest_sigma_scale(meta: dict) -> float | None:
    """A model's own scale for the sigma of the fused points the frame fit cannot take (``rest_sigma`` in its JSON:
    ``{"scale": c, "chosen_by": ...}``, chosen on its own val stretches by ``benchmarks/rest_sigma_rule.md``); None
    where the JSON names none (the frame fit then uses the product's, ``recon.track.REST_SIGMA_SCALE``)."""
    raw = meta.get(REST_SIGMA_KEY)
    if raw is None:
        return None
    scale = raw.get("scale") if isinstance(raw, dict) else None
    if isinstance(scale, int | float) and not isinstance(scale, bool) and math.isfinite(scale) and scale >= 1:
        return float(scale)
    raise ModelFileError(f"{REST_SIGMA_KEY}: expected {{'scale': a factor >= 1 (it may not shrink a sigma), ...}}, "
                         f"got {raw!r}")


def still_burst_noise(frames: np.ndarray) -> float | None:
    """Per-frame noise of ``(3, H, W)`` frames in [0, 1] of a burst taken as still
    (:func:`~gearscan.core.phase.still_frame_noise` over its lit pixels, as :func:`frame_motion_share` counts them)."""
    f = np.asarray(frames, np.float32)
    return still_frame_noise(f, 2.0 * frame_swing(f) >= BURST_GATE_MODULATION)


def frame_motion_share(frames: np.ndarray) -> float | None:
    """Share of a burst's lit pixels whose three frames swing more than a still fringe can: the
    three-step amplitude B' above the frames' mean A'. ``frames``: ``(3, H, W)`` in [0, 1]; lit: three-step
    modulation ``2B'`` at least :data:`BURST_GATE_MODULATION`. None when fewer than
    :data:`BURST_GATE_MIN_PIXELS` pixels are lit.

    A still pixel sees ``A + B cos(phi + delta)`` with ``B <= A`` (light is not negative), so B' <= A' up
    to noise; a pixel that an outline or shadow border crosses between the frames need not: dark,
    dark, lit gives ``B' = 2 A'``. Evidence from the frames alone, not from the network.
    """
    f = np.asarray(frames, np.float32)
    if f.ndim != 3 or f.shape[0] != 3:
        raise ValueError(f"frames: expected (3, H, W), got shape {f.shape}")
    swing = frame_swing(f)
    lit = 2.0 * swing >= BURST_GATE_MODULATION
    n = int(lit.sum())
    if n < BURST_GATE_MIN_PIXELS:
        return None
    return float(np.count_nonzero(swing[lit] > f.mean(0)[lit]) / n)


def burst_departure(phase: np.ndarray, classical: np.ndarray) -> float | None:
    """Median ``|wrap(phase - three-step phase)|`` (rad) over the burst's interior: pixels whose
    three-step modulation is at least :data:`BURST_GATE_MODULATION` and every pixel within
    :data:`BURST_GATE_ERODE_PX` of them too. ``classical``: three-step M, D ``(2, H, W)``. None when
    fewer than :data:`BURST_GATE_MIN_PIXELS` pixels qualify.

    A median over the interior, not a mean over every modulated pixel: on still val bursts the
    network departs 0.2 rad and more near edges and creases and in patches, which a mean counts
    (session 24's gate failed on that); the interior's median stays at the noise (0.015-0.05 rad).
    """
    m3, d3 = classical
    lit = (np.hypot(m3, d3) >= BURST_GATE_MODULATION).astype(np.uint8)
    size = 2 * BURST_GATE_ERODE_PX + 1
    inner = cv2.erode(lit, np.ones((size, size), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    inner = inner.astype(bool)
    if int(inner.sum()) < BURST_GATE_MIN_PIXELS:
        return None
    diff = np.asarray(phase, np.float64)[inner] - np.arctan2(m3, d3)[inner]
    return float(np.median(np.abs((diff + np.pi) % (2 * np.pi) - np.pi)))


def still_burst_gate(
    result: PhaseResult, classical: np.ndarray, rad: float, calibration: SigmaMap | None = None,
    sigma_map: BurstSigma | None = None, *, frames: np.ndarray | None = None,
    max_motion: float = NO_MOTION_CHECK,
) -> tuple[PhaseResult, bool]:
    """``result`` decoded by three-step PS if its :func:`burst_departure` is below ``rad`` and, unless
    ``max_motion`` is ``inf``, the :func:`frame_motion_share` of ``frames`` (the burst's ``(3, H, W)`` in [0, 1];
    none, or too few lit pixels: no verdict, so no gate) is below ``max_motion``; and whether it was (its
    ``mode`` then says ``"three-step"``). Each test runs only if the ones before it passed.

    The sigma of a gated burst: with :data:`THREE_STEP_NOISE`, three-step's own noise propagation
    ``sqrt(2/3) s_n / B'`` of the frames' measured noise ``s_n`` (:func:`still_burst_noise`; none: no gate) and
    ``sigma_model`` 0; with a fitted map ``(a, b, c)``, ``a * sigma**b * max(2B/S, 0.01)**c`` of the
    network's sigma and the three-step modulation; without either, what the model's map gives an output
    that agrees with three-step PS (departure 0; a map without the departure term: unchanged).
    """
    score = burst_departure(result.phase, classical)
    if score is None or score >= rad:
        return result, False
    if max_motion < NO_MOTION_CHECK:
        motion = None if frames is None else frame_motion_share(frames)
        if motion is None or not motion < max_motion:
            return result, False
    phase3, m3, d3 = still_phase(*classical)  # three-step PS of a still burst, non-sinusoidal-fringe error removed
    gated = dataclasses.replace(result, phase=phase3, M=m3, D=d3, mode="three-step")
    if sigma_map == THREE_STEP_NOISE:
        noise = None if frames is None else still_burst_noise(frames)
        if noise is None:
            return result, False
        return dataclasses.replace(gated, **three_step_noise_sigma(np.hypot(m3, d3), noise)), True
    f = None
    if sigma_map is not None:
        a, b, c = (np.float32(v) for v in sigma_map)
        s = np.maximum(result.sigma_total.astype(np.float32), np.float32(1e-12))
        mod = np.maximum(np.hypot(m3, d3), np.float32(0.01))
        f = (a * np.power(s, b - 1) * np.power(mod, c)).astype(np.float32)
    elif calibration is not None and calibration.needs_classical:
        # the map read at three-step PS's own departure (0) instead of the network's: the departure it read is the
        # network's phase against three-step PS of the raw frames (to_phase_result), not against still_phase's
        dep = departure(result.phase, np.arctan2(*classical))
        local = local_departure(dep) if calibration.needs_local else None
        zero = np.zeros((), np.float32)
        f = (calibration.departure_factor(zero, None if local is None else zero)
             / calibration.departure_factor(dep, local)).astype(np.float32)
    if f is None:
        return gated, True
    scale = {name: (getattr(result, name) * f).astype(np.float32)
             for name in ("sigma_model", "sigma_data", "sigma_total")}
    scale |= {name: (getattr(result, name) * f * f).astype(np.float32)
              for name in ("var_M", "var_D") if getattr(result, name) is not None}
    return dataclasses.replace(gated, **scale), True


def three_step_noise_sigma(modulation: np.ndarray, noise: float) -> dict[str, np.ndarray]:
    """Three-step PS's noise propagation (:func:`~gearscan.core.phase.noise_sigma`) for frames in [0, 1] with
    per-frame noise ``noise``, the modulation floored at 0.01: data sigma and total, model sigma 0, and M, D
    variances ``8/3 noise**2`` (M, D normalised by ``N S / 4`` with S = 1)."""
    sigma = noise_sigma(np.maximum(np.asarray(modulation, np.float32), np.float32(0.01)), noise, 1.0)
    var = np.full_like(sigma, np.float32(8 / 3 * noise**2))
    return {"sigma_model": np.zeros_like(sigma), "sigma_data": sigma, "sigma_total": sigma.copy(),
            "var_M": var, "var_D": var.copy()}


def apply_still_gates(
    result: PhaseResult, classical: np.ndarray | None, *, pixel_rad: float, burst_rad: float,
    calibration: SigmaMap | None = None, burst_sigma: BurstSigma | None = None,
    frames: np.ndarray | None = None, max_motion: float = NO_MOTION_CHECK,
) -> tuple[PhaseResult, bool]:
    """The burst gate (:func:`still_burst_gate`) on the network's ``result``, then, if it left the
    burst to the network, the per-pixel one (:func:`still_gate`); and whether the burst gate took it."""
    if classical is None:
        return result, False
    if burst_rad > 0:
        result, taken = still_burst_gate(result, classical, burst_rad, calibration, burst_sigma,
                                         frames=frames, max_motion=max_motion)
        if taken:
            return result, True
    return (still_gate(result, classical, pixel_rad) if pixel_rad > 0 else result), False
