"""Hardware-triggered projection (DLP LightCrafter-style pattern sequence mode).

The projector stores the pattern images, plays them in a fixed sequence with its own
timing, and raises TRIGGER-OUT at the start of each pattern exposure; that line fires the
camera (``camera.trigger = "hardware"``). There is no software in the loop, so the frame
rate is the projector's and the pattern of camera frame ``n`` is
``sequence[n % len(sequence)]`` (camera ``pattern_cycle = len(sequence)``).

The contract a real device driver implements is :class:`PatternTransport`:
``upload`` images, ``configure`` the sequence, ``start``/``stop``. The mock transport
(:class:`gearscan.mocks.projector.MockPatternTransport`) plays the sequence in a thread and calls
``on_trigger_out(pattern_index, host_ns)``, which is what a camera's trigger line would see.

Minimum exposures per bit depth are those of the DLP LightCrafter 4500 (DLPC350) pattern
mode (DLPU010, table "pattern exposure"); override ``min_exposure_us`` for other devices.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

LCR4500_MIN_EXPOSURE_US = {1: 235, 2: 700, 3: 1570, 4: 1700, 5: 2000, 6: 2500, 7: 4500, 8: 8333}


class PatternEntry(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    pattern: int = Field(ge=0, description="index into the uploaded pattern set")
    bit_depth: int = Field(8, ge=1, le=8)
    exposure_us: int = Field(gt=0)
    dark_us: int = Field(0, ge=0, description="projector dark time after the exposure")
    trigger_out: bool = True


class PatternSequenceConfig(BaseModel):
    """A hardware pattern sequence; validated against the device's exposure limits."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    entries: tuple[PatternEntry, ...]
    repeat: bool = True
    trigger_out_delay_us: int = Field(0, ge=0)
    min_exposure_us: dict[int, int] = Field(default_factory=lambda: dict(LCR4500_MIN_EXPOSURE_US))

    @model_validator(mode="after")
    def _check(self) -> PatternSequenceConfig:
        if not self.entries:
            raise ValueError("projector.sequence.entries: empty sequence")
        for k, e in enumerate(self.entries):
            lo = self.min_exposure_us.get(e.bit_depth, 0)
            if e.exposure_us < lo:
                raise ValueError(
                    f"projector.sequence.entries[{k}].exposure_us: {e.exposure_us} us is below the "
                    f"{lo} us minimum for {e.bit_depth}-bit patterns"
                )
        return self

    @classmethod
    def for_patterns(cls, n: int, exposure_us: int = 8333, dark_us: int = 0, bit_depth: int = 8) -> PatternSequenceConfig:
        return cls(entries=tuple(PatternEntry(pattern=i, bit_depth=bit_depth, exposure_us=exposure_us, dark_us=dark_us) for i in range(n)))

    @property
    def period_us(self) -> int:
        return sum(e.exposure_us + e.dark_us for e in self.entries)

    @property
    def frame_rate_hz(self) -> float:
        """Camera frames per second (one per trigger-out)."""
        return 1e6 * sum(e.trigger_out for e in self.entries) / self.period_us

    def pattern_for_frame(self, n: int) -> int:
        """Pattern index seen by the n-th camera frame (counting only triggering entries)."""
        trig = [e.pattern for e in self.entries if e.trigger_out]
        return trig[n % len(trig)]

    def check_camera(self, camera_exposure_us: float) -> None:
        """The camera exposure must end before the shortest pattern exposure does."""
        shortest = min(e.exposure_us for e in self.entries if e.trigger_out)
        if camera_exposure_us + self.trigger_out_delay_us > shortest:
            raise ValueError(
                f"camera.exposure_us: {camera_exposure_us:g} + trigger delay {self.trigger_out_delay_us} us "
                f"exceeds the shortest pattern exposure {shortest} us: frames would mix two patterns"
            )


class PatternTransport(Protocol):
    def upload(self, images: list[np.ndarray]) -> None: ...
    def configure(self, config: PatternSequenceConfig) -> None: ...
    def start(self) -> None: ...
    def stop(self) -> None: ...


class HardwareTriggeredProjector:
    """Uploads a pattern set, configures the sequence, starts it; the camera follows."""

    def __init__(self, transport: PatternTransport, config: PatternSequenceConfig):
        self.transport = transport
        self.config = config

    def prepare(self, images: list[np.ndarray], camera_exposure_us: float) -> int:
        """Upload + configure; returns the ``pattern_cycle`` to give the camera."""
        self.config.check_camera(camera_exposure_us)
        self.transport.upload(images)
        self.transport.configure(self.config)
        return sum(e.trigger_out for e in self.config.entries)

    def start(self) -> None:
        self.transport.start()

    def stop(self) -> None:
        self.transport.stop()
