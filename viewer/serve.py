"""Serve the rerun web viewer from this machine (``--serve``), bound to 127.0.0.1 by default.

The SDK's own ``serve_grpc`` binds every interface; a shop-floor PC should not expose a
port unless asked, so we start the bundled ``rerun`` binary with ``--bind`` and connect
the logging stream to it over gRPC.

Ports are fixed so that a bookmarked viewer URL keeps working: gRPC :data:`DEFAULT_GRPC_PORT`
and web :data:`DEFAULT_WEB_PORT` from the command line (0 picks a free port, what tests use).
The viewer process dies with the one that started it: normal exit and exceptions close it
(``atexit``); SIGTERM, SIGKILL or a crash of the parent reach it through Linux's parent-death
signal (``PR_SET_PDEATHSIG``), so no orphaned viewer keeps the ports.
"""

from __future__ import annotations

import atexit
import errno
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

DEFAULT_GRPC_PORT = 9876  # rerun's own default gRPC port
DEFAULT_WEB_PORT = 9090  # rerun's own default web viewer port


class ViewerError(RuntimeError):
    """The viewer server could not be started."""


def rerun_binary() -> str:
    """Path of the ``rerun`` executable bundled with rerun-sdk (falls back to PATH)."""
    try:
        import rerun_cli

        path = Path(rerun_cli.__file__).parent / "rerun"
        if path.exists():
            return str(path)
    except ImportError:
        pass
    found = shutil.which("rerun")
    if not found:
        raise ViewerError("the rerun viewer binary was not found (is rerun-sdk installed in this environment?)")
    return found


def _local(bind: str) -> str:
    """The address to reach a server bound to ``bind`` from this machine."""
    return "127.0.0.1" if bind in ("0.0.0.0", "::", "") else bind


def free_port(bind: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((_local(bind), 0))
        return int(s.getsockname()[1])


def check_port(bind: str, port: int, what: str, option: str) -> None:
    """Raise :class:`ViewerError` naming the port, what wants it and the option to change it
    when ``bind:port`` cannot be listened on (taken, privileged, or not an address of this host)."""
    if not 0 < port < 65536:
        raise ViewerError(f"{what} port {port}: expected 1..65535 ({option})")
    family = socket.AF_INET6 if ":" in bind else socket.AF_INET
    with socket.socket(family) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server does: TIME_WAIT is no conflict
        try:
            s.bind((bind, port))
            s.listen(1)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise ViewerError(f"{what} port {port} on {bind} is already in use (another gearscan --serve or "
                                  f"rerun viewer?); stop it or choose another port with {option}") from exc
            raise ViewerError(f"{what} port {port} on {bind}: cannot listen ({exc.strerror}); "
                              f"check --bind or choose another port with {option}") from exc


def _wait_port(host: str, port: int, timeout: float, proc: subprocess.Popen) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        with socket.socket() as s:
            s.settimeout(0.2)
            if s.connect_ex((host, port)) == 0:
                return True
        time.sleep(0.1)
    return False


def _die_with_parent(parent: int):
    """``preexec_fn``: SIGTERM this child when the thread that started it dies (Linux only).

    Runs between fork and exec; if the parent already died in that window, exit at once.
    """
    def set_pdeathsig() -> None:
        import ctypes

        pr_set_pdeathsig = 1
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(pr_set_pdeathsig, signal.SIGTERM, 0, 0, 0)
        if os.getppid() != parent:
            os._exit(1)

    return set_pdeathsig if sys.platform.startswith("linux") else None


@dataclass
class WebViewer:
    """A running ``rerun --serve-web`` process."""

    process: subprocess.Popen
    bind: str
    grpc_port: int
    web_port: int

    @property
    def grpc_url(self) -> str:
        return f"rerun+http://{_local(self.bind)}:{self.grpc_port}/proxy"

    @property
    def web_url(self) -> str:
        return f"http://{_local(self.bind)}:{self.web_port}/?url={self.grpc_url}"

    def close(self) -> None:
        """Stop the viewer (SIGTERM, then SIGKILL after 5 s); safe to call twice."""
        atexit.unregister(self.close)
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=5)


def serve_web(bind: str = "127.0.0.1", grpc_port: int = 0, web_port: int = 0,
              memory_limit: str = "1GiB", timeout: float = 20.0) -> WebViewer:
    """Start the web viewer + gRPC server; returns once both ports accept connections.

    ``grpc_port`` / ``web_port``: 0 picks a free port. A port that is taken is a
    :class:`ViewerError` naming it, before anything is started.
    Call from the main thread: the parent-death signal follows the thread that started the viewer.
    """
    if grpc_port and grpc_port == web_port:
        raise ViewerError(f"--grpc-port and --web-port are both {grpc_port}: they need two different ports")
    if grpc_port:
        check_port(bind, grpc_port, "gRPC", "--grpc-port")
    else:
        grpc_port = free_port(bind)
    if web_port:
        check_port(bind, web_port, "web viewer", "--web-port")
    else:
        web_port = free_port(bind)
        while web_port == grpc_port:
            web_port = free_port(bind)
    cmd = [rerun_binary(), "--serve-web", "--bind", bind, "--port", str(grpc_port),
           "--web-viewer-port", str(web_port), "--server-memory-limit", memory_limit]
    # stderr to a file, not a pipe: an unread pipe fills up and stalls a viewer that runs for hours
    err_file = tempfile.TemporaryFile()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err_file,
                            preexec_fn=_die_with_parent(os.getpid()))  # noqa: PLW1509 (fork+exec, nothing else)
    viewer = WebViewer(proc, bind, grpc_port, web_port)
    atexit.register(viewer.close)
    host = _local(bind)
    if not (_wait_port(host, grpc_port, timeout, proc) and _wait_port(host, web_port, timeout, proc)):
        viewer.close()
        err_file.seek(0)
        err = err_file.read().decode(errors="replace")[-500:]
        err_file.close()
        raise ViewerError(f"rerun web viewer did not start on {bind}:{grpc_port}/{web_port} within {timeout} s: {err}")
    return viewer
