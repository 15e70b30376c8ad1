"""The train / val / test splits are disjoint, and the test families only draw from test."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gearscan.core.gear import GearSpec
from gearscan.core.rig import default_rig
from gearscan.inference.model_io import read_config
from gearscan.inference.predictor import DEFAULT_MODEL
from gearscan.twin.families import FAMILIES, SEED_BLOCK, draw_gear, family_seed
from gearscan.twin.randomize import aim_point, view_rig
from gearscan.twin.splits import (
    CANDIDATE_V10,
    DEFAULT_RIG_V6_FINETUNE,
    SHIPPED,
    SHIPPED_DEFAULT_RIG,
    SHIPPED_V5,
    SHIPPED_V6,
    SHIPPED_V9,
    SPLITS,
    TEETH_RANGE,
    SplitError,
    check_disjoint,
    describe,
    refuse_test,
    split_of_rig,
    split_of_seed,
    split_of_teeth,
)

REPO = Path(__file__).resolve().parents[1]


def test_splits_are_disjoint_by_gear_rig_and_seed() -> None:
    check_disjoint()
    train, val, test = (SPLITS[k] for k in ("train", "val", "test"))
    for a, b in ((train, val), (train, test), (val, test)):
        assert not a.teeth & b.teeth
        assert not a.rig_families & b.rig_families
        assert not any(ra.overlaps(rb) for ra in a.seeds for rb in b.seeds)
    # every tooth count GearSpec allows has exactly one owner; test spans the families' 10-80
    assert train.teeth | val.teeth | test.teeth == set(TEETH_RANGE)
    assert min(test.teeth) == 10 and max(test.teeth) == 80
    for seed in (0, 1, 2, 3, 9_999, 10_000, 19_999, 20_000, 29_999):
        split_of_seed(seed)  # exactly one owner, or it raises


@pytest.mark.parametrize("shipped", [SHIPPED_V5, SHIPPED_V6, SHIPPED_V9, SHIPPED_DEFAULT_RIG, DEFAULT_RIG_V6_FINETUNE,
                                     CANDIDATE_V10],
                         ids=["v5", "v6", "v9", "default-rig", "default-rig-until-s54", "v10-candidate"])
def test_shipped_models_saw_only_train_and_val(shipped) -> None:
    assert shipped.train_teeth <= SPLITS["train"].teeth
    assert shipped.val_teeth <= SPLITS["val"].teeth
    assert all(split_of_seed(s) == "train" for s in shipped.train_dataset_seeds)
    assert all(split_of_seed(s) == "val" for s in shipped.val_dataset_seeds)
    assert "25" in shipped.summary()


def test_v6_record_matches_the_plan_that_rendered_it() -> None:
    meta = read_config(DEFAULT_MODEL.with_name("v6.safetensors"))["training"]
    assert meta["version"] == "v6"
    assert {t for _, teeth, *_ in meta["train_sets"] for t in teeth} == SHIPPED_V6.train_teeth
    assert {t for _, teeth, *_ in meta["val_sets"] for t in teeth} == SHIPPED_V6.val_teeth
    assert {s[-1] for s in meta["train_sets"]} == set(SHIPPED_V6.train_dataset_seeds)


def test_v9_record_matches_the_lease_run_that_made_it() -> None:
    """The shipped v9's record (what its reports say it saw) is the lease run's own: v6's sets plus the dense ones."""
    meta = read_config(DEFAULT_MODEL)["training"]
    assert SHIPPED is SHIPPED_V9 and meta["version"] == "v9" and meta["continues"].startswith("v6")
    assert {t for _, teeth, *_ in meta["train_sets"] for t in teeth} == SHIPPED_V9.train_teeth
    assert {s[5] for s in meta["train_sets"]} == set(SHIPPED_V9.train_dataset_seeds)
    assert {t for _, teeth, *_ in meta["val_sets"] for t in teeth} == SHIPPED_V9.val_teeth
    assert {s[5] for s in meta["val_sets"]} <= set(SHIPPED_V9.val_dataset_seeds)
    assert set(SHIPPED_V6.train_dataset_seeds) < set(SHIPPED_V9.train_dataset_seeds)


def test_default_rig_record_matches_the_run_that_made_it() -> None:
    """The default-rig option's record (what its reports say it saw) is its run's own, gears and seeds: since
    session 54 v9's and the GPU run's (benchmarks/default_rig/gpu/run.json)."""
    import json
    from pathlib import Path

    raw = Path(__file__).resolve().parents[1] / "benchmarks/default_rig"
    gpu = json.loads((raw / "gpu/run.json").read_text())
    assert "--init inference/weights/default.safetensors" in gpu["command"] and "--seed 3301 " in gpu["command"]
    assert "--val-seed 10005 " in gpu["command"] and set(gpu["val_teeth"]) <= SHIPPED_DEFAULT_RIG.val_teeth
    assert set(gpu["train_teeth"]) <= SHIPPED_DEFAULT_RIG.train_teeth
    assert set(SHIPPED_DEFAULT_RIG.train_dataset_seeds) - set(SHIPPED_V9.train_dataset_seeds) == set(
        range(3301, 3301 + len(gpu["train_teeth"])))
    assert read_config(DEFAULT_MODEL.with_name("default_rig.safetensors"))["training"]["init"] == \
        "inference/weights/default.safetensors"
    # its predecessor (v6 fine-tuned, sessions 26-28): the runs below
    previous = DEFAULT_RIG_V6_FINETUNE  # the record the runs below are read against
    run = json.loads((raw / "run.json").read_text())
    cont = json.loads((raw / "continue/run.json").read_text())  # the second run continued the first on its data
    assert (cont["train_teeth"], cont["val_teeth"], cont["train_dirs"]) == (run["train_teeth"], run["val_teeth"], run["train_dirs"])
    assert "--init inference/weights/default_rig.safetensors" in cont["command"] and "--seed 3201 " in cont["command"]
    assert set(run["train_teeth"]) <= previous.train_teeth and set(run["val_teeth"]) <= previous.val_teeth
    seeds = set(previous.train_dataset_seeds) - set(SHIPPED_V6.train_dataset_seeds)
    assert "--seed 3201 " in run["command"] and "--val-seed 10005 " in run["command"]
    assert all(split_of_teeth(z) == "train" for z in run["train_teeth"])
    assert all(split_of_teeth(z) == "val" for z in run["val_teeth"])
    # the third run continued the second on new gears of the same rig: seed + k again
    third = json.loads((raw / "anneal/run.json").read_text())
    assert "--init inference/weights/default_rig.safetensors" in third["command"] and "--seed 3301 " in third["command"]
    assert third["val_teeth"] == run["val_teeth"] and "--val-seed 10005 " in third["command"]
    assert set(third["train_teeth"]) <= previous.train_teeth
    assert seeds == set(range(3201, 3201 + len(run["train_teeth"]))) | set(range(3301, 3301 + len(third["train_teeth"])))
    assert all(split_of_teeth(z) == "train" for z in third["train_teeth"])
    fourth = json.loads((raw / "cycle2/run.json").read_text())  # a second cycle on the third run's data
    assert (fourth["train_teeth"], fourth["train_dirs"]) == (third["train_teeth"], third["train_dirs"])
    assert "--init inference/weights/default_rig.safetensors" in fourth["command"] and "--seed 3301 " in fourth["command"]


def test_families_draw_test_gears_rigs_and_seeds_only() -> None:
    seeds = {family_seed(f, i) for f in FAMILIES for i in (0, SEED_BLOCK - 1)}
    assert len(seeds) == 2 * len(FAMILIES)
    assert all(split_of_seed(s) == "test" for s in seeds)
    assert all(split_of_rig(f) == "test" for f in FAMILIES)
    rng = np.random.default_rng(0)
    assert all(split_of_teeth(draw_gear(rng).teeth) == "test" for _ in range(50))
    with pytest.raises(ValueError, match="family"):
        family_seed("nope", 0)


def test_stored_datasets_refuse_test_gears_and_seeds() -> None:
    refuse_test(teeth=[25, 20], seed=2)
    with pytest.raises(SplitError, match=r"tooth counts \[35\].*test split"):
        refuse_test(teeth=[20, 35])
    with pytest.raises(SplitError, match="seed 20000"):
        refuse_test(seed=20_000)
    with pytest.raises(SplitError, match=r"teeth=35 \(split test\).*seed=20000 \(split test\)"):
        SPLITS["train"].check(teeth=35, rig_family="radial-random", seed=20_000)
    assert "radial-random" in describe("train")


def test_radial_view_rig_is_the_default_rig() -> None:
    gear = GearSpec(teeth=35)
    a, b = view_rig(64, 48, gear, view="radial"), default_rig(64, 48, working_radius=gear.pitch_radius)
    assert np.allclose(a.camera.T_from_world, b.camera.T_from_world)
    assert np.allclose(a.projector.T_from_world, b.projector.T_from_world)
    assert np.allclose(aim_point(b), [gear.pitch_radius, 0, 0], atol=1e-9)
    face = view_rig(64, 48, gear, view="face")
    assert np.allclose(aim_point(face), [gear.pitch_radius, 0, gear.face_width / 2], atol=1e-9)
    with pytest.raises(ValueError, match="view"):
        view_rig(64, 48, gear, view="top")


def test_dataset_generation_refuses_the_test_split(tmp_path) -> None:
    from gearscan.twin.dataset import DatasetError, DatasetSpec, generate_dataset

    spec = DatasetSpec(gears=[GearSpec(teeth=37)], width=32, height=32, max_start_points=1)
    with pytest.raises(DatasetError, match=r"tooth counts \[37\] belong to the test split"):
        generate_dataset(tmp_path / "d", spec)
    assert not (tmp_path / "d").exists()
    # the default rig aimed at a test gear (the test family's scene) is refused as stored data as well
    from gearscan.twin.families import DEFAULT_RIG_PERIOD_PX, default_rig_scene, draw_gear

    gear = draw_gear(np.random.default_rng(0), module=2.0, teeth=37)
    rig, optics = default_rig_scene(gear, (32, 32))
    with pytest.raises(DatasetError, match=r"tooth counts \[37\] belong to the test split"):
        generate_dataset(tmp_path / "r", spec, scene=(rig, optics, gear, DEFAULT_RIG_PERIOD_PX))
    assert draw_gear(np.random.default_rng(0), module=2.0, teeth=20).teeth == 20  # a train gear drawn the family's way


def test_v10_candidate_record_matches_the_lease_run_that_made_it() -> None:
    """v10's record is its lease's own (benchmarks/v10_lease/reproduce.json): v9's sets at twice the scale, v6's start."""
    meta = read_config(DEFAULT_MODEL.with_name("v10.safetensors"))["training"]
    run = json.loads((REPO / "benchmarks/v10_lease/reproduce.json").read_text())
    assert meta["version"] == "v10" and meta["continues"].startswith("v6")
    assert meta["train_sets"] == run["train_sets"] and meta["val_sets"] == run["val_sets"]
    assert run["args"]["scale"] == "1.4" and run["args"]["init"] == "inference/weights/v6.safetensors"
    assert {t for _, teeth, *_ in meta["train_sets"] for t in teeth} == CANDIDATE_V10.train_teeth
    assert {s[5] for s in meta["train_sets"]} == set(CANDIDATE_V10.train_dataset_seeds)
    assert {t for _, teeth, *_ in meta["val_sets"] for t in teeth} == CANDIDATE_V10.val_teeth
    # the same sets as v9's, the radial and any-view ones with twice the scenes per tooth count (the third field); the
    # same trainer but for the epochs (45 against 46) and the init's path (both v6's weights): the data-size point
    v9_record = read_config(DEFAULT_MODEL)["training"]
    assert v9_record["version"] == "v9"  # the pair's other half (the shipped default since session 39)
    v9 = {s[0]: s for s in v9_record["train_sets"]}
    for name, teeth, scenes, *rest in meta["train_sets"]:
        assert v9[name][1] == teeth and v9[name][3:] == rest
        assert scenes == (v9[name][2] if name.startswith("radial_dense") else 2 * v9[name][2])
    differ = {k for k in meta["trainer"] if meta["trainer"][k] != v9_record["trainer"].get(k)}
    assert differ == {"epochs_deterministic", "init"}
    assert meta["loss"] == v9_record["loss"] == meta["trainer"]["loss"]  # what a fine-tune from it reads


def test_a_test_seed_for_a_users_own_gear_is_refused_with_a_hint_that_fits_it():
    """An adaptation dataset (a user's own gear: any tooth count) on a test seed: the hint names other seeds, not the
    train split's tooth counts, which do not bind it."""
    from gearscan.twin.splits import SplitError, refuse_test

    with pytest.raises(SplitError) as err:
        refuse_test(seed=20001, what="adaptation dataset")
    text = str(err.value)
    assert "seed 20001 belongs to the test split" in text and "use another seed" in text
    assert "20000-29999" in text and "teeth 6-9" not in text
    with pytest.raises(SplitError) as err:  # a project dataset (its teeth checked) keeps the split's own hint
        refuse_test(teeth=[11], seed=20001)
    assert "use train teeth/seeds" in str(err.value) and "any tooth count" not in str(err.value)
