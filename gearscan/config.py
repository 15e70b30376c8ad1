"""The ``gearscan live`` configuration: one validated TOML file for the whole rig.

It extends the acquisition config (camera, encoder, projector) with the rig calibration,
the gear, the model, reconstruction and viewer settings. Every error names the key, what
is allowed and what was found. ``gearscan config init`` writes :data:`TEMPLATE`.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from gearscan.acquisition.config import AcquisitionConfig, ConfigError, format_errors
from gearscan.core.gear import GearSpec
from gearscan.inference.decoder import STILL_SPAN_DEG
from gearscan.recon.measure import MAX_SIGMA_RAD

TEMPLATE = """\
# gearscan live configuration. Lengths in mm, angles in degrees, times as named.
# Validate with: gearscan live --config THIS_FILE --check

[camera]
driver = "aravis"            # "aravis" (GenICam/GigE/USB3), "v4l2" or "replay"
# id = "Basler-12345678"     # Aravis id, serial or IP; /dev/videoN; recording folder for replay
pixel_format = "Mono8"       # Mono8, Mono12 or Mono16
exposure_us = 5000.0
gain_db = 0.0
trigger = "software"         # "software" (projector sequencing), "hardware" or "free-run"
# pattern_cycle = 3          # trigger = "hardware": frames per sequence the projector plays by itself
                             # (6 with projector.alternate_order: 0,1,2,0,2,1; the order comes from [projector])
# roi = [0, 0, 800, 800]     # x, y, width, height

[projector]
backend = "window"           # "window" (full-screen on a display), "lightcrafter" or "mock"
display = 0                  # screen for the window backend: 0 = the first; a projector on a
                             # second output is usually 1 (`--check` says how many there are)
width = 1280
height = 800
period_px = 40.0             # fringe period, projector pixels
settle_ms = 20.0             # wait after showing a pattern before triggering the camera
# gamma = 2.2                # display gamma to pre-compensate
# coarse_period_px = 160.0   # CAD-free: a coarse burst at this period first and then every
# coarse_every = 4           # coarse_every measuring bursts (with recon.unwrap = "coarse")
# alternate_order = true     # every other burst shows its patterns as 0, 2, 1: the fused model's
                             # frame fit (inspect, replay --fuse) then fits nearly every point
                             # (a hardware-sequenced projector must play that order too)

# [encoder]                  # omit without an encoder: the gear is then taken as standing still
                             # at angle 0 (its CAD pose); every burst goes to three-step PS.
                             # A turning gear needs the encoder.
# port = "/dev/ttyUSB0"
# counts_per_rev = 131072
# baudrate = 115200
# zero_on_index = true       # angle 0 at the index mark
# index_wait_s = 15.0        # wait this long for the index before measuring (0: angles from the first count)

[rig]
calibration = "rig.json"     # written by `gearscan calibrate`; relative to this file

[gear]                       # the gear under test (for unwrapping bounds and CAD deviation)
teeth = 20
module = 2.0
pressure_angle_deg = 20.0
face_width = 20.0
bore = 10.0

[model]
# path = "my-model.safetensors"   # default: the model shipped with gearscan
mc = 0                       # Monte Carlo passes for model uncertainty (0: one deterministic pass)
precision = "auto"           # "auto", "fp32" or "bf16"
# workers = 2                # bursts decoded at once; default: 2 on a CPU (faster than 1), 1 on a GPU
still_span_deg = 0.0375      # bursts spanning less turntable angle go to three-step PS (0: never; val choice)
orientation = "auto"         # fringe phase along the camera's columns: "normal" (rising, as the twin's
                             # rigs), "mirrored", or "auto" (from the rig calibration's geometry; 3 still
                             # bursts that agree against it win, with a warning; a calibration without
                             # one: a vote per burst until 3 still bursts agree)

[recon]
min_modulation = 0.05        # drop pixels below this normalised modulation 2B/S
max_sigma_rad = 0.7          # report no point whose total phase uncertainty exceeds this (val choice;
                             # the fringe orders are found on the pixels within it)
# network_support_px = 2     # a network's pixel needs fringes in its own frames on every pixel within this
                             # many px (-1: no such test). Unset: the model's own, from its JSON
                             # (network_support.per_burst_px: none for the shipped v9 and the default-rig
                             # option, 2 for v6, which invents phase at shadow borders; none there: v9's)
unwrap = "cad"               # fringe orders from the gear's CAD ("cad") or its envelope only ("envelope",
                             # CAD-free: needs fringes wider than the tooth depth, see --check), or
                             # around the last coarse burst ("coarse", CAD-free at any period: needs
                             # projector.coarse_period_px; costs one burst in coarse_every + 1)
cad_deviation = true         # colour the cloud by distance to the gear's CAD model

[viewer]
# save = "measurement.rrd"   # write the stream to a file
# connect = "rerun+http://192.168.0.10:9876/proxy"   # a viewer elsewhere on the shop floor
max_save_mb = 2000.0         # the .rrd file (save, or out/live.rrd when no viewer is named) stops
                             # growing at this size, about 4 min at 512x512; the measurement goes on (0: no cap)
serve = false                # serve the web viewer from this machine
bind = "127.0.0.1"           # address --serve binds to
grpc_port = 9876             # --serve: gRPC port (--connect rerun+http://HOST:9876/proxy; 0: any free port)
web_port = 9090              # --serve: web viewer page, http://HOST:9090 (0: any free port)
"""


class RigRef(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # a setting is a finite number

    calibration: Path = Field(Path("rig.json"), description="rig calibration JSON")


class ModelSection(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # a setting is a finite number

    path: Path | None = None
    mc: int = Field(0, ge=0, le=200)
    precision: Literal["auto", "fp32", "bf16"] = "auto"
    workers: int | None = Field(None, ge=1, le=16)
    still_span_deg: float = Field(STILL_SPAN_DEG, ge=0, le=10)
    orientation: Literal["auto", "normal", "mirrored"] = "auto"


class ReconSection(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # a setting is a finite number

    min_modulation: float = Field(0.05, ge=0, le=1)
    max_sigma_rad: float = Field(MAX_SIGMA_RAD, gt=0)
    network_support_px: int | None = Field(None, ge=-1, le=16)  # None: the model's; -1: off (TOML has no null)
    unwrap: Literal["cad", "envelope", "coarse"] = "cad"
    cad_deviation: bool = True


class ViewerSection(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # a setting is a finite number

    save: Path | None = None
    connect: str | None = None
    max_save_mb: float = Field(2000.0, ge=0)  # cap of the .rrd file (0: none)
    serve: bool = False
    bind: str = "127.0.0.1"
    grpc_port: int = Field(9876, ge=0, le=65535)  # --serve ports; 0: any free one
    web_port: int = Field(9090, ge=0, le=65535)


class LiveConfig(AcquisitionConfig):
    """Everything ``gearscan live`` needs; relative paths resolve against the file's folder."""

    rig: RigRef = Field(default_factory=RigRef)
    gear: GearSpec = Field(default_factory=GearSpec)
    model: ModelSection = Field(default_factory=ModelSection)
    recon: ReconSection = Field(default_factory=ReconSection)
    viewer: ViewerSection = Field(default_factory=ViewerSection)

    @classmethod
    def from_toml(cls, text: str, source: str = "config", base: Path | None = None) -> LiveConfig:
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{source}: invalid TOML ({exc})") from exc
        try:
            cfg = cls.model_validate(data)
        except ValidationError as exc:
            raise ConfigError(f"{source}: " + format_errors(exc)) from exc
        if cfg.recon.unwrap == "coarse" and cfg.projector.coarse_period_px is None:
            raise ConfigError(f"{source}: recon.unwrap = 'coarse' unwraps around coarse bursts: set "
                              "projector.coarse_period_px (e.g. 160, wider than the tooth depth; `live --check` says)")
        if base is not None and not cfg.rig.calibration.is_absolute():
            cfg = cfg.model_copy(update={"rig": RigRef(calibration=base / cfg.rig.calibration)})
        return cfg

    @classmethod
    def load(cls, path: str | Path) -> LiveConfig:
        path = Path(path)
        if not path.exists():
            raise ConfigError(f"config file {path} does not exist (write a template with `gearscan config init {path}`)")
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as exc:
            raise ConfigError(f"config file {path}: not UTF-8 text (TOML is UTF-8; byte {exc.start}): save it as UTF-8") from exc
        except OSError as exc:  # a folder, no permission
            raise ConfigError(f"config file {path}: cannot read it ({exc.strerror or exc}): expected a TOML file") from exc
        return cls.from_toml(text, str(path), path.parent)

    def defaulted_sections(self) -> list[str]:
        """What a user should be told was not in their file and runs on defaults: the gear measured against (a
        20-tooth module-2 CAD) and the projector driven (the mock: none)."""
        notes = {"gear": f"no [gear] section: measuring against the default gear (z = {self.gear.teeth}, "
                         f"m = {self.gear.module:g} mm); set it to the gear on the turntable",
                 "projector": "no [projector] section: the mock projector (no projector is driven, "
                              f"{self.projector.width}x{self.projector.height} px, period {self.projector.period_px:g} "
                              "px); set it to yours"}
        return [text for key, text in notes.items() if key not in self.model_fields_set]

    def recording_meta(self, rig, source: str) -> dict:
        """What a recording made with this config stores besides the acquisition (rig, gear, the
        config itself), so that ``gearscan replay`` measures it as the run that recorded it did."""
        return {"source": source, "rig": rig.to_json(), "gear": self.gear.model_dump(),
                "live_config": self.model_dump(mode="json")}

    def load_rig(self):
        from gearscan.core.rig import Rig, RigError

        try:
            rig = Rig.load(self.rig.calibration)
        except RigError as exc:
            raise ConfigError(f"rig.calibration: {exc}") from exc
        size, calibrated = (self.projector.width, self.projector.height), (rig.projector.width, rig.projector.height)
        # the window backend draws the fringes at this size (the mock draws for no camera; a LightCrafter plays its own
        # resolution): drawn at one size, decoded at another, every point would be wrong
        if self.projector.backend == "window" and size != calibrated:
            raise ConfigError(
                f"projector: {size[0]}x{size[1]} px, but the rig calibration ({self.rig.calibration}) has a "
                f"{calibrated[0]}x{calibrated[1]} projector: period_px and every decoded point are in the calibrated "
                "projector's pixels; set projector.width/height to it or calibrate this projector")
        return rig
