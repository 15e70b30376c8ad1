"""Replay camera: recorded timing, as-fast-as-possible, software trigger."""

from __future__ import annotations

import time

import numpy as np
import pytest

from gearscan.acquisition.bursts import BurstAssembler
from gearscan.acquisition.camera import Camera, CameraError, CameraSettings, GrabTimeout
from gearscan.core.recording import RecordingWriter
from gearscan.core.types import Frame
from gearscan.mocks.replay_camera import ReplayCamera

PERIOD_NS = 20_000_000  # recorded at 50 fps


@pytest.fixture()
def recording(tmp_path):
    with RecordingWriter(tmp_path / "rec", {}) as w:
        for i in range(12):
            w.write_frame(Frame(np.full((8, 8), i, np.uint8), 100 + i, 5 * 10**9 + i * PERIOD_NS, i % 3, 1000.0, 8, 0, 0.1 * i))
    return tmp_path / "rec"


def test_fast_replay_serves_every_frame_in_order_and_assembles(recording):
    cam = ReplayCamera(recording, realtime=False)
    assert isinstance(cam, Camera)
    asm = BurstAssembler()
    with cam:
        cam.configure(CameraSettings(buffer_count=2))
        cam.start()
        frames = [cam.grab(1.0) for _ in range(12)]
        with pytest.raises(GrabTimeout, match="all 12 frames served"):
            cam.grab(0.2)
    assert [f.frame_id for f in frames] == list(range(100, 112))
    assert all(int(f.image[0, 0]) == i for i, f in enumerate(frames))
    bursts = [b for b in map(asm.push, frames) if b is not None]
    assert len(bursts) == 4 and bursts[1].angles == pytest.approx((0.3, 0.4, 0.5))
    assert cam.stats.missing_frames == 0


def test_realtime_replay_keeps_recorded_intervals(recording):
    cam = ReplayCamera(recording, realtime=True, speed=2.0)
    with cam:
        cam.start()
        t = []
        for _ in range(12):
            f = cam.grab(1.0)
            t.append(f.host_timestamp_ns)
    dt = np.diff(t) / 1e6
    assert abs(np.median(dt) - 10.0) < 2.0, dt  # 20 ms recorded, at 2x speed
    assert (t[-1] - t[0]) / 1e6 == pytest.approx(110.0, abs=15.0)


def test_software_trigger_releases_exactly_one_frame(recording):
    cam = ReplayCamera(recording)
    with cam:
        cam.configure(CameraSettings(trigger="software"))
        cam.start()
        time.sleep(0.1)
        assert cam.try_grab() is None
        for k in range(3):
            cam.software_trigger()
            assert cam.grab(1.0).frame_id == 100 + k
            time.sleep(0.05)
            assert cam.try_grab() is None
        with pytest.raises(CameraError, match="hardware trigger"):
            cam.configure(CameraSettings(trigger="hardware"))
