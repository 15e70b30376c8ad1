"""The modulation-test rule (``scripts/choose_frame_fit_modulation.py``, ``benchmarks/frame_fit_modulation_rule.md``):
it scores its candidates with the settle rule's decision, and the product ships what its val run shipped."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_the_rule_scores_its_field_with_the_settle_rules_decision():
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import choose_frame_fit_modulation as rule
        import choose_frame_fit_settle as settle
    finally:
        del sys.path[0]
    assert rule.CANDIDATES == (None, 1.0) and rule.FIELD == "modulation_ratio"
    cells = [{"model": "m", "seed": s, "order": o, rule.FIELD: c, "rms_um": r, "coverage": 0.98}
             for s in (31, 61) for o in ("fixed", "alternating") for c, r in ((None, 8.0), (1.0, 7.0))]
    got = settle.choose(cells, None, models=("m",), field=rule.FIELD, candidates=rule.CANDIDATES)
    assert got["chosen"] == 1.0 and got["score_um"] == {"off": pytest.approx(8.0), "1": pytest.approx(7.0)}


def test_the_product_ships_what_the_val_run_shipped():
    """``shipped`` in the run's json is set once the shipping condition is read (no json or no key: nothing ships)."""
    from gearscan.recon.track import MODULATION_RATIO

    path = ROOT / "benchmarks" / "frame_fit_modulation_val.json"
    run = json.loads(path.read_text()) if path.exists() else {}
    assert MODULATION_RATIO == run.get("shipped")
    if run.get("shipped") is not None:
        assert run["choice"]["chosen"] == run["shipped"]
