"""The depth-sigma rule's arithmetic (scripts/calibrate_depth_sigma.py, benchmarks/depth_sigma_rule.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "scripts"))
from calibrate_depth_sigma import (  # noqa: E402
    CHECK_BEYOND_2,
    CHECK_MIN_POINTS,
    check,
    choose,
    choose_pooled,
    choose_worst_family,
    family,
    family_scales,
    recheck,
)

from gearscan.recon.depth_sigma import (  # noqa: E402
    DEPTH_SIGMA_BY_CLASS,
    DEPTH_SIGMA_SCALES,
    EDGE_BANDS_PX,
    FIRST_CHOICE_SCALES,
    MOTION_CLASSES,
    TRAINED_SPAN_DEG,
    band_labels,
    check_scales,
)


def _table(needs: dict[str, list[float]], beyond: float = 0.04, points: int = 5000) -> dict:
    return {kind: {label: {"points": points, "median": 0.5, "beyond_2sigma": beyond, "z_q9545": 2 * n,
                           "needed_scale": n} for label, n in zip(band_labels(), ns, strict=True)}
            for kind, ns in needs.items()}


def test_the_first_choice_takes_each_bands_larger_need_rounded_up_and_never_shrinks() -> None:
    fit = _table({"still": [2.94, 1.46, 0.9, 1.21, 1.19], "moving": [4.94, 1.2, 0.8, 1.82, 1.3999]})
    assert choose_pooled(fit) == (4.95, 1.5, 1.0, 1.85, 1.4)
    assert choose_pooled(_table({"still": [1.1] * 5, "moving": [1.25] * 5})) == (1.25,) * 5  # on a step: not one more


def test_each_motion_class_takes_its_own_need_and_every_class_must_have_points() -> None:
    needs = {c: [1.0 + i + 0.01 * b for b in range(5)] for i, c in enumerate(MOTION_CLASSES)}
    needs["three_step"] = [0.5, 1.21, 1.2, 1.0, 0.9]
    out = choose(_table(needs))
    assert out["three_step"] == (1.0, 1.25, 1.2, 1.0, 1.0)  # rounded up to 0.05 (on a step: not one more), >= 1
    assert out["network_faster"] == (4.0, 4.05, 4.05, 4.05, 4.05)
    thin = _table(needs)
    thin["network_fast"]["0-1.5 px"] = {"points": 0}
    with pytest.raises(ValueError, match="network_fast.*0-1.5 px"):
        choose(thin)


def test_the_worst_family_rules_each_class_and_band_where_it_has_enough_points() -> None:
    assert [family(r) for r in ("data/repro/val_radial", "data/repro/val_views", "data/default_rig/val/z25")] == [
        "val_radial", "val_views", "default_rig"]
    needs = {f"{fam}/{c}": [1.1 + i] * 5 for i, fam in enumerate(("val_radial", "val_views", "default_rig"))
             for c in MOTION_CLASSES}
    fit = _table(needs)
    fit["val_views/network"]["8.5-inf px"]["needed_scale"] = 9.0
    fit["default_rig/network"]["0-1.5 px"].update(needed_scale=20.0, points=CHECK_MIN_POINTS - 1)  # too few: not counted
    out = choose_worst_family(fit)
    assert out["network"] == (2.1, 3.1, 3.1, 3.1, 9.0) and out["three_step"] == (3.1,) * 5  # band 0: default_rig uncounted
    assert family_scales(fit, out)["val_radial/network"] == out["network"]
    for kind in [k for k in fit if k.endswith("/network_fast")]:
        fit[kind]["1.5-2.5 px"]["points"] = 10
    with pytest.raises(ValueError, match="network_fast.*1.5-2.5 px"):
        choose_worst_family(fit)


def test_the_check_reads_the_raw_grid_at_each_bands_scale() -> None:
    raw = _table({"still": [1.0] * 5, "moving": [1.0] * 5})
    for kind in raw:
        for cell in raw[kind].values():
            cell["beyond_2x_scale"] = {"1.00": 0.2, "1.50": 0.05, "2.00": 0.01}
    out = recheck(raw, (2.0, 1.5, 1.5, 1.0, 1.0))
    assert [c["beyond_2sigma"] for c in out["moving"].values()] == [0.01, 0.05, 0.05, 0.2, 0.2]
    assert len(check(out)) == 4  # the two 1.0 bands, still and moving
    per_kind = recheck(raw, {"still": (2.0,) * 5, "moving": (1.0, 1.5, 2.0, 2.0, 2.0)})  # each kind its own
    assert [c["beyond_2sigma"] for c in per_kind["moving"].values()] == [0.2, 0.05, 0.01, 0.01, 0.01]
    assert check(per_kind) == ["moving 0-1.5 px: 20.0% beyond 2 sigma"]


def test_the_check_judges_every_cell_large_enough_to_count() -> None:
    ok = _table({"still": [1.0] * 5, "moving": [1.0] * 5}, beyond=CHECK_BEYOND_2)
    assert check(ok) == []
    bad = json.loads(json.dumps(ok))
    bad["moving"]["8.5-inf px"]["beyond_2sigma"] = 0.06
    assert check(bad) == ["moving 8.5-inf px: 6.0% beyond 2 sigma"]
    bad["moving"]["8.5-inf px"]["points"] = 999  # too few to judge
    assert check(bad) == []


def test_the_stored_val_run_recomputes_its_choice_and_the_product_ships_it() -> None:
    """The fifth amendment's run (benchmarks/depth_sigma_val.json): per motion class and band the worst val family's
    need, recomputed from its fit table; the check recomputed from its raw check table (not from the json's verdict),
    in every family's cell, on a seed set no earlier form saw."""
    from gearscan.inference.model_io import model_fingerprint
    from gearscan.inference.predictor import DEFAULT_MODEL

    stored = json.loads((ROOT / "benchmarks" / "depth_sigma_val.json").read_text())
    earlier = {name: json.loads((ROOT / "benchmarks" / f"depth_sigma_val_{name}.json").read_text())
               for name in ("pooled", "amend2_missed", "amend3", "amend4_missed")}
    assert stored["split"] == "val" and stored["fit_seed"] != stored["check_seed"] and stored["per_motion"] == 5
    assert stored["check_seed"] not in {e["check_seed"] for e in earlier.values()}  # a fresh check set
    assert stored["model_fingerprint"] == model_fingerprint(DEFAULT_MODEL)  # chosen for the decode that ships
    assert stored["edge_bands_px"] == list(EDGE_BANDS_PX)
    assert stored["motion_classes"] == {"classes": list(MOTION_CLASSES), "trained_span_deg": TRAINED_SPAN_DEG}
    assert (stored["check_bound_beyond_2sigma"], stored["check_min_points"]) == (CHECK_BEYOND_2, CHECK_MIN_POINTS)
    assert {k.split("/")[0] for k in stored["fit_raw"]} == {"val_radial", "val_views", "default_rig"}
    chosen = choose_worst_family(stored["fit_raw"])
    assert chosen == {c: tuple(v) for c, v in stored["scales"].items()} == DEPTH_SIGMA_BY_CLASS
    assert check_scales(chosen) == DEPTH_SIGMA_SCALES
    per_kind = family_scales(stored["check_raw"], chosen)
    rechecked = recheck(stored["check_raw"], per_kind)
    assert check(rechecked) == [] and stored["check_passed"]
    for kind, cells in stored["check_raw"].items():  # the scaled table the run wrote is the raw one divided
        for (label, raw), scale in zip(cells.items(), per_kind[kind], strict=True):
            scaled = stored["check_scaled"][kind][label]
            assert scaled["median"] == pytest.approx(raw["median"] / scale)
            assert scaled["beyond_2sigma"] == pytest.approx(rechecked[kind][label]["beyond_2sigma"], abs=1e-9)
    # raw, the network classes flattered on the radial rigs in every band (what the rule is for), and the farther a
    # burst spans beyond its training, the more its sigma is widened
    for cls in ("network", "network_fast", "network_faster"):
        assert all(c["beyond_2sigma"] > 0.0455 for c in stored["check_raw"][f"val_radial/{cls}"].values())
    assert all(chosen["network_faster"][b] >= chosen["network_fast"][b] >= chosen["network"][b] for b in range(5))
    # the earlier forms, each recomputed from its own record, so that what they say can fail:
    first = earlier["pooled"]  # session 50's one set for every burst
    assert choose_pooled(first["fit_raw"]) == tuple(first["scales"]) == FIRST_CHOICE_SCALES
    missed = earlier["amend2_missed"]  # one fast class: missed its check, nothing shipped
    missed_scales = {c: tuple(v) for c, v in missed["scales"].items()}
    assert choose(missed["fit_raw"], classes=tuple(missed["fit_raw"])) == missed_scales
    assert check(recheck(missed["check_raw"], missed_scales)) == ["network_fast 8.5-inf px: 6.1% beyond 2 sigma"]
    third = earlier["amend3"]  # four classes, pooled over families: passed, shipped, replaced by this one
    assert choose(third["fit_raw"]) == {c: tuple(v) for c, v in third["scales"].items()}
    assert check(recheck(third["check_raw"], choose(third["fit_raw"]))) == [] and third["check_passed"]
    fourth = earlier["amend4_missed"]  # the worst family at one burst per motion: missed
    fourth_scales = choose_worst_family(fourth["fit_raw"])
    assert fourth_scales == {c: tuple(v) for c, v in fourth["scales"].items()}
    assert check(recheck(fourth["check_raw"], family_scales(fourth["check_raw"], fourth_scales))) == [
        "val_radial/network_faster 8.5-inf px: 5.7% beyond 2 sigma", "val_views/network_fast 4.5-8.5 px: 6.2% beyond 2 sigma"]


def test_the_inspection_revolution_met_the_shipping_condition_with_these_scales() -> None:
    """Recomputed from the committed inspection run (benchmarks/inspect_report.json), which records the scales."""
    from gearscan.recon.track import REST_SIGMA_SCALE

    run = json.loads((ROOT / "benchmarks" / "inspect_report.json").read_text())
    assert run["depth_sigma_scales"] == DEPTH_SIGMA_SCALES.as_dict() and run["rest_sigma_scale"] == REST_SIGMA_SCALE
    assert run["fused_rms_mm"] <= 0.004 and run["coverage"] >= 0.875
    assert run["chipped"] == run["truth_chipped"]
    assert all(abs(measured - truth) <= 5 + 0.05 * abs(truth) for _, truth, measured, _ in run["rows"])
    assert run["fp_max_error_um"] <= 5 + 0.05 * 30  # the per-tooth fp row of the report (its truth: 30 um)


def test_the_default_rig_options_own_scales_are_its_val_choice() -> None:
    """The rule's amendment: a model fine-tuned on one rig carries scales chosen on that rig's val scenes, recomputed
    here from the committed run and compared with what its JSON carries (the reconstructor reads them from there).
    The option fine-tuned on a GPU (session 54) by the eighth amendment's protocol (30 bursts per motion, fit seed set
    2000, check 3200); the runs that chose its predecessor's (v6 fine-tuned, fingerprint 89a4a8767165, weights in git
    history) stay as the amendments' record and are recomputed below."""
    from gearscan.inference.model_io import model_fingerprint, read_config
    from gearscan.inference.predictor import model_depth_sigma_scales

    weights = ROOT / "inference" / "weights" / "default_rig.safetensors"
    meta = read_config(weights)
    assert meta["depth_sigma"]["edge_bands_px"] == list(EDGE_BANDS_PX)
    gpu = json.loads((ROOT / "benchmarks" / "depth_sigma_val_default_rig_gpu.json").read_text())
    assert gpu["model_fingerprint"] == model_fingerprint(weights) == meta["depth_sigma"]["model_fingerprint"]
    assert all(s.startswith("data/default_rig/val/") for s in gpu["sets"])  # its own rig's val gears only
    assert (gpu["per_motion"], gpu["fit_seed"], gpu["check_seed"]) == (30, 2000, 3200)
    own = choose_worst_family(gpu["fit_raw"])
    assert own == {c: tuple(v) for c, v in gpu["scales"].items()}
    assert check(recheck(gpu["check_raw"], family_scales(gpu["check_raw"], own))) == [] and gpu["check_passed"]
    assert gpu["written"] == "default_rig.json" and model_depth_sigma_scales(meta) == own

    # the predecessor's record: every run on one model, its own rig's val gears
    stored = json.loads((ROOT / "benchmarks" / "depth_sigma_val_default_rig.json").read_text())
    old = stored["model_fingerprint"]
    assert old == "89a4a8767165" != gpu["model_fingerprint"]
    assert all(s.startswith("data/default_rig/val/") for s in stored["sets"])
    scales = choose_pooled(stored["fit_raw"])  # the first amendment: one set for every burst of this model
    assert check(recheck(stored["check_raw"], scales)) == [] and stored["check_passed"]
    assert scales == tuple(stored["scales"])  # what it carried until the eighth amendment (below)
    # the sixth amendment (per class, the fifth form) missed its check on those gears: recomputed, nothing written
    classes = json.loads((ROOT / "benchmarks" / "depth_sigma_val_default_rig_classes.json").read_text())
    assert classes["model_fingerprint"] == old and "written" not in classes
    per_class = choose_worst_family(classes["fit_raw"])
    assert per_class == {c: tuple(v) for c, v in classes["scales"].items()} and not classes["check_passed"]
    assert check(recheck(classes["check_raw"], family_scales(classes["check_raw"], per_class))) == [
        "default_rig/network_fast 1.5-2.5 px: 5.6% beyond 2 sigma", "default_rig/network_fast 2.5-4.5 px: 6.1% beyond 2 sigma"]
    # ... and the seventh (10 bursts per motion) missed too: recomputed, nothing written
    tenfold = json.loads((ROOT / "benchmarks" / "depth_sigma_val_default_rig_classes10.json").read_text())
    assert tenfold["per_motion"] == 10 and tenfold["check_seed"] not in (classes["check_seed"], classes["fit_seed"])
    assert tenfold["model_fingerprint"] == old and "written" not in tenfold and not tenfold["check_passed"]
    ten = choose_worst_family(tenfold["fit_raw"])
    assert ten == {c: tuple(v) for c, v in tenfold["scales"].items()}
    assert check(recheck(tenfold["check_raw"], family_scales(tenfold["check_raw"], ten))) == [
        "default_rig/network_faster 8.5-inf px: 5.9% beyond 2 sigma"]
    # the eighth (30 bursts per motion, a fresh check set) passed and was what the predecessor carried
    thirty = json.loads((ROOT / "benchmarks" / "depth_sigma_val_default_rig_classes30.json").read_text())
    assert thirty["model_fingerprint"] == old and thirty["per_motion"] == 30
    seen = {stored["check_seed"], classes["check_seed"], tenfold["check_seed"], classes["fit_seed"]}
    assert thirty["fit_seed"] == 2000 and thirty["check_seed"] not in seen
    eighth = choose_worst_family(thirty["fit_raw"])
    assert eighth == {c: tuple(v) for c, v in thirty["scales"].items()}
    assert check(recheck(thirty["check_raw"], family_scales(thirty["check_raw"], eighth))) == [] and thirty["check_passed"]
    assert thirty["written"] == "default_rig.json"
    assert thirty["model_scales_before"] == {c: list(scales) for c in eighth}  # the first amendment's one set ...
    before = check(thirty["check_model_before_scaled"])  # ... flattered the fast classes on that check set
    assert before == thirty["check_model_before_misses"] and before and all("network_fast" in m for m in before)
    # and with the product's scales its moving bursts flattered on those gears (why it has its own)
    shipped = json.loads((ROOT / "benchmarks" / "depth_sigma_check_default_rig.json").read_text())
    assert shipped["scales"] == list(FIRST_CHOICE_SCALES) and not shipped["check_passed"]  # the product's then
    assert check(recheck(shipped["check_raw"], FIRST_CHOICE_SCALES))


def test_monte_carlo_modes_scales_are_the_ninth_amendments_val_choice() -> None:
    """The ninth amendment: the fifth form on MC decodes (T = 20) of the same val scenes, recomputed from the committed
    run; its check passed on a fresh seed set, where the deterministic table missed in one cell."""
    from gearscan.inference.model_io import model_fingerprint
    from gearscan.inference.predictor import DEFAULT_MODEL
    from gearscan.recon.depth_sigma import DEPTH_SIGMA_BY_CLASS_MC

    run = json.loads((ROOT / "benchmarks" / "depth_sigma_val_mc.json").read_text())
    det = json.loads((ROOT / "benchmarks" / "depth_sigma_val.json").read_text())
    assert run["mc"] == 20 and run["model_fingerprint"] == model_fingerprint(DEFAULT_MODEL) == det["model_fingerprint"]
    assert run["fit_seed"] == det["fit_seed"] and run["check_seed"] not in (det["check_seed"], det["fit_seed"])
    chosen = choose_worst_family(run["fit_raw"])
    assert chosen == {c: tuple(v) for c, v in DEPTH_SIGMA_BY_CLASS_MC.items()} == {
        c: tuple(v) for c, v in run["scales"].items()}
    assert check(recheck(run["check_raw"], family_scales(run["check_raw"], chosen))) == [] and run["check_passed"]
    assert chosen["three_step"] == DEPTH_SIGMA_SCALES.by_class["three_step"]  # three-step PS decodes alike
    misses = check(run["check_deterministic_scales_scaled"])
    assert misses == run["check_deterministic_scales_misses"] == ["val_radial/network_faster 8.5-inf px: 6.0% beyond 2 sigma"]


def test_the_options_revolution_met_the_amendments_shipping_condition_with_its_own_scales() -> None:
    """Recomputed from the committed run (benchmarks/inspect_default_rig_report.json), which records the scales its
    reconstructor read: the option's own depth-sigma and rest-sigma scales, from its JSON."""
    from gearscan.inference.model_io import read_config
    from gearscan.inference.predictor import model_depth_sigma_scales, model_rest_sigma_scale
    from gearscan.recon.track import REST_SIGMA_SCALE

    meta = read_config(ROOT / "inference" / "weights" / "default_rig.safetensors")
    own = model_depth_sigma_scales(meta)
    run = json.loads((ROOT / "benchmarks" / "inspect_default_rig_report.json").read_text())
    assert check_scales(run["depth_sigma_scales"]) == check_scales(own) != DEPTH_SIGMA_SCALES  # a flat list before s51
    assert run["rest_sigma_scale"] == model_rest_sigma_scale(meta) != REST_SIGMA_SCALE  # its own since session 54
    assert run["fused_rms_mm"] <= 0.0045 and run["coverage"] >= 0.867
    assert run["chipped"] == run["truth_chipped"] and run["fp_max_error_um"] <= 5 + 0.05 * 30
    assert all(abs(measured - truth) <= 5 + 0.05 * abs(truth) for _, truth, measured, _ in run["rows"])


def test_the_scripts_val_sets_name_what_is_wrong(tmp_path, monkeypatch) -> None:
    """``--sets`` (a user's model's own val scenes, README): folders relative to the working directory, each a twin
    dataset; anything else stops with the folder named and what was expected."""
    import argparse

    from calibrate_depth_sigma import val_sets

    ap = argparse.ArgumentParser(prog="calibrate_depth_sigma.py")
    (tmp_path / "gear1").mkdir()
    (tmp_path / "gear1" / "index.json").write_text("{}")
    monkeypatch.chdir(tmp_path)
    assert val_sets("gear1", ap) == (str(tmp_path / "gear1"),)  # outside the repository: absolute
    assert val_sets(None, ap) is None  # the product's val scenes
    for bad in ("gear2", "gear1,", ""):
        with pytest.raises(SystemExit):
            val_sets(bad, ap)


def test_the_script_refuses_a_model_without_its_json_and_val_scenes_too_small(tmp_path, monkeypatch, capsys) -> None:
    """A user's model whose JSON is missing stops before any decode with the file named; val scenes too small for
    the rule to choose in some class and band stop with why and what to do, and nothing is written."""
    import shutil

    import calibrate_depth_sigma as script

    from gearscan.inference.predictor import DEFAULT_MODEL

    lone = tmp_path / "lone.safetensors"
    shutil.copy(DEFAULT_MODEL, lone)  # the weights without their JSON
    (tmp_path / "val").mkdir()
    (tmp_path / "val" / "index.json").write_text("{}")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["calibrate_depth_sigma.py", "--model", str(lone), "--sets", "val",
                                      "--out", str(tmp_path / "o.json"), "--write"])
    with pytest.raises(SystemExit) as stop:
        script.main()
    assert stop.value.code == 2 and "--model" in capsys.readouterr().err
    own = tmp_path / "own.safetensors"
    shutil.copy(DEFAULT_MODEL, own)
    shutil.copy(DEFAULT_MODEL.with_suffix(".json"), own.with_suffix(".json"))
    before = own.with_suffix(".json").read_text()
    monkeypatch.setattr(sys, "argv", ["calibrate_depth_sigma.py", "--model", str(own), "--sets", "val",
                                      "--out", str(tmp_path / "o.json"), "--write"])
    monkeypatch.setattr(script, "collect", lambda *a, **k: {})  # no point in any cell: scenes far too small
    with pytest.raises(SystemExit) as stop:
        script.main()
    assert "too small for a measured choice" in str(stop.value.code) and "nothing written" in str(stop.value.code)
    assert own.with_suffix(".json").read_text() == before and not (tmp_path / "o.json").exists()
