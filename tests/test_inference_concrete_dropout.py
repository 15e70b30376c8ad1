"""Concrete Dropout: regulariser by hand, modes, mask shape, learned rates move."""

from __future__ import annotations

import math

import pytest
import torch

from gearscan.inference.concrete_dropout import (
    ConcreteDropout2d,
    dropout_rates,
    dropout_regularization,
    set_stochastic,
)
from gearscan.inference.losses import PhaseLoss
from gearscan.inference.models import build_model

torch.set_num_threads(1)


def test_regularizer_matches_hand_computation():
    torch.manual_seed(0)
    layer = ConcreteDropout2d(3, 2, weight_reg=1e-2, dropout_reg=1e-1)
    with torch.no_grad():
        layer.conv.weight.fill_(0.5)  # 2*3*3*3 = 54 weights
        layer.conv.bias.fill_(-1.0)  # 2 biases
        layer.p_logit.fill_(math.log(0.25 / 0.75))  # p = 0.25
    p = 0.25
    sum_w2 = 54 * 0.25 + 2 * 1.0
    expected = 1e-2 * sum_w2 / (1 - p) + 1e-1 * 3 * (p * math.log(p) + (1 - p) * math.log(1 - p))
    assert layer.regularization().item() == pytest.approx(expected, rel=1e-6)


def test_elementwise_input_dim_is_chw():
    layer = ConcreteDropout2d(2, weight_reg=0.0, dropout_reg=1.0, channelwise=False)
    with torch.no_grad():
        layer.p_logit.fill_(0.0)  # p = 0.5
    layer(torch.rand(1, 2, 4, 5))
    assert layer.regularization().item() == pytest.approx(2 * 4 * 5 * math.log(0.5), rel=1e-6)


def test_deterministic_mode_is_scaled_plain_conv():
    layer = ConcreteDropout2d(4, 6)
    x = torch.rand(2, 4, 8, 8)
    torch.testing.assert_close(layer(x), layer.conv(x * layer.keep_scale()))


@pytest.mark.parametrize("temperature", [0.1, 0.5, 2 / 3])
def test_deterministic_mode_is_expectation_of_stochastic(temperature):
    """Mean of many stochastic passes of the layer equals its deterministic pass."""
    torch.manual_seed(0)
    layer = ConcreteDropout2d(64, init_min=0.3, init_max=0.3, temperature=temperature)
    with torch.no_grad():
        kept = layer.drop(
            torch.ones(4000, 64, 1, 1)
        )  # the conv is linear: comparing its input suffices
    # SE of the mean of 256000 draws is < 0.002
    assert kept.mean().item() == pytest.approx(layer.keep_scale().item(), abs=5e-3)
    assert 0.28 < layer.p.item() < 0.32


def test_channelwise_mask_is_constant_over_the_image():
    torch.manual_seed(0)
    layer = ConcreteDropout2d(64, init_min=0.3, init_max=0.3)
    dropped = layer.drop(torch.ones(8, 64, 5, 7))
    assert torch.allclose(dropped, dropped[..., :1, :1].expand_as(dropped))
    assert not torch.allclose(dropped[:, :1], dropped[:, 1:2])


def test_initial_rates_in_range_and_temperature_defaults():
    m = build_model("cd-dcu-net", width=4)
    rates = dropout_rates(m)
    assert len(rates) == 9 and all(0.1 <= p <= 0.4 for p in rates)
    assert ConcreteDropout2d(4).temperature == pytest.approx(2 / 3)
    assert ConcreteDropout2d(4, channelwise=False).temperature == pytest.approx(0.1)
    assert ConcreteDropout2d(4, temperature=0.5).temperature == 0.5
    with pytest.raises(ValueError, match="init_min/init_max"):
        ConcreteDropout2d(4, init_min=0.5, init_max=0.2)


def test_stochastic_switch_changes_outputs_only_when_on():
    torch.manual_seed(0)
    m = build_model("cd-dcu-net", width=4).eval()
    x = torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        a, b = m(x), m(x)
        assert torch.equal(a, b)
        assert set_stochastic(m, True) == 9
        c, d = m(x), m(x)
    assert not torch.allclose(c, d)
    set_stochastic(m, False)


def test_rates_move_during_training():
    """Stage-2 style training (masks + regulariser) moves every learned rate."""
    torch.manual_seed(0)
    m = build_model("cd-dcu-net", width=4).train()
    set_stochastic(m, True)
    before = dropout_rates(m)
    opt = torch.optim.Adam(m.parameters(), lr=1e-2)
    loss_fn = PhaseLoss()
    x = torch.rand(4, 3, 32, 32)
    target = torch.rand(4, 2, 32, 32) - 0.5
    for _ in range(15):
        out = loss_fn(m(x), target, None, m)
        opt.zero_grad()
        out["total"].backward()
        opt.step()
    after = dropout_rates(m)
    moved = [abs(a - b) for a, b in zip(after, before, strict=True)]
    assert min(moved) > 1e-3, f"rates did not move: {before} -> {after}"
    assert dropout_regularization(m).requires_grad
