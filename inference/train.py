"""Training loop (paper §3.3): deterministic stage, then Concrete Dropout stage.

- Stage 1 trains with every Concrete Dropout mask off and without the regulariser (the
  dropout rates get no gradient); stage 2 turns the masks and the regulariser on, starting
  from the best stage-1 weights. Models without dropout (the peers) run stage 1 only.
- Adam, learning rate ``lr`` with a schedule restarted per stage: ``step`` (x ``gamma`` every
  ``step_every`` epochs; paper: 1e-3, x0.9 every 20), ``cosine``, ``constant`` or ``cosine-time`` (a cosine
  over the stage's time, the CPU budget's or the deadline's, for a run whose epochs the time decides); torch's
  schedulers, stepped once per epoch (:mod:`gearscan.inference.lr_schedule`).
- Early stopping per stage after ``patience`` epochs without validation improvement. The
  validation score is ``alpha*NLL + mse_weight*MSE`` in deterministic mode (no regulariser), so
  it compares across stages; ``val_objective="full"`` adds the loss's outside-mask term, so that a
  run trained with it is stopped on what it is trained for (with an outside term, every row keeps
  ``val_inside_loss`` and ``val_outside`` apart). A resumed run must read the same objective.
- Split by ``group``: no start point in both train and validation.
- Output folder: ``best.safetensors/.json`` (a Predictor-ready model, with the fitted variance
  scale and the per-mode sigma calibration of :mod:`gearscan.inference.uncertainty`), ``last.*`` + ``last_optim.pt`` (resume), ``metrics.csv``, ``metrics.json``,
  ``loss_curve.png``, ``reliability.png``.
- ``init``: start from pre-trained weights (transfer learning: pre-train on twin, fine-tune). Every model the run
  saves carries the init's fringe-support tests (``network_support``), marked inherited (:func:`inherited_meta`).
  The initial weights are validated first (row ``epoch 0``), so the best-on-val weights are
  never worse on val than the ones fine-tuning started from.
- ``budget_cpu_min``: stop cleanly when this process has used that many CPU minutes
  (``time.process_time()``: all its threads, plus the child processes a training step waited for, such as the
  compiler of a compiled step; so other load on shared cores does not eat the budget; training steps stop early
  enough to leave room for the last validation), keeping
  the best-on-val weights. ``checkpoints_cpu_min``: at the first validation past each mark,
  the best-on-val weights so far are saved as ``cpu_<m>min.safetensors`` (a 10-minute budget's
  result, read off a longer run with a constant schedule). Every metrics row has ``cpu_min``.
- ``deadline``: the same stop at a wall-clock time (Unix seconds; a lent GPU machine's command has a hard
  limit, and the process's own start counts against it). With a dropout stage to run, the deterministic stage
  stops at its share of the time left when ``fit()`` began (its epochs over all epochs), so the dropout stage
  always runs. Distributed ranks stop together (the stop is all-reduced).
- ``bank``: draw the training bursts on the training device (:class:`~gearscan.inference.burst_bank.BurstBank`;
  the train set must be twin dataset folders) instead of through DataLoader workers, so a GPU step waits on
  no worker and no per-item copy.
- ``average_from``: from this share of a stage on (of its CPU budget or deadline when it has one, else of its
  epochs), the weights after every epoch are averaged (stochastic weight averaging: ``AveragedModel``, BatchNorm
  buffers averaged too). At the stage's end the average is validated like an epoch and kept only if it beats the
  stage's best epoch on val. A resumed run restarts the average.
- ``compile``: the training step's network runs through ``torch.compile`` (inductor: fused kernels, 202
  operator calls a step instead of 843). On an AMX CPU the profile's synthetic w = 8 step took 1.5x less time
  (``benchmarks/train_step_profile.md``), but a real 30-CPU-minute fine-tune only 1.16x per step and made 1.07x
  the steps (loss, data and validation stay eager; ``benchmarks/adaptation_compile_rule.md``). Where a step is
  bound by operator dispatch it may pay more; the GPU lease measures that. Validation and calibration stay eager,
  on the same weights. Compiling costs tens of seconds per stage (the dropout stage's graph is another), and,
  under a CPU budget, runs in this process so that the budget counts it. With a deadline or budget, a later stage
  is compiled only if at least ``COMPILE_ROOM`` times stage 1's compiling step is left, else it runs eagerly. If a
  stage's first compiled step fails (no C++ compiler, an operator inductor lacks), training goes on eagerly and
  says so; on more than one process (DDP) it stops instead, since the ranks could not agree to fall back together.
- No host sync per training step (the progress bar's loss is read every ``PROGRESS_EVERY`` steps), so
  the host queues work ahead of a GPU.
- DDP: launched with ``torchrun`` (env ``WORLD_SIZE`` > 1), gloo on CPU, nccl on CUDA; rank 0
  writes files; validation sums are all-reduced so every rank takes the same decisions
  (:mod:`gearscan.inference.distributed`).

Resuming restores weights, optimizer, stage, epoch, best score and history, and rebuilds the
stage's learning-rate schedule at that epoch (not the data order's RNG state, so a resumed run is
statistically, not bitwise, the same).
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import resource
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from torch.utils.data import DataLoader, Dataset, Subset

from gearscan.inference.concrete_dropout import (
    concrete_layers,
    dropout_rates,
    reset_dropout_rates,
    set_stochastic,
)
from gearscan.inference.data import dataset_groups, split_by_group
from gearscan.inference.distributed import (
    Dist,
    all_reduce_sum,
    barrier,
    init_distributed,
    resolve_device,
)
from gearscan.inference.losses import LossConfig, PhaseLoss
from gearscan.inference.lr_schedule import SCHEDULES, TIMED_SCHEDULES, build_scheduler
from gearscan.inference.model_io import load_into, load_state, read_config, save_model, widen_inputs
from gearscan.inference.models import ModelConfig, PhaseNet, build_model
from gearscan.inference.plots import plot_history

VAL_OBJECTIVES = ("inside", "full")
PROGRESS_EVERY = 25  # steps between the progress bar's loss read-outs (each is a host sync on a GPU)
BANK_SHARE = 0.6  # of the GPU's free memory a BurstBank may take (the network's activations need the rest)


COMPILE_ROOM = 3.0  # a later stage compiles only with this many times stage 1's compiling step left (deadline, budget)


def children_cpu_seconds() -> float:
    """CPU seconds of the child processes this process has waited for (such as the C++ compiler that
    ``torch.compile`` runs)."""
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return kids.ru_utime + kids.ru_stime


def _running_mean(averaged: torch.Tensor, current: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """The weight average's update: the running mean of float tensors; an integer buffer (BatchNorm's batch count)
    takes the current value, since torch's own averaging divides it, which CUDA refuses."""
    if not averaged.is_floating_point():
        return current
    return averaged + (current - averaged) / (n.to(averaged.dtype) + 1)


def validation_row(inside: float, outside: float, rmse: float, loss: LossConfig, objective: str) -> dict:
    """A validation row: ``val_loss`` is what early stopping reads (the inside-mask loss, plus ``outside_weight``
    x the outside-mask error for the "full" objective); with an outside term both parts are kept apart."""
    row = {"val_loss": inside, "val_rmse": rmse}
    if loss.outside_weight > 0:
        row["val_inside_loss"], row["val_outside"] = inside, outside
        if objective == "full":
            row["val_loss"] = inside + loss.outside_weight * outside
    return row


@dataclass
class TrainConfig:
    out_dir: str = "runs/cd-dcu-net"
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    epochs_deterministic: int = 50
    epochs_dropout: int = 50
    batch_size: int = 16
    lr: float = 1e-3
    lr_dropout: float | None = None  # peak learning rate of stage 2 (default: lr)
    schedule: str = "step"
    step_every: int = 20
    gamma: float = 0.9
    patience: int = 10
    val_fraction: float = 0.2
    crop: int | None = None  # random square crop per batch (multiple of 16 recommended)
    steps_per_epoch: int | None = None  # cap on batches per epoch
    device: str = "auto"
    precision: str = "auto"  # autocast: "auto" = bf16 on CUDA and on CPUs with AMX, else fp32
    num_workers: int = 0
    seed: int = 0
    init: str | None = None
    reset_dropout: bool = False  # after ``init``: re-draw dropout rates from the model config's range
    widen_inputs: bool = False  # ``init`` has fewer input channels: add the new ones zero-initialised
    resume: bool = False
    progress: bool = True
    calibrate: bool = True
    calibrate_mc: int = 20  # MC passes for the MC-mode sigma calibration (0: deterministic only)
    budget_cpu_min: float | None = None  # stop at this many CPU minutes of this process (threads, a step's children)
    deadline: float | None = None  # stop by this wall-clock time (Unix seconds, time.time())
    bank: bool = False  # draw training bursts on the device (BurstBank) instead of DataLoader workers
    compile: bool = False  # torch.compile the training step's network (eager again, with a message, if it fails)
    average_from: float | None = None  # average every epoch's weights from this share of a stage on (kept if better)
    checkpoints_cpu_min: tuple[float, ...] = ()  # save the best-on-val weights so far at these CPU minutes
    # what early stopping reads: "inside" (the truth mask only; every model so far) or "full" (the trained
    # objective, with the loss's ``outside_weight`` term, which "full" requires)
    val_objective: str = "inside"

    def __post_init__(self) -> None:
        if isinstance(self.model, dict):
            self.model = ModelConfig.from_json(self.model)
        if isinstance(self.loss, dict):
            self.loss = LossConfig(**self.loss)
        if self.schedule not in SCHEDULES:
            raise ValueError(f"schedule: expected one of {SCHEDULES}, got {self.schedule!r}")
        if self.schedule in TIMED_SCHEDULES and self.budget_cpu_min is None and self.deadline is None:
            raise ValueError(f"schedule {self.schedule!r}: expected budget_cpu_min or deadline (the time it anneals "
                             "over)")
        for name in ("batch_size", "step_every", "patience"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1, got {getattr(self, name)}")
        if self.epochs_deterministic < 0 or self.epochs_dropout < 0:
            raise ValueError(
                f"epochs: expected >= 0, got {self.epochs_deterministic}, {self.epochs_dropout}"
            )
        if self.lr <= 0:
            raise ValueError(f"lr: expected > 0, got {self.lr}")
        if self.budget_cpu_min is not None and not self.budget_cpu_min > 0:
            raise ValueError(f"budget_cpu_min: expected > 0 CPU minutes, got {self.budget_cpu_min}")
        if self.deadline is not None and not self.deadline > 0:
            raise ValueError(f"deadline: expected a wall-clock time in Unix seconds, got {self.deadline}")
        self.checkpoints_cpu_min = tuple(sorted(float(m) for m in self.checkpoints_cpu_min))
        if any(not m > 0 for m in self.checkpoints_cpu_min):
            raise ValueError(f"checkpoints_cpu_min: expected CPU minutes > 0, got {self.checkpoints_cpu_min}")
        if self.average_from is not None and not 0.0 <= self.average_from < 1.0:
            raise ValueError(f"average_from: expected a share of the stage in [0, 1), got {self.average_from}")
        if self.val_objective not in VAL_OBJECTIVES:
            raise ValueError(f"val_objective: expected one of {VAL_OBJECTIVES}, got {self.val_objective!r}")
        if self.val_objective == "full" and not self.loss.outside_weight > 0:
            raise ValueError("val_objective 'full': expected loss.outside_weight > 0 (without it 'full' is 'inside')")
        from gearscan.inference.predictor import PRECISIONS

        if self.precision not in PRECISIONS:
            raise ValueError(f"precision: expected one of {PRECISIONS}, got {self.precision!r}")

    def to_json(self) -> dict:
        d = asdict(self)
        d["model"] = self.model.to_json()
        d["loss"] = self.loss.to_json()
        return d


# --- the loop -------------------------------------------------------------------------------------
@dataclass
class TrainResult:
    best_path: Path | None
    history: list[dict]
    best_val: float
    var_scale: float
    seconds: float
    cpu_seconds: float = 0.0  # CPU time of this process over the whole fit (all threads)
    budget_hit: bool = False


def _crop(batch: dict, size: int | None, gen: torch.Generator) -> dict:
    if size is None:
        return batch
    h, w = batch["input"].shape[-2:]
    if size > h or size > w:
        return batch
    top = int(torch.randint(0, h - size + 1, (1,), generator=gen))
    left = int(torch.randint(0, w - size + 1, (1,), generator=gen))
    out = dict(batch)
    for k in ("input", "target", "mask", "phase"):
        if k in batch:  # a BurstBank batch has no phase
            out[k] = batch[k][..., top : top + size, left : left + size]
    return out


def _wrapped_sq_err(
    pred: torch.Tensor, phase: torch.Tensor, mask: torch.Tensor
) -> tuple[float, float]:
    est = torch.atan2(pred[:, 0], pred[:, 1])
    err = torch.remainder(est - phase + math.pi, 2 * math.pi) - math.pi
    m = mask.bool()
    return float((err[m] ** 2).sum()), float(m.sum())


class Trainer:
    """Holds model, optimizer and state; ``fit()`` runs both stages. Use :func:`train`."""

    def __init__(
        self, config: TrainConfig, train_set: Dataset, val_set: Dataset | None = None
    ) -> None:
        self.config = config
        self.device = resolve_device(config.device, Dist())
        self.dist = init_distributed(self.device.type)
        self.device = resolve_device(config.device, self.dist)
        from gearscan.inference.predictor import resolve_precision

        self.precision = resolve_precision(config.precision, self.device, training=True)  # bf16 on CPUs with AMX
        torch.manual_seed(config.seed + self.dist.rank)
        if val_set is None:
            if config.bank:
                raise ValueError("bank: expected a val_set (a bank draws from whole folders, not a group split)")
            tr, va = split_by_group(dataset_groups(train_set), config.val_fraction, config.seed)
            train_set, val_set = Subset(train_set, tr), Subset(train_set, va)
        self.train_set, self.val_set = train_set, val_set
        self.bank = None
        if config.bank:
            from gearscan.inference.burst_bank import BurstBank, bank_bytes, twin_parts

            parts = twin_parts(train_set)
            need = bank_bytes(parts)
            free = torch.cuda.mem_get_info(self.device)[0] if self.device.type == "cuda" else math.inf
            if need <= BANK_SHARE * free:
                self.bank = BurstBank(parts, self.device, crop=config.crop)  # a crop per item, not per batch
                self._bank_gen = torch.Generator(device=self.device)  # seeded per epoch: a resumed run draws anew
            else:  # the run still trains, through the DataLoader
                print(f"bank: the training bursts need {need / 2**30:.1f} GiB, the GPU has {free / 2**30:.1f} GiB "
                      f"free (at most {BANK_SHARE:.0%} of it is used): drawing them through the DataLoader", flush=True)
        self._train_loader: DataLoader | None = None
        self.out = Path(config.out_dir)
        if self.dist.main:
            self.out.mkdir(parents=True, exist_ok=True)
        self.model: PhaseNet = build_model(config.model).to(self.device)
        self.inherited = inherited_meta(config.init) if config.init else {}  # in every model this run saves
        if config.init:
            state = load_state(config.init)
            if config.widen_inputs:
                widen_inputs(state, self.model)
            load_into(self.model, state, config.init)
            if config.reset_dropout:
                reset_dropout_rates(self.model, config.model.init_min, config.model.init_max)
        self.criterion = PhaseLoss(config.loss)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.lr)
        self.scheduler: torch.optim.lr_scheduler.LRScheduler | None = None  # the running stage's
        self.has_dropout = bool(concrete_layers(self.model))
        self.state = {"stage": 1, "epoch": 0, "best": math.inf, "bad": 0, "stage_best": math.inf, "cpu_s": 0.0,
                      "checkpoints": []}
        if config.compile and config.budget_cpu_min is not None:
            import torch._inductor.config as inductor_config

            inductor_config.compile_threads = 1  # compile in this process: its compiler runs count in the budget
        self._compiled: dict[int, torch.nn.Module] = {}  # the running stage -> its compiled network (cfg.compile)
        self._compile_failed = False
        self._compile_cost: tuple[float, float] | None = None  # stage 1's compiling step: wall s, CPU s
        self._compiled_ok: int | None = None  # the stage whose compiled network has made a step
        self._cpu0 = time.process_time()
        self._kids_s = 0.0  # CPU of the children training steps waited for (a compiler), since _cpu0
        self._stage_deadline: float | None = None  # the deterministic stage's share of the deadline (fit() sets it)
        self._stage_t0 = time.time()  # wall-clock start of the running stage (fit() sets it)
        self._val_cpu = self._val_wall = 0.0  # the last validation's CPU and wall seconds: kept free at a budget's end
        self.history: list[dict] = []
        self._last_plot = -math.inf
        if config.resume and (self.out / "last.safetensors").is_file():
            self._load_last()

    # checkpointing -----------------------------------------------------------------------------
    def _load_last(self) -> None:
        load_into(
            self.model, load_state(self.out / "last.safetensors"), self.out / "last.safetensors"
        )
        st = json.loads((self.out / "last_state.json").read_text())
        scored = st.get("val_objective", {"objective": "inside"})  # before session 33: always the inside loss
        here = self._val_objective()
        if scored != here:  # the best-so-far score would be on another scale
            raise ValueError(f"resume {self.out}: its validation read {scored}, this config reads {here}")
        self.state, self.history = st["state"], st["history"]
        from gearscan.inference.predictor import NETWORK_SUPPORT_KEY

        carried = read_config(self.out / "last.safetensors").get(NETWORK_SUPPORT_KEY)  # what its saves carried
        self.inherited = {NETWORK_SUPPORT_KEY: carried} if carried is not None else {}
        self.state.setdefault("cpu_s", 0.0)
        self.state.setdefault("checkpoints", [])
        opt = self.out / "last_optim.pt"
        if opt.is_file():
            self.optimizer.load_state_dict(
                torch.load(opt, map_location=self.device, weights_only=True)
            )

    def _val_objective(self) -> dict:
        """What validation's ``val_loss`` scores (a resumed run must score the same)."""
        if self.config.val_objective == "full":
            return {"objective": "full", "outside_weight": float(self.config.loss.outside_weight)}
        return {"objective": "inside"}

    def _save_last(self) -> None:
        self.state["cpu_s"], self._cpu0, self._kids_s = self.cpu_seconds(), time.process_time(), 0.0
        self._save(self.model, "last", {"training": self.config.to_json()})
        torch.save(self.optimizer.state_dict(), self.out / "last_optim.pt")
        tmp = self.out / "last_state.json.tmp"
        tmp.write_text(json.dumps({"state": self.state, "history": self.history,
                                   "val_objective": self._val_objective()}, indent=1))
        tmp.replace(self.out / "last_state.json")

    def _write_metrics(self, plot: bool = False) -> None:
        """CSV + JSON every epoch; the PNG at most every 30 s (or when ``plot``) to keep tiny epochs cheap."""
        if not self.history:
            return
        keys = list(dict.fromkeys(k for row in self.history for k in row))  # a column some rows lack stays
        with open(self.out / "metrics.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
            w.writeheader()
            for row in self.history:
                w.writerow({k: row.get(k) for k in keys})
        (self.out / "metrics.json").write_text(json.dumps(self.history, indent=1))
        if plot or time.monotonic() - self._last_plot > 30.0:
            plot_history(self.history, self.out / "loss_curve.png")
            self._last_plot = time.monotonic()

    # one epoch -------------------------------------------------------------------------------
    def _autocast(self):
        if self.precision == "bf16":
            return torch.autocast(device_type=self.device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def _loader(self, dataset: Dataset, shuffle: bool, epoch: int) -> DataLoader:
        sampler = None
        if self.dist.world > 1:
            from torch.utils.data.distributed import DistributedSampler

            sampler = DistributedSampler(
                dataset,
                self.dist.world,
                self.dist.rank,
                shuffle=shuffle,
                seed=self.config.seed,
                drop_last=False,
            )
            sampler.set_epoch(epoch)
        workers = self.config.num_workers
        # a compiled step is specialised to its batch shape: a shuffled epoch's short last batch would recompile
        drop_last = shuffle and self.config.compile and len(dataset) // self.dist.world >= self.config.batch_size
        return DataLoader(
            dataset,
            batch_size=self.config.batch_size,
            shuffle=shuffle and sampler is None,
            sampler=sampler,
            num_workers=workers,
            drop_last=drop_last,
            pin_memory=self.device.type == "cuda",
            persistent_workers=workers > 0 and shuffle,  # the train loader's workers live through the run
        )

    def _train_batches(self, epoch: int):
        """This epoch's training batches: drawn from the bank, or from one DataLoader kept for the run (its
        workers start once; a distributed sampler is told the epoch)."""
        if self.bank is not None:
            while True:
                yield self.bank.draw(self.config.batch_size, self._bank_gen)
        if self._train_loader is None:
            self._train_loader = self._loader(self.train_set, True, epoch)
        sampler = self._train_loader.sampler
        if hasattr(sampler, "set_epoch"):
            sampler.set_epoch(epoch)
        yield from self._train_loader

    # CPU budget ------------------------------------------------------------------------------
    def cpu_seconds(self) -> float:
        """CPU seconds this fit has used (this process, all threads, and the children its training steps waited
        for; carried over on resume)."""
        return self.state["cpu_s"] + time.process_time() - self._cpu0 + self._kids_s

    def budget_spent(self, reserve_cpu: float = 0.0, reserve_wall: float = 0.0, *, stage: bool = True) -> bool:
        """True when the CPU budget or the deadline (the running stage's with ``stage``) leaves less than its
        reserve (s); distributed ranks all-reduce it, so every rank stops at the same step."""
        cpu = self.config.budget_cpu_min
        ends = [d for d in (self.config.deadline, self._stage_deadline if stage else None) if d is not None]
        if cpu is None and not ends:
            return False
        spent = ((cpu is not None and self.cpu_seconds() + reserve_cpu >= 60.0 * cpu)
                 or any(time.time() + reserve_wall >= d for d in ends))
        if self.dist.world > 1:
            spent = all_reduce_sum([float(spent)], self.dist, self.device)[0] > 0
        return spent

    def stage_progress(self) -> float:
        """Share (0-1) of the running stage's time spent: of the CPU budget left at the stage's start, or of the
        wall time to its deadline (a resumed run anneals over its new deadline), whichever is further on; the mean
        over distributed ranks (each has its own clocks), so every rank steps at the same rate and averages alike."""
        cfg, shares = self.config, [0.0]
        if cfg.budget_cpu_min is not None:
            c0 = self.state.get("stage_cpu0", 0.0)
            shares.append((self.cpu_seconds() - c0) / max(1e-9, 60.0 * cfg.budget_cpu_min - c0))
        end = self._stage_deadline or cfg.deadline
        if end is not None:
            shares.append((time.time() - self._stage_t0) / max(1e-9, end - self._stage_t0))
        share = max(shares)
        if self.dist.world > 1:
            share = all_reduce_sum([share], self.dist, self.device)[0] / self.dist.world
        return min(1.0, share)

    def _average_room(self) -> tuple[float, float]:
        """CPU and wall seconds an epoch must leave when averaging: the average's closing validation (the last
        validation's cost); none otherwise."""
        return (self._val_cpu, self._val_wall) if self.config.average_from is not None else (0.0, 0.0)

    def _stage_share(self, n_epochs: int) -> float:
        """Share of the running stage done: of its time with a CPU budget or deadline, else of its epochs."""
        if self.config.budget_cpu_min is not None or self.config.deadline is not None:
            return self.stage_progress()
        return self.state["epoch"] / max(1, n_epochs)

    def _try_average(self, stage: int, average: torch.optim.swa_utils.AveragedModel) -> None:
        """Validate the stage's weight average like an epoch; it becomes the stage's best if it beats it on val."""
        n = int(average.n_averaged)
        trained = {k: v.detach().clone() for k, v in self.model.state_dict().items()}
        self.model.load_state_dict(average.module.state_dict())
        row = {k: math.nan for k in self.history[-1]} | {
            "stage": stage, "epoch": self.state["epoch"], "lr": 0.0, "steps": 0, "averaged": n,
            **self._validate(), "cpu_min": self.cpu_seconds() / 60.0}
        row["seconds"] = self._val_wall
        for j, p in enumerate(dropout_rates(self.model)):
            row[f"p{j}"] = p
        self.history.append(row)
        kept = row["val_loss"] < self.state["stage_best"]
        print(f"average of {n} epochs: val loss {row['val_loss']:.6g} against the best epoch's "
              f"{self.state['stage_best']:.6g}: {'kept' if kept else 'not kept'}", flush=True)
        if kept:
            self.state["stage_best"] = row["val_loss"]
            if self.dist.main:
                self._save(self.model, f"stage{stage}_best", {"metrics": row})
        else:
            self.model.load_state_dict(trained)
        if self.dist.main:
            self._save_checkpoints(stage)
            self._write_metrics()

    def _save_checkpoints(self, stage: int) -> None:
        """Copy the best-on-val weights so far to ``cpu_<m>min.*`` for every mark just passed."""
        cpu_min = self.cpu_seconds() / 60.0
        for m in self.config.checkpoints_cpu_min:
            if m in self.state["checkpoints"] or cpu_min < m:
                continue
            self.state["checkpoints"].append(m)
            src = self.out / f"stage{stage}_best.safetensors"
            if self.dist.main and src.is_file():  # the metrics of the weights copied; the mark's epoch beside them
                kept = json.loads(src.with_suffix(".json").read_text()).get("metrics", self.history[-1])
                self._save(self._best_copy(src), f"cpu_{m:g}min",
                           {"cpu_min": cpu_min, "mark_cpu_min": m, "metrics": kept, "mark_metrics": self.history[-1]})

    def _kept_metrics(self, final: dict) -> dict:
        """The validation row of the weights the run ends with (its last stage's best, which ``fit`` loads back), not
        the last epoch's: a model's JSON describes the weights beside it."""
        stage = max((int(h["stage"]) for h in self.history), default=1)
        best = self.out / f"stage{stage}_best.json"
        return json.loads(best.read_text()).get("metrics", final) if best.is_file() else final

    def _save(self, model: torch.nn.Module, name: str, extra: dict, var_scale: float = 1.0) -> Path:
        """``out/<name>.safetensors`` with its JSON: ``extra`` plus what the run inherits from its init."""
        return save_model(model, self.out / f"{name}.safetensors", var_scale=var_scale,
                          extra={**self.inherited, **extra})

    def _best_copy(self, src: Path) -> PhaseNet:
        net = build_model(self.config.model)
        load_into(net, load_state(src), src)
        return net

    def _train_epoch(self, net: torch.nn.Module, stage: int, epoch: int) -> dict:
        self.model.train()
        set_stochastic(self.model, stage == 2)
        gen = torch.Generator().manual_seed(self.config.seed * 100003 + epoch * 7 + self.dist.rank)
        if self.bank is not None:
            self._bank_gen.manual_seed(self.config.seed * 1_000_003 + stage * 10_007 + epoch * 101 + self.dist.rank)
            total = self.config.steps_per_epoch or max(1, len(self.bank) // self.config.batch_size // self.dist.world)
        else:
            n_batches = math.ceil(math.ceil(len(self.train_set) / self.dist.world) / self.config.batch_size)
            total = min(n_batches, self.config.steps_per_epoch or n_batches)
        bar = task = None
        if self.config.progress and self.dist.main:
            from rich.progress import Progress

            bar = Progress(*Progress.get_default_columns(), "{task.fields[loss]}", transient=True)
            task = bar.add_task(f"stage {stage} epoch {epoch + 1}", total=total, loss="")
            bar.start()
        keys = ("total", "nll", "mse", "reg")
        acc = torch.zeros(len(keys), device=self.device)  # summed on the device: no host sync per step
        n, wait_s, t_epoch = 0, 0.0, time.perf_counter()
        batches = self._train_batches(epoch)
        for step in range(total):
            t_wait = time.perf_counter()
            batch = next(batches, None)
            wait_s += time.perf_counter() - t_wait  # blocked on the loader: where a starved device shows
            if batch is None:
                break
            batch = _crop(batch, self.config.crop, gen)
            losses = self._compiled_step(net, batch, stage) if stage in self._compiled else self._step(net, batch, stage)
            acc += torch.stack([losses[k].detach().float() for k in keys])
            n += 1
            if bar is not None:
                loss = {"loss": f"loss {float(losses['total'].detach()):.4g}"} if step % PROGRESS_EVERY == 0 else {}
                bar.update(task, advance=1, **loss)
            avg_cpu, avg_wall = self._average_room()  # room for the closing validation, and the average's
            if self.budget_spent(self._val_cpu + avg_cpu, self._val_wall + avg_wall):
                break
        if bar is not None:
            bar.stop()
        set_stochastic(self.model, False)
        sums = acc.tolist()  # the one host sync of the epoch
        train_s = time.perf_counter() - t_epoch
        vals = all_reduce_sum(sums + [n], self.dist, self.device)
        return ({f"train_{k}": vals[j] / max(vals[-1], 1) for j, k in enumerate(keys)} | {"steps": n}
                | {"train_s": train_s, "data_wait_s": wait_s})

    def _compiled_step(self, net: torch.nn.Module, batch: dict, stage: int) -> dict:
        """A step through the stage's compiled network. Its first step compiles (timed, for the next stage's
        choice); if that fails, the rest of the run is eager (one process) or stops (DDP)."""
        if self._compiled_ok == stage:
            return self._step(self._compiled[stage], batch, stage)
        w0, c0 = time.perf_counter(), time.process_time() + children_cpu_seconds()
        failure = None
        try:
            losses = self._step(self._compiled[stage], batch, stage)
        except Exception as exc:  # noqa: BLE001 - a compiler fails with many types; eager re-raises real errors
            if self.dist.world > 1:
                raise
            failure = f"{type(exc).__name__}: {(str(exc).splitlines() or [''])[0][:200]}"
        if failure is not None:  # outside the handler: the failed step's tensors are free before the retry
            print(f"compile: torch.compile failed ({failure}); training goes on eagerly", flush=True)
            self._compile_failed = True
            self._compiled.clear()
            return self._step(net, batch, stage)
        self._compiled_ok = stage
        if stage == 1 and self._compile_cost is None:
            self._compile_cost = (time.perf_counter() - w0, time.process_time() + children_cpu_seconds() - c0)
        return losses

    def _compile_room(self) -> bool:
        """Whether a later stage has time to compile: ``COMPILE_ROOM`` x stage 1's compiling step left to the
        deadline and to the CPU budget (always, without either or without a measured compile)."""
        if self._compile_cost is None:
            return True
        wall, cpu = self._compile_cost
        cfg = self.config
        if cfg.deadline is not None and cfg.deadline - time.time() < COMPILE_ROOM * wall:
            return False
        return cfg.budget_cpu_min is None or 60.0 * cfg.budget_cpu_min - self.cpu_seconds() >= COMPILE_ROOM * cpu

    def _step(self, net: torch.nn.Module, batch: dict, stage: int) -> dict:
        """One optimizer step on ``batch``; returns the losses. The CPU of the children it waits for counts."""
        kids0 = children_cpu_seconds()
        try:  # a compile that fails still counts
            self.optimizer.zero_grad(set_to_none=True)  # first: a step that failed half-way leaves no gradient
            with self._autocast():
                pred = net(batch["input"].to(self.device, non_blocking=True))
            losses = self.criterion(
                pred,
                batch["target"].to(self.device),
                batch["mask"].to(self.device),
                self.model,
                include_regularization=stage == 2,
            )
            losses["total"].backward()
            self.optimizer.step()
        finally:
            self._kids_s += children_cpu_seconds() - kids0
        return losses

    @torch.no_grad()
    def _validate(self) -> dict:
        c0, w0 = time.process_time(), time.perf_counter()
        try:
            return self._validate_once()
        finally:
            self._val_cpu, self._val_wall = time.process_time() - c0, time.perf_counter() - w0

    def _validate_once(self) -> dict:
        self.model.eval()
        set_stochastic(self.model, False)
        c = self.config.loss
        acc = [0.0, 0.0, 0.0, 0.0, 0.0]  # inside score*batches, batches, sq err, pixels, outside*batches
        for batch in self._loader(self.val_set, False, 0):
            with self._autocast():
                pred = self.model(batch["input"].to(self.device))
            mask = batch["mask"].to(self.device)
            losses = self.criterion(
                pred, batch["target"].to(self.device), mask, None, include_regularization=False
            )
            acc[0] += float(c.alpha * losses["nll"] + c.mse_weight * losses["mse"])
            acc[1] += 1
            se, npx = _wrapped_sq_err(pred.float(), batch["phase"].to(self.device), mask)
            acc[2] += se
            acc[3] += npx
            acc[4] += float(losses["outside"]) if "outside" in losses else 0.0
        acc = all_reduce_sum(acc, self.dist, self.device)
        n = max(acc[1], 1)
        return validation_row(acc[0] / n, acc[4] / n, math.sqrt(acc[2] / max(acc[3], 1)), c, self.config.val_objective)

    # both stages -----------------------------------------------------------------------------
    def fit(self) -> TrainResult:
        t0 = time.perf_counter()
        cfg = self.config
        stages = [(1, cfg.epochs_deterministic)] + (
            [(2, cfg.epochs_dropout)] if self.has_dropout else []
        )
        if cfg.deadline is not None and self.state["stage"] == 1 and len(stages) == 2 and cfg.epochs_dropout:
            share = cfg.epochs_deterministic / (cfg.epochs_deterministic + cfg.epochs_dropout)
            self._stage_deadline = time.time() + share * max(0.0, cfg.deadline - time.time())
        if cfg.init and not self.history and self.state["stage"] == 1:  # the starting point is a candidate too
            row = {"stage": 1, "epoch": 0, "lr": 0.0, **{f"train_{k}": math.nan for k in ("total", "nll", "mse", "reg")},
                   "steps": 0, **self._validate(), "seconds": time.perf_counter() - t0}
            row["cpu_min"] = self.cpu_seconds() / 60.0
            self.history.append(row)
            self.state["stage_best"] = row["val_loss"]
            if self.dist.main:
                self._save(self.model, "stage1_best", {"metrics": row})
        for stage, n_epochs in stages:
            if stage < self.state["stage"]:
                continue
            for layer in concrete_layers(self.model):
                layer.p_logit.requires_grad_(stage == 2)
            net: torch.nn.Module = self.model
            if self.dist.world > 1:
                from torch.nn.parallel import DistributedDataParallel as DDP

                net = DDP(
                    self.model,
                    device_ids=[self.device.index] if self.device.type == "cuda" else None,
                )
            self._compiled = {}
            if cfg.compile and not self._compile_failed:  # compiled lazily, at the stage's first step
                if self._compile_room():
                    self._compiled = {stage: torch.compile(net)}
                else:
                    print(f"compile: stage {stage} runs eagerly: less than {COMPILE_ROOM:g} x stage 1's compiling "
                          f"step ({self._compile_cost[0]:.0f} s) is left", flush=True)
            if self.state["epoch"] == 0 or "stage_cpu0" not in self.state:  # a resumed stage keeps its start
                self.state["stage_cpu0"] = self.cpu_seconds()
            self._stage_t0 = time.time()
            # epoch > 0 when resuming mid-stage: the schedule picks up where it was
            self.scheduler = build_scheduler(self.optimizer, cfg, stage, n_epochs, self.state["epoch"],
                                             progress=self.stage_progress)
            average = None  # the stage's weight average (average_from), begun at its share of the stage
            while (self.state["epoch"] < n_epochs and self.state["bad"] < cfg.patience
                   and not self.budget_spent(*self._average_room())):
                epoch = self.state["epoch"]
                te = time.perf_counter()
                row = {"stage": stage, "epoch": epoch + 1, "lr": self.scheduler.get_last_lr()[0]}
                row.update(self._train_epoch(net, stage, epoch))
                self.scheduler.step()
                row.update(self._validate())
                row["seconds"] = time.perf_counter() - te
                row["cpu_min"] = self.cpu_seconds() / 60.0
                for j, p in enumerate(dropout_rates(self.model)):
                    row[f"p{j}"] = p
                improved = row["val_loss"] < self.state["stage_best"]
                if improved:
                    self.state["stage_best"] = row["val_loss"]
                    self.state["bad"] = 0
                else:
                    self.state["bad"] += 1
                self.state["epoch"] = epoch + 1
                if cfg.average_from is not None and self._stage_share(n_epochs) >= cfg.average_from:
                    if average is None:
                        average = torch.optim.swa_utils.AveragedModel(self.model, avg_fn=_running_mean,
                                                                      use_buffers=True)
                    average.update_parameters(self.model)
                    row["averaged"] = int(average.n_averaged)
                self.history.append(row)
                if self.dist.main:
                    if improved:
                        self._save(self.model, f"stage{stage}_best", {"metrics": row})
                    self._save_checkpoints(stage)
                    self._save_last()
                    self._write_metrics()
            if average is not None and int(average.n_averaged) >= 2:  # alike on every rank: one shared share
                self._try_average(stage, average)
            self._stage_deadline = None  # the next stage runs to the deadline itself
            # stage done: continue from this stage's best weights
            best_file = self.out / f"stage{stage}_best.safetensors"
            barrier(self.dist)
            if best_file.is_file():
                load_into(self.model, load_state(best_file), best_file)
            self.state.update(
                {
                    "stage": stage + 1,
                    "epoch": 0,
                    "bad": 0,
                    "best": self.state["stage_best"] if math.isfinite(self.state["stage_best"]) else self.state["best"],
                    "stage_best": math.inf,
                }
            )
            if self.dist.main:
                self._save_last()
                self._write_metrics(plot=True)
        budget_hit = self.budget_spent(stage=False)
        fit_cpu = self.cpu_seconds()
        var_scale, calib, sigma_cal = 1.0, {}, {}
        if cfg.calibrate:
            from gearscan.inference.calibrate import calibrate_trained_model

            var_scale, calib, sigma_cal = calibrate_trained_model(
                self.model,
                self._loader(self.val_set, False, 0),
                self.device,
                self._autocast,
                mc=cfg.calibrate_mc if cfg.model.dropout else 0,
                reliability_png=self.out / "reliability.png" if self.dist.main else None,
            )
        best_path = None
        if self.dist.main:
            final = self.history[-1] if self.history else {}
            kept = self._kept_metrics(final)
            best_path = self._save(
                self.model,
                "best",
                var_scale=var_scale,
                extra={
                    "training": cfg.to_json(),
                    "metrics": kept,
                    "final_metrics": final,
                    "calibration": calib,
                    **({"sigma_calibration": sigma_cal} if sigma_cal else {}),
                    "train_seconds": time.perf_counter() - t0,
                    "train_cpu_min": fit_cpu / 60.0,
                    "budget_cpu_min": cfg.budget_cpu_min,
                    "deadline": cfg.deadline,
                    "budget_hit": budget_hit,
                },
            )
        barrier(self.dist)
        return TrainResult(
            best_path, self.history, float(self.state["best"]), var_scale, time.perf_counter() - t0,
            fit_cpu, budget_hit,
        )


def inherited_meta(init: str | Path) -> dict:
    """What a fine-tune carries over from its init model's JSON: its fringe-support tests (``network_support``), marked
    as inherited. A fine-tune starts from its init's behaviour at shadow borders, not from the product default's (how
    far fine-tuning moves it was not measured); rerun the val choices to choose for the fine-tune itself."""
    from gearscan.inference.model_io import config_path
    from gearscan.inference.predictor import NETWORK_SUPPORT_KEY, model_network_support

    if not config_path(init).is_file():  # bare weights: nothing to inherit (load_state needs only the weights)
        return {}
    support = model_network_support(read_config(init))
    if support is None:
        return {}
    return {NETWORK_SUPPORT_KEY: support.to_json(f"inherited from the init model {init} (not chosen for this fine-tune)")}


def train(config: TrainConfig, train_set: Dataset, val_set: Dataset | None = None) -> TrainResult:
    """Train per ``config`` on ``train_set`` (split by group if ``val_set`` is None)."""
    return Trainer(config, train_set, val_set).fit()


if (
    __name__ == "__main__"
):  # torchrun entry point: torchrun --nproc_per_node 2 -m gearscan.inference.train ...
    import typer

    from gearscan.inference.commands import train as train_command

    typer.run(train_command)
