"""The settle-test rule's decision (``scripts/choose_frame_fit_settle.py``, ``benchmarks/frame_fit_settle_rule.md``) on
made-up val cells: the coverage and per-cell RMS floors against no test, the geometric mean and the 3 % margin; and the
product's constant against the val run's choice."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def rule():
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import choose_frame_fit_settle
    finally:
        del sys.path[0]
    assert choose_frame_fit_settle.CANDIDATES == (None, 0.3, 0.1, 0.03)
    return choose_frame_fit_settle


KEYS = [("m", 31, "fixed"), ("m", 31, "alternating"), ("m", 61, "fixed"), ("m", 61, "alternating")]


def cells(rms: dict, coverage: dict | None = None) -> list[dict]:
    """Cells with the same RMS per candidate on every key (``rms[c]``: a number or a list per key)."""
    out = []
    for i, (model, seed, order) in enumerate(KEYS):
        for c, r in rms.items():
            r = r[i] if isinstance(r, list) else r
            cov = (coverage or {}).get(c, 0.98)
            out.append({"model": model, "seed": seed, "order": order, "settle_rad": c, "rms_um": r,
                        "coverage": cov[i] if isinstance(cov, list) else cov})
    return out


def pick(rule, table: list[dict]) -> dict:
    return rule.choose(table, models=("m",))


def test_the_lowest_admissible_score_ships_when_it_clears_the_margin(rule):
    got = pick(rule, cells({None: 8.0, 0.3: 7.9, 0.1: 6.5, 0.03: 6.4}))
    assert got["chosen"] == 0.03 and got["best"] == 0.03
    assert got["score_um"]["0.1"] == pytest.approx(6.5)
    assert set(got["fresh_score_um"]) == {"off", "0.3", "0.1", "0.03"}


def test_a_gain_under_the_margin_keeps_no_test(rule):
    got = pick(rule, cells({None: 8.0, 0.3: 7.9, 0.1: 7.8, 0.03: 7.8}))  # 2.5 % lower: 3 % asked
    assert got["best"] in (0.1, 0.03) and got["chosen"] is None


def test_coverage_lost_on_one_cell_rules_a_candidate_out(rule):
    got = pick(rule, cells({None: 8.0, 0.3: 7.9, 0.1: 6.5, 0.03: 6.0},
                            {None: 0.98, 0.3: 0.98, 0.1: 0.976, 0.03: [0.98, 0.98, 0.974, 0.98]}))
    assert got["admissible"] == {"off": True, "0.3": True, "0.1": True, "0.03": False}
    assert got["chosen"] == 0.1


def test_one_cell_paying_more_than_5_percent_rules_a_candidate_out(rule):
    got = pick(rule, cells({None: [8.0, 4.0, 8.0, 4.0], 0.3: 7.9, 0.1: [6.0, 4.3, 6.0, 4.0],
                             0.03: [6.1, 4.19, 6.1, 4.1]}))
    assert not got["admissible"]["0.1"] and got["admissible"]["0.03"]
    assert got["chosen"] == 0.03


def test_a_missing_cell_is_refused_not_skipped(rule):
    partial = [c for c in cells({None: 8.0, 0.3: 7.9, 0.1: 6.5, 0.03: 6.4}) if not (c["seed"] == 61 and c["settle_rad"] == 0.1)]
    with pytest.raises(ValueError, match="missing"):
        rule.choose(partial, models=("m",))


def test_cells_of_other_models_are_not_pooled(rule):
    mixed = cells({None: 8.0, 0.3: 7.9, 0.1: 6.5, 0.03: 6.4}) + [
        {**c, "model": "other", "rms_um": 1.0} for c in cells({None: 8.0, 0.3: 7.9, 0.1: 6.5, 0.03: 6.4})]
    assert rule.choose(mixed, models=("m",))["score_um"]["off"] == pytest.approx(8.0)


def test_the_product_ships_what_the_val_run_chose_and_its_shipping_condition_passed():
    """``shipped`` in the run's json is set once the shipping condition is read (absent: nothing ships)."""
    from gearscan.recon.track import SETTLE_RAD

    run = json.loads((ROOT / "benchmarks" / "frame_fit_settle_val.json").read_text())
    shipped = run.get("shipped")
    assert SETTLE_RAD == shipped
    if shipped is not None:
        assert run["choice"]["chosen"] == shipped
