"""The keep-bound rule's decision (``scripts/choose_keep_bound.py``, ``benchmarks/keep_bound_rule.md``) on small
made-up val tables: step 2's floors and tie, and step 1 comparing the two unwrap masks at the bounds that would ship
(session 46), not at 0.3 rad."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
BOUNDS = (0.2, 0.3, 0.4, 0.5, 0.7, 1.0, math.inf)
# per bound: still clipped RMS, still gross, still coverage, moving clipped RMS, moving gross, moving coverage
SAME = {0.2: (35.0, 0, 0.78, 78.0, 24000, 0.50), 0.3: (36.0, 700, 0.81, 82.0, 37000, 0.70),
        0.4: (37.0, 1300, 0.83, 86.0, 50000, 0.77), 0.5: (38.0, 1400, 0.84, 89.0, 58000, 0.80),
        0.7: (38.4, 11, 0.905, 89.8, 60000, 0.84), 1.0: (39.0, 25, 0.915, 92.9, 67000, 0.83),
        math.inf: (39.3, 53, 0.92, 94.8, 72000, 0.83)}


@pytest.fixture(scope="module")
def rule():
    sys.path.insert(0, str(SCRIPTS))
    try:
        import choose_keep_bound
    finally:
        del sys.path[0]
    assert choose_keep_bound.BOUNDS == BOUNDS
    return choose_keep_bound


def row(still_rms, still_gross, still_cov, moving_rms, moving_gross, moving_cov) -> dict:
    return {"still": {"clipped_rms_um": still_rms, "gross": still_gross, "coverage": still_cov},
            "moving": {"clipped_rms_um": moving_rms, "gross": moving_gross, "coverage": moving_cov}}


def table(rule, all_rows: dict, *, three_step_moving_cov: float = 0.55) -> dict:
    t = {rule.key("same", b): row(*SAME[b]) for b in BOUNDS}
    t.update({rule.key("all", b): row(*all_rows.get(b, SAME[b])) for b in BOUNDS})
    t[rule.key("same", math.inf)] = t[rule.key("all", math.inf)]  # without a bound the two masks are one setting
    t["three-step"] = row(38.5, 9, 0.88, 232.0, 650000, three_step_moving_cov)
    return t


def test_step_two_keeps_the_lowest_mean_clipped_rms_above_the_coverage_floors(rule):
    # floors: still >= 0.98 x 0.92, moving >= 0.9 x 0.83 and >= three-step's: 0.7, 1.0 and none admissible
    t = table(rule, {})
    assert rule.bound_under(t, "same") == 0.7
    # a bound within 1 % of the best mean clipped RMS wins when it is looser (more points)
    t[rule.key("same", 1.0)] = row(38.6, 25, 0.915, 90.0, 67000, 0.83)
    assert rule.bound_under(t, "same") == 1.0
    # no bound clears three-step PS's moving coverage: 0.3 stays
    assert rule.bound_under(table(rule, {}, three_step_moving_cov=0.99), "same") == 0.3


def test_step_one_compares_the_masks_at_the_bounds_that_ship_not_at_0_3_rad(rule):
    # "every pixel" is far better at 0.3 rad (what sessions 44-45 compared) but worse at the 0.7 both ship with
    better_at_03 = {0.3: (35.5, 0, 0.83, 82.6, 30000, 0.75), 0.7: (38.4, 11, 0.912, 91.0, 59000, 0.816)}
    t = table(rule, better_at_03)
    assert rule.beats(t["all/0.3"], t["same/0.3"])
    assert not rule.adopt_unwrap_all(t)
    assert rule.choose(t) == ("same", 0.7)
    # within 1 % in clipped RMS and coverage at 0.7, with fewer gross points: adopted, and its own bound ships
    t = table(rule, {0.7: (38.4, 11, 0.905, 90.5, 59000, 0.835)})
    assert rule.adopt_unwrap_all(t)
    assert rule.choose(t) == ("all", 0.7)
    # the same setting with one still gross point more is not adopted
    t = table(rule, {0.7: (38.4, 12, 0.905, 90.5, 59000, 0.835)})
    assert rule.choose(t) == ("same", 0.7)


def test_each_mask_takes_its_own_bound(rule):
    # "every pixel" clears the still floor already at 0.5 and is best there; it beats "same" at same's 0.7
    t = table(rule, {0.5: (37.0, 5, 0.91, 85.0, 50000, 0.84)})
    assert rule.bound_under(t, "all") == 0.5 and rule.bound_under(t, "same") == 0.7
    assert rule.choose(t) == ("all", 0.5)
    # no bound is best under both masks: they are one setting then, so "same" stays, reported as None
    t = table(rule, {math.inf: (30.0, 0, 0.92, 80.0, 40000, 0.85)})
    assert rule.bound_under(t, "all") == rule.bound_under(t, "same") == math.inf
    assert rule.choose(t) == ("same", None)
