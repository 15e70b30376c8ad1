"""The rest-sigma rule (``scripts/calibrate_rest_sigma.py``, ``benchmarks/rest_sigma_rule.md``) on made-up cells of
known error: the scale it picks for Gaussian errors of a known size against their stated sigma, a scale that passes
only by dropping every point said apart, and ``--write`` refusing to stamp a decode the cells did not run."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def rule():
    sys.path[:0] = [str(ROOT / "scripts"), str(ROOT / "benchmarks")]
    try:
        import calibrate_rest_sigma
    finally:
        del sys.path[:2]
    return calibrate_rest_sigma


def cell(true_over_stated: float, sigma_mm: float = 0.005, n: int = 20000, seed: int = 0) -> dict:
    """Unfitted points whose |error| is Gaussian with ``true_over_stated`` times their stated sigma."""
    rng = np.random.default_rng(seed)
    sigma = np.full(n, sigma_mm)
    return {"error_mm": np.abs(rng.normal(0.0, true_over_stated * sigma_mm, n)), "sigma_mm": sigma}


def test_honest_sigma_needs_no_scale(rule):
    """Errors 0.9x their sigma (an exact sigma sits on the rule's edge, a median |z| of 0.6745)."""
    rows, c = rule.scan([cell(0.9), cell(0.8, seed=1)], bound=0.030)
    assert c == 1.0 and len(rows) == 1
    assert 0.56 < rows[0]["cells"][0]["median_z"] < 0.65  # 0.9 x a Gaussian's median |z|: 0.607
    assert 0.018 < rows[0]["cells"][0]["beyond_2sigma"] < 0.034  # and its tail: P(|z| > 2.22) = 2.6 %


def test_sigma_stated_too_small_gets_the_smallest_honest_step(rule):
    """True errors 1.8x the stated sigma: 1.5 leaves a median |z| of 0.81, 2.0 gives 0.61 (in steps of 0.5)."""
    rows, c = rule.scan([cell(0.9), cell(1.8, seed=2)], bound=0.030)
    assert c == 2.0
    assert [r["scale"] for r in rows] == [1.0, 1.5, 2.0]
    assert not rule.honest(rows[1]["cells"]) and rule.honest(rows[2]["cells"])
    assert not rule.keeps_none(rows)


def test_a_scale_that_keeps_nothing_is_said(rule):
    """Sigma 12.5 um and errors 10x it: no scale calibrates them; 2.5 passes only because 31 um is over the 30 um
    bound (2.0: 25 um, all kept and dishonest)."""
    rows, c = rule.scan([cell(10.0, sigma_mm=0.0125)], bound=0.030)
    assert c == 2.5 and rule.keeps_none(rows)
    assert rows[-1]["cells"][0]["kept"] == 0 and rows[-2]["cells"][0]["kept"] == 20000


def test_write_refuses_cells_of_another_decode(rule, tmp_path):
    from gearscan.inference.model_io import model_fingerprint

    weights = ROOT / "inference" / "weights" / "default_rig.safetensors"
    json_path = weights.with_suffix(".json")
    before = json_path.read_bytes()
    now = model_fingerprint(weights)
    row = {"scale": 2.0, "keeps_no_unfitted_point": False, "scan": []}
    for scored in ("0123456789ab", None):  # another decode; a cell from before fingerprints were recorded
        done = {"cells": [{"model": "default-rig option", "model_fingerprint": now},
                          {"model": "default-rig option", "model_fingerprint": scored}],
                "scale_by_model": {"default-rig option": row}}
        with pytest.raises(SystemExit, match="scored with decode"):
            rule.write_option_scale(done, tmp_path / "rest.json")
    assert json_path.read_bytes() == before  # nothing written
