"""Saving and loading networks: weights in safetensors, configuration in JSON beside them.

A model is two files with the same stem: ``NAME.safetensors`` (the state dict, no pickle)
and ``NAME.json``::

    {"format": "gearscan-model", "version": 1,
     "model": {...ModelConfig...}, "var_scale": 1.0, ...free-form extras (metrics, training)}

Loading checks both files and names the file and the mismatch when something is wrong.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from gearscan.inference.models import ModelConfig, PhaseNet, build_model

MODEL_FORMAT = "gearscan-model"
MODEL_VERSION = 1


class ModelFileError(ValueError):
    """A weight or config file is missing, unreadable or does not match the network."""


def config_path(weights: str | Path) -> Path:
    return Path(weights).with_suffix(".json")


def save_model(
    model: PhaseNet, path: str | Path, *, var_scale: float = 1.0, extra: dict | None = None
) -> Path:
    """Write ``path`` (.safetensors) and its JSON config atomically; returns the weights path."""
    from safetensors.torch import save_file

    path = Path(path)
    if path.suffix != ".safetensors":
        raise ModelFileError(f"model path: expected a .safetensors file, got {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in unwrap(model).state_dict().items()}
    tmp = path.with_name(path.name + ".tmp")
    save_file(state, str(tmp), metadata={"format": MODEL_FORMAT})
    tmp.replace(path)
    meta = {
        "format": MODEL_FORMAT,
        "version": MODEL_VERSION,
        "model": unwrap(model).config.to_json(),
        "var_scale": float(var_scale),
    }
    meta.update(extra or {})
    write_config(path, meta)
    return path


def write_config(path: str | Path, meta: dict) -> Path:
    """Atomically (re)write the JSON beside ``path`` (.safetensors); the weights are untouched."""
    cfg = config_path(path)
    tmp_cfg = cfg.with_name(cfg.name + ".tmp")
    tmp_cfg.write_text(json.dumps(meta, indent=2) + "\n")
    tmp_cfg.replace(cfg)
    return cfg


def unwrap(model: torch.nn.Module) -> PhaseNet:
    """The bare network inside a DDP / compiled wrapper."""
    while hasattr(model, "module") and isinstance(model.module, torch.nn.Module):
        model = model.module
    return model  # type: ignore[return-value]


def read_config(path: str | Path) -> dict:
    """The JSON beside ``path`` (.safetensors), validated; raises :class:`ModelFileError`."""
    cfg = config_path(path)
    try:
        meta = json.loads(cfg.read_text())
    except FileNotFoundError as exc:
        raise ModelFileError(
            f"model config not found: {cfg} (expected beside the weights {Path(path).name})"
        ) from exc
    except json.JSONDecodeError as exc:
        raise ModelFileError(f"{cfg}: invalid JSON at line {exc.lineno}: {exc.msg}") from exc
    if not isinstance(meta, dict) or meta.get("format") != MODEL_FORMAT:
        raise ModelFileError(
            f'{cfg}: not a gearscan model config (expected "format": "{MODEL_FORMAT}")'
        )
    if meta.get("version") != MODEL_VERSION:
        raise ModelFileError(
            f"{cfg}: model config version {meta.get('version')!r} unsupported (expected {MODEL_VERSION})"
        )
    if "model" not in meta:
        raise ModelFileError(f'{cfg}: missing section "model"')
    return meta


DECODE_KEYS = ("var_scale", "sigma_calibration", "uncertainty_calibration", "still_gate", "still_burst_gate")
"""A model JSON's entries that its deterministic decode reads besides the weights: sigma maps and still gates
(``uncertainty_calibration``, the maps' fit report, changes with them). Not in it: ``model`` (the architecture,
which changes only with the weights) and ``mc_phase`` (MC mode only; no val choice keyed on this decodes MC)."""


def model_fingerprint(path: str | Path) -> str:
    """12 hex digits of sha256 over the weights and the JSON entries their decode reads (:data:`DECODE_KEYS`): a
    val choice recorded with one fingerprint was made for exactly this decode (refitted sigma maps change it)."""
    import hashlib

    meta = read_config(path)
    decode = json.dumps({k: meta.get(k) for k in DECODE_KEYS}, sort_keys=True).encode()
    return hashlib.sha256(Path(path).read_bytes() + decode).hexdigest()[:12]


def load_state(path: str | Path) -> dict[str, torch.Tensor]:
    """Tensors of a safetensors file; raises :class:`ModelFileError` naming the file."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"model weights not found: {path}")
    try:
        state = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as exc:
        raise ModelFileError(f"{path}: not a readable safetensors file ({exc})") from exc
    for name, tensor in state.items():  # one NaN weight makes every output pixel NaN
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            bad = int((~torch.isfinite(tensor)).sum())
            raise ModelFileError(f"{path}: tensor {name!r} holds {bad} NaN or infinite value(s) of {tensor.numel()}: "
                                 "damaged or diverged weights, refused")
    return state


def widen_inputs(state: dict[str, torch.Tensor], model: torch.nn.Module, after: int = 3) -> list[str]:
    """Give ``state``'s first convs the extra input channels ``model`` has, zero-initialised.

    The new channels go after the ``after`` frames (where :class:`ModelConfig` puts extras such
    as the motion channels), so the widened network computes exactly what the file's did and
    learns to use the new inputs from there. Returns the keys it widened.
    """
    own = unwrap(model).state_dict()
    widened = []
    for k, w in state.items():
        o = own.get(k)
        if o is None or w.ndim != 4 or o.ndim != 4 or o.shape[1] <= w.shape[1]:
            continue
        if o.shape[0] != w.shape[0] or o.shape[2:] != w.shape[2:]:
            continue
        extra = torch.zeros((w.shape[0], o.shape[1] - w.shape[1], *w.shape[2:]), dtype=w.dtype)
        state[k] = torch.cat([w[:, :after], extra, w[:, after:]], dim=1)
        widened.append(k)
    return widened


def load_into(model: torch.nn.Module, state: dict[str, torch.Tensor], source: str | Path) -> None:
    """Strictly load ``state`` into ``model``, with a message listing every mismatch."""
    own = unwrap(model).state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    shapes = [
        f"{k}: file {tuple(state[k].shape)} vs model {tuple(own[k].shape)}"
        for k in own
        if k in state and state[k].shape != own[k].shape
    ]
    if missing or unexpected or shapes:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing keys (e.g. {missing[:3]})")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected keys (e.g. {unexpected[:3]})")
        if shapes:
            parts.append(f"{len(shapes)} shape mismatches (e.g. {shapes[:3]})")
        raise ModelFileError(f"{source}: weights do not match the network: " + "; ".join(parts))
    unwrap(model).load_state_dict(state, strict=True)


def load_model(path: str | Path, map_location: str | torch.device = "cpu") -> tuple[PhaseNet, dict]:
    """Build the network described by ``path``'s JSON and load its weights; returns (model, meta)."""
    path = Path(path)
    meta = read_config(path)
    try:
        config = ModelConfig.from_json(meta["model"], source=str(config_path(path)))
    except (TypeError, ValueError) as exc:
        raise ModelFileError(f'{config_path(path)}: bad "model" section: {exc}') from exc
    model = build_model(config)
    load_into(model, load_state(path), path)
    return model.to(map_location).eval(), meta
