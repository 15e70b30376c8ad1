"""Serve the rerun web viewer from this machine (``--serve``), bound to 127.0.0.1 by default.

The SDK's own ``serve_grpc`` binds every interface; a shop-floor PC should not expose a
port unless asked, so we start the bundled ``rerun`` binary with ``--bind`` and connect
the logging stream to it over gRPC.
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path


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


def free_port(bind: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((bind, 0))
        return int(s.getsockname()[1])


def _wait_port(host: str, port: int, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket() as s:
            s.settimeout(0.2)
            if s.connect_ex((host, port)) == 0:
                return True
        time.sleep(0.1)
    return False


@dataclass
class WebViewer:
    """A running ``rerun --serve-web`` process."""

    process: subprocess.Popen
    bind: str
    grpc_port: int
    web_port: int

    @property
    def grpc_url(self) -> str:
        host = "127.0.0.1" if self.bind in ("0.0.0.0", "::") else self.bind
        return f"rerun+http://{host}:{self.grpc_port}/proxy"

    @property
    def web_url(self) -> str:
        host = "127.0.0.1" if self.bind in ("0.0.0.0", "::") else self.bind
        return f"http://{host}:{self.web_port}/?url={self.grpc_url}"

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()


def serve_web(bind: str = "127.0.0.1", grpc_port: int | None = None, web_port: int | None = None,
              memory_limit: str = "1GiB", timeout: float = 20.0) -> WebViewer:
    """Start the web viewer + gRPC server; returns once both ports accept connections."""
    grpc_port = grpc_port or free_port(bind if bind not in ("0.0.0.0", "::") else "127.0.0.1")
    web_port = web_port or free_port(bind if bind not in ("0.0.0.0", "::") else "127.0.0.1")
    cmd = [rerun_binary(), "--serve-web", "--bind", bind, "--port", str(grpc_port),
           "--web-viewer-port", str(web_port), "--server-memory-limit", memory_limit]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    host = "127.0.0.1" if bind in ("0.0.0.0", "::") else bind
    if not (_wait_port(host, grpc_port, timeout) and _wait_port(host, web_port, timeout)):
        proc.kill()
        err = proc.stderr.read().decode(errors="replace")[-500:] if proc.stderr else ""
        raise ViewerError(f"rerun web viewer did not start on {bind}:{grpc_port}/{web_port} within {timeout} s: {err}")
    return WebViewer(proc, bind, grpc_port, web_port)
