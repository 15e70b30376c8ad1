"""Per-rig adaptation (the paper's digital-twin workflow): a user's own rig and gear render into an
adaptation dataset (any tooth count), and fine-tuning the shipped model on it lowers its error there."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from gearscan.cli import app
from gearscan.core.gear import GearSpec
from gearscan.core.phase import phase_error
from gearscan.core.rig import Rig
from gearscan.evaluate import Scene, network_method, render_cases
from gearscan.generalization import PAPER, PAPER_REVERSED
from gearscan.inference.losses import LossConfig
from gearscan.inference.model_io import read_config
from gearscan.inference.models import ModelConfig
from gearscan.inference.predictor import DEFAULT_MODEL, Predictor
from gearscan.inference.train import TrainConfig, train
from gearscan.twin.dataset import DatasetError, DatasetSpec, TwinBurstDataset, generate_dataset
from gearscan.twin.randomize import balance_projector_power, projector_period_for_surface, view_rig
from gearscan.twin.render import Optics, TwinRenderer
from gearscan.twin.splits import SPLITS

SIZE = 96
GEAR = GearSpec(teeth=35, module=3.0)  # a test-split tooth count: the user's own gear


def tiny_scene():
    """A 96 px side view of the teeth (a view the shipped model never trained on), 12 px fringes."""
    rig = view_rig(SIZE, SIZE, GEAR, view="side", angle_deg=45, standoff=160.0,
                   field_mm=3 * GEAR.pitch_angle * GEAR.pitch_radius, triangulation_deg=-24.0)
    optics = balance_projector_power(rig, Optics())
    period = projector_period_for_surface(TwinRenderer(rig, GEAR, optics).surface(0.0), 12.0)
    return rig, optics, GEAR, period


@pytest.fixture(scope="module")
def adapt(tmp_path_factory):
    root = tmp_path_factory.mktemp("adapt") / "ds"
    scene = tiny_scene()
    spec = DatasetSpec(gears=[GEAR], width=SIZE, height=SIZE, period_px=scene[3], seed=1, max_start_points=3,
                       start_step_deg=3.0)
    generate_dataset(root, spec, scene=scene, purpose="adaptation")
    return root, spec, scene


def test_adaptation_dataset_takes_the_users_gear_and_records_the_rig(adapt, tmp_path):
    root, spec, scene = adapt
    assert GEAR.teeth in SPLITS["test"].teeth
    index = json.loads((root / "index.json").read_text())
    assert index["purpose"] == "adaptation" and len(index["entries"]) == 3
    assert index["scene"]["gear"]["teeth"] == 35 and index["scene"]["period_px"] == pytest.approx(scene[3])
    assert Rig.from_json(index["scene"]["rig"]).camera.K.tolist() == scene[0].camera.K.tolist()
    # the project's own (protocol) datasets still refuse test gears and seeds
    with pytest.raises(DatasetError, match=r"tooth counts \[35\] belong to the test split"):
        generate_dataset(tmp_path / "p", spec, scene=scene)
    with pytest.raises(DatasetError, match="seed 20000"):
        generate_dataset(tmp_path / "a", spec.model_copy(update={"seed": 20_000}), scene=scene, purpose="adaptation")
    with pytest.raises(DatasetError, match="one given scene"):
        generate_dataset(tmp_path / "a", spec, purpose="adaptation")
    with pytest.raises(DatasetError, match="differs from the rig's camera"):
        generate_dataset(tmp_path / "a", spec.model_copy(update={"width": 64}), scene=scene, purpose="adaptation")
    assert not (tmp_path / "p").exists() and not (tmp_path / "a").exists()


def _rmse(predictor: Predictor, cases) -> float:
    decode = network_method(predictor)
    se = n = 0.0
    for c in cases:
        err = phase_error(decode(c.frames, c.full_scale, c.angles_rad).phase, c.truth.phase)[c.truth.mask]
        se, n = se + float(np.sum(err.astype(np.float64) ** 2)), n + err.size
    return math.sqrt(se / n)


def test_fine_tuning_on_a_tiny_rendered_rig_lowers_its_error(adapt, tmp_path):
    torch.set_num_threads(1)
    root, _, scene = adapt
    meta = read_config(DEFAULT_MODEL)
    train_set = TwinBurstDataset(root, groups=[0, 1], static=True, reverse=True, crop=64)
    val_set = torch.utils.data.Subset(TwinBurstDataset(root, groups=[2], static=True, reverse=True),
                                      list(range(0, 1650, 50)))
    cfg = TrainConfig(out_dir=str(tmp_path / "ft"), model=ModelConfig.from_json(meta["model"]),
                      loss=LossConfig(**meta["training"]["loss"]), epochs_deterministic=5, epochs_dropout=0,
                      steps_per_epoch=10, batch_size=8, lr=3e-4, schedule="constant", init=str(DEFAULT_MODEL),
                      precision="fp32", progress=False, calibrate=False)
    result = train(cfg, train_set, val_set)
    assert result.history[0]["epoch"] == 0  # the shipped weights were validated first
    # held-out bursts of that rig: other start angles and noise (seed 5), the paper's motions both ways
    cases = render_cases(Scene("tiny side rig", *scene), {**PAPER, **PAPER_REVERSED}, 1, seed=5)
    before = _rmse(Predictor.load(DEFAULT_MODEL, precision="fp32"), cases)
    after = _rmse(Predictor.load(result.best_path, precision="fp32"), cases)
    assert after < 0.93 * before, (before, after)


def test_cli_renders_a_users_rig_and_fine_tunes_within_a_cpu_budget(adapt, tmp_path):
    root, _, scene = adapt
    rig_file = tmp_path / "rig.json"
    scene[0].save(rig_file)
    runner = CliRunner()
    out = tmp_path / "mine"
    args = ["twin", "dataset", str(out), "--rig", str(rig_file), "--teeth", "35", "--module", "3",
            "--period", f"{scene[3]}", "--max-start-points", "1", "--seed", "3"]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    index = json.loads((out / "index.json").read_text())
    assert index["purpose"] == "adaptation" and (index["spec"]["width"], index["spec"]["height"]) == (SIZE, SIZE)
    # without --rig the same gear is a protocol dataset: refused, naming the split
    res = runner.invoke(app, ["twin", "dataset", str(tmp_path / "p"), "--teeth", "35", "--width", "32",
                              "--height", "32", "--max-start-points", "1"])
    assert res.exit_code == 2 and "test split" in res.output
    res = runner.invoke(app, [*args[:2], str(tmp_path / "w"), *args[3:], "--width", "64"])
    assert res.exit_code == 2 and "differ from the rig's camera" in res.output
    # fine-tune the shipped model under a CPU budget: it stops by itself and keeps the shipped network
    run = tmp_path / "run"
    res = runner.invoke(app, ["train", "--init", str(DEFAULT_MODEL), "--data", str(root), "--val-data", str(out),
                              "--budget-cpu-min", "0.05", "--epochs-deterministic", "100000", "--epochs-dropout", "0",
                              "--steps-per-epoch", "2", "--batch-size", "4", "--crop", "64", "--calibrate-mc", "0",
                              "--precision", "fp32", "--no-progress", "--out", str(run), "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert "CPU budget 0.05 min reached" in res.output
    best = read_config(run / "best.safetensors")
    # the same network (compared as configs: an option added since is written at its default)
    assert ModelConfig.from_json(best["model"]) == ModelConfig.from_json(read_config(DEFAULT_MODEL)["model"])
    assert best["budget_hit"] is True
    assert best["training"]["loss"]["mse_weighting"] == "modulation"  # the init's loss, not the CLI default
    # the init's own fringe-support tests travel with the fine-tune, marked as inherited
    assert Predictor.load(run / "best.safetensors").network_support == Predictor.load(DEFAULT_MODEL).network_support
    assert best["network_support"]["chosen_by"].startswith("inherited from the init model")


def test_cli_fine_tunes_from_the_bank_within_a_wall_clock_budget(adapt, tmp_path):
    """`gearscan train --bank --wall-minutes`: bursts drawn on the device (a crop per item), stopped by the clock
    with both stages run; --bank on data that are not twin folders is refused by name."""
    root, _, _ = adapt
    runner = CliRunner()
    run = tmp_path / "bank"
    t0 = time.time()
    res = runner.invoke(app, ["train", "--init", str(DEFAULT_MODEL), "--data", str(root), "--val-data", str(root),
                              "--bank", "--wall-minutes", "0.15", "--epochs-deterministic", "3",
                              "--epochs-dropout", "1", "--steps-per-epoch", "100000", "--batch-size", "4",
                              "--crop", "64", "--calibrate-mc", "0", "--precision", "fp32", "--no-progress",
                              "--out", str(run), "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert "wall-clock budget 0.15 min reached" in res.output and time.time() - t0 < 0.15 * 60 + 30
    best = read_config(run / "best.safetensors")
    assert best["training"]["bank"] is True and best["budget_hit"] is True
    rows = json.loads((run / "metrics.json").read_text())
    assert {r["stage"] for r in rows if r["steps"]} == {1, 2}
    # items stored as .npz (the other --data form) cannot be banked: refused by name, nothing trained
    from gearscan.inference.data import NpzBurstDataset
    from gearscan.twin.dataset import TwinBurstDataset

    item = TwinBurstDataset(root, crop=64)[0]
    NpzBurstDataset.write([item, item], tmp_path / "npz")
    res = runner.invoke(app, ["train", "--data", str(tmp_path / "npz"), "--val-data", str(root), "--bank",
                              "--out", str(tmp_path / "no"), "--device", "cpu", "--no-progress"])
    assert res.exit_code == 2 and "expected twin dataset folders" in res.output
    assert not (tmp_path / "no" / "best.safetensors").exists()
    # a val folder that is not there is named by its own flag (it had been called --data)
    res = runner.invoke(app, ["train", "--data", str(root), "--val-data", str(tmp_path / "nope_val"),
                              "--out", str(tmp_path / "no"), "--device", "cpu", "--no-progress"])
    assert res.exit_code == 2 and "--val-data" in res.output and "nope_val" in res.output, res.output
