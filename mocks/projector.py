"""Projector stand-ins: a software-sequenced projector that shows nothing, and a LightCrafter-style
pattern transport that plays its sequence in a thread and fires the trigger-out a camera would see."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from gearscan.projector.lightcrafter import PatternSequenceConfig
from gearscan.projector.sequencer import ProjectorError, Shown


@dataclass
class MockProjector:
    """Records the patterns it is asked to show (``log``: the latest ``max_log`` to ``2 * max_log``,
    so a long simulated run stays flat in memory), with their host time; ``shown`` counts them all."""

    width: int = 912
    height: int = 1140
    latency_s: float = 0.0
    log: list[Shown] = field(default_factory=list)
    max_log: int = 10_000
    shown: int = 0
    is_open: bool = False
    last_image: np.ndarray | None = None

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def show(self, image: np.ndarray, index: int) -> int:
        if not self.is_open:
            raise ProjectorError("mock projector: show() before open()")
        if image.shape != (self.height, self.width):
            raise ProjectorError(f"pattern image must be ({self.height}, {self.width}), got {image.shape}")
        if self.latency_s:
            time.sleep(self.latency_s)
        t = time.monotonic_ns()
        self.last_image = image
        self.log.append(Shown(index, t, int(image.sum(dtype=np.int64))))
        self.shown += 1
        if len(self.log) > 2 * self.max_log:
            del self.log[: len(self.log) - self.max_log]
        return t


@dataclass
class MockPatternTransport:
    """Plays the sequence in real time; each trigger-out calls ``on_trigger_out``."""

    on_trigger_out: Callable[[int, int], None] | None = None
    max_cycles: int | None = None
    commands: list[str] = field(default_factory=list)
    triggers: list[tuple[int, int]] = field(default_factory=list)  # (pattern, host ns)
    images: list[np.ndarray] = field(default_factory=list)
    config: PatternSequenceConfig | None = None

    def __post_init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def upload(self, images: list[np.ndarray]) -> None:
        self.commands.append(f"upload {len(images)}")
        self.images = list(images)

    def configure(self, config: PatternSequenceConfig) -> None:
        missing = [e.pattern for e in config.entries if e.pattern >= len(self.images)]
        if missing:
            raise ValueError(f"projector.sequence: patterns {missing} not uploaded ({len(self.images)} images)")
        self.commands.append(f"configure {len(config.entries)} entries")
        self.config = config

    def start(self) -> None:
        if self.config is None:
            raise RuntimeError("start() before configure()")
        self.commands.append("start")
        self._stop.clear()
        self._thread = threading.Thread(target=self._play, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.commands.append("stop")

    def wait(self, timeout: float = 10.0) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    def _play(self) -> None:
        cfg = self.config
        assert cfg is not None
        t = time.monotonic_ns()
        cycle = 0
        while not self._stop.is_set() and (self.max_cycles is None or cycle < self.max_cycles):
            for e in cfg.entries:
                delay = (t - time.monotonic_ns()) / 1e9
                if delay > 0 and self._stop.wait(delay):
                    return
                if e.trigger_out:
                    now = time.monotonic_ns()
                    self.triggers.append((e.pattern, now))
                    if self.on_trigger_out is not None:
                        self.on_trigger_out(e.pattern, now)
                t += (e.exposure_us + e.dark_us) * 1000
            cycle += 1
            if not cfg.repeat:
                return
