"""The paper's small training experiments (section 3), as reusable functions.

``gearscan evaluate`` (the report) calls them and scores what they return on its own test bursts:

- :func:`transfer` [Fig. 11]: fine-tune the twin-pretrained model on a target domain vs train the
  same network from Kaiming init, with the same budget (:func:`render_target_datasets` and
  :func:`target_split` make the target domain's data);
- :func:`loss_ablation` [Figs. 15-17]: the loss with the temperature constant and MSE weight vs a
  plain Gaussian NLL, both from Kaiming init (:func:`ablation_split` makes the data).

Each returns one :class:`Run` per variant: the trained predictor, its validation RMSE per epoch
and where its best weights are. Datasets and checkpoints go under the ``work`` folder given.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from torch.utils.data import ConcatDataset, Dataset, Subset

from gearscan.core.gear import GearSpec
from gearscan.inference.losses import LossConfig
from gearscan.inference.models import ModelConfig
from gearscan.inference.predictor import DEFAULT_MODEL, Predictor
from gearscan.inference.train import TrainConfig, train
from gearscan.twin.dataset import DatasetSpec, TwinBurstDataset, generate_dataset

PRETRAINED = "twin-pretrained"
KAIMING = "Kaiming init"
OURS = "with temperature + MSE weight (ours)"
PLAIN_NLL = "plain Gaussian NLL (alpha=1, no MSE)"
LOSS_VARIANTS = {  # the loss ablation's two losses, by the label the report shows
    OURS: LossConfig(alpha=1e-4, mse_weight=1.0, mse_weighting="modulation"),
    PLAIN_NLL: LossConfig(alpha=1.0, mse_weight=0.0),
}
VALIDATION_SAMPLES = 16  # validation items drawn (seeded) from the held-out start points


@dataclass(frozen=True)
class Budget:
    """Training budget of one small run: ``epochs`` of ``steps`` batches of ``batch`` items."""

    epochs: int
    steps: int
    batch: int


@dataclass
class Run:
    """One trained variant: its best-on-validation predictor and validation RMSE per epoch."""

    label: str
    predictor: Predictor
    curve: list[float]
    best_path: Path | None


def train_run(label: str, out_dir: Path, train_set: Dataset, val_set: Dataset, *, model: ModelConfig,
              loss: LossConfig, budget: Budget, lr: float, init: Path | None = None) -> Run:
    """Train ``model`` (deterministic stage only, cosine schedule) and load its best weights."""
    cfg = TrainConfig(
        out_dir=str(out_dir), model=model, loss=loss, epochs_deterministic=budget.epochs, epochs_dropout=0,
        batch_size=budget.batch, lr=lr, schedule="cosine", steps_per_epoch=budget.steps,
        init=str(init) if init is not None else None, progress=False, calibrate=False,
    )
    res = train(cfg, train_set, val_set)
    return Run(label, Predictor.load(res.best_path), [h["val_rmse"] for h in res.history], res.best_path)


def _validation_subset(dataset: Dataset, n: int = VALIDATION_SAMPLES) -> Subset:
    return Subset(dataset, np.random.default_rng(0).choice(len(dataset), n, replace=False).tolist())


# --- transfer learning -------------------------------------------------------------------------
def render_target_datasets(root: Path, scenes: Sequence[tuple], *, points: int, seed: int,
                           poses: int = 18) -> list[Path]:
    """Render a target domain with the dataset protocol, one twin dataset per scene.

    ``scenes``: ``(rig, optics, gear, period_px)`` per scene (the protocol renders default rigs
    otherwise). ``points`` start points per gear; a half-written dataset is rendered again.
    """
    roots = []
    for k, (rig, optics, gear, period_px) in enumerate(scenes):
        d = root / f"target{k}"
        if d.exists() and not (d / "index.json").exists():
            shutil.rmtree(d)
        spec = DatasetSpec(gears=[gear], width=rig.camera.width, height=rig.camera.height, period_px=period_px,
                           max_start_points=points, seed=seed + k, poses=poses)
        generate_dataset(d, spec, scene=(rig, optics, gear, period_px))
        roots.append(d)
    return roots


def target_split(roots: Sequence[Path], crop: int) -> tuple[Dataset, Dataset]:
    """Start point 0 of each target dataset trains (random crops), start point 1 validates."""
    train_set = ConcatDataset([TwinBurstDataset(r, groups=[0], crop=crop, static=True) for r in roots])
    val_set = ConcatDataset([TwinBurstDataset(r, groups=[1], static=True) for r in roots])
    return train_set, _validation_subset(val_set)


def transfer(train_set: Dataset, val_set: Dataset, *, pretrained: Path | None, budget: Budget,
             work: Path) -> dict[str, Run]:
    """Fine-tune ``pretrained`` (default: the shipped model) vs the same network from Kaiming init.

    Same data and budget; fine-tuning at a lower learning rate (5e-4 vs 2e-3). Keys:
    :data:`PRETRAINED`, :data:`KAIMING`.
    """
    pretrained = Path(pretrained) if pretrained is not None else DEFAULT_MODEL
    mcfg = Predictor.load(pretrained).model.config
    loss = LossConfig(mse_weighting="modulation")
    runs = {}
    for label, init in ((PRETRAINED, pretrained), (KAIMING, None)):
        runs[label] = train_run(
            label, work / f"transfer-{label.split()[0].lower()}", train_set, val_set,
            model=ModelConfig(**{**mcfg.to_json(), "dropout": mcfg.dropout}), loss=loss, budget=budget,
            lr=5e-4 if init else 2e-3, init=init,
        )
    return runs


# --- loss ablation -----------------------------------------------------------------------------
def ablation_split(root: Path | None, work: Path, *, size: int, poses: int, crop: int,
                   seed: int) -> tuple[Dataset, Dataset]:
    """Training crops and held-out validation items for the loss ablation.

    ``root``: a twin dataset (its last start point validates); without one (or an incomplete
    one) a small randomised twin set of gears z=16 and z=30 is rendered under ``work``.
    """
    if root is None or not (root / "index.json").exists():
        root = work / "ablation-data"
        spec = DatasetSpec(gears=[GearSpec(teeth=16), GearSpec(teeth=30)], width=size, height=size,
                           randomize=True, max_start_points=1, seed=seed, poses=poses)
        generate_dataset(root, spec)
    n_sp = len(TwinBurstDataset(root).start_points)
    train_set = TwinBurstDataset(root, crop=crop, static=True, groups=list(range(n_sp - 1)))
    val_full = TwinBurstDataset(root, static=True, groups=[n_sp - 1])  # a held-out start point
    return train_set, _validation_subset(val_full)


def loss_ablation(train_set: Dataset, val_set: Dataset, *, model: ModelConfig, budget: Budget,
                  work: Path, variants: dict[str, LossConfig] | None = None) -> dict[str, Run]:
    """Train ``model`` from Kaiming init once per loss (default :data:`LOSS_VARIANTS`)."""
    runs = {}
    for label, loss in (variants or LOSS_VARIANTS).items():
        runs[label] = train_run(label, work / ("ablation-" + label.split()[0]), train_set, val_set,
                                model=ModelConfig(**model.to_json()), loss=loss, budget=budget, lr=2e-3)
    return runs
