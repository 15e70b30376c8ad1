"""A turntable encoder that speaks the gearscan encoder protocol on a pseudo-terminal.

Run as its own process::

    python -m gearscan.mocks.encoder_device --link /tmp/enc0 --rate 1000 --cpr 10000 \\
        --motion uniform --rpm 6 --duration 10 --garbage-every 200 --drop-every 500 \\
        --disconnect-at 1.0 --disconnect-for 0.5

``--link`` is a symlink to the current pty slave (what the reader opens, like a udev
``/dev/serial/by-id`` name). A disconnect closes the pty and, after ``--disconnect-for``
seconds, opens a new one and re-points the link: a pulled and re-plugged USB adapter.

Stdout: ``READY <link>`` once the pty exists; after the host's ``HELLO`` handshake
``START <monotonic_ns> OFFSET_US <us> DRIFT_PPM <ppm>``, from which a test computes the true
host time of every device timestamp (both processes read the same CLOCK_MONOTONIC):
``host_ns = start + (t_us - offset_us) * 1000 / (1 + drift)``; after the last line
``SENT <samples written> DROPPED <n> GARBAGE <n> UNREAD_SAMPLES <n> UNREAD_GARBAGE <n>``, then
the pty stays open ``--linger`` s. ``UNREAD_*`` count the written lines still unread in the pty
when the cable was pulled: a real unplug loses them, so a reader can never see them.

``--reboot-at T`` pulls the cable at device time T like ``--disconnect-at`` and the device
restarts when it is plugged back: seq, clock and count begin again at 0 (the count at the
position the table has then). It prints ``REBOOT <k0> <due0_s>``: sample k >= k0 has seq
``k - k0``, device time ``offset_us + (k - k0) / rate * 1e6 * (1 + drift)`` and true angle
``theta(due0_s + (k - k0) / rate)``.

Motion (true angle theta(t), rad, t in seconds of device time):
``uniform``: ``w t``; ``nonuniform``: ``w t + (a w / 2 pi f)(1 - cos 2 pi f t)`` (speed
swings by +-a); ``stop``: uniform until ``--stop-at``, then still. The count is
``floor(cpr * theta / 2 pi) + count_offset``; the index mark is at theta = 0 mod 2 pi, so
after index zeroing the reader's angle equals theta up to one count.
"""

from __future__ import annotations

import argparse
import collections
import fcntl
import math
import os
import select
import subprocess
import sys
import termios
import time
import tty

import numpy as np

from gearscan.acquisition.encoder_protocol import PROTOCOL_VERSION, SEQ_MODULUS, Banner, RawSample


def theta(args: argparse.Namespace, t: float) -> float:
    w = args.rpm * 2 * math.pi / 60.0
    if args.motion == "uniform":
        return args.start_angle + w * t
    if args.motion == "nonuniform":
        f, a = args.wobble_hz, args.wobble
        return args.start_angle + w * t + (a * w / (2 * math.pi * f)) * (1 - math.cos(2 * math.pi * f * t))
    if args.motion == "stop":
        return args.start_angle + w * min(t, args.stop_at)
    raise SystemExit(f"--motion must be uniform, nonuniform or stop, got {args.motion!r}")


def unread_lines(recent: collections.deque[tuple[int, int]], unread: int) -> tuple[int, int]:
    """(sample lines, garbage lines) whose newline lies in the last ``unread`` bytes written."""
    samples = garbage = 0
    for size, junk in reversed(recent):
        if unread <= 0:
            break
        samples += 1  # the sample line ends the write, so its newline is unread
        if junk and unread > size - junk:
            garbage += 1  # the garbage line's newline is unread as well
        unread -= size
    return samples, garbage


class PtyPort:
    """One pty whose slave is published under ``link``."""

    def __init__(self, link: str):
        self.link = link
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        name = os.ttyname(self.slave)
        tmp = f"{link}.tmp{os.getpid()}"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(name, tmp)
        os.replace(tmp, link)
        os.set_blocking(self.master, True)

    def unread_bytes(self) -> int:
        """Bytes written to the master that no reader has taken from the slave yet."""
        return int.from_bytes(fcntl.ioctl(self.slave, termios.FIONREAD, b"\0\0\0\0"), sys.byteorder)

    def close(self) -> None:
        os.close(self.master)
        os.close(self.slave)


class MockEncoderProcess:
    """Starts ``python -m gearscan.mocks.encoder_device`` and parses its READY/SENT lines.

    ``options`` are the command-line options without dashes (``rate=1000``,
    ``garbage_every=100``); ``true_host_ns(t_us)`` inverts the device clock.
    """

    def __init__(self, link: str, **options: object):
        self.link = link
        self.options = options
        self.proc: subprocess.Popen[str] | None = None
        self.start_ns = 0
        self.offset_us = 0
        self.drift = 0.0
        self.summary: dict[str, int] = {}
        self.reboot: tuple[int, float] | None = None  # (k0, due0_s) once the device restarted

    def start(self, timeout: float = 10.0) -> MockEncoderProcess:
        cmd = [sys.executable, "-m", "gearscan.mocks.encoder_device", "--link", self.link]
        for k, v in self.options.items():
            cmd += [f"--{k.replace('_', '-')}", str(v)]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline().split()
        if not line or line[0] != "READY":
            self.proc.kill()
            raise RuntimeError(f"mock encoder did not start: {line} (exit {self.proc.poll()})")
        return self

    def _read_until(self, word: str) -> list[str]:
        assert self.proc is not None and self.proc.stdout is not None
        while True:
            line = self.proc.stdout.readline()
            if not line:
                raise RuntimeError(f"mock encoder exited (code {self.proc.wait()}) before printing {word}")
            if line.startswith("REBOOT"):
                self.reboot = (int(line.split()[1]), float(line.split()[2]))
            if line.startswith(word):
                return line.split()

    def wait_started(self) -> None:
        """Block until the handshake happened; the clock parameters are then known."""
        w = self._read_until("START")
        self.start_ns, self.offset_us, self.drift = int(w[1]), int(w[3]), float(w[5]) * 1e-6

    def true_host_ns(self, t_us: np.ndarray | int) -> np.ndarray:
        return self.start_ns + (np.asarray(t_us, dtype=np.float64) - self.offset_us) * 1000.0 / (1 + self.drift)

    def wait(self) -> dict[str, int]:
        """Block until the last line was written; the summary, e.g. ``{"SENT": n, "DROPPED": n, ...}``."""
        if not self.start_ns:
            self.wait_started()
        w = self._read_until("SENT")
        self.summary = {w[i]: int(w[i + 1]) for i in range(0, len(w) - 1, 2)}
        return self.summary

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=5)

    def __enter__(self) -> MockEncoderProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.kill()


def wait_hello(port: PtyPort, banner: bytes, timeout: float = 30.0) -> None:
    """Handshake: stay silent until the host sends ``HELLO``, answer with the banner.

    (pyserial flushes the input buffer when it opens a port, so lines sent before the
    host is listening would be lost; a real device streams regardless, the mock waits so
    tests can count every line.)
    """
    buf = b""
    deadline = time.monotonic() + timeout
    while b"HELLO" not in buf:
        if time.monotonic() > deadline:
            raise SystemExit(f"no HELLO from a host within {timeout} s")
        r, _, _ = select.select([port.master], [], [], 0.05)
        if r:
            try:
                buf += os.read(port.master, 256)
            except OSError:
                buf = b""
    os.write(port.master, banner)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--link", required=True, help="symlink path to publish the pty slave under")
    p.add_argument("--rate", type=float, default=1000.0, help="samples per second")
    p.add_argument("--cpr", type=int, default=10000, help="counts per revolution")
    p.add_argument("--duration", type=float, default=10.0, help="seconds to run (device time)")
    p.add_argument("--motion", default="uniform", choices=["uniform", "nonuniform", "stop"])
    p.add_argument("--rpm", type=float, default=6.0)
    p.add_argument("--start-angle", type=float, default=-0.3, help="rad; negative: index passes early")
    p.add_argument("--wobble", type=float, default=0.3, help="nonuniform: relative speed swing")
    p.add_argument("--wobble-hz", type=float, default=0.5)
    p.add_argument("--stop-at", type=float, default=1.0)
    p.add_argument("--count-offset", type=int, default=123_456)
    p.add_argument("--clock-offset-us", type=int, default=5_000_000)
    p.add_argument("--drift-ppm", type=float, default=50.0)
    p.add_argument("--garbage-every", type=int, default=0, help="insert garbage bytes every N samples")
    p.add_argument("--drop-every", type=int, default=0, help="skip sending every Nth sample (seq advances)")
    p.add_argument("--disconnect-at", type=float, default=-1.0, help="device time (s) to pull the cable")
    p.add_argument("--disconnect-for", type=float, default=0.5)
    p.add_argument("--reboot-at", type=float, default=-1.0, help="device time (s) to pull the cable; the device restarts")
    p.add_argument("--name", default="mockenc")
    p.add_argument("--linger", type=float, default=1.0, help="seconds to keep the pty open after the last line")
    p.add_argument("--hello-timeout", type=float, default=30.0)
    args = p.parse_args(argv)

    port = PtyPort(args.link)
    print(f"READY {args.link}", flush=True)
    banner = Banner(PROTOCOL_VERSION, args.cpr, args.name).encode()
    wait_hello(port, banner)
    start = time.monotonic_ns()
    drift = args.drift_ppm * 1e-6
    print(f"START {start} OFFSET_US {args.clock_offset_us} DRIFT_PPM {args.drift_ppm}", flush=True)
    period = 1.0 / args.rate
    n_total = int(round(args.duration * args.rate))
    sent = dropped = garbage = unread_samples = unread_garbage = 0
    recent: collections.deque[tuple[int, int]] = collections.deque(maxlen=256)  # (bytes, garbage bytes)
    last_turn = math.floor(theta(args, 0.0) / (2 * math.pi))
    disconnected = False
    k0, count0 = 0, 0  # a reboot restarts seq at sample k0 and the count at count0
    inbuf = b""
    k = 0
    while k < n_total:
        now = (time.monotonic_ns() - start) / 1e9
        due = k * period
        if due > now:
            time.sleep(min(due - now, 0.002))
            continue
        unplug_at = args.reboot_at if args.reboot_at >= 0 else args.disconnect_at
        if unplug_at >= 0 and not disconnected and due >= unplug_at:
            disconnected = True
            time.sleep(0.005)  # the pty moves written bytes to the slave's queue asynchronously
            lost_s, lost_g = unread_lines(recent, port.unread_bytes())
            unread_samples += lost_s
            unread_garbage += lost_g
            port.close()
            os.unlink(args.link)
            time.sleep(args.disconnect_for)
            port = PtyPort(args.link)
            wait_hello(port, banner)
            # samples due while unplugged are lost, as on a real link
            k = int(math.ceil((time.monotonic_ns() - start) / 1e9 / period))
            if args.reboot_at >= 0:  # powered up again: seq, clock and count start over
                k0 = k
                count0 = math.floor(args.cpr * theta(args, k0 * period) / (2 * math.pi)) + args.count_offset
                print(f"REBOOT {k0} {k0 * period!r}", flush=True)
            continue
        th = theta(args, due)
        count = math.floor(args.cpr * th / (2 * math.pi)) + args.count_offset
        turn = math.floor(th / (2 * math.pi))
        index, index_count = False, None
        if turn != last_turn:
            index, index_count = True, args.cpr * max(turn, last_turn) + args.count_offset - count0
            last_turn = turn
        t_us = int(round((k - k0) * period * 1e6 * (1 + drift))) + args.clock_offset_us
        line = RawSample((k - k0) % SEQ_MODULUS, t_us, count - count0, index, index_count).encode()
        if args.drop_every and k % args.drop_every == args.drop_every - 1 and not index:
            dropped += 1
        else:
            junk = b""
            if args.garbage_every and k % args.garbage_every == args.garbage_every // 2:
                junk = b"\x00\xff$E,9,zz*" + line[: len(line) // 2] + b"\n"
                garbage += 1
            os.write(port.master, junk + line)
            recent.append((len(junk) + len(line), len(junk)))
            sent += 1
        k += 1
        r, _, _ = select.select([port.master], [], [], 0)
        if r:
            try:
                inbuf += os.read(port.master, 256)
            except OSError:
                inbuf = b""  # no reader attached to the slave yet
            if b"HELLO" in inbuf:
                os.write(port.master, banner)
                inbuf = b""
    print(
        f"SENT {sent} DROPPED {dropped} GARBAGE {garbage} UNREAD_SAMPLES {unread_samples} UNREAD_GARBAGE {unread_garbage}",
        flush=True,
    )
    time.sleep(args.linger)  # let the reader drain (and its owner stop it) before the pty closes
    port.close()
    if os.path.lexists(args.link):
        os.unlink(args.link)
    return 0


if __name__ == "__main__":
    sys.exit(main())
