"""`gearscan live` end to end with real counterparts: replay camera fed by a twin recording,
the mock encoder process on a pty, the mock projector; recording on; then replay."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gearscan.cli import app
from gearscan.config import TEMPLATE, LiveConfig
from gearscan.core.recording import RecordingReader
from gearscan.core.rig import default_rig
from gearscan.inference.decoder import Decoder
from gearscan.twin.recordings import render_recording

runner = CliRunner()


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    root = tmp_path_factory.mktemp("live")
    rig = default_rig(128, 128)
    rec = render_recording(root / "twin", rig=rig, motion="uniform:0.6", bursts=4, seed=2)
    rig_path = root / "rig.json"
    RecordingReader(rec).rig.save(rig_path)
    return root, rec, rig_path


def _config(root: Path, rec: Path, rig_path: Path, port: str | None, model: str | None = None, loop: bool = False) -> Path:
    encoder = f'[encoder]\nport = "{port}"\ncounts_per_rev = 10000\n' if port else ""
    text = f"""
[camera]
driver = "replay"
id = "{rec}"
trigger = "software"
loop = {str(loop).lower()}

[projector]
backend = "mock"
width = 1280
height = 800
period_px = 40.0
settle_ms = 1

{encoder}
[rig]
calibration = "{rig_path}"

[gear]
teeth = 20

[model]
mc = 0
{f'path = "{model}"' if model else ""}
"""
    path = root / "live.toml"
    path.write_text(text)
    return path


def test_template_is_valid_and_errors_name_the_key(tmp_path):
    cfg = LiveConfig.from_toml(TEMPLATE)
    assert cfg.camera.trigger == "software" and cfg.gear.teeth == 20
    bad = TEMPLATE.replace("exposure_us = 5000.0", "exposure_us = -1").replace('backend = "window"', 'backend = "laser"')
    with pytest.raises(ValueError) as err:
        LiveConfig.from_toml(bad, "rig.toml")
    msg = str(err.value)
    assert "camera.exposure_us" in msg and "(got -1)" in msg
    assert "projector.backend" in msg and "'laser'" in msg
    assert cfg.model.orientation == "auto"
    # the template states the val choices the code ships (a user's copy keeps what it says)
    from gearscan.inference.decoder import STILL_SPAN_DEG
    from gearscan.recon.measure import MAX_SIGMA_RAD

    assert cfg.model.still_span_deg == STILL_SPAN_DEG and cfg.recon.max_sigma_rad == MAX_SIGMA_RAD
    with pytest.raises(ValueError, match="model.orientation"):
        LiveConfig.from_toml(TEMPLATE.replace('orientation = "auto"', 'orientation = "upside"'), "rig.toml")
    assert cfg.recon.network_support_px is None  # the template leaves it to the model's own val choice
    off = LiveConfig.from_toml(TEMPLATE.replace("# network_support_px = 2 ", "network_support_px = -1 "))
    assert off.recon.network_support_px == -1
    with pytest.raises(ValueError, match="recon.network_support_px"):
        LiveConfig.from_toml(TEMPLATE.replace("# network_support_px = 2 ", "network_support_px = -3 "), "rig.toml")
    assert LiveConfig.from_toml(TEMPLATE.replace('orientation = "auto"', 'orientation = "mirrored"')).model.orientation == "mirrored"
    res = runner.invoke(app, ["config", "init", str(tmp_path / "rig.toml")])
    assert res.exit_code == 0 and (tmp_path / "rig.toml").read_text() == TEMPLATE


def test_live_records_and_the_recording_replays_to_the_same_results(twin, tmp_path):
    from gearscan.live import run_live
    from gearscan.mocks.encoder_device import MockEncoderProcess
    from gearscan.replay import replay

    root, rec, rig_path = twin
    link = str(tmp_path / "enc")
    decoder = Decoder(classical=True)
    live_results = {}
    with MockEncoderProcess(link, rate=1000, cpr=10000, rpm=6.0, duration=60, linger=0) as dev:
        cfg = LiveConfig.load(_config(tmp_path, rec, rig_path, link))
        report = run_live(cfg, record=tmp_path / "rec", bursts=4, decoder=decoder, save=tmp_path / "live.rrd",
                          on_burst=lambda m, row: live_results.setdefault(m.burst.index, (m.result.phase.copy(), len(m.cloud))),
                          handle_signals=False)
        dev.kill()
    # every acquired burst is recorded; a burst the busy pipeline skipped (drop-oldest, so it
    # stays live; the first reconstruction is slow) is counted as such, never lost silently
    assert report.bursts == 4 and len(live_results) + report.skipped == 4 and len(live_results) >= 2, report.summary()
    out = RecordingReader(tmp_path / "rec")
    assert out.finished and len(out) == 12 and out.meta["source"] == "live"
    assert len(out.encoder_samples()) > 0
    # the live recording replays through the same pipeline into the same phase and clouds
    replayed = {}
    replay(tmp_path / "rec", decoder=decoder, on_burst=lambda m, row: replayed.setdefault(m.burst.index, (m.result.phase, len(m.cloud))))
    assert set(live_results) <= set(replayed) and len(replayed) == 4
    for k, (phase, n) in live_results.items():
        assert np.array_equal(replayed[k][0], phase) and replayed[k][1] == n > 100


def test_ctrl_c_leaves_a_recording_that_replays(twin, tmp_path):
    root, rec, rig_path = twin
    cfg_path = _config(tmp_path, rec, rig_path, None, os.environ.get("GEARSCAN_TEST_MODEL"), loop=True)
    env = {**os.environ, "HOME": str(tmp_path), "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "gearscan.cli", "live", "--config", str(cfg_path), "--record", str(tmp_path / "rec"),
         "--save", str(tmp_path / "o.rrd"), "--duration", "120"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        lines = (tmp_path / "rec" / "frames.jsonl")
        if lines.exists() and len(lines.read_text().splitlines()) >= 6:
            break
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    assert "stopped by Ctrl-C (SIGINT)" in out
    assert "network: fringes " in out  # the end summary says which fringe orientation the network decoded with
    reader = RecordingReader(tmp_path / "rec")
    assert reader.finished and len(reader) >= 6 and len(reader) % 3 == 0
    res = runner.invoke(app, ["replay", str(tmp_path / "rec"), "--classical", "--save", str(tmp_path / "r.rrd")])
    assert res.exit_code == 0, res.output
    assert f"bursts: {len(reader) // 3}" in res.output


def test_killed_viewer_does_not_stop_the_measurement(twin, tmp_path, monkeypatch):
    from gearscan.live import run_live
    from gearscan.viewer.serve import serve_web

    monkeypatch.setenv("HOME", str(tmp_path))
    root, rec, rig_path = twin
    cfg = LiveConfig.load(_config(tmp_path, rec, rig_path, None))
    web = serve_web()
    done = []

    def on_burst(m, row):
        done.append(m.burst.index)
        if len(done) == 1:
            web.process.kill()  # the viewer goes away mid-measurement
            web.process.wait()

    try:
        report = run_live(cfg, bursts=4, decoder=Decoder(classical=True), connect=web.grpc_url, on_burst=on_burst,
                          handle_signals=False)
    finally:
        web.close()
    # bursts after the kill are measured; one a busy stage skipped to stay live is counted as such
    assert report.bursts == 4 and len(done) + report.skipped == 4 and len(done) >= 2, report.summary()


def test_check_verifies_what_it_claims(twin, tmp_path):
    """`live --check` says OK only after a frame of the rig's size arrived and the encoder port
    answered in the encoder protocol; each failure is an error naming the setting."""
    import tty

    from gearscan.mocks.encoder_device import MockEncoderProcess

    root, rec, rig_path = twin
    missing = tmp_path / "no-such-port"
    res = runner.invoke(app, ["live", "--config", str(_config(tmp_path, rec, rig_path, str(missing))), "--check"])
    assert res.exit_code == 2 and f"encoder.port: cannot open '{missing}'" in res.output, res.output
    master, slave = os.openpty()  # a port that opens but where nothing speaks the protocol
    tty.setraw(slave)
    try:
        res = runner.invoke(app, ["live", "--config", str(_config(tmp_path, rec, rig_path, os.ttyname(slave))), "--check"])
    finally:
        os.close(master)
        os.close(slave)
    assert res.exit_code == 2 and "opened, but no gearscan encoder (silent" in res.output, res.output
    link = str(tmp_path / "enc")
    with MockEncoderProcess(link, rate=500, cpr=10000, duration=60, linger=0):
        res = runner.invoke(app, ["live", "--config", str(_config(tmp_path, rec, rig_path, link)), "--check"])
    assert res.exit_code == 0, res.output
    assert f"encoder: {link} answered: gearscan encoder 'mockenc', protocol v1, 10000 counts/rev" in res.output
    assert "camera: replay camera" in res.output and "one 128x128 Mono8 frame grabbed" in res.output
    assert "pattern sequence: 0, 1, 2 (shown by software" in res.output
    assert "its calibration states no uncertainty of its own" in " ".join(res.output.split())
    with MockEncoderProcess(link, rate=500, cpr=4096, duration=60, linger=0):
        res = runner.invoke(app, ["live", "--config", str(_config(tmp_path, rec, rig_path, link)), "--check"])
    assert res.exit_code == 2 and "encoder.counts_per_rev: 10000 in the config, but the encoder" in res.output
    assert "reports 4096" in res.output
    small = tmp_path / "rig64.json"
    default_rig(64, 64).save(small)
    res = runner.invoke(app, ["live", "--config", str(_config(tmp_path, rec, small, None)), "--check"])
    assert res.exit_code == 2 and "camera: it delivers 128x128 px images" in res.output and "64x64" in res.output
    assert "encoder: none" not in res.output


def test_status_drops_stop_reasons_and_the_rrd_cap(twin, tmp_path):
    """The status counts what was measured and what was dropped and why (every acquired burst is
    either measured or counted as skipped); the end names why the run stopped; the .rrd cap stops
    the viewer stream, not the measurement."""
    import time

    from gearscan.live import run_live

    root, rec, rig_path = twin
    cfg = LiveConfig.load(_config(tmp_path, rec, rig_path, None))
    classical = Decoder(classical=True)
    statuses = []

    def slow(burst):  # a decoder slower than the camera: the oldest waiting burst is skipped
        time.sleep(0.6)
        return classical(burst)

    full = run_live(cfg, bursts=4, decoder=slow, save=tmp_path / "full.rrd", on_status=statuses.append,
                    handle_signals=False)
    st = full.status
    assert full.stopped_by == "--bursts 4 reached" and full.bursts == st.acquired == 4
    assert st.drops.get("decoder busy", 0) >= 1 and st.measured + full.skipped == 4, st
    assert st.encoder_hz is None and "no encoder" in st.line()  # the replay camera's frames carry angles
    assert st.rrd == tmp_path / "full.rrd" and st.rrd_mb == pytest.approx((tmp_path / "full.rrd").stat().st_size / 1e6)
    assert not st.rrd_full and len(statuses) >= 3 and statuses[-1].elapsed_s > 1
    summary = full.summary()
    assert summary.startswith("stopped by --bursts 4 reached") and "bursts skipped while the decoder was busy" in summary
    assert f"rerun {tmp_path / 'full.rrd'}" in summary

    capped = run_live(cfg, decoder=classical, save=tmp_path / "capped.rrd", max_save_mb=1e-4, handle_signals=False)
    assert capped.stopped_by.startswith("end of input") and capped.bursts == 4  # the measurement went on
    assert capped.status.rrd_full and capped.status.measured == 4 - capped.skipped >= 2
    assert "FULL" in capped.status.line() and "size cap reached" in capped.summary()
    assert (tmp_path / "capped.rrd").stat().st_size < 0.5 * (tmp_path / "full.rrd").stat().st_size


def test_an_error_stops_with_what_was_measured_and_the_status_prints_without_a_terminal(twin, tmp_path):
    import io

    from rich.console import Console

    from gearscan.live import LiveError, LiveStatus, StatusLine, run_live

    root, rec, rig_path = twin
    cfg = LiveConfig.load(_config(tmp_path, rec, rig_path, None))
    classical = Decoder(classical=True)

    def failing(burst):
        if burst.index == 2:
            raise RuntimeError("decoder fault")
        return classical(burst)

    done = []
    with pytest.raises(LiveError, match="stage 'infer' failed: RuntimeError: decoder fault") as err:
        run_live(cfg, decoder=failing, save=tmp_path / "e.rrd", handle_signals=False,
                 on_burst=lambda m, row: done.append(m.burst.index))
    partial = err.value.live_report  # what really came out before the failure (bursts in flight are not finished)
    assert partial.stopped_by == "an error in stage 'infer'" and partial.bursts >= 3
    assert partial.status.measured == len(done) and set(done) <= {0, 1}
    assert partial.summary().startswith(f"stopped by an error in stage 'infer' after {partial.pipeline.wall_s:.1f} s: "
                                        f"{partial.bursts} bursts acquired, {len(done)} measured")
    # without a terminal (a log file, a service) the status comes as a plain line every every_s seconds
    out = io.StringIO()
    st = LiveStatus(elapsed_s=12.0, acquired=30, measured=28, rate_per_s=2.5, drops={"decoder busy": 2},
                    encoder_hz=1000.0, rrd=Path("out/live.rrd"), rrd_mb=42.0, fringes="fringes normal (set)")
    with StatusLine(Console(file=out, width=200), every_s=0.0) as line:
        line.update(st)
    assert out.getvalue() == ("  12 s 28 bursts 2.5/s | drops 2 decoder busy | encoder 1000 Hz | fringes normal (set) "
                              "| out/live.rrd 42 MB\n")
    res = runner.invoke(app, ["live"])
    assert res.exit_code == 2 and "--config: a live configuration is needed" in res.output and "--simulate" in res.output


def test_a_second_live_on_the_same_encoder_runs(twin, tmp_path):
    """The encoder keeps streaming between two runs (as a real one does): the second run opens the
    port again and measures; it once failed on the previous run's stale input."""
    from gearscan.live import run_live
    from gearscan.mocks.encoder_device import MockEncoderProcess

    root, rec, rig_path = twin
    link = str(tmp_path / "enc")
    with MockEncoderProcess(link, rate=1000, cpr=10000, rpm=6.0, duration=120, linger=0) as dev:
        cfg = LiveConfig.load(_config(tmp_path, rec, rig_path, link))
        reports = []
        for k in range(2):
            reports.append(run_live(cfg, bursts=3, decoder=Decoder(classical=True), save=tmp_path / f"l{k}.rrd",
                                    handle_signals=False))
            time.sleep(1.0)  # the device streams into the closed port meanwhile
        dev.kill()
    assert [r.bursts for r in reports] == [3, 3], [r.summary() for r in reports]


def test_live_sequences_coarse_bursts_for_cad_free_unwrapping(tmp_path):
    """projector.coarse_period_px makes live show a coarse burst first and then after every
    coarse_every measuring bursts; recon.unwrap = "coarse" measures the fine bursts around it without
    the CAD: as many points as around the CAD on a still gear 0.6 mm off its CAD, with its true
    deviation; the live recording keeps the coarse bursts, so it replays CAD-free too."""
    from gearscan.live import run_live
    from gearscan.replay import replay
    from gearscan.twin.defects import GearDefects

    rec = render_recording(tmp_path / "twin", rig=default_rig(192, 192), motion="static", bursts=4,
                           defects=GearDefects(module=2.06), coarse_period_px=160.0, coarse_every=2)
    rig_path = tmp_path / "rig.json"
    RecordingReader(rec).rig.save(rig_path)
    text = _config(tmp_path, rec, rig_path, None).read_text()
    points = {}
    for mode in ("coarse", "cad"):
        cfg = LiveConfig.from_toml(text.replace("settle_ms = 1", "settle_ms = 1\ncoarse_period_px = 160.0\ncoarse_every = 2")
                                   + f'\n[recon]\nunwrap = "{mode}"\n', "live.toml")
        seen = {}
        report = run_live(cfg, record=tmp_path / f"rec-{mode}", bursts=4, decoder=Decoder(classical=True),
                          on_burst=lambda m, row, seen=seen: seen.setdefault(m.burst.index, m), handle_signals=False)
        assert report.bursts == 4 and report.coarse_bursts == 2, report.summary()
        assert "2 coarse bursts" in report.summary()
        assert all(m.burst.group == 0 for m in seen.values())  # coarse bursts are the prior, not a result
        points[mode] = {k: len(m.cloud) for k, m in seen.items()}  # a busy stage may skip a burst (counted)
        assert len(seen) >= 2 and report.status.measured == len(seen), report.summary()
    both = set(points["coarse"]) & set(points["cad"])
    assert both, points
    for k in both:  # the coarse prior finds the orders the CAD finds: the same points, burst by burst
        assert points["coarse"][k] >= 0.95 * points["cad"][k] > 1000, points
    live_rec = RecordingReader(tmp_path / "rec-coarse")
    assert live_rec.patterns.coarse_period_px == 160.0 and len(live_rec) == 3 * (4 + 2)
    metrics = replay(tmp_path / "rec-coarse", decoder=Decoder(classical=True), unwrap="coarse", truth=False)
    assert metrics.assembler["coarse_bursts"] == 2 and len(metrics.per_burst) == 4


def test_coarse_unwrapping_needs_a_coarse_period():
    text = TEMPLATE.replace('unwrap = "cad"', 'unwrap = "coarse"')
    with pytest.raises(ValueError, match="projector.coarse_period_px"):
        LiveConfig.from_toml(text, "rig.toml")
    with pytest.raises(ValueError, match="coarse_period_px must exceed period_px"):
        LiveConfig.from_toml(text.replace("# coarse_period_px = 160.0", "coarse_period_px = 20.0"), "rig.toml")
    cfg = LiveConfig.from_toml(text.replace("# coarse_period_px = 160.0", "coarse_period_px = 160.0"), "rig.toml")
    assert cfg.projector.patterns().cycle(cfg.projector.coarse_every) == [3, 4, 5] + [0, 1, 2] * 4


def test_live_alternates_the_pattern_order(tmp_path):
    """projector.alternate_order: every other burst is shown 0, 2, 1; live decodes both orders to the
    same surface (a still twin gear: as many points in a reversed burst as in a forward one), and its
    recording keeps the order, so it replays."""
    from gearscan.live import run_live
    from gearscan.replay import replay

    rec = render_recording(tmp_path / "twin", rig=default_rig(160, 160), motion="static", bursts=4, alternate_order=True)
    rig_path = tmp_path / "rig.json"
    RecordingReader(rec).rig.save(rig_path)
    cfg = LiveConfig.from_toml(_config(tmp_path, rec, rig_path, None).read_text()
                               .replace("settle_ms = 1", "settle_ms = 1\nalternate_order = true"), "live.toml")
    assert cfg.projector.patterns().cycle(alternate=cfg.projector.alternate_order) == [0, 1, 2, 0, 2, 1]
    seen = {}
    report = run_live(cfg, record=tmp_path / "rec", bursts=4, decoder=Decoder(classical=True),
                      on_burst=lambda m, row: seen.setdefault(m.burst.index, m), handle_signals=False)
    assert report.bursts == 4 and report.status.measured == len(seen) >= 2, report.summary()
    orders = {k: m.burst.reversed_order for k, m in seen.items()}
    assert all(orders[k] == (k % 2 == 1) for k in orders), orders
    counts = {k: len(m.cloud) for k, m in seen.items()}
    assert min(counts.values()) >= 0.95 * max(counts.values()) > 500, counts
    metrics = replay(tmp_path / "rec", decoder=Decoder(classical=True), truth=False)
    assert len(metrics.per_burst) == 4 and metrics.assembler["pattern_errors"] == 0


def test_a_hardware_sequenced_projector_plays_the_alternating_order(tmp_path):
    """With trigger = hardware the projector plays the sequence by itself: the camera must count its
    length and numbers each frame by it (0, 1, 2, 0, 2, 1), or the session is refused by name."""
    from gearscan.acquire import AcquisitionSession
    from gearscan.acquisition.config import ConfigError

    rec = render_recording(tmp_path / "twin", rig=default_rig(64, 64), motion="static", bursts=1)
    text = _config(tmp_path, rec, tmp_path / "rig.json", None).read_text().replace(
        'trigger = "software"', 'trigger = "hardware"').replace("settle_ms = 1", "settle_ms = 1\nalternate_order = true")
    with pytest.raises(ConfigError, match=r"camera.pattern_cycle: must be 6 .*\[0, 1, 2, 0, 2, 1\]"):
        AcquisitionSession(LiveConfig.from_toml(text.replace('trigger = "hardware"', 'trigger = "hardware"\npattern_cycle = 3'), "live.toml"))
    with pytest.raises(ConfigError, match="camera.pattern_sequence"):
        AcquisitionSession(LiveConfig.from_toml(text.replace(
            'trigger = "hardware"', 'trigger = "hardware"\npattern_cycle = 6\npattern_sequence = [0, 1, 2, 0, 1, 2]'), "live.toml"))
    session = AcquisitionSession(LiveConfig.from_toml(text.replace('trigger = "hardware"', 'trigger = "hardware"\npattern_cycle = 6'), "live.toml"))
    assert session.settings.pattern_sequence == (0, 1, 2, 0, 2, 1)


def test_live_gives_the_reconstructor_the_models_own_support_test(twin, tmp_path, monkeypatch, own_support_decoder,
                                                                 support_spy):
    """Unset in the config, the live reconstructor runs the decoding model's per-burst fringe-support test (its JSON's
    ``network_support``), else the product's; ``network_support_px`` in the config overrides both (-1: off)."""
    from gearscan.live import run_live
    from gearscan.recon import measure

    root, rec, rig_path = twin
    cfg = LiveConfig.load(_config(tmp_path, rec, rig_path, None))
    assert cfg.recon.network_support_px is None
    monkeypatch.setattr(measure, "NETWORK_SUPPORT_PX", 6)
    off = cfg.model_copy(update={"recon": cfg.recon.model_copy(update={"network_support_px": -1})})
    for config, decoder, expected in ((cfg, own_support_decoder(4, 9), 4), (cfg, Decoder(classical=True), 6),
                                      (off, own_support_decoder(4, 9), None)):
        with pytest.raises(support_spy.Called):
            run_live(config, bursts=1, decoder=decoder, handle_signals=False)
        assert support_spy.calls[-1]["network_support_px"] == expected


def test_a_real_projector_at_another_size_than_its_calibration_is_refused(tmp_path):
    """The template's window projector (1280x800) against a rig calibrated at 912x1140: the fringe period and every
    decoded point are in the calibrated projector's pixels, so the mismatch is named at load; the mock backend, which
    draws for no camera, is not held to it; the calibrated size loads."""
    import dataclasses

    from gearscan.acquisition.config import ConfigError
    from gearscan.config import TEMPLATE
    from gearscan.core.rig import default_rig

    rig = default_rig()
    other = dataclasses.replace(rig, projector=dataclasses.replace(rig.projector, width=912, height=1140))
    other.save(tmp_path / "rig.json")
    cfg = LiveConfig.from_toml(TEMPLATE, "live.toml", tmp_path)
    with pytest.raises(ConfigError, match=r"projector: 1280x800 px, but the rig calibration .* has a 912x1140"):
        cfg.load_rig()
    mock = LiveConfig.from_toml(TEMPLATE.replace('backend = "window"', 'backend = "mock"'), "live.toml", tmp_path)
    assert mock.load_rig().projector.width == 912
    rig.save(tmp_path / "rig.json")
    assert cfg.load_rig().projector.width == 1280
    # --simulate draws with the mock projector: a config's window projector at another size is not held against it
    from gearscan.simulated import simulated_config

    other.save(tmp_path / "rig.json")
    sim = simulated_config(cfg, "sim-camera", str(tmp_path / "enc"), tmp_path)
    assert sim.projector.backend == "mock" and sim.load_rig().projector.width == 912
    # a LightCrafter plays its own resolution: its configured size is not compared
    lc = LiveConfig.from_toml(TEMPLATE.replace('backend = "window"', 'backend = "lightcrafter"'), "live.toml", tmp_path)
    assert lc.load_rig().projector.width == 912


def test_a_config_without_gear_or_projector_says_what_it_runs_on(tmp_path):
    """A live config lacking [gear] or [projector] runs on defaults (a 20-tooth module-2 CAD, the mock projector):
    said, not silent; the template lacks neither."""
    import re

    from typer.testing import CliRunner

    from gearscan.cli import app
    from gearscan.config import TEMPLATE

    assert LiveConfig.from_toml(TEMPLATE).defaulted_sections() == []
    sections = re.split(r"(?m)^(?=\[)", TEMPLATE)  # the template's tables, each from its header line
    bare = "".join(t for t in sections if not t.startswith(("[gear]", "[projector]")))
    notes = LiveConfig.from_toml(bare).defaulted_sections()
    assert len(notes) == 2 and "default gear (z = 20, m = 2 mm)" in notes[0] and "mock projector" in notes[1]
    path = tmp_path / "bare.toml"
    path.write_text(bare)
    res = CliRunner().invoke(app, ["live", "--config", str(path), "--check"])  # the devices are absent: it stops
    assert "no [gear] section" in res.output and "no [projector] section" in res.output, res.output
