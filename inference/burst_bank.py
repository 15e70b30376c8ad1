"""Training bursts drawn on the training device: the pose stacks held there as tensors, batches cut by gathers.

A :class:`~gearscan.twin.dataset.TwinBurstDataset` item is three frames picked from one start point's
rendered poses and a crop of them. Built in DataLoader workers, each item travels to the device as about
0.5 MB at 128x128 (input, label, mask, phase, analytic M, D). :class:`BurstBank` holds only what training reads
(the three patterns of every pose, the 18-step label, the mask: about 14 MB per 256x256 start point) on the
device and draws whole batches there with one gather each, so a GPU step waits on no worker and no copy
(whether the workers or the per-operator overhead set session 22's 58 ms steps is what
``benchmarks/train_step_profile.py`` measures). Items are the datasets' own (the same bursts, still
repeats and reversals, the same crop rule), drawn uniformly with replacement rather than in epoch
permutations; validation still goes through the datasets. On a CPU it is no faster than the DataLoader
(``benchmarks/train_step_profile.md``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch.utils.data import ConcatDataset, Dataset

from gearscan.twin.dataset import DatasetError, TwinBurstDataset


def twin_parts(train_set: Dataset) -> list[TwinBurstDataset]:
    """The twin dataset folders behind a train set (one, or a ConcatDataset of them)."""
    parts = train_set.datasets if isinstance(train_set, ConcatDataset) else [train_set]
    wrong = [type(p).__name__ for p in parts if not isinstance(p, TwinBurstDataset)]
    if wrong:
        raise DatasetError(f"bank: expected twin dataset folders (TwinBurstDataset, or a ConcatDataset of them), "
                           f"got {', '.join(sorted(set(wrong)))}")
    return list(parts)


class BurstBank:
    """The training items of ``datasets`` (one crop size and image size), kept as tensors on one device; ``crop``
    (px) replaces the datasets' own crop (None: theirs)."""

    def __init__(self, datasets: Sequence[TwinBurstDataset], device: str | torch.device = "cpu",
                 crop: int | None = None) -> None:
        if not datasets:
            raise DatasetError("BurstBank: expected at least one twin dataset, got none")
        first = datasets[0]
        shape = (first.spec.poses, first.spec.height, first.spec.width)
        for ds in datasets:
            if not isinstance(ds, TwinBurstDataset):
                raise DatasetError(f"BurstBank: expected TwinBurstDataset folders, got {type(ds).__name__}")
            here = (ds.spec.poses, ds.spec.height, ds.spec.width)
            if here != shape or ds.crop != first.crop:
                raise DatasetError(f"BurstBank {ds.root}: poses x height x width {here}, crop {ds.crop}; expected "
                                   f"{shape}, crop {first.crop} as in {first.root} (one bank holds one shape)")
            if ds.prior:
                raise DatasetError(f"BurstBank {ds.root}: prior inputs are built per item; train them through "
                                   "the DataLoader")
        self.device = torch.device(device)
        self.crop = first.crop if crop is None else int(crop)
        self.height, self.width = shape[1:]
        if self.crop is not None and not 16 <= self.crop <= min(self.height, self.width):
            raise DatasetError(f"BurstBank crop: expected 16..{min(self.height, self.width)} px, got {self.crop}")
        points = [(ds, g) for ds in datasets for g in ds.start_points]
        deep = any(ds.full_scale(g) > 255 for ds, g in points)
        n, (poses, h, w) = len(points), shape
        dev = self.device
        # filled one start point at a time: no host copy of the whole bank
        self.frames = torch.empty((n, poses, 3, h, w), dtype=torch.int32 if deep else torch.uint8, device=dev)
        self.label = torch.empty((n, poses, 2, h, w), dtype=torch.float32, device=dev)
        self.mask = torch.empty((n, poses, h, w), dtype=torch.bool, device=dev)
        self.scale = torch.tensor([ds.full_scale(g) for ds, g in points], dtype=torch.float32, device=dev)
        rows = []
        for s, (ds, g) in enumerate(points):
            stack = ds.pose_stack(g)
            if not deep and stack["frames"].dtype != np.uint8:
                raise DatasetError(f"BurstBank {ds.root} start point {g}: {stack['frames'].dtype} frames of an 8-bit "
                                   "camera (expected uint8)")
            raw = stack["frames"].astype(np.int32) if deep else stack["frames"]  # torch gathers no uint16
            self.frames[s].copy_(torch.from_numpy(raw))
            self.label[s].copy_(torch.from_numpy(stack["label"]))
            self.mask[s].copy_(torch.from_numpy(stack["mask"]))
            combos = torch.tensor(ds.combos, dtype=torch.int32)
            rows.append(torch.cat([torch.full((len(combos), 1), s, dtype=torch.int32), combos], dim=1))
        self.rows = torch.cat(rows).to(dev)  # (items, 4): start point, poses i, j, k (the label's pose is i)

    def __len__(self) -> int:
        return int(self.rows.shape[0])

    @property
    def nbytes(self) -> int:
        """Device memory the bank holds."""
        return sum(t.numel() * t.element_size() for t in (self.frames, self.label, self.mask, self.scale, self.rows))

    def items(self, rows: torch.Tensor, top: torch.Tensor, left: torch.Tensor) -> dict[str, torch.Tensor]:
        """The items at item indices ``rows`` cropped at ``top``, ``left`` (ignored without a crop): ``input``
        (n, 3, c, c) float32 in [0, 1], ``target`` (n, 2, c, c), ``mask`` (n, c, c)."""
        r = self.rows[rows].long()
        s, poses = r[:, 0], r[:, 1:]
        if self.crop is None:
            ys = torch.arange(self.height, device=self.device).expand(len(r), -1)
            xs = torch.arange(self.width, device=self.device).expand(len(r), -1)
        else:
            span = torch.arange(self.crop, device=self.device)
            ys, xs = top[:, None] + span, left[:, None] + span
        y, x = ys[:, None, :, None], xs[:, None, None, :]
        three = torch.arange(3, device=self.device)[None, :, None, None]
        frames = self.frames[s[:, None, None, None], poses[:, :, None, None], three, y, x]
        two = torch.arange(2, device=self.device)[None, :, None, None]
        first = poses[:, :1, None, None]
        return {
            "input": frames.float() / self.scale[s][:, None, None, None],
            "target": self.label[s[:, None, None, None], first, two, y, x],
            "mask": self.mask[s[:, None, None], first[:, 0], y[:, 0], x[:, 0]],
        }

    def draw(self, n: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """``n`` items drawn uniformly with replacement, each at a uniform crop position (``generator`` on
        the bank's device)."""
        rows = torch.randint(0, len(self), (n,), generator=generator, device=self.device)
        top = left = torch.zeros(n, dtype=torch.long, device=self.device)
        if self.crop is not None:
            top = torch.randint(0, self.height - self.crop + 1, (n,), generator=generator, device=self.device)
            left = torch.randint(0, self.width - self.crop + 1, (n,), generator=generator, device=self.device)
        return self.items(rows, top, left)


def bank_bytes(datasets: Sequence[TwinBurstDataset]) -> int:
    """Bytes a :class:`BurstBank` of ``datasets`` would hold, from their indexes alone (to check it fits first)."""
    points = [(ds, g) for ds in datasets for g in ds.start_points]
    raw = 4 if any(ds.full_scale(g) > 255 for ds, g in points) else 1  # a deeper camera widens the whole store
    pixels = sum(ds.spec.poses * ds.spec.height * ds.spec.width for ds, _ in points)
    return int(pixels * (3 * raw + 2 * 4 + 1) + 4 * len(points) + 16 * sum(len(ds) for ds in datasets))
