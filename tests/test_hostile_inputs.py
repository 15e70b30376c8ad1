"""Hostile inputs to the CLI: each a clear error (exit 2 naming the input and what was expected)
or a warning, never a traceback or a silent wrong result."""

from __future__ import annotations

import shutil

import numpy as np
from typer.testing import CliRunner

from gearscan.cli import app
from gearscan.config import TEMPLATE

runner = CliRunner()


def _frames(tmp_path, frames: np.ndarray):
    path = tmp_path / "burst.npz"
    np.savez(path, frames=frames)
    return path


def _fringes(h: int = 32, w: int = 32) -> np.ndarray:
    """A three-step burst of vertical fringes (period 8 px), 8-bit."""
    x = np.arange(w)[None, :]
    return np.stack([np.broadcast_to(128 + 100 * np.cos(2 * np.pi * x / 8 + k * 2 * np.pi / 3), (h, w))
                     for k in range(3)]).astype(np.uint8)


def test_bind_that_is_not_an_address_is_exit_2_naming_it(tmp_path):
    res = runner.invoke(app, ["replay", str(tmp_path), "--classical", "--serve", "--bind", "not an address"])
    assert res.exit_code == 2, res.output
    assert "not an address" in res.output and "--bind" in res.output, res.output


def test_infinite_exposure_in_the_config_is_exit_2_naming_the_key(tmp_path):
    cfg = tmp_path / "rig.toml"
    cfg.write_text(TEMPLATE.replace("exposure_us = 5000.0", "exposure_us = inf"))
    res = runner.invoke(app, ["live", "--config", str(cfg), "--check"])
    assert res.exit_code == 2, res.output
    assert "camera.exposure_us: Input should be a finite number (got inf)" in res.output, res.output


def test_speed_nan_or_inf_is_exit_2(tmp_path):
    for value in ("nan", "inf", "-1"):
        res = runner.invoke(app, ["replay", str(tmp_path), "--classical", "--speed", value])
        assert res.exit_code == 2, res.output
        assert f"--speed must be a positive number or 'max', got '{value}'" in res.output, res.output


def test_nan_weights_are_refused_naming_the_tensor(tmp_path):
    from safetensors.torch import load_file, save_file

    from gearscan.inference.predictor import model_path

    shipped = model_path(None)
    state = load_file(str(shipped))
    name = sorted(k for k, v in state.items() if v.is_floating_point() and v.numel() > 1)[0]
    state[name].view(-1)[1] = float("nan")
    bad = tmp_path / "bad.safetensors"
    save_file(state, str(bad))
    shutil.copy(shipped.with_suffix(".json"), bad.with_suffix(".json"))
    res = runner.invoke(app, ["predict", str(_frames(tmp_path, _fringes())), "--model", str(bad),
                              "-o", str(tmp_path / "out.npz")])
    assert res.exit_code == 2, res.output
    assert f"tensor {name!r} holds 1 NaN or infinite value(s)" in res.output and str(bad) in res.output, res.output
    assert not (tmp_path / "out.npz").exists()


def test_all_zero_frames_warn_of_no_fringe_modulation(tmp_path):
    path = _frames(tmp_path, np.zeros((3, 32, 32), np.uint8))
    res = runner.invoke(app, ["predict", str(path), "-o", str(tmp_path / "out.npz")])
    assert res.exit_code == 0, res.output
    assert "the three frames are all zero: no fringe modulation" in res.output, res.output
    res = runner.invoke(app, ["predict", str(_frames(tmp_path, _fringes())), "-o", str(tmp_path / "out.npz")])
    assert res.exit_code == 0 and "no fringe modulation" not in res.output, res.output


def test_output_is_written_under_exactly_the_name_given(tmp_path):
    out = tmp_path / "result.txt"
    res = runner.invoke(app, ["predict", str(_frames(tmp_path, _fringes())), "-o", str(out)])
    assert res.exit_code == 0 and res.output.startswith(f"{out}:"), res.output
    assert not (tmp_path / "result.txt.npz").exists()
    with np.load(out) as z:  # an npz under the given name, with the phase of the fringes
        phase = z["phase"]
    assert phase.shape == (32, 32) and np.isfinite(phase).all()
    res = runner.invoke(app, ["predict", str(_frames(tmp_path, _fringes())), "-o", "/proc/nope/out.npz"])
    assert res.exit_code == 2 and "--output: cannot write /proc/nope/out.npz" in res.output, res.output


def test_orientation_is_checked_and_mirrored_flips_the_decode(tmp_path):
    frames = _fringes()
    path = _frames(tmp_path, frames)
    res = runner.invoke(app, ["predict", str(path), "--orientation", "sideways", "-o", str(tmp_path / "x.npz")])
    assert res.exit_code == 2 and "--orientation" in res.output and "sideways" in res.output, res.output
    assert not (tmp_path / "x.npz").exists()
    for o in ("normal", "mirrored"):  # the network's decode (no still-burst gate: this burst is still)
        res = runner.invoke(app, ["predict", str(path), "--orientation", o, "--still-burst-rad", "0",
                                  "-o", str(tmp_path / f"{o}.npz")])
        assert res.exit_code == 0, res.output
    (tmp_path / "m").mkdir()
    mirrored_in = _frames(tmp_path / "m", np.ascontiguousarray(frames[:, :, ::-1]))
    res = runner.invoke(app, ["predict", str(mirrored_in), "--orientation", "mirrored", "--still-burst-rad", "0",
                              "-o", str(tmp_path / "mm.npz")])
    assert res.exit_code == 0, res.output
    with np.load(tmp_path / "normal.npz") as a, np.load(tmp_path / "mm.npz") as b:
        np.testing.assert_allclose(b["phase"][:, ::-1], a["phase"], atol=1e-5)
        assert str(a["fringes"]) == "normal (set)" and str(b["fringes"]) == "mirrored (set)"  # what decoded it
    # auto votes on the burst, says what it chose, and warns that the vote can misread fast bursts
    res = runner.invoke(app, ["predict", str(mirrored_in), "--still-burst-rad", "0", "-o", str(tmp_path / "auto.npz")])
    assert res.exit_code == 0 and "fringes mirrored (voted on this burst)" in res.output, res.output
    assert "pass --rig rig.json or set --orientation normal|mirrored" in res.output
    with np.load(tmp_path / "auto.npz") as c, np.load(tmp_path / "mm.npz") as b:
        np.testing.assert_array_equal(c["phase"], b["phase"])
    # a burst the encoder saw standing still goes to three-step PS: no orientation, no note
    res = runner.invoke(app, ["predict", str(path), "--angles-deg", "0,0,0", "-o", str(tmp_path / "s.npz")])
    assert res.exit_code == 0 and "fringes not used (three-step PS)" in res.output and "note:" not in res.output
    assert "route: the encoder's angles turned less than" in res.output


def test_predict_takes_the_fringe_orientation_from_a_rig_calibration(tmp_path):
    """``--rig`` sets the orientation from the rig's geometry (a projector hung upside down: mirrored), says so in the
    output, warns where ``--orientation`` contradicts it, and a file that is not a rig is exit 2 naming ``--rig``."""
    from dataclasses import replace

    from gearscan.core.rig import default_rig

    rig = default_rig(64, 64)
    t = rig.projector.T_from_world.copy()
    t[:2] *= -1  # turned 180 deg about its optical axis
    upside_down = tmp_path / "rig.json"
    replace(rig, projector=replace(rig.projector, T_from_world=t)).save(upside_down)
    normal_rig = tmp_path / "normal.json"
    rig.save(normal_rig)
    frames = _fringes()
    path = _frames(tmp_path, frames)
    res = runner.invoke(app, ["predict", str(path), "--rig", str(upside_down), "-o", str(tmp_path / "r.npz")])
    assert res.exit_code == 0 and "fringes mirrored (rig calibration)" in res.output and "note:" not in res.output, res.output
    res = runner.invoke(app, ["predict", str(path), "--orientation", "mirrored", "-o", str(tmp_path / "m.npz")])
    assert res.exit_code == 0 and "fringes mirrored (set)" in res.output, res.output
    with np.load(tmp_path / "r.npz") as a, np.load(tmp_path / "m.npz") as b:
        np.testing.assert_array_equal(a["phase"], b["phase"])
    res = runner.invoke(app, ["predict", str(path), "--rig", str(normal_rig), "--orientation", "mirrored",
                              "-o", str(tmp_path / "c.npz")])
    assert res.exit_code == 0 and "--orientation mirrored, but --rig" in res.output and "fringes mirrored (set)" in res.output
    res = runner.invoke(app, ["predict", str(path), "--rig", str(normal_rig), "--orientation", "normal",
                              "-o", str(tmp_path / "n.npz")])
    # this still burst in its own orientation: the shipped still-burst gate takes it, and then no orientation decoded it
    assert res.exit_code == 0 and "fringes not used (three-step PS)" in res.output and "warning" not in res.output, res.output
    assert "route: still-burst gate 0.03 rad (the model's) took it as still: three-step PS" in res.output
    res = runner.invoke(app, ["predict", str(path), "--rig", str(normal_rig), "--orientation", "normal",
                              "--still-burst-rad", "0", "-o", str(tmp_path / "n0.npz")])
    assert res.exit_code == 0 and "fringes normal (set)" in res.output and "warning" not in res.output, res.output
    assert "route: the network, no still-burst gate (set)" in res.output
    not_rig = tmp_path / "x.json"
    not_rig.write_text("{}")
    res = runner.invoke(app, ["predict", str(path), "--rig", str(not_rig), "-o", str(tmp_path / "x.npz")])
    said = " ".join(res.output.replace("│", " ").split())  # the error box wraps its lines
    assert res.exit_code == 2 and "Invalid value for --rig" in said and "not a gearscan rig file" in said, res.output
    assert not (tmp_path / "x.npz").exists()


def test_predict_reports_the_sigma_of_the_pixels_with_fringes_not_the_background(tmp_path):
    """A gear filling part of the frame: the printed median sigma is the fringe pixels' (three-step modulation >= 0.05,
    recomputed here from the frames), not the whole image's, which the dark background's large sigma would swamp."""
    import re

    import pytest

    from gearscan.core.phase import three_step

    frames = _fringes(64, 64).astype(np.float64)
    rng = np.random.default_rng(3)
    dark = np.zeros((64, 64), bool)
    dark[:, 24:] = True  # the background, most of the frame: no fringes
    frames[:, dark] = 6.0
    frames += rng.normal(0, 1.5, frames.shape)  # sensor noise everywhere: the sigma has something to propagate
    path = _frames(tmp_path, np.clip(frames, 0, 255).astype(np.uint8))
    out = tmp_path / "out.npz"
    res = runner.invoke(app, ["predict", str(path), "--orientation", "normal", "-o", str(out)])
    assert res.exit_code == 0, res.output
    _, m, d = three_step(np.load(path)["frames"], 255.0)
    lit = np.hypot(m, d) >= 0.05
    assert 0.3 < lit.mean() < 0.45  # the fringe part, not the background
    sigma = np.load(out)["sigma_total"]
    printed = float(re.search(r"median sigma_total ([0-9.]+) rad over the (\d+) %", res.output).group(1))
    assert printed == pytest.approx(float(np.median(sigma[lit])), abs=1e-4)
    assert np.median(sigma) > 1.5 * printed  # what the whole image's median would have said
