"""Encoder link against the mock device process speaking the protocol on a real pty.

Truth: the mock prints its clock parameters, so every sample's true host time and true
angle theta(t) (uniform motion, index at theta = 0) are known to the test.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np
import pytest

from gearscan.acquisition.encoder import EncoderError, EncoderHistory, EncoderReader
from gearscan.acquisition.encoder_protocol import ProtocolError, RawSample, parse_line
from gearscan.mocks.encoder_device import MockEncoderProcess

CPR = 10_000
RPM = 6.0  # 0.628 rad/s
START = -0.3  # rad: index (theta = 0) passes 0.48 s in


def _collect(tmp_path, duration, clock_window=4096, **faults):
    link = str(tmp_path / "enc0")
    samples = []
    with MockEncoderProcess(link, rate=1000, cpr=CPR, rpm=RPM, start_angle=START, duration=duration, **faults) as dev:
        reader = EncoderReader(link, CPR, on_sample=samples.append, clock_window=clock_window)
        with reader:
            dev.wait_started()
            summary = dev.wait()
            time.sleep(0.2)
    return dev, reader, samples, summary


def _check_truth(dev, samples):
    t_us = np.array([s.device_time_us for s in samples])
    host = np.array([s.host_time_ns for s in samples], dtype=np.float64)
    true_host = dev.true_host_ns(t_us)
    err_ms = (host - true_host) / 1e6
    # mapped host time lies just after the true event (minimum pty latency), never far off
    assert np.percentile(np.abs(err_ms), 99) < 2.0, f"clock mapping error p99 {np.percentile(np.abs(err_ms), 99):.3f} ms"
    # angle after index zeroing = true theta at that device time, to one count
    t_dev = (t_us - dev.offset_us) / 1e6 / (1 + dev.drift)
    theta = START + RPM * 2 * math.pi / 60 * t_dev
    ang = np.array([s.angle for s in samples])
    assert np.max(np.abs(ang - theta)) <= 2 * math.pi / CPR + 1e-9


def test_protocol_roundtrip_and_rejects():
    s = RawSample(4_294_967_295, 12_345_678_901, -42, True, -40)
    assert parse_line(s.encode()) == s
    bad = bytearray(s.encode())
    bad[5] ^= 1
    for line in (bytes(bad), b"$E,1,2,3,0,*00", b"\x00\xff$E,9,zz*", b"$E,1,2*", b"hello"):
        with pytest.raises(ProtocolError):
            parse_line(line)


def test_1khz_for_2s_no_lost_lines_and_truth(tmp_path):
    dev, reader, samples, summary = _collect(tmp_path, 2.0)
    assert summary["SENT"] == 2000
    assert reader.stats.samples == 2000 and reader.stats.lost == 0
    assert reader.stats.corrupt == reader.stats.out_of_order == reader.stats.disconnects == 0
    assert [s.seq for s in samples] == list(range(2000))
    assert reader.zeroed and reader.banner is not None and reader.banner.counts_per_rev == CPR
    _check_truth(dev, [s for s in samples if s.device_time_us > dev.offset_us + 600_000])
    # the history interpolates the true angle at an arbitrary host time
    t_mid = int(dev.true_host_ns(dev.offset_us + 1_500_000))
    a, why = reader.history.interpolate(t_mid, max_gap_ns=5_000_000)
    assert why == "" and abs(a - (START + RPM * 2 * math.pi / 60 * 1.5)) < 2e-3  # 2 mrad ~ 3 ms of motion


@pytest.mark.slow
def test_1khz_for_10s_no_lost_lines(tmp_path):
    dev, reader, samples, summary = _collect(tmp_path, 10.0, clock_window=16_384, drift_ppm=500)
    assert summary["SENT"] == 10_000 and reader.stats.samples == 10_000 and reader.stats.lost == 0
    # the device clock runs 500 ppm fast: host advances (1 - 500e-6) s per device second
    assert abs(reader.clock.drift_ppm - (-500.0)) < 30.0, reader.clock.drift_ppm
    _check_truth(dev, [s for s in samples if s.device_time_us > dev.offset_us + 600_000])


def test_garbage_drops_and_disconnect_are_counted_not_fatal(tmp_path):
    dev, reader, samples, summary = _collect(
        tmp_path, 2.5, garbage_every=100, drop_every=250, disconnect_at=1.2, disconnect_for=0.4
    )
    st = reader.stats
    assert summary["GARBAGE"] > 10 and summary["DROPPED"] > 3
    # every line that reached the reader is accounted for; lines still unread in the pty when
    # the cable was pulled are gone (as on a real unplug) and the mock says how many
    unread_s, unread_g = summary["UNREAD_SAMPLES"], summary["UNREAD_GARBAGE"]
    assert summary["GARBAGE"] - unread_g <= st.corrupt <= summary["GARBAGE"], (st, summary)
    assert summary["SENT"] - unread_s <= st.samples <= summary["SENT"], (st, summary)
    assert st.partial <= 1  # at most the one line the unplug cut
    # dropped lines are sequence gaps while connected; the samples the device produced
    # while unplugged (or left unread at the unplug) are counted apart
    seqs = np.array([s.seq for s in samples])
    assert st.lost + st.missed_disconnected == seqs[-1] - seqs[0] + 1 - len(seqs)
    assert summary["DROPPED"] - 1 <= st.lost <= summary["DROPPED"]  # a drop may abut the unplug gap
    assert 300 <= st.missed_disconnected <= 600  # 0.4 s unplugged at 1 kHz (+ re-open time)
    assert st.disconnects == 1 and st.reconnects == 1
    kinds = [e.kind for e in reader.events]
    assert kinds.index("disconnected") < kinds.index("reconnected")
    assert np.all(np.diff(seqs) > 0)
    _check_truth(dev, [s for s in samples if s.device_time_us > dev.offset_us + 600_000])


def test_bad_settings_name_the_setting(tmp_path):
    with pytest.raises(EncoderError, match=r"encoder.counts_per_rev must be > 0, got 0"):
        EncoderReader(str(tmp_path / "x"), 0)
    with pytest.raises(EncoderError, match=r"encoder.port: '.*/nope' does not exist; serial ports found"):
        EncoderReader(str(tmp_path / "nope"), 100).start()


def test_history_refuses_gaps_and_outside_times():
    h = EncoderHistory(capacity=8)
    for i in range(12):  # wraps the ring buffer
        h.append(i * 1_000_000 + (5_000_000 if i >= 9 else 0), i * 0.1)
    t, a = h.arrays()
    assert t.size == 8 and np.all(np.diff(t) > 0) and a[0] == pytest.approx(0.4)
    assert h.interpolate(5_500_000, 2_000_000)[0] == pytest.approx(0.55)
    assert h.interpolate(10_000_000, 2_000_000)[0] is None  # 6 ms gap between samples 8 and 9
    assert "after last" in h.interpolate(10**9, 2_000_000)[1]


def test_waiting_for_the_index_then_a_frozen_reference(tmp_path):
    """The index zeroes the angles once; after freeze_reference a later index changes nothing,
    so a run that started before the index keeps one reference (angles from the first count)."""
    link = str(tmp_path / "enc1")
    with MockEncoderProcess(link, rate=1000, cpr=CPR, rpm=RPM, start_angle=START, duration=1.5) as dev:
        reader = EncoderReader(link, CPR)
        with reader:
            dev.wait_started()
            assert reader.wait_for_index(5.0) and reader.zeroed  # index passes 0.48 s in
            assert reader.freeze_reference() == "index"
            dev.wait()
    link = str(tmp_path / "enc2")
    samples = []
    with MockEncoderProcess(link, rate=1000, cpr=CPR, rpm=RPM, start_angle=START, duration=1.5) as dev:
        reader = EncoderReader(link, CPR, on_sample=samples.append)
        with reader:
            dev.wait_started()
            while reader.stats.samples < 50:
                time.sleep(0.01)
            assert reader.freeze_reference() == "first count"  # before the index
            assert not reader.wait_for_index(1.2)
            dev.wait()
            time.sleep(0.2)
    assert not reader.zeroed and reader.stats.index_ignored == 1
    steps = np.diff([s.angle for s in samples])
    # one reference throughout: steady steps of ~0.63 mrad per 1 ms sample, no jump at the index
    assert np.all(np.abs(steps - RPM * 2 * math.pi / 60 / 1000) < 2 * 2 * math.pi / CPR), steps.min()


def test_mock_counts_lines_left_unread_at_unplug(tmp_path):
    """The mock's unplug accounting: FIONREAD on the pty slave, split into whole lines."""
    import collections

    from gearscan.mocks.encoder_device import PtyPort, unread_lines

    port = PtyPort(str(tmp_path / "enc"))
    try:
        lines = [RawSample(k, 1000 * k, k, False, None).encode() for k in range(3)]
        junk = b"\x00\xff$E,9,zz*" + lines[2][:10] + b"\n"
        recent: collections.deque[tuple[int, int]] = collections.deque()
        for line, j in zip(lines, (b"", b"", junk), strict=True):
            os.write(port.master, j + line)
            recent.append((len(j) + len(line), len(j)))
        total = sum(n for n, _ in recent)

        def settled(expected: int) -> int:  # the pty hands bytes to the slave asynchronously
            deadline = time.monotonic() + 2.0
            while port.unread_bytes() != expected and time.monotonic() < deadline:
                time.sleep(0.001)
            return port.unread_bytes()

        assert settled(total) == total
        os.read(port.slave, len(lines[0]) + 4)  # the reader took line 0 and a bit of line 1
        assert unread_lines(recent, settled(total - len(lines[0]) - 4)) == (2, 1)
        os.read(port.slave, len(lines[1]) - 4 + len(junk))  # ... then line 1 and the garbage line
        assert unread_lines(recent, settled(len(lines[2]))) == (1, 0)
        assert unread_lines(recent, 0) == (0, 0)
    finally:
        port.close()
