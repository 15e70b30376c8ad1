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


def _true_theta(dev, t_us, rpm, start):
    """True angle of device times ``t_us`` (before or after a restart, from the mock's REBOOT line)."""
    t_us = np.asarray(t_us, dtype=np.float64)
    due = (t_us - dev.offset_us) / 1e6 / (1 + dev.drift)
    if dev.reboot is not None:
        due = due + dev.reboot[1]
    return start + rpm * 2 * math.pi / 60 * due, dev.start_ns + due * 1e9


def test_rebooted_encoder_is_resynchronised_at_the_index(tmp_path, caplog):
    """A re-plugged encoder that restarts at seq 0 (clock and count at a new zero) is recognised,
    its angles pause until the index mark and then continue in the run's reference: equal to the
    true turntable angle (whole turns included) to one count."""
    rpm, start = 60.0, -0.3  # one turn a second: the index passes at 0.05 s, 1.05 s, 2.05 s
    link = str(tmp_path / "enc")
    samples = []
    with MockEncoderProcess(link, rate=1000, cpr=CPR, rpm=rpm, start_angle=start, duration=2.6,
                            reboot_at=1.2, disconnect_for=0.3) as dev:
        reader = EncoderReader(link, CPR, on_sample=samples.append)
        with reader:
            dev.wait_started()
            assert reader.wait_for_index(2.0) and reader.freeze_reference() == "index"
            dev.wait()
            time.sleep(0.2)
    assert dev.reboot is not None
    st = reader.stats
    assert st.restarts == 1 and st.out_of_order == 0 and reader.error is None, st
    kinds = [e.kind for e in reader.events]
    assert kinds.index("restart") < kinds.index("resync"), kinds
    assert "restarted" in caplog.text and "angles restored" in caplog.text
    seqs = np.array([s.seq for s in samples])
    cut = int(np.argmax(np.diff(seqs) < 0)) + 1  # first sample after the restart
    after = samples[cut:]
    assert after[0].index and after[0].seq > 0  # nothing between the restart and the index
    assert st.unreferenced == after[0].seq  # ... each of those samples counted
    t_us = np.array([s.device_time_us for s in after])
    theta, true_host = _true_theta(dev, t_us, rpm, start)
    assert theta[0] > 2 * math.pi  # the third index: two whole turns, restored too
    assert np.max(np.abs(np.array([s.angle for s in after]) - theta)) <= 2 * math.pi / CPR + 1e-9
    assert np.percentile(np.abs(np.array([s.host_time_ns for s in after]) - true_host), 99) < 2e6
    # the history answers for host times after the resync, with the true angle
    t_mid = int(true_host[len(after) // 2])
    a, why = reader.history.interpolate(t_mid, max_gap_ns=5_000_000)
    assert why == "" and abs(a - theta[len(after) // 2]) < 1e-2


def test_restart_that_loses_a_first_count_reference_is_an_error(tmp_path):
    """A run referenced to the first count (no index seen) cannot be put back after a restart:
    the reader stops with an error saying so, instead of angles from a new zero."""
    link = str(tmp_path / "enc")
    with MockEncoderProcess(link, rate=1000, cpr=CPR, rpm=RPM, start_angle=START, duration=1.2,
                            reboot_at=0.3, disconnect_for=0.2) as dev:
        reader = EncoderReader(link, CPR)
        with reader:
            dev.wait_started()
            while reader.stats.samples < 50:
                time.sleep(0.01)
            assert reader.freeze_reference() == "first count"  # the index passes only at 0.48 s
            dev.wait()
    assert reader.stats.restarts == 1
    with pytest.raises(EncoderError, match=r"restarted .* reference \(the first count\) cannot be restored"):
        reader.raise_if_failed()
    assert "cannot be restored" in reader.history.interpolate(time.monotonic_ns(), 10**9)[1]


def _pty_reader(tmp_path, **options):
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    link = tmp_path / "enc"
    link.symlink_to(os.ttyname(slave))
    reader = EncoderReader(str(link), CPR, **options)
    reader.start()
    return master, slave, reader


def _feed(master, reader, lines, lines_seen):
    os.write(master, b"".join(lines))
    deadline = time.monotonic() + 3
    while reader.stats.lines < lines_seen and reader.error is None and time.monotonic() < deadline:
        time.sleep(0.01)


def test_late_lines_are_glitches_and_a_restart_starts_afresh(tmp_path):
    """A late or repeated line (even three, if the stream goes on after them) is out of order; lines
    near seq 0 and back in time that go on are a restart. Before a run has a reference, the
    angles then simply start from the new first count."""
    master, slave, reader = _pty_reader(tmp_path)
    try:
        line = lambda seq, t_us, count: RawSample(seq, t_us, count, False, None).encode()  # noqa: E731
        stream = [line(k, 1000 * k, 10 * k) for k in range(20)]
        stream += [line(3, 3000, 30), line(4, 4000, 40)]  # two late lines (a retransmission)
        stream += [line(k, 1000 * k, 10 * k) for k in range(20, 30)]
        _feed(master, reader, stream, 32)
        assert reader.stats.out_of_order == 2 and reader.stats.restarts == 0 and reader.stats.samples == 30
        restarted = [line(k, 100 + 1000 * k, 5000 + 10 * k) for k in range(10)]  # new clock, new count
        _feed(master, reader, restarted, 42)
    finally:
        reader.stop()
        os.close(master)
        os.close(slave)
    st = reader.stats
    assert st.restarts == 1 and st.out_of_order == 2 and st.samples == 40 and reader.error is None
    assert reader.last_sample.seq == 9 and reader.last_sample.angle == pytest.approx(2 * math.pi * 90 / CPR)
    assert [e.kind for e in reader.events].count("restart") == 1


def test_a_dying_reader_thread_sets_its_error(tmp_path):
    """Anything unexpected in the reader thread stops it with ``error`` set, naming the cause, and
    the history says so instead of 'not yet received'."""
    def broken(sample):
        if sample.seq == 5:
            raise ZeroDivisionError("consumer bug")

    master, slave, reader = _pty_reader(tmp_path, on_sample=broken)
    try:
        _feed(master, reader, [RawSample(k, 1000 * k, k, False, None).encode() for k in range(10)], 10)
        reader._thread.join(2.0)
        assert not reader._thread.is_alive()
    finally:
        reader.stop()
        os.close(master)
        os.close(slave)
    with pytest.raises(EncoderError, match=r"encoder reader on .* died: ZeroDivisionError: consumer bug") as err:
        reader.raise_if_failed()
    assert isinstance(err.value.__cause__, ZeroDivisionError)
    assert "died: ZeroDivisionError" in reader.history.interpolate(10**9, 10**9)[1]


def test_a_narrow_counter_that_wraps_is_continued_and_an_impossible_jump_stops_the_reader(tmp_path):
    """A device whose count is a 16-bit counter wraps from 65535 to 0 while turning slowly: the angle continues
    (the wrap undone and counted) instead of jumping thousands of degrees between two frames; a jump no turntable
    makes and no counter width explains stops the reader with the cause named."""
    master, slave, reader = _pty_reader(tmp_path)
    try:
        line = lambda seq, t_us, count: RawSample(seq, t_us, count, False, None).encode()  # noqa: E731
        counts = [65_500 + 10 * k for k in range(20)]  # 10 counts per ms: crosses 65 536 at k = 4
        _feed(master, reader, [line(k, 1000 * k, c % 65_536) for k, c in enumerate(counts)], 20)
        assert reader.error is None and reader.stats.count_wraps == 1 and reader.stats.samples == 20
        assert reader.last_sample.angle == pytest.approx(2 * math.pi * (counts[-1] - counts[0]) / CPR)
        assert [e.kind for e in reader.events].count("count_wrap") == 1
        # two 16-bit ranges and a little in 1 ms: no single counter's wrap, not motion either (not "undone" twice)
        _feed(master, reader, [line(20, 20_000, counts[-1] % 65_536 + 2 * 65_536 + 10)], 21)
    finally:
        reader.stop()
        os.close(master)
        os.close(slave)
    with pytest.raises(EncoderError, match=r"count jumped by 131082 .* faster than any turntable"):
        reader.raise_if_failed()
    assert reader.stats.count_wraps == 1
