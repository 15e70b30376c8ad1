"""The fit-sigma rule's arithmetic (scripts/calibrate_fit_sigma.py, benchmarks/fit_sigma_rule.md)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "scripts"))
from calibrate_fit_sigma import choose, first_scale, honest, needed_scale  # noqa: E402


def _cell(seed, order, scale, z, q, beyond, coverage=0.98, measured=1.0):
    return {"seed": seed, "order": order, "scale": scale, "z_fitted_ray": z, "z_q9545_fitted_ray": q,
            "beyond_2sigma_fitted_ray": beyond, "coverage": coverage, "ray_measured_fitted": measured}


def test_the_needed_scale_is_the_worse_of_the_body_and_the_tail():
    assert needed_scale(_cell(1, "fixed", 1.0, 0.6745 * 1.04, 2.0 * 1.17, 0.06)) == pytest.approx(1.17)
    assert needed_scale(_cell(1, "fixed", 1.0, 0.6745 * 1.3, 2.0, 0.045)) == pytest.approx(1.3)


def test_the_first_scale_rounds_the_largest_cell_up_and_never_shrinks():
    rows = [_cell(1, "a", 1.0, 0.70, 2.10, 0.05), _cell(2, "a", 1.0, 0.60, 2.33, 0.06)]
    assert first_scale(rows) == pytest.approx(1.2)  # 2.33 / 2 = 1.165 -> 1.2
    assert first_scale([_cell(1, "a", 1.0, 0.50, 1.5, 0.01)]) == 1.0
    assert first_scale([_cell(1, "a", 1.0, 0.6745 * 1.1, 2.0, 0.04)]) == pytest.approx(1.1)  # on a step: not one more


def test_honesty_needs_both_the_median_and_the_tail():
    assert honest(_cell(1, "a", 1.2, 0.60, 1.9, 0.04))
    assert not honest(_cell(1, "a", 1.2, 0.68, 1.9, 0.04))
    assert not honest(_cell(1, "a", 1.2, 0.60, 2.1, 0.05))
    # a tail the rays could not measure is not an honest one
    assert not honest(_cell(1, "a", 1.2, 0.60, 1.9, 0.04, measured=0.99))


def test_choose_steps_up_until_every_cell_is_honest_and_counts_the_coverage_cost():
    cells = [_cell(1, "a", 1.0, 0.70, 2.3, 0.06, 0.980), _cell(2, "f", 1.0, 0.71, 2.2, 0.06, 0.970),
             # at s_1 = 1.15 one cell still fails the tail; at 1.2 both pass
             _cell(1, "a", 1.15, 0.61, 2.0, 0.046, 0.978), _cell(2, "f", 1.15, 0.62, 1.9, 0.04, 0.969),
             _cell(1, "a", 1.2, 0.58, 1.9, 0.04, 0.977), _cell(2, "f", 1.2, 0.59, 1.8, 0.03, 0.960)]
    out = choose(cells)
    assert out["s1"] == pytest.approx(1.15) and out["chosen"] == pytest.approx(1.2)
    assert out["coverage_cost"]["1 a"] == pytest.approx(0.003) and out["coverage_cost"]["2 f"] == pytest.approx(0.010)
    assert out["coverage_floor_met"] is False  # 1 point lost on one cell: beyond the 0.5-point floor
    assert choose(cells[:4])["chosen"] is None  # the run stopped before an honest scale: nothing chosen


def test_the_stored_val_run_recomputes_its_choice_and_the_product_ships_it():
    import json

    from gearscan.recon.track import FIT_SIGMA_SCALE

    stored = json.loads((ROOT / "benchmarks" / "fit_sigma_val.json").read_text())
    assert stored["split"] == "val" and len(stored["stretches"]) == 6
    again = choose(stored["cells"])
    assert again["chosen"] == stored["choice"]["chosen"] == pytest.approx(1.25)
    assert again["coverage_floor_met"]
    assert FIT_SIGMA_SCALE == stored["shipped"] == again["chosen"]
    # the shipping condition, recomputed from the committed inspection run (not from the json's own verdict): a later
    # run at this scale must meet it too
    run = json.loads((ROOT / stored["shipping_condition"]["report"].replace(".md", ".json")).read_text())
    assert run["fit_sigma_scale"] == FIT_SIGMA_SCALE
    assert run["fused_rms_mm"] <= 0.010 and run["coverage"] >= 0.880 - 0.01
    assert run["chipped"] == run["truth_chipped"]
    assert all(abs(measured - truth) <= 5 + 0.05 * abs(truth) for _, truth, measured, _ in run["rows"])
    # every one of the 12 cells failed honesty at 1 and passes at the chosen scale
    at = lambda s: [c for c in stored["cells"] if c["scale"] == s]  # noqa: E731
    assert len(at(1.0)) == len(at(again["chosen"])) == 12
    assert not any(honest(c) for c in at(1.0)) and all(honest(c) for c in at(again["chosen"]))
