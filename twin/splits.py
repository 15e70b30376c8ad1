"""The three disjoint data splits (train / val / test), defined once for every producer.

DESIGN.md, "Numbers we can trust": train fits the weights; val decides everything else (early
stopping, model choice, sigma calibration, thresholds); test is touched only to report. A twin
scene is identified by its gear (tooth count), its rig family and its seed, and each of the three
belongs to exactly one split:

- **gear**: tooth counts. Test holds 10, 35, 37, 39, the odd counts 41-79 and 80, so a test gear
  is never one the shipped model trained on (11-40 except 25, 32, 35, 37, 39) and the test
  families span 10-80 teeth. Val holds 25 (the shipped model's validation gear), 32 and
  42, 46, ..., 78 (for wider training later). Train holds every other count GearSpec allows.
- **rig family**: ``radial-random`` (:mod:`gearscan.twin.randomize`, radial view) and
  ``view-random`` (:func:`~gearscan.twin.randomize.random_view_scene`: any view, module 0.5-5 mm,
  camera period 5-60 px, radial stand-off/triangulation ranges) are train; ``radial-random-val``
  and ``view-random-val`` (the same randomisers, val gears and seeds) are val; the product's ``default`` rig
  and the families of :mod:`gearscan.twin.families` (radial rigs outside the training ranges,
  side, oblique and face views) are test.
- **seed**: the scene seed (rig, optics, start angles and noise of a test scene derive from it).
  Train 1 and 3-9999, val 0, 2 and 10000-19999, test 20000-29999.

The split rules govern the project's model-development datasets (``purpose: protocol`` in a
dataset's ``index.json``). A user's adaptation dataset (``gearscan twin dataset --rig``, ``purpose:
adaptation``) renders their own rig and gear, whatever its tooth count: :func:`refuse_test` is
called there with the seed only. A benchmark that fine-tunes on a test scene's rig keeps its test
bursts untouched by other means (non-test seeds, other start angles: ``benchmarks/adaptation.py``).

What the shipped model saw is :data:`SHIPPED` (v9, :data:`SHIPPED_V9`: v6, :data:`SHIPPED_V6`, continued; both
rendered by ``scripts/reproduce_model.py`` under these rules). The earlier default, v5, predates this module
(:data:`SHIPPED_V5`, from ``scripts/train_default.py`` and its model card); one exception is
stated there: its validation used the default rig (gear 25), which the test split now owns.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

SplitName = Literal["train", "val", "test"]
SPLIT_NAMES: tuple[SplitName, ...] = ("train", "val", "test")
TEETH_RANGE = range(6, 401)  # what GearSpec accepts


class SplitError(ValueError):
    """A scene (gear, rig family or seed) does not belong to the split it is used for."""


@dataclass(frozen=True, slots=True)
class SeedRange:
    """Half-open seed interval ``[start, stop)``."""

    start: int
    stop: int

    def __post_init__(self) -> None:
        if not 0 <= self.start < self.stop:
            raise ValueError(f"SeedRange: expected 0 <= start < stop, got [{self.start}, {self.stop})")

    def __contains__(self, seed: object) -> bool:
        return isinstance(seed, int) and self.start <= seed < self.stop

    def overlaps(self, other: SeedRange) -> bool:
        return self.start < other.stop and other.start < self.stop


@dataclass(frozen=True, slots=True)
class Split:
    """One split: its tooth counts, rig families and seed ranges, and what it may be used for."""

    name: SplitName
    teeth: frozenset[int]
    rig_families: frozenset[str]
    seeds: tuple[SeedRange, ...]
    use: str

    def has_seed(self, seed: int) -> bool:
        return any(seed in r for r in self.seeds)

    def seed(self, offset: int) -> int:
        """The ``offset``-th seed of this split (0-based, across its ranges in order)."""
        if offset < 0:
            raise SplitError(f"{self.name} split: seed offset must be >= 0, got {offset}")
        for r in self.seeds:
            if offset < r.stop - r.start:
                return r.start + offset
            offset -= r.stop - r.start
        raise SplitError(f"{self.name} split: seed offset out of its ranges {self.seeds}")

    def check(self, *, teeth: int | None = None, rig_family: str | None = None, seed: int | None = None) -> None:
        """Raise :class:`SplitError` naming every input that belongs to another split."""
        bad = []
        if teeth is not None and teeth not in self.teeth:
            bad.append(f"teeth={teeth} (split {split_of_teeth(teeth)})")
        if rig_family is not None and rig_family not in self.rig_families:
            bad.append(f"rig family {rig_family!r} (split {split_of_rig(rig_family)})")
        if seed is not None and not self.has_seed(seed):
            bad.append(f"seed={seed} (split {split_of_seed(seed)})")
        if bad:
            raise SplitError(f"not in the {self.name} split: {', '.join(bad)}")


_TEST_TEETH = frozenset({10, 35, 37, 39, 80, *range(41, 80, 2)})
_VAL_TEETH = frozenset({25, 32, *range(42, 79, 4)})
_TRAIN_TEETH = frozenset(TEETH_RANGE) - _TEST_TEETH - _VAL_TEETH

# rig families of gearscan.twin.families (kept here so the registry has no import cycle)
TEST_RIG_FAMILIES = frozenset({"default", "radial-wide", "side", "oblique", "face"})

SPLITS: dict[SplitName, Split] = {
    "train": Split(
        "train", _TRAIN_TEETH, frozenset({"radial-random", "view-random"}), (SeedRange(1, 2), SeedRange(3, 10_000)),
        "fitting the weights",
    ),
    "val": Split(
        "val", _VAL_TEETH, frozenset({"radial-random-val", "view-random-val"}), (SeedRange(0, 1), SeedRange(2, 3), SeedRange(10_000, 20_000)),
        "early stopping, model choice, sigma calibration, thresholds",
    ),
    "test": Split("test", _TEST_TEETH, TEST_RIG_FAMILIES, (SeedRange(20_000, 30_000),), "reporting only"),
}


def _owner(kind: str, value: object, hit) -> SplitName:
    owners = [name for name, s in SPLITS.items() if hit(s)]
    if len(owners) != 1:
        raise SplitError(f"{kind} {value!r} belongs to {owners or 'no split'}; every {kind} needs exactly one")
    return owners[0]


def split_of_teeth(teeth: int) -> SplitName:
    return _owner("tooth count", teeth, lambda s: teeth in s.teeth)


def split_of_rig(family: str) -> SplitName:
    return _owner("rig family", family, lambda s: family in s.rig_families)


def split_of_seed(seed: int) -> SplitName:
    return _owner("seed", seed, lambda s: s.has_seed(seed))


def check_disjoint() -> None:
    """Raise :class:`SplitError` if two splits share a tooth count, rig family or seed."""
    names = list(SPLITS)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            sa, sb = SPLITS[a], SPLITS[b]
            shared = []
            if sa.teeth & sb.teeth:
                shared.append(f"teeth {sorted(sa.teeth & sb.teeth)}")
            if sa.rig_families & sb.rig_families:
                shared.append(f"rig families {sorted(sa.rig_families & sb.rig_families)}")
            if any(ra.overlaps(rb) for ra in sa.seeds for rb in sb.seeds):
                shared.append("seeds")
            if shared:
                raise SplitError(f"splits {a} and {b} share {', '.join(shared)}")


def refuse_test(*, teeth: list[int] | tuple[int, ...] = (), seed: int | None = None, what: str = "dataset") -> None:
    """Raise :class:`SplitError` if a stored ``what`` would hold test gears or a test seed.

    Test scenes are rendered on the fly by the report (``benchmarks/generalization.py``); a
    training or validation dataset never holds them. Adaptation datasets (a user's own gear) pass
    no ``teeth``: only their seed is checked.
    """
    test = SPLITS["test"]
    bad = sorted({t for t in teeth if t in test.teeth})
    msg = []
    if bad:
        msg.append(f"tooth counts {bad}")
    if seed is not None and test.has_seed(seed):
        msg.append(f"seed {seed}")
    if msg:
        seeds = ", ".join(f"{r.start}-{r.stop - 1}" for r in test.seeds)
        hint = (f"use train teeth/seeds ({describe('train')}) or val ones ({describe('val')})" if teeth else
                f"use another seed (the test split's seeds: {seeds}; any tooth count is fine for your own gear in an "
                "adaptation dataset)")
        verb = "belong" if bad else "belongs"
        raise SplitError(f"{what}: {' and '.join(msg)} {verb} to the test split (touched only to report); {hint}")


def _runs(values: frozenset[int], limit: int = 80) -> str:
    """Compact text of integer sets, e.g. ``10, 35-37`` (values above ``limit`` summarised)."""
    vals = sorted(v for v in values if v <= limit)
    parts, start = [], None
    for k, v in enumerate(vals):
        if start is None:
            start = v
        if k + 1 == len(vals) or vals[k + 1] != v + 1:
            parts.append(str(v) if v == start else f"{start}-{v}")
            start = None
    if any(v > limit for v in values):
        parts.append(f"{limit + 1}-{max(values)}")
    return ", ".join(parts)


def describe(name: SplitName) -> str:
    """One line: the split's tooth counts, rig families and seed ranges."""
    s = SPLITS[name]
    seeds = ", ".join(f"{r.start}" if r.stop == r.start + 1 else f"{r.start}-{r.stop - 1}" for r in s.seeds)
    return f"teeth {_runs(s.teeth)}; rig families {', '.join(sorted(s.rig_families))}; seeds {seeds}"


@dataclass(frozen=True, slots=True)
class ShippedData:
    """What a shipped model was trained and validated on (from its recipe and model card)."""

    model: str
    train_teeth: frozenset[int]
    train_dataset_seeds: tuple[int, ...]
    train_rig: str
    train_module_mm: tuple[float, float]
    train_camera_period_px: tuple[float, float]
    val_teeth: frozenset[int]
    val_dataset_seeds: tuple[int, ...]
    val_rigs: str
    val_used_for: str

    def summary(self) -> str:
        return (
            f"{self.model} trained on teeth {_runs(self.train_teeth)} ({self.train_rig}, module "
            f"{self.train_module_mm[0]:g}-{self.train_module_mm[1]:g} mm, camera fringe period "
            f"{self.train_camera_period_px[0]:g}-{self.train_camera_period_px[1]:g} px, dataset seeds "
            f"{', '.join(map(str, self.train_dataset_seeds))}); validated on teeth {_runs(self.val_teeth)} "
            f"({self.val_rigs}; dataset seeds {', '.join(map(str, self.val_dataset_seeds))}), used for "
            f"{self.val_used_for}"
        )


_V5_TRAIN2 = (11, 13, 14, 15, 17, 18, 19, 21, 22, 23, 24, 26, 27, 28, 29, 31, 33, 34, 38, 40)
SHIPPED_V5 = ShippedData(
    model="v5 (inference/weights/v5.*, weights in git history since session 50; the default until session 23)",
    train_teeth=frozenset({12, 16, 20, 30, 36, *_V5_TRAIN2}),
    train_dataset_seeds=(1, 7, 11),
    train_rig="radial-random rigs of twin/randomize.py at 256x256",
    train_module_mm=(1.5, 3.0),
    train_camera_period_px=(12.0, 40.0),
    val_teeth=frozenset({25}),
    val_dataset_seeds=(2, 0),
    val_rigs="data/val: 3 radial-random rigs, seed 2; data/val_default: the default rig, seed 0",
    val_used_for="early stopping, v5 over v4, the sigma calibration and the still threshold (0.075 deg)",
)

_V6_RADIAL = (11, 17, 23, 30, 40, 12, 18, 24, 31, 13, 19, 26, 33, 14, 20, 27, 34, 15, 21, 28, 36, 16, 22, 29, 38)
_V6_VIEWS = (11, 21, 33, 64, 12, 22, 34, 68, 13, 23, 36, 72, 14, 24, 38, 76, 15, 26, 40, 16, 27, 44, 17, 28, 48,
             18, 29, 52, 19, 30, 56, 20, 31, 60)
SHIPPED_V6 = ShippedData(
    model="v6 (inference/weights/default.*, the default since session 23)",
    train_teeth=frozenset({*_V6_RADIAL, *_V6_VIEWS}),
    train_dataset_seeds=(*range(3001, 3007), *range(4001, 4011)),
    train_rig="radial-random rigs (teeth 11-40) and any-view rigs: radial, side, oblique, face (teeth 11-76) of "
              "twin/randomize.py at 256x256",
    train_module_mm=(0.5, 5.0),
    train_camera_period_px=(5.0, 60.0),
    val_teeth=frozenset({25, 32, *range(42, 79, 4)}),
    val_dataset_seeds=(10002, 10001),
    val_rigs="val_radial: radial-random rigs, seed 10002; val_views: any-view rigs, seed 10001",
    val_used_for="early stopping, v6 over the w = 32 run and v5, and the sigma calibration (its form too)",
)
SHIPPED_V6 = replace(SHIPPED_V6, model="v6 (inference/weights/v6.*; the default from session 23 to 38)")
# v9: v6 continued on a lent GPU (session 39) on v6's data plus one repeat of the dense radial set (radial-random
# rigs, camera period 5-40 px, teeth of v6's train split, seeds 3101-3104); early stopping also read the dense val
# set (seed 10003), and the choice over v6 the default rig's val gears (seeds 10005-10008)
_V9_DENSE = (11, 15, 19, 23, 28, 33, 40, 56, 72, 12, 16, 20, 24, 29, 34, 44, 60, 76, 13, 17, 21, 26, 30, 36, 48, 64,
             14, 18, 22, 27, 31, 38, 52, 68)
SHIPPED_V9 = ShippedData(
    model="v9 (inference/weights/default.*, the default since session 39: v6 continued on a GPU)",
    train_teeth=frozenset({*SHIPPED_V6.train_teeth, *_V9_DENSE}),
    train_dataset_seeds=(*SHIPPED_V6.train_dataset_seeds, *range(3101, 3105)),
    train_rig=SHIPPED_V6.train_rig + ", then also dense radial-random rigs (camera period 5-40 px, teeth 11-76)",
    train_module_mm=(0.5, 5.0),
    train_camera_period_px=(5.0, 60.0),
    val_teeth=SHIPPED_V6.val_teeth,
    val_dataset_seeds=(*SHIPPED_V6.val_dataset_seeds, 10003, *range(10005, 10009)),
    val_rigs=SHIPPED_V6.val_rigs + "; val_radial_dense: radial-random rigs with camera period 5-40 px, seed 10003 "
             "(early stopping); the default rig with teeth 25, 32, 46, 62, seeds 10005-10008 (the choice over v6)",
    val_used_for="v6's uses, then early stopping of the continuation, v9 over v6 (benchmarks/v9_choice_rule.md), "
                 "its sigma map, still-burst gate and MC phase",
)
SHIPPED = SHIPPED_V9  # what the shipped default model (inference/weights/default.*) saw
# v10, a candidate (session 50; benchmarks/v10_choice_rule.md): v6 trained as v9 was on twice v9's data (the same
# sets at scale 1.4: the same tooth counts and seeds, twice the start points); the same val sets
CANDIDATE_V10 = replace(
    SHIPPED_V9,
    model="v10 (inference/weights/v10.*, a candidate: v6 trained on twice v9's data with v9's steps)",
    val_used_for="v6's uses, then early stopping of the run, v10 over v9 (benchmarks/v10_choice_rule.md)",
)
_DEFAULT_RIG_TRAIN = (11, 15, 20, 24, 28, 33, 36, 40, 44, 48, 56, 60, 64, 68, 72, 76)  # its first two runs, seeds 3201-
# its third and fourth runs (session 28: the rate annealed, twice), seeds 3301-
_DEFAULT_RIG_TRAIN_3 = (11, 13, 15, 17, 19, 21, 24, 26, 28, 30, 31, 34, 36, 38, 40, 44, 48, 52, 56, 60, 64, 68, 72, 76)
DEFAULT_RIG_V6_FINETUNE = ShippedData(
    model="default-rig model until session 54 (default_rig.* then, an option: v6 fine-tuned on the product's rig)",
    train_teeth=frozenset({*SHIPPED_V6.train_teeth, *_DEFAULT_RIG_TRAIN, *_DEFAULT_RIG_TRAIN_3}),
    train_dataset_seeds=(*SHIPPED_V6.train_dataset_seeds, *range(3201, 3201 + len(_DEFAULT_RIG_TRAIN)),
                         *range(3301, 3301 + len(_DEFAULT_RIG_TRAIN_3))),
    train_rig="v6's rigs, then the product's default rig (a test rig family: per-rig adaptation, its gears and "
              "seeds from the train split; scripts/default_rig_model.py) with teeth "
              + ", ".join(map(str, sorted({*_DEFAULT_RIG_TRAIN, *_DEFAULT_RIG_TRAIN_3}))) + " at module 2",
    train_module_mm=(0.5, 5.0),
    train_camera_period_px=(5.0, 60.0),
    val_teeth=frozenset({*SHIPPED_V6.val_teeth, 25, 32, 46, 62}),
    val_dataset_seeds=(*SHIPPED_V6.val_dataset_seeds, *range(10005, 10009)),
    val_rigs="v6's, then the default rig with teeth 25, 32, 46, 62, seeds 10005-10008",
    val_used_for="its weights (best on val, in each of its four runs), the choice to ship it and to replace it "
                 "by each continuation (benchmarks/default_rig/choice_rule.md, choice_rule_continue.md, "
                 "choice_rule_anneal.md, choice_rule_cycle2.md), the ablation's read-out (ablation_rule.md) "
                 "and its sigma calibration",
)
# the option since session 54: v9 fine-tuned on the default rig on a lent GPU (scripts/default_rig_model.py through
# scripts/lease_train.sh, LEASE_TASK=default-rig): the third run's gears and seeds (3301-3324) at 16 start angles each
SHIPPED_DEFAULT_RIG = ShippedData(
    model="default-rig model (inference/weights/default_rig.*, an option: v9 fine-tuned on the product's rig, session 54)",
    train_teeth=frozenset({*SHIPPED_V9.train_teeth, *_DEFAULT_RIG_TRAIN_3}),
    train_dataset_seeds=(*SHIPPED_V9.train_dataset_seeds, *range(3301, 3301 + len(_DEFAULT_RIG_TRAIN_3))),
    train_rig="v9's rigs, then the product's default rig (a test rig family: per-rig adaptation, its gears and "
              "seeds from the train split; scripts/default_rig_model.py) with teeth "
              + ", ".join(map(str, _DEFAULT_RIG_TRAIN_3)) + " at module 2",
    train_module_mm=(0.5, 5.0),
    train_camera_period_px=(5.0, 60.0),
    val_teeth=SHIPPED_V9.val_teeth,
    val_dataset_seeds=SHIPPED_V9.val_dataset_seeds,
    val_rigs="v9's (the default rig with teeth 25, 32, 46, 62, seeds 10005-10008 among them)",
    val_used_for="v9's uses, then its weights (best on 48 of the default rig's val items), the choice to replace "
                 "its predecessor (benchmarks/default_rig/choice_rule_gpu.md), its sigma maps, still-burst gate "
                 "(none), MC phase, depth-sigma and rest-sigma scales",
)
