"""Faults during acquisition with real counterparts: the Aravis GigE simulator (software
trigger), the mock projector and the mock encoder process on a pty, through the session that
`live` and `record` share. A restarted encoder, a reader thread that dies. Truth: the mock's
clock parameters give the true turntable angle at every host time."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_acquisition_record import _toml, sim  # noqa: F401 - sim is a fixture

from gearscan.acquisition.config import AcquisitionConfig
from gearscan.core.recording import RecordingReader


def test_a_rebooted_encoder_is_resynchronised_with_angles_in_one_reference(tmp_path, sim, caplog):  # noqa: F811
    """The encoder restarts mid-run (seq, clock and count back at 0): acquisition goes on, discards
    the bursts without an angle until the index mark passes, and every recorded frame's angle is
    the true turntable angle at its exposure, before and after the restart."""
    from gearscan.acquire import AcquisitionSession
    from gearscan.mocks.encoder_device import MockEncoderProcess

    rpm, start = 30.0, -0.3  # a turn in 2 s: the index at 0.1 s, 2.1 s, 4.1 s
    link = str(tmp_path / "enc")
    with MockEncoderProcess(link, rate=1000, cpr=10000, rpm=rpm, start_angle=start, duration=30,
                            reboot_at=1.0, disconnect_for=0.3, linger=0) as dev:
        session = AcquisitionSession(AcquisitionConfig.load(_toml(tmp_path, sim.serial, link)), tmp_path / "rec")
        after = 0
        with session:
            dev.wait_started()
            for _burst in session.bursts(max_frames=30):  # as live: 30 frames without a burst abort it
                if session.encoder.stats.restarts:
                    after += 1
                if after >= 5:
                    break
        dev._read_until("REBOOT")
        dev.kill()
    st = session.encoder.stats
    assert st.restarts == 1 and st.unreferenced > 300 and st.out_of_order == 0, st
    assert "restarted" in caplog.text and "angles restored" in caplog.text
    assert session.assembler.stats.encoder_gaps >= 1  # bursts during the pause: discarded, counted
    out = RecordingReader(tmp_path / "rec")
    assert out.meta["encoder_stats"]["restarts"] == 1
    reboot_host = dev.start_ns + dev.reboot[1] * 1e9
    mid = np.array([r.host_timestamp_ns + r.exposure_us * 500 for r in out.records])
    assert (mid < reboot_host).sum() >= 9 and (mid > reboot_host).sum() >= 9, "bursts on both sides of the restart"
    theta = start + rpm * 2 * math.pi / 60 * (mid - dev.start_ns) / 1e9
    err = np.array([r.encoder_angle for r in out.records]) - theta
    # 3.1 rad/s: 0.01 rad is 3 ms of clock mapping and interpolation error; a lost reference is radians
    assert np.max(np.abs(err)) < 0.01, err


def test_a_dead_encoder_reader_stops_acquisition_at_once_with_its_cause(tmp_path, sim, monkeypatch):  # noqa: F811
    """A reader thread that dies stops the acquisition with its cause at the next frame, not as
    'no valid burst ... not yet received' a second later."""
    import time

    import gearscan.acquisition.encoder as encoder
    from gearscan.acquire import AcquisitionSession
    from gearscan.acquisition.encoder import EncoderError
    from gearscan.mocks.encoder_device import MockEncoderProcess

    parse, died = encoder.parse_line, []

    def failing_parse(line):  # an exception nobody foresaw, 1.5 s into the stream
        if died or parse(line).__class__.__name__ == "RawSample" and parse(line).seq >= 1500:
            died.append(time.monotonic())
            raise MemoryError("injected fault")
        return parse(line)

    monkeypatch.setattr(encoder, "parse_line", failing_parse)
    link = str(tmp_path / "enc")
    bursts = 0
    with MockEncoderProcess(link, rate=1000, cpr=10000, rpm=30.0, duration=30, linger=0):
        session = AcquisitionSession(AcquisitionConfig.load(_toml(tmp_path, sim.serial, link)), tmp_path / "rec")
        with pytest.raises(EncoderError) as err, session:
            for _ in session.bursts(max_frames=30):
                bursts += 1
        caught = time.monotonic()
    assert "encoder reader on" in str(err.value) and "died: MemoryError: injected fault" in str(err.value)
    assert bursts > 3 and caught - died[0] < 0.5  # it measured until the fault, then stopped at once
    out = RecordingReader(tmp_path / "rec")
    assert out.finished and len(out) == 3 * bursts  # every burst measured is in the recording


def test_a_stop_ends_the_bursts_while_a_restarted_encoder_waits_for_its_index(tmp_path, sim):  # noqa: F811
    """The encoder restarts while the turntable stands still, so its index mark never comes back and no burst is made:
    a stop asked from another thread (live's --duration, Ctrl-C) ends the bursts at the next frame instead of waiting
    for a burst that does not come (it had run on until the device's end, 30 s here); the recording stays whole."""
    import threading
    import time

    from gearscan.acquire import AcquisitionSession
    from gearscan.mocks.encoder_device import MockEncoderProcess

    link = str(tmp_path / "enc")
    stop, asked = threading.Event(), []

    def ask() -> None:
        asked.append(time.monotonic())
        stop.set()

    timer = threading.Timer(3.0, ask)  # well after the restart (1 s), from another thread
    with MockEncoderProcess(link, rate=1000, cpr=10000, rpm=30.0, start_angle=-0.3, motion="stop", stop_at=0.5,
                            reboot_at=1.0, disconnect_for=0.3, duration=30, linger=0):
        session = AcquisitionSession(AcquisitionConfig.load(_toml(tmp_path, sim.serial, link)), tmp_path / "rec")
        with session:
            timer.start()
            for _burst in session.bursts(max_frames=30, stop=stop.is_set):
                pass
            ended = time.monotonic()
    timer.join()
    assert asked and session.encoder.stats.restarts == 1 and session.encoder.resyncing
    assert ended - asked[0] < 5.0  # the next frame (a grab waits at most 2 s), not the device's end
    out = RecordingReader(tmp_path / "rec")
    assert out.finished and len(out) == 3 * session.burst_count


def test_a_pulled_encoder_cable_is_named_as_the_cause_when_no_burst_comes(tmp_path, sim):  # noqa: F811
    """The encoder's cable is pulled and stays out: no frame gets an angle, so no burst is made; the run stops naming
    the disconnected encoder (it had said "no valid burst in 30 frames" with the assembler's raw counters)."""
    from gearscan.acquire import AcquisitionSession
    from gearscan.acquisition.encoder import EncoderError
    from gearscan.mocks.encoder_device import MockEncoderProcess

    link = str(tmp_path / "enc")
    with MockEncoderProcess(link, rate=1000, cpr=10000, rpm=30.0, duration=60, disconnect_at=1.0, disconnect_for=50,
                            linger=0):
        session = AcquisitionSession(AcquisitionConfig.load(_toml(tmp_path, sim.serial, link)), tmp_path / "rec")
        bursts = 0
        with pytest.raises(EncoderError, match=r"encoder on .* is disconnected \(cable or power\?\)"), session:
            for _ in session.bursts(max_frames=30):
                bursts += 1
    assert bursts >= 1 and session.encoder.stats.disconnects >= 1
    out = RecordingReader(tmp_path / "rec")
    assert out.finished and len(out) == 3 * bursts  # what was measured before the cable came out is kept
