"""Projector: software sync with the mock projector and the replay camera, gamma
pre-compensation against a simulated display, hardware-triggered sequence contract."""

from __future__ import annotations

import math
import sys
import types

import numpy as np
import pytest

from gearscan.acquisition.camera import CameraSettings
from gearscan.core.patterns import PatternSet
from gearscan.core.recording import RecordingWriter
from gearscan.core.types import Frame
from gearscan.mocks.projector import MockPatternTransport, MockProjector
from gearscan.mocks.replay_camera import ReplayCamera
from gearscan.projector.gamma import GammaCorrection, GammaError
from gearscan.projector.lightcrafter import HardwareTriggeredProjector, PatternSequenceConfig
from gearscan.projector.sequencer import (
    ProjectorError,
    SoftwareSequencer,
    WindowProjector,
)


@pytest.fixture()
def camera(tmp_path):
    with RecordingWriter(tmp_path / "rec", {}) as w:
        for i in range(9):
            w.write_frame(Frame(np.full((4, 4), i, np.uint8), i, i * 10**7, 0))
    cam = ReplayCamera(tmp_path / "rec")
    with cam:
        cam.configure(CameraSettings(trigger="software"))
        cam.start()
        yield cam


def test_software_sync_shows_then_triggers_and_stamps_patterns(camera):
    proj = MockProjector(width=64, height=8)
    proj.open()
    pats = PatternSet.three_step(16.0)
    seq = SoftwareSequencer(proj, camera, pats, settle_s=0.01)
    frames = list(seq.run(cycles=3))
    assert [f.pattern_index for f in frames] == [0, 1, 2] * 3
    assert [s.index for s in proj.log] == [0, 1, 2] * 3
    # the projector showed exactly the pattern set's images, in order
    assert [s.checksum for s in proj.log[:3]] == [int(pats.image(i, 64, 8).sum()) for i in range(3)]
    # each frame was grabbed after its pattern was shown and the settle time passed
    assert min(seq.stats.show_to_frame_ms) >= 10.0
    assert [f.frame_id for f in frames] == list(range(9))


def test_coarse_bursts_are_shown_in_the_cycle_order(camera):
    """With a coarse group the projector shows a coarse burst first and then coarse_every measuring
    bursts (the order twin recordings use); each frame is stamped with the pattern it saw."""
    proj = MockProjector(width=64, height=8)
    proj.open()
    pats = PatternSet.with_coarse(16.0, 64.0)
    order = pats.cycle(coarse_every=2)
    assert order == [3, 4, 5, 0, 1, 2, 0, 1, 2]
    frames = list(SoftwareSequencer(proj, camera, pats, settle_s=0.0).run(cycles=1, order=order))
    assert [f.pattern_index for f in frames] == order == [s.index for s in proj.log]
    assert [s.checksum for s in proj.log[:3]] == [int(pats.image(i, 64, 8).sum()) for i in (3, 4, 5)]
    assert PatternSet.three_step(16.0).cycle(coarse_every=5) == [0, 1, 2]  # no coarse group: the plain burst
    with pytest.raises(ValueError, match="order"):
        next(SoftwareSequencer(proj, camera, pats).run(order=[0, 6]))


def test_gamma_precompensation_linearises_a_simulated_display():
    gamma, black = 2.2, 0.03

    def display(code: np.ndarray) -> np.ndarray:  # light out, 0..1
        return black + (1 - black) * (code / 255.0) ** gamma

    levels = np.linspace(0, 255, 17)
    gc = GammaCorrection.from_measurements(levels, display(levels))
    pats = PatternSet.three_step(32.0)
    ideal = pats.image(0, 256, 1)[0].astype(float) / 255  # wanted light fraction
    light = (display(gc.apply(pats.image(0, 256, 1))[0].astype(float)) - black) / (1 - black)
    raw = (display(pats.image(0, 256, 1)[0].astype(float)) - black) / (1 - black)
    assert np.max(np.abs(light - ideal)) < 0.02  # 17-point curve + 8-bit rounding
    assert np.max(np.abs(raw - ideal)) > 0.2  # without it the fringes are far from sinusoidal
    # the phase decoded from compensated three-step fringes is right to < 10 mrad
    u = np.arange(256)
    img = np.stack([(display(gc.apply(pats.image(n, 256, 1))[0].astype(float))) for n in range(3)])
    d = 2 * np.pi * np.arange(3) / 3
    phi = np.arctan2(-(img * np.sin(d)[:, None]).sum(0), (img * np.cos(d)[:, None]).sum(0))
    err = np.angle(np.exp(1j * (phi - 2 * np.pi * u / 32.0)))
    assert np.max(np.abs(err)) < 0.01
    with pytest.raises(GammaError, match="flat"):
        GammaCorrection.from_measurements(levels, np.ones(17))


def test_hardware_sequence_contract():
    cfg = PatternSequenceConfig.for_patterns(3, exposure_us=10_000, dark_us=2_000)
    assert cfg.period_us == 36_000 and cfg.frame_rate_hz == pytest.approx(3 / 0.036)
    assert [cfg.pattern_for_frame(n) for n in range(7)] == [0, 1, 2, 0, 1, 2, 0]
    seen = []
    tr = MockPatternTransport(on_trigger_out=lambda p, t: seen.append((p, t)), max_cycles=3)
    proj = HardwareTriggeredProjector(tr, cfg)
    pats = PatternSet.three_step(16.0)
    cycle = proj.prepare([pats.image(i, 32, 4) for i in range(3)], camera_exposure_us=8_000)
    assert cycle == 3
    proj.start()
    tr.wait()
    proj.stop()
    assert tr.commands == ["upload 3", "configure 3 entries", "start", "stop"]
    assert [p for p, _ in seen] == [0, 1, 2] * 3
    dt = np.diff([t for _, t in seen]) / 1e6
    assert np.median(dt) == pytest.approx(12.0, abs=1.5)  # exposure + dark
    with pytest.raises(ValueError, match="camera.exposure_us: 11000 .* exceeds the shortest pattern exposure 10000"):
        proj.prepare([], camera_exposure_us=11_000)
    with pytest.raises(ValueError, match=r"entries\[0\].exposure_us: 1000 us is below the 8333 us minimum for 8-bit"):
        PatternSequenceConfig.for_patterns(3, exposure_us=1000)


def test_window_projector_against_a_stand_in_pygame(monkeypatch):
    """pygame is optional (not in the venv): check our use of its API with a stand-in."""
    blits = []
    pg = types.SimpleNamespace(FULLSCREEN=1, NOFRAME=2)
    pg.display = types.SimpleNamespace(
        init=lambda: None,
        quit=lambda: None,
        get_num_displays=lambda: 2,
        get_desktop_sizes=lambda: [(1920, 1080), (40, 10)],
        set_mode=lambda size, flags, display: ("screen", size, flags, display),
        flip=lambda: None,
    )
    pg.mouse = types.SimpleNamespace(set_visible=lambda v: None)
    pg.event = types.SimpleNamespace(get=lambda: [])
    pg.surfarray = types.SimpleNamespace(blit_array=lambda s, a: blits.append((s, a)))
    monkeypatch.setitem(sys.modules, "pygame", pg)
    w = WindowProjector(display=1)
    w.open()
    assert (w.width, w.height) == (40, 10)
    img = PatternSet.three_step(8.0).image(1, 40, 10)
    w.show(img, 1)
    screen, arr = blits[0]
    assert screen[3] == 1 and arr.shape == (40, 10, 3)
    np.testing.assert_array_equal(arr[:, :, 0].T, img)
    with pytest.raises(ProjectorError, match="projector.display: 5 not available; 2 display"):
        WindowProjector(display=5).open()
    assert math.isfinite(w.show(img, 0))


def test_window_projector_with_real_pygame_headless(monkeypatch):
    """Real SDL2 window on the dummy video driver: the pixels on screen are the pattern."""
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    pygame = pytest.importorskip("pygame", reason="pygame is an optional dependency (pip install pygame)")
    w = WindowProjector(display=0, width=64, height=16, fullscreen=False)
    w.open()
    try:
        img = PatternSet.three_step(8.0).image(2, 64, 16)
        w.show(img, 2)
        shown = pygame.surfarray.array3d(w._screen)
        np.testing.assert_array_equal(shown[:, :, 0].T, img)
    finally:
        w.close()


def test_the_mock_projector_log_stays_bounded():
    """A long simulated run keeps only the latest patterns (it grew ~9 MB/h before); all are counted."""
    import numpy as np


    proj = MockProjector(width=4, height=2, max_log=5)
    proj.open()
    for i in range(23):
        proj.show(np.full((2, 4), i, np.uint8), i % 3)
    assert proj.shown == 23 and 5 <= len(proj.log) <= 10
    assert proj.log[-1].checksum == 22 * 8  # the newest is kept


def test_alternating_cycle_shows_every_other_burst_reversed():
    assert PatternSet.three_step(16.0).cycle(alternate=True) == [0, 1, 2, 0, 2, 1]
    coarse = PatternSet.with_coarse(16.0, 64.0)
    assert coarse.cycle(coarse_every=2, alternate=True) == [3, 4, 5, 0, 1, 2, 0, 2, 1]
    # an odd count between coarse bursts: two coarse periods per cycle, so the alternation goes on
    assert coarse.cycle(coarse_every=1, alternate=True) == [3, 4, 5, 0, 1, 2, 3, 4, 5, 0, 2, 1]
