"""Aravis's GigE Vision simulator (``arv-fake-gv-camera-0.8``) as a managed subprocess.

Tests and benchmarks start one daemon directly (no shell), keep its PID and kill exactly
that process. Two simulators on one address clash (both bind GVCP port 3956), so use one
at a time, each with a unique serial so discovery finds the right one.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
import uuid

BINARY = "arv-fake-gv-camera-0.8"


class SimulatorMissing(RuntimeError):
    """The simulator binary is not installed (apt package aravis-tools)."""


def simulator_path() -> str:
    path = shutil.which(BINARY)
    if path is None:
        raise SimulatorMissing(f"{BINARY} not found on PATH: install the apt package aravis-tools (see README setup)")
    return path


class GvSimulator:
    """One fake GigE Vision camera on ``address``; ``camera_id`` is its Aravis id."""

    def __init__(self, serial: str | None = None, address: str = "127.0.0.1"):
        self.serial = serial or f"GS{uuid.uuid4().hex[:8].upper()}"
        self.address = address
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def camera_id(self) -> str:
        return f"Aravis-Fake-{self.serial}"

    @property
    def pid(self) -> int | None:
        return None if self.proc is None else self.proc.pid

    def start(self, settle: float = 0.3) -> GvSimulator:
        if self.proc is not None and self.proc.poll() is None:
            return self
        others = running_simulators(self.address)
        if others:
            raise RuntimeError(
                f"another {BINARY} already serves {self.address} (pid {others}); two simulators on one "
                "address clash (a killed test run may have left it): stop it first"
            )
        self.proc = subprocess.Popen(
            [simulator_path(), "-i", self.address, "-s", self.serial],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        time.sleep(settle)
        if self.proc.poll() is not None:
            raise RuntimeError(f"{BINARY} exited at once with code {self.proc.returncode} (address {self.address} in use?)")
        return self

    def kill(self) -> None:
        """SIGKILL the daemon (a pulled cable, as far as the driver can tell)."""
        if self.proc is not None and self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=5)
        self.proc = None

    def __enter__(self) -> GvSimulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.kill()


def running_simulators(address: str) -> list[int]:
    """PIDs of simulator daemons listening on ``address`` (scans /proc)."""
    pids = []
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/cmdline", "rb") as fh:
                argv = fh.read().split(b"\0")
        except OSError:
            continue  # process ended meanwhile
        if argv and argv[0].endswith(BINARY.encode()) and address.encode() in argv:
            pids.append(int(d))
    return pids


def aravis_missing_reason() -> str | None:
    """Why the Aravis Python bindings cannot be used here (None when they can)."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401
    except (ImportError, ValueError) as exc:
        return f"gi/Aravis typelib missing ({exc}); install gir1.2-aravis-0.8 and pip 'pygobject<3.51'"
    return None
