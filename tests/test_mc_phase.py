"""Monte Carlo mode's phase: the deterministic pass's, with the passes' spread about it (benchmarks/mc_phase_rule.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from gearscan.core.gear import GearSpec
from gearscan.core.patterns import PatternSet
from gearscan.core.phase import phase_error
from gearscan.core.rig import default_rig
from gearscan.inference.model_io import ModelFileError
from gearscan.inference.predictor import DEFAULT_MODEL, Predictor, model_mc_phase
from gearscan.inference.uncertainty import MomentStats, moments_about
from gearscan.twin.render import Optics, TwinRenderer


def test_moments_about_a_point_add_the_offset_of_the_mean():
    """The passes' mean square deviation from the point: their variance plus the squared offset of their mean."""
    rng = np.random.default_rng(0)
    passes = torch.from_numpy(rng.normal(0.3, 0.05, (50, 2, 1, 4, 4)))  # 50 passes of M, D
    mean, var = passes.mean(0), passes.var(0, unbiased=False)
    mc = MomentStats(mean[0], mean[1], var[0], var[1], torch.full_like(var[0], 0.01), torch.full_like(var[0], 0.02))
    point = MomentStats(mean[0] + 0.1, mean[1] - 0.2, *(torch.zeros_like(var[0]),) * 4)
    out = moments_about(mc, point)
    torch.testing.assert_close(out.M, point.M)
    torch.testing.assert_close(out.D, point.D)
    torch.testing.assert_close(out.model_var_M, ((passes[:, 0] - point.M) ** 2).mean(0))
    torch.testing.assert_close(out.model_var_D, ((passes[:, 1] - point.D) ** 2).mean(0))
    torch.testing.assert_close(out.data_var_M, mc.data_var_M)  # the passes' data variance stays


@pytest.fixture(scope="module")
def moving_burst():
    """A 0.6 deg/frame burst of the default rig with a validation gear (z = 25), and its truth."""
    gear = GearSpec(teeth=25, module=2.0)
    twin = TwinRenderer(default_rig(128, 128, working_radius=gear.pitch_radius), gear, Optics())
    frames, truths = twin.render_sequence(np.radians([3.0, 3.6, 4.2]), PatternSet.three_step(40.0), [0, 1, 2], 5)
    return frames, truths[0]


V6 = DEFAULT_MODEL.with_name("v6.safetensors")  # the default until session 38; v9, shipped since, keeps the mean


def test_a_model_that_chose_the_deterministic_phase_reports_it_in_mc_mode(moving_burst):
    """v6's JSON chose the deterministic pass's phase for MC mode on val: an MC decode gives the deterministic phase,
    the same on every run, with a model sigma from the passes; the paper's MC mean varies between runs."""
    frames, _ = moving_burst
    shipped = Predictor.load(V6, orientation="normal")
    assert shipped.mc_phase == "deterministic"
    det = shipped.predict(frames)
    torch.manual_seed(0)
    a = shipped.predict(frames, 8)
    torch.manual_seed(1)
    b = shipped.predict(frames, 8)
    assert a.mode == "mc8"
    np.testing.assert_allclose(a.phase, det.phase, atol=1e-6)
    np.testing.assert_allclose(b.phase, a.phase, atol=1e-6)
    assert a.sigma_model.max() > 0 and not det.sigma_model.any()
    # the model variance is the passes' mean square deviation about the deterministic M, D: with the sigma maps off
    # and the same dropout draws, the mean-phase decode's variance plus its mean's squared offset
    raw = Predictor.load(V6, orientation="normal", still_burst_rad=0.0)
    raw.calibration = {}
    raw_mean = Predictor.load(V6, orientation="normal", still_burst_rad=0.0, mc_phase="mean")
    raw_mean.calibration = {}
    torch.manual_seed(3)
    about = raw.predict(frames, 8)
    torch.manual_seed(3)
    spread = raw_mean.predict(frames, 8)
    k = raw.var_scale  # every variance is scaled by the model's var_scale before propagation
    np.testing.assert_allclose(about.var_M, spread.var_M + k * (spread.M - about.M) ** 2, rtol=1e-3, atol=1e-7)
    np.testing.assert_allclose(about.var_D, spread.var_D + k * (spread.D - about.D) ** 2, rtol=1e-3, atol=1e-7)
    assert np.abs(spread.M - about.M).max() > 1e-3  # the offset is there to be added
    paper = Predictor.load(DEFAULT_MODEL, orientation="normal", mc_phase="mean")
    torch.manual_seed(0)
    m0 = paper.predict(frames, 8)
    torch.manual_seed(1)
    m1 = paper.predict(frames, 8)
    assert np.abs(phase_error(m0.phase, m1.phase)).max() > 1e-3  # two draws, two phases
    assert np.abs(phase_error(m0.phase, det.phase)).max() > 1e-3


def test_the_shipped_v9_chose_the_deterministic_phase_by_the_two_sided_rule(moving_burst):
    """v9's MC phase was chosen by benchmarks/mc_phase_rule_v2.md (session 41): the rule replayed on its stored val
    table gives the deterministic pass; its MC map is the one refitted for it; an MC decode reports that phase."""
    from gearscan.inference.mc_phase_choice import verdict_two_sided

    config = json.loads(DEFAULT_MODEL.with_suffix(".json").read_text())
    meta = config["mc_phase"]
    assert meta["phase"] == "deterministic" and meta["rule"].startswith("benchmarks/mc_phase_rule_v2.md")
    assert meta["seed"] == 11 and meta["bursts_per_family"] == {"moving": 96, "still": 48}
    table = {k: v for k, v in meta["val"].items() if k != "rule"}
    assert verdict_two_sided(table) == meta["val"]["rule"] and meta["val"]["rule"]["adopt"]
    assert all({"mc2", "mc3", "mc4", "mc5"} <= set(r) for r in table.values())
    assert config["sigma_calibration"]["mc"] == config["uncertainty_calibration"]["mc"]["map"]
    pred = Predictor.load(DEFAULT_MODEL, orientation="normal", still_burst_rad=0.0)
    assert pred.mc_phase == "deterministic"
    frames, _ = moving_burst
    torch.manual_seed(0)
    np.testing.assert_allclose(pred.predict(frames, 4).phase, pred.predict(frames).phase, atol=1e-6)


@pytest.mark.parametrize(("model", "rows", "rule"), [(V6, 7, "one-sided"),
                                                     (DEFAULT_MODEL.with_name("default_rig.safetensors"), 3, "two-sided")],
                         ids=["v6", "default-rig option"])
def test_the_val_choice_is_recorded_and_bad_entries_are_named(model, rows, rule, moving_burst):
    """v6 (one-sided rule, session 38) and the default-rig option (two-sided rule, rerun for the GPU fine-tune in session 54) chose the deterministic
    phase on val (the rule replayed on their tables), load with it, and carry the MC sigma map refitted for it; a bad
    entry is named."""
    from gearscan.inference.mc_phase_choice import verdict, verdict_two_sided

    config = json.loads(model.with_suffix(".json").read_text())
    meta = config["mc_phase"]
    assert meta["phase"] == "deterministic" and "val split" in meta["chosen_on"] and meta["val"]["rule"]["adopt"]
    table = {k: v for k, v in meta["val"].items() if k != "rule"}
    assert len(table) == rows
    draws = [k for k in next(iter(table.values())) if k.startswith("mc") and k[2:].isdigit()]
    assert all(r["mc_mean_of_draws"] == pytest.approx(np.mean([r[d] for d in draws])) for r in table.values())
    if rule == "one-sided":  # pooled moving no worse, and no family above 1.03 x the MC mean
        assert meta["rule"] == "benchmarks/mc_phase_rule.md" and draws == ["mc0", "mc1"]
        assert table["pooled:moving"]["det"] <= table["pooled:moving"]["mc_mean_of_draws"]
        assert all(r["det"] <= 1.03 * r["mc_mean_of_draws"] for r in table.values())
        assert verdict(table)["adopt"]
    else:
        assert meta["rule"].startswith("benchmarks/mc_phase_rule_v2.md") and draws == ["mc2", "mc3", "mc4", "mc5"]
        assert verdict_two_sided(table) == meta["val"]["rule"]
    assert config["sigma_calibration"]["mc"] == config["uncertainty_calibration"]["mc"]["map"]
    pred = Predictor.load(model, orientation="normal")
    assert pred.mc_phase == "deterministic"
    frames, _ = moving_burst
    torch.manual_seed(5)
    np.testing.assert_allclose(pred.predict(frames, 4).phase, pred.predict(frames).phase, atol=1e-6)
    assert model_mc_phase({}) == "mean"  # a model without the entry: the paper's mean
    with pytest.raises(ModelFileError, match="mc_phase.phase"):
        model_mc_phase({"mc_phase": {"phase": "median"}})
    with pytest.raises(ValueError, match="mc_phase"):
        Predictor.load(model, mc_phase="median")


def test_the_rule_adopts_the_deterministic_phase_only_when_no_worse():
    """benchmarks/mc_phase_rule.md on scripted tables: pooled moving no worse than the MC draws' mean, and no
    family's moving or still RMSE above 1.03 x it."""
    from gearscan.inference.mc_phase_choice import verdict

    def row(det: float, mc: float) -> dict:
        return {"det": det, "mc0": mc, "mc1": mc, "mc_mean_of_draws": mc}

    good = {"a:moving": row(0.10, 0.11), "a:still": row(0.05, 0.05), "pooled:moving": row(0.10, 0.11)}
    assert verdict(good)["adopt"]
    worse_pooled = {**good, "pooled:moving": row(0.111, 0.11)}
    assert not verdict(worse_pooled)["adopt"] and verdict(worse_pooled)["2 no family above 1.03x"]
    one_family_still = {**good, "a:still": row(0.0520, 0.05)}  # 1.04x
    assert not verdict(one_family_still)["adopt"] and verdict(one_family_still)["1 pooled moving det <= MC"]
    assert verdict({**good, "a:still": row(0.0514, 0.05)})["adopt"]  # 1.028x: within the bound


def test_the_two_sided_rule_picks_the_phase_with_the_lower_worst_cell():
    """benchmarks/mc_phase_rule_v2.md on scripted tables: each phase is judged by its worst cell against the other;
    within 1.03x everywhere, pooled moving RMSE decides (ties: deterministic)."""
    from gearscan.inference.mc_phase_choice import verdict_two_sided

    def row(det: float, mc: float) -> dict:
        return {"det": det, "mc2": mc, "mc3": mc, "mc_mean_of_draws": mc}

    # session 39's shape: det 1.04x on one family, the mean 1.22x on another -> deterministic
    mixed = {"r:moving": row(0.1085, 0.1043), "d:moving": row(0.0987, 0.1207), "r:still": row(0.05, 0.05),
             "pooled:moving": row(0.2727, 0.2759)}
    v = verdict_two_sided(mixed)
    assert v["phase"] == "deterministic" and v["adopt"] and v["decided by"].startswith("2")
    assert v["worst cell if deterministic"] == pytest.approx(0.1085 / 0.1043)
    assert v["worst cell if mean"] == pytest.approx(0.1207 / 0.0987)
    # the mirror image keeps the mean, even though det wins pooled
    mirror = {**mixed, "r:moving": row(0.1207, 0.0987), "d:moving": row(0.1043, 0.1085)}
    assert verdict_two_sided(mirror)["phase"] == "mean"
    # within 1.03x everywhere: pooled decides, either way
    close = {"a:moving": row(0.100, 0.101), "a:still": row(0.0505, 0.050), "pooled:moving": row(0.100, 0.101)}
    assert verdict_two_sided(close)["phase"] == "deterministic"
    assert verdict_two_sided({**close, "pooled:moving": row(0.102, 0.101)})["phase"] == "mean"
    assert verdict_two_sided({**close, "pooled:moving": row(0.101, 0.101)})["phase"] == "deterministic"
    with pytest.raises(ValueError, match="no family"):
        verdict_two_sided({"pooled:moving": row(0.1, 0.1)})
