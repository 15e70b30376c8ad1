"""End to end: `gearscan record` with the GigE simulator (software trigger), the mock
projector and the mock encoder process on a pty; then bad configs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gearscan.acquisition.config import AcquisitionConfig, ConfigError
from gearscan.core.recording import RecordingReader

RPM = 6.0


def _toml(tmp_path, camera_id: str, port: str | None, extra_encoder: str = "") -> str:
    """The config file; ``port`` None leaves the [encoder] table out."""
    path = tmp_path / "rig.toml"
    encoder = f'[encoder]\nport = "{port}"\ncounts_per_rev = 10000\n{extra_encoder}' if port else ""
    path.write_text(
        f"""
[camera]
driver = "aravis"
id = "{camera_id}"
pixel_format = "Mono8"
exposure_us = 10000
roi = [0, 0, 64, 48]
trigger = "software"

{encoder}

[projector]
backend = "mock"
width = 64
height = 8
settle_ms = 5
"""
    )
    return str(path)


@pytest.fixture()
def sim():
    from gearscan.mocks.gv_simulator import GvSimulator, aravis_missing_reason, simulator_path

    if (reason := aravis_missing_reason()) is not None:
        pytest.fail(f"{reason} (scripts/setup.sh installs both)")  # a missing install must not pass as green
    simulator_path()  # fails (not skips) when aravis-tools is missing

    with GvSimulator() as s:
        yield s


def test_record_bursts_from_simulator_and_encoder(tmp_path, sim):
    from gearscan.cli import record
    from gearscan.core.rig import default_rig
    from gearscan.mocks.encoder_device import MockEncoderProcess

    link = str(tmp_path / "enc")
    default_rig(64, 48).save(tmp_path / "rig.json")  # the config's default rig.calibration, next to it
    with MockEncoderProcess(link, rate=1000, cpr=10000, rpm=RPM, start_angle=-0.1, duration=30, linger=0) as dev:
        record(tmp_path / "rec", config=_toml(tmp_path, sim.serial, link), bursts=3, overwrite=False)
        dev.kill()
    rec = RecordingReader(tmp_path / "rec")
    assert rec.finished and len(rec) == 9
    assert rec.rig.to_json() == default_rig(64, 48).to_json() and rec.meta["source"] == "record"
    assert [r.pattern_index for r in rec.records] == [0, 1, 2] * 3
    assert rec.meta["assembler"]["bursts"] == 3 and rec.meta["camera"]["serial"] == sim.serial
    assert rec.meta["encoder_reference"] == "index"  # the session waited for it (0.16 s in)
    angles = np.array([r.encoder_angle for r in rec.records])
    dt = np.diff([r.host_timestamp_ns for r in rec.records]) / 1e9
    # the turntable turns at 6 rpm: angle steps match the time steps between exposures
    np.testing.assert_allclose(np.diff(angles), RPM * 2 * math.pi / 60 * dt, atol=3e-3)
    enc = rec.encoder_samples()
    assert len(enc) > 50 and all(b.seq > a.seq for a, b in zip(enc, enc[1:], strict=False))
    for i in range(len(rec)):  # the simulator's exact test image
        f = rec.frame(i)
        y, x = np.mgrid[0:48, 0:64]
        np.testing.assert_array_equal(f.image, (x + y + f.frame_id) % 255)


def test_no_index_mark_in_time_is_a_clear_error_and_zero_wait_measures_from_the_first_count(tmp_path, sim):
    from gearscan.acquire import record_bursts
    from gearscan.acquisition.encoder import EncoderError
    from gearscan.mocks.encoder_device import MockEncoderProcess

    link = str(tmp_path / "enc")
    # the index (theta = 0) comes 9 s in at 6 rpm from 0.5 rad
    with MockEncoderProcess(link, rate=1000, cpr=10000, rpm=RPM, start_angle=0.5, duration=30, linger=0) as dev:
        cfg = AcquisitionConfig.load(_toml(tmp_path, sim.serial, link, "index_wait_s = 0.5"))
        with pytest.raises(EncoderError, match=r"no index mark within encoder.index_wait_s = 0.5 s .*turntable turning"):
            record_bursts(cfg, tmp_path / "r0", 1)
        assert not (tmp_path / "r0").exists()  # nothing half-made to clean up before a retry
        cfg = AcquisitionConfig.load(_toml(tmp_path, sim.serial, link, "index_wait_s = 0"))
        record_bursts(cfg, tmp_path / "r1", 2)
        dev.kill()
    rec = RecordingReader(tmp_path / "r1")
    assert rec.meta["encoder_reference"] == "first count" and len(rec) == 6


def test_bad_configs_name_the_setting(tmp_path, sim):
    from gearscan.acquire import record_bursts

    with pytest.raises(ConfigError, match=r"encoder.counts_per_rev: Input should be greater than 0 \(got 0\)"):
        AcquisitionConfig.from_dict({"encoder": {"port": "/dev/ttyUSB0", "counts_per_rev": 0}})
    with pytest.raises(ConfigError, match=r"camera.pixel_format: Value error, pixel_format must be one of .* got 'RGB8'"):
        AcquisitionConfig.from_dict({"camera": {"pixel_format": "RGB8"}})
    with pytest.raises(ConfigError, match=r"camera.exposre_us: Extra inputs are not permitted"):
        AcquisitionConfig.from_dict({"camera": {"exposre_us": 5}})
    cfg = AcquisitionConfig.load(_toml(tmp_path, sim.serial, str(tmp_path / "no-such-tty")))
    from gearscan.acquisition.encoder import EncoderError

    with pytest.raises(EncoderError, match=r"encoder.port: '.*no-such-tty' does not exist"):
        record_bursts(cfg, tmp_path / "r1", 1)
    from gearscan.acquisition.camera import CameraConfigError, CameraNotFound

    cfg = AcquisitionConfig.from_dict({"camera": {"id": "GS-NOT-THERE", "trigger": "software"}})
    with pytest.raises(CameraNotFound, match=rf"camera.id: 'GS-NOT-THERE' not found; Aravis sees: .*{sim.serial}"):
        record_bursts(cfg, tmp_path / "r2", 1)
    cfg = AcquisitionConfig.from_dict({"camera": {"id": sim.serial, "pixel_format": "Mono12", "trigger": "software"}})
    with pytest.raises(CameraConfigError, match=r"camera.pixel_format: 'Mono12' not offered .*\['Mono8', 'Mono16'\]"):
        record_bursts(cfg, tmp_path / "r3", 1)


def test_devices_lists_the_simulator_and_serial_ports(sim, capsys, monkeypatch):
    from gearscan.acquisition.commands import devices

    monkeypatch.setenv("COLUMNS", "200")
    devices(timeout=0.3, port=[], probe=True)
    out = capsys.readouterr().out
    assert sim.serial in out and "Aravis" in out and "127.0.0.1" in out
    assert "Serial ports" in out


def test_without_encoder_the_gear_is_taken_as_still_at_angle_zero(tmp_path, sim):
    """The template says [encoder] may be left out: then every burst is measured at angle 0
    (it used to be discarded with "no encoder angle") and the recording says so."""
    from gearscan.acquire import NO_ENCODER_REFERENCE, record_bursts

    cfg = AcquisitionConfig.load(_toml(tmp_path, sim.serial, None))
    assert cfg.encoder is None
    summary = record_bursts(cfg, tmp_path / "rec", 2)
    rec = RecordingReader(tmp_path / "rec")
    assert summary.bursts == 2 and summary.assembler["encoder_gaps"] == 0 and len(rec) == 6
    assert [r.encoder_angle for r in rec.records] == [0.0] * 6
    assert rec.meta["encoder_reference"] == NO_ENCODER_REFERENCE and rec.meta["encoder"] is None
