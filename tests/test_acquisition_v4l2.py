"""V4L2 camera logic against a scripted fake device (no /dev/video* exists on CI machines;
see PLATFORM.md). Images encode their sequence number, so every check is exact."""

from __future__ import annotations

import numpy as np
import pytest

from gearscan.acquisition.camera import (
    CameraConfigError,
    CameraDisconnected,
    CameraNotFound,
    CameraSettings,
    GrabTimeout,
)
from gearscan.acquisition.v4l2 import V4L2Camera
from gearscan.mocks.v4l2_backend import FakeV4L2Backend


def test_format_negotiation_strided_buffers_and_sequence_numbers():
    fake = FakeV4L2Backend()
    with V4L2Camera("/dev/videoX", backend=fake) as cam:
        cam.configure(CameraSettings(pixel_format="Mono12", roi=(0, 0, 320, 240), exposure_us=1234))
        assert cam.granted["fourcc"] == "Y12 " and cam.granted["bytes_per_line"] == 320 * 2 + 32
        assert cam.granted["exposure_us"] == 1200.0  # the driver's 100 us steps
        cam.start()
        frames = [cam.grab(1.0) for _ in range(5)]
        cam.stop()
    for k, f in enumerate(frames):
        assert f.frame_id == k and f.bit_depth == 12 and f.image.dtype == np.uint16
        np.testing.assert_array_equal(f.image, FakeV4L2Backend.image(k, 320, 240, "Y12 "))
        assert f.host_timestamp_ns == f.timestamp_ns  # V4L2 stamps are CLOCK_MONOTONIC already
    assert cam.info.model == "Fake Mono Cam"


def test_missing_format_and_adjusted_size_are_config_errors():
    with V4L2Camera("/dev/videoX", backend=FakeV4L2Backend()) as cam:
        with pytest.raises(CameraConfigError, match=r"camera.pixel_format: 'Mono16' .* it offers \['Mono8', 'Mono12'\]"):
            cam.configure(CameraSettings(pixel_format="Mono16"))
        with pytest.raises(CameraConfigError, match="camera.roi: driver adjusted 330x240 to 320x240"):
            cam.configure(CameraSettings(roi=(0, 0, 330, 240)))
        with pytest.raises(CameraConfigError, match="camera.trigger: V4L2 has no standard trigger"):
            cam.configure(CameraSettings(trigger="software"))


def test_gaps_error_buffers_timeout_and_unplug():
    fake = FakeV4L2Backend(skip_sequences={3, 4}, error_sequences={6}, unplug_after=7)
    with V4L2Camera("/dev/videoX", backend=fake) as cam:
        cam.configure(CameraSettings(roi=(0, 0, 64, 48)))
        cam.start()
        ids = [cam.grab(1.0).frame_id for _ in range(6)]
        # 3, 4 dropped by the driver, 6 arrived flagged corrupt and was discarded
        assert ids == [0, 1, 2, 5, 7, 8] and cam.stats.missing_frames == 3 and cam.stats.incomplete == 1
        with pytest.raises(CameraDisconnected, match="disappeared"):
            cam.grab(1.0)
        fake.unplug_after = None
        cam.reconnect(timeout=2.0)
        assert fake.opened == 2 and cam.streaming
        f = cam.grab(1.0)
        np.testing.assert_array_equal(f.image, FakeV4L2Backend.image(f.frame_id, 64, 48, "GREY"))
        cam.stop()
        cam.start()
        fake.streaming = False  # a stalled device: no frame, no crash
        with pytest.raises(GrabTimeout):
            cam.grab(0.05)


def test_unknown_device_path_names_the_setting():
    with pytest.raises(CameraNotFound, match=r"camera.id: '/dev/video99' not found; V4L2 devices"):
        with V4L2Camera("/dev/video99"):
            pass


def test_frames_are_numbered_by_the_projectors_sequence():
    """A projector that plays 0, 1, 2, 0, 2, 1 by itself: frame n shows entry n % 6, and a dropped
    frame (sequence gap) does not shift the numbering of the ones after it."""
    seq = (0, 1, 2, 0, 2, 1)
    with V4L2Camera("/dev/videoX", backend=FakeV4L2Backend(skip_sequences={8})) as cam:
        cam.configure(CameraSettings(pixel_format="Mono8", roi=(0, 0, 64, 48), pattern_cycle=6, pattern_sequence=seq))
        cam.start()
        frames = [cam.grab(1.0) for _ in range(11)]
        cam.stop()
    assert [f.frame_id for f in frames] == [0, 1, 2, 3, 4, 5, 6, 7, 9, 10, 11]
    assert [f.pattern_index for f in frames] == [seq[f.frame_id % 6] for f in frames]
    with pytest.raises(ValueError, match="pattern_sequence: expected 6 pattern indices"):
        CameraSettings(pattern_cycle=6, pattern_sequence=(0, 1, 2))
