"""`gearscan evaluate --quick`: the report's structure, and numbers ordered as physics demands."""

from __future__ import annotations

import json
import math

import pytest
from typer.testing import CliRunner

from gearscan.cli import app


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("eval") / "report"
    res = CliRunner().invoke(app, ["evaluate", str(out), "--quick"])
    assert res.exit_code == 0, res.output
    return out, json.loads((out / "results.json").read_text())


def test_report_has_all_six_parts_and_their_figures(report):
    out, r = report
    md = (out / "report.md").read_text()
    for heading in ("1. Transfer learning", "2. Networks", "3. Loss ablation", "4. Uncertainty",
                    "5. Against classical", "6. Generalisation"):
        assert heading in md
    for fig in ("fig11_transfer.png", "fig13_14_networks.png", "fig15_loss_ablation.png", "fig18_reliability.png",
                "fig18_uncertainty_maps.png", "fig19_sparsification.png", "fig20_classical.png", "fig22_generalisation.png"):
        assert (out / fig).stat().st_size > 5000, fig
        assert fig in md


def _rmse(scores, method, motion):
    return next(s["rmse_rad"] for s in scores if s["method"] == method and s["motion"] == motion)


def test_numbers_are_finite_and_ordered_by_physics(report):
    _, r = report
    cls = r["classical"]["scores"]
    for s in cls:
        assert math.isfinite(s["rmse_rad"]) and s["rmse_rad"] >= 0
    # a static burst has only noise: three-step PS is far better there than on a rotating gear
    static = _rmse(cls, "three-step PS", "static")
    assert static < 0.1
    for motion in ("uniform 0.6/0.6", "non-uniform 0.1/1.6"):
        assert _rmse(cls, "three-step PS", motion) > 5 * static
    # the network corrects motion: better than three-step PS on the paper's motions
    for motion in ("uniform 0.6/0.6", "non-uniform 0.1/1.6"):
        assert _rmse(cls, "CD-DCU-Net", motion) < _rmse(cls, "three-step PS", motion)
    # generalisation: three-step error grows with the frame 1-3 span
    gen = r["generalisation"]["scores"]
    assert _rmse(gen, "three-step PS", "uniform 2") > _rmse(gen, "three-step PS", "uniform 0.5")
    # uncertainty: a calibration error exists and the sparsification curve never beats the oracle
    u = r["uncertainty"]
    assert 0 <= u["ece"] <= 1
    sp = u["sparsification"]
    assert all(m >= o - 1e-9 for m, o in zip(sp["model"], sp["oracle"], strict=True))
    # transfer learning: both initialisations produced finite errors per target gear
    for per_gear in r["transfer"]["per_gear_rmse"].values():
        assert all(math.isfinite(v) for g in per_gear.values() for v in g.values())


def test_markdown_embeds_only_figures_it_wrote_and_states_options_as_a_table(report):
    import re

    out, r = report
    md = (out / "report.md").read_text()
    images = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert len(images) >= 8
    for name in images:  # every image the report shows exists
        assert (out / name).stat().st_size > 5000, name
    # no peer runs given: no loss-curve figure, and the report says why
    assert "fig12_loss_curves.png" not in md and not (out / "fig12_loss_curves.png").exists()
    assert "--peers" in md
    # options and budgets in words and tables, not a Python dict; --quick's overrides are stated
    assert "{'" not in md
    assert "| option | value |" in md and "| mc | 4 (--quick; asked 20) |" in md
    # section 4's table holds the ECE the reliability figure's title states (the pooled line)
    u = r["uncertainty"]
    assert u["per_motion"]["both paper motions pooled"]["ece"] == u["ece"]
    assert f"| both paper motions pooled | 2 | {u['rmse_rad']:.4f} | {u['mean_sigma_rad']:.4f} | {u['ece']:.3f} |" in md
