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


def test_depth_z_measures_a_points_depth_error_along_its_own_ray():
    """A point moved by d along its camera ray off the true surface has a depth error of d times the cosine between
    the ray and the optical axis; over its sigma, that is what ``depth_z`` returns (NaN where the ray meets nothing)."""
    import numpy as np
    import open3d as o3d

    from gearscan.core.gear import GearSpec
    from gearscan.core.rig import default_rig, rot_z
    from gearscan.evaluate import depth_z

    rig, angle = default_rig(64, 64), 0.3
    surface = o3d.t.geometry.RaycastingScene()
    surface.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(GearSpec().mesh()))
    gear_to_cam = rig.camera.T_from_world @ rot_z(angle)
    centre = np.linalg.inv(gear_to_cam)[:3, 3]
    axis = np.linalg.inv(gear_to_cam)[:3, 2]  # the optical axis in the gear frame
    rng = np.random.default_rng(0)
    rays = axis + 0.08 * rng.standard_normal((200, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    hit = surface.cast_rays(o3d.core.Tensor(np.concatenate([np.broadcast_to(centre, rays.shape), rays], 1)
                                            .astype(np.float32)))["t_hit"].numpy().astype(np.float64)
    seen = np.isfinite(hit)
    assert 50 < seen.sum() < 200  # some rays meet the gear, some pass it
    shift = rng.uniform(-0.05, 0.05, len(rays))  # mm along the ray, either way (small: the same surface is met)
    points = centre + np.where(seen, hit + shift, 100.0)[:, None] * rays
    sigma = np.full(len(rays), 0.01)
    z = depth_z(surface, rig, angle, points, sigma)
    expected = np.abs(shift) * (rays @ axis) / 0.01
    np.testing.assert_allclose(z[seen], expected[seen], rtol=1e-3, atol=2e-3)
    assert np.isnan(z[~seen]).all()
