"""Concrete Dropout (Gal, Hron & Kendall 2017) with a learned rate per layer.

A :class:`ConcreteDropout2d` layer drops input features with a relaxed-Bernoulli mask whose
rate ``p`` is a trainable parameter, then applies its own 3x3 convolution (paper §2.2: "each
Concrete Dropout layer includes a dedicated 3x3 convolution"). Its contribution to the
variational KL term (paper eq. 16) is :meth:`ConcreteDropout2d.regularization`:

``weight_reg * sum(W^2) / (1 - p) + dropout_reg * input_dim * (p log p + (1 - p) log(1 - p))``

with ``W`` all parameters of the layer's convolution (weight and bias, as in the reference
code ``yaringal/ConcreteDropout``) and ``input_dim`` the number of independently dropped
units per sample.

Choices (and why)
-----------------
- **Channel-wise masks** by default: noise of shape ``(B, C, 1, 1)`` (the reference code's
  spatial variant). Neighbouring pixels of a feature map are strongly correlated, so
  element-wise dropout barely removes information, and the reference README warns that the
  element-wise regulariser is mis-weighted on conv layers; on CPU an element-wise mask also
  costs up to half a bf16 forward pass while a channel mask costs almost nothing
  (PLATFORM.md). ``input_dim`` is then ``C``. ``channelwise=False`` gives element-wise masks
  of shape ``(B, C, H, W)`` with ``input_dim = C*H*W`` of the last input seen.
- **Temperature 2/3** by default for channel-wise masks (the reference spatial variant's
  value) and 0.1 for element-wise ones (the reference dense value). The paper's eq. 18 says
  0.5; pass ``temperature=0.5`` to follow it. A temperature near 2/3 keeps the relaxed mask
  away from hard 0/1 so the gradient with respect to ``p`` stays informative when only
  ``B*C`` mask values are drawn per step.
- **Inverted scaling**: kept features are divided by ``1 - p`` during stochastic passes (as in
  the reference code). The relaxed mask is not unbiased (at temperature 2/3 and p = 0.3,
  ``E[1 - z] / (1 - p)`` is 0.946, not 1), so the deterministic mode multiplies the input by
  that exact expectation, :meth:`ConcreteDropout2d.keep_scale` (64-point Gauss-Legendre
  quadrature over the uniform noise, differentiable in p), before the plain convolution. As the
  convolution is linear, the deterministic output is then exactly the expectation of the
  stochastic one.

Modes: ``stochastic=True`` draws masks in every forward pass, in training *and* eval mode
(MC sampling runs the network in eval mode so batch norm uses its running statistics);
``stochastic=False`` is the plain deterministic convolution. Use :func:`set_stochastic` to
switch every layer of a model at once.

References
----------
Y. Gal, J. Hron, A. Kendall, "Concrete Dropout", NeurIPS 2017, arXiv:1705.07832.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

EPS = 1e-7
_GL_NODES, _GL_WEIGHTS = (torch.from_numpy(a) for a in np.polynomial.legendre.leggauss(64))


def _logit(p: float) -> float:
    return math.log(p) - math.log1p(-p)


class ConcreteDropout2d(nn.Module):
    """Relaxed-Bernoulli dropout with learned rate followed by its own conv.

    Parameters
    ----------
    in_channels, out_channels : channels of the input and of the conv output (out defaults to in)
    kernel_size : size of the layer's own convolution (3 as in the paper)
    weight_reg, dropout_reg : lambda_1 and lambda_2 of eq. 16 (paper: 1e-5 and 1e-6)
    init_min, init_max : the initial rate is drawn uniformly in logit space between these
    temperature : relaxation temperature; ``None`` picks 2/3 (channel-wise) or 0.1 (element-wise)
    channelwise : mask shape ``(B, C, 1, 1)`` if True, ``(B, C, H, W)`` otherwise

    Shapes: input ``(B, C_in, H, W)``, output ``(B, C_out, H, W)``.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int | None = None,
        *,
        kernel_size: int = 3,
        weight_reg: float = 1e-5,
        dropout_reg: float = 1e-6,
        init_min: float = 0.1,
        init_max: float = 0.4,
        temperature: float | None = None,
        channelwise: bool = True,
    ) -> None:
        super().__init__()
        if not 0.0 < init_min <= init_max < 1.0:
            raise ValueError(
                f"init_min/init_max: expected 0 < min <= max < 1, got {init_min}, {init_max}"
            )
        if temperature is not None and temperature <= 0:
            raise ValueError(f"temperature: expected > 0, got {temperature}")
        out_channels = in_channels if out_channels is None else out_channels
        self.conv = nn.Conv2d(in_channels, out_channels, kernel_size, padding=kernel_size // 2)
        self.weight_reg = float(weight_reg)
        self.dropout_reg = float(dropout_reg)
        self.channelwise = bool(channelwise)
        self.temperature = float(
            temperature if temperature is not None else (2 / 3 if channelwise else 0.1)
        )
        lo, hi = _logit(init_min), _logit(init_max)
        self.p_logit = nn.Parameter(torch.empty(1).uniform_(lo, hi))
        self.stochastic = False
        self._input_dim = in_channels

    @property
    def p(self) -> torch.Tensor:
        """Current dropout rate, a 1-element tensor in (0, 1)."""
        return torch.sigmoid(self.p_logit)

    def keep_scale(self) -> torch.Tensor:
        """``E[(1 - z) / (1 - p)]`` of the relaxed mask (1-element tensor), by quadrature over u."""
        p = self.p.double()
        u = (_GL_NODES.to(p.device) + 1) / 2
        w = _GL_WEIGHTS.to(p.device) / 2
        z = torch.sigmoid(
            (torch.log(p) - torch.log1p(-p) + torch.log(u) - torch.log1p(-u)) / self.temperature
        )
        return ((w * (1 - z)).sum() / (1 - p)).float()

    def extra_repr(self) -> str:
        return (
            f"p={self.p.item():.3f}, temperature={self.temperature:g}, channelwise={self.channelwise}, "
            f"stochastic={self.stochastic}"
        )

    def drop(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` times a freshly drawn relaxed mask, kept features scaled by ``1 / (1 - p)``; the
        stochastic pass applies the layer's conv to this (MC sampling may batch that conv itself)."""
        p = self.p.to(torch.float32)
        shape = (x.shape[0], x.shape[1], 1, 1) if self.channelwise else x.shape
        u = torch.rand(shape, device=x.device, dtype=torch.float32)
        drop_prob = torch.sigmoid(
            (
                torch.log(p + EPS)
                - torch.log1p(-p + EPS)
                + torch.log(u + EPS)
                - torch.log1p(-u + EPS)
            )
            / self.temperature
        )
        keep = (1.0 - drop_prob) / (1.0 - p)
        return x * keep.to(x.dtype)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim != 4:
            raise ValueError(f"ConcreteDropout2d: expected (B, C, H, W), got {tuple(x.shape)}")
        self._input_dim = x.shape[1] if self.channelwise else x.shape[1] * x.shape[2] * x.shape[3]
        if self.stochastic:
            return self.conv(self.drop(x))
        # deterministic: conv(x * s) == conv with weights * s, without a pass over the feature map
        scale = self.keep_scale().to(self.conv.weight.dtype)
        c = self.conv
        return F.conv2d(x, c.weight * scale, c.bias, c.stride, c.padding, c.dilation, c.groups)

    def regularization(self) -> torch.Tensor:
        """This layer's KL contribution (scalar tensor, differentiable in W and p)."""
        p = self.p.squeeze(0)
        sq = sum(torch.sum(w.float() ** 2) for w in self.conv.parameters())
        weight_term = self.weight_reg * sq / (1.0 - p)
        entropy_term = p * torch.log(p) + (1.0 - p) * torch.log1p(-p)
        return weight_term + self.dropout_reg * self._input_dim * entropy_term


def concrete_layers(model: nn.Module) -> list[ConcreteDropout2d]:
    """All Concrete Dropout layers of ``model`` in registration order."""
    return [m for m in model.modules() if isinstance(m, ConcreteDropout2d)]


def set_stochastic(model: nn.Module, enabled: bool) -> int:
    """Switch the masks of every Concrete Dropout layer on (MC) or off; returns the layer count."""
    layers = concrete_layers(model)
    for layer in layers:
        layer.stochastic = bool(enabled)
    return len(layers)


def dropout_regularization(model: nn.Module) -> torch.Tensor:
    """Sum of the regularisers of all Concrete Dropout layers (0 if there are none)."""
    layers = concrete_layers(model)
    if not layers:
        return torch.zeros((), device=next(model.parameters()).device)
    return torch.stack([layer.regularization() for layer in layers]).sum()


def reset_dropout_rates(model: nn.Module, init_min: float, init_max: float) -> None:
    """Re-draw every layer's rate uniformly in logit space between ``init_min`` and ``init_max``.

    For fine-tuning from a deterministic pre-training whose (untrained) rates came from
    another range.
    """
    if not 0.0 < init_min <= init_max < 1.0:
        raise ValueError(f"init_min/init_max: expected 0 < min <= max < 1, got {init_min}, {init_max}")
    with torch.no_grad():
        for layer in concrete_layers(model):
            layer.p_logit.uniform_(_logit(init_min), _logit(init_max))


def dropout_rates(model: nn.Module) -> list[float]:
    """Current rate ``p`` of each Concrete Dropout layer."""
    return [float(layer.p.item()) for layer in concrete_layers(model)]
