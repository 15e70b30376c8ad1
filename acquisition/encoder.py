"""Turntable encoder link: a pyserial reader thread speaking :mod:`encoder_protocol`.

The thread reads bytes, splits lines, checks checksums and sequence numbers, converts
counts to radians (counts-per-rev, zeroed at the index mark), maps the device clock onto
the host clock (:class:`ClockSync`: offset and drift) and appends
:class:`~gearscan.core.types.EncoderSample` to a bounded :class:`EncoderHistory` that the burst
assembler interpolates in. It never dies on bad input: corrupt, partial and out-of-order
lines are counted in :class:`EncoderStats` and skipped; a vanished port (unplugged adapter)
is reported in ``events`` and reopened until it comes back.

A device that restarts (power cycle, watchdog, re-plug of a bus-powered encoder) begins again
at seq 0 with its clock and count at a new zero. The reader recognises it: lines behind the
last one in sequence AND in device time, near seq 0, several in a row that follow each other
(one late or repeated line is a glitch, counted as out of order). The counts after a restart
are relative to wherever the table stood at power-up, so the run's angle reference is lost:
the reader pauses the angles (frames in between get none and their bursts are discarded,
counted as encoder gaps) until the index mark passes, which is a fixed place on the table and
restores the reference exactly (whole turns continued in the direction of motion). Angles
relative to a new zero would silently mix two references in one run, which a metrology user
cannot see and cannot undo. Without a known index position, or without an index within
``resync_wait_s``, the reader stops with an :class:`EncoderError` saying so.

A reader thread that dies on anything unexpected sets :attr:`EncoderReader.error`;
:meth:`EncoderReader.raise_if_failed` (called by the acquisition per frame) raises it.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from gearscan.acquisition.clock import ClockSync
from gearscan.acquisition.encoder_protocol import (
    PROTOCOL_VERSION,
    SEQ_MODULUS,
    Banner,
    ProtocolError,
    RawSample,
    parse_line,
)
from gearscan.core.types import EncoderSample

MAX_LINE = 256
#: a restart begins at seq 0; the reader may miss its first lines while it reopens the port
RESTART_SEQ_MAX = 10_000
#: consecutive lines behind the last one (seq and time) that follow each other: a restart, not a glitch
RESTART_CONFIRM = 3
# a count step faster than this is no turntable's motion (3000 rpm); a device's counter narrower than the protocol's
# int64 that wraps makes such a step of one of these widths, which is undone (and counted); any other is a fault
MAX_TURNS_PER_S = 50.0
COUNTER_BITS = (16, 24, 32)

log = logging.getLogger(__name__)


class EncoderError(RuntimeError):
    """The encoder link cannot be used (port missing, wrong protocol version, bad setting)."""


@dataclass(slots=True)
class EncoderStats:
    lines: int = 0
    samples: int = 0
    corrupt: int = 0  # bad checksum / fields / garbage
    partial: int = 0  # over-long or cut lines (no newline within MAX_LINE)
    out_of_order: int = 0  # seq not after the last one (duplicate or late)
    lost: int = 0  # seq gaps while connected: lines the device sent that never arrived
    missed_disconnected: int = 0  # seq gap across a disconnect/reconnect
    banners: int = 0
    disconnects: int = 0
    reconnects: int = 0
    index_ignored: int = 0  # index marks after the reference was frozen at the first count
    restarts: int = 0  # device restarts (seq and clock back near 0)
    count_wraps: int = 0  # the device's count wrapped (a 16/24/32-bit counter): undone, the angle continues
    unreferenced: int = 0  # samples after a restart before the index restored the angle reference

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass(frozen=True, slots=True)
class LinkEvent:
    host_time_ns: int
    kind: str  # "connected", "disconnected", "reconnected", "banner", "version", "index", "reference",
    # "restart", "resync", "count_wrap", "error"
    detail: str


class EncoderHistory:
    """Bounded, time-ordered samples with interpolation of the angle at a host time.

    With ``clock`` set, samples are stored in DEVICE time and a host-time query is mapped
    through the clock's current fit: every sample is then placed with the best mapping
    known at query time, and a refit (a faster message lowering the latency floor) never
    leaves a step in the history. Without a clock, times are host times as given.
    """

    def __init__(self, capacity: int = 65_536, clock: ClockSync | None = None):
        self.capacity = int(capacity)
        self.clock = clock
        self._t = np.zeros(self.capacity, dtype=np.int64)
        self._a = np.zeros(self.capacity, dtype=np.float64)
        self._n = 0  # total ever appended
        self._lock = threading.Lock()
        #: why no angle can be had past the stored samples (the encoder restarted), "" normally
        self.unavailable = ""

    def __len__(self) -> int:
        return min(self._n, self.capacity)

    def append(self, host_time_ns: int, angle: float) -> None:
        with self._lock:
            i = self._n % self.capacity
            self._t[i], self._a[i] = host_time_ns, angle
            self._n += 1
            self.unavailable = ""

    def shift(self, delta: float) -> None:
        """Add ``delta`` rad to every stored angle (re-zeroing at the index mark)."""
        with self._lock:
            self._a[: len(self)] += delta

    def clear(self, reason: str) -> None:
        """Forget every sample (their device times belong to a clock that restarted); until the
        next append, :meth:`interpolate` answers ``reason``."""
        with self._lock:
            self._n = 0
            self.unavailable = reason

    def extend(self, samples: list[EncoderSample]) -> None:
        for s in samples:
            self.append(s.host_time_ns, s.angle)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(times ns, angles rad), oldest first."""
        with self._lock:
            n = len(self)
            if self._n <= self.capacity:
                return self._t[:n].copy(), self._a[:n].copy()
            i = self._n % self.capacity
            return np.roll(self._t, -i).copy(), np.roll(self._a, -i).copy()

    def interpolate(self, t_ns: int, max_gap_ns: int) -> tuple[float | None, str]:
        """Angle at host time ``t_ns`` linearly between the two bracketing samples.

        Returns ``(angle, "")`` or ``(None, reason)`` when ``t_ns`` is outside the history
        or the bracketing samples are more than ``max_gap_ns`` apart (an encoder gap).
        """
        t, a = self.arrays()
        if t.size < 2:
            return None, self.unavailable or "encoder history empty"
        if self.clock is not None:
            t_ns = self.clock.to_device(t_ns)
        if t_ns < t[0]:
            return None, f"time {t_ns} before encoder history start {t[0]}"
        if t_ns > t[-1]:
            return None, f"time {t_ns} after last encoder sample {t[-1]} (not yet received?)"
        j = int(np.searchsorted(t, t_ns, side="right"))
        j = min(max(j, 1), t.size - 1)
        t0, t1 = int(t[j - 1]), int(t[j])
        if t1 - t0 > max_gap_ns:
            return None, f"encoder gap of {(t1 - t0) / 1e6:.2f} ms around the exposure (max {max_gap_ns / 1e6:g} ms)"
        if t1 == t0:
            return float(a[j]), ""
        w = (t_ns - t0) / (t1 - t0)
        return float(a[j - 1] + w * (a[j] - a[j - 1])), ""


class EncoderReader:
    """Reads an encoder on ``port`` in a thread; use as a context manager.

    counts_per_rev: from the config; must match the device banner when it states one.
    zero_on_index: angle 0 at the index mark; until the first index, angles are relative to
    the first count seen (``zeroed`` says which). :meth:`freeze_reference` fixes the reference
    when acquisition starts, so one recording never mixes the two (a late index is then ignored).
    resync_wait_s: after a device restart, how long to wait for the index mark that restores
    the angle reference before giving up with :attr:`error` set.
    """

    def __init__(
        self,
        port: str,
        counts_per_rev: int,
        *,
        baudrate: int = 115_200,
        zero_on_index: bool = True,
        history: EncoderHistory | None = None,
        on_sample: Callable[[EncoderSample], None] | None = None,
        reconnect_poll_s: float = 0.1,
        clock_window: int = 4096,
        resync_wait_s: float = 60.0,
    ):
        if counts_per_rev <= 0:
            raise EncoderError(f"encoder.counts_per_rev must be > 0, got {counts_per_rev}")
        self.port = port
        self.counts_per_rev = int(counts_per_rev)
        self.baudrate = baudrate
        self.zero_on_index = zero_on_index
        self.on_sample = on_sample
        self.reconnect_poll_s = reconnect_poll_s
        self.clock = ClockSync(window=clock_window, min_span_ns=500_000_000, refit_every=64)
        self.history = history if history is not None else EncoderHistory(clock=self.clock)
        self.stats = EncoderStats()
        self.events: list[LinkEvent] = []
        self.banner: Banner | None = None
        self.zero_count: int | None = None
        self.zeroed = False
        self._zeroed_event = threading.Event()
        self.reference_frozen = False
        self.connected = threading.Event()
        self.last_sample: EncoderSample | None = None
        self._last_seq: int | None = None
        self._last_t_us = 0
        self._last_rel = 0  # last sample's count - zero_count
        self._count_offset = 0  # added to the device's count: undoes its counter's wraps (COUNTER_BITS)
        self._last_count: int | None = None  # the last accepted sample's count, wraps undone
        self._index_rel: int | None = None  # where the index mark is in the current reference (counts)
        self._pending: list[tuple[RawSample, int]] = []  # lines behind the last one: a restart or a glitch
        self.resync_wait_s = resync_wait_s
        self._resync_since_ns: int | None = None  # a restart paused the angles at this host time
        self._after_reconnect = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._serial = None
        self.error: BaseException | None = None

    # -- lifecycle ------------------------------------------------------------------------
    def __enter__(self) -> EncoderReader:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self, wait_connected_s: float = 2.0) -> None:
        """Open the port (raising EncoderError naming it if missing) and start the thread."""
        if not os.path.exists(self.port) and not self.port.startswith(("socket://", "loop://", "rfc2217://")):
            raise EncoderError(f"encoder.port: {self.port!r} does not exist; serial ports found: {list_serial_ports()}")
        self._open()
        self._event("connected", self.port)
        self._thread = threading.Thread(target=self._run, name=f"encoder {self.port}", daemon=True)
        self._thread.start()

    @property
    def resyncing(self) -> bool:
        """True from a device restart until the index mark restored the angle reference."""
        return self._resync_since_ns is not None

    def raise_if_failed(self) -> None:
        """Raise :attr:`error` (the reader thread stopped: its cause, what it means) if set."""
        if self.error is not None:
            raise self.error

    def wait_for_index(self, timeout_s: float) -> bool:
        """Block until the index mark has zeroed the angles (True) or ``timeout_s`` passes (False)."""
        return self._zeroed_event.wait(timeout_s)

    def freeze_reference(self) -> str:
        """Keep the current angle reference for the rest of the run; returns it ("index" or
        "first count"). Called when acquisition starts: angles stamped on frames before a later
        index would otherwise sit in another reference than those after it."""
        self.reference_frozen = True
        reference = "index" if self.zeroed else "first count"
        self._event("reference", f"angles relative to the {reference}")
        return reference

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._close()

    def _open(self) -> None:
        import serial

        self._serial = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.05)
        try:
            self._serial.write(b"HELLO\n")
        except (OSError, serial.SerialException):
            pass  # a read-only link still works; the banner also arrives on connect
        self.connected.set()

    def _close(self) -> None:
        self.connected.clear()
        if self._serial is not None:
            try:
                self._serial.close()
            except OSError:
                pass  # already gone with the device
            self._serial = None

    def _event(self, kind: str, detail: str) -> None:
        self.events.append(LinkEvent(time.monotonic_ns(), kind, detail))

    # -- thread -----------------------------------------------------------------------------
    def _run(self) -> None:
        """The thread: any exception it did not expect ends it with :attr:`error` set (the
        acquisition raises it at the next frame) instead of a silent death."""
        try:
            self._loop()
        except BaseException as exc:  # noqa: BLE001 - handed to the acquisition through self.error
            self._fail(f"encoder reader on {self.port} died: {type(exc).__name__}: {exc}", exc)

    def _fail(self, msg: str, cause: BaseException | None = None) -> None:
        error = EncoderError(msg)
        error.__cause__ = cause
        self.error = error
        self._event("error", msg)
        self.history.clear(msg)
        self._stop.set()

    def _loop(self) -> None:
        import serial

        buf = b""
        while not self._stop.is_set():
            try:
                chunk = self._serial.read(max(1, self._serial.in_waiting))
            except (OSError, serial.SerialException, TypeError, AttributeError) as exc:
                self.stats.disconnects += 1
                self._event("disconnected", f"{self.port}: {exc}")
                self._close()
                if buf:
                    self.stats.partial += 1  # a line cut by the unplug
                buf = b""
                if not self._reconnect():
                    return
                continue
            if not chunk:
                continue
            arrival = time.monotonic_ns()
            buf += chunk
            *lines, buf = buf.split(b"\n")
            if len(buf) > MAX_LINE:
                self.stats.partial += 1
                buf = b""
            for line in lines:
                self._handle(line, arrival)

    def _reconnect(self) -> bool:
        import serial

        while not self._stop.is_set():
            time.sleep(self.reconnect_poll_s)
            if not os.path.exists(self.port):
                continue
            try:
                self._open()
            except (OSError, serial.SerialException):
                continue
            self.stats.reconnects += 1
            self._after_reconnect = True
            self._event("reconnected", self.port)
            return True
        return False

    def _handle(self, line: bytes, arrival_ns: int) -> None:
        if not line.strip() or self.error is not None:  # after a fatal error no line is data
            return
        self.stats.lines += 1
        if len(line) > MAX_LINE:
            self.stats.partial += 1
            return
        try:
            msg = parse_line(line)
        except ProtocolError:
            self.stats.corrupt += 1
            return
        if isinstance(msg, Banner):
            self._on_banner(msg)
            return
        self._on_sample(msg, arrival_ns)

    def _on_banner(self, b: Banner) -> None:
        self.stats.banners += 1
        if b.version != PROTOCOL_VERSION:
            self.error = EncoderError(f"encoder at {self.port} speaks protocol v{b.version}, this reader v{PROTOCOL_VERSION}")
            self._event("version", str(self.error))
            self._stop.set()
            return
        if b.counts_per_rev != self.counts_per_rev:
            self._event(
                "banner",
                f"device {b.device!r} reports {b.counts_per_rev} counts/rev, config says {self.counts_per_rev}: using config",
            )
        else:
            self._event("banner", f"device {b.device!r} v{b.version}, {b.counts_per_rev} counts/rev")
        self.banner = b

    def _on_sample(self, s: RawSample, arrival_ns: int) -> None:
        if self._last_seq is not None:
            step = (s.seq - self._last_seq) % SEQ_MODULUS
            if step == 0 or step > SEQ_MODULUS // 2:
                self._behind(s, arrival_ns)
                return
            if self._pending:  # the stream went on: the lines behind it were late or repeated
                self.stats.out_of_order += len(self._pending)
                self._pending.clear()
            if self._after_reconnect:
                self.stats.missed_disconnected += step - 1
            else:
                self.stats.lost += step - 1
        self._accept(s, arrival_ns)

    def _behind(self, s: RawSample, arrival_ns: int) -> None:
        """A line not after the last one: a glitch, or (RESTART_CONFIRM of them following each
        other, near seq 0 and back in device time) the first lines of a restarted device."""
        if self._pending:
            prev = self._pending[-1][0]
            follows = (s.seq - prev.seq) % SEQ_MODULUS == 1 and s.t_us > prev.t_us
        else:
            follows = s.seq <= RESTART_SEQ_MAX and s.t_us < self._last_t_us
        if not follows:
            self.stats.out_of_order += 1
            return
        self._pending.append((s, arrival_ns))
        if len(self._pending) < RESTART_CONFIRM:
            return
        pending, self._pending = self._pending, []
        self._restart(pending[0][0])
        if self.error is not None:
            return
        for p, t in pending:
            self._accept(p, t)

    def _restart(self, first: RawSample) -> None:
        """The device restarted: its clock and count are at a new zero. Pause the angles until
        the index mark restores the run's reference (or start afresh before the run has one)."""
        self.stats.restarts += 1
        was = f"seq {self._last_seq} -> {first.seq}, device time {self._last_t_us} -> {first.t_us} us"
        self.clock.reset()
        self._last_seq = None
        self._count_offset, self._last_count = 0, None  # a restarted device counts from a new zero
        self._after_reconnect = False
        if not self.reference_frozen and self._index_rel is None:  # no run yet: a fresh start
            self.zero_count, self.zeroed = None, False
            self._zeroed_event.clear()
            msg = f"encoder at {self.port} restarted ({was}): angles start afresh"
            self.history.clear(msg)
        elif self._index_rel is None:
            self._fail(
                f"encoder at {self.port} restarted ({was}): its count starts at a new zero and the run's angle "
                "reference (the first count) cannot be restored, as no index mark was seen before the restart. "
                "Angles after it would not be comparable with those before: start a new run (with "
                "encoder.index_wait_s > 0 a run is referenced to the index mark and survives a restart)"
            )
            return
        else:
            msg = (f"encoder at {self.port} restarted ({was}): no angles until the index mark restores the "
                   "angle reference (bursts in between are discarded)")
            self._resync_since_ns = time.monotonic_ns()
            self.history.clear(msg)
        self._event("restart", msg)
        log.warning("%s", msg)

    def _resync(self, s: RawSample) -> None:
        """At the first index after a restart: choose the zero that puts the index where the run's
        reference has it, whole turns continuing the last angle in the direction of motion."""
        assert s.index_count is not None and self._index_rel is not None
        motion = s.count - s.index_count  # counts moved since the pulse: its sign is the direction
        turns = (self._last_rel - self._index_rel) / self.counts_per_rev
        m = math.ceil(turns) if motion > 0 else math.floor(turns) if motion < 0 else round(turns)
        self.zero_count = s.index_count - self._index_rel - m * self.counts_per_rev
        waited = (time.monotonic_ns() - (self._resync_since_ns or 0)) / 1e9
        self._resync_since_ns = None
        msg = (f"index mark at count {s.index_count} after the restart: angles restored in the run's reference "
               f"({waited:.1f} s without angles, {self.stats.unreferenced} samples)")
        self._event("resync", msg)
        log.warning("%s", msg)

    def _unwrap_count(self, s: RawSample) -> RawSample | None:
        """``s`` with its count (and index count) continued past a wrap of the device's counter; None (and the reader
        failed) where the count jumps faster than a turntable turns and no counter width explains it."""
        count = s.count + self._count_offset
        if self._last_count is not None:
            dt = max(s.t_us - self._last_t_us, 0) / 1e6
            limit = self.counts_per_rev * (MAX_TURNS_PER_S * dt + 0.25)
            step = count - self._last_count
            if abs(step) > limit:
                # one wrap of a counter of b bits, where one can be told from motion at all (half its range beyond
                # what the turntable could have turned since the last sample; after a long gap it cannot)
                wrap = next((w for b in COUNTER_BITS if (1 << (b - 1)) > limit
                             for w in (1 << b, -(1 << b)) if abs(step - w) <= limit), None)
                if wrap is None:
                    self._fail(
                        f"encoder at {self.port}: count jumped by {step} ({step / self.counts_per_rev:+.2f} turns) in "
                        f"{1e3 * dt:.1f} ms, faster than any turntable ({MAX_TURNS_PER_S:g} turns/s) and no counter "
                        "wrap: the angle reference is lost (check the encoder's counter and wiring), start a new run"
                    )
                    return None
                self._count_offset -= wrap
                count -= wrap
                self.stats.count_wraps += 1
                msg = (f"encoder count wrapped ({wrap:+d} counts: a {abs(wrap).bit_length() - 1}-bit counter): "
                       "undone, the angle continues")
                self._event("count_wrap", msg)
                if self.stats.count_wraps == 1:
                    log.warning("encoder at %s: %s", self.port, msg)
        index_count = s.index_count
        if index_count is not None:  # latched on the same counter; the nearest to the count where a wrap fell between
            index_count += self._count_offset
            for b in COUNTER_BITS:
                k = round((count - index_count) / (1 << b))
                if k and abs(count - index_count - k * (1 << b)) < self.counts_per_rev:
                    index_count += k * (1 << b)
                    break
        return s if (count, index_count) == (s.count, s.index_count) else \
            RawSample(s.seq, s.t_us, count, s.index, index_count)

    def _accept(self, s: RawSample, arrival_ns: int) -> None:
        unwrapped = self._unwrap_count(s)
        if unwrapped is None:
            return
        s = unwrapped
        self._last_count = s.count
        self._last_seq, self._last_t_us = s.seq, s.t_us
        self._after_reconnect = False
        self.clock.add(s.t_us * 1000, arrival_ns)  # also while resyncing: the new clock is fitted meanwhile
        if self._resync_since_ns is not None:
            if not s.index:
                self.stats.unreferenced += 1
                if (arrival_ns - self._resync_since_ns) / 1e9 > self.resync_wait_s:
                    self._fail(
                        f"encoder at {self.port} restarted and no index mark came within {self.resync_wait_s:g} s "
                        "to restore the angle reference: is the turntable turning? Start a new run"
                    )
                return
            self._resync(s)
        elif s.index and self.zero_count is not None:
            self._index_rel = s.index_count - self.zero_count  # where the index is in this reference
        if s.index and self.zero_on_index and not self.zeroed:
            if self.reference_frozen:
                if not self.stats.index_ignored:
                    self._event("index", f"index at count {s.index_count} ignored: reference frozen at the first count")
                self.stats.index_ignored += 1
            else:
                if self.zero_count is not None:  # re-reference what was stored before the index
                    self.history.shift(-2 * math.pi * (s.index_count - self.zero_count) / self.counts_per_rev)
                self.zero_count, self.zeroed = s.index_count, True
                self._index_rel = 0
                self._zeroed_event.set()
                self._event("index", f"zeroed at count {s.index_count}")
        if self.zero_count is None:
            self.zero_count = s.count
            if s.index:
                self._index_rel = s.index_count - self.zero_count
        sample = EncoderSample(
            seq=s.seq,
            device_time_us=s.t_us,
            count=s.count,
            index=s.index,
            angle=2 * math.pi * (s.count - self.zero_count) / self.counts_per_rev,
            host_time_ns=self.clock.to_host(s.t_us * 1000),
        )
        self.stats.samples += 1
        self._last_rel = s.count - self.zero_count
        self.last_sample = sample
        self.history.append(s.t_us * 1000 if self.history.clock is self.clock else sample.host_time_ns, sample.angle)
        if self.on_sample is not None:
            self.on_sample(sample)


def list_serial_ports() -> list[str]:
    """Serial devices pyserial can enumerate (USB/ACM/ttyS with hardware)."""
    from serial.tools import list_ports

    return [p.device for p in list_ports.comports()]
