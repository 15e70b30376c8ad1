"""Acquisition config (camera, encoder, projector) read from TOML and validated.

Example ``rig.toml``::

    [camera]
    driver = "aravis"            # "aravis" | "v4l2" | "replay"
    id = "Aravis-Fake-GS01"      # Aravis id, serial or IP; /dev/videoN; recording folder
    pixel_format = "Mono8"
    exposure_us = 10000
    roi = [0, 0, 800, 800]
    trigger = "software"

    [encoder]
    port = "/dev/ttyUSB0"        # or omit the table: the gear is taken as still at angle 0
    counts_per_rev = 10000

    [projector]
    backend = "mock"             # "mock" | "window" | "lightcrafter"
    period_px = 16
    settle_ms = 20

Errors name the key, the allowed range and the value found
(``encoder.counts_per_rev: Input should be greater than 0 (got 0)``). Angles are
radians inside; the config has no angles.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from gearscan.acquisition.camera import CameraSettings
from gearscan.core.patterns import PatternSet


class ConfigError(ValueError):
    """The acquisition config is invalid; the message names every bad key."""


class CameraConfig(CameraSettings):
    driver: Literal["aravis", "v4l2", "replay"] = "aravis"
    id: str | None = None
    loop: bool = False  # replay driver only: start over at the end of the recording

    def settings(self) -> CameraSettings:
        return CameraSettings(**self.model_dump(exclude={"driver", "id", "loop"}))


class EncoderConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # a setting is a finite number

    port: str
    counts_per_rev: int = Field(gt=0)
    baudrate: int = Field(115_200, gt=0)
    zero_on_index: bool = True
    # with zero_on_index: wait this long at start for the index mark before taking bursts, so
    # every angle of a run is measured from the index; 0: start at once, angles from the first count
    index_wait_s: float = Field(15.0, ge=0)
    max_gap_ms: float = Field(20.0, gt=0)


class ProjectorConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # a setting is a finite number

    backend: Literal["mock", "window", "lightcrafter"] = "mock"
    display: int = Field(0, ge=0)
    width: int = Field(912, gt=0)
    height: int = Field(1140, gt=0)
    period_px: float = Field(16.0, ge=2)
    settle_ms: float = Field(20.0, ge=0)
    gamma: float | None = Field(None, gt=0)
    # CAD-free unwrapping: a coarse three-step burst at this period first and then after every
    # coarse_every measuring bursts (recon.unwrap = "coarse" unwraps the fine ones around it)
    coarse_period_px: float | None = Field(None, ge=2)
    coarse_every: int = Field(4, ge=1)
    # every other measuring burst in the order 0, 2, 1 (PatternSet.cycle): the fused model's frame fit
    # then fits nearly every point of a turning gear (a hardware-sequenced projector must play that order:
    # camera.pattern_cycle = 6)
    alternate_order: bool = False

    @model_validator(mode="after")
    def _coarse_wider(self) -> ProjectorConfig:
        if self.coarse_period_px is not None and not self.coarse_period_px > self.period_px:
            raise ValueError(f"coarse_period_px must exceed period_px = {self.period_px:g} "
                             f"(got {self.coarse_period_px:g})")
        return self

    def patterns(self) -> PatternSet:
        """The pattern set this projector shows: three-step, plus the coarse group when configured."""
        if self.coarse_period_px is None:
            return PatternSet.three_step(self.period_px)
        return PatternSet.with_coarse(self.period_px, self.coarse_period_px)


class AcquisitionConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # a setting is a finite number

    camera: CameraConfig = Field(default_factory=CameraConfig)
    encoder: EncoderConfig | None = None
    projector: ProjectorConfig = Field(default_factory=ProjectorConfig)

    @classmethod
    def from_dict(cls, data: dict, source: str = "config") -> AcquisitionConfig:
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise ConfigError(f"{source}: " + format_errors(exc)) from exc

    @classmethod
    def load(cls, path: str | Path) -> AcquisitionConfig:
        path = Path(path)
        if not path.exists():
            raise ConfigError(f"config file {path} does not exist")
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: invalid TOML ({exc})") from exc
        return cls.from_dict(data, str(path))


def format_errors(exc: ValidationError) -> str:
    """One line per bad key: ``a.b: message (got value)``."""
    parts = []
    for e in exc.errors():
        key = ".".join(str(p) for p in e["loc"])
        got = e.get("input")
        parts.append(f"{key}: {e['msg']} (got {got!r})")
    return "; ".join(parts)
