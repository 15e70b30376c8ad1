"""Training loop on a tiny twin set: overfits, two stages, group split, LR schedules, resume, init, DDP."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from gearscan.core.phase import three_step, wrapped_rmse
from gearscan.inference.data import (
    NpzBurstDataset,
    TensorBurstDataset,
    split_by_group,
)
from gearscan.inference.losses import LossConfig
from gearscan.inference.lr_schedule import build_scheduler
from gearscan.inference.model_io import load_model
from gearscan.inference.models import ModelConfig
from gearscan.inference.predictor import Predictor
from gearscan.inference.train import TrainConfig, Trainer, train
from gearscan.mocks.twin_bursts import render_twin_bursts

torch.set_num_threads(1)


@functools.lru_cache(maxsize=2)
def twin_items(starts: int = 2, per_start: int = 2, size: int = 48) -> tuple:
    """Moving bursts (steps up to 0.6 deg) of a 20-tooth gear seen at 6 mm field, 48 px."""
    return tuple(
        render_twin_bursts(
            size=size, field_mm=6.0, starts=starts, bursts_per_start=per_start, seed=1
        )
    )


def _cfg(tmp_path, **kw) -> TrainConfig:
    base = dict(
        out_dir=str(tmp_path / "run"),
        model=ModelConfig(width=4),
        batch_size=4,
        progress=False,
        seed=0,
    )
    base.update(kw)
    return TrainConfig(**base)


def test_tiny_model_overfits_tiny_twin_set(tmp_path):
    items = list(twin_items())
    ds = TensorBurstDataset(items)
    classical = np.mean(
        [wrapped_rmse(three_step(it["input"], 1.0)[0], it["phase"], it["mask"]) for it in items]
    )
    cfg = _cfg(
        tmp_path,
        model=ModelConfig(width=8),
        loss=LossConfig(mse_weighting="modulation"),
        epochs_deterministic=150,
        epochs_dropout=0,
        lr=3e-3,
        patience=150,
        calibrate=False,
    )
    result = train(cfg, ds, ds)
    final = result.history[-1]["val_rmse"]
    # each epoch says how long it trained and how much of that it waited on the loader
    row = result.history[-1]
    assert 0 <= row["data_wait_s"] <= row["train_s"] <= row["seconds"] and row["steps"] > 0
    # three-step PS on these moving bursts is ~0.4 rad off; the net must fit them to < 0.05 rad
    assert classical > 0.2
    assert final < 0.05, f"did not overfit: RMSE {final:.3f} rad (three-step {classical:.3f})"
    pred = Predictor.load(result.best_path)
    r = pred.predict((items[0]["input"] * 255).round().astype(np.uint8))
    assert wrapped_rmse(r.phase, items[0]["phase"], items[0]["mask"]) < 0.1


def test_two_stages_split_files_and_rates_move(tmp_path):
    items = list(twin_items(starts=3, per_start=2))
    ds = TensorBurstDataset(items)
    cfg = _cfg(tmp_path, epochs_deterministic=2, epochs_dropout=3, lr=1e-2, val_fraction=0.34)
    trainer = Trainer(cfg, ds)
    train_groups = {ds.groups[i] for i in trainer.train_set.indices}
    val_groups = {ds.groups[i] for i in trainer.val_set.indices}
    assert train_groups and val_groups and not (train_groups & val_groups)
    result = trainer.fit()
    hist = result.history
    assert [h["stage"] for h in hist] == [1, 1, 2, 2, 2]
    p_keys = [k for k in hist[0] if k.startswith("p")]
    assert len(p_keys) == 9
    # stage 1 leaves the rates alone, stage 2 learns them
    assert all(hist[0][k] == hist[1][k] for k in p_keys)
    assert all(abs(hist[-1][k] - hist[1][k]) > 1e-4 for k in p_keys)
    assert hist[0]["train_reg"] == 0 and hist[-1]["train_reg"] != 0
    out = Path(cfg.out_dir)
    for name in (
        "best.safetensors",
        "best.json",
        "metrics.csv",
        "metrics.json",
        "loss_curve.png",
        "last_optim.pt",
    ):
        assert (out / name).is_file(), name
    meta = json.loads((out / "best.json").read_text())
    assert (
        meta["var_scale"] > 0 and "calibration" in meta and meta["training"]["epochs_dropout"] == 3
    )
    # its metrics are the kept weights' (the last stage's best on val), the last epoch's beside them
    kept = min((h for h in hist if h["stage"] == 2), key=lambda h: h["val_loss"])
    assert (meta["metrics"]["stage"], meta["metrics"]["epoch"]) == (2, kept["epoch"])
    assert meta["metrics"]["val_loss"] == pytest.approx(kept["val_loss"])
    assert (meta["final_metrics"]["stage"], meta["final_metrics"]["epoch"]) == (2, hist[-1]["epoch"])
    # the sigma maps are fitted per mode by the event score on the validation truth, and the predictor applies them
    fits = meta["calibration"]["sigma_calibration"]
    assert set(meta["sigma_calibration"]) == {"deterministic", "mc"} and fits["mc"]["passes"] == 20
    assert all(f["score"] == "event" and f["event_score_after"] <= f["event_score_before"] for f in fits.values())
    assert set(Predictor.load(out / "best.safetensors").calibration) == {"deterministic", "mc"}
    assert (out / "metrics.csv").read_text().splitlines()[0].startswith("stage,epoch,lr")


def test_resume_and_init(tmp_path, monkeypatch):
    ds = TensorBurstDataset(list(twin_items()))
    cfg = _cfg(tmp_path, epochs_deterministic=2, epochs_dropout=2, calibrate=False)
    # interrupt the run (Ctrl-C) in the third epoch, i.e. the first of stage 2
    original = Trainer._train_epoch
    calls = {"n": 0}

    def flaky(self, *a, **kw):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return original(self, *a, **kw)

    monkeypatch.setattr(Trainer, "_train_epoch", flaky)
    with pytest.raises(KeyboardInterrupt):
        train(cfg, ds, ds)
    monkeypatch.setattr(Trainer, "_train_epoch", original)
    done = json.loads((Path(cfg.out_dir) / "metrics.json").read_text())
    assert [h["stage"] for h in done] == [1, 1]
    # resume picks up at stage 2 with history, optimizer and weights restored
    resumed = train(
        _cfg(tmp_path, epochs_deterministic=2, epochs_dropout=2, calibrate=False, resume=True),
        ds,
        ds,
    )
    assert [(h["stage"], h["epoch"]) for h in resumed.history] == [(1, 1), (1, 2), (2, 1), (2, 2)]
    assert resumed.history[:2] == done
    # --init: a new run starts from the trained weights
    init_path = Path(cfg.out_dir) / "best.safetensors"
    cfg3 = _cfg(
        tmp_path,
        out_dir=str(tmp_path / "ft"),
        epochs_deterministic=1,
        epochs_dropout=0,
        init=str(init_path),
        lr=1e-9,
        calibrate=False,
    )
    ft = Trainer(cfg3, ds, ds)
    ref, _ = load_model(init_path)
    for (k, a), b in zip(ref.state_dict().items(), ft.model.state_dict().values(), strict=True):
        assert torch.equal(a, b), k
    # --init with reset_dropout: same weights, rates re-drawn from the new model config's range
    from gearscan.inference.concrete_dropout import dropout_rates

    cfg4 = _cfg(tmp_path, out_dir=str(tmp_path / "ft2"), epochs_deterministic=1, epochs_dropout=0,
                init=str(init_path), reset_dropout=True, calibrate=False,
                model=ModelConfig(width=4, init_min=0.02, init_max=0.05))
    ft2 = Trainer(cfg4, ds, ds)
    rates = dropout_rates(ft2.model)
    assert rates and all(0.02 - 1e-6 <= r <= 0.05 + 1e-6 for r in rates), rates
    assert all(r > 0.09 for r in dropout_rates(ft.model))  # the default range 0.1..0.4, kept by plain --init
    for (k, a), b in zip(ref.state_dict().items(), ft2.model.state_dict().values(), strict=True):
        assert k.endswith("p_logit") or torch.equal(a, b), k


def test_cpu_budget_stops_cleanly_and_keeps_the_best_on_val(tmp_path):
    ds = TensorBurstDataset(list(twin_items()))
    start = train(_cfg(tmp_path, out_dir=str(tmp_path / "start"), epochs_deterministic=3, epochs_dropout=0,
                       lr=3e-3, calibrate=False), ds, ds)
    # an absurd learning rate wrecks the weights: best-on-val must stay the starting point
    cfg = _cfg(tmp_path, out_dir=str(tmp_path / "ft"), init=str(start.best_path), epochs_deterministic=100_000,
               epochs_dropout=1, steps_per_epoch=1, lr=5.0, schedule="constant", patience=100_000,
               budget_cpu_min=0.02, checkpoints_cpu_min=(0.01,), calibrate=False)
    t0 = time.process_time()
    result = train(cfg, ds, ds)
    used = time.process_time() - t0
    assert result.budget_hit and 1.2 <= result.cpu_seconds <= used
    assert result.cpu_seconds <= 1.2 + 2.0  # at most one step and one validation past the budget
    hist = result.history
    assert hist[0]["epoch"] == 0 and hist[0]["steps"] == 0  # the init, validated before any step
    assert len(hist) > 2 and all(h["stage"] == 1 for h in hist)  # the budget ended stage 1, stage 2 never ran
    assert [h["cpu_min"] for h in hist] == sorted(h["cpu_min"] for h in hist)
    assert not any(h["val_loss"] <= hist[0]["val_loss"] for h in hist[1:])  # worse (or NaN) every time
    ref, _ = load_model(start.best_path)
    best, meta = load_model(result.best_path)
    for (k, a), b in zip(ref.state_dict().items(), best.state_dict().values(), strict=True):
        assert torch.equal(a, b), k
    assert meta["budget_hit"] and meta["train_cpu_min"] == pytest.approx(result.cpu_seconds / 60)
    mark = Path(cfg.out_dir) / "cpu_0.01min.safetensors"
    assert mark.is_file() and json.loads(mark.with_suffix(".json").read_text())["cpu_min"] >= 0.01
    # the JSONs describe the weights beside them (the init's validation row), the epoch they were written at beside it
    mark_meta = json.loads(mark.with_suffix(".json").read_text())
    assert mark_meta["metrics"]["epoch"] == 0 and mark_meta["mark_metrics"]["epoch"] > 0
    assert meta["metrics"]["epoch"] == 0 and meta["final_metrics"]["epoch"] == hist[-1]["epoch"] > 0


def test_val_objective_full_stops_on_the_trained_objective(tmp_path, monkeypatch):
    """With ``outside_weight``, every row keeps the inside loss and the outside term apart, and early stopping reads
    the inside loss by default and the trained objective (inside + weight * outside) with "full": on scripted
    validations where the two disagree, each keeps its own epoch. A resume refuses to switch objective."""
    ds = TensorBurstDataset(list(twin_items()))
    assert any((~it["mask"]).any() for it in ds.items)  # background to be taught
    w = 0.5
    # the real validation first: the row's parts and its formula
    cfg = _cfg(tmp_path, out_dir=str(tmp_path / "real"), loss=LossConfig(outside_weight=w), epochs_deterministic=2,
               epochs_dropout=0, lr=3e-3, calibrate=False, val_objective="full")
    for h in train(cfg, ds, ds).history:
        assert h["val_outside"] > 0 and h["val_inside_loss"] > 0
        assert h["val_loss"] == pytest.approx(h["val_inside_loss"] + w * h["val_outside"], rel=1e-9)
    # scripted validations: inside is lowest at epoch 2, inside + 0.5 x outside at epoch 3
    from gearscan.inference import train as train_module

    scripted = [(0.30, 0.60), (0.10, 0.50), (0.20, 0.10), (0.40, 0.40)]  # (inside, outside) per epoch 1-4
    chosen = {}
    for objective in ("inside", "full"):
        calls = iter(scripted)

        def fake(self, calls=calls):
            inside, outside = next(calls)
            return train_module.validation_row(inside, outside, 0.1, self.config.loss, self.config.val_objective)

        monkeypatch.setattr(Trainer, "_validate_once", fake)
        out = tmp_path / objective
        train(_cfg(tmp_path, out_dir=str(out), loss=LossConfig(outside_weight=w), epochs_deterministic=4,
                   epochs_dropout=0, steps_per_epoch=1, calibrate=False, val_objective=objective), ds, ds)
        chosen[objective] = json.loads((out / "stage1_best.json").read_text())["metrics"]["epoch"]
    assert chosen == {"inside": 2, "full": 3}
    monkeypatch.undo()
    # a run validated on one objective cannot be resumed on the other: its best-so-far is on another scale
    with pytest.raises(ValueError, match="resume"):
        Trainer(_cfg(tmp_path, out_dir=str(tmp_path / "full"), loss=LossConfig(outside_weight=w),
                     val_objective="inside", resume=True), ds)
    with pytest.raises(ValueError, match="val_objective"):
        _cfg(tmp_path, val_objective="outside")
    with pytest.raises(ValueError, match="outside_weight"):
        _cfg(tmp_path, val_objective="full")  # no outside term: nothing to add


def test_split_by_group_never_mixes():
    groups = [g for g in range(10) for _ in range(5)]
    tr, va = split_by_group(groups, 0.3, seed=3)
    assert len(tr) + len(va) == 50
    assert not ({groups[i] for i in tr} & {groups[i] for i in va})
    assert len({groups[i] for i in va}) == 3
    with pytest.raises(ValueError, match="need >= 2 distinct groups"):
        split_by_group([1, 1, 1])


def _epoch_lrs(cfg: TrainConfig, stage_epochs: int, stage: int = 1, start: int = 0) -> list[float]:
    """The learning rate of each epoch of a stage from ``start`` on, stepped as the trainer does."""
    opt = torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))], lr=cfg.lr)
    scheduler = build_scheduler(opt, cfg, stage, stage_epochs, start)
    lrs = []
    for _ in range(start, stage_epochs):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        scheduler.step()
    return lrs


def test_learning_rate_schedules():
    cfg = TrainConfig(lr=1e-3, step_every=20, gamma=0.9)
    step = _epoch_lrs(cfg, 100)
    assert step[:20] == pytest.approx([1e-3] * 20)  # epochs 0-19
    assert step[20] == pytest.approx(9e-4)
    assert step[45] == pytest.approx(1e-3 * 0.81)
    assert step == pytest.approx([1e-3 * 0.9 ** (e // 20) for e in range(100)], rel=1e-12)
    cos = TrainConfig(lr=1e-3, schedule="cosine")
    cosine = _epoch_lrs(cos, 100)
    assert cosine[0] == pytest.approx(1e-3) and cosine[50] == pytest.approx(5e-4)  # half way: half
    assert cosine == pytest.approx([0.5e-3 * (1 + math.cos(math.pi * e / 100)) for e in range(100)], rel=1e-12)
    assert _epoch_lrs(TrainConfig(lr=1e-3, schedule="constant"), 30) == pytest.approx([1e-3] * 30)
    # stage 2 restarts at lr_dropout, also on the optimizer stage 1 ran on
    two = TrainConfig(lr=1e-3, lr_dropout=2e-4, step_every=20, gamma=0.9)
    assert _epoch_lrs(two, 50, stage=2)[::20] == pytest.approx([2e-4, 1.8e-4, 1.62e-4])
    opt = torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))], lr=two.lr)
    build_scheduler(opt, two, 1, 50, 45)
    assert opt.param_groups[0]["lr"] == pytest.approx(1e-3 * 0.81)
    build_scheduler(opt, two, 2, 50)
    assert opt.param_groups[0]["lr"] == pytest.approx(2e-4)
    # resuming at an epoch: the rates of the uninterrupted stage
    assert _epoch_lrs(cfg, 100, start=45) == step[45:]
    assert _epoch_lrs(cos, 100, start=37) == cosine[37:]
    with pytest.raises(ValueError, match="schedule: expected one of"):
        TrainConfig(schedule="linear")


def test_cosine_time_anneals_over_the_stage_time():
    """``cosine-time`` reads the share of the stage's time spent, not the epoch: half way, half the rate; at the
    end 0; past it, still 0. Without a budget or deadline to anneal over, the config is refused."""
    cfg = TrainConfig(lr=1e-3, schedule="cosine-time", budget_cpu_min=1.0)
    spent = [0.0]
    opt = torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))], lr=cfg.lr)
    scheduler = build_scheduler(opt, cfg, 1, 1_000_000, progress=lambda: spent[0])
    lrs = []
    for f in (0.25, 0.5, 1.0, 1.7):
        lrs.append(opt.param_groups[0]["lr"])
        spent[0] = f
        opt.step()
        scheduler.step()
    lrs.append(opt.param_groups[0]["lr"])
    assert lrs == pytest.approx([1e-3, 0.5e-3 * (1 + math.cos(math.pi / 4)), 0.5e-3, 0.0, 0.0], abs=1e-15)
    with pytest.raises(ValueError, match="budget_cpu_min or deadline"):
        TrainConfig(schedule="cosine-time")
    with pytest.raises(ValueError, match="progress"):
        build_scheduler(opt, cfg, 1, 10)
    TrainConfig(schedule="cosine-time", deadline=time.time() + 60)  # a deadline is a time to anneal over too


def test_cosine_time_training_ends_annealed(tmp_path):
    """A real fit under a CPU budget with ``cosine-time``: the rate falls epoch by epoch from its peak, and the last
    epoch before the budget runs at a small share of it (the budget stops training one validation early)."""
    ds = TensorBurstDataset(list(twin_items()))
    cfg = _cfg(tmp_path, epochs_deterministic=100_000, epochs_dropout=0, steps_per_epoch=1, lr=1e-3,
               schedule="cosine-time", patience=100_000, budget_cpu_min=0.04, calibrate=False)
    trainer = Trainer(cfg, ds, ds)
    result = trainer.fit()
    rows = [h for h in result.history if h["epoch"] > 0]
    lrs = [h["lr"] for h in rows]
    assert result.budget_hit and len(lrs) >= 5
    assert lrs[0] == pytest.approx(1e-3, rel=0.05)
    assert lrs == sorted(lrs, reverse=True)  # monotone down
    assert lrs[-1] < 0.25e-3  # the last epoch ran past 2/3 of the budget

    def cos_at(cpu_min: float, c0: float) -> float:  # the rate at that CPU time of a stage begun at c0 CPU s
        f = min(1.0, max(0.0, (60.0 * cpu_min - c0) / (60.0 * cfg.budget_cpu_min - c0)))
        return 0.5e-3 * (1 + math.cos(math.pi * f))

    # the rate of epoch k+1 was set when epoch k's training ended: after row k-1's stamp, before row k's. The
    # stage began between 0 and the first row's stamp, so bound with each end (a later start: a higher rate)
    first = 60.0 * rows[0]["cpu_min"]
    for prev, row, nxt in zip(rows, rows[1:], rows[2:], strict=False):
        assert cos_at(row["cpu_min"], 0.0) - 1e-12 <= nxt["lr"] <= cos_at(prev["cpu_min"], first) + 1e-12


def test_weight_average_is_a_candidate_kept_only_if_better_on_val(tmp_path, monkeypatch):
    """``average_from``: the epochs from that share on are averaged (their mean, BatchNorm buffers too), the
    average is validated once more at the stage's end and becomes the stage's best only if it beats the best
    epoch on val; otherwise the best epoch is kept. Scripted validations decide each way."""
    ds = TensorBurstDataset(list(twin_items()))
    for scripted, kept in (([0.9, 0.8, 0.7, 0.6, 0.5, 0.1], True), ([0.9, 0.8, 0.7, 0.6, 0.5, 0.55], False)):
        out = tmp_path / f"kept{kept}"
        cfg = _cfg(tmp_path, out_dir=str(out), epochs_deterministic=5, epochs_dropout=0, steps_per_epoch=1,
                   lr=1e-3, schedule="constant", average_from=0.4, calibrate=False)
        vals = iter(scripted)
        monkeypatch.setattr(Trainer, "_validate_once",
                            lambda self, v=vals: {"val_loss": (x := next(v)), "val_rmse": x})
        weights: list[dict] = []  # every epoch's weights, as the trainer leaves them
        real_epoch = Trainer._train_epoch

        def spy(self, *a, _real=real_epoch, _w=weights, **k):
            r = _real(self, *a, **k)
            _w.append({n: t.detach().clone() for n, t in self.model.state_dict().items()})
            return r

        monkeypatch.setattr(Trainer, "_train_epoch", spy)
        result = train(cfg, ds, ds)
        monkeypatch.undo()
        hist = result.history
        assert [h.get("averaged") for h in hist] == [None, 1, 2, 3, 4, 4]  # epochs ending at share >= 0.4, then it
        assert hist[-1]["steps"] == 0 and hist[-1]["val_loss"] == scripted[-1]
        best, _ = load_model(out / "stage1_best.safetensors")
        expect = weights[-1] if not kept else {
            n: torch.stack([w[n].float() for w in weights[1:]]).mean(0) for n in weights[-1]}
        for n, t in best.state_dict().items():
            if t.is_floating_point():
                assert torch.allclose(t, expect[n], atol=1e-6), n
        assert result.best_val == pytest.approx(min(scripted))
    with pytest.raises(ValueError, match="average_from"):
        TrainConfig(average_from=1.0)


def test_weight_average_fits_in_the_cpu_budget(tmp_path, monkeypatch):
    """Under a CPU budget the average is still made and validated, and the run ends as a plain budgeted one does:
    at most a step and a validation past the budget (no epoch starts without room for the average's validation)."""
    import itertools

    import gearscan.inference.train as train_module

    ds = TensorBurstDataset(list(twin_items()))
    monkeypatch.setattr(Trainer, "_validate_once", lambda self: {"val_loss": 1.0, "val_rmse": 1.0})
    # the CPU clock advances a fixed 0.05 s per reading: the budget's arithmetic, not this machine's load, decides
    # (a loaded host had fitted one averaged step in 1.2 real CPU seconds, where a quiet one fits several)
    clock = itertools.count(0.0, 0.05)
    monkeypatch.setattr(train_module.time, "process_time", lambda: next(clock))
    budget = train(_cfg(tmp_path, epochs_deterministic=100_000, epochs_dropout=0, steps_per_epoch=1, lr=1e-3,
                        schedule="constant", patience=100_000, budget_cpu_min=0.02, average_from=0.5,
                        calibrate=False), ds, ds)
    assert budget.budget_hit and budget.history[-1]["averaged"] >= 2 and budget.history[-1]["steps"] == 0
    assert budget.cpu_seconds <= 1.2 + 2.0  # the plain budget test's bound


def test_weight_average_update_never_divides_an_integer_buffer():
    """The update CUDA can run: floats by running mean; an integer buffer (BatchNorm's count) copied, not divided."""
    from gearscan.inference.train import _running_mean

    avg = _running_mean(torch.tensor([1.0, 3.0]), torch.tensor([4.0, 0.0]), torch.tensor(2))
    assert avg.tolist() == pytest.approx([2.0, 2.0])
    count = _running_mean(torch.tensor(7), torch.tensor(9), torch.tensor(2))
    assert count.dtype == torch.int64 and int(count) == 9


def test_resume_mid_stage_keeps_the_schedule(tmp_path, monkeypatch):
    ds = TensorBurstDataset(list(twin_items()))
    kw = dict(epochs_deterministic=4, epochs_dropout=0, schedule="cosine", steps_per_epoch=1, calibrate=False)
    original = Trainer._train_epoch
    calls = {"n": 0}

    def flaky(self, *a, **kw):
        calls["n"] += 1
        if calls["n"] == 3:  # Ctrl-C in the third epoch of stage 1
            raise KeyboardInterrupt
        return original(self, *a, **kw)

    monkeypatch.setattr(Trainer, "_train_epoch", flaky)
    with pytest.raises(KeyboardInterrupt):
        train(_cfg(tmp_path, **kw), ds, ds)
    monkeypatch.setattr(Trainer, "_train_epoch", original)
    resumed = train(_cfg(tmp_path, resume=True, **kw), ds, ds)
    assert [(h["stage"], h["epoch"]) for h in resumed.history] == [(1, 1), (1, 2), (1, 3), (1, 4)]
    expected = [0.5e-3 * (1 + math.cos(math.pi * e / 4)) for e in range(4)]
    assert [h["lr"] for h in resumed.history] == pytest.approx(expected, rel=1e-12)


def test_ddp_two_processes_gloo(tmp_path):
    """torchrun with 2 CPU processes (gloo) trains, syncs validation, and rank 0 writes the model (~15 s)."""
    data = tmp_path / "data"
    NpzBurstDataset.write(list(twin_items(starts=2, per_start=2)), data)
    out = tmp_path / "ddp"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
        "-m", "gearscan.inference.train", "--data", str(data), "--out", str(out), "--width", "4",
        "--epochs-deterministic", "2", "--epochs-dropout", "1", "--batch-size", "1", "--device", "cpu", "--no-progress",
    ]  # fmt: skip
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (out / "best.safetensors").is_file()
    hist = json.loads((out / "metrics.json").read_text())
    assert [h["stage"] for h in hist] == [1, 1, 2]
    assert time.perf_counter() - t0 < 300


def _stage1(tmp_path, name: str, **kw) -> TrainConfig:
    """Two deterministic epochs in fp32 on 32 px crops: a compiled step must give the eager step's numbers."""
    return _cfg(tmp_path, out_dir=str(tmp_path / name), epochs_deterministic=2, epochs_dropout=0, lr=3e-3,
                crop=32, precision="fp32", calibrate=False, **kw)


def test_compiled_training_matches_eager(tmp_path, capsys):
    """``compile=True`` runs the steps through inductor (a real compile: tens of seconds) and trains the same
    network: per-epoch losses and final weights agree with the eager run's to float32 rounding."""
    from torch._dynamo.utils import counters

    ds = TensorBurstDataset(list(twin_items()))
    eager = Trainer(_stage1(tmp_path, "eager"), ds, ds)
    compiled = Trainer(_stage1(tmp_path, "compiled", compile=True), ds, ds)
    r_eager = eager.fit()
    counters.clear()
    r_comp = compiled.fit()
    assert "torch.compile failed" not in capsys.readouterr().out and not compiled._compile_failed
    assert counters["stats"]["unique_graphs"] >= 1 and compiled._compile_cost[0] > 0  # dynamo did compile the steps
    for a, b in zip(r_eager.history, r_comp.history, strict=True):
        assert b["steps"] == a["steps"] > 0
        assert b["train_total"] == pytest.approx(a["train_total"], rel=1e-4)
        assert b["val_rmse"] == pytest.approx(a["val_rmse"], rel=1e-3, abs=1e-5)
    # the weights moved the same way: Adam divides by the gradient's own size, so where a gradient is near zero
    # float32 rounding moves single weights by a share of a step; the whole update agrees to 1 %
    start = torch.nn.utils.parameters_to_vector(Trainer(_stage1(tmp_path, "start"), ds, ds).model.parameters()).detach()
    w_eager, w_comp = (torch.nn.utils.parameters_to_vector(t.model.parameters()).detach() for t in (eager, compiled))
    assert float((w_comp - w_eager).norm() / (w_eager - start).norm()) < 0.01  # 2e-4 measured


def test_compile_failure_falls_back_to_eager(tmp_path, monkeypatch, capsys):
    """A compiler that fails (no C++ compiler, an operator inductor lacks) costs the run nothing: it says so and
    trains eagerly, to the eager run's numbers."""

    class Broken(torch.nn.Module):
        def forward(self, x):
            raise RuntimeError("InductorError: no working C++ compiler found")

    monkeypatch.setattr(torch, "compile", lambda net, **kw: Broken())
    ds = TensorBurstDataset(list(twin_items()))
    eager = train(_stage1(tmp_path, "eager"), ds, ds)
    trainer = Trainer(_stage1(tmp_path, "fallback", compile=True), ds, ds)
    result = trainer.fit()
    out = capsys.readouterr().out
    assert out.count("torch.compile failed (RuntimeError: InductorError: no working C++ compiler") == 1
    assert trainer._compile_failed
    assert [h["train_total"] for h in result.history] == [h["train_total"] for h in eager.history]


def test_cpu_budget_counts_the_children_a_step_waits_for(tmp_path, monkeypatch):
    """A CPU budget counts work a training step waits for in child processes (the C++ compiler of a compiled
    step), not only this process's threads."""
    ds = TensorBurstDataset(list(twin_items()))
    adam_step, ran = torch.optim.Adam.step, []
    busy = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.4: pass"

    def step_waiting_for_a_child(self, *args, **kwargs):  # as a compiling step waits for its compiler
        if not ran:
            ran.append(subprocess.run([sys.executable, "-c", busy], check=True))
        return adam_step(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.Adam, "step", step_waiting_for_a_child)
    c0 = time.process_time()
    result = train(_stage1(tmp_path, "kids"), ds, ds)
    own = time.process_time() - c0  # this process's CPU over the fit, a little more than the fit counts of it
    assert ran and result.cpu_seconds >= own - 0.1 + 0.4


def test_a_later_stage_compiles_only_with_room_left(tmp_path, capsys):
    """With a deadline or a CPU budget, a stage is compiled only if COMPILE_ROOM x stage 1's compiling step is
    left; else it runs eagerly and says so (a compile must not eat a short dropout stage)."""
    from gearscan.inference.train import COMPILE_ROOM

    ds = TensorBurstDataset(list(twin_items()))
    trainer = Trainer(_stage1(tmp_path, "room", compile=True, deadline=time.time() + 3600), ds, ds)
    assert trainer._compile_room()  # nothing measured yet: stage 1 compiles
    trainer._compile_cost = (3600 / COMPILE_ROOM + 60, 1.0)  # wall: too little of the hour left
    assert not trainer._compile_room()
    trainer._compile_cost = (3600 / COMPILE_ROOM - 60, 1.0)
    assert trainer._compile_room()
    trainer.config.budget_cpu_min = (COMPILE_ROOM * 1.0 - 0.5) / 60  # CPU: less than 3 x 1 CPU s in the budget
    assert not trainer._compile_room()
    trainer.config.budget_cpu_min = None
    trainer._compile_cost = (1e6, 1.0)
    trainer.config.epochs_dropout = 1
    trainer.fit()
    out = capsys.readouterr().out
    assert "compile: stage 1 runs eagerly" in out and "compile: stage 2 runs eagerly" in out
    assert not trainer._compiled and "torch.compile failed" not in out  # nothing was compiled


def test_a_fine_tune_carries_its_inits_support_tests(tmp_path):
    """Every model a fine-tune saves (stage best, checkpoints, last, best) carries its init's ``network_support``,
    marked inherited; an init that names none passes none on (the product's then apply)."""
    from gearscan.inference.model_io import read_config, save_model, write_config
    from gearscan.inference.models import build_model
    from gearscan.inference.predictor import NetworkSupport, model_network_support

    ds = TensorBurstDataset(list(twin_items()))
    init = save_model(build_model(ModelConfig(width=4)), tmp_path / "init.safetensors")
    plain = _cfg(tmp_path, out_dir=str(tmp_path / "plain"), epochs_deterministic=1, epochs_dropout=0, init=str(init),
                 calibrate=False)
    train(plain, ds, ds)
    assert model_network_support(read_config(tmp_path / "plain" / "best.safetensors")) is None
    meta = read_config(init)
    meta["network_support"] = {"per_burst_px": 3, "frame_fit_px": 1, "chosen_by": "val"}
    write_config(init, meta)
    own = _cfg(tmp_path, out_dir=str(tmp_path / "own"), epochs_deterministic=2, epochs_dropout=0, init=str(init),
               calibrate=False, checkpoints_cpu_min=(1e-6,))
    train(own, ds, ds)
    saved = sorted((tmp_path / "own").glob("*.safetensors"))
    assert {p.name for p in saved} >= {"best.safetensors", "last.safetensors", "stage1_best.safetensors",
                                       "cpu_1e-06min.safetensors"}
    for path in saved:
        meta = read_config(path)
        assert model_network_support(meta) == NetworkSupport(3, 1), path.name
        assert meta["network_support"]["chosen_by"].startswith("inherited from the init model"), path.name
    # a resumed run keeps what its saves carried, even if the init's JSON changed since
    meta = read_config(init)
    meta["network_support"] = {"per_burst_px": 5, "frame_fit_px": None}
    write_config(init, meta)
    train(dataclasses.replace(own, epochs_deterministic=3, resume=True), ds, ds)
    assert model_network_support(read_config(tmp_path / "own" / "last.safetensors")) == NetworkSupport(3, 1)
