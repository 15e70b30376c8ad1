"""The command line: help on every command, named errors, render -> replay round trip."""

from __future__ import annotations

import json

import numpy as np
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


def test_render_with_a_rig_keeps_its_camera_unless_told_and_says_so(tmp_path):
    """A user's rig renders at its calibrated size by default (it had been rescaled to 512 px silently); an explicit
    other size rescales it and says so."""
    from gearscan.core.rig import default_rig

    rig = tmp_path / "rig.json"
    default_rig(64, 48).save(rig)
    res = runner.invoke(app, ["twin", "render", str(tmp_path / "own"), "--rig", str(rig), "--bursts", "1"])
    assert res.exit_code == 0, res.output
    camera = json.loads((tmp_path / "own" / "recording.json").read_text())["rig"]["camera"]
    assert (camera["width"], camera["height"]) == (64, 48) and "rescaled" not in res.output
    res = runner.invoke(app, ["twin", "render", str(tmp_path / "big"), "--rig", str(rig), "--bursts", "1",
                              "--width", "96", "--height", "72"])
    assert res.exit_code == 0, res.output
    camera = json.loads((tmp_path / "big" / "recording.json").read_text())["rig"]["camera"]
    assert (camera["width"], camera["height"]) == (96, 72)
    assert "64x48" in res.output and "rescaled to it" in res.output


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


def test_version_is_the_package_metadata():
    from importlib.metadata import version

    res = runner.invoke(app, ["--version"])
    assert res.exit_code == 0 and res.output.strip() == f"gearscan {version('gearscan')}"


def _ply_points(folder):
    from gearscan.recon.cloud import load_cloud

    return {p.name: load_cloud(p) for p in sorted(folder.glob("burst_*.ply"))}


def test_record_with_the_config_init_file_then_replay(twin_recording, tmp_path):
    """config init -> simulator devices (replay camera fed by a twin recording, mock projector)
    -> record -> replay: the recording holds the rig, gear and patterns of the config and
    replays into exactly the clouds the source recording gives; --rig serves one without a rig."""
    from gearscan.core.recording import RecordingReader
    from gearscan.core.rig import default_rig
    from gearscan.recon.cloud import load_cloud
    from gearscan.recon.deviation import CadScorer

    cfg = tmp_path / "rig.toml"
    assert runner.invoke(app, ["config", "init", str(cfg)]).exit_code == 0
    text = cfg.read_text()
    for old, new in (('driver = "aravis"', f'driver = "replay"\nid = "{twin_recording}"'),
                     ('backend = "window"', 'backend = "mock"'), ("settle_ms = 20.0", "settle_ms = 1.0")):
        assert old in text
        text = text.replace(old, new)
    cfg.write_text(text)
    rec = tmp_path / "rec"
    res = runner.invoke(app, ["record", str(rec), "-c", str(cfg), "-n", "2"])
    assert res.exit_code == 2 and f"rig.calibration: rig file not found: {tmp_path / 'rig.json'}" in res.output
    RecordingReader(twin_recording).rig.save(tmp_path / "rig.json")  # `calibration = "rig.json"`, next to the config
    res = runner.invoke(app, ["record", str(rec), "-c", str(cfg), "-n", "2"])
    assert res.exit_code == 0, res.output
    reader = RecordingReader(rec)
    assert reader.finished and len(reader) == 6 and reader.meta["source"] == "record"
    assert reader.meta["rig"] == json.loads((tmp_path / "rig.json").read_text())
    assert reader.meta["gear"]["teeth"] == 20 and reader.patterns.periods[0] == 40.0

    res = runner.invoke(app, ["replay", str(rec), "--classical", "--ply", str(tmp_path / "ply"), "--csv", str(tmp_path / "csv"),
                              "--save", str(tmp_path / "r.rrd")])
    assert res.exit_code == 0, res.output
    assert "bursts: 2" in res.output and "burst clouds: 2" in res.output
    res = runner.invoke(app, ["replay", str(twin_recording), "--classical", "--no-truth", "--ply", str(tmp_path / "src"),
                              "--save", str(tmp_path / "s.rrd")])
    assert res.exit_code == 0, res.output
    recorded, source = _ply_points(tmp_path / "ply"), _ply_points(tmp_path / "src")
    assert sorted(recorded) == sorted(source) == ["burst_000000.ply", "burst_000001.ply"]
    gear = reader.gear
    for name, cloud in recorded.items():
        # the recorded frames measure exactly what the source recording measures
        assert len(cloud) > 500 and cloud.points.tobytes() == source[name].points.tobytes()
        # on the gear, in the gear frame, mm: between root and tip radius and near its CAD surface
        # (three-step PS of a turning gear: about 0.1 mm typical error)
        r = np.hypot(cloud.points[:, 0], cloud.points[:, 1])
        assert np.percentile(r, 5) > gear.root_radius - 0.2 and np.percentile(r, 95) < gear.tip_radius + 0.2
        dev = CadScorer(gear).distances(cloud.points)
        assert np.median(np.abs(dev)) < 0.2
        np.testing.assert_allclose(cloud.deviation, dev, atol=1e-5)  # each file carries it (signed, mm)
        csv = load_cloud(tmp_path / "csv" / name.replace(".ply", ".csv"))
        np.testing.assert_allclose(csv.points, cloud.points, atol=1e-5)
        np.testing.assert_allclose(csv.sigma, cloud.sigma, rtol=1e-5)
        np.testing.assert_allclose(csv.deviation, cloud.deviation, atol=1e-5)
        assert np.all(csv.sigma > 0)

    # a recording without its rig (as `record` wrote them before): named error, then --rig
    meta = json.loads((rec / "recording.json").read_text())
    del meta["rig"]
    (rec / "recording.json").write_text(json.dumps(meta))
    res = runner.invoke(app, ["replay", str(rec), "--classical", "--save", str(tmp_path / "r.rrd")])
    assert res.exit_code == 2 and "recording.json holds no rig calibration" in res.output and "--rig" in res.output
    res = runner.invoke(app, ["replay", str(rec), "--classical", "--rig", str(tmp_path / "rig.json"),
                              "--ply", str(tmp_path / "ply2"), "--save", str(tmp_path / "r.rrd")])
    assert res.exit_code == 0, res.output
    assert {k: v.points.tobytes() for k, v in _ply_points(tmp_path / "ply2").items()} == \
        {k: v.points.tobytes() for k, v in recorded.items()}
    default_rig(64, 64).save(tmp_path / "small.json")
    res = runner.invoke(app, ["replay", str(rec), "--classical", "--rig", str(tmp_path / "small.json")])
    assert res.exit_code == 2 and "64x64" in res.output and "128x128" in res.output
    res = runner.invoke(app, ["replay", str(rec), "--classical", "--rig", str(tmp_path / "nope.json")])
    assert res.exit_code == 2 and "nope.json" in res.output
    # an export folder that already holds burst clouds is refused (two runs never mix)
    res = runner.invoke(app, ["replay", str(rec), "--classical", "--rig", str(tmp_path / "rig.json"), "--ply", str(tmp_path / "ply2")])
    assert res.exit_code == 2 and "already holds burst clouds" in res.output
    # a rig of another size than the camera's frames: record refuses it at the first frame
    default_rig(64, 64).save(tmp_path / "rig.json")
    res = runner.invoke(app, ["record", str(tmp_path / "rec2"), "-c", str(cfg), "-n", "1"])
    assert res.exit_code == 2 and "rig.calibration" in res.output and "64x64" in res.output and "128x128" in res.output


def test_twin_render_alternate_order_replays_both_orders(tmp_path):
    """`twin render --alternate-order` writes 0, 1, 2 then 0, 2, 1; replay decodes both to the truth
    (still gear: three-step PS at its noise floor in either order)."""
    out = tmp_path / "alt"
    res = runner.invoke(app, ["twin", "render", str(out), "--bursts", "2", "--width", "96", "--height", "96",
                              "--motion", "static", "--alternate-order"])
    assert res.exit_code == 0, res.output
    lines = [json.loads(x) for x in (out / "frames.jsonl").read_text().splitlines()]
    assert [d["pattern_index"] for d in lines] == [0, 1, 2, 0, 2, 1]
    metrics = tmp_path / "m.json"
    res = runner.invoke(app, ["replay", str(out), "--classical", "--metrics", str(metrics)])
    assert res.exit_code == 0, res.output
    data = json.loads(metrics.read_text())
    assert data["summary"]["bursts"] == 2 and data["summary"]["three-step_rmse_rad"] < 0.05, data["summary"]


def test_replay_keep_settings_reach_the_reconstructor(twin_recording, tmp_path):
    """`--network-support-px N` turns a fringe-support test of the network's pixels on (without it, the model's own:
    none for the shipped v9; -1 is off), `--max-sigma-rad` sets the keep bound; the metrics say what ran and count
    the pixels the support test drops, and a tighter bound reports fewer points."""
    from gearscan.inference.model_io import read_config
    from gearscan.inference.predictor import DEFAULT_MODEL, model_network_support
    from gearscan.recon.measure import MAX_SIGMA_RAD, unwrapper_sees

    shipped = model_network_support(read_config(DEFAULT_MODEL)).per_burst_px
    expected = {"default": shipped, "off": None, "2 px": 2, "tight": shipped}
    runs = {}
    for label, extra in (("default", []), ("off", ["--network-support-px", "-1"]), ("2 px", ["--network-support-px", "2"]),
                         ("tight", ["--max-sigma-rad", "0.1"])):
        metrics = tmp_path / f"{label}.json"
        res = runner.invoke(app, ["replay", str(twin_recording), "--orientation", "normal", "--metrics",
                                  str(metrics), "--save", str(tmp_path / f"{label}.rrd"), *extra])
        assert res.exit_code == 0, res.output
        runs[label] = data = json.loads(metrics.read_text())
        assert data["recon"]["network_support_px"] == expected[label]  # the metrics say what ran
        assert data["recon"]["max_sigma_rad"] == (0.1 if label == "tight" else MAX_SIGMA_RAD)
        bound = data["recon"]["max_sigma_rad"]
        assert data["recon"]["unwrapper_sees"] == unwrapper_sees(max_sigma=bound)

    def total(label, key):
        return sum(r.get(key, 0) for r in runs[label]["bursts"])

    assert total("off", "unwrap_unsupported") == 0
    assert total("2 px", "unwrap_unsupported") > total("default", "unwrap_unsupported")
    assert 0 < total("tight", "unwrap_points") < total("default", "unwrap_points")
    for bad in (["--network-support-px", "-2"], ["--max-sigma-rad", "0"], ["--max-sigma-rad", "nan"],
                ["--max-sigma-rad", "inf"]):
        assert runner.invoke(app, ["replay", str(twin_recording), *bad]).exit_code == 2, bad


def test_replay_with_the_frame_fit_gets_the_frame_fit_paths_support_test(twin_recording, tmp_path, replay_spy,
                                                                        monkeypatch):
    """Without ``--network-support-px``, ``replay --fuse`` (which fits the fused points to the frames) runs the
    model's frame-fit test (``network_support.frame_fit_px`` in its JSON, chosen on val stretches:
    benchmarks/fused_support_rule.md); per-burst replays and ``--fuse --no-refine`` its per-burst one; the option
    overrides both. The model's two are stubbed apart here (5 and 7 px; the product's 11 and 13) so the route shows
    whatever the shipped values are."""
    from gearscan.inference import predictor
    from gearscan.recon import measure

    monkeypatch.setattr(measure, "NETWORK_SUPPORT_PX", 13)
    monkeypatch.setattr(measure, "FRAME_FIT_NETWORK_SUPPORT_PX", 11)
    monkeypatch.setattr(predictor, "model_network_support", lambda meta: predictor.NetworkSupport(5, 7))
    fused = ["--fuse", str(tmp_path / "fused.ply")]
    for extra, expected in (([], 5), (fused, 7), ([*fused, "--no-refine"], 5),
                            ([*fused, "--network-support-px", "3"], 3), ([*fused, "--network-support-px", "-1"], None)):
        with pytest.raises(replay_spy.Called):
            runner.invoke(app, ["replay", str(twin_recording), "--save", str(tmp_path / "x.rrd"), *extra],
                          catch_exceptions=False)
        assert replay_spy.calls[-1]["network_support_px"] == expected, extra


def test_replay_says_when_bursts_span_beyond_the_calibrated_sigma(tmp_path):
    """3 deg/frame (6 deg from frame 1 to 3) is beyond the depth sigma's val calibration (5 deg): the network's bursts
    are counted in the metrics and replay says so; three-step PS's are not (its sigma class is calibrated)."""
    rec = tmp_path / "fast"
    res = runner.invoke(app, ["twin", "render", str(rec), "--bursts", "2", "--width", "64", "--height", "64",
                              "--motion", "uniform:3"])
    assert res.exit_code == 0, res.output
    metrics = tmp_path / "m.json"
    res = runner.invoke(app, ["replay", str(rec), "--no-truth", "--metrics", str(metrics)])
    assert res.exit_code == 0, res.output
    assert json.loads(metrics.read_text())["recon"]["bursts_sigma_uncalibrated"] == 2
    assert "2 burst(s) spanned more than the depth sigma was calibrated for (5 deg" in res.output
    res = runner.invoke(app, ["replay", str(rec), "--no-truth", "--classical", "--metrics", str(metrics)])
    assert res.exit_code == 0, res.output
    assert json.loads(metrics.read_text())["recon"]["bursts_sigma_uncalibrated"] == 0
    assert "spanned more than" not in res.output
    # ... but three-step PS on a turning burst has no motion term at all: a baseline, said and counted
    assert json.loads(metrics.read_text())["decoder"]["turning_three_step"] == 2
    assert "three-step PS decoded 2 burst(s) that turned (--classical, a baseline)" in res.output
    still = tmp_path / "still"
    res = runner.invoke(app, ["twin", "render", str(still), "--bursts", "2", "--width", "64", "--height", "64",
                              "--motion", "uniform:0"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["replay", str(still), "--no-truth", "--classical", "--metrics", str(metrics)])
    assert res.exit_code == 0, res.output
    assert json.loads(metrics.read_text())["decoder"]["turning_three_step"] == 0 and "that turned" not in res.output


def test_replay_says_when_a_model_borrows_the_products_depth_sigma(tmp_path):
    """The product's depth-sigma scales were chosen for the shipped decode (recon.depth_sigma.SCALES_CHOSEN_FOR): the
    shipped model and three-step PS use them as measured, the default-rig option its own (chosen for its decode);
    unmeasured, which the metrics record and replay says: a model with other sigma maps and none of its own
    (borrowed), the option with a refitted map (its own scales stale), the option in Monte Carlo mode (its own were
    chosen deterministic). The shipped model in Monte Carlo mode reconstructs with the product's MC table."""
    import shutil

    from gearscan.inference.predictor import DEFAULT_MODEL
    from gearscan.recon.depth_sigma import (
        DEPTH_SIGMA_SCALES,
        DEPTH_SIGMA_SCALES_MC,
        UNMEASURED_NOTES,
    )

    rec = tmp_path / "rec"
    res = runner.invoke(app, ["twin", "render", str(rec), "--bursts", "1", "--width", "64", "--height", "64"])
    assert res.exit_code == 0, res.output
    refitted = tmp_path / "refitted.safetensors"  # the shipped weights with an identity deterministic map
    shutil.copyfile(DEFAULT_MODEL, refitted)
    meta = json.loads(DEFAULT_MODEL.with_suffix(".json").read_text())
    meta["sigma_calibration"]["deterministic"] = {"a": 1.0, "b": 1.0}
    refitted.with_suffix(".json").write_text(json.dumps(meta))
    option = DEFAULT_MODEL.with_name("default_rig.safetensors")
    stale = tmp_path / "stale.safetensors"  # the option with its deterministic map refitted
    shutil.copyfile(option, stale)
    meta = json.loads(option.with_suffix(".json").read_text())
    meta["sigma_calibration"]["deterministic"] = {"a": 1.0, "b": 1.0}
    stale.with_suffix(".json").write_text(json.dumps(meta))
    metrics = tmp_path / "m.json"
    for extra, source in (([], "product"), (["--classical"], "product"), (["--model", str(option)], "model"),
                          (["--model", str(refitted)], "borrowed"), (["--model", str(stale)], "stale"),
                          (["--mc", "2"], "product"), (["--model", str(option), "--mc", "2"], "mc")):
        res = runner.invoke(app, ["replay", str(rec), "--no-truth", "--metrics", str(metrics), *extra])
        assert res.exit_code == 0, res.output
        recon = json.loads(metrics.read_text())["recon"]
        assert recon["depth_sigma_source"] == source, extra
        if "--model" not in extra:  # the product's scales: the MC table in Monte Carlo mode
            assert recon["depth_sigma_scales"] == (DEPTH_SIGMA_SCALES_MC if "--mc" in extra else
                                                   DEPTH_SIGMA_SCALES).as_dict(), extra
        for name, note in UNMEASURED_NOTES.items():  # said where unmeasured, and only there
            assert (note.split(":")[0][:60] in " ".join(res.output.split())) == (name == source), (extra, res.output)


def test_an_output_that_cannot_be_written_is_named_before_the_run(twin_recording, tmp_path):
    """Outputs are checked before any work: a folder that cannot be made (/proc), a file where a folder is expected
    and a folder where a file is: exit 2 naming the option, no traceback; a missing parent folder is made."""
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    cases = [
        (["replay", str(twin_recording), "--classical", "--metrics", "/proc/gearscan_x/m.json"], "--metrics"),
        (["replay", str(twin_recording), "--classical", "--save", str(tmp_path)], "--save"),
        (["replay", str(twin_recording), "--classical", "--fuse", "/proc/gearscan_x/f.ply"], "--fuse"),
        (["replay", str(twin_recording), "--classical", "--ply", str(blocker)], "--ply"),
        (["inspect", str(twin_recording), "--classical", "-o", str(blocker / "rep")], "--out"),
        (["twin", "render", "/proc/gearscan_x", "--bursts", "1", "--width", "64", "--height", "64"], "/proc/gearscan_x"),
    ]
    for args, named in cases:
        res = runner.invoke(app, args)
        assert res.exit_code == 2 and named in res.output and "Traceback" not in res.output, (args, res.output)
    metrics = tmp_path / "new" / "deeper" / "m.json"
    res = runner.invoke(app, ["replay", str(twin_recording), "--classical", "--metrics", str(metrics),
                              "--save", str(tmp_path / "r.rrd")])
    assert res.exit_code == 0, res.output
    assert len(json.loads(metrics.read_text())["bursts"]) == 2  # the fixture's two bursts


def test_a_config_that_is_a_folder_or_not_utf8_and_an_init_into_a_new_folder(tmp_path):
    """`live --config` on a folder or a Latin-1 file: the file named, not IsADirectoryError/UnicodeDecodeError;
    `config init` into a folder that does not exist yet makes it."""
    (tmp_path / "adir.toml").mkdir()
    latin = tmp_path / "latin.toml"
    latin.write_bytes("[gear]\n# Zahnrad f\xfcr die Pr\xfcfung\n".encode("latin-1"))
    for cfg, needle in ((tmp_path / "adir.toml", "cannot read it"), (latin, "not UTF-8 text")):
        res = runner.invoke(app, ["live", "--config", str(cfg), "--check"])
        assert res.exit_code == 2 and needle in res.output and str(cfg) in res.output, res.output
    res = runner.invoke(app, ["config", "init", str(tmp_path / "new" / "rig.toml")])
    assert res.exit_code == 0 and (tmp_path / "new" / "rig.toml").is_file(), res.output


def test_a_connect_url_rerun_cannot_use_is_named_before_the_run(twin_recording, tmp_path):
    """`--connect bogus://nope` (or the live config's viewer.connect): exit 2 naming the option and the schemes rerun
    takes, before any burst (it was a RuntimeError traceback from the stream); a served viewer's own URL passes."""
    from gearscan.config import TEMPLATE
    from gearscan.core.rig import default_rig
    from gearscan.viewer.log import check_connect_url

    res = runner.invoke(app, ["replay", str(twin_recording), "--classical", "--connect", "bogus://nope"])
    assert res.exit_code == 2 and "--connect" in res.output and "rerun+http://" in res.output, res.output
    assert "Traceback" not in res.output
    default_rig().save(tmp_path / "rig.json")
    cfg = tmp_path / "live.toml"
    cfg.write_text(TEMPLATE.replace("\n[viewer]\n", '\n[viewer]\nconnect = "127.0.0.1:9876"\n', 1))
    res = runner.invoke(app, ["live", "--config", str(cfg), "--bursts", "1"])
    assert res.exit_code == 2 and "viewer.connect" in res.output and "'127.0.0.1:9876'" in res.output, res.output
    assert check_connect_url("rerun+http://127.0.0.1:9876/proxy") == "rerun+http://127.0.0.1:9876/proxy"
