"""BurstBank: training bursts cut on the training device are exactly the twin datasets' items, drawn uniformly;
a Trainer drawing from it trains, and a wall-clock budget stops it."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest
import torch
from torch.utils.data import ConcatDataset

from gearscan.core.gear import GearSpec
from gearscan.inference.burst_bank import BurstBank, bank_bytes, twin_parts
from gearscan.inference.losses import LossConfig
from gearscan.inference.models import ModelConfig
from gearscan.inference.train import TrainConfig, train
from gearscan.twin.dataset import DatasetError, DatasetSpec, TwinBurstDataset, generate_dataset

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """Two small twin folders (other gears, views, seeds and bit depths), 6 poses of 64x64 px."""
    roots = []
    for i, (teeth, depth) in enumerate(((18, 8), (26, 12))):
        root = tmp_path_factory.mktemp(f"bank{i}")
        spec = DatasetSpec(gears=[GearSpec(teeth=teeth)], width=64, height=64, poses=6, max_start_points=2,
                           randomize=True, views=True, seed=40 + i)
        generate_dataset(root, spec)
        if depth != 8:  # a 12-bit camera: the bank must keep its raw counts exactly and scale by 4095
            index = json.loads((root / "index.json").read_text())
            for e in index["entries"]:
                e["optics"]["bit_depth"] = depth
                images = np.load(root / e["id"] / "images.npy")
                np.save(root / e["id"] / "images.npy", images.astype(np.uint16) * 16 + 7)
            (root / "index.json").write_text(json.dumps(index))
        roots.append(root)
    return roots


def _parts(roots, crop, **kw):
    return [TwinBurstDataset(r, crop=crop, static=True, static_repeat=3, reverse=True, **kw) for r in roots]


def test_bank_items_are_the_datasets_items(folders):
    full = ConcatDataset(_parts(folders, None))
    bank = BurstBank(_parts(folders, 32))
    assert len(bank) == len(full) and bank.frames.dtype == torch.int32  # the 12-bit folder widens the raw store
    assert bank.nbytes == bank_bytes(_parts(folders, 32))
    rng = np.random.default_rng(3)
    rows = rng.integers(0, len(full), 40)
    rows[:2] = (0, len(full) - 1)
    tops, lefts = rng.integers(0, 64 - 32 + 1, (2, len(rows)))
    got = bank.items(torch.as_tensor(rows), torch.as_tensor(tops), torch.as_tensor(lefts))
    assert got["input"].shape == (len(rows), 3, 32, 32) and got["input"].dtype == torch.float32
    for n, (r, y, x) in enumerate(zip(rows, tops, lefts, strict=True)):
        item, sl = full[int(r)], (slice(y, y + 32), slice(x, x + 32))
        # exact: the same raw counts over the same full scale, the label and mask at the burst's first pose
        assert torch.equal(got["input"][n], torch.from_numpy(item["input"][:, sl[0], sl[1]])), r
        assert torch.equal(got["target"][n], torch.from_numpy(item["target"][:, sl[0], sl[1]])), r
        assert torch.equal(got["mask"][n], torch.from_numpy(item["mask"][sl])), r
    # an 8-bit folder alone keeps its frames as uint8, and whole images (no crop) come back whole
    small = BurstBank(_parts(folders[:1], None))
    one = ConcatDataset(_parts(folders[:1], None))
    assert small.frames.dtype == torch.uint8
    rows = torch.as_tensor([0, 7, len(one) - 1])
    got = small.items(rows, torch.zeros(3, dtype=torch.long), torch.zeros(3, dtype=torch.long))
    for n, r in enumerate(rows.tolist()):
        assert torch.equal(got["input"][n], torch.from_numpy(one[r]["input"]))
        assert torch.equal(got["target"][n], torch.from_numpy(one[r]["target"]))


def test_draws_are_uniform_over_items_and_crops(folders):
    parts = _parts(folders, 16)
    bank = BurstBank(parts)
    n = 20_000
    batch = bank.draw(n, torch.Generator().manual_seed(0))
    assert batch["input"].shape == (n, 3, 16, 16) and batch["mask"].shape == (n, 16, 16)
    # a draw is uniform item rows, then uniform crop corners, from the one generator
    gen = torch.Generator().manual_seed(0)
    rows = torch.randint(0, len(bank), (n,), generator=gen)
    top, left = (torch.randint(0, 64 - 16 + 1, (n,), generator=gen) for _ in range(2))
    assert torch.equal(batch["input"], bank.items(rows, top, left)["input"])
    assert {int(top.min()), int(top.max()), int(left.min()), int(left.max())} == {0, 48}  # edges reached
    # so still bursts (poses i = j = k, repeated) come up as often as in the datasets
    r = bank.rows[rows]
    still = ((r[:, 1] == r[:, 2]) & (r[:, 2] == r[:, 3])).float().mean().item()
    expect = sum(sum(c[0] == c[2] for c in p.combos) * len(p.start_points) for p in parts) / len(bank)
    assert abs(still - expect) < 4 * math.sqrt(expect * (1 - expect) / n)
    full = BurstBank(_parts(folders, None))  # no crop: whole images
    assert full.draw(2, gen)["input"].shape == (2, 3, 64, 64)
    # a crop of its own (the trainer's): each item cut at its own corner from the same rows
    own = BurstBank(_parts(folders, None), crop=16)
    assert torch.equal(own.draw(n, torch.Generator().manual_seed(0))["input"], batch["input"])


def test_bank_refuses_what_it_cannot_serve(folders):
    with pytest.raises(DatasetError, match="one bank holds one shape"):
        BurstBank([*_parts(folders[:1], 32), *_parts(folders[1:], 16)])
    with pytest.raises(DatasetError, match="prior inputs are built per item"):
        BurstBank(_parts(folders, 32, prior=True))
    with pytest.raises(DatasetError, match="crop: expected 16..64 px, got 8"):
        BurstBank(_parts(folders, None), crop=8)
    with pytest.raises(DatasetError, match="at least one twin dataset"):
        BurstBank([])
    with pytest.raises(DatasetError, match="expected twin dataset folders"):
        twin_parts(ConcatDataset([_parts(folders, 32)[0], [1, 2]]))
    with pytest.raises(ValueError, match="expected a val_set"):
        train(TrainConfig(out_dir="unused", bank=True, progress=False), ConcatDataset(_parts(folders, 32)))
    with pytest.raises(ValueError, match="deadline: expected a wall-clock time"):
        TrainConfig(deadline=0)


def test_training_from_the_bank_learns_and_a_wall_budget_stops_it(folders, tmp_path):
    train_set = ConcatDataset(_parts(folders, 32))
    whole = ConcatDataset(_parts(folders, None))
    val_set = torch.utils.data.Subset(whole, list(range(0, len(whole), len(whole) // 10)))
    cfg = TrainConfig(out_dir=str(tmp_path / "bank"), model=ModelConfig(width=4), loss=LossConfig(),
                      batch_size=8, lr=3e-3, epochs_deterministic=6, epochs_dropout=1, steps_per_epoch=15,
                      schedule="constant", patience=100, bank=True, progress=False, calibrate=False)
    result = train(cfg, train_set, val_set)
    hist = result.history
    assert [h["stage"] for h in hist] == [1] * 6 + [2]
    assert all(h["steps"] == 15 for h in hist)
    assert min(h["val_loss"] for h in hist[1:]) < 0.7 * hist[0]["val_loss"]  # it learns from the drawn bursts
    # a deadline ends the run, keeping room for its closing validation; the dropout stage keeps its share of the
    # time (1 epoch of 4) although one deterministic epoch alone (100 000 steps) would run far past it
    deadline = time.time() + 6.0
    cfg = TrainConfig(**{**cfg.__dict__, "out_dir": str(tmp_path / "wall"), "epochs_deterministic": 3,
                         "epochs_dropout": 1, "steps_per_epoch": 100_000, "deadline": deadline})
    result = train(cfg, train_set, val_set)
    assert result.budget_hit and time.time() < deadline + 3.0 and result.best_path.is_file()
    assert {h["stage"] for h in result.history} == {1, 2} and all(h["steps"] < 100_000 for h in result.history)
