"""``--serve``: fixed ports with a clear error when one is taken, and a viewer process that
dies with the process that started it (SIGTERM, SIGINT, SIGKILL of the parent)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gearscan.viewer.serve import ViewerError, check_port, serve_web

PARENT = """
import signal, sys, time
# a program started in a terminal dies on SIGINT, even when this test run ignores it (nohup, a background job)
signal.signal(signal.SIGINT, signal.default_int_handler)
from gearscan.viewer.serve import serve_web
viewer = serve_web()
print(viewer.process.pid, viewer.grpc_port, viewer.web_port, flush=True)
time.sleep(120)
"""


def _alive(pid: int) -> bool:
    """True while ``pid`` runs (a zombie waiting for its reaper counts as gone)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return False
    return state not in ("Z", "X")


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.fixture
def home(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))  # rerun writes analytics under ~/.config
    monkeypatch.setenv("RERUN_ANALYTICS", "0")
    return tmp_path


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="parent-death signal is Linux only")
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGKILL])
def test_viewer_dies_with_its_parent(home, sig):
    parent = subprocess.Popen([sys.executable, "-c", PARENT], stdout=subprocess.PIPE, text=True,
                              start_new_session=True)  # its own group: only the parent gets the signal
    child = None
    try:
        line = parent.stdout.readline().split()
        assert len(line) == 3, f"parent printed {line!r}, exit {parent.poll()}"
        child, grpc_port, web_port = (int(x) for x in line)
        assert _alive(child) and _listening(grpc_port) and _listening(web_port)
        os.kill(parent.pid, sig)
        parent.wait(timeout=10)
        deadline = time.monotonic() + 5.0
        while _alive(child) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(child), f"viewer {child} still runs 5 s after its parent got {sig.name}"
        # its sockets go with it, though on a loaded machine not always in the same instant
        while (_listening(grpc_port) or _listening(web_port)) and time.monotonic() < deadline + 5.0:
            time.sleep(0.1)
        assert not _listening(grpc_port) and not _listening(web_port)
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        if child is not None and _alive(child):
            os.kill(child, signal.SIGKILL)


def test_a_taken_port_is_a_clear_error_before_anything_starts(home):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        with pytest.raises(ViewerError, match=rf"gRPC port {port} on 127.0.0.1 is already in use.*--grpc-port"):
            serve_web(grpc_port=port)
        with pytest.raises(ViewerError, match=rf"web viewer port {port} .*already in use.*--web-port"):
            serve_web(web_port=port)
    check_port("127.0.0.1", port, "gRPC", "--grpc-port")  # free again: no error
    with pytest.raises(ViewerError, match="both"):
        serve_web(grpc_port=port, web_port=port)
    with pytest.raises(ViewerError, match="expected 1..65535"):
        check_port("127.0.0.1", 70000, "gRPC", "--grpc-port")


def test_fixed_ports_are_the_ones_served(home):
    grpc_port, web_port = (serve_web.__globals__["free_port"]() for _ in range(2))
    if grpc_port == web_port:
        pytest.skip("the OS handed out the same free port twice")
    viewer = serve_web(grpc_port=grpc_port, web_port=web_port)
    try:
        assert (viewer.grpc_port, viewer.web_port) == (grpc_port, web_port)
        assert _listening(grpc_port) and _listening(web_port)
        assert viewer.grpc_url == f"rerun+http://127.0.0.1:{grpc_port}/proxy"
        assert viewer.web_url.startswith(f"http://127.0.0.1:{web_port}/?url=")
        with pytest.raises(ViewerError, match=f"{grpc_port}.*already in use"):
            serve_web(grpc_port=grpc_port)  # a second --serve on the same port
    finally:
        viewer.close()
    assert viewer.process.poll() is not None


def test_cli_serve_on_a_taken_port_is_exit_2_naming_it(home, tmp_path):
    from typer.testing import CliRunner

    from gearscan.cli import app
    from gearscan.config import LiveConfig

    assert (LiveConfig().viewer.grpc_port, LiveConfig().viewer.web_port) == (9876, 9090)  # documented defaults
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        res = CliRunner().invoke(app, ["replay", str(tmp_path / "rec"), "--classical", "--serve",
                                       "--grpc-port", str(port), "--web-port", "0"])
    assert res.exit_code == 2, res.output
    assert f"gRPC port {port} on 127.0.0.1 is already in use" in res.output and "--grpc-port" in res.output
    assert "Traceback" not in res.output
