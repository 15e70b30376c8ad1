"""Data plumbing for training: the item contract, a group-aware split, small datasets.

Any ``torch.utils.data.Dataset`` works for training if its items are dicts with

- ``"input"``: ``(3, H, W)`` float32 frames in [0, 1] (or ``(C, H, W)`` with extra channels),
- ``"target"``: ``(2, H, W)`` float32 normalised M, D label,
- ``"mask"``: ``(H, W)`` bool valid pixels,
- ``"phase"``: ``(H, W)`` float32 true wrapped phase,
- ``"group"``: int start-point id; items of one group never go to both train and validation.

A dataset may expose ``groups`` (a sequence with one id per item) so the split does not have
to load every item.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

KEYS = ("input", "target", "mask", "phase", "group")


def dataset_groups(dataset: Dataset) -> list[int]:
    """Group id of every item (from ``dataset.groups`` if present, else by loading items)."""
    groups = getattr(dataset, "groups", None)
    if groups is not None:
        return [int(g) for g in groups]
    return [int(dataset[i]["group"]) for i in range(len(dataset))]


def split_by_group(
    groups: Sequence[int], val_fraction: float = 0.2, seed: int = 0
) -> tuple[list[int], list[int]]:
    """Item indices (train, val) with whole groups on one side; at least one group in each.

    ``val_fraction`` is the fraction of *groups* put in validation (rounded, >= 1 group).
    """
    if not 0.0 < val_fraction < 1.0:
        raise ValueError(f"val_fraction: expected in (0, 1), got {val_fraction}")
    unique = sorted(set(int(g) for g in groups))
    if len(unique) < 2:
        raise ValueError(f"split_by_group: need >= 2 distinct groups to split, got {len(unique)}")
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(unique))
    n_val = min(len(unique) - 1, max(1, round(val_fraction * len(unique))))
    val_groups = {unique[i] for i in order[:n_val]}
    train = [i for i, g in enumerate(groups) if int(g) not in val_groups]
    val = [i for i, g in enumerate(groups) if int(g) in val_groups]
    return train, val


def check_item(item: dict, where: str = "dataset item") -> None:
    """Validate one item against the contract above (shapes and dtypes)."""
    missing = [k for k in KEYS if k not in item]
    if missing:
        raise ValueError(f"{where}: missing keys {missing} (expected {list(KEYS)})")
    x, t, m = item["input"], item["target"], item["mask"]
    if x.ndim != 3 or x.shape[0] < 3:
        raise ValueError(f"{where}: input expected (C>=3, H, W), got {tuple(x.shape)}")
    if tuple(t.shape) != (2, *x.shape[1:]):
        raise ValueError(f"{where}: target expected {(2, *x.shape[1:])}, got {tuple(t.shape)}")
    if tuple(m.shape) != tuple(x.shape[1:]):
        raise ValueError(f"{where}: mask expected {tuple(x.shape[1:])}, got {tuple(m.shape)}")


class TensorBurstDataset(Dataset):
    """In-memory dataset of items following the contract (tensors built once)."""

    def __init__(self, items: list[dict]) -> None:
        self.items = []
        for i, it in enumerate(items):
            check_item(it, f"item {i}")
            self.items.append(
                {
                    "input": torch.as_tensor(np.asarray(it["input"], dtype=np.float32)),
                    "target": torch.as_tensor(np.asarray(it["target"], dtype=np.float32)),
                    "mask": torch.as_tensor(np.asarray(it["mask"], dtype=bool)),
                    "phase": torch.as_tensor(np.asarray(it["phase"], dtype=np.float32)),
                    "group": int(it["group"]),
                }
            )
        self.groups = [it["group"] for it in self.items]

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        return self.items[i]


class NpzBurstDataset(TensorBurstDataset):
    """Items stored one per ``.npz`` file (keys of the contract) in a folder, sorted by name."""

    def __init__(self, folder: str | Path) -> None:
        folder = Path(folder)
        files = sorted(folder.glob("*.npz"))
        if not files:
            raise FileNotFoundError(f"no .npz items in {folder}")
        items = []
        for f in files:
            with np.load(f) as z:
                missing = [k for k in KEYS if k not in z.files]
                if missing:
                    raise ValueError(f"{f}: missing arrays {missing} (expected {list(KEYS)})")
                items.append({k: z[k] for k in KEYS})
        super().__init__(items)

    @staticmethod
    def write(items: list[dict], folder: str | Path) -> list[Path]:
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        paths = []
        for i, it in enumerate(items):
            p = folder / f"item_{i:06d}.npz"
            np.savez_compressed(p, **{k: np.asarray(it[k]) for k in KEYS})
            paths.append(p)
        return paths


class _ExtraChannels(Dataset):
    """A dataset whose items' ``"input"`` gets more channels, computed per item by :meth:`channels`.
    ``groups`` passes through, so group-aware splits still work."""

    def __init__(self, dataset: Dataset) -> None:
        self.dataset = dataset

    def __len__(self) -> int:
        return len(self.dataset)  # type: ignore[arg-type]

    @property
    def groups(self) -> Sequence[int] | None:
        return getattr(self.dataset, "groups", None)

    def channels(self, item: dict, i: int, height: int, width: int) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def __getitem__(self, i: int) -> dict:
        item = dict(self.dataset[i])
        inp = np.asarray(item["input"], dtype=np.float32)
        item["input"] = np.concatenate([inp, self.channels(item, i, *inp.shape[1:])])
        return item


class MotionInput(_ExtraChannels):
    """Appends :func:`~gearscan.inference.models.motion_channels` of each item's ``"angles"``
    (the three frames' turntable angles, rad) to its ``"input"``: what a ``motion_input``
    network is fed."""

    def channels(self, item: dict, i: int, height: int, width: int) -> np.ndarray:
        from gearscan.inference.models import motion_channels

        if "angles" not in item:
            raise KeyError(f"item {i}: a motion-input network needs the burst's 'angles' (rad); this dataset has none")
        return motion_channels(item["angles"], height, width)


class PriorInput(_ExtraChannels):
    """Appends :func:`~gearscan.inference.models.prior_channels` of each item's ``prior_change``,
    ``prior_ratio`` and ``prior_known`` (``TwinBurstDataset(prior=True)``) to its ``"input"``:
    what a ``prior_input`` network is fed. Wrap after :class:`MotionInput` (channel order)."""

    def channels(self, item: dict, i: int, height: int, width: int) -> np.ndarray:
        from gearscan.inference.models import prior_channels

        missing = [k for k in ("prior_change", "prior_ratio", "prior_known") if k not in item]
        if missing:
            raise KeyError(f"item {i}: a prior-input network needs the twin's prediction {missing}; "
                           "render items with TwinBurstDataset(prior=True)")
        return prior_channels(item["prior_change"], item["prior_ratio"], item["prior_known"])
