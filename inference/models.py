"""CD-DCU-Net and its peer networks (paper §2.2 and §3.4), all with one interface.

Every model maps ``(B, C_in, H, W)`` float32 frames in [0, 1] (the three phase-shifted
frames, then any extra channels) to ``(B, 4, H, W)``: mean M, mean D, var M, var D, with the
variances passed through ``softplus + 1e-3`` (paper §3.3). M and D are on the scale of the
labels, normalised by ``N*S/4`` so that ``hypot(M, D) = 2B/S`` (DESIGN.md). Any H, W works:
the input is padded to a multiple of 16 (reflect) and the output cropped back.

Models (``build_model(name, ...)``):

- ``cd-dcu-net``: Double Conv U-Net, Concrete Dropout (own 3x3 conv) after the stem, every
  down stage and every up stage (9 layers), dual 3x3 head with no norm/activation.
- ``unet``: the same encoder/decoder without dropout, 1x1 head.
- ``ts-unet``: three parallel encoders, one per frame, fused per scale by a 1x1 conv, one
  decoder, 3x3 head.
- ``dr-unet``: residual blocks instead of Double Conv, 1x1 head.

Two options let the network start from what three-step phase shifting already knows
(computed inside the model from the first three input channels, so callers still feed only
frames): ``classical_input`` appends the classical M, D as two extra input channels, and
``residual`` makes the mean outputs a correction added to the classical M, D.
``motion_input`` (not in the paper) adds the turntable's rotation from frame 1 to frames 2 and
3, as measured by the encoder, as two constant input channels (:func:`motion_channels`): three
frames alone cannot tell a still gear from a slowly moving one on a smooth flank.

Monte Carlo sampling (:func:`gearscan.inference.uncertainty.mc_moments`) splits a pass in two:
:meth:`PhaseNet.mc_prefix` computes what precedes the first stochastic layer once per input
(classical M, D, padding and, for the U-Net family, the stem), :meth:`PhaseNet.mc_passes` runs the
rest for ``k`` passes; for the same random stream the samples are those of ``forward``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gearscan.inference.blocks import (
    Decoder,
    DoubleConv,
    Encoder,
    ResidualBlock,
    encoder_channels,
    make_head,
)
from gearscan.inference.concrete_dropout import ConcreteDropout2d

MULTIPLE = 16
VAR_FLOOR = 1e-3
MOTION_CHANNELS = 2
PRIOR_CHANNELS = 7
PRIOR_LOG_RATIO_CLIP = 1.4  # |log| of a shading ratio beyond 4x is no longer one surface's shading
MODEL_NAMES = ("cd-dcu-net", "unet", "ts-unet", "dr-unet")


@dataclass
class ModelConfig:
    """Everything needed to rebuild a network; stored as JSON beside its weights."""

    name: str = "cd-dcu-net"
    width: int = 16
    in_channels: int = 3
    classical_input: bool = False
    residual: bool = False
    motion_input: bool = False  # channels 3, 4 of the input: motion_channels() of the burst
    prior_input: bool = False  # then PRIOR_CHANNELS of prior_channels(): the twin's per-pixel prediction
    dropout: bool | None = None  # None: Concrete Dropout for cd-dcu-net only
    channelwise: bool = True
    temperature: float | None = None
    weight_reg: float = 1e-5
    dropout_reg: float = 1e-6
    init_min: float = 0.1
    init_max: float = 0.4
    head_fp32: bool = True  # run the output head outside autocast (bf16 would quantise M, D)

    def __post_init__(self) -> None:
        if self.name not in MODEL_NAMES:
            raise ValueError(f"model name: expected one of {MODEL_NAMES}, got {self.name!r}")
        if self.width < 1:
            raise ValueError(f"width: expected >= 1, got {self.width}")
        if self.in_channels < 3:
            raise ValueError(
                f"in_channels: expected >= 3 (three frames + extras), got {self.in_channels}"
            )
        if self.motion_input and self.in_channels < 3 + MOTION_CHANNELS:
            raise ValueError(
                f"in_channels: motion_input needs >= {3 + MOTION_CHANNELS} (frames + motion), got {self.in_channels}"
            )
        if self.prior_input and self.in_channels < 3 + MOTION_CHANNELS * self.motion_input + PRIOR_CHANNELS:
            raise ValueError(
                f"in_channels: prior_input needs >= {3 + MOTION_CHANNELS * self.motion_input + PRIOR_CHANNELS} "
                f"(frames{' + motion' if self.motion_input else ''} + prior), got {self.in_channels}"
            )
        if self.dropout is None:
            self.dropout = self.name == "cd-dcu-net"

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict, source: str = "model config") -> ModelConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(
                f"{source}: unknown model config keys {unknown} (known: {sorted(known)})"
            )
        return cls(**data)


def motion_channels(angles_rad, height: int, width: int) -> np.ndarray:
    """``(2, H, W)`` float32: |rotation| from frame 1 to frames 2 and 3 in degrees, constant maps.

    Magnitudes only: the sign depends on the turntable's direction, which the images show.
    """
    a = np.asarray(angles_rad, dtype=np.float64).reshape(-1)
    if a.size != 3 or not np.all(np.isfinite(a)):
        raise ValueError(f"angles: expected the 3 finite frame angles of a burst (rad), got {angles_rad!r}")
    deltas = np.degrees(np.abs(a[1:] - a[0])).astype(np.float32)
    return np.broadcast_to(deltas[:, None, None], (MOTION_CHANNELS, height, width)).copy()


def prior_channels(change: np.ndarray, ratio: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``(PRIOR_CHANNELS, H, W)`` float32 network input from the twin's prediction for one burst.

    ``change`` ``(2, H, W)``: the fringe phase change (rad) the CAD predicts at each pixel from the
    first frame to the second and third; ``ratio`` ``(2, H, W)``: their irradiance over the first
    frame's; ``known`` ``(H, W)`` bool: where the prediction holds (one smooth lit surface). Channels:
    sin and 1 - cos of each change (continuous across the wrap, 0 for a still gear), the clipped log
    ratios, and ``known``; all 0 where not known. Only phase *changes* enter, never the CAD's phase,
    so a gear off its CAD keeps its deviation.
    """
    change, ratio, known = np.asarray(change, np.float64), np.asarray(ratio, np.float64), np.asarray(known, bool)
    if change.ndim != 3 or change.shape[0] != 2 or ratio.shape != change.shape or known.shape != change.shape[1:]:
        raise ValueError(f"prior maps: expected change and ratio (2, H, W) and known (H, W), got "
                         f"{change.shape}, {ratio.shape}, {known.shape}")
    ok = known & np.isfinite(change).all(0) & np.isfinite(ratio).all(0) & (ratio > 0).all(0)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_ratio = np.clip(np.log(np.where(ratio > 0, ratio, 1.0)), -PRIOR_LOG_RATIO_CLIP, PRIOR_LOG_RATIO_CLIP)
    ch = np.concatenate([np.sin(change[:1]), 1 - np.cos(change[:1]), np.sin(change[1:]), 1 - np.cos(change[1:]),
                         log_ratio, np.ones((1, *known.shape))])
    return np.where(ok[None], np.nan_to_num(ch), 0.0).astype(np.float32)


def classical_md(frames: torch.Tensor) -> torch.Tensor:
    """Three-step M, D ``(B, 2, H, W)`` of frames ``(B, 3, H, W)`` in [0, 1] (S = 1, N = 3)."""
    shifts = torch.tensor(
        [0.0, 2 * math.pi / 3, 4 * math.pi / 3], device=frames.device, dtype=frames.dtype
    )
    norm = 3.0 / 4.0
    m = -(frames * torch.sin(shifts)[None, :, None, None]).sum(1) / norm
    d = (frames * torch.cos(shifts)[None, :, None, None]).sum(1) / norm
    return torch.stack([m, d], dim=1)


def pad_to_multiple(
    x: torch.Tensor, multiple: int = MULTIPLE
) -> tuple[torch.Tensor, tuple[int, int, int, int]]:
    """Pad ``(B, C, H, W)`` so H and W are multiples of ``multiple``; returns (padded, (l, r, t, b)).

    Reflect padding where the image is large enough, replicate otherwise (reflect needs pad < size).
    """
    h, w = x.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    pads = (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2)
    if ph == 0 and pw == 0:
        return x, pads
    mode = "reflect" if max(pads[0], pads[1]) < w and max(pads[2], pads[3]) < h else "replicate"
    return F.pad(x, pads, mode=mode), pads


@dataclass(frozen=True)
class McPrefix:
    """The part of a network's pass over one input that Monte Carlo sampling computes once.

    ``shared``: input of the first stochastic layer, ``(B, ...)`` (padded);
    ``base``: classical M, D ``(B, 2, H, W)`` that the mean outputs correct (``residual``), or None;
    ``crop``: ``(top, left, h, w)`` of the input inside the padded maps.
    """

    shared: torch.Tensor
    base: torch.Tensor | None
    crop: tuple[int, int, int, int]


def _crop(raw: torch.Tensor, crop: tuple[int, int, int, int]) -> torch.Tensor:
    """``raw`` cropped back to the input size, float32, contiguous (NCHW).

    Contiguous because the head's output may be channels_last, and softplus on a channel slice
    of that runs a strided scalar loop (measured ~10x slower than on contiguous maps).
    """
    top, left, h, w = crop
    return raw[:, :, top : top + h, left : left + w].float().contiguous()


def repeat_batch(x: torch.Tensor, k: int) -> torch.Tensor:
    """``x`` ``(B, ...)`` repeated ``k`` times along the batch (pass-major), in ``x``'s memory format."""
    if k == 1:
        return x
    cl = x.ndim == 4 and not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last)
    out = x.repeat(k, *([1] * (x.ndim - 1)))
    return out.contiguous(memory_format=torch.channels_last) if cl else out


def dropout_on_shared_input(layer: nn.Module, x: torch.Tensor, k: int) -> torch.Tensor:
    """``layer(repeat_batch(x, k))``: ``k`` passes of a dropout layer over one shared input.

    For a stochastic channel-wise :class:`ConcreteDropout2d` and ``x`` ``(1, C, H, W)``, pass
    ``t`` is ``conv(x * m_t) = conv(x; W * m_t)`` (a channel mask on the input of a linear conv
    scales the weights per input channel), so the ``k`` passes are ONE convolution of ``x`` with
    the ``k`` scaled weight sets stacked along its output channels: ``x`` is read once, no masked
    copies of it are made, and a conv with ``k * C_out`` outputs runs faster than ``k`` with
    ``C_out``. The masks are the layer's own draw for a batch of ``k`` (same shape, same random
    stream), so the samples are those of the plain path. Anything else: the plain path.
    """
    if not (
        isinstance(layer, ConcreteDropout2d)
        and layer.stochastic
        and layer.channelwise
        and x.ndim == 4
        and x.shape[0] == 1
    ):
        return layer(repeat_batch(x, k))
    c = layer.conv
    keep = layer.drop(torch.ones(k, x.shape[1], 1, 1, device=x.device))  # (k, C_in, 1, 1) float32
    w = c.weight.unsqueeze(0) * keep.unsqueeze(1).to(c.weight.dtype)  # (k, C_out, C_in, kh, kw)
    w = w.reshape(-1, *c.weight.shape[1:])
    b = None if c.bias is None else c.bias.repeat(k)
    y = F.conv2d(x, w, b, c.stride, c.padding, c.dilation, c.groups)  # (1, k*C_out, H', W')
    if y.is_contiguous():  # NCHW: already pass-major
        return y.view(k, -1, *y.shape[2:])
    # channels_last: memory (H', W', k, C_out) -> (k, H', W', C_out)
    h, w_ = y.shape[2:]
    return (
        y.permute(0, 2, 3, 1)
        .reshape(h, w_, k, -1)
        .permute(2, 3, 0, 1)
        .contiguous(memory_format=torch.channels_last)
    )


class PhaseNet(nn.Module):
    """Common wrapper: input checks, classical M/D options, padding, output activation.

    Subclasses implement :meth:`core`, mapping padded ``(B, C, H, W)`` to raw ``(B, 4, H, W)``.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config

    @property
    def core_in_channels(self) -> int:
        return self.config.in_channels + (2 if self.config.classical_input else 0)

    def drop_factory(self):
        c = self.config
        if not c.dropout:
            return None

        def make(ch: int) -> nn.Module:
            return ConcreteDropout2d(
                ch,
                weight_reg=c.weight_reg,
                dropout_reg=c.dropout_reg,
                init_min=c.init_min,
                init_max=c.init_max,
                temperature=c.temperature,
                channelwise=c.channelwise,
            )

        return make

    def core(self, x: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def run_head(self, head: nn.Module, x: torch.Tensor) -> torch.Tensor:
        if self.config.head_fp32 and torch.is_autocast_enabled(x.device.type):
            with torch.autocast(device_type=x.device.type, enabled=False):
                return head(x.float())
        return head(x)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, C_in, H, W)`` -> ``(B, 4, H, W)``: mean M, mean D, var M, var D (float32)."""
        padded, base, crop = self._prepare(x)
        raw = _crop(self.core(padded), crop)
        mean = raw[:, :2] + base if self.config.residual else raw[:, :2]
        var = F.softplus(raw[:, 2:]) + VAR_FLOOR
        return torch.cat([mean, var], dim=1)

    def _prepare(
        self, x: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None, tuple[int, int, int, int]]:
        """Checked, padded core input; classical M, D (or None); ``(top, left, h, w)`` to crop back."""
        if x.ndim != 4 or x.shape[1] != self.config.in_channels:
            raise ValueError(
                f"{self.config.name}: expected input (B, {self.config.in_channels}, H, W), got {tuple(x.shape)}"
            )
        h, w = x.shape[-2:]
        base = (
            classical_md(x[:, :3].float())
            if (self.config.classical_input or self.config.residual)
            else None
        )
        inp = torch.cat([x, base.to(x.dtype)], dim=1) if self.config.classical_input else x
        padded, (left, _, top, _) = pad_to_multiple(inp)
        return padded, base, (top, left, h, w)

    # --- Monte Carlo sampling: the deterministic prefix once, the stochastic rest per pass -----
    def core_prefix(self, x: torch.Tensor) -> torch.Tensor:
        """The part of :meth:`core` before its first stochastic layer (here: none; subclasses)."""
        return x

    def core_passes(self, shared: torch.Tensor, k: int) -> torch.Tensor:
        """:meth:`core` for ``k`` stochastic passes from ``core_prefix``'s output ``(B, ...)``:
        ``(k*B, 4, H, W)`` raw, pass-major (the order of ``x.repeat(k, 1, 1, 1)``)."""
        return self.core(repeat_batch(shared, k))

    def mc_prefix(self, x: torch.Tensor) -> McPrefix:
        """What every stochastic pass over ``x`` ``(B, C_in, H, W)`` shares, computed once."""
        padded, base, crop = self._prepare(x)
        return McPrefix(self.core_prefix(padded), base if self.config.residual else None, crop)

    def mc_passes(self, prefix: McPrefix, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``k`` stochastic passes: means WITHOUT ``prefix.base`` and variances, each ``(k*B, 2, H, W)``.

        ``forward`` of ``x.repeat(k, 1, 1, 1)`` gives the same samples (same masks for the same
        random stream) with ``prefix.base`` added to the means; leaving that constant out lets the
        caller accumulate the small corrections and add it once.
        """
        raw = _crop(self.core_passes(prefix.shared, k), prefix.crop)
        return raw[:, :2], F.softplus(raw[:, 2:]) + VAR_FLOOR


class UNetFamily(PhaseNet):
    """Single-stream encoder/decoder with a configurable block and head."""

    def __init__(self, config: ModelConfig, block, head: str) -> None:
        super().__init__(config)
        drop = self.drop_factory()
        self.encoder = Encoder(self.core_in_channels, config.width, block, drop)
        self.decoder = Decoder(self.encoder.channels, block, drop)
        self.head = make_head(head, config.width)

    def core(self, x: torch.Tensor) -> torch.Tensor:
        return self.run_head(self.head, self.decoder(self.encoder(x)))

    def core_prefix(self, x: torch.Tensor) -> torch.Tensor:
        """The stem: deterministic, full resolution, before the first dropout layer."""
        return self.encoder.stem(x)

    def core_passes(self, shared: torch.Tensor, k: int) -> torch.Tensor:
        first = dropout_on_shared_input(self.encoder.drops[0], shared, k)
        return self.run_head(self.head, self.decoder(self.encoder.from_first(first)))


class CDDCUNet(UNetFamily):
    """CD-DCU-Net (paper Fig. 4): Double Conv U-Net + Concrete Dropout + dual 3x3 head."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__(config, DoubleConv, "dual3x3")


class UNet(UNetFamily):
    """Classic U-Net peer (Ronneberger et al.): Double Conv blocks, 1x1 output conv."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__(config, DoubleConv, "1x1")


class DRUNet(UNetFamily):
    """Deep residual U-Net peer: residual blocks instead of Double Conv, 1x1 output conv."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__(config, ResidualBlock, "1x1")


class TSUNet(PhaseNet):
    """Temporal three-stream U-Net peer: one encoder per frame, fused per scale, 3x3 head.

    Stream ``k`` sees frame ``k`` plus every extra channel (classical M/D or user extras).
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__(config)
        drop = self.drop_factory()
        extra = self.core_in_channels - 3
        self.streams = nn.ModuleList(
            Encoder(1 + extra, config.width, DoubleConv, drop) for _ in range(3)
        )
        chans = encoder_channels(config.width)
        self.fuse = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(3 * c, c, 1, bias=False), nn.BatchNorm2d(c), nn.ReLU(inplace=True)
            )
            for c in chans
        )
        self.decoder = Decoder(chans, DoubleConv, drop)
        self.head = make_head("3x3", config.width)

    def core(self, x: torch.Tensor) -> torch.Tensor:
        extras = x[:, 3:]
        per_stream = [
            enc(torch.cat([x[:, k : k + 1], extras], dim=1)) for k, enc in enumerate(self.streams)
        ]
        fused = [
            f(torch.cat(level, dim=1))
            for f, level in zip(self.fuse, zip(*per_stream, strict=True), strict=True)
        ]
        return self.run_head(self.head, self.decoder(fused))


_REGISTRY: dict[str, type[PhaseNet]] = {
    "cd-dcu-net": CDDCUNet,
    "unet": UNet,
    "ts-unet": TSUNet,
    "dr-unet": DRUNet,
}


def build_model(
    name: str | ModelConfig = "cd-dcu-net", width: int = 16, in_channels: int = 3, **options
) -> PhaseNet:
    """Build a network by name (``cd-dcu-net``, ``unet``, ``ts-unet``, ``dr-unet``) or from a config.

    ``options`` are the other :class:`ModelConfig` fields (``classical_input``, ``residual``,
    ``dropout``, ``temperature``, ``channelwise``, ``weight_reg``, ``dropout_reg``, ...).
    """
    config = (
        name
        if isinstance(name, ModelConfig)
        else ModelConfig(name=name, width=width, in_channels=in_channels, **options)
    )
    return _REGISTRY[config.name](config)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
