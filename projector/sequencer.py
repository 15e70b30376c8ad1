"""Projector sequencing: show pattern -> settle -> trigger camera -> next.

Backends implement :class:`ProjectorBackend` (``open/close/show``):

- :class:`gearscan.mocks.projector.MockProjector` records what it showed and when (tests, simulators);
- :class:`WindowProjector` draws full-screen on a chosen display with pygame/SDL2
  (lazy import; headless with ``SDL_VIDEODRIVER=dummy``);
- :mod:`gearscan.projector.lightcrafter` drives a hardware-triggered pattern sequence,
  where the projector's trigger-out fires the camera and no software sync is needed.

:class:`SoftwareSequencer` is the software sync loop for window/mock backends: the camera
is in software-trigger mode and each frame is stamped with the pattern it saw.
"""

from __future__ import annotations

import collections
import dataclasses
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from gearscan.core.patterns import PatternSet
from gearscan.core.types import Frame
from gearscan.projector.gamma import GammaCorrection


class ProjectorError(RuntimeError):
    """A projector backend failed (no display, unknown screen, device error)."""


class ProjectorBackend(Protocol):
    width: int
    height: int

    def open(self) -> None: ...
    def close(self) -> None: ...
    def show(self, image: np.ndarray, index: int) -> int:
        """Display ``image`` (H, W) uint8; return host ns when it was on screen."""
        ...


@dataclass(frozen=True, slots=True)
class Shown:
    index: int
    host_time_ns: int
    checksum: int  # sum of pixel values, to check WHAT was shown


class WindowProjector:
    """Full-screen pygame window on display ``display`` (0 = primary).

    The projector is an extra monitor output; ``display`` picks it. pygame is imported on
    ``open`` so the package works without it (``pip install pygame``).
    """

    def __init__(self, display: int = 0, width: int | None = None, height: int | None = None, fullscreen: bool = True):
        self.display = display
        self.fullscreen = fullscreen
        self.width = width or 0
        self.height = height or 0
        self._pg = None
        self._screen = None

    def open(self) -> None:
        try:
            import pygame
        except ImportError as exc:
            raise ProjectorError("window projector needs pygame (pip install pygame)") from exc
        pygame.display.init()
        n = pygame.display.get_num_displays()
        if not 0 <= self.display < n:
            raise ProjectorError(f"projector.display: {self.display} not available; {n} display(s) found")
        sizes = pygame.display.get_desktop_sizes()
        w, h = sizes[self.display]
        self.width, self.height = self.width or w, self.height or h
        flags = pygame.FULLSCREEN | pygame.NOFRAME if self.fullscreen else 0
        self._screen = pygame.display.set_mode((self.width, self.height), flags, display=self.display)
        pygame.mouse.set_visible(False)
        self._pg = pygame

    def close(self) -> None:
        if self._pg is not None:
            self._pg.display.quit()
            self._pg = None

    def show(self, image: np.ndarray, index: int) -> int:
        if self._pg is None:
            raise ProjectorError("window projector: show() before open()")
        if image.shape != (self.height, self.width):
            raise ProjectorError(f"pattern image must be ({self.height}, {self.width}), got {image.shape}")
        pg = self._pg
        for _ in pg.event.get():
            pass  # keep the window responsive; events are not used
        rgb = np.repeat(image.T[:, :, None], 3, axis=2)  # pygame surfaces are (W, H, 3)
        pg.surfarray.blit_array(self._screen, rgb)
        pg.display.flip()
        return time.monotonic_ns()


@dataclass
class SequencerStats:
    patterns_shown: int = 0
    frames: int = 0
    timeouts: int = 0
    show_to_frame_ms: collections.deque[float] = field(default_factory=lambda: collections.deque(maxlen=10_000))  # latest


class SoftwareSequencer:
    """Show pattern, wait ``settle_s``, trigger the camera, grab, stamp the pattern index.

    ``camera`` must be configured with ``trigger="software"`` and started. Pattern images
    are rendered once (with optional gamma pre-compensation) at the projector's size.
    """

    def __init__(
        self,
        projector: ProjectorBackend,
        camera,
        patterns: PatternSet,
        *,
        settle_s: float = 0.02,
        grab_timeout_s: float = 1.0,
        gamma: GammaCorrection | None = None,
    ):
        if settle_s < 0:
            raise ValueError(f"settle_s must be >= 0, got {settle_s}")
        self.projector = projector
        self.camera = camera
        self.patterns = patterns
        self.settle_s = settle_s
        self.grab_timeout_s = grab_timeout_s
        self.gamma = gamma
        self.stats = SequencerStats()
        self._images: list[np.ndarray] | None = None

    def images(self) -> list[np.ndarray]:
        if self._images is None:
            imgs = [self.patterns.image(i, self.projector.width, self.projector.height) for i in range(len(self.patterns))]
            self._images = [self.gamma.apply(im) for im in imgs] if self.gamma else imgs
        return self._images

    def capture(self, index: int) -> Frame:
        """One pattern -> one frame (raises the camera's GrabTimeout if none arrives)."""
        image = self.images()[index]
        t_show = self.projector.show(image, index)
        self.stats.patterns_shown += 1
        if self.settle_s:
            time.sleep(self.settle_s)
        self.camera.software_trigger()
        frame = self.camera.grab(self.grab_timeout_s)
        self.stats.frames += 1
        self.stats.show_to_frame_ms.append((time.monotonic_ns() - t_show) / 1e6)
        return dataclasses.replace(frame, pattern_index=index)

    def run(self, cycles: int | None = None, order: Sequence[int] | None = None) -> Iterator[Frame]:
        """Frames for the patterns of ``order`` (default 0..N-1: :meth:`PatternSet.cycle`), repeated
        ``cycles`` times (None: forever)."""
        order = list(range(len(self.patterns))) if order is None else list(order)
        bad = [i for i in order if not 0 <= i < len(self.patterns)]
        if bad or not order:
            raise ValueError(f"order: expected pattern indices in 0..{len(self.patterns) - 1}, got {order}")
        c = 0
        while cycles is None or c < cycles:
            for i in order:
                yield self.capture(i)
            c += 1
