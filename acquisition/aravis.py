"""GenICam cameras (GigE Vision, USB3 Vision) through Aravis (``gi.repository.Aravis``).

Aravis is imported lazily so the rest of gearscan works where it is absent. Tested against
Aravis's GigE Vision simulator ``arv-fake-gv-camera-0.8`` on 127.0.0.1 (see PLATFORM.md).

Buffer pool: ``settings.buffer_count`` Aravis buffers; each grabbed image is copied out and
its buffer re-queued at once, so memory stays bounded and a slow consumer shows up as
frame-id gaps (``stats.missing_frames``), never as growth. Lost cameras are detected by a
GVCP register read after a grab timeout (~2.5 s to declare loss) and by failing control
writes; :meth:`AravisCamera.reconnect` finds the camera again by id and restores settings.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from gearscan.acquisition.camera import (
    PIXEL_FORMATS,
    BaseCamera,
    CameraConfigError,
    CameraDisconnected,
    CameraError,
    CameraInfo,
    CameraNotFound,
    CameraSettings,
    RawFrame,
)

_ARAVIS: Any = None
_GLIB: Any = None


def aravis() -> tuple[Any, Any]:
    """Import ``(Aravis, GLib)`` on first use; clear error if the bindings are missing."""
    global _ARAVIS, _GLIB
    if _ARAVIS is None:
        try:
            import gi

            gi.require_version("Aravis", "0.8")
            from gi.repository import Aravis, GLib
        except (ImportError, ValueError) as exc:
            raise CameraError(
                "Aravis is not available: install the apt packages gir1.2-aravis-0.8 and "
                f"aravis-tools and pip 'pygobject<3.51' ({exc})"
            ) from exc
        _ARAVIS, _GLIB = Aravis, GLib
    return _ARAVIS, _GLIB


def list_cameras() -> list[CameraInfo]:
    """Every camera Aravis can see (GigE discovery takes about 1 s)."""
    Aravis, _ = aravis()
    Aravis.update_device_list()
    out = []
    for i in range(Aravis.get_n_devices()):
        out.append(
            CameraInfo(
                id=Aravis.get_device_id(i) or "",
                vendor=Aravis.get_device_vendor(i) or "",
                model=Aravis.get_device_model(i) or "",
                serial=Aravis.get_device_serial_nbr(i) or "",
                address=Aravis.get_device_address(i) or "",
                driver=f"aravis/{Aravis.get_device_protocol(i) or '?'}",
            )
        )
    return out


def _find(camera_id: str | None, found: list[CameraInfo]) -> CameraInfo:
    if not found:
        raise CameraNotFound(f"camera.id: {camera_id!r} not found: Aravis sees no camera at all")
    if camera_id is None:
        return found[0]
    for c in found:
        if camera_id in (c.id, c.serial, c.address):
            return c
    listing = ", ".join(f"{c.id!r} (serial {c.serial}, {c.address})" for c in found)
    raise CameraNotFound(f"camera.id: {camera_id!r} not found; Aravis sees: {listing}")


def _interface_mtu(camera_address: str) -> int | None:
    """MTU of the host interface on the camera's subnet (/24 match; loopback for 127.x)."""
    import fcntl
    import socket
    import struct

    if not camera_address:
        return None
    prefix = camera_address.rsplit(".", 1)[0] + "."
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for _, name in socket.if_nameindex():
            req = struct.pack("256s", name.encode()[:15])
            try:
                addr = socket.inet_ntoa(fcntl.ioctl(s.fileno(), 0x8915, req)[20:24])  # SIOCGIFADDR
                mtu = struct.unpack("i", fcntl.ioctl(s.fileno(), 0x8921, req)[16:20])[0]  # SIOCGIFMTU
            except OSError:
                continue  # interface without IPv4 address
            if addr.startswith(prefix):
                return int(mtu)
    return None


class AravisCamera(BaseCamera):
    """One GenICam camera. ``camera_id`` is an Aravis id, serial number or IP (None = first).

    GigE Vision v1 block ids are 16-bit and skip 0; the gap detector knows.
    """

    driver = "aravis"
    frame_id_modulus = 1 << 16
    frame_id_skips_zero = True

    def __init__(self, camera_id: str | None = None, *, discovery_attempts: int = 1):
        super().__init__()
        self.camera_id = camera_id
        self.discovery_attempts = max(1, discovery_attempts)
        self.info = CameraInfo(id=str(camera_id), vendor="", model="", serial="", address="", driver="aravis")
        self._cam: Any = None
        self._stream: Any = None
        self._payload = 0
        self._lost = threading.Event()
        self._dtype: type = np.uint8
        self._bits = 8
        self.packet_size = 0
        self.reconnects = 0

    # -- open / close ----------------------------------------------------------------------
    def open(self) -> None:
        Aravis, GLib = aravis()
        found: list[CameraInfo] = []
        for _ in range(self.discovery_attempts):
            found = list_cameras()
            try:
                info = _find(self.camera_id, found)
                break
            except CameraNotFound:
                time.sleep(0.2)
        else:
            info = _find(self.camera_id, found)  # raises with the listing
        try:
            self._cam = Aravis.Camera.new(info.id)
        except GLib.Error as exc:
            raise CameraError(f"camera {info.id!r}: could not open ({exc.message})") from exc
        self.info = info
        self._lost.clear()
        self._cam.get_device().connect("control-lost", lambda *_: self._lost.set())

    def close(self) -> None:
        if self._cam is None:
            return
        try:
            self.stop()
        except CameraError:
            pass  # a lost camera cannot be stopped; we are dropping it anyway
        self._stream = None
        self._cam = None

    def available_pixel_formats(self) -> list[str]:
        return list(self._require().dup_available_pixel_formats_as_strings())

    def sensor_size(self) -> tuple[int, int]:
        s = self._require().get_sensor_size()
        return int(s.width), int(s.height)

    def features(self) -> dict[str, str]:
        """What the camera offers that the live config can set, in words (for `gearscan devices`)."""
        _, GLib = aravis()
        cam = self._require()
        out: dict[str, str] = {}
        for name, read in (
            ("sensor", lambda: "{}x{}".format(*self.sensor_size())),
            ("roi", lambda: "{}, {}, {}, {}".format(*cam.get_region())),
            ("pixel formats", lambda: ", ".join(self.available_pixel_formats())),
            ("exposure µs", lambda: "{:g} to {:g}".format(*cam.get_exposure_time_bounds())),
            ("gain dB", lambda: "{:g} to {:g}".format(*cam.get_gain_bounds())),
            ("frame rate Hz", lambda: "{:g} to {:g}".format(*cam.get_frame_rate_bounds())),
            ("trigger sources", lambda: ", ".join(cam.dup_available_trigger_sources())),
        ):
            try:
                out[name] = read()
            except (GLib.Error, TypeError) as exc:  # a camera without the feature
                out[name] = f"n/a ({getattr(exc, 'message', exc)})"
        return out

    def _require(self) -> Any:
        if self._cam is None:
            raise CameraError(f"aravis camera {self.camera_id!r} is not open (use it as a context manager)")
        return self._cam

    # -- settings ---------------------------------------------------------------------------
    def _apply(self, s: CameraSettings) -> None:
        _, GLib = aravis()
        cam = self._require()
        formats = self.available_pixel_formats()
        if s.pixel_format not in formats:
            mono = [f for f in formats if f in PIXEL_FORMATS]
            raise CameraConfigError(
                f"camera.pixel_format: {s.pixel_format!r} not offered by {self.info.model} "
                f"{self.info.serial}; it offers {mono} (all: {formats})"
            )
        try:
            cam.set_pixel_format_from_string(s.pixel_format)
            if s.roi is not None:
                w, h = self.sensor_size()
                x, y, rw, rh = s.roi
                if x + rw > w or y + rh > h:
                    raise CameraConfigError(f"camera.roi: {s.roi} exceeds the sensor {w}x{h}")
                cam.set_region(x, y, rw, rh)
            lo, hi = cam.get_exposure_time_bounds()
            if not lo <= s.exposure_us <= hi:
                raise CameraConfigError(f"camera.exposure_us: {s.exposure_us} outside [{lo}, {hi}]")
            cam.set_exposure_time(s.exposure_us)
            glo, ghi = cam.get_gain_bounds()
            if not glo <= s.gain_db <= ghi:
                raise CameraConfigError(f"camera.gain_db: {s.gain_db} outside [{glo}, {ghi}]")
            cam.set_gain(s.gain_db)
            if s.trigger == "free-run":
                cam.clear_triggers()
                if s.frame_rate_hz is not None:
                    flo, fhi = cam.get_frame_rate_bounds()
                    if not flo <= s.frame_rate_hz <= fhi:
                        raise CameraConfigError(f"camera.frame_rate_hz: {s.frame_rate_hz} outside [{flo}, {fhi}]")
                    cam.set_frame_rate(s.frame_rate_hz)
            elif s.trigger == "software":
                cam.set_trigger("Software")
            else:
                sources = list(cam.dup_available_trigger_sources())
                if s.trigger_line not in sources:
                    raise CameraConfigError(f"camera.trigger_line: {s.trigger_line!r} not offered; sources: {sources}")
                cam.set_trigger(s.trigger_line)
            if cam.is_gv_device():
                self._tune_packet_size(s.packet_size)
        except GLib.Error as exc:
            raise self._as_error(exc, "configure") from exc
        self._dtype, self._bits = PIXEL_FORMATS[s.pixel_format]

    def _tune_packet_size(self, requested: int | None) -> None:
        """GigE packet size: larger packets cost fewer interrupts (800x800 on loopback:
        ~180 fps at 1400 B, ~370 fps at 16 kB).

        None: Aravis's probe (test packets with don't-fragment); when the camera cannot fire
        test packets (the simulator) and the probe leaves a standard-MTU size, fall back to
        the host interface MTU minus IP/UDP headers, capped by the camera's maximum.
        """
        _, GLib = aravis()
        cam = self._cam
        self.tuning_note = ""
        if requested is None:
            try:
                cam.gv_auto_packet_size()
            except GLib.Error as exc:
                self.tuning_note = f"auto packet size failed ({exc.message}); "
            if cam.gv_get_packet_size() <= 1500:
                mtu = _interface_mtu(self.info.address)
                try:
                    hi = int(cam.get_integer_bounds("GevSCPSPacketSize")[1])
                except GLib.Error:
                    hi = 1500
                if mtu is not None and mtu - 28 > 1500:
                    size = min(mtu - 28, hi)
                    cam.gv_set_packet_size(size)
                    self.tuning_note += f"interface MTU {mtu}: packet size {size}"
        elif requested > 0:
            cam.gv_set_packet_size(int(requested))
        self.packet_size = int(cam.gv_get_packet_size())

    # -- streaming ---------------------------------------------------------------------------
    def _start(self) -> None:
        Aravis, GLib = aravis()
        cam = self._require()
        try:
            self._payload = int(cam.get_payload())
            self._stream = cam.create_stream(None, None)
            if cam.is_gv_device():
                self._size_socket_buffer()
            for _ in range(self.settings.buffer_count):
                self._stream.push_buffer(Aravis.Buffer.new_allocate(self._payload))
            cam.start_acquisition()
        except GLib.Error as exc:
            raise self._as_error(exc, "start") from exc

    def _size_socket_buffer(self) -> None:
        """Receive buffer for several frames (up to net.core.rmem_max): a consumer thread
        that is briefly descheduled must not cost packets (measured: fewer damaged frames)."""
        Aravis, _ = aravis()
        try:
            rmem_max = int(Path("/proc/sys/net/core/rmem_max").read_text())
        except (OSError, ValueError):
            return
        size = min(rmem_max, max(4 * self._payload, 1 << 20))
        self._stream.set_property("socket-buffer", Aravis.GvStreamSocketBuffer.FIXED)
        self._stream.set_property("socket-buffer-size", size)
        self.socket_buffer_size = size

    def _stop(self) -> None:
        _, GLib = aravis()
        try:
            if self._cam is not None:
                self._cam.stop_acquisition()
        except GLib.Error as exc:
            raise self._as_error(exc, "stop") from exc
        finally:
            self._stream = None

    def software_trigger(self) -> None:
        _, GLib = aravis()
        if self.settings.trigger != "software":
            raise CameraError(f"software_trigger() needs camera.trigger = 'software', it is {self.settings.trigger!r}")
        try:
            self._require().software_trigger()
        except GLib.Error as exc:
            raise self._as_error(exc, "software trigger") from exc

    def _pop(self, timeout: float) -> RawFrame | None:
        Aravis, _ = aravis()
        if self._lost.is_set():
            raise CameraDisconnected(f"camera {self.info.id!r} lost (heartbeat failed); call reconnect()")
        deadline = time.monotonic() + timeout
        while True:
            left_us = max(0, int((deadline - time.monotonic()) * 1e6))
            buf = self._stream.timeout_pop_buffer(left_us) if left_us else self._stream.try_pop_buffer()
            if buf is None:
                return None
            arrival = time.monotonic_ns()
            status = buf.get_status()
            if status != Aravis.BufferStatus.SUCCESS:
                self.stats.incomplete += 1
                self._stream.push_buffer(buf)
                if time.monotonic() >= deadline:
                    return None
                continue
            w, h = buf.get_image_width(), buf.get_image_height()
            image = np.frombuffer(buf.get_data(), dtype=self._dtype, count=w * h).reshape(h, w).copy()
            frame_id = int(buf.get_frame_id())
            dev_ts = int(buf.get_timestamp())
            self._stream.push_buffer(buf)
            return RawFrame(image, frame_id, dev_ts, arrival, self._bits)

    def _check_alive(self) -> None:
        """After a timeout: one GVCP register read tells a silent camera from a lost one."""
        _, GLib = aravis()
        if self._lost.is_set():
            raise CameraDisconnected(f"camera {self.info.id!r} lost (heartbeat failed); call reconnect()")
        try:
            self._require().get_device().read_register(0x0)
        except GLib.Error as exc:
            raise CameraDisconnected(
                f"camera {self.info.id!r} at {self.info.address} stopped answering ({exc.message}); "
                "check cable/power, then call reconnect()"
            ) from exc

    def _as_error(self, exc: Any, what: str) -> CameraError:
        msg = getattr(exc, "message", str(exc))
        if "timeout" in msg.lower():
            return CameraDisconnected(f"camera {self.info.id!r}: {what} failed, camera not answering ({msg})")
        return CameraError(f"camera {self.info.id!r}: {what} failed ({msg})")

    def stats_from_aravis(self) -> dict[str, int]:
        """Aravis's own stream counters (completed/failed buffers, underruns, resent packets)."""
        if self._stream is None:
            return {}
        resent, missing = self._stream.get_statistics()
        return {"resent_packets": int(resent), "missing_packets": int(missing)}

    # -- recovery ----------------------------------------------------------------------------
    def reconnect(self, timeout: float = 30.0, poll: float = 0.5) -> None:
        """Drop the lost camera, wait until it is found again, re-apply settings, restart.

        Raises CameraDisconnected if it does not come back within ``timeout`` s.
        """
        was_streaming = self._streaming
        self._streaming = False
        self._stream = None
        self._cam = None
        self.clock.reset()
        deadline = time.monotonic() + timeout
        last: Exception | None = None
        while time.monotonic() < deadline:
            try:
                self.open()
                self._apply(self.settings)
                if was_streaming:
                    self.start()
                self.reconnects += 1
                return
            except CameraError as exc:
                last = exc
                self._cam = None
                time.sleep(poll)
        raise CameraDisconnected(f"camera {self.camera_id!r} did not come back within {timeout:g} s ({last})")
