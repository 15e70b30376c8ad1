"""The joint frame-fit rule (``scripts/choose_frame_fit_joint.py``, ``benchmarks/frame_fit_joint_rule.md``) on made-up
cells: its floors are the incumbent's, a change needs the margin, a missing cell is refused, fresh seeds are read out
apart, and the product ships the incumbent or the run's choice."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def rule():
    sys.path.insert(0, str(ROOT / "scripts"))
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import choose_frame_fit_joint
    finally:
        del sys.path[:2]
    return choose_frame_fit_joint


def cells(rule, rms: dict, coverage: dict | None = None, seeds=(31, 89)) -> list[dict]:
    """Every pair on every (seed, order): ``rms`` / ``coverage`` by pair (default 6 um / 98 %), the same on every cell
    unless a value is a dict by (seed, order)."""
    def at(table, pair, key, default):
        v = (table or {}).get(pair, default)
        return v.get(key, default) if isinstance(v, dict) else v

    return [{"seed": s, "order": o, "max_sigma": p[0], "support_px": p[1],
             "rms_um": at(rms, p, (s, o), 6.0), "coverage": at(coverage, p, (s, o), 0.98)}
            for s in seeds for o in ("alternating", "fixed") for p in rule.PAIRS]


def test_the_incumbent_stays_without_the_margin(rule):
    got = rule.choose(cells(rule, {(1.0, 0): 5.9}))  # 1.7 % better: not enough
    assert got["best"] == [1.0, 0] and got["chosen"] == list(rule.INCUMBENT)


def test_a_pair_with_the_margin_replaces_the_incumbent(rule):
    got = rule.choose(cells(rule, {(0.5, None): 5.0, (1.0, None): 5.5}))
    assert got["chosen"] == [0.5, None] and got["chosen_label"] == "0.5 rad / off"
    assert got["score_um"]["0.5 rad / off"] == pytest.approx(5.0)


def test_the_floors_are_the_incumbents_on_every_cell(rule):
    # better overall, but one cell loses 0.6 coverage points against the incumbent: not admissible
    got = rule.choose(cells(rule, {(0.5, 0): 5.0}, {(0.5, 0): {(89, "fixed"): 0.974}}))
    assert got["admissible"]["0.5 rad / 0 px"] is False and got["chosen"] == list(rule.INCUMBENT)
    # one cell 6 % worse than the incumbent's, the rest far better: not admissible
    got = rule.choose(cells(rule, {(1.0, None): {(31, "alternating"): 6.36, (31, "fixed"): 4.0, (89, "alternating"): 4.0,
                                                  (89, "fixed"): 4.0}}))
    assert got["admissible"]["1 rad / off"] is False
    # one cell at or above the 10 um target: not admissible, even against an incumbent above it too
    high = {(31, "fixed"): 10.0}
    got = rule.choose(cells(rule, {rule.INCUMBENT: high, (0.5, None): {(31, "fixed"): 10.2, (31, "alternating"): 3.0}}))
    assert got["admissible"]["0.5 rad / off"] is False


def test_with_no_pair_admissible_the_incumbent_stays(rule):
    # every cell of every pair at or above the target, the incumbent's too: nothing is admissible, nothing changes
    got = rule.choose(cells(rule, {p: 12.0 for p in rule.PAIRS} | {(0.5, None): 10.5}))
    assert not any(got["admissible"].values()) and got["chosen"] == list(rule.INCUMBENT)


def test_fresh_seeds_are_read_out_apart(rule):
    got = rule.choose(cells(rule, {(0.5, 0): {(89, "alternating"): 3.0, (89, "fixed"): 3.0}}))
    assert got["fresh_score_um"]["0.5 rad / 0 px"] == pytest.approx(3.0)
    assert got["per_order_score_um"]["fixed"]["0.5 rad / 0 px"] == pytest.approx((6.0 * 3.0) ** 0.5)


def test_a_missing_cell_is_refused(rule):
    c = cells(rule, {})
    with pytest.raises(ValueError, match="every pair on every cell"):
        rule.choose(c[1:])


def test_the_product_ships_the_incumbent_or_the_runs_choice(rule):
    """Until the run's json records ``shipped`` (set once the shipping condition is read), the incumbent ships."""
    from gearscan.inference.decoder import Decoder
    from gearscan.recon.measure import FRAME_FIT_MAX_SIGMA_RAD

    path = ROOT / "benchmarks" / "frame_fit_joint_val.json"
    run = json.loads(path.read_text()) if path.exists() else {}
    want = tuple(run["shipped"]) if run.get("shipped") is not None else rule.INCUMBENT
    assert (FRAME_FIT_MAX_SIGMA_RAD, Decoder(None).network_support.frame_fit_px) == want
