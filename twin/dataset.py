"""The paper's dataset protocol (section 3.2), rendered by the twin and read lazily.

Per gear: start points every ``start_step_deg`` within one pitch; from each, ``poses`` poses
``pose_step_deg`` apart; at each pose the ``steps``-step pattern set. Only this
``poses x steps`` image block is stored per start point; the three-step inputs (pattern 0,
6, 12 from poses i < j < k: C(18, 3) = 816 per start point) are built on the fly.

On-disk layout (``root/``), all plain numpy so it memory-maps::

    index.json                        spec + one entry per start point (rig, optics, gear, period)
    sp_00000/images.npy               (poses, steps, H, W) uint8/uint16 raw frames
    sp_00000/label.npy                (poses, 2, H, W) float32  18-step PS M, D (normalised)
    sp_00000/truth_md.npy             (poses, 2, H, W) float32  analytic M, D
    sp_00000/phase.npy                (poses, H, W) float32     analytic wrapped phase
    sp_00000/mask.npy                 (poses, H, W) bool        valid pixels

Generation is resumable: a start point is listed as done in ``index.json`` only after all its
files were renamed into place.

``index.json`` records the dataset's ``purpose``: ``protocol`` (the project's model-development
data: the split rules of :mod:`gearscan.twin.splits` refuse test gears and test seeds) or
``adaptation`` (a user's own rig and gear, ``gearscan twin dataset --rig``: any tooth count, since
the gear is the user's; test seeds are still refused; the scene is recorded as ``scene``).
"""

from __future__ import annotations

import itertools
import json
import math
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from gearscan.core.gear import GearSpec
from gearscan.core.patterns import DEFAULT_PERIOD_PX, PatternSet
from gearscan.core.phase import decode_md
from gearscan.core.rig import Rig, default_rig
from gearscan.twin.render import Optics, TwinRenderer

INDEX = "index.json"
FORMAT = "gearscan-twin-dataset"
PURPOSES = ("protocol", "adaptation")


class DatasetError(ValueError):
    """A dataset folder or spec is invalid."""


class DatasetSpec(BaseModel):
    """What to render: gears, protocol constants, image size and randomisation."""

    model_config = ConfigDict(extra="forbid")

    gears: list[GearSpec] = Field(default_factory=lambda: [GearSpec(teeth=12), GearSpec(teeth=20), GearSpec(teeth=30)])
    start_step_deg: float = Field(2.0, gt=0, le=90)
    poses: int = Field(18, ge=3, le=64)
    pose_step_deg: float = Field(0.1, gt=0, le=10)
    steps: int = Field(18, ge=13, le=64, description="phase steps per pose; three-step inputs use 0, N/3, 2N/3")
    width: int = Field(512, ge=32, le=4096)
    height: int = Field(512, ge=32, le=4096)
    period_px: float = Field(DEFAULT_PERIOD_PX, ge=4)
    randomize: bool = Field(False, description="randomise rig, optics and fringe period per gear")
    views: bool = Field(False, description="with randomize: any view (radial, side, oblique, face), module "
                        "0.5-5 mm, camera fringe period 5-60 px (twin.randomize.random_view_scene)")
    radial_period_px: tuple[float, float] | None = Field(
        None, description="with randomize (radial view): camera fringe period range LO, HI in px, drawn "
        "log-uniformly; None: the radial randomiser's own range (twin.randomize.RANGES, uniform 12-40)")
    seed: int = 0
    max_start_points: int | None = Field(None, ge=1, description="per gear, for quick sets")
    start_offset_deg: float = Field(0.0, ge=0, lt=90, description="the first start point's angle (deg); the grid "
                                    "moves with it, e.g. off another set's angles")

    @field_validator("steps")
    @classmethod
    def _divisible(cls, v: int) -> int:
        if v % 3:
            raise ValueError(f"steps must be a multiple of 3 so patterns 0, N/3, 2N/3 form a three-step set, got {v}")
        return v

    @field_validator("radial_period_px")
    @classmethod
    def _period_range(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and not 4.0 <= v[0] < v[1]:
            raise ValueError(f"radial_period_px: expected 4 <= LO < HI (camera px), got {v}")
        return v

    @model_validator(mode="after")
    def _period_needs_radial(self) -> DatasetSpec:
        if self.radial_period_px is not None and (not self.randomize or self.views):
            raise ValueError("radial_period_px applies to the radial randomiser only: set randomize=True, views=False")
        return self


def start_points(gear: GearSpec, step_deg: float) -> list[float]:
    """Start angles (deg) every ``step_deg`` within one pitch: 15, 9, 6 for 12, 20, 30 teeth."""
    pitch = 360.0 / gear.teeth
    n = int(math.floor(pitch / step_deg + 1e-9))
    return [k * step_deg for k in range(n)]


def combinations(poses: int) -> list[tuple[int, int, int]]:
    """All ascending pose triples i < j < k (816 for 18 poses)."""
    return list(itertools.combinations(range(poses), 3))


def scene_for(spec: DatasetSpec, gear_index: int) -> tuple[Rig, Optics, GearSpec, float]:
    """The rig, optics, gear and projector period the spec renders for gear ``gear_index`` (seeded)."""
    gear = spec.gears[gear_index]
    if not spec.randomize:
        return default_rig(spec.width, spec.height), Optics(), gear, spec.period_px
    from gearscan.twin.randomize import random_scene, random_view_scene

    rng = np.random.default_rng([spec.seed, gear_index])
    if spec.views:
        for _ in range(20):  # a view that misses the gear (all shadow) is redrawn
            rig, optics, g, period = random_view_scene(rng, gear, spec.width, spec.height)
            renderer = TwinRenderer(rig, g, optics)
            if renderer.truth(renderer.surface(0.0), period).mask.mean() >= 0.03:
                return rig, optics, g, period
        raise DatasetError(f"gear {gear_index}: no random view in 20 draws sees the gear")
    return random_scene(rng, gear, spec.width, spec.height, camera_period_px=spec.radial_period_px)


def generate_dataset(
    root: str | Path,
    spec: DatasetSpec,
    *,
    progress: Callable[[int, int], None] | None = None,
    scene: tuple[Rig, Optics, GearSpec, float] | None = None,
    purpose: str = "protocol",
) -> Path:
    """Render (or resume rendering) the dataset described by ``spec`` into ``root``.

    ``scene`` (rig, optics, gear, period) replaces the spec's default/randomised scene, for
    target domains with their own rig and camera. ``purpose="adaptation"`` (needs ``scene``) is a
    user's fine-tuning data for their own rig and gear: the test split's tooth counts are allowed
    there (the split rule is for the project's own datasets), its test seeds are not.
    """
    from gearscan.twin.splits import SplitError, refuse_test

    if purpose not in PURPOSES:
        raise DatasetError(f"purpose: expected one of {PURPOSES}, got {purpose!r}")
    if purpose == "adaptation" and (scene is None or spec.randomize):
        raise DatasetError("an adaptation dataset renders one given scene (the user's rig and gear), "
                           "not the spec's default or randomised ones")
    if scene is not None and (scene[0].camera.width, scene[0].camera.height) != (spec.width, spec.height):
        raise DatasetError(f"spec size {spec.width}x{spec.height} differs from the rig's camera "
                           f"{scene[0].camera.width}x{scene[0].camera.height}")
    teeth = [] if purpose == "adaptation" else [g.teeth for g in ([scene[2]] if scene is not None else spec.gears)]
    try:  # test scenes are rendered on the fly by the report, never stored (twin/splits.py)
        refuse_test(teeth=teeth, seed=spec.seed, what=f"dataset {root}")
    except SplitError as exc:
        raise DatasetError(str(exc)) from exc
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    index_path = root / INDEX
    if index_path.exists():
        index = json.loads(index_path.read_text())
        try:  # compared as specs, so a field added since (at its default) still matches
            same = DatasetSpec.model_validate(index.get("spec", {})) == spec
        except ValueError:
            same = False
        if not same:
            raise DatasetError(f"{index_path} was written for another spec; use a new folder or the same spec")
        if index.get("purpose", "protocol") != purpose:
            raise DatasetError(f"{index_path} is a {index.get('purpose', 'protocol')} dataset, not {purpose}; "
                               "use a new folder")
    else:
        index = {"format": FORMAT, "version": 1, "purpose": purpose, "spec": json.loads(spec.model_dump_json()),
                 "entries": []}
        if purpose == "adaptation":
            rig, optics, gear, period = scene
            index["scene"] = {"rig": rig.to_json(), "optics": optics.model_dump(), "gear": gear.model_dump(),
                              "period_px": period}
    done = {e["id"] for e in index["entries"]}
    jobs = []
    for g in range(len(spec.gears)):
        starts = [spec.start_offset_deg + a for a in start_points(spec.gears[g], spec.start_step_deg)[: spec.max_start_points]]
        for s, start in enumerate(starts):
            jobs.append((f"sp_{g:02d}_{s:03d}", g, start))
    renderers: dict[int, tuple[TwinRenderer, float, Rig, Optics, GearSpec]] = {}
    for n, (sp_id, g, start) in enumerate(jobs):
        if sp_id in done:
            if progress:
                progress(n + 1, len(jobs))
            continue
        if g not in renderers:
            rig, optics, gear, period = scene if scene is not None else scene_for(spec, g)
            renderers = {g: (TwinRenderer(rig, gear, optics), period, rig, optics, gear)}
        renderer, period, rig, optics, gear = renderers[g]
        ps = PatternSet.n_step(spec.steps, period)
        rng = np.random.default_rng([spec.seed, g, int(round(start * 1000))])
        h, w = spec.height, spec.width
        images = np.empty((spec.poses, spec.steps, h, w), dtype=optics.dtype)
        label = np.empty((spec.poses, 2, h, w), np.float32)
        truth_md = np.empty((spec.poses, 2, h, w), np.float32)
        phase = np.empty((spec.poses, h, w), np.float32)
        mask = np.empty((spec.poses, h, w), bool)
        for p in range(spec.poses):
            angle = math.radians(start + p * spec.pose_step_deg)
            imgs, tr = renderer.render(angle, ps, rng)
            images[p] = imgs
            label[p] = decode_md(imgs, ps.shifts, optics.full_scale)
            truth_md[p, 0], truth_md[p, 1] = tr.M, tr.D
            phase[p], mask[p] = tr.phase, tr.mask
        tmp = root / f"{sp_id}.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        for name, arr in (("images", images), ("label", label), ("truth_md", truth_md), ("phase", phase), ("mask", mask)):
            np.save(tmp / f"{name}.npy", arr)
        shutil.rmtree(root / sp_id, ignore_errors=True)
        tmp.rename(root / sp_id)
        index["entries"].append(
            {
                "id": sp_id,
                "gear_index": g,
                "start_deg": start,
                "period_px": period,
                "gear": gear.model_dump(),
                "rig": rig.to_json(),
                "optics": optics.model_dump(),
            }
        )
        tmp_index = index_path.with_name(INDEX + ".tmp")
        tmp_index.write_text(json.dumps(index, indent=1))
        tmp_index.replace(index_path)
        if progress:
            progress(n + 1, len(jobs))
    return root


Motion = Literal["all", "uniform", "nonuniform"]


class TwinBurstDataset:
    """Three-step bursts from a rendered dataset, as a map-style torch-compatible dataset.

    Items are dicts: ``input`` (3, H, W) float32 in [0, 1] (patterns 0, N/3, 2N/3 at poses
    i < j < k), ``target`` (2, H, W) the 18-step M, D label at pose i, ``truth_md`` the analytic
    M, D, ``mask`` (H, W) bool, ``phase`` (H, W) truth wrapped phase, ``group`` (start point id,
    for splits) and ``span_deg`` (angle from frame 1 to frame 3). ``static=True`` adds the
    ``poses`` motionless bursts (i, i, i) to the protocol's i < j < k ones, ``static_repeat``
    times each (oversampling: they are 2 % of the inputs otherwise). ``angles`` are the three
    frames' turntable angles (rad, from the start point): what an encoder would report.
    ``reverse=True`` adds every moving burst played backwards (poses k > j > i, the same three
    patterns in the same order, label at pose k): the turntable turning the other way, from the
    same renders.
    """

    def __init__(
        self,
        root: str | Path,
        *,
        motion: Motion = "all",
        max_span: int | None = None,
        min_span: int | None = None,
        static: bool = False,
        static_repeat: int = 1,
        crop: int | None = None,
        groups: list[int] | None = None,
        seed: int = 0,
        reverse: bool = False,
        prior: bool = False,
        prior_jitter: float = 0.0,
    ) -> None:
        if not 0.0 <= prior_jitter < 1.0:
            raise DatasetError(f"prior_jitter: expected a fraction in [0, 1), got {prior_jitter}")
        self.prior, self.prior_jitter = bool(prior), float(prior_jitter)
        self.root = Path(root)
        index_path = self.root / INDEX
        if not index_path.exists():
            raise DatasetError(f"{self.root} is not a twin dataset ({INDEX} missing; run `gearscan twin dataset`)")
        index = json.loads(index_path.read_text())
        self.spec = DatasetSpec(**index["spec"])
        self.entries = index["entries"]
        if not self.entries:
            raise DatasetError(f"{index_path}: no rendered start points yet")
        self.start_points = list(range(len(self.entries))) if groups is None else list(groups)
        bad = [g for g in self.start_points if not 0 <= g < len(self.entries)]
        if bad:
            raise DatasetError(f"groups {bad} out of range 0..{len(self.entries) - 1}")
        combos = combinations(self.spec.poses)
        if motion == "uniform":
            combos = [c for c in combos if c[1] - c[0] == c[2] - c[1]]
        elif motion == "nonuniform":
            combos = [c for c in combos if c[1] - c[0] != c[2] - c[1]]
        elif motion != "all":
            raise DatasetError(f"motion must be all, uniform or nonuniform, got {motion!r}")
        if max_span is not None:
            combos = [c for c in combos if c[2] - c[0] <= max_span]
        if min_span is not None:
            combos = [c for c in combos if c[2] - c[0] >= min_span]
        if not combos and (min_span is not None or not static):
            raise DatasetError(f"no moving burst of {self.spec.poses} poses spans {min_span or 0}.."
                               f"{self.spec.poses - 1 if max_span is None else max_span} poses")
        if static_repeat < 1:
            raise DatasetError(f"static_repeat must be >= 1, got {static_repeat}")
        if reverse:  # the turntable turning the other way: poses k > j > i, label at pose k
            combos = combos + [c[::-1] for c in combos]
        if static:  # all three frames at one pose: no motion, the static noise floor
            combos = combos + [(p, p, p) for p in range(self.spec.poses)] * static_repeat
        self.combos = combos
        if crop is not None and not (16 <= crop <= min(self.spec.width, self.spec.height)):
            raise DatasetError(f"crop must be in 16..{min(self.spec.width, self.spec.height)}, got {crop}")
        self.crop = crop
        self._seed, self._pid = seed, os.getpid()
        self._rng = np.random.default_rng(seed)
        self._arrays: dict[int, dict[str, np.ndarray]] = {}
        self._idx3 = [0, self.spec.steps // 3, 2 * self.spec.steps // 3]

    def __len__(self) -> int:
        return len(self.start_points) * len(self.combos)

    @property
    def groups(self) -> list[int]:
        """Start-point id of every item (the split unit: no start point in train and validation)."""
        return [g for g in self.start_points for _ in self.combos]

    def _open(self, g: int) -> dict[str, np.ndarray]:
        if g not in self._arrays:
            d = self.root / self.entries[g]["id"]
            self._arrays[g] = {n: np.load(d / f"{n}.npy", mmap_mode="r") for n in ("images", "label", "truth_md", "phase", "mask")}
        return self._arrays[g]

    def full_scale(self, g: int) -> float:
        return float((1 << int(self.entries[g]["optics"]["bit_depth"])) - 1)

    def pose_stack(self, g: int) -> dict[str, np.ndarray]:
        """Start point ``g``'s arrays that training bursts are cut from, read into memory: ``frames``
        (poses, 3, H, W) raw (the three patterns of a burst, at every pose), ``label`` (poses, 2, H, W)
        and ``mask`` (poses, H, W). :meth:`__getitem__` builds its items from the same arrays."""
        a = self._open(g)
        return {"frames": np.array(a["images"][:, self._idx3]), "label": np.array(a["label"]),
                "mask": np.array(a["mask"])}

    def _prior(self, a: dict[str, np.ndarray], poses: tuple[int, int, int], sl: tuple) -> dict[str, np.ndarray]:
        """What the twin prior (:class:`gearscan.twin.prior.TwinPrior`) predicts for this burst, from
        the stored truth of the same renders: the fringe phase change from the first frame to the
        others (wrapped; the fringes are periodic, so that is all an image shows), their irradiance
        ratio (the analytic modulation's: the contrast is the rig's) and where every frame's truth is
        valid. ``prior_jitter`` scales each burst's changes by a random factor in ``1 +- jitter``, an
        encoder or calibration that is a little off."""
        phase = np.stack([a["phase"][p][sl] for p in poses]).astype(np.float64)
        mod = np.stack([np.hypot(*a["truth_md"][p][(slice(None), *sl)]) for p in poses]).astype(np.float64)
        known = np.logical_and.reduce([a["mask"][p][sl] for p in poses])
        change = np.angle(np.exp(1j * (phase[1:] - phase[:1])))
        if self.prior_jitter:
            change = change * (1.0 + self.prior_jitter * (2.0 * self._rng.random() - 1.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where((mod[:1] > 0) & (mod[1:] > 0), mod[1:] / mod[:1], 1.0)
        return {"prior_change": change.astype(np.float32), "prior_ratio": ratio.astype(np.float32),
                "prior_known": known}

    def __getitem__(self, item: int) -> dict[str, object]:
        if not 0 <= item < len(self):
            raise IndexError(item)
        g = self.start_points[item // len(self.combos)]
        i, j, k = self.combos[item % len(self.combos)]
        a = self._open(g)
        h, w = self.spec.height, self.spec.width
        if os.getpid() != self._pid:  # a DataLoader worker: its own random stream, not a copy of the parent's
            self._pid = os.getpid()
            self._rng = np.random.default_rng([self._seed, self._pid])
        if self.crop:
            y = int(self._rng.integers(0, h - self.crop + 1))
            x = int(self._rng.integers(0, w - self.crop + 1))
            sl = (slice(y, y + self.crop), slice(x, x + self.crop))
        else:
            sl = (slice(None), slice(None))
        frames = np.stack([a["images"][p, s][sl] for p, s in zip((i, j, k), self._idx3, strict=True)])
        inp = frames.astype(np.float32) / self.full_scale(g)
        extra = self._prior(a, (i, j, k), sl) if self.prior else {}
        return extra | {
            "input": inp,
            # copies: memory-mapped views are read-only and torch warns on them
            "target": np.array(a["label"][i][(slice(None), *sl)]),
            "truth_md": np.array(a["truth_md"][i][(slice(None), *sl)]),
            "mask": np.array(a["mask"][i][sl]),
            "phase": np.array(a["phase"][i][sl]),
            "group": g,
            "span_deg": (k - i) * self.spec.pose_step_deg,  # negative: turning backwards
            "poses": (i, j, k),
            "angles": np.radians(np.array([i, j, k], dtype=np.float64) * self.spec.pose_step_deg),
        }
