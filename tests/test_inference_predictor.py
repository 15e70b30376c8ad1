"""Predictor loading (clear errors for bad files), input conversion, and the predict CLI function."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from gearscan.core.types import Burst, Frame
from gearscan.inference.commands import predict
from gearscan.inference.model_io import ModelFileError, load_model, save_model
from gearscan.inference.models import build_model
from gearscan.inference.predictor import (
    DEFAULT_MODEL,
    Predictor,
    auto_mc_chunk,
    frames_to_tensor,
    resolve_precision,
)

torch.set_num_threads(1)

# Tolerances between compute paths (never exact equality across paths: oneDNN picks kernels by
# ISA, layout and thread count, so AVX2, AVX-512 and AMX hosts round differently).
# fp32: the Predictor folds BatchNorm into the convs and runs channels_last, a different
# summation order than the bare model; ~20 conv layers of O(1) activations keep the
# difference near 1e-6 relative, so 2e-5 absolute on M, D (|M|, |D| <= 1) leaves 10x room.
FP32_ATOL = 2e-5
# bf16 autocast: 8 mantissa bits (eps 2^-8 = 3.9e-3) per rounding; measured up to 2.3e-3 on M, D
# against the fp32 path on an AVX-512-BF16 host. Phase derived from them: atan2 amplifies by
# 1/|(M, D)|, so phases are compared where the modulation is not tiny.
BF16_ATOL = 2e-2


def _close_phase(a, b, M, D, atol):
    """Wrap-aware phase comparison where the modulation |(M, D)| > 0.05 (phase is defined there)."""
    ok = np.hypot(M, D) > 0.05
    err = np.angle(np.exp(1j * (a - b)))[ok]
    assert ok.mean() > 0.5 and np.max(np.abs(err)) <= atol / 0.05, np.max(np.abs(err))


@pytest.fixture
def saved(tmp_path):
    torch.manual_seed(0)
    model = build_model("cd-dcu-net", width=4).eval()
    return model, save_model(model, tmp_path / "net.safetensors", var_scale=1.0)


def _frames(dtype=np.uint8, hw=(37, 45), seed=0):
    hi = 255 if dtype == np.uint8 else 4095
    return np.random.default_rng(seed).integers(0, hi + 1, size=(3, *hw)).astype(dtype)


def test_corrupt_weight_file_error_names_file(saved, tmp_path):
    _, path = saved
    path.write_bytes(b"\x00garbage, not safetensors" * 3)
    with pytest.raises(ModelFileError, match=r"net\.safetensors: not a readable safetensors file"):
        load_model(path)


def test_truncated_weight_file(saved):
    _, path = saved
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ModelFileError, match="net.safetensors"):
        Predictor.load(path)


def test_mismatched_weights_error_lists_shapes(saved):
    _, path = saved
    cfg = json.loads(path.with_suffix(".json").read_text())
    cfg["model"]["width"] = 8  # config says w=8, file holds w=4
    path.with_suffix(".json").write_text(json.dumps(cfg))
    with pytest.raises(
        ModelFileError,
        match=r"weights do not match the network: .*shape mismatches.*file \(4, 3, 3, 3\) vs model \(8, 3, 3, 3\)",
    ):
        load_model(path)


def test_mismatched_architecture_lists_keys(saved):
    _, path = saved
    cfg = json.loads(path.with_suffix(".json").read_text())
    cfg["model"]["name"] = "unet"
    cfg["model"]["dropout"] = False
    path.with_suffix(".json").write_text(json.dumps(cfg))
    with pytest.raises(
        ModelFileError,
        match=r"net\.safetensors: weights do not match the network: .*unexpected keys",
    ):
        load_model(path)


def test_missing_and_bad_config(saved):
    _, path = saved
    path.with_suffix(".json").write_text("{not json")
    with pytest.raises(ModelFileError, match=r"net\.json: invalid JSON"):
        load_model(path)
    path.with_suffix(".json").unlink()
    with pytest.raises(ModelFileError, match=r"model config not found: .*net\.json"):
        load_model(path)


def test_missing_default_model_names_path(monkeypatch, tmp_path):
    missing = tmp_path / "weights" / "default.safetensors"
    monkeypatch.setattr("gearscan.inference.predictor.DEFAULT_MODEL", missing)
    with pytest.raises(ModelFileError, match="default.safetensors"):
        Predictor.load(None)
    assert DEFAULT_MODEL.name == "default.safetensors" and DEFAULT_MODEL.parent.name == "weights"


def test_frames_to_tensor_scales():
    f8 = np.array([[[0, 255]]] * 3, dtype=np.uint8)
    assert frames_to_tensor(f8).max().item() == 1.0
    f16 = np.full((3, 2, 2), 4095, dtype=np.uint16)
    assert frames_to_tensor(f16, full_scale=4095).max().item() == 1.0
    with pytest.raises(ValueError, match=r"frames: expected \(3, H, W\), got shape \(2, 4, 4\)"):
        frames_to_tensor(np.zeros((2, 4, 4), np.uint8))
    with pytest.raises(ValueError, match="expected uint8 or uint16"):
        frames_to_tensor(np.zeros((3, 4, 4), np.float32))


def test_predict_matches_model_and_sizes(saved):
    model, path = saved
    pred = Predictor.load(path, precision="fp32")  # the bare model below runs fp32
    frames = _frames()
    r = pred.predict(frames)
    with torch.no_grad():
        ref = model(torch.from_numpy(frames.astype(np.float32) / 255)[None])[0].numpy()
    assert r.phase.shape == frames.shape[1:] and r.mode == "deterministic"
    np.testing.assert_allclose(r.M, ref[0], atol=FP32_ATOL)
    np.testing.assert_allclose(r.D, ref[1], atol=FP32_ATOL)
    _close_phase(r.phase, np.arctan2(ref[0], ref[1]), ref[0], ref[1], FP32_ATOL)
    assert np.all(r.sigma_model == 0) and np.all(r.sigma_data > 0)
    mc = pred.predict(frames, mc=4)
    assert mc.mode == "mc4" and mc.sigma_model.mean() > 0
    np.testing.assert_allclose(mc.sigma_total, np.hypot(mc.sigma_model, mc.sigma_data), rtol=1e-5)


def test_bf16_close_to_fp32(saved):
    _, path = saved
    frames = _frames(np.uint16, (32, 40))
    a = Predictor.load(path).predict(frames, full_scale=4095)
    b = Predictor.load(path, precision="bf16").predict(frames, full_scale=4095)
    mod = np.hypot(a.M, a.D)
    ok = mod > 0.05
    err = np.angle(np.exp(1j * (a.phase - b.phase)))[ok]
    assert np.sqrt(np.mean(err**2)) < 0.05


def test_predict_burst_uses_bit_depth(saved):
    _, path = saved
    frames = _frames(np.uint16, (20, 20))
    burst = Burst(
        tuple(Frame(f, i, i, i, bit_depth=12) for i, f in enumerate(frames)),
        (0.1, 0.2, 0.3),
        index=7,
    )
    pred = Predictor.load(path)
    r = pred.predict_burst(burst)
    ref = pred.predict(frames, full_scale=4095)  # same predictor, same path: same numbers
    np.testing.assert_array_equal(r.phase, ref.phase)
    assert not np.array_equal(pred.predict(frames, full_scale=65535).phase, ref.phase)  # 12 bit mattered
    assert r.burst_index == 7 and r.angle == pytest.approx(0.1)


def test_motion_input_model_takes_the_burst_angles(tmp_path):
    torch.manual_seed(0)
    model = build_model("cd-dcu-net", width=4, classical_input=True, residual=True, in_channels=5, motion_input=True)
    path = save_model(model.eval(), tmp_path / "m.safetensors")
    pred = Predictor.load(path, precision="fp32")
    frames = _frames(hw=(20, 24))
    with pytest.raises(ValueError, match="angles: this model takes the turntable's rotation"):
        pred.predict(frames)
    angles = np.radians([5.0, 5.6, 6.2])
    burst = Burst(tuple(Frame(f, i, i, i) for i, f in enumerate(frames)), tuple(angles))
    r = pred.predict_burst(burst)
    np.testing.assert_array_equal(r.phase, pred.predict(frames, angles=angles).phase)
    # the angles matter: a still burst decodes differently from a moving one
    assert not np.array_equal(r.phase, pred.predict(frames, angles=np.radians([5.0, 5.0, 5.0])).phase)
    np.savez(tmp_path / "b.npz", frames=frames, angles=angles)
    predict([tmp_path / "b.npz"], output=tmp_path / "o.npz", mc=0, model=path, precision="fp32")
    with np.load(tmp_path / "o.npz") as z:  # the CLI loads its own copy: a second path
        _close_phase(z["phase"], r.phase, r.M, r.D, FP32_ATOL)


def test_prior_input_model_takes_the_twin_prediction(tmp_path):
    from gearscan.inference.models import PRIOR_CHANNELS, prior_channels

    torch.manual_seed(0)
    model = build_model("cd-dcu-net", width=4, classical_input=True, residual=True,
                        in_channels=3 + PRIOR_CHANNELS, prior_input=True)
    path = save_model(model.eval(), tmp_path / "p.safetensors")
    pred = Predictor.load(path, precision="fp32")
    assert pred.needs_prior and not pred.needs_angles
    frames = _frames(hw=(20, 24))
    with pytest.raises(ValueError, match="prior: this model takes the twin's per-pixel prediction"):
        pred.predict(frames)
    with pytest.raises(ValueError, match=r"expected prior_channels\(\) of shape \(7, 20, 24\), got shape \(7, 20, 20\)"):
        pred.predict(frames, prior=np.zeros((PRIOR_CHANNELS, 20, 20), np.float32))
    known = np.ones((20, 24), bool)
    still = prior_channels(np.zeros((2, 20, 24)), np.ones((2, 20, 24)), known)
    moving = prior_channels(np.full((2, 20, 24), [[[0.4]], [[0.9]]]), np.ones((2, 20, 24)), known)
    assert not np.array_equal(pred.predict(frames, prior=still).phase, pred.predict(frames, prior=moving).phase)
    # a burst through the pipeline path has no prior to give it: a clear error, not a guess
    burst = Burst(tuple(Frame(f, i, i, i) for i, f in enumerate(frames)), (0.0, 0.01, 0.02))
    with pytest.raises(ValueError, match="prior_input"):
        pred.predict_burst(burst)


def test_peer_model_refuses_mc(tmp_path):
    path = save_model(build_model("unet", width=4), tmp_path / "u.safetensors")
    with pytest.raises(ValueError, match="no Concrete Dropout layers"):
        Predictor.load(path).predict(_frames(), mc=3)


def test_predict_cli_npz_roundtrip(saved, tmp_path):
    _, path = saved
    frames = _frames()
    np.savez(tmp_path / "burst.npz", frames=frames)
    out = tmp_path / "out" / "phase.npz"
    predict([tmp_path / "burst.npz"], output=out, mc=0, model=path)  # default precision: auto
    ref = Predictor.load(path).predict(frames)  # auto too: same precision on this host
    atol = BF16_ATOL if resolve_precision("auto", "cpu") == "bf16" else FP32_ATOL
    with np.load(out) as z:
        for key in ("phase", "M", "D", "sigma_model", "sigma_data", "sigma_total"):
            assert z[key].dtype == np.float32 and z[key].shape == frames.shape[1:]
        np.testing.assert_allclose(z["M"], ref.M, atol=atol)
        np.testing.assert_allclose(z["D"], ref.D, atol=atol)
        _close_phase(z["phase"], ref.phase, ref.M, ref.D, atol)
        np.testing.assert_array_equal(z["sigma_model"], 0)
        ok = ref.modulation > 0.05  # sigma ~ 1/modulation: relative agreement where defined
        np.testing.assert_allclose(z["sigma_total"][ok], ref.sigma_total[ok], rtol=20 * atol)
        assert str(z["mode"]) == "deterministic"


def test_auto_precision_follows_the_cpu(monkeypatch):
    import gearscan.inference.predictor as P

    monkeypatch.setattr(P, "cpu_has_fast_bf16", lambda: True)
    monkeypatch.setattr(P, "cpu_has_amx_bf16", lambda: False)  # AVX512-BF16 without AMX
    assert resolve_precision("auto", "cpu") == "bf16"  # inference: measured faster there
    assert resolve_precision("auto", "cpu", training=True) == "fp32"  # a training step: measured slower there
    monkeypatch.setattr(P, "cpu_has_amx_bf16", lambda: True)
    assert resolve_precision("auto", "cpu", training=True) == "bf16"
    monkeypatch.setattr(P, "cpu_has_fast_bf16", lambda: False)
    monkeypatch.setattr(P, "cpu_has_amx_bf16", lambda: False)
    assert resolve_precision("auto", "cpu") == "fp32" and resolve_precision("auto", "cpu", training=True) == "fp32"
    assert resolve_precision("auto", "cuda") == "bf16" and resolve_precision("fp32", "cuda") == "fp32"
    assert resolve_precision("auto", "cuda", training=True) == "bf16"
    with pytest.raises(ValueError, match=r"precision: expected one of .*got 'fp8'"):
        resolve_precision("fp8", "cpu")


def test_cpu_bf16_detection_reads_the_flags(monkeypatch, tmp_path):
    import gearscan.inference.predictor as P

    for flags, fast, amx in (("fpu avx2 fma", False, False), ("avx512f avx512_bf16", True, False),
                             ("amx_bf16 amx_tile", True, True)):
        info = tmp_path / "cpuinfo"
        info.write_text(f"processor : 0\nflags : {flags}\nbugs : amx_bf16_not_a_flag\n")
        monkeypatch.setattr(P, "CPUINFO", info)
        assert P.cpu_has_fast_bf16() is fast and P.cpu_has_amx_bf16() is amx


def test_predict_cli_three_images_mc(saved, tmp_path):
    _, path = saved
    frames = _frames(np.uint16, (24, 33))
    files = []
    for i, f in enumerate(frames):
        files.append(tmp_path / f"f{i}.png")
        assert cv2.imwrite(str(files[-1]), f)
    out = tmp_path / "mc.npz"
    predict(files, output=out, mc=3, model=path)
    with np.load(out) as z:
        assert str(z["mode"]) == "mc3" and z["phase"].shape == (24, 33)
        assert z["sigma_model"].mean() > 0


def test_predictor_folds_batchnorm_exactly_and_leaves_the_callers_model_alone():
    """BN with non-trivial statistics folded into the convs gives the same M, D and variances,
    in deterministic and MC mode (same masks), and the model passed in keeps its BN layers."""
    from gearscan.inference.uncertainty import deterministic_moments, mc_moments

    torch.manual_seed(3)
    model = build_model("cd-dcu-net", width=4)
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)
    model.eval()
    n_bn = sum(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())
    pred = Predictor(model, channels_last=False)
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in pred.model.modules()) == 0
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules()) == n_bn
    x = torch.from_numpy(_frames(hw=(32, 48)).astype(np.float32) / 255)[None]
    with torch.no_grad():
        a, b = deterministic_moments(model, x), deterministic_moments(pred.model, x)
        torch.testing.assert_close(b.M, a.M, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(b.data_var_D, a.data_var_D, atol=1e-5, rtol=1e-4)
        torch.manual_seed(7)
        a = mc_moments(model, x, 3, 3)
        torch.manual_seed(7)
        b = mc_moments(pred.model, x, 3, 3)
        torch.testing.assert_close(b.D, a.D, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(b.model_var_M, a.model_var_M, atol=1e-5, rtol=1e-4)


def test_mc_chunk_on_cuda_by_free_memory(monkeypatch):
    """On a GPU all passes go in one batch where half the free memory holds them (measured faster on an H100,
    benchmarks/inference_speed_gpu.md), fewer where it does not, never none."""
    gib = 2**30
    free = {"bytes": 70 * gib, "cached": 0}
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (free["bytes"], 80 * gib))
    monkeypatch.setattr(torch.cuda, "memory_reserved", lambda device=None: free["cached"] + gib)
    monkeypatch.setattr(torch.cuda, "memory_allocated", lambda device=None: gib)
    assert auto_mc_chunk(512, 512, 20, "cuda") == 20 and auto_mc_chunk(1232, 1360, 20, "cuda") == 20
    free["bytes"] = 8 * gib  # 4 GiB for chunks of 1232x1360 x 300 bytes (503 MB a pass): 8 passes
    assert auto_mc_chunk(1232, 1360, 20, "cuda") == 8
    assert auto_mc_chunk(1232, 1360, 20, "cuda", model_width=32) == 2  # 4x the width, 4x the memory a pass
    free["cached"] = 8 * gib  # what torch holds cached but unused counts as free: 8 GiB for chunks, 17 passes
    assert auto_mc_chunk(1232, 1360, 20, "cuda") == 17
    free["bytes"], free["cached"] = gib // 4, 0
    assert auto_mc_chunk(1232, 1360, 20, "cuda") == 1
    assert auto_mc_chunk(512, 512, 20, "cpu") == 2  # the CPU keeps its cache-bound chunks


def test_the_predictor_chunks_by_its_own_device_and_width(saved, monkeypatch):
    """The Predictor asks for its chunk with its device and its network's width."""
    from gearscan.inference import predictor as predictor_module

    seen = []
    real = predictor_module.auto_mc_chunk
    monkeypatch.setattr(predictor_module, "auto_mc_chunk", lambda *a: seen.append(a) or real(*a))
    model, path = saved
    Predictor.load(path).predict(_frames(hw=(32, 40), seed=3), mc=2)
    assert seen == [(32, 40, 2, torch.device("cpu"), model.config.width)]


def test_mc_chunk_by_image_size(saved):
    """Passes per batched forward: 2 at 512x512, 1 from 800x800 up (measured), all of them for
    small images; an explicit chunk is kept, a bad one refused."""
    assert auto_mc_chunk(512, 512, 20) == 2
    assert auto_mc_chunk(800, 800, 20) == 1 and auto_mc_chunk(1232, 1360, 20) == 1
    assert auto_mc_chunk(64, 64, 20) == 20 and auto_mc_chunk(64, 64, 3) == 3
    _, path = saved
    assert Predictor.load(path).mc_chunk is None and Predictor.load(path, mc_chunk=3).mc_chunk == 3
    with pytest.raises(ValueError, match="mc_chunk: expected >= 1 or None"):
        Predictor.load(path, mc_chunk=0)
    frames = _frames(hw=(32, 40), seed=2)
    torch.manual_seed(0)
    auto = Predictor.load(path).predict(frames, mc=4)  # 32x40: the 4 passes in one chunk
    torch.manual_seed(0)
    four = Predictor.load(path, mc_chunk=4).predict(frames, mc=4)
    np.testing.assert_allclose(auto.sigma_model, four.sigma_model, rtol=1e-5, atol=1e-7)


def test_predictor_applies_the_calibration_of_its_mode(saved):
    model, path = saved
    frames = _frames(hw=(32, 40), seed=3)
    plain = Predictor.load(path)
    meta = json.loads(path.with_suffix(".json").read_text())
    meta["sigma_calibration"] = {"deterministic": {"a": 2.0, "b": 1.0}, "mc": {"a": 0.5, "b": 0.8}}
    path.with_suffix(".json").write_text(json.dumps(meta))
    cal = Predictor.load(path)
    np.testing.assert_allclose(cal.predict(frames).sigma_total, 2.0 * plain.predict(frames).sigma_total, rtol=1e-5)
    torch.manual_seed(1)
    ref = plain.predict(frames, mc=3).sigma_total
    torch.manual_seed(1)
    np.testing.assert_allclose(cal.predict(frames, mc=3).sigma_total, 0.5 * ref**0.8, rtol=1e-4)


@pytest.mark.parametrize("entry, match", [
    ({"fast": {"a": 1.0, "b": 1.0}}, r"sigma_calibration: expected an object with keys \['deterministic', 'mc'\]"),
    ({"mc": {"a": 0.0, "b": 1.0}}, r"net\.json: sigma_calibration\.mc: sigma calibration: expected a > 0"),
])
def test_bad_sigma_calibration_in_the_config_is_named(saved, entry, match):
    _, path = saved
    meta = json.loads(path.with_suffix(".json").read_text())
    meta["sigma_calibration"] = entry
    path.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(ModelFileError, match=match):
        Predictor.load(path)


def test_mirrored_fringes_are_decoded_in_the_trained_orientation(saved):
    """Phase decreasing along the columns (a mirrored camera or projector) is mirrored in and out,
    sigma map included."""
    from gearscan.core.phase import three_step
    from gearscan.inference.predictor import fringe_phase_decreases_along_columns
    from gearscan.inference.uncertainty import departure

    _, path = saved
    h, w = 24, 40
    xx = np.arange(w)[None, :] + 0.02 * np.arange(h)[:, None] ** 2
    shifts = (0.0, 2 * np.pi / 3, 4 * np.pi / 3)
    frames = np.stack([127 + 100 * np.cos(2 * np.pi * xx / 11 + d) for d in shifts]).astype(np.uint8)
    mirrored = np.ascontiguousarray(frames[:, :, ::-1])
    assert not fringe_phase_decreases_along_columns(frames_to_tensor(frames))
    assert fringe_phase_decreases_along_columns(frames_to_tensor(mirrored))
    meta = json.loads(path.with_suffix(".json").read_text())
    meta["sigma_calibration"] = {"deterministic": {"a": 0.4, "b": 0.6, "c": 0.3, "d0": 0.01}}
    path.with_suffix(".json").write_text(json.dumps(meta))
    pred = Predictor.load(path)
    a, b = pred.predict(frames), pred.predict(mirrored)
    for key in ("phase", "M", "D", "sigma_total"):
        np.testing.assert_allclose(getattr(b, key)[:, ::-1], getattr(a, key), atol=1e-6)
    # the departure map reads the network's phase against three-step PS's in the same orientation
    raw = Predictor.load(path)
    raw.calibration = {}
    r = raw.predict(frames)
    dep = departure(r.phase, three_step(frames, 255)[0])
    expected = 0.4 * r.sigma_total**0.6 * (dep + 0.01) ** 0.3
    np.testing.assert_allclose(a.sigma_total, expected, rtol=1e-4)
    np.testing.assert_allclose(b.sigma_total[:, ::-1], expected, rtol=1e-4)


def _bent_burst() -> np.ndarray:
    """A still 24x40 burst of 7 px fringes bending down the rows (three-step shifts, uint8)."""
    xx = np.arange(40)[None, :] + 0.02 * np.arange(24)[:, None] ** 2
    return np.stack([127 + 100 * np.cos(2 * np.pi * xx / 7 + d)
                     for d in (0.0, 2 * np.pi / 3, 4 * np.pi / 3)]).astype(np.uint8)


def _with_map(path, cal, frames):
    """Store ``cal`` as the model's deterministic map; the Predictor that reads it, and the raw (unmapped)
    result on ``frames``."""
    meta = json.loads(path.with_suffix(".json").read_text())
    meta["sigma_calibration"] = {"deterministic": cal.to_json()}
    path.with_suffix(".json").write_text(json.dumps(meta))
    pred = Predictor.load(path)
    assert pred.calibration["deterministic"] == cal
    raw = Predictor.load(path)
    raw.calibration = {}
    return pred, raw.predict(frames)


def test_a_stored_additive_map_reads_the_fringe_density_of_the_networks_phase(saved, monkeypatch):
    """An additive sigma map in the model's JSON: the Predictor reports sigma' from the raw sigma, the departure from
    three-step PS and the density of its own phase (mirrored fringes alike); the still-burst gate reads it at zero
    departure."""
    from gearscan.core.phase import three_step
    from gearscan.inference.models import classical_md
    from gearscan.inference.predictor import still_burst_gate
    from gearscan.inference.uncertainty import (
        AdditiveSigmaMap,
        HingeTerm,
        departure,
        fringe_density,
    )

    _, path = saved
    frames = _bent_burst()
    cal = AdditiveSigmaMap(-0.5, (HingeTerm("sigma", 0.7, (-2.0,), (0.2,)), HingeTerm("departure", 0.2),
                                  HingeTerm("density", 0.5, (-1.0,), (-0.3,))))
    pred, r = _with_map(path, cal, frames)
    dep = departure(r.phase, three_step(frames, 255)[0])
    expected = cal(r.sigma_total, dep, fringe_density(r.phase))
    np.testing.assert_allclose(pred.predict(frames).sigma_total, expected, rtol=1e-4)
    mirrored = pred.predict(np.ascontiguousarray(frames[:, :, ::-1]))
    np.testing.assert_allclose(mirrored.sigma_total[:, ::-1], expected, rtol=1e-4)
    # a burst the gate takes: three-step's phase, the map at zero departure
    classical = classical_md(frames_to_tensor(frames).float())[0].numpy()
    # a still_phase that moves three-step's phase (its harmonic removal on non-sinusoidal fringes): the gate must
    # still swap out the departure the map read, the network's against three-step PS of the raw frames
    import gearscan.inference.predictor as predictor_module

    def shifted(m, d):
        p = np.arctan2(m, d) + np.float32(0.2)
        return p, np.hypot(m, d) * np.sin(p), np.hypot(m, d) * np.cos(p)

    monkeypatch.setattr(predictor_module, "still_phase", shifted)
    gated, taken = still_burst_gate(pred.predict(frames), classical, np.inf, cal)
    assert taken and gated.mode == "three-step"
    assert np.abs(departure(gated.phase, three_step(frames, 255)[0])).min() > 0.19  # still_phase moved it
    at_zero = cal(r.sigma_total, np.zeros_like(dep), fringe_density(r.phase))
    np.testing.assert_allclose(gated.sigma_total, at_zero, rtol=1e-4)


def test_a_stored_local_map_reads_the_curvature_and_local_departure(saved, monkeypatch):
    """An additive-local sigma map: the Predictor reads the curvature of its own phase and the 7x7 RMS of its
    departure (mirrored fringes alike); the still-burst gate reads the map at zero departure, its own and the
    local one."""
    from gearscan.core.phase import three_step
    from gearscan.inference.models import classical_md
    from gearscan.inference.predictor import still_burst_gate
    from gearscan.inference.uncertainty import (
        AdditiveSigmaMap,
        HingeTerm,
        departure,
        fringe_density,
        local_departure,
        phase_curvature,
    )

    _, path = saved
    frames = _bent_burst()
    cal = AdditiveSigmaMap(-0.5, (HingeTerm("sigma", 0.7), HingeTerm("departure", 0.2),
                                  HingeTerm("density", 0.5), HingeTerm("curvature", 0.3, (-2.0,), (0.2,)),
                                  HingeTerm("local_departure", 0.4)))
    pred, r = _with_map(path, cal, frames)
    dep = departure(r.phase, three_step(frames, 255)[0])
    loc = local_departure(dep)
    expected = cal(r.sigma_total, dep, fringe_density(r.phase), curvature=phase_curvature(r.phase),
                   local_departure=loc)
    np.testing.assert_allclose(pred.predict(frames).sigma_total, expected, rtol=1e-4)
    mirrored = pred.predict(np.ascontiguousarray(frames[:, :, ::-1]))
    np.testing.assert_allclose(mirrored.sigma_total[:, ::-1], expected, rtol=1e-4)
    classical = classical_md(frames_to_tensor(frames).float())[0].numpy()
    gated, taken = still_burst_gate(pred.predict(frames), classical, np.inf, cal)
    assert taken and gated.mode == "three-step"
    zero = np.zeros_like(dep)
    at_zero = cal(r.sigma_total, zero, fringe_density(r.phase), curvature=phase_curvature(r.phase),
                  local_departure=zero)
    np.testing.assert_allclose(gated.sigma_total, at_zero, rtol=1e-4)


def test_predict_cli_sends_a_still_burst_to_three_step(saved, tmp_path):
    """With angles, predict follows the pipeline's rule: a burst that did not turn has no motion
    error, so three-step PS decodes it (exactly the closed form); a turning one goes to the network."""
    from gearscan.core.phase import three_step

    _, path = saved
    frames = _frames()
    np.savez(tmp_path / "still.npz", frames=frames, angles=np.radians([10.0, 10.0, 10.0]))
    predict([tmp_path / "still.npz"], output=tmp_path / "s.npz", mc=0, model=path)
    phase3 = three_step(frames, 255)[0]
    with np.load(tmp_path / "s.npz") as z:
        assert str(z["mode"]) == "three-step"
        np.testing.assert_allclose(z["phase"], phase3, atol=1e-6)
    predict([tmp_path / "still.npz"], output=tmp_path / "n.npz", mc=0, model=path, still_span_deg=0.0)
    predict([tmp_path / "still.npz"], output=tmp_path / "m.npz", mc=0, model=path, angles_deg="10,10.6,11.2")
    for name in ("n.npz", "m.npz"):  # --still-span-deg 0, or a turning burst: the network
        with np.load(tmp_path / name) as z:
            assert str(z["mode"]) == "deterministic"


def test_dim_steep_pixels_do_not_outvote_the_fringe_direction():
    """The orientation vote is weighted by modulation: a bright region with fringes rising along
    the columns outweighs a larger dim region whose phase steps fall (steep flanks, shadows)."""
    from gearscan.inference.predictor import fringe_phase_decreases_along_columns

    cols = np.arange(64, dtype=np.float64)
    shifts = np.array([0.0, 2 * np.pi / 3, 4 * np.pi / 3])[:, None, None]
    rising = np.broadcast_to(2 * np.pi * cols / 12.0, (64, 64))  # 12 px fringes, increasing
    falling = -rising
    phase = np.where(np.arange(64)[:, None] < 24, rising, falling)  # 24 bright rows up, 40 dim rows down
    amp = np.where(np.arange(64)[:, None] < 24, 0.4, 0.08)[None]
    frames = (0.5 + amp * np.cos(phase[None] + shifts)).astype(np.float32)
    x = torch.from_numpy(frames)[None]
    assert not fringe_phase_decreases_along_columns(x)  # an unweighted count would say "decreasing" (40 of 64 rows)
    assert fringe_phase_decreases_along_columns(torch.flip(x, dims=[-1]))


def test_fast_drift_fools_the_vote_and_a_set_orientation_does_not(saved):
    """Fringes drifting a third of a period per frame make the three frames the reversed three-step set
    (shifts 0, 4pi/3, 8pi/3 = 2pi/3): their phase runs backwards and the per-burst vote reads the rig as
    mirrored. ``orientation="normal"`` decodes the burst as the rig is; ``"mirrored"`` flips every burst."""
    from gearscan.inference.predictor import fringe_phase_decreases_along_columns

    _, path = saved
    h, w = 24, 40
    xx = np.arange(w)[None, :] + 0.02 * np.arange(h)[:, None] ** 2
    drift = 2 * np.pi / 3  # phase drift per frame: a third of a period
    frames = np.stack([127 + 100 * np.cos(2 * np.pi * xx / 11 + k * (2 * np.pi / 3 + drift))
                       for k in range(3)]).astype(np.uint8)
    assert fringe_phase_decreases_along_columns(frames_to_tensor(frames))  # rising fringes, read as mirrored
    auto, normal, flipped = (Predictor.load(path, orientation=o) for o in ("auto", "normal", "mirrored"))
    a, n, f = auto.predict(frames), normal.predict(frames), flipped.predict(frames)
    np.testing.assert_allclose(a.phase, f.phase, atol=1e-6)  # the vote flipped it
    mirrored_in = np.ascontiguousarray(frames[:, :, ::-1])
    np.testing.assert_allclose(flipped.predict(mirrored_in).phase[:, ::-1], n.phase, atol=1e-6)
    with pytest.raises(ValueError, match="orientation: expected one of auto, normal, mirrored"):
        Predictor.load(path, orientation="sideways")


def test_a_model_carries_its_own_fringe_support_tests(saved, tmp_path):
    """The reconstructor's fringe-support tests chosen on val travel in the model's JSON (``network_support``): read
    into ``Predictor.network_support`` and the decoder; none named: None (the product's apply); a bad entry names the
    key and what was expected."""
    from gearscan.inference.decoder import Decoder
    from gearscan.inference.model_io import read_config
    from gearscan.inference.predictor import WEIGHTS_DIR, NetworkSupport, model_network_support

    model, path = saved
    assert Predictor.load(path).network_support is None
    assert Decoder(classical=True).network_support is None
    save_model(model, path, extra={"network_support": {"per_burst_px": 2, "frame_fit_px": None}})
    assert Predictor.load(path).network_support == NetworkSupport(2, None)
    assert Decoder(path, workers=1).network_support == NetworkSupport(2, None)
    for bad, match in (({"per_burst_px": 2}, "network_support: expected"),
                       ({"per_burst_px": -1, "frame_fit_px": 0}, r"network_support\.per_burst_px: expected null"),
                       ({"per_burst_px": 0, "frame_fit_px": 1.5}, r"network_support\.frame_fit_px"),
                       ({"per_burst_px": True, "frame_fit_px": 0}, r"network_support\.per_burst_px"),
                       ("2 px", "network_support: expected")):
        save_model(model, path, extra={"network_support": bad})
        with pytest.raises(ModelFileError, match=match):
            Predictor.load(path)
    # the shipped files: v9 its own val choices (the product's constants, which tests/test_inspect.py ties to the val
    # runs' jsons), v6 2 px / 0 px, the option (fine-tuned from v9 in session 54) v9's, inherited
    from gearscan.recon.measure import FRAME_FIT_NETWORK_SUPPORT_PX, NETWORK_SUPPORT_PX

    shipped = {name: model_network_support(read_config(WEIGHTS_DIR / f"{name}.safetensors"))
               for name in ("default", "v6", "default_rig")}
    assert shipped == {"default": NetworkSupport(NETWORK_SUPPORT_PX, FRAME_FIT_NETWORK_SUPPORT_PX),
                       "v6": NetworkSupport(2, 0), "default_rig": shipped["default"]}
    assert "inherited from the init model inference/weights/default.safetensors" in read_config(
        WEIGHTS_DIR / "default_rig.safetensors")["network_support"]["chosen_by"]


def test_a_model_carries_its_own_rest_sigma_scale_and_the_frame_fit_reads_it(saved, tmp_path):
    """``rest_sigma`` in a model's JSON (benchmarks/rest_sigma_rule.md, rerun 6: per model) is what the frame fit
    multiplies its unfitted points' sigma by; none named: the product's; a bad entry names the key. The shipped option
    carries the scale its own val cells chose (benchmarks/rest_sigma_val.json), v9 none (the product's is its)."""
    from gearscan.inference.decoder import Decoder
    from gearscan.inference.model_io import model_fingerprint, read_config
    from gearscan.inference.predictor import WEIGHTS_DIR
    from gearscan.recon.track import REST_SIGMA_SCALE

    model, path = saved
    assert Predictor.load(path).rest_sigma_scale is None and Decoder(classical=True).rest_sigma_scale is None
    # a run's decoder summary (replay's metrics, inspect's report) names the network that decoded it
    named = {"model": str(path), "model_fingerprint": model_fingerprint(path)}
    assert named.items() <= Decoder(path, workers=1).summary().items()
    assert (Decoder(classical=True).summary()["model"], Decoder(classical=True).summary()["model_fingerprint"]) == (None, None)
    save_model(model, path, extra={"rest_sigma": {"scale": 2.5}})
    assert Predictor.load(path).rest_sigma_scale == 2.5 and Decoder(path, workers=1).rest_sigma_scale == 2.5
    for bad in ({"scale": 0.5}, {"scale": float("nan")}, {"scale": True}, {}, 2.0):
        save_model(model, path, extra={"rest_sigma": bad})
        with pytest.raises(ModelFileError, match="rest_sigma: expected"):
            Predictor.load(path)
    # whose scale a run's frame fit reads (recon.depth_sigma.decoder_rest_sigma): the model's own, chosen for this
    # decode or naming none; stale where chosen for another; mc in Monte Carlo mode; else the product's
    from gearscan.recon.depth_sigma import decoder_rest_sigma

    class Run:
        rest_sigma_scale, rest_sigma_chosen_for, model_fingerprint, mc = 2.0, "abc", "abc", 0

    assert decoder_rest_sigma(Run()) == (2.0, "model")
    Run.rest_sigma_chosen_for = None
    assert decoder_rest_sigma(Run()) == (2.0, "model")
    Run.mc = 20
    assert decoder_rest_sigma(Run()) == (2.0, "mc")
    Run.rest_sigma_chosen_for = "other"
    assert decoder_rest_sigma(Run()) == (2.0, "stale")
    Run.rest_sigma_scale = None
    assert decoder_rest_sigma(Run()) == (None, "product")
    # the frame fit of a fused replay takes the model's own, else the product's
    from gearscan.replay import make_refiner

    class _Reader:
        path = "rec"

        def __len__(self):
            return 3

        def frame(self, i):
            return type("F", (), {"image": np.zeros((8, 8), np.uint8)})()

    from gearscan.core.rig import default_rig

    rig = default_rig()
    assert make_refiner(_Reader(), rig, 40.0, object()).rest_sigma_scale == REST_SIGMA_SCALE
    assert make_refiner(_Reader(), rig, 40.0, object(), rest_sigma_scale=2.0).rest_sigma_scale == 2.0
    # the shipped files
    option = WEIGHTS_DIR / "default_rig.safetensors"
    rest = json.loads((WEIGHTS_DIR.parents[1] / "benchmarks" / "rest_sigma_val.json").read_text())
    meta = read_config(option)["rest_sigma"]
    assert meta["scale"] == rest["scale_by_model"]["default-rig option"]["scale"] == 2.0
    assert meta["model_fingerprint"] == model_fingerprint(option)
    assert rest["scale"] == rest["scale_by_model"]["v9 (shipped)"]["scale"] == REST_SIGMA_SCALE
    assert "rest_sigma" not in read_config(WEIGHTS_DIR / "default.safetensors")
