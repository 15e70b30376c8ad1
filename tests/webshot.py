"""Screenshots of a web page in headless Chromium over the DevTools protocol (test helper).

Why a helper rather than selenium/playwright: the only extra needed is the pure-python
``websocket-client``; Chromium itself is the Debian package (``scripts/setup.sh``).

The rerun web viewer renders with WebGL/WebGPU. Headless Chromium without a GPU renders
WebGL on SwiftShader (software), which recent Chromium only allows with
``--enable-unsafe-swiftshader``; the viewer needs several seconds of real time before its
first frame, so :meth:`Chromium.screenshot_until` polls until a pixel check passes.
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

CHROMIUM_CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")

# Flags for a quiet, offline, GPU-less headless browser (PLATFORM.md); the two SwiftShader
# flags give the page a software WebGL context instead of none.
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-quic",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--disable-dev-shm-usage",
    "--mute-audio",
)


class BrowserError(RuntimeError):
    """Chromium could not be started or did not answer over the DevTools protocol."""


def find_chromium() -> str | None:
    """Path of a Chromium-like browser on PATH (``None`` when there is none)."""
    for name in CHROMIUM_CANDIDATES:
        path = shutil.which(name)
        if path:
            return path
    return None


@dataclass
class Chromium:
    """A headless Chromium with one page, driven over CDP; use as a context manager.

    ``width`` x ``height`` is the CSS viewport (device scale 1), so screenshots are
    ``(height, width, 3)`` uint8 RGB arrays.
    """

    width: int = 1600
    height: int = 1000
    binary: str | None = None
    start_timeout: float = 30.0
    process: subprocess.Popen | None = field(default=None, init=False)
    _profile: str | None = field(default=None, init=False)
    _ws: object = field(default=None, init=False)
    _ids: itertools.count = field(default_factory=lambda: itertools.count(1), init=False)
    log_path: Path | None = field(default=None, init=False)

    def __post_init__(self) -> None:
        if self.width < 64 or self.height < 64:
            raise ValueError(f"viewport must be at least 64x64 px, got {self.width}x{self.height}")

    def __enter__(self) -> Chromium:
        try:
            self.start()
        except BaseException:
            self.close()  # a half-started browser must not outlive a failed start
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- process ---------------------------------------------------------------------------
    def start(self) -> None:
        """Launch Chromium on ``about:blank`` with a fresh profile and attach to its page."""
        import websocket

        binary = self.binary or find_chromium()
        if binary is None:
            raise BrowserError(f"no Chromium found on PATH (tried {', '.join(CHROMIUM_CANDIDATES)})")
        self._profile = tempfile.mkdtemp(prefix="gearscan-chromium-")
        self.log_path = Path(self._profile) / "chromium.log"
        cmd = [binary, *CHROMIUM_FLAGS, f"--user-data-dir={self._profile}", "--remote-debugging-port=0",
               f"--window-size={self.width},{self.height}", "about:blank"]
        env = dict(os.environ, HOME=self._profile)  # keep the user's real profile and caches out
        with open(self.log_path, "wb") as log:
            # own process group, so close() can take the renderer/GPU children down with it
            self.process = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                                            start_new_session=True)
        port = self._devtools_port()
        targets = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=5).read())
        pages = [t for t in targets if t.get("type") == "page"]
        if not pages:
            raise BrowserError(f"Chromium opened no page target: {targets}")
        self._ws = websocket.create_connection(pages[0]["webSocketDebuggerUrl"], timeout=30,
                                               suppress_origin=True)
        self.send("Page.enable")
        self.send("Emulation.setDeviceMetricsOverride",
                  {"width": self.width, "height": self.height, "deviceScaleFactor": 1, "mobile": False})

    def _devtools_port(self) -> int:
        """Port chosen by ``--remote-debugging-port=0``, read from ``DevToolsActivePort``."""
        path = Path(self._profile) / "DevToolsActivePort"
        deadline = time.monotonic() + self.start_timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise BrowserError(f"Chromium exited with {self.process.returncode}: {self.log_tail()}")
            if path.exists():
                first = path.read_text().split("\n", 1)[0].strip()
                if first.isdigit():
                    return int(first)
            time.sleep(0.1)
        raise BrowserError(f"Chromium wrote no DevToolsActivePort within {self.start_timeout} s: {self.log_tail()}")

    def log_tail(self, chars: int = 2000) -> str:
        """The end of Chromium's own stdout/stderr (for failure messages)."""
        if self.log_path is None or not self.log_path.exists():
            return ""
        return self.log_path.read_bytes()[-chars:].decode(errors="replace")

    def close(self) -> None:
        """Close the DevTools socket, kill Chromium's process group, delete the profile."""
        if self._ws is not None:
            try:
                self._ws.close()
            except OSError:
                pass  # the browser may already be gone; the process kill below is what matters
            self._ws = None
        if self.process is not None and self.process.poll() is None:
            try:
                os.killpg(self.process.pid, signal.SIGTERM)
                self.process.wait(timeout=5)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                if self.process.poll() is None:
                    os.killpg(self.process.pid, signal.SIGKILL)
                    self.process.wait(timeout=5)
        if self._profile is not None:
            shutil.rmtree(self._profile, ignore_errors=True)
            self._profile = None

    # -- DevTools protocol -----------------------------------------------------------------
    def send(self, method: str, params: dict | None = None, timeout: float = 30.0) -> dict:
        """One CDP command; returns its ``result`` (events arriving meanwhile are dropped)."""
        if self._ws is None:
            raise BrowserError("Chromium is not started")
        msg_id = next(self._ids)
        self._ws.send(json.dumps({"id": msg_id, "method": method, "params": params or {}}))
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            reply = json.loads(self._ws.recv())
            if reply.get("id") == msg_id:
                if "error" in reply:
                    raise BrowserError(f"{method} failed: {reply['error']}")
                return reply.get("result", {})
        raise BrowserError(f"{method}: no reply within {timeout} s")

    def navigate(self, url: str, timeout: float = 30.0) -> None:
        """Open ``url`` and wait for its load event (until then the page target may be detached)."""
        result = self.send("Page.navigate", {"url": url})
        if result.get("errorText"):
            raise BrowserError(f"navigating to {url} failed: {result['errorText']}")
        self.wait_event("Page.loadEventFired", timeout)

    def wait_event(self, method: str, timeout: float = 30.0) -> dict:
        """Parameters of the next CDP event ``method`` (other messages are dropped)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            msg = json.loads(self._ws.recv())
            if msg.get("method") == method:
                return msg.get("params", {})
        raise BrowserError(f"no {method} event within {timeout} s")

    def evaluate(self, expression: str):
        """Value of a JavaScript expression in the page (JSON-serialisable results only)."""
        result = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True})
        return result.get("result", {}).get("value")

    def screenshot_png(self) -> bytes:
        """The page as PNG bytes (``Page.captureScreenshot``)."""
        data = self.send("Page.captureScreenshot", {"format": "png", "fromSurface": True}, timeout=60)["data"]
        return base64.b64decode(data)

    def screenshot(self) -> tuple[np.ndarray, bytes]:
        """The page as ``(H, W, 3)`` uint8 RGB and as the PNG bytes it was decoded from."""
        import cv2

        png = self.screenshot_png()
        bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise BrowserError(f"screenshot is not a decodable PNG ({len(png)} bytes)")
        return np.ascontiguousarray(bgr[..., ::-1]), png

    def screenshot_until(
        self, check: Callable[[np.ndarray], list[str]], timeout: float = 40.0, interval: float = 3.0
    ) -> tuple[np.ndarray, bytes, list[str], float]:
        """Screenshot every ``interval`` s until ``check(rgb)`` returns no failures or ``timeout``.

        Returns the last ``(rgb, png, failures, seconds waited)``; the caller asserts on
        ``failures`` so the message says which pixel check never passed.
        """
        t0 = time.monotonic()
        while True:
            time.sleep(interval)  # the viewer needs seconds of real time before its first frame
            rgb, png = self.screenshot()
            failures = check(rgb)
            waited = time.monotonic() - t0
            if not failures or waited + interval > timeout:
                return rgb, png, failures, waited
