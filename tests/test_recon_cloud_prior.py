"""CAD-free unwrapping around a coarse burst's cloud: the fine orders of a gear off its CAD, none wrong."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gearscan.core.gear import GearSpec
from gearscan.core.patterns import PatternSet
from gearscan.core.phase import classical_result
from gearscan.core.rig import default_rig
from gearscan.core.types import Burst, Frame
from gearscan.recon.cloud_prior import CloudDepthPrior
from gearscan.recon.measure import Reconstructor
from gearscan.recon.triangulate import to_turntable
from gearscan.twin.render import Optics, TwinRenderer

CAD = GearSpec(teeth=20, module=2.0)
ANGLE = math.radians(11.0)


@pytest.fixture(scope="module")
def scene():
    rig = default_rig(256, 256, working_radius=CAD.pitch_radius)
    return rig, TwinRenderer(rig, GearSpec(teeth=20, module=2.06), Optics())


def _burst(renderer, period, angles, seed):
    frames, truths = renderer.render_sequence(list(angles), PatternSet.three_step(period), [0, 1, 2], seed)
    return Burst(tuple(Frame(f, i, 0, i) for i, f in enumerate(frames)), tuple(angles)), truths[0]


def test_a_cloud_turned_to_another_angle_is_the_surface_seen_there(scene):
    rig, renderer = scene
    truth = renderer.truth(renderer.surface(ANGLE), 40.0)
    prior = CloudDepthPrior(rig, to_turntable(truth.points[truth.mask].astype(np.float64), rig, ANGLE))
    turned = ANGLE + math.radians(1.0)
    depth = prior.depth(turned)
    true = renderer.surface(turned).depth
    both = np.isfinite(depth) & np.isfinite(true)
    assert both.sum() > 0.5 * truth.mask.sum()
    assert np.median(np.abs(depth[both] - true[both])) < 0.02  # mm: the same surface, turned


def test_a_coarse_burst_unwraps_the_fine_one_without_a_cad(scene):
    """Module 2.06 against a 2.0 CAD, still: a 160 px burst unwrapped by the envelope alone is the
    prior of the 40 px burst; as many points as around the CAD, no pixel a fringe off."""
    rig, renderer = scene
    coarse_burst, _ = _burst(renderer, 160.0, (ANGLE,) * 3, 1)
    coarse = Reconstructor.for_gear(rig, 160.0, CAD, unwrap="envelope", mixed_border_px=None)(
        coarse_burst, classical_result(coarse_burst))
    fine_burst, truth = _burst(renderer, 40.0, (ANGLE,) * 3, 2)
    res = classical_result(fine_burst)
    rc = Reconstructor.for_gear(rig, 40.0, CAD, unwrap="coarse")
    assert len(rc(fine_burst, res).cloud) == 0  # no prior yet: nothing resolved, nothing guessed
    rc.set_prior(CloudDepthPrior(rig, coarse.cloud.points))
    m = rc(fine_burst, res)
    ok = np.isfinite(m.phase_abs) & truth.mask
    assert (np.abs(m.phase_abs[ok] - truth.phase_abs[ok]) < math.pi).all()
    around_cad = Reconstructor.for_gear(rig, 40.0, CAD)(fine_burst, res)
    envelope = Reconstructor.for_gear(rig, 40.0, CAD, unwrap="envelope")(fine_burst, res)
    assert len(m.cloud) >= 0.95 * len(around_cad.cloud) and len(m.cloud) > 1.5 * len(envelope.cloud)


def test_set_prior_belongs_to_coarse_mode(scene):
    rig, _ = scene
    with pytest.raises(ValueError, match="coarse"):
        Reconstructor.for_gear(rig, 40.0, CAD).set_prior(CloudDepthPrior(rig, np.zeros((1, 3))))
    with pytest.raises(ValueError, match="points_gear"):
        CloudDepthPrior(rig, np.zeros((4, 2)))


def test_a_recording_with_coarse_bursts_replays_cad_free(tmp_path):
    """`twin render --coarse-period` interleaves coarse bursts (patterns 3-5); `replay --unwrap
    coarse` measures the fine bursts around them without the CAD: as many points as around the CAD
    on a still gear 0.6 mm off its CAD, its true deviation, and no point a fringe off."""
    import json

    from typer.testing import CliRunner

    from gearscan.cli import app

    runner = CliRunner()
    rec = tmp_path / "rec"
    res = runner.invoke(app, ["twin", "render", str(rec), "--bursts", "4", "--width", "192", "--height", "192",
                              "--motion", "static", "--true-module", "2.06", "--coarse-period", "160", "--coarse-every", "2"])
    assert res.exit_code == 0, res.output
    assert runner.invoke(app, ["check", str(rec)]).exit_code == 0  # interleaved groups are not damage
    summaries = {}
    for mode in ("coarse", "cad"):
        out = tmp_path / f"{mode}.json"
        res = runner.invoke(app, ["replay", str(rec), "--classical", "--unwrap", mode, "--metrics", str(out),
                                  "--save", str(tmp_path / "o.rrd")])
        assert res.exit_code == 0, res.output
        data = json.loads(out.read_text())
        assert data["assembler"]["coarse_bursts"] == 2 and data["summary"]["bursts"] == 4
        summaries[mode] = data["summary"]
    coarse, cad = summaries["coarse"], summaries["cad"]
    assert coarse["cloud_points"] >= 0.95 * cad["cloud_points"]
    assert coarse["accuracy_max_mm"] < 0.5 and coarse["pixel_depth_mismatch"] == 0
    assert coarse["cad_dev_p95_mm"] == pytest.approx(coarse["true_cad_dev_p95_mm"], rel=0.1)


def test_unwrap_coarse_needs_coarse_bursts(tmp_path):
    from typer.testing import CliRunner

    from gearscan.cli import app

    runner = CliRunner()
    rec = tmp_path / "plain"
    assert runner.invoke(app, ["twin", "render", str(rec), "--bursts", "1", "--width", "64", "--height", "64"]).exit_code == 0
    res = runner.invoke(app, ["replay", str(rec), "--classical", "--unwrap", "coarse", "--save", str(tmp_path / "o.rrd")])
    assert res.exit_code == 2 and "coarse bursts" in res.output and "plain" in res.output
