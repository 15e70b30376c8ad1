"""`gearscan calibrate-uncertainty`: fit the sigma map on twin truth, store it, apply it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from gearscan.cli import app
from gearscan.core.gear import GearSpec
from gearscan.inference.calibrate import calibrate_model, collect_errors
from gearscan.inference.model_io import ModelFileError, save_model
from gearscan.inference.models import build_model, classical_md
from gearscan.inference.predictor import Predictor
from gearscan.inference.uncertainty import SigmaCalibration
from gearscan.twin.dataset import DatasetSpec, TwinBurstDataset, generate_dataset

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def val_set(tmp_path_factory):
    root = tmp_path_factory.mktemp("val")
    generate_dataset(root, DatasetSpec(gears=[GearSpec(teeth=20)], width=96, height=96, max_start_points=2))
    return root


@pytest.fixture
def model_path(tmp_path):
    torch.manual_seed(0)
    return save_model(build_model("cd-dcu-net", width=4, classical_input=True, residual=True).eval(),
                      tmp_path / "net.safetensors", var_scale=1.0)


def test_calibration_is_fitted_on_truth_stored_and_applied(val_set, model_path, tmp_path):
    out = tmp_path / "cal" / "net.safetensors"
    report = calibrate_model(model_path, val_set, items=8, mc=3, output=out)
    assert "sigma_calibration" not in json.loads(model_path.with_suffix(".json").read_text())  # source untouched
    meta = json.loads(out.with_suffix(".json").read_text())
    assert set(meta["sigma_calibration"]) == {"deterministic", "mc"}
    assert report["items"] == {"moving": 8, "still": 4}
    assert report["orientation"] == "normal"  # every twin rig's: no per-burst vote misreads enter the fit
    for mode in ("deterministic", "mc"):
        r = report[mode]
        assert r["all"]["event_score_after"] <= r["all"]["event_score_before"] and r["all"]["pixels"] > 1500
        (piece,) = r["held_out"]  # one folder: fitted on one start point, scored on the other
        assert piece["scored"] == "start points [1]"
        assert {"ece_moving", "ece_still"} <= set(piece["after"])
    # the predictor applies the stored map, reading the departure from the same frames
    ds = TwinBurstDataset(val_set, crop=None, reverse=True)
    pick = sorted(np.random.default_rng(0).choice(len(ds), 8, replace=False).tolist())
    raw, cal = collect_errors(Predictor.load(model_path), ds, pick), collect_errors(Predictor.load(out), ds, pick)
    np.testing.assert_array_equal(raw.error, cal.error)  # the phase is not touched
    stored = SigmaCalibration.from_json(meta["sigma_calibration"]["deterministic"])
    assert stored.needs_departure
    np.testing.assert_allclose(cal.sigma, stored(raw.sigma, raw.departure), rtol=1e-5)


def test_calibration_over_two_folders_scores_each_by_a_map_fitted_on_the_other(val_set, model_path, tmp_path):
    other = tmp_path / "val2"
    generate_dataset(other, DatasetSpec(gears=[GearSpec(teeth=17)], width=96, height=96, max_start_points=1, seed=5))
    report = calibrate_model(model_path, [val_set, other], items=4, mc=0, output=tmp_path / "c" / "n.safetensors")
    assert report["items"] == {"moving": 8, "still": 4}
    det = report["deterministic"]
    assert [p["scored"] for p in det["held_out"]] == [f"folder {val_set}", f"folder {other}"]
    # each folder is scored by a map fitted without it: neither is the map fitted on both
    assert all(p["map"] != det["map"] for p in det["held_out"]) and det["held_out"][0]["map"] != det["held_out"][1]["map"]


def test_cli_calibrates_in_place_and_names_bad_input(val_set, model_path, tmp_path):
    runner = CliRunner()
    res = runner.invoke(app, ["calibrate-uncertainty", str(val_set), "--model", str(model_path), "--items", "4", "--mc", "0"])
    assert res.exit_code == 0, res.output
    assert "deterministic: sigma' = " in res.output and "held-out start points [1]: ECE" in res.output
    assert f"wrote the sigma maps (deterministic) to {model_path.with_suffix('.json')}" in res.output
    # a held-out piece scored worse by the map than by the raw sigma is said (this tiny sample's may or may not be)
    import re

    pairs = [(float(b), float(a)) for b, a in re.findall(r"held-out [^:]+: ECE ([0-9.]+) -> ([0-9.]+)", res.output)]
    warned = "warning: deterministic: on start points" in res.output
    assert pairs
    if any(b < a for b, a in pairs):  # printed to 3 decimals: a printed tie says nothing either way
        assert warned, res.output
    if all(b > a for b, a in pairs):
        assert not warned, res.output
    meta = json.loads(model_path.with_suffix(".json").read_text())
    assert set(meta["sigma_calibration"]) == {"deterministic"} and meta["var_scale"] == 1.0
    not_a_dataset = tmp_path / "empty"
    not_a_dataset.mkdir()
    res = runner.invoke(app, ["calibrate-uncertainty", str(not_a_dataset), "--model", str(model_path)])
    assert res.exit_code == 2 and "empty" in res.output
    res = runner.invoke(app, ["calibrate-uncertainty", str(val_set), "--model", str(model_path), "--orientation", "up"])
    assert res.exit_code == 2 and "orientation: expected one of auto, normal, mirrored, got 'up'" in res.output, res.output
    res = runner.invoke(app, ["calibrate-uncertainty", str(val_set), "--model", str(model_path), "--items", "4",
                              "--mc", "0", "--form", "additive"])
    assert res.exit_code == 0, res.output
    assert "deterministic: additive map in log sigma (3 knots), departure (3 knots), density (3 knots)" in res.output
    assert "mc:" not in res.output  # --mc 0: no MC map fitted, none printed
    assert json.loads(model_path.with_suffix(".json").read_text())["sigma_calibration"]["deterministic"]["form"] == \
        "additive"
    res = runner.invoke(app, ["calibrate-uncertainty", f"{val_set},{tmp_path / 'nowhere'}", "--model", str(model_path)])
    assert res.exit_code == 2 and f"validation folder(s) '{tmp_path / 'nowhere'}': expected existing" in res.output
    res = runner.invoke(app, ["calibrate-uncertainty", f"{val_set},", "--model", str(model_path)])
    assert res.exit_code == 2 and "validation folder(s) '': expected existing" in res.output
    res = runner.invoke(app, ["calibrate-uncertainty", str(val_set), "--model", str(model_path), "--form", "spline"])
    assert res.exit_code == 2 and "form: expected one of ('power', 'additive', 'additive-local', " \
        "'additive-local-data')" in res.output, res.output
    res = runner.invoke(app, ["calibrate-uncertainty", str(val_set), "--model", str(model_path), "--items", "4",
                              "--form", "additive-local-data"])
    assert res.exit_code == 2 and "MC mode only; pass --modes mc (modes=('mc',)), got ('deterministic', 'mc')" \
        in res.output, res.output
    res = runner.invoke(app, ["calibrate-uncertainty", str(val_set), "--model", str(model_path), "--modes", "median"])
    assert res.exit_code == 2 and "modes: expected some of ('deterministic', 'mc'), got ('median',)" in res.output, \
        res.output


def test_collected_errors_follow_the_burst_gate_as_the_predictor_applies_it(val_set, model_path):
    """A gate wide enough to take every burst: the errors the calibration collects are three-step PS's,
    in Monte Carlo mode too (where the Predictor decides on the deterministic pass)."""
    from gearscan.core.phase import phase_error, still_phase, three_step

    ds = TwinBurstDataset(val_set, crop=None, reverse=True)
    pick = [0, 5]
    pred = Predictor.load(model_path, still_burst_rad=3.0)
    expected = np.concatenate([phase_error(still_phase(*three_step(ds[i]["input"][:3], 1.0)[1:])[0],
                                           ds[i]["phase"])[ds[i]["mask"]] for i in pick])
    for mc in (0, 2):
        px = collect_errors(pred, ds, pick, mc)
        np.testing.assert_allclose(px.error, expected, atol=1e-4)
        assert px.gated.all()  # scored, never fitted (the map does not touch them at run time)
        x = torch.from_numpy(np.asarray(ds[0]["input"], np.float32))[None]
        assert pred.predict_tensor(x, mc).mode == "three-step"


def test_the_sigma_map_is_fitted_without_the_gated_bursts():
    """Pixels of bursts the still-burst gate decoded keep three-step's sigma at run time, so the map is fitted
    on the others only, and scored with the gated pixels' own sigma."""
    from gearscan.inference.calibrate import PixelErrors, fit_mode

    rng = np.random.default_rng(3)
    n = 4000
    sigma = rng.uniform(0.02, 0.2, n).astype(np.float32)
    error = (rng.normal(0, 1, n) * 0.5 * sigma).astype(np.float32)  # the network's sigma is 2x too wide
    dep = np.abs(rng.normal(0, 0.05, n)).astype(np.float32)
    base = PixelErrors(error, sigma, dep, np.zeros(n, np.int16), np.arange(n, dtype=np.int32) % 8, np.zeros(n, bool),
                       np.zeros(n, bool), np.full(n, 0.3, np.float32), np.full(n, 0.1, np.float32), dep.copy(),
                       sigma.copy())
    # gated pixels: tiny errors with a huge sigma, which would drag a map fitted on them
    g = 2000
    gated = PixelErrors(np.full(g, 1e-3, np.float32), np.full(g, 5.0, np.float32), np.zeros(g, np.float32),
                        np.zeros(g, np.int16), np.arange(g, dtype=np.int32) % 8, np.ones(g, bool), np.ones(g, bool),
                        np.full(g, 0.3, np.float32), np.full(g, 0.1, np.float32), np.zeros(g, np.float32),
                        np.full(g, 5.0, np.float32))
    alone, _ = fit_mode(base, ["val"])
    mixed, report = fit_mode(PixelErrors.concat([base, gated]), ["val"])
    np.testing.assert_allclose(mixed(sigma, dep), alone(sigma, dep), rtol=1e-6)
    assert report["all"]["gated_pixels"] == g


def test_a_refit_of_the_mc_map_alone_keeps_the_deterministic_one(val_set, model_path, tmp_path):
    """``modes=("mc",)`` (after MC mode's phase changed, scripts/choose_mc_phase.py): the MC map is refitted for the
    deterministic phase the JSON now names; the deterministic map and its report stay as they were."""
    out = tmp_path / "cal" / "net.safetensors"
    calibrate_model(model_path, val_set, items=8, mc=3, output=out)
    meta = json.loads(out.with_suffix(".json").read_text())
    meta["mc_phase"] = {"phase": "deterministic"}
    out.with_suffix(".json").write_text(json.dumps(meta))
    torch.manual_seed(0)
    report = calibrate_model(out, val_set, items=8, mc=3, modes=("mc",))
    again = json.loads(out.with_suffix(".json").read_text())
    assert again["sigma_calibration"]["deterministic"] == meta["sigma_calibration"]["deterministic"]
    assert again["uncertainty_calibration"]["deterministic"] == meta["uncertainty_calibration"]["deterministic"]
    assert again["sigma_calibration"]["mc"] == report["mc"]["map"] != meta["sigma_calibration"]["mc"]
    assert again["mc_phase"] == {"phase": "deterministic"}
    with pytest.raises(ValueError, match="modes"):
        calibrate_model(out, val_set, items=8, mc=3, modes=("median",))
    with pytest.raises(ValueError, match="nothing to fit"):
        calibrate_model(out, val_set, items=8, mc=0, modes=("mc",))


def test_the_data_form_refits_the_mc_map_alone_and_the_predictor_applies_it(val_set, model_path, tmp_path):
    """``--form additive-local-data --modes mc`` (sigma_map_data_mc_rule.md): the MC map reads the aleatoric sigma
    apart, the deterministic map is kept, and MC mode's sigma is that map applied to the passes' own data sigma."""
    from gearscan.inference.uncertainty import FORM_FEATURES, map_form, map_inputs

    out = tmp_path / "cal" / "net.safetensors"
    calibrate_model(model_path, val_set, items=8, mc=3, output=out, form="additive-local")
    before = json.loads(out.with_suffix(".json").read_text())
    res = CliRunner().invoke(app, ["calibrate-uncertainty", str(val_set), "--model", str(out), "--items", "8",
                                   "--mc", "3", "--form", "additive-local-data", "--modes", "mc"])
    assert res.exit_code == 0, res.output
    assert "mc: additive map in log sigma (3 knots)" in res.output and "sigma_data (3 knots)" in res.output
    assert "deterministic:" not in res.output
    after = json.loads(out.with_suffix(".json").read_text())
    assert after["sigma_calibration"]["deterministic"] == before["sigma_calibration"]["deterministic"]
    pred = Predictor.load(out)
    cal = pred.calibration["mc"]
    assert map_form(cal) == "additive-local-data" and cal.features == FORM_FEATURES["additive-local-data"]
    assert after["uncertainty_calibration"]["mc"]["form"] == "additive-local-data"
    # MC mode's sigma: the stored map of the raw total and the passes' data sigma, drawn with the same masks
    ds = TwinBurstDataset(val_set, crop=None, reverse=True)
    x = torch.from_numpy(np.asarray(ds[0]["input"], np.float32))[None]
    raw_pred = Predictor.load(out)
    raw_pred.calibration = {}
    raw_pred.still_gate_rad = raw_pred.still_burst_rad = pred.still_gate_rad = pred.still_burst_rad = 0.0
    torch.manual_seed(1)
    raw = raw_pred.predict_tensor(x, 3)
    torch.manual_seed(1)
    got = pred.predict_tensor(x, 3)
    np.testing.assert_array_equal(got.phase, raw.phase)
    classical = classical_md(x[:, :3])[0].numpy()
    inputs = map_inputs(cal, raw.phase, np.arctan2(*classical))
    np.testing.assert_allclose(got.sigma_total, cal(raw.sigma_total, sigma_data=raw.sigma_data, **inputs), rtol=1e-4)
    with pytest.raises(ValueError, match="MC mode only"):
        calibrate_model(out, val_set, items=8, mc=3, modes=("deterministic",), form="additive-local-data")
    # a data map copied into the deterministic slot: refused on load and on a refit that keeps the stored form
    meta = json.loads(out.with_suffix(".json").read_text())
    meta["sigma_calibration"]["deterministic"] = meta["sigma_calibration"]["mc"]
    out.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(ModelFileError, match="sigma_calibration.deterministic reads the aleatoric sigma apart"):
        Predictor.load(out)
    with pytest.raises(ModelFileError, match="sigma_calibration.deterministic reads the aleatoric sigma apart"):
        calibrate_model(out, val_set, items=8, mc=0, modes=("deterministic",))  # loads it first


def test_the_mc_phase_table_scores_each_draw_against_the_truth(val_set, model_path):
    """scripts/choose_mc_phase.py's table on a rendered val folder: the two-sided rule's four draws, each cell's
    MC figure the mean of the draws' RMSEs, pooled moving = the one family's moving cell, and a verdict."""
    from gearscan.inference.mc_phase_choice import mc_phase_table, verdict_two_sided

    table = mc_phase_table(str(model_path), {"v": [str(val_set)]}, seed=1, moving=4, still=2, passes=3,
                           rule="two-sided")
    assert set(table) == {"v:moving", "v:still", "pooled:moving", "rule"}
    row = table["v:moving"]
    assert set(row) == {"det", "mc2", "mc3", "mc4", "mc5", "mc_mean_of_draws"}
    assert row["mc_mean_of_draws"] == pytest.approx(np.mean([row[f"mc{s}"] for s in (2, 3, 4, 5)]))
    assert table["pooled:moving"] == pytest.approx(row)
    assert all(0 < v < np.pi for r in ("v:moving", "v:still") for v in table[r].values())
    assert len({row[f"mc{s}"] for s in (2, 3, 4, 5)}) > 1  # the draws differ: dropout is sampled
    assert table["rule"] == verdict_two_sided(table)
    with pytest.raises(ValueError, match="rule"):
        mc_phase_table(str(model_path), {"v": [str(val_set)]}, rule="median")


def test_an_additive_map_is_fitted_kept_on_refit_and_applied(val_set, model_path, tmp_path):
    """``form="additive"``: both modes' maps are stored in the additive form with their held-out check; a refit
    without a form keeps the model's; a family of pooled folders is one family (also given comma-joined, as the
    report stores it); the Predictor applies the stored map."""
    from gearscan.inference.uncertainty import AdditiveSigmaMap

    out = tmp_path / "add" / "net.safetensors"
    report = calibrate_model(model_path, val_set, items=8, mc=3, output=out, form="additive")
    meta = json.loads(out.with_suffix(".json").read_text())
    for mode in ("deterministic", "mc"):
        assert meta["sigma_calibration"][mode]["form"] == "additive" and report[mode]["form"] == "additive"
        assert report[mode]["held_out"] and report[mode]["all"]["form"] == "additive"
    pred = Predictor.load(out)
    assert isinstance(pred.calibration["deterministic"], AdditiveSigmaMap)
    again = calibrate_model(out, [[val_set, val_set]], items=8, mc=3, modes=("deterministic",))
    assert again["deterministic"]["form"] == "additive"  # the model's form, kept
    assert again["data"] == [f"{val_set},{val_set}"] and again["items"] == {"moving": 8, "still": 4}
    assert calibrate_model(out, again["data"], items=8, mc=3, modes=("deterministic",))["items"] == again["items"]
    before = json.loads(out.with_suffix(".json").read_text())
    power = calibrate_model(out, val_set, items=8, mc=0, form="power", seed=3)  # mc=0: the MC map is kept
    after = json.loads(out.with_suffix(".json").read_text())
    assert after["sigma_calibration"]["mc"] == before["sigma_calibration"]["mc"] and power["fitted"] == ["deterministic"]
    kept = after["uncertainty_calibration"]["mc"]  # its own sample, not this run's
    assert kept["seed"] == 0 and kept["orientation"] == "normal" and after["uncertainty_calibration"]["seed"] == 3
    assert power["deterministic"]["form"] == "power" and "form" not in power["deterministic"]["map"]
    with pytest.raises(ValueError, match="form"):
        calibrate_model(out, val_set, items=8, form="spline")
    with pytest.raises(ValueError, match=r"val family '.*,': expected one or more folder names"):
        calibrate_model(out, f"{val_set},", items=8)
    with pytest.raises(ValueError, match=r"cannot be shared out over the 3 folders .* expected items >= 6"):
        calibrate_model(out, [[val_set] * 3], items=4)
    # a stored comma-joined family draws the same sample through val_samples (scripts/score_sigma_map.py)
    from gearscan.inference.calibrate import val_samples

    joined = val_samples(again["data"], 8, 0, False)
    assert [(k, len(p), st) for k, _, p, st in joined] == [(0, 4, False), (0, 2, True), (0, 4, False), (0, 2, True)]


def test_a_local_map_is_fitted_on_every_feature_and_kept_on_refit(val_set, model_path, tmp_path):
    """``form="additive-local"``: the deterministic map reads the curvature and the local departure too, the MC map
    keeps its form; a refit without a form keeps the local one; the Predictor applies it."""
    from gearscan.inference.uncertainty import FORM_FEATURES, map_form

    out = tmp_path / "local" / "net.safetensors"
    report = calibrate_model(model_path, val_set, items=8, mc=0, output=out, form="additive-local")
    assert report["fitted"] == ["deterministic"] and report["deterministic"]["form"] == "additive-local"
    pred = Predictor.load(out)
    cal = pred.calibration["deterministic"]
    assert map_form(cal) == "additive-local" and cal.features == FORM_FEATURES["additive-local"]
    again = calibrate_model(out, val_set, items=8, mc=0)
    assert again["deterministic"]["form"] == "additive-local"
    r = pred.predict(np.stack([127 + 100 * np.cos(2 * np.pi * np.arange(48)[None, :] / 9 + d) * np.ones((32, 1))
                               for d in (0.0, 2 * np.pi / 3, 4 * np.pi / 3)]).astype(np.uint8))
    assert np.all(np.isfinite(r.sigma_total)) and np.all(r.sigma_total > 0)
