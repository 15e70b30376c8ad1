"""Training loss: temperature-scaled Gaussian NLL + weighted MSE + Concrete Dropout regulariser.

The paper's eqs. 10 and 11 disagree on where the temperature ``alpha`` goes: eq. 10 puts it
on the variance inside the exponent (``sigma^(2 alpha)``), eq. 11 on the log-variance term.
Taken literally with ``alpha = 1e-4`` both are degenerate: eq. 10 makes the squared error
independent of sigma while ``log sigma`` pulls sigma to its floor, and eq. 11's optimum is
``sigma^2 = r^2 / alpha``, i.e. sigma 100x the actual error. Neither can give the calibrated
reliability diagrams of §3.6.

Reading implemented here (the "temperature" scales the whole likelihood term against the
MSE term, which §3.5 describes as "introducing a temperature constant into the normal
distribution loss and increasing the weight of the MSE term"):

``L = alpha * mean_i[ (y_i - mu_i)^2 / (2 s_i) + 0.5 log s_i ] + mse_weight * mean_i[ w_i (y_i - mu_i)^2 ] + KL``

with ``s_i`` the predicted variance, the means over valid pixels and both channels (M, D),
and ``KL`` the sum of the Concrete Dropout regularisers (eq. 16). The minimiser in ``s`` is
still ``s = E[(y - mu)^2]`` for any ``alpha > 0`` (the variance head sees only the NLL term,
so it stays calibrated), while the means are driven mostly by the MSE term, which is what
§3.5 reports as the 10-20 % accuracy gain. ``alpha = 1`` and ``mse_weight = 0`` give the plain
heteroscedastic NLL of Kendall & Gal (2017). ``detach_mean=True`` stops the NLL gradient to the
means altogether (they then learn from the MSE alone).

``w_i``: ``mse_weighting="uniform"`` gives 1; ``"modulation"`` gives ``1 / max(m_i, floor)^2``
(normalised to mean 1 over valid pixels) with ``m_i = hypot(M_i, D_i)`` of the label, so the MSE
on (M, D) approximates the squared *phase* error ``|dMD|^2 / m^2``, and weakly modulated pixels
are not under-weighted.

``outside_weight`` adds ``outside_weight * mean_j[ (y_j - mu_j)^2 ]`` over the pixels *outside* the mask (the
18-step label there: low modulation in shadow, the blurred measurement at edges and creases). Without it the
network is never told what to output where the truth mask ends, and invents phase and modulation there
(session 32, ``benchmarks/network_support_rule.md``). 0 (the default): the loss of every model so far.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from gearscan.inference.concrete_dropout import dropout_regularization


@dataclass
class LossConfig:
    alpha: float = 1e-4
    mse_weight: float = 1.0
    mse_weighting: str = "uniform"  # "uniform" or "modulation"
    modulation_floor: float = 0.05
    detach_mean: bool = False
    regularization: bool = True
    outside_weight: float = 0.0

    def __post_init__(self) -> None:
        if not self.outside_weight >= 0:
            raise ValueError(f"outside_weight: expected >= 0, got {self.outside_weight}")
        if self.alpha < 0 or self.mse_weight < 0:
            raise ValueError(
                f"alpha and mse_weight: expected >= 0, got {self.alpha}, {self.mse_weight}"
            )
        if self.mse_weighting not in ("uniform", "modulation"):
            raise ValueError(
                f"mse_weighting: expected 'uniform' or 'modulation', got {self.mse_weighting!r}"
            )
        if self.modulation_floor <= 0:
            raise ValueError(f"modulation_floor: expected > 0, got {self.modulation_floor}")

    def to_json(self) -> dict:
        return asdict(self)


def _check(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    if pred.ndim != 4 or pred.shape[1] != 4:
        raise ValueError(f"pred: expected (B, 4, H, W), got {tuple(pred.shape)}")
    if target.shape != (pred.shape[0], 2, *pred.shape[2:]):
        raise ValueError(
            f"target: expected {(pred.shape[0], 2, *pred.shape[2:])}, got {tuple(target.shape)}"
        )
    if mask is None:
        return torch.ones((pred.shape[0], *pred.shape[2:]), dtype=torch.bool, device=pred.device)
    if mask.shape != (pred.shape[0], *pred.shape[2:]):
        raise ValueError(
            f"mask: expected {(pred.shape[0], *pred.shape[2:])}, got {tuple(mask.shape)}"
        )
    return mask.bool()


def gaussian_nll(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    detach_mean: bool = False,
) -> torch.Tensor:
    """Mean Gaussian NLL ``r^2/(2s) + log(s)/2`` over valid pixels and both channels (no constant)."""
    valid = _check(pred, target, mask).unsqueeze(1).float()
    mean, var = pred[:, :2], pred[:, 2:]
    if detach_mean:
        mean = mean.detach()
    per = 0.5 * (target - mean) ** 2 / var + 0.5 * torch.log(var)
    return (per * valid).sum() / (2 * valid.sum()).clamp_min(1)


def weighted_mse(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    weighting: str = "uniform",
    floor: float = 0.05,
) -> torch.Tensor:
    """Mean squared error of the means over valid pixels and both channels, optionally 1/m^2 weighted."""
    valid = _check(pred, target, mask).float()
    sq = ((target - pred[:, :2]) ** 2).sum(1)  # (B, H, W), summed over M and D
    if weighting == "modulation":
        w = 1.0 / torch.hypot(target[:, 0], target[:, 1]).clamp_min(floor) ** 2
        w = w * valid
        w = w / (w.sum() / valid.sum().clamp_min(1)).clamp_min(1e-12)
    else:
        w = valid
    return (sq * w).sum() / (2 * valid.sum()).clamp_min(1)


class PhaseLoss(nn.Module):
    """The training objective; ``forward`` returns a dict of scalar tensors (``total`` to backprop)."""

    def __init__(self, config: LossConfig | None = None) -> None:
        super().__init__()
        self.config = config or LossConfig()

    def forward(
        self,
        pred: torch.Tensor,
        target: torch.Tensor,
        mask: torch.Tensor | None = None,
        model: nn.Module | None = None,
        *,
        include_regularization: bool | None = None,
    ) -> dict[str, torch.Tensor]:
        c = self.config
        pred = pred.float()
        target = target.float()
        nll = gaussian_nll(pred, target, mask, detach_mean=c.detach_mean)
        mse = weighted_mse(pred, target, mask, weighting=c.mse_weighting, floor=c.modulation_floor)
        use_reg = c.regularization if include_regularization is None else include_regularization
        reg = (
            dropout_regularization(model)
            if (use_reg and model is not None)
            else torch.zeros((), device=pred.device)
        )
        total = c.alpha * nll + c.mse_weight * mse + reg
        out = {"nll": nll.detach(), "mse": mse.detach(), "reg": reg.detach()}
        if c.outside_weight > 0 and mask is not None:
            outside = weighted_mse(pred, target, ~_check(pred, target, mask))
            total = total + c.outside_weight * outside
            out["outside"] = outside.detach()
        return {"total": total, **out}
