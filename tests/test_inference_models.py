"""Shape, any-size, gradient and save/load checks shared by every phase network (smp-style base tester)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gearscan.core.phase import three_step
from gearscan.inference.blocks import DoubleConv
from gearscan.inference.concrete_dropout import ConcreteDropout2d, concrete_layers
from gearscan.inference.model_io import load_model, save_model
from gearscan.inference.models import (
    MODEL_NAMES,
    VAR_FLOOR,
    ModelConfig,
    build_model,
    classical_md,
    pad_to_multiple,
)

torch.set_num_threads(1)
WIDTH = 4


class BaseModelTester:
    """Checks every model must pass; subclasses set ``name`` and add their specifics."""

    name: str = ""

    def model(self, **kw) -> torch.nn.Module:
        torch.manual_seed(0)
        return build_model(self.name, width=WIDTH, **kw).eval()

    @pytest.mark.parametrize("hw", [(32, 32), (37, 50), (16, 23), (9, 7), (64, 48)])
    def test_any_size_shape(self, hw):
        x = torch.rand(2, 3, *hw)
        with torch.no_grad():
            y = self.model()(x)
        assert y.shape == (2, 4, *hw)
        assert y.dtype == torch.float32
        assert torch.all(y[:, 2:] >= VAR_FLOOR), "variances must be softplus + 1e-3"
        assert torch.isfinite(y).all()

    def test_forward_backward(self):
        m = self.model().train()
        y = m(torch.rand(2, 3, 32, 32))
        y.sum().backward()
        grads = [p.grad for p in m.parameters() if p.requires_grad and p.grad is not None]
        assert len(grads) > 0 and all(torch.isfinite(g).all() for g in grads)

    def test_crop_is_consistent_with_padding(self):
        """A size that needs no padding gives the same output as the core applied directly."""
        m = self.model()
        x = torch.rand(1, 3, 32, 48)
        with torch.no_grad():
            raw = m.core(x)
            y = m(x)
        assert torch.allclose(y[:, :2], raw[:, :2], atol=1e-6)

    def test_wrong_channels_message(self):
        with pytest.raises(
            ValueError, match=r"expected input \(B, 3, H, W\), got \(1, 2, 16, 16\)"
        ):
            self.model()(torch.rand(1, 2, 16, 16))

    def test_save_load_roundtrip(self, tmp_path):
        m = self.model()
        x = torch.rand(1, 3, 20, 24)
        path = save_model(m, tmp_path / "m.safetensors", var_scale=2.5)
        loaded, meta = load_model(path)
        assert meta["var_scale"] == 2.5 and meta["model"]["name"] == self.name
        with torch.no_grad():
            assert torch.equal(m(x), loaded(x))

    def test_extra_channels_and_classical_options(self):
        m = self.model(in_channels=4, classical_input=True, residual=True)
        with torch.no_grad():
            y = m(torch.rand(1, 4, 24, 24))
        assert y.shape == (1, 4, 24, 24)


class TestCDDCUNet(BaseModelTester):
    name = "cd-dcu-net"

    def test_has_nine_concrete_dropout_layers_with_paper_channels(self):
        m = build_model("cd-dcu-net", width=64)
        chans = [layer.conv.in_channels for layer in concrete_layers(m)]
        # after stem + 4 down stages, then 4 up stages (paper §2.2)
        assert chans == [64, 128, 256, 512, 1024, 512, 256, 128, 64]
        assert all(
            isinstance(layer, ConcreteDropout2d) and layer.conv.kernel_size == (3, 3)
            for layer in concrete_layers(m)
        )

    def test_dual_3x3_head_without_norm_or_activation(self):
        head = self.model().head
        assert [type(h) for h in head] == [torch.nn.Conv2d, torch.nn.Conv2d]
        assert head[0].kernel_size == (3, 3) and head[0].out_channels == WIDTH
        assert head[1].kernel_size == (3, 3) and head[1].out_channels == 4

    def test_paper_width_parameter_count(self):
        n = sum(p.numel() for p in build_model("cd-dcu-net", width=64).parameters())
        assert 40e6 < n < 55e6  # PLATFORM.md: 46.8 M

    def test_residual_starts_from_classical(self):
        """With the head zeroed, a residual model outputs exactly the three-step M, D."""
        m = self.model(residual=True)
        for p in m.head.parameters():
            torch.nn.init.zeros_(p)
        rng = np.random.default_rng(0)
        frames = rng.integers(0, 256, size=(3, 21, 30)).astype(np.uint8)
        _, m_ref, d_ref = three_step(frames, 255)
        with torch.no_grad():
            y = m(torch.from_numpy(frames.astype(np.float32) / 255)[None])
        np.testing.assert_allclose(y[0, 0].numpy(), m_ref, atol=1e-5)
        np.testing.assert_allclose(y[0, 1].numpy(), d_ref, atol=1e-5)
        np.testing.assert_allclose(y[0, 2:].numpy(), math.log(2) + VAR_FLOOR, rtol=1e-6)


class TestUNet(BaseModelTester):
    name = "unet"

    def test_1x1_head_and_no_dropout(self):
        m = self.model()
        assert isinstance(m.head, torch.nn.Conv2d) and m.head.kernel_size == (1, 1)
        assert concrete_layers(m) == []


class TestTSUNet(BaseModelTester):
    name = "ts-unet"

    def test_three_streams_one_frame_each(self):
        m = self.model()
        assert len(m.streams) == 3
        assert all(s.stem[0].in_channels == 1 for s in m.streams)
        assert isinstance(m.head, torch.nn.Conv2d) and m.head.kernel_size == (3, 3)


class TestDRUNet(BaseModelTester):
    name = "dr-unet"

    def test_residual_blocks(self):
        m = self.model()
        assert not any(isinstance(mod, DoubleConv) for mod in m.modules())
        assert isinstance(m.head, torch.nn.Conv2d) and m.head.kernel_size == (1, 1)


def test_classical_md_matches_recon():
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 4096, size=(3, 8, 9)).astype(np.uint16)
    _, m_ref, d_ref = three_step(frames, 4095)
    md = classical_md(torch.from_numpy(frames.astype(np.float32) / 4095)[None])[0].numpy()
    np.testing.assert_allclose(md[0], m_ref, atol=1e-5)
    np.testing.assert_allclose(md[1], d_ref, atol=1e-5)


@pytest.mark.parametrize(
    "hw,expected", [((16, 16), (16, 16)), ((17, 33), (32, 48)), ((5, 3), (16, 16))]
)
def test_pad_to_multiple(hw, expected):
    x = torch.arange(hw[0] * hw[1], dtype=torch.float32).reshape(1, 1, *hw)
    y, (left, right, top, bottom) = pad_to_multiple(x)
    assert tuple(y.shape[-2:]) == expected
    assert torch.equal(y[..., top : top + hw[0], left : left + hw[1]], x)


def test_config_rejects_unknown_name_and_keys():
    with pytest.raises(ValueError, match="model name: expected one of"):
        ModelConfig(name="resnet")
    with pytest.raises(ValueError, match=r"unknown model config keys \['depth'\]"):
        ModelConfig.from_json({"name": "unet", "depth": 5})
    assert set(MODEL_NAMES) == {"cd-dcu-net", "unet", "ts-unet", "dr-unet"}


def test_motion_channels_and_zero_widened_weights_compute_the_same_as_before():
    """Widening a trained net for the encoder's motion channels starts exactly where it was."""
    from gearscan.inference.model_io import load_into, widen_inputs
    from gearscan.inference.models import motion_channels

    maps = motion_channels(np.radians([10.0, 10.1, 11.7]), 4, 5)
    assert maps.shape == (2, 4, 5) and maps.dtype == np.float32
    np.testing.assert_allclose(maps[:, 0, 0], [0.1, 1.7], rtol=1e-5)
    np.testing.assert_allclose(motion_channels(np.radians([0.0, -0.6, -1.2]), 1, 1)[:, 0, 0], [0.6, 1.2], rtol=1e-5)
    with pytest.raises(ValueError, match="3 finite frame angles"):
        motion_channels([0.0, 1.0], 2, 2)
    with pytest.raises(ValueError, match="motion_input needs >= 5"):
        ModelConfig(motion_input=True)

    torch.manual_seed(0)
    old = build_model("cd-dcu-net", width=WIDTH, classical_input=True, residual=True).eval()
    new = build_model("cd-dcu-net", width=WIDTH, classical_input=True, residual=True,
                      in_channels=5, motion_input=True).eval()
    state = dict(old.state_dict())
    assert widen_inputs(state, new) == ["encoder.stem.0.weight"]
    load_into(new, state, "test")
    frames = torch.rand(1, 3, 32, 32)
    motion = torch.from_numpy(motion_channels(np.radians([0.0, 0.6, 1.2]), 32, 32))[None]
    with torch.no_grad():
        torch.testing.assert_close(new(torch.cat([frames, motion], 1)), old(frames))


def test_prior_channels_and_zero_widened_weights_compute_the_same_as_before():
    """The twin's prediction as input: still means zero, the wrap is continuous, unknown pixels are
    zero; widening a trained net for it starts exactly where the net was."""
    from gearscan.inference.model_io import load_into, widen_inputs
    from gearscan.inference.models import PRIOR_CHANNELS, prior_channels

    known = np.ones((2, 3), bool)
    known[0, 0] = False
    still = prior_channels(np.zeros((2, 2, 3)), np.ones((2, 2, 3)), known)
    assert still.shape == (PRIOR_CHANNELS, 2, 3) and still.dtype == np.float32
    assert np.abs(still[:-1]).max() == 0 and still[-1].sum() == 5 and still[:, 0, 0].max() == 0
    near_pi = prior_channels(np.full((2, 1, 2), [np.pi - 1e-3, -np.pi + 1e-3]), np.ones((2, 1, 2)), np.ones((1, 2), bool))
    np.testing.assert_allclose(near_pi[:4, 0, 0], near_pi[:4, 0, 1], atol=3e-3)  # no jump across the wrap
    ratio = prior_channels(np.zeros((2, 1, 1)), np.array([2.0, 100.0]).reshape(2, 1, 1), np.ones((1, 1), bool))
    np.testing.assert_allclose(ratio[4:6, 0, 0], [np.log(2.0), 1.4], rtol=1e-6)  # clipped far from one surface
    with pytest.raises(ValueError, match="prior maps: expected"):
        prior_channels(np.zeros((3, 2, 2)), np.ones((3, 2, 2)), np.ones((2, 2), bool))
    with pytest.raises(ValueError, match="prior_input needs >= 10"):
        ModelConfig(prior_input=True)

    torch.manual_seed(0)
    old = build_model("cd-dcu-net", width=WIDTH, classical_input=True, residual=True).eval()
    new = build_model("cd-dcu-net", width=WIDTH, classical_input=True, residual=True,
                      in_channels=3 + PRIOR_CHANNELS, prior_input=True).eval()
    state = dict(old.state_dict())
    assert widen_inputs(state, new) == ["encoder.stem.0.weight"]
    load_into(new, state, "test")
    frames = torch.rand(1, 3, 32, 32)
    prior = torch.rand(1, PRIOR_CHANNELS, 32, 32)
    with torch.no_grad():
        torch.testing.assert_close(new(torch.cat([frames, prior], 1)), old(frames))
