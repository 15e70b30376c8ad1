"""Building blocks of the U-Net family: conv blocks, encoder, decoder, output heads.

The models in :mod:`gearscan.inference.models` are thin compositions of these parts
(segmentation_models_pytorch style). Every block keeps the spatial size except the
2x2 max pool (halves) and the 2x2 transposed conv (doubles).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

BlockFactory = Callable[[int, int], nn.Module]
DropFactory = Callable[[int], nn.Module]


class DoubleConv(nn.Sequential):
    """(3x3 conv, BN, ReLU) twice: the paper's Double Conv unit (§2.2)."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__(
            nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(inplace=True),
            nn.Conv2d(out_channels, out_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(inplace=True),
        )


class ResidualBlock(nn.Module):
    """Pre-activation-free residual block (DR-U-Net): ReLU(BN(conv(ReLU(BN(conv x)))) + skip)."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(inplace=True),
            nn.Conv2d(out_channels, out_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(out_channels),
        )
        self.skip: nn.Module = (
            nn.Identity()
            if in_channels == out_channels
            else nn.Sequential(
                nn.Conv2d(in_channels, out_channels, 1, bias=False), nn.BatchNorm2d(out_channels)
            )
        )
        self.act = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.body(x) + self.skip(x))


def encoder_channels(width: int, depth: int = 4) -> list[int]:
    """Channels per scale: ``w, 2w, ..., 2**depth w`` (paper: 64 ... 1024)."""
    return [width * 2**i for i in range(depth + 1)]


def _identity(_: int) -> nn.Module:
    return nn.Identity()


class Encoder(nn.Module):
    """Stem block then ``depth`` stages of (2x2 max pool, block), each followed by ``drop``.

    Returns the feature maps of every scale, finest first: ``[(B, w, H, W), ...,
    (B, 16w, H/16, W/16)]`` for depth 4.
    """

    def __init__(
        self,
        in_channels: int,
        width: int,
        block: BlockFactory,
        drop: DropFactory | None = None,
        depth: int = 4,
    ) -> None:
        super().__init__()
        drop = drop or _identity
        chans = encoder_channels(width, depth)
        self.channels = chans
        self.stem = block(in_channels, chans[0])
        self.downs = nn.ModuleList(
            nn.Sequential(nn.MaxPool2d(2), block(chans[i], chans[i + 1])) for i in range(depth)
        )
        self.drops = nn.ModuleList(drop(c) for c in chans)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        return self.from_first(self.drops[0](self.stem(x)))

    def from_first(self, first: torch.Tensor) -> list[torch.Tensor]:
        """The feature maps of every scale given the finest one, ``drops[0](stem(x))``.

        Lets Monte Carlo sampling run the deterministic stem once per input and only the rest
        once per pass (:meth:`gearscan.inference.models.UNetFamily.core_passes`).
        """
        feats = [first]
        for down, dr in zip(self.downs, self.drops[1:], strict=True):
            feats.append(dr(down(feats[-1])))
        return feats


class DecoderStage(nn.Module):
    """2x2 transposed conv (c -> c/2), concat the skip (c/2), block (c -> c/2), drop."""

    def __init__(self, channels: int, block: BlockFactory, drop: DropFactory) -> None:
        super().__init__()
        half = channels // 2
        self.up = nn.ConvTranspose2d(channels, half, 2, stride=2)
        self.block = block(channels, half)
        self.drop = drop(half)

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        return self.drop(self.block(torch.cat([self.up(x), skip], dim=1)))


class Decoder(nn.Module):
    """U-Net decoder: one :class:`DecoderStage` per scale, coarsest first; out ``(B, w, H, W)``."""

    def __init__(
        self, channels: list[int], block: BlockFactory, drop: DropFactory | None = None
    ) -> None:
        super().__init__()
        drop = drop or _identity
        self.stages = nn.ModuleList(DecoderStage(c, block, drop) for c in reversed(channels[1:]))

    def forward(self, feats: list[torch.Tensor]) -> torch.Tensor:
        x = feats[-1]
        for stage, skip in zip(self.stages, reversed(feats[:-1]), strict=True):
            x = stage(x, skip)
        return x


def make_head(kind: str, width: int, out_channels: int = 4) -> nn.Module:
    """Output head without norm or activation.

    ``"dual3x3"``: 3x3 conv keeping ``width`` channels then 3x3 conv to ``out_channels``
    (CD-DCU-Net, paper §2.2); ``"3x3"``: one 3x3 conv (TS-U-Net); ``"1x1"``: one 1x1 conv (U-Net).
    """
    if kind == "dual3x3":
        return nn.Sequential(
            nn.Conv2d(width, width, 3, padding=1), nn.Conv2d(width, out_channels, 3, padding=1)
        )
    if kind == "3x3":
        return nn.Conv2d(width, out_channels, 3, padding=1)
    if kind == "1x1":
        return nn.Conv2d(width, out_channels, 1)
    raise ValueError(f"head kind: expected 'dual3x3', '3x3' or '1x1', got {kind!r}")


@torch.no_grad()
def fold_batchnorm(model: nn.Module) -> nn.Module:
    """Fold every eval-mode BatchNorm that directly follows a conv in a Sequential into that conv.

    Exact for inference (BN in eval mode is affine), one pass less over each feature map. The
    model is changed in place and returned; only for models that will not be trained again.
    """
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    if model.training:
        raise ValueError("fold_batchnorm: call model.eval() first (training-mode BN cannot be folded)")
    for seq in [m for m in model.modules() if isinstance(m, nn.Sequential)]:
        names = list(seq._modules)
        for a, b in zip(names, names[1:], strict=False):
            conv, bn = seq._modules[a], seq._modules[b]
            if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d):
                seq._modules[a] = fuse_conv_bn_eval(conv, bn)
                seq._modules[b] = nn.Identity()
    return model
