"""The still-burst gate: a burst whose network phase stays within the noise of three-step PS over its
interior is decoded by three-step PS, so a still gear is measured as well as three-step measures it.
(Through the Predictor on a rendered still burst: tests/test_still_gate.py.)"""

from __future__ import annotations

import numpy as np
import pytest

from gearscan.core.types import PhaseResult
from gearscan.inference.model_io import ModelFileError
from gearscan.inference.predictor import (
    DEFAULT_MODEL,
    WEIGHTS_DIR,
    Predictor,
    burst_departure,
    burst_sigma_map,
    still_burst_gate,
)

OPTION = WEIGHTS_DIR / "default_rig.safetensors"


def _lit_square(size: int = 48, lit: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Three-step phase ramp and M, D: unit modulation on a centred square, none elsewhere."""
    phase3 = np.tile(np.linspace(-3.0, 3.0, size, dtype=np.float32), (size, 1))
    mod = np.zeros((size, size), np.float32)
    a = (size - lit) // 2
    mod[a:a + lit, a:a + lit] = 1.0
    return phase3, np.stack([mod * np.sin(phase3), mod * np.cos(phase3)])


def _result(phase: np.ndarray) -> PhaseResult:
    z = np.zeros_like(phase)
    return PhaseResult(phase.astype(np.float32), np.sin(phase), np.cos(phase), z, z + 0.1, z + 0.1)


def test_the_interior_median_ignores_edges_and_patches():
    """Wild departures on the lit square's rim and in one patch (what the network invents on a still
    gear) leave the interior median at the small departure elsewhere: the burst is gated."""
    phase3, classical = _lit_square()
    bump = np.full_like(phase3, 0.01)
    bump[8:12, :] = 0.8            # the rim, rows 8-11 of the lit square 8..39
    bump[20:26, 20:26] = 0.5       # a patch inside
    score = burst_departure(phase3 + bump, classical)
    assert score == pytest.approx(0.01, abs=1e-4)
    gated, taken = still_burst_gate(_result(phase3 + bump), classical, 0.025)
    assert taken
    lit = np.hypot(*classical) > 0
    np.testing.assert_allclose(gated.phase[lit], phase3[lit], atol=1e-6)
    np.testing.assert_array_equal(gated.sigma_total, np.full_like(phase3, 0.1))  # no map: sigma unchanged


def test_a_coherent_correction_keeps_the_network_result():
    phase3, classical = _lit_square()
    res = _result(phase3 + 0.1)
    out, taken = still_burst_gate(res, classical, 0.025)
    assert not taken and out is res


def test_too_few_interior_pixels_give_no_verdict():
    phase3, classical = _lit_square(lit=16)  # 10 x 10 interior after the 7x7 erosion: 100 < 256 px
    assert burst_departure(phase3, classical) is None
    assert not still_burst_gate(_result(phase3), classical, 0.5)[1]


def test_the_gated_sigma_map():
    phase3, classical = _lit_square()
    classical = classical * 0.5  # modulation 0.5 in the lit square
    gated, taken = still_burst_gate(_result(phase3), classical, 0.025, sigma_map=(0.2, 0.5, -1.0))
    assert taken
    i = (24, 24)
    assert gated.sigma_total[i] == pytest.approx(0.2 * 0.1**0.5 * 0.5**-1.0, rel=1e-5)
    assert gated.sigma_data[i] == pytest.approx(gated.sigma_total[i], rel=1e-5)  # ratio kept


def test_a_broken_sigma_map_in_the_json_is_named():
    with pytest.raises(ModelFileError, match="still_burst_gate.sigma"):
        burst_sigma_map({"still_burst_gate": {"rad": 0.025, "sigma": {"a": -1, "b": 1, "c": 0}}})
    with pytest.raises(ModelFileError, match="still_burst_gate.sigma"):
        burst_sigma_map({"still_burst_gate": {"rad": 0.025, "sigma": {"a": 1}}})
    assert burst_sigma_map({}) is None


@pytest.mark.parametrize("model", [DEFAULT_MODEL, OPTION], ids=["v6", "default-rig option"])
def test_the_models_record_the_val_choice(model):
    """Both models carry the val rule's choice (0.025 rad) and the val table it read; v6 ships with the
    gate off and says why (the test split's face and oblique views), the default-rig option with it on."""
    pred = Predictor.load(model)
    meta = pred.meta["still_burst_gate"]
    chosen = meta.get("val_choice_rad", meta["rad"])
    assert chosen == 0.025 and "val split" in meta["chosen_on"] and "still_burst_gate_rule" in meta["rule"]
    if model == DEFAULT_MODEL:
        assert pred.still_burst_rad == 0.0 and "face" in meta["withdrawn"]
    else:
        assert pred.still_burst_rad == 0.025 and "withdrawn" not in meta
    assert set(meta["sigma"]) >= {"a", "b", "c", "fitted_on"}
    # the val table the rule read: the chosen gate brings every family's still bursts within 5 % of
    # three-step PS where the network was above it, and costs moving bursts at most 3 %
    for fam in meta["val"].values():
        base, gated = fam["0"], fam["0.025"]
        assert gated["moving"]["rmse"] <= 1.03 * base["moving"]["rmse"]
        if base["still"]["rmse"] > 1.05 * base["still"]["three_step"]:
            assert gated["still"]["rmse"] <= 1.05 * gated["still"]["three_step"]


def _chooser():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "choose_still_burst_gate.py"
    spec = importlib.util.spec_from_file_location("choose_still_burst_gate", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _row(rmse: float, ece: float = 0.03, three: float = 0.03) -> dict[str, float]:
    return {"rmse": rmse, "ece": ece, "three_step": three}


def test_the_rule_takes_the_smallest_gate_that_fixes_still_within_cost():
    """benchmarks/still_burst_gate_rule.md: the smallest rad that brings still bursts to 1.05x three-step
    within a 3 % moving/slow cost; a family that pays more than 3 % caps the gate below it."""
    choose = _chooser()
    grid = choose.GRID

    def fam(still_at, cost_from=None):
        table = {}
        for rad in (0.0, *grid):
            still = 0.030 if rad >= still_at else 0.045
            moving = 0.2 * (1.10 if cost_from is not None and rad >= cost_from else 1.0)
            table[f"{rad:g}"] = {"moving": _row(moving), "slow": _row(0.1), "still": _row(still)}
        return table

    assert choose.choose({"a": fam(0.025)}) == 0.025
    # a second family whose moving bursts pay 10 % from 0.02 on: the still target cannot be reached
    # within cost, so the largest gate within cost (0.015)
    assert choose.choose({"a": fam(0.025), "b": fam(0.025, cost_from=0.02)}) == 0.015
    assert choose.choose({"a": fam(0.025, cost_from=0.015)}) == 0.0


def test_by_view_splits_a_folder_by_its_rigs(tmp_path):
    import json

    choose = _chooser()
    entries = [{"rig": {"name": n}} for n in ("face view", "side view", "face view")]
    (tmp_path / "index.json").write_text(json.dumps({"entries": entries}))
    views = choose.by_view([(str(tmp_path), None)])
    assert views == {"face view": [(str(tmp_path), [0, 2])], "side view": [(str(tmp_path), [1])]}
