"""`gearscan devices`: the encoder probe against the mock encoder process (known rate, counts
per revolution and name) and a silent pty; the camera features of the GigE simulator."""

from __future__ import annotations

import os
import threading
import tty

import pytest
from typer.testing import CliRunner

from gearscan.acquisition.probe import probe_encoder
from gearscan.cli import app
from gearscan.mocks.encoder_device import MockEncoderProcess


def test_probe_names_the_encoder_its_rate_and_what_is_not_one(tmp_path):
    link = str(tmp_path / "enc")
    with MockEncoderProcess(link, rate=500, cpr=4096, name="bench7", garbage_every=20, duration=60, linger=0):
        found = probe_encoder(link, timeout_s=2.0)
    assert found.is_encoder and found.error is None
    assert (found.banner.device, found.banner.counts_per_rev, found.banner.version) == ("bench7", 4096, 1)
    assert found.rate_hz == pytest.approx(500, rel=0.01)  # by the device clock (50 ppm drift)
    assert found.invalid >= 1  # the injected garbage lines are counted, not taken for samples
    assert "gearscan encoder 'bench7', protocol v1, 4096 counts/rev, 500 samples/s" in found.describe()
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        # another device's lines, after the probe opened the port (pyserial drops what came before)
        threading.Timer(0.1, os.write, (master, b"AT+OK\r\nnot an encoder\n")).start()
        other = probe_encoder(os.ttyname(slave), timeout_s=0.5)
    finally:
        os.close(master)
        os.close(slave)
    assert not other.is_encoder and other.invalid == 2 and "no gearscan encoder" in other.describe()
    gone = probe_encoder(str(tmp_path / "missing"), timeout_s=0.3)
    assert gone.error and gone.describe().startswith("cannot open")


def test_devices_lists_camera_features_and_probes_ports(tmp_path):
    from gearscan.mocks.gv_simulator import GvSimulator, aravis_missing_reason

    if (reason := aravis_missing_reason()) is not None:
        pytest.fail(f"{reason} (scripts/setup.sh installs both)")  # a missing install must not pass as green
    link = str(tmp_path / "enc")
    with GvSimulator() as sim, MockEncoderProcess(link, rate=1000, cpr=10000, duration=60, linger=0):
        res = CliRunner().invoke(app, ["devices", "--port", link], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert sim.camera_id in res.output and "features" in res.output
    rows = {line.split("│")[1].strip(): line.split("│")[2].strip() for line in res.output.splitlines() if line.count("│") == 3}
    assert rows["sensor"] == "2048x2048" and "Mono8" in rows["pixel formats"] and "Software" in rows["trigger sources"]
    assert rows["exposure µs"] == "10 to 1e+07"
    assert rows[link].startswith("gearscan encoder 'mockenc', protocol v1, 10000 counts/rev")
