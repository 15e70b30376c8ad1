"""The command line: help on every command, named errors, render -> replay round trip."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from gearscan.cli import app

runner = CliRunner()


def _commands(typer_app, prefix=()):
    import typer.main

    group = typer.main.get_command(typer_app)
    stack = [(prefix, group)]
    while stack:
        path, cmd = stack.pop()
        yield path
        for name, sub in getattr(cmd, "commands", {}).items():
            stack.append(((*path, name), sub))


def test_help_on_every_command():
    paths = list(_commands(app))
    assert ("twin", "render") in paths and ("replay",) in paths
    for path in paths:
        res = runner.invoke(app, [*path, "--help"])
        assert res.exit_code == 0, (path, res.output)
        assert "Usage" in res.output


def test_bad_gear_is_named(tmp_path):
    res = runner.invoke(app, ["twin", "render", str(tmp_path / "r"), "--teeth", "5"])
    assert res.exit_code == 2
    assert "teeth" in res.output and "greater than or equal to 6" in res.output


def test_bad_motion_is_named(tmp_path):
    res = runner.invoke(app, ["twin", "render", str(tmp_path / "r"), "--motion", "wobble:3", "--width", "64", "--height", "64"])
    assert res.exit_code == 2
    assert "wobble:3" in res.output and "uniform" in res.output


@pytest.fixture(scope="module")
def twin_recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "rec"
    res = runner.invoke(app, ["twin", "render", str(out), "--bursts", "2", "--width", "128", "--height", "128", "--motion", "uniform:0.6"])
    assert res.exit_code == 0, res.output
    return out


def test_replay_classical_reports_accuracy(twin_recording, tmp_path):
    metrics = tmp_path / "m.json"
    res = runner.invoke(app, ["replay", str(twin_recording), "--classical", "--metrics", str(metrics), "--save", str(tmp_path / "o.rrd")])
    assert res.exit_code == 0, res.output
    data = json.loads(metrics.read_text())
    assert data["summary"]["bursts"] == 2
    # rotating 0.6/0.6 deg: three-step PS is off by far more than its static floor
    assert data["summary"]["three-step_rmse_rad"] > 0.1
    assert (tmp_path / "o.rrd").stat().st_size > 10_000


def test_replay_no_truth_skips_scoring_but_measures(twin_recording, tmp_path):
    metrics = tmp_path / "m.json"
    res = runner.invoke(app, ["replay", str(twin_recording), "--classical", "--no-truth", "--metrics", str(metrics),
                              "--save", str(tmp_path / "o.rrd")])
    assert res.exit_code == 0, res.output
    data = json.loads(metrics.read_text())
    assert data["summary"] == {"bursts": 2}  # no accuracy keys: nothing was scored
    assert data["pipeline"]["reconstruct"]["emitted"] == 2  # but every burst was measured


def test_replay_missing_recording_is_named(tmp_path):
    res = runner.invoke(app, ["replay", str(tmp_path / "nope"), "--classical"])
    assert res.exit_code == 2
    assert "recording.json is missing" in res.output
