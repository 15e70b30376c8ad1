"""Learning-rate schedule of each training stage, built on torch's schedulers (not hand-written)."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING

import torch
from torch.optim.lr_scheduler import CosineAnnealingLR, LambdaLR, LRScheduler, StepLR

if TYPE_CHECKING:
    from gearscan.inference.train import TrainConfig

SCHEDULES = ("step", "cosine", "constant", "cosine-time")
TIMED_SCHEDULES = ("cosine-time",)  # anneal over the stage's time (CPU budget or deadline), not its epochs


def stage_lr(config: TrainConfig, stage: int) -> float:
    """First-epoch (peak) learning rate of a stage: ``lr``, or ``lr_dropout`` in stage 2 if set."""
    return config.lr if stage == 1 or config.lr_dropout is None else config.lr_dropout


def build_scheduler(
    optimizer: torch.optim.Optimizer,
    config: TrainConfig,
    stage: int,
    stage_epochs: int,
    epoch: int = 0,
    progress: Callable[[], float] | None = None,
) -> LRScheduler:
    """The schedule of one training stage, restarted at :func:`stage_lr` and stepped once per epoch.

    ``step``: x ``gamma`` every ``step_every`` epochs (``StepLR``); ``cosine``:
    ``0.5*lr*(1 + cos(pi*e/stage_epochs))`` (``CosineAnnealingLR``); ``constant``: ``lr``;
    ``cosine-time``: ``0.5*lr*(1 + cos(pi*f))`` with ``f = progress()`` the share of the stage's time spent (0-1),
    so a run stopped by a CPU budget or a deadline ends annealed, however many epochs that time held.
    Sets the optimizer's learning rates to those of epoch ``epoch`` (0-based within the stage;
    > 0 when resuming), replaying the schedule from the stage's start so that a resumed run gets
    the same rates as an uninterrupted one (``cosine-time``: its CPU budget's share carries over; a deadline is
    the resumed run's own, so its share starts again).
    """
    base = stage_lr(config, stage)
    for group in optimizer.param_groups:  # a new stage restarts from its own peak
        group["lr"] = group["initial_lr"] = base
    scheduler: LRScheduler
    if config.schedule == "step":
        scheduler = StepLR(optimizer, step_size=config.step_every, gamma=config.gamma)
    elif config.schedule == "cosine":
        scheduler = CosineAnnealingLR(optimizer, T_max=max(1, stage_epochs))
    elif config.schedule == "constant":
        scheduler = LambdaLR(optimizer, lambda _: 1.0)
    elif config.schedule == "cosine-time":
        if progress is None:
            raise ValueError("schedule 'cosine-time': expected progress (the share of the stage's time spent)")
        scheduler = LambdaLR(optimizer, lambda _: 0.5 * (1.0 + math.cos(math.pi * min(1.0, max(0.0, progress())))))
    else:
        raise ValueError(f"schedule: expected one of {SCHEDULES}, got {config.schedule!r}")
    with warnings.catch_warnings():  # replayed epochs were trained before: no optimizer step now
        warnings.filterwarnings("ignore", "Detected call of `lr_scheduler.step", UserWarning)
        for _ in range(epoch):
            scheduler.step()
    return scheduler
