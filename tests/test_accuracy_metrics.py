"""Replay's accuracy figures: distance to the twin's true gear, able to fail, beside the CAD deviation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from typer.testing import CliRunner

from gearscan.cli import app

runner = CliRunner()


@pytest.fixture(scope="module")
def oversize_recording(tmp_path_factory):
    """A still twin gear cut at module 2.06 whose recording keeps the 2.0 CAD (0.66 mm p95 off it)."""
    out = tmp_path_factory.mktemp("acc") / "rec"
    res = runner.invoke(app, ["twin", "render", str(out), "--bursts", "1", "--width", "192", "--height", "192",
                              "--motion", "static", "--true-module", "2.06"])
    assert res.exit_code == 0, res.output
    return out


def test_accuracy_is_the_distance_to_the_true_gear_and_can_fail(oversize_recording):
    """Points of the oversize gear lie on its true surface (not on the CAD that picked their orders),
    its deviation from the CAD is the true one, and the same cloud moved one fringe along the rays
    (what a wrong fringe order does) is scored as millimetres off."""
    from gearscan.core.phase import classical_result
    from gearscan.core.recording import RecordingReader
    from gearscan.replay import TruthScorer, replay

    seen = []
    metrics = replay(oversize_recording, decoder=classical_result, on_burst=lambda m, row: seen.append((m, row)))
    s = metrics.summary()
    assert s["bursts"] == 1 and s["coverage"] > 0.9
    assert s["accuracy_rms_mm"] < 0.03 and s["accuracy_max_mm"] < 0.5, s
    assert s["true_cad_dev_p95_mm"] > 0.5  # the defect is real
    assert s["cad_dev_p95_mm"] == pytest.approx(s["true_cad_dev_p95_mm"], rel=0.1)
    # silhouette pixels whose blur mixes two surfaces measure the front one: counted, and rare
    assert s["pixel_depth_mismatch"] < 0.01 * s["cloud_points"]

    m, _ = seen[0]
    scorer = TruthScorer(RecordingReader(oversize_recording))
    rays = m.cloud.points - m.cloud.points.mean(axis=0)  # any consistent displacement of ~2.8 mm
    moved = m.cloud.points + 2.8 * rays / np.linalg.norm(rays, axis=1, keepdims=True)
    bad = dataclasses.replace(m, cloud=dataclasses.replace(m.cloud, points=moved))
    _, row, _, _ = scorer(bad)
    assert row["accuracy_rms_mm"] > 0.5 and row["pixel_depth_mismatch"] > 0.5 * row["cloud_points"]
