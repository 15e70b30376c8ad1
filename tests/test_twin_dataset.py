"""Dataset protocol of paper section 3.2."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gearscan.core.gear import GearSpec
from gearscan.core.phase import wrapped_rmse
from gearscan.inference.data import MotionInput
from gearscan.twin.dataset import (
    DatasetError,
    DatasetSpec,
    TwinBurstDataset,
    combinations,
    generate_dataset,
    start_points,
)


def test_protocol_counts():
    assert [len(start_points(GearSpec(teeth=t), 2.0)) for t in (12, 20, 30)] == [15, 9, 6]
    combos = combinations(18)
    assert len(combos) == 816 and all(i < j < k for i, j, k in combos)


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    spec = DatasetSpec(gears=[GearSpec(teeth=20)], width=80, height=80, max_start_points=2)
    return generate_dataset(root, spec), spec


def test_items_labels_and_truth(small_dataset):
    root, spec = small_dataset
    ds = TwinBurstDataset(root)
    assert len(ds) == 2 * 816
    item = ds[816 + 5]
    assert item["group"] == 1 and item["input"].shape == (3, 80, 80) and item["input"].dtype == np.float32
    assert 0 <= item["input"].min() and item["input"].max() <= 1
    i, j, k = item["poses"]
    assert i < j < k and item["span_deg"] == pytest.approx((k - i) * 0.1)
    # the 18-step label agrees with the analytic truth at pose i
    label_phase = np.arctan2(item["target"][0], item["target"][1])
    assert wrapped_rmse(label_phase, item["phase"], item["mask"]) < 0.03
    truth_phase = np.arctan2(item["truth_md"][0], item["truth_md"][1])
    assert wrapped_rmse(truth_phase, item["phase"], item["mask"]) < 1e-5


def test_motion_input_carries_the_encoder_rotation(small_dataset):
    root, spec = small_dataset
    plain = TwinBurstDataset(root)
    moving = MotionInput(plain)
    assert moving.groups == plain.groups
    a, b = plain[816 + 5], moving[816 + 5]
    i, j, k = b["poses"]
    np.testing.assert_allclose(a["angles"], np.radians(np.array([i, j, k]) * spec.pose_step_deg))
    assert b["input"].shape == (5, 80, 80)
    np.testing.assert_array_equal(b["input"][:3], a["input"])
    np.testing.assert_allclose(b["input"][3:, 0, 0], [(j - i) * spec.pose_step_deg, (k - i) * spec.pose_step_deg], rtol=1e-5)
    assert np.ptp(b["input"][3:], axis=(1, 2)).max() == 0  # constant maps


def test_motion_filters_and_crops(small_dataset):
    root, _ = small_dataset
    uni = TwinBurstDataset(root, motion="uniform", groups=[0])
    non = TwinBurstDataset(root, motion="nonuniform", groups=[0])
    assert len(uni) == sum(18 - 2 * d for d in range(1, 9)) == 72
    assert len(uni) + len(non) == 816
    assert all(j - i == k - j for i, j, k in uni.combos)
    assert len(TwinBurstDataset(root, static=True, groups=[0])) == 816 + 18
    over = TwinBurstDataset(root, static=True, static_repeat=5, groups=[0])
    assert len(over) == 816 + 5 * 18
    still = over[len(over) - 1]  # a motionless burst: one pose, the three pattern phases
    assert still["span_deg"] == 0 and len(set(still["poses"])) == 1
    with pytest.raises(DatasetError, match="static_repeat must be >= 1"):
        TwinBurstDataset(root, static=True, static_repeat=0)
    crop = TwinBurstDataset(root, crop=48, seed=1)[3]
    assert crop["input"].shape == (3, 48, 48) and crop["mask"].shape == (48, 48)
    with pytest.raises(DatasetError, match="crop must be in 16..80"):
        TwinBurstDataset(root, crop=100)


def test_generation_resumes_and_refuses_another_spec(small_dataset):
    root, spec = small_dataset
    before = (root / "sp_00_000" / "images.npy").stat().st_mtime_ns
    generate_dataset(root, spec)
    assert (root / "sp_00_000" / "images.npy").stat().st_mtime_ns == before
    assert len(json.loads((root / "index.json").read_text())["entries"]) == 2
    with pytest.raises(DatasetError, match="written for another spec"):
        generate_dataset(root, spec.model_copy(update={"seed": 9}))
    with pytest.raises(DatasetError, match="not a twin dataset"):
        TwinBurstDataset(root / "sp_00_000")


def test_spec_validation():
    with pytest.raises(ValueError, match="multiple of 3"):
        DatasetSpec(steps=16)


def test_reverse_plays_moving_bursts_backwards(small_dataset):
    root, spec = small_dataset
    fwd, both = TwinBurstDataset(root, groups=[0]), TwinBurstDataset(root, groups=[0], reverse=True, static=True)
    assert len(both) == 2 * 816 + 18
    i, j, k = fwd.combos[40]
    rev = both[both.combos.index((k, j, i))]
    sp = root / both.entries[0]["id"]
    a = np.load(sp / "images.npy", mmap_mode="r")
    # the same three patterns in the same order, shown at the poses in reverse
    np.testing.assert_allclose(rev["input"][0], a[k, 0] / fwd.full_scale(0), rtol=1e-6)
    np.testing.assert_allclose(rev["input"][2], a[i, 2 * spec.steps // 3] / fwd.full_scale(0), rtol=1e-6)
    np.testing.assert_array_equal(rev["target"], np.load(sp / "label.npy")[k])
    assert rev["span_deg"] == pytest.approx(-(k - i) * spec.pose_step_deg)


def test_min_span_keeps_the_bursts_that_turn_at_least_that_far(small_dataset):
    """The user's turntable speed: only bursts spanning >= min_span poses (both senses), still ones kept."""
    root, spec = small_dataset
    ds = TwinBurstDataset(root, groups=[0], reverse=True, static=True, min_span=10)
    moving = [c for c in ds.combos if c[0] != c[2]]
    assert moving and all(abs(c[2] - c[0]) >= 10 for c in moving)
    assert len(moving) == 2 * sum((18 - s) * (s - 1) for s in range(10, 18))  # every i<j<k with k-i >= 10, twice
    assert sum(1 for c in ds.combos if c[0] == c[2]) == 18
    assert all(abs(ds[ds.combos.index(c)]["span_deg"]) >= 10 * spec.pose_step_deg - 1e-9 for c in moving[:3])
    for static in (False, True):  # with still bursts too: an impossible speed is an error, not a still-only set
        with pytest.raises(DatasetError, match="spans 18..17"):
            TwinBurstDataset(root, groups=[0], min_span=18, static=static)


def test_view_randomised_scenes_span_views_modules_and_fringe_periods():
    """random_view_scene draws every view, modules 0.5-5 mm and camera periods 5-60 px (median over
    the lit pixels, measured here on the rendered surface), keeping the gear's tooth count."""
    import numpy as np

    from gearscan.core.gear import GearSpec
    from gearscan.twin.randomize import VIEW_RANGES, random_view_scene
    from gearscan.twin.render import TwinRenderer

    rng = np.random.default_rng(3)
    names, periods = set(), []
    for _ in range(12):
        rig, optics, g, period = random_view_scene(rng, GearSpec(teeth=23), 96, 96)
        assert g.teeth == 23 and 0.5 <= g.module <= 5.0
        names.add(rig.name)
        surf = TwinRenderer(rig, g, optics).surface(0.0)
        gy, gx = np.gradient(surf.u_proj)
        grad = np.hypot(gx, gy)[surf.lit]
        grad = grad[np.isfinite(grad) & (grad > 0)]
        if grad.size > 50:
            periods.append(period / np.median(grad))  # camera px per fringe
    assert len(names) >= 3
    lo, hi = VIEW_RANGES["camera_period_px"]
    assert all(lo * 0.99 <= p <= hi * 1.01 for p in periods) and max(periods) / min(periods) > 2


def test_dataloader_workers_draw_their_own_crops(small_dataset):
    """Each DataLoader worker crops from its own random stream, not a copy of the parent's: items
    0 and 1 (same first frame, so equal crops would give equal first images) land on two workers."""
    import torch

    root, _ = small_dataset
    ds = TwinBurstDataset(root, crop=32, seed=3)
    loader = torch.utils.data.DataLoader(torch.utils.data.Subset(ds, [0, 1]), batch_size=1, num_workers=2)
    a, b = (item["input"][0, 0].numpy() for item in loader)
    assert ds.combos[0][0] == ds.combos[1][0]  # same first pose
    assert np.ptp(a) > 0 and not np.array_equal(a, b)


def test_dense_radial_scenes_keep_the_rig_and_draw_the_wider_fringe_period():
    """``radial_period_px`` changes only the fringe period of the radial randomiser (its last draw):
    the rig, optics and gear of a seed stay those of the default range, and the camera period on the
    rim spans the wider range, dense fringes included, as measured on the rendered surface."""
    from gearscan.core.gear import GearSpec
    from gearscan.twin.randomize import projector_period_for, random_scene
    from gearscan.twin.render import TwinRenderer

    cam_periods = []
    for seed in range(16):
        base = random_scene(np.random.default_rng(seed), GearSpec(teeth=60), 96, 96)
        rig, optics, g, period = random_scene(np.random.default_rng(seed), GearSpec(teeth=60), 96, 96,
                                              camera_period_px=(5.0, 40.0))
        assert g == base[2] and optics == base[1]
        assert rig.to_json() == base[0].to_json()
        cam = period / projector_period_for(rig, 1.0, g.pitch_radius)
        assert 5.0 <= cam <= 40.0
        cam_periods.append(cam)
        if seed < 4:  # the rendered fringes agree with the drawn period (median over lit pixels)
            surf = TwinRenderer(rig, g, optics).surface(0.0)
            gy, gx = np.gradient(surf.u_proj)
            grad = np.hypot(gx, gy)[surf.lit]
            measured = period / np.median(grad[np.isfinite(grad) & (grad > 0)])
            assert 0.6 * cam <= measured <= 1.6 * cam, (seed, cam, measured)
    assert min(cam_periods) < 12.0 < max(cam_periods)  # below the default range's floor, and inside it


def test_radial_period_spec_is_checked_and_old_indexes_still_resume(small_dataset, tmp_path):
    with pytest.raises(ValueError, match="radial randomiser only"):
        DatasetSpec(randomize=True, views=True, radial_period_px=(5.0, 40.0))
    with pytest.raises(ValueError, match="radial randomiser only"):
        DatasetSpec(radial_period_px=(5.0, 40.0))
    with pytest.raises(ValueError, match="4 <= LO < HI"):
        DatasetSpec(randomize=True, radial_period_px=(40.0, 5.0))
    # an index written before the field existed resumes (the field at its default matches)
    root, spec = small_dataset
    index = json.loads((root / "index.json").read_text())
    index["spec"].pop("radial_period_px")
    (root / "index.json").write_text(json.dumps(index))
    generate_dataset(root, spec)
    with pytest.raises(DatasetError, match="written for another spec"):
        generate_dataset(root, spec.model_copy(update={"randomize": True, "radial_period_px": (5.0, 40.0)}))


def test_fringe_drift_per_degree_follows_the_rim_motion():
    """scripts/fringe_drift_stats: on the default rig the pitch circle moves r * dtheta mm per degree,
    about width / field_mm px per mm at the image centre, and the drift in periods scales as 1/period."""
    import importlib.util
    from pathlib import Path

    from gearscan.core.rig import default_rig

    path = Path(__file__).resolve().parents[1] / "scripts" / "fringe_drift_stats.py"
    spec = importlib.util.spec_from_file_location("fringe_drift_stats", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    gear = GearSpec(teeth=60)
    rig = default_rig(256, 256, working_radius=gear.pitch_radius)
    drift, cam_period = mod.periods_per_degree(rig, gear, 40.0)
    expected_px = gear.pitch_radius * np.radians(1.0) * 256 / 26.0  # field_mm 26 at the stand-off
    assert drift * cam_period == pytest.approx(expected_px, rel=0.05)
    assert 8.0 < cam_period < 16.0  # 40 projector px over 36 mm, seen over 26 mm at 256 px, obliquely
    assert mod.periods_per_degree(rig, gear, 20.0)[0] == pytest.approx(2 * drift, rel=1e-9)


@pytest.fixture(scope="module")
def prior_dataset(tmp_path_factory):
    """Large enough for the twin prior's clean pixels (blur footprints away from edges and creases)."""
    spec = DatasetSpec(gears=[GearSpec(teeth=20)], width=160, height=160, max_start_points=1, poses=8,
                       pose_step_deg=0.25)
    return generate_dataset(tmp_path_factory.mktemp("prior"), spec), spec


def test_prior_items_are_what_the_twin_prior_predicts_at_run_time(prior_dataset):
    """The training-time prior (from the stored truth) equals the run-time one (ray cast from the CAD)."""
    from gearscan.core.rig import Rig
    from gearscan.inference.data import PriorInput
    from gearscan.inference.models import PRIOR_CHANNELS, prior_channels
    from gearscan.twin.prior import TwinPrior
    from gearscan.twin.render import Optics

    root, spec = prior_dataset
    ds = TwinBurstDataset(root, prior=True, reverse=True, static=True)
    e = ds.entries[0]
    optics = Optics(**e["optics"])
    prior = TwinPrior(Rig.from_json(e["rig"]), GearSpec(**e["gear"]), e["period_px"],
                      camera_defocus_px=optics.camera_defocus_px)
    n_moving = len(combinations(spec.poses))
    for idx in (3, 50, 2 * n_moving - 1, 2 * n_moving + 5):  # forward, forward, backward, still
        item = ds[idx]
        poses = np.array(item["poses"])
        maps = prior.maps(np.radians(e["start_deg"] + poses * spec.pose_step_deg))
        run_time = prior_channels(maps.phase_change(), maps.ratio[1:], maps.clean)
        train_time = prior_channels(item["prior_change"], item["prior_ratio"], item["prior_known"])
        known = run_time[-1] > 0
        assert known.mean() > 0.05
        np.testing.assert_array_equal(train_time[-1] > 0, known)
        np.testing.assert_allclose(train_time[:, known], run_time[:, known], atol=1e-5)
        if poses[0] == poses[2]:  # a still burst: the prior says nothing moved
            assert np.abs(train_time[:-1]).max() < 1e-6
        else:  # a moving one: the fringes move by a visible fraction of a period
            assert np.abs(train_time[2, known]).max() > 0.05
    fed = PriorInput(ds)[3]
    assert fed["input"].shape == (3 + PRIOR_CHANNELS, 160, 160)
    np.testing.assert_array_equal(fed["input"][:3], ds[3]["input"])
    with pytest.raises(KeyError, match="TwinBurstDataset\\(prior=True\\)"):
        PriorInput(TwinBurstDataset(root))[0]
    with pytest.raises(DatasetError, match="prior_jitter"):
        TwinBurstDataset(root, prior=True, prior_jitter=1.5)


def test_prior_jitter_scales_each_bursts_changes_within_its_bound(prior_dataset):
    root, _ = prior_dataset
    exact = TwinBurstDataset(root, prior=True)[40]
    factors = []
    jittered = TwinBurstDataset(root, prior=True, prior_jitter=0.05, seed=3)
    for _ in range(20):
        item = jittered[40]
        big = np.abs(exact["prior_change"]) > 0.1
        ratio = item["prior_change"][big] / exact["prior_change"][big]
        assert np.ptp(ratio) < 1e-5  # one factor per burst
        factors.append(float(ratio.mean()))
    assert 0.95 - 1e-6 <= min(factors) and max(factors) <= 1.05 + 1e-6 and np.ptp(factors) > 0.02
