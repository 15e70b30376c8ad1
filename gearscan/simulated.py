"""``gearscan live --simulate``: simulators standing in for the rig's devices.

The camera is Aravis's GigE Vision simulator (``arv-fake-gv-camera-0.8`` on 127.0.0.1, apt
package aravis-tools), reached through the real Aravis driver; the encoder is the mock device
(:mod:`gearscan.mocks.encoder_device`) on a pseudo-terminal, read by the real serial reader;
the projector is the mock one. Every code path of a shop-floor run is exercised except the
optics: the simulator's image is Aravis's test ramp, not fringes on a gear, so its phase is
flat and its point cloud nearly empty (a twin recording replayed shows a gear).
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Iterator
from pathlib import Path

from gearscan.acquisition.config import CameraConfig, EncoderConfig
from gearscan.config import LiveConfig, RigRef

SIM_RPM = 2.5  # the mock turntable's speed: 15 deg/s
SIM_COUNTS_PER_REV = 10_000
SIM_ENCODER_HZ = 1000
SIM_PERIOD_PX = 40.0  # the built-in rig's fringe period, projector px
SIM_SENSOR = (2048, 2048)  # the simulator's sensor, px
SIM_EXPOSURE_US = 10_000.0  # at 10 ms and gain 0 the simulator's ramp is unscaled


class SimulationError(RuntimeError):
    """A simulator cannot start (not installed, or one already serves 127.0.0.1)."""


def simulated_config(base: LiveConfig | None, camera_id: str, encoder_port: str, workdir: Path) -> LiveConfig:
    """``base`` (or the defaults with the built-in rig) with camera, encoder and projector
    replaced by the simulators; the camera's ROI is the rig's image size."""
    from gearscan.core.rig import default_rig

    cfg = base or LiveConfig()
    if base is None:  # the built-in rig, its projector and fringe period (as in `config init`'s template)
        default_rig().save(workdir / "rig.json")
        cfg = cfg.model_copy(update={"rig": RigRef(calibration=workdir / "rig.json")})
    # the simulators draw with the mock projector: a config's real one (and its size) is not used
    cfg = cfg.model_copy(update={"projector": cfg.projector.model_copy(update={"backend": "mock"})})
    rig = cfg.load_rig()
    if base is None:
        cfg = cfg.model_copy(update={"projector": cfg.projector.model_copy(update={
            "width": rig.projector.width, "height": rig.projector.height, "period_px": SIM_PERIOD_PX})})
    w, h = rig.camera.width, rig.camera.height
    if w > SIM_SENSOR[0] or h > SIM_SENSOR[1]:
        raise SimulationError(f"rig.calibration: the rig's camera is {w}x{h} px, larger than the simulator's "
                              f"{SIM_SENSOR[0]}x{SIM_SENSOR[1]} sensor")
    camera = CameraConfig(driver="aravis", id=camera_id, pixel_format="Mono8", exposure_us=SIM_EXPOSURE_US,
                          trigger="software", roi=(0, 0, w, h))
    encoder = EncoderConfig(port=encoder_port, counts_per_rev=SIM_COUNTS_PER_REV, index_wait_s=5.0)
    projector = cfg.projector.model_copy(update={"backend": "mock"})
    return cfg.model_copy(update={"camera": camera, "encoder": encoder, "projector": projector})


@contextlib.contextmanager
def simulated_devices(base: LiveConfig | None = None) -> Iterator[LiveConfig]:
    """Start the GigE camera simulator and the mock encoder, yield a config that uses them,
    stop both (by their own PIDs) on exit."""
    from gearscan.mocks.encoder_device import MockEncoderProcess
    from gearscan.mocks.gv_simulator import GvSimulator, aravis_missing_reason

    if (reason := aravis_missing_reason()) is not None:
        raise SimulationError(f"--simulate needs Aravis: {reason} (bash scripts/setup.sh installs it)")
    with tempfile.TemporaryDirectory(prefix="gearscan-sim-") as tmp, contextlib.ExitStack() as stack:
        workdir = Path(tmp)
        try:
            sim = stack.enter_context(GvSimulator())
            encoder = stack.enter_context(MockEncoderProcess(
                str(workdir / "encoder"), rate=SIM_ENCODER_HZ, cpr=SIM_COUNTS_PER_REV, rpm=SIM_RPM,
                duration=10_000_000, start_angle=-0.05, linger=0, hello_timeout=600))  # index 0.2 s in
        except RuntimeError as exc:  # SimulatorMissing, a simulator already running, a mock that did not start
            raise SimulationError(f"--simulate: {exc}") from exc
        yield simulated_config(base, sim.camera_id, encoder.link, workdir)
