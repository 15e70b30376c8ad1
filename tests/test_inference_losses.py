"""Loss terms against hand computations."""

from __future__ import annotations

import math

import pytest
import torch

from gearscan.inference.losses import LossConfig, PhaseLoss, gaussian_nll, weighted_mse


def _pred(mean_m, mean_d, var_m, var_d, shape=(1, 1, 2, 2)):
    return torch.cat([torch.full(shape, float(v)) for v in (mean_m, mean_d, var_m, var_d)], dim=1)


def test_nll_and_mse_hand_values():
    pred = _pred(0.1, 0.2, 0.04, 0.01)
    target = torch.cat([torch.full((1, 1, 2, 2), 0.3), torch.full((1, 1, 2, 2), 0.2)], dim=1)
    nll_m = 0.5 * 0.2**2 / 0.04 + 0.5 * math.log(0.04)
    nll_d = 0.5 * 0.0 / 0.01 + 0.5 * math.log(0.01)
    assert gaussian_nll(pred, target).item() == pytest.approx((nll_m + nll_d) / 2, rel=1e-5)
    assert weighted_mse(pred, target).item() == pytest.approx(0.2**2 / 2, rel=1e-5)
    out = PhaseLoss(LossConfig(alpha=0.5, mse_weight=3.0))(pred, target)
    assert out["total"].item() == pytest.approx(0.5 * (nll_m + nll_d) / 2 + 3.0 * 0.02, rel=1e-5)


def test_variance_optimum_is_squared_error_for_any_alpha():
    """The variance gradient vanishes at var = r^2 whatever alpha is (calibration-preserving reading)."""
    target = torch.zeros(1, 2, 1, 1)
    for alpha in (1e-4, 1.0):
        var = torch.tensor([0.09], requires_grad=True)
        pred = torch.cat(
            [torch.full((1, 2, 1, 1), 0.3), var.view(1, 1, 1, 1).expand(1, 2, 1, 1)], dim=1
        )
        PhaseLoss(LossConfig(alpha=alpha))(pred, target)["total"].backward()
        assert abs(var.grad.item()) < 1e-6


def test_mask_excludes_pixels():
    pred = _pred(0.0, 0.0, 1.0, 1.0)
    target = torch.zeros(1, 2, 2, 2)
    target[0, :, 0, 0] = 10.0  # a bad pixel
    mask = torch.ones(1, 2, 2, dtype=torch.bool)
    mask[0, 0, 0] = False
    assert weighted_mse(pred, target, mask).item() == pytest.approx(0.0)
    assert weighted_mse(pred, target).item() > 1.0


def test_modulation_weighting_approximates_phase_error():
    """1/m^2 weights make an M/D error on a dim pixel count like the same phase error on a bright one."""
    target = torch.zeros(1, 2, 1, 2)
    target[0, 1, 0, 0], target[0, 1, 0, 1] = 0.1, 0.8  # modulation 0.1 and 0.8, phase 0
    pred = torch.zeros(1, 4, 1, 2)
    pred[0, 1] = target[0, 1]
    pred[0, 0, 0, 0], pred[0, 0, 0, 1] = 0.1 * 0.01, 0.8 * 0.01  # same 0.01 rad phase error
    pred[:, 2:] = 1.0
    mask_dim = torch.tensor([[[True, False]]])
    mask_bright = torch.tensor([[[False, True]]])
    both = torch.ones(1, 1, 2, dtype=torch.bool)
    full = weighted_mse(pred, target, both, weighting="modulation").item()
    # each pixel contributes equally under 1/m^2 weighting
    w = torch.tensor([1 / 0.1**2, 1 / 0.8**2])
    w = w / w.mean()
    expected = ((w * torch.tensor([(0.1 * 0.01) ** 2, (0.8 * 0.01) ** 2])).sum() / 4).item()
    assert full == pytest.approx(expected, rel=1e-4)
    assert (w[0] * (0.1 * 0.01) ** 2).item() == pytest.approx(
        (w[1] * (0.8 * 0.01) ** 2).item(), rel=1e-4
    )
    assert (
        weighted_mse(pred, target, mask_dim).item() < weighted_mse(pred, target, mask_bright).item()
    )


def test_shape_errors_name_the_argument():
    with pytest.raises(ValueError, match=r"pred: expected \(B, 4, H, W\)"):
        gaussian_nll(torch.zeros(1, 2, 3, 3), torch.zeros(1, 2, 3, 3))
    with pytest.raises(ValueError, match="mask: expected"):
        weighted_mse(
            torch.zeros(1, 4, 3, 3), torch.zeros(1, 2, 3, 3), torch.ones(1, 2, 2, dtype=torch.bool)
        )
    with pytest.raises(ValueError, match="mse_weighting"):
        LossConfig(mse_weighting="phase")


def test_outside_weight_teaches_the_pixels_outside_the_mask():
    """Outside the truth mask the 18-step label (low modulation in shadow) is learnt with ``outside_weight``:
    a prediction right inside the mask but inventing fringes outside it costs more, and only then; 0 keeps the
    loss of every shipped model bit for bit."""
    import torch

    from gearscan.inference.losses import LossConfig, PhaseLoss

    torch.manual_seed(0)
    target = torch.zeros(1, 2, 8, 8)
    target[:, :, :, :4] = 0.4  # lit half with fringes, dark half with none
    mask = torch.zeros(1, 8, 8, dtype=torch.bool)
    mask[:, :, :4] = True
    pred = torch.cat([target.clone(), torch.full((1, 2, 8, 8), 0.01)], 1)  # means, variances
    pred[:, :2, :, 4:] = 0.4  # invented fringes in the dark half
    pred.requires_grad_(True)
    plain, taught = PhaseLoss(LossConfig()), PhaseLoss(LossConfig(outside_weight=0.1))
    a, b = plain(pred, target, mask), taught(pred, target, mask)
    assert "outside" not in a and float(b["outside"]) == pytest.approx(0.4**2, rel=1e-5)
    assert float(b["total"].detach()) == pytest.approx(float(a["total"].detach()) + 0.1 * 0.4**2, rel=1e-5)
    b["total"].backward()
    assert pred.grad[:, :2, :, 4:].abs().min() > 0  # the outside means are pulled toward the label
    assert float(taught(pred, target, None)["total"].detach()) == pytest.approx(float(plain(pred, target, None)["total"].detach()))
    with pytest.raises(ValueError, match="outside_weight"):
        LossConfig(outside_weight=-1.0)
