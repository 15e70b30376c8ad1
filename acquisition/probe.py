"""Ask devices what they are: `gearscan devices` and `gearscan live --check` use these.

:func:`probe_encoder` opens a serial port, sends the protocol's ``HELLO`` and reads for a
moment: a gearscan encoder answers with its banner and streams sample lines. :func:`check_projector`
counts the displays a window projector can use. (The camera check, which opens any configured
camera including the replay mock, is :func:`gearscan.acquire.check_camera`.)
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from gearscan.acquisition.config import AcquisitionConfig, ConfigError
from gearscan.acquisition.encoder_protocol import Banner, ProtocolError, RawSample, parse_line


@dataclass(frozen=True)
class EncoderProbe:
    """What answered on one serial port within the probe's time."""

    port: str
    banner: Banner | None = None
    samples: int = 0  # valid sample lines
    invalid: int = 0  # lines that are not valid protocol lines (noise, another device, wrong baudrate)
    bytes_read: int = 0
    rate_hz: float | None = None  # sample rate by the device's own clock
    error: str | None = None  # the port could not be opened

    @property
    def is_encoder(self) -> bool:
        return self.banner is not None or self.samples > 0

    def describe(self) -> str:
        if self.error is not None:
            return f"cannot open ({self.error})"
        if not self.is_encoder:
            what = f"{self.bytes_read} bytes, {self.invalid} invalid lines" if self.bytes_read else "silent"
            return f"no gearscan encoder ({what}: another device, the wrong baudrate, or not the encoder protocol)"
        who = (f"gearscan encoder {self.banner.device!r}, protocol v{self.banner.version}, "
               f"{self.banner.counts_per_rev} counts/rev" if self.banner else "gearscan encoder samples without a banner")
        rate = f", {self.rate_hz:.0f} samples/s" if self.rate_hz else ""
        return f"{who}{rate}" + (f", {self.invalid} invalid lines" if self.invalid else "")


def probe_encoder(port: str, baudrate: int = 115_200, timeout_s: float = 1.0) -> EncoderProbe:
    """Open ``port``, send ``HELLO`` and read for up to ``timeout_s`` s (less once the banner
    and a few samples are in); never raises for a port that is missing or busy."""
    import serial

    try:
        link = serial.serial_for_url(port, baudrate=baudrate, timeout=0.05)
    except (OSError, ValueError, serial.SerialException) as exc:
        return EncoderProbe(port, error=str(exc))
    banner, samples, invalid, nbytes, buf = None, [], 0, 0, b""
    try:
        link.write(b"HELLO\n")
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not (banner is not None and len(samples) >= 50):
            chunk = link.read(max(1, link.in_waiting))
            nbytes += len(chunk)
            *lines, buf = (buf + chunk).split(b"\n")
            for line in filter(bytes.strip, lines):
                try:
                    msg = parse_line(line)
                except ProtocolError:
                    invalid += 1
                    continue
                if isinstance(msg, Banner):
                    banner = msg
                elif isinstance(msg, RawSample):
                    samples.append(msg.t_us)
    except (OSError, serial.SerialException) as exc:
        return EncoderProbe(port, banner, len(samples), invalid, nbytes, error=f"read failed: {exc}")
    finally:
        link.close()
    span_us = samples[-1] - samples[0] if len(samples) > 1 else 0
    rate = (len(samples) - 1) / (span_us / 1e6) if span_us > 0 else None
    return EncoderProbe(port, banner, len(samples), invalid, nbytes, rate)


def check_projector(cfg: AcquisitionConfig) -> str:
    """Whether the projector backend can show patterns here, in words; ConfigError if not."""
    p = cfg.projector
    if p.backend == "mock":
        return "mock projector (shows nothing)"
    if p.backend == "lightcrafter":
        return "lightcrafter: plays its own sequence, not checked here"
    try:
        import pygame
    except ImportError as exc:
        raise ConfigError("projector.backend: 'window' needs pygame (pip install pygame)") from exc
    try:
        pygame.display.init()
        n = pygame.display.get_num_displays()
    except pygame.error as exc:
        raise ConfigError(f"projector.display: no display to open a window on ({exc}); is a screen attached "
                          "(DISPLAY set)?") from exc
    finally:
        pygame.display.quit()
    if not 0 <= p.display < n:
        raise ConfigError(f"projector.display: {p.display} not available; {n} display(s) found (0 to {n - 1})")
    return f"window projector on display {p.display} of {n}"
