"""Rerun logging of bursts: raw frames, wrapped phase, uncertainty, error and point cloud.

Entity layout (stable, the blueprint and the tests rely on it)::

    world/camera                      Pinhole + Transform3D (static)
    world/camera/frames/{0,1,2}       raw frames of the burst
    world/camera/phase                wrapped phase, cyclic colours (RGB)
    world/camera/phase_rad            wrapped phase, float32 values (rad)
    world/camera/sigma/{model,data,total}   uncertainty (rad), viridis 0..sigma_max (0.2 rad)
    world/camera/sigma_rad/total      total uncertainty, float32 values (rad)
    world/camera/error                |phase error| vs truth, magma 0..0.5 rad, when truth exists
    world/cloud                       points (turntable frame), coloured by uncertainty
    world/fused                       the revolution's fused model (gear frame), coloured by
                                      signed deviation from CAD; legend in fused/legend (text)
                                      and fused/colorbar (image), logged once at the end
    stats/*                           scalars (encoder angle, rmse, latency)
Timelines: ``burst`` (sequence) and ``capture_time`` (device time since the camera's epoch);
the turntable angle is a scalar plot (``stats/turntable_deg``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from gearscan.rig import Rig
from gearscan.types import Burst, Cloud, PhaseResult

APP_ID = "gearscan"
log = logging.getLogger(__name__)


def _lut(name: str) -> np.ndarray:
    """256 x RGB: entry 0 black (masked pixels), entries 1..255 the colormap from lo to hi."""
    import matplotlib

    lut = np.zeros((256, 3), np.uint8)
    lut[1:] = (matplotlib.colormaps[name](np.linspace(0, 1, 255))[:, :3] * 255).astype(np.uint8)
    return lut


_LUTS: dict[str, np.ndarray] = {}


def colorize(values: np.ndarray, lo: float, hi: float, cmap: str, mask: np.ndarray | None = None) -> np.ndarray:
    """Map ``values`` to RGB uint8 with a matplotlib colormap; masked-out pixels black.

    NaN and values below ``lo`` take the low colour, values above ``hi`` (and inf) the high one.
    One gather per pixel through a table whose entry 0 is black (a few ms for 512x512).
    """
    lut = _LUTS.get(cmap)
    if lut is None:
        lut = _LUTS[cmap] = _lut(cmap)
    x = np.subtract(values, np.float32(lo), dtype=np.float32)
    x *= np.float32(254.0 / max(hi - lo, 1e-12))
    np.fmax(x, 0.0, out=x)  # fmax/fmin drop NaN: NaN -> low end
    np.fmin(x, 254.0, out=x)
    x += 1.0
    idx = x.astype(np.uint8)
    if mask is not None:
        idx[~mask] = 0
    return np.take(lut, idx, axis=0)


def _eye_for(rig: Rig):
    """A 3/4 view of the measured rim: from behind and above the camera, towards its target."""
    import rerun.blueprint as rrb

    cam = rig.camera
    c = cam.center_world
    z = cam.T_world_from[:3, :3][:, 2]  # optical axis in the world frame
    x = cam.T_world_from[:3, :3][:, 0]
    d = 0.88 * float(np.linalg.norm(c[:2]))  # the rim lies a little before the turntable axis
    target = c + d * z
    eye = target - 0.3 * d * z + 0.15 * d * np.array([0.0, 0.0, 1.0]) + 0.15 * d * x
    return rrb.EyeControls3D(position=eye, look_target=target, eye_up=[0.0, 0.0, 1.0])


def default_blueprint(rig: Rig | None = None):
    """Frames and phase on the left, uncertainty in the middle, cloud and plots on the right."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(name="frame", origin="world/camera", contents="world/camera/frames/0"),
                rrb.Spatial2DView(name="wrapped phase", origin="world/camera", contents="world/camera/phase"),
                rrb.Spatial2DView(name="phase error", origin="world/camera", contents="world/camera/error"),
            ),
            rrb.Vertical(
                rrb.Spatial2DView(name="total uncertainty", origin="world/camera", contents="world/camera/sigma/total"),
                rrb.Spatial2DView(name="model uncertainty", origin="world/camera", contents="world/camera/sigma/model"),
                rrb.Spatial2DView(name="data uncertainty", origin="world/camera", contents="world/camera/sigma/data"),
            ),
            rrb.Vertical(
                rrb.Spatial3DView(name="point cloud", origin="world",
                                  eye_controls=_eye_for(rig) if rig is not None else None),
                rrb.TimeSeriesView(name="turntable and accuracy", origin="stats"),
                row_shares=[3, 2],
            ),
            column_shares=[1, 1, 2],
        ),
        collapse_panels=True,
    )


DEVIATION_RANGE_MM = 0.1  # fused cloud colours: -range (blue, material missing) .. +range (red)


def fused_blueprint():
    """The fused model large, with its deviation legend beside it (sent when the model is logged)."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="fused model: deviation from CAD", origin="world", contents="world/fused"),
            rrb.Vertical(
                rrb.TextDocumentView(name="legend", origin="fused/legend"),
                rrb.Spatial2DView(name="colour scale (mm)", origin="fused/colorbar"),
                row_shares=[3, 1],
            ),
            column_shares=[3, 1],
        ),
        collapse_panels=True,
    )


def deviation_legend(deviation: np.ndarray, range_mm: float, bursts: int, sigma: np.ndarray | None = None) -> str:
    """Markdown legend of the fused cloud's colours and the deviation it shows."""
    d = deviation[np.isfinite(deviation)]
    lines = [
        "## Fused model: signed deviation from CAD",
        "",
        "| colour | deviation |",
        "|---|---|",
        f"| blue | <= -{range_mm:g} mm (material missing) |",
        "| white | 0 mm (on the CAD) |",
        f"| red | >= +{range_mm:g} mm (material added) |",
        "",
        f"{len(deviation):,} points fused from {bursts} bursts.",
    ]
    if d.size:
        p5, p50, p95 = np.percentile(d, [5, 50, 95])
        lines += [f"Deviation: median {p50:+.3f} mm, 5-95 % {p5:+.3f} to {p95:+.3f} mm, "
                  f"RMS {float(np.sqrt(np.mean(d**2))):.3f} mm."]
    if sigma is not None and len(sigma):
        lines += [f"Fused sigma: median {float(np.median(sigma)) * 1e3:.1f} µm."]
    return "\n".join(lines)


class RerunLogger:
    """Streams pipeline results to a rerun sink: a file, a remote viewer, or a spawned viewer.

    ``connect`` takes a gRPC URL (``rerun+http://HOST:9876/proxy``) of a viewer elsewhere on
    the shop floor. If the viewer goes away, rerun drops data for it; measurement goes on.
    """

    def __init__(
        self,
        *,
        save: str | Path | None = None,
        connect: str | None = None,
        spawn: bool = False,
        recording_id: str | None = None,
        cloud_color: str = "sigma",
    ) -> None:
        import rerun as rr

        if cloud_color not in ("sigma", "deviation"):
            raise ValueError(f"cloud_color must be 'sigma' or 'deviation', got {cloud_color!r}")

        self.rr = rr
        self.stream = rr.RecordingStream(APP_ID, recording_id=recording_id)
        self.connect_url = connect
        self.errors = 0  # log calls lost to a broken viewer connection
        self._retry_at = 0.0
        blueprint = default_blueprint()
        self._blueprint = blueprint
        if save is not None:
            Path(save).parent.mkdir(parents=True, exist_ok=True)
            self.stream.save(str(save), default_blueprint=blueprint)
        elif connect is not None:
            self.stream.connect_grpc(connect, default_blueprint=blueprint)
        elif spawn:
            self.stream.spawn(default_blueprint=blueprint)
        else:
            raise ValueError("RerunLogger needs a sink: save, connect or spawn")
        self.sigma_max = 0.2  # rad, top of the uncertainty colour scale
        self.cloud_color = cloud_color

    def log_rig(self, rig: Rig) -> None:
        """Camera intrinsics and pose in the turntable frame, logged once (static).

        Also sends the blueprint again with the 3D view aimed at what this rig measures.
        """
        rr = self.rr
        try:
            self.stream.send_blueprint(default_blueprint(rig))
        except RuntimeError as exc:
            self._viewer_lost(exc)
        cam = rig.camera
        t_wc = cam.T_world_from
        self.stream.log(
            "world/camera",
            rr.Transform3D(translation=t_wc[:3, 3], mat3x3=t_wc[:3, :3]),
            rr.Pinhole(image_from_camera=cam.K, width=cam.width, height=cam.height),
            static=True,
        )
        t_wp = rig.projector.T_world_from
        self.stream.log(
            "world/projector",
            rr.Transform3D(translation=t_wp[:3, 3], mat3x3=t_wp[:3, :3]),
            rr.Pinhole(image_from_camera=rig.projector.K, width=rig.projector.width, height=rig.projector.height),
            static=True,
        )

    def _viewer_lost(self, exc: Exception) -> None:
        """A dead viewer must not stop the measurement: count, warn once, retry later."""
        import time

        if self.errors == 0:
            log.warning("viewer connection lost (%s); measurement continues, retrying every 5 s", exc)
        self.errors += 1
        self._retry_at = time.monotonic() + 5.0

    def log_burst(self, *args, **kwargs) -> None:
        """Log one burst (see :meth:`_log_burst`); viewer failures are counted, not raised."""
        import time

        if self._retry_at and time.monotonic() < self._retry_at:
            self.errors += 1
            return
        try:
            if self._retry_at and self.connect_url:
                self.stream.connect_grpc(self.connect_url, default_blueprint=self._blueprint)
            self._log_burst(*args, **kwargs)
            self._retry_at = 0.0
        except RuntimeError as exc:
            self._viewer_lost(exc)

    def _log_burst(
        self,
        burst: Burst,
        result: PhaseResult,
        *,
        mask: np.ndarray | None = None,
        cloud: Cloud | None = None,
        error: np.ndarray | None = None,
        stats: dict[str, float] | None = None,
    ) -> None:
        rr, s = self.rr, self.stream
        s.set_time("burst", sequence=burst.index)
        s.set_time("capture_time", duration=burst.timestamp_ns * 1e-9)
        for i, f in enumerate(burst.frames):
            s.log(f"world/camera/frames/{i}", rr.Image(f.image))
        valid = mask if mask is not None else (result.modulation > 0.02) & np.isfinite(result.sigma_total)
        # coloured views for people (fixed scales, invalid pixels black); raw float32 values for tools
        s.log("world/camera/phase", rr.Image(colorize(result.phase, -np.pi, np.pi, "twilight", valid)))
        s.log("world/camera/phase_rad", rr.Image(result.phase.astype(np.float32)))
        for name in ("model", "data", "total"):
            sigma = getattr(result, f"sigma_{name}")
            s.log(f"world/camera/sigma/{name}", rr.Image(colorize(sigma, 0.0, self.sigma_max, "viridis", valid)))
        s.log("world/camera/sigma_rad/total", rr.Image(result.sigma_total.astype(np.float32)))
        if error is not None:
            s.log("world/camera/error", rr.Image(colorize(np.abs(error), 0.0, 0.5, "magma", valid)))
        if cloud is not None and len(cloud):
            if self.cloud_color == "deviation" and cloud.deviation is not None:
                colors = colorize(cloud.deviation, -0.1, 0.1, "coolwarm")  # mm, signed distance to CAD
            else:  # depth sigma, stretched between its 1st and 99th percentile
                lo, hi = np.percentile(cloud.sigma, [1, 99])
                colors = colorize(cloud.sigma, float(lo), max(float(hi), float(lo) + 1e-9), "viridis")
            # radius in screen points, not mm: sub-mm points vanish when the view is zoomed out
            s.log("world/cloud", rr.Points3D(cloud.points, colors=colors, radii=rr.Radius.ui_points(1.5)))
        s.log("stats/turntable_deg", rr.Scalars(np.degrees(burst.angles[0])))
        for k, v in (stats or {}).items():
            s.log(f"stats/{k}", rr.Scalars(float(v)))

    def log_fused(self, points: np.ndarray, deviation: np.ndarray, *, bursts: int,
                  sigma: np.ndarray | None = None, range_mm: float = DEVIATION_RANGE_MM) -> None:
        """Log the fused model coloured by signed deviation from CAD (mm, fixed scale +-``range_mm``)
        with a text legend and a colour bar, and show it (:func:`fused_blueprint`)."""
        rr, s = self.rr, self.stream
        if not range_mm > 0:
            raise ValueError(f"range_mm: expected > 0, got {range_mm}")
        try:
            colors = colorize(deviation, -range_mm, range_mm, "coolwarm")
            s.log("world/fused", rr.Points3D(points, colors=colors, radii=rr.Radius.ui_points(1.5)), static=True)
            s.log("fused/legend", rr.TextDocument(deviation_legend(deviation, range_mm, bursts, sigma),
                                                   media_type=rr.MediaType.MARKDOWN), static=True)
            ramp = np.linspace(range_mm, -range_mm, 256, dtype=np.float32)[:, None].repeat(24, axis=1)
            s.log("fused/colorbar", rr.Image(colorize(ramp, -range_mm, range_mm, "coolwarm")), static=True)
            s.send_blueprint(fused_blueprint())
        except RuntimeError as exc:
            self._viewer_lost(exc)

    def close(self) -> None:
        try:
            self.stream.flush()
            self.stream.disconnect()
        except RuntimeError as exc:
            self._viewer_lost(exc)
