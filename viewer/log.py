"""Rerun logging of bursts: raw frames, wrapped phase, uncertainty, error and point cloud.

The phase, uncertainty and error panels are float images in their own unit, drawn by the
viewer with a colormap over a fixed range (``rr.DepthImage``), so hovering a pixel reads its
value ("Val:"; the "Depth:" line rerun adds to every depth image means nothing here).
Each panel has a colour bar beside it with the range and the unit.

Entity layout (stable, the blueprints and the tests rely on it)::

    world/camera                      Pinhole + Transform3D (static)
    world/camera/frames/{0,1,2}       raw frames of the burst
    world/camera/phase                wrapped phase, float32, rad, twilight -pi..pi
    world/camera/sigma/{model,data,total}   phase uncertainty, float32, rad, viridis 0..0.2
    world/camera/sigma_mm             depth uncertainty of each cloud point at its pixel, float32, mm
    world/camera/error                |phase error| vs truth, float32, rad, magma 0..0.5 (truth only)
    world/camera/masks/{phase,cloud}  segmentation overlays (classes in MASK_CLASSES): grey where a panel has
                                      no value; on the depth panel, pixels that should have measured but got
                                      no point, by cause (unresolved fringe order, mixed pixel)
    (each image entity also holds a static ``unit`` string, for tools reading the .rrd)
    legend/{phase,sigma_rad,sigma_mm,error}   the colour bars (static RGB images with ticks and unit)
    world/cloud                       points (turntable frame), coloured by depth uncertainty (log scale)
    world/fused                       the revolution's fused model (gear frame), coloured by
                                      signed deviation from CAD; legend in fused/legend (text)
                                      and fused/colorbar (image), logged once at the end
    stats/turntable_deg               turntable angle of the burst's first frame
    stats/accuracy_rad/*              phase accuracy vs truth (keys ending in ``_rad``)
    stats/cloud_mm/*                  cloud accuracy / deviation (keys ending in ``_mm``)
    stats/latency_ms/*, stats/dropped/*   pipeline throughput (live)
    log/warnings                      TextLog: bursts without fringes, and the like
Timelines: ``burst`` (sequence) and ``capture_time`` (device time since the camera's epoch).
The layout follows the data: the error panel, each plot and the warnings panel appear once
something is logged to them (a live run without truth has no error panel).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gearscan.core.rig import Rig
from gearscan.core.types import Burst, Cloud, PhaseResult

APP_ID = "gearscan"
log = logging.getLogger(__name__)
CONNECT_SCHEMES = ("rerun://", "rerun+http://", "rerun+https://")  # what rerun's connect_grpc takes


def check_connect_url(url: str) -> str:
    """``url`` if rerun can connect to it (a gRPC URL such as ``rerun+http://127.0.0.1:9876/proxy``), else a
    ValueError naming it and what was expected: said before a run, not as a traceback when the stream opens."""
    if not isinstance(url, str) or not url.startswith(CONNECT_SCHEMES) or len(url) <= len(url.split("//", 1)[0]) + 2:
        raise ValueError(f"{url!r} is not a rerun gRPC URL: expected one starting {', '.join(CONNECT_SCHEMES)} "
                         "(e.g. rerun+http://127.0.0.1:9876/proxy, what `--serve` or the viewer prints)")
    return url


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


@dataclass(frozen=True)
class Scale:
    """How one float image panel is drawn: colormap over ``lo..hi`` in ``unit``, with a colour bar."""

    entity: str
    title: str
    unit: str
    cmap: str  # a colormap both matplotlib and rerun have (rerun.components.Colormap)
    lo: float
    hi: float
    legend: str  # entity of its colour bar
    mask: str = "world/camera/masks/phase"  # the grey overlay on pixels without a value

    def image(self, values: np.ndarray, valid: np.ndarray | None = None):
        """A float32 ``rr.DepthImage`` of ``values`` (invalid pixels NaN) drawn with this scale."""
        import rerun as rr

        img = np.asarray(values, np.float32)
        if valid is not None:  # NaN reads "no value" on hover; the viewer would colour it as the top end,
            img = np.where(valid, img, np.float32(np.nan))  # so the mask overlay greys it out
        return rr.DepthImage(img, meter=1.0, colormap=self.cmap, depth_range=(self.lo, self.hi))


SIGMA_MAX_RAD = 0.2  # top of the phase-uncertainty scale
SIGMA_MAX_MM = 0.03  # top of the depth-uncertainty scale (classical twin: median 0.005, 99 % 0.028)
ERROR_MAX_RAD = 0.5  # top of the |phase error| scale
SCALES: dict[str, Scale] = {s.entity: s for s in (
    Scale("world/camera/phase", "wrapped phase", "rad", "twilight", -np.pi, np.pi, "legend/phase"),
    Scale("world/camera/error", "|phase error| vs truth", "rad", "magma", 0.0, ERROR_MAX_RAD, "legend/error"),
    Scale("world/camera/sigma/total", "total uncertainty", "rad", "viridis", 0.0, SIGMA_MAX_RAD, "legend/sigma_rad"),
    Scale("world/camera/sigma/model", "model uncertainty", "rad", "viridis", 0.0, SIGMA_MAX_RAD, "legend/sigma_rad"),
    Scale("world/camera/sigma/data", "data uncertainty", "rad", "viridis", 0.0, SIGMA_MAX_RAD, "legend/sigma_rad"),
    Scale("world/camera/sigma_mm", "depth uncertainty", "mm", "viridis", 0.0, SIGMA_MAX_MM, "legend/sigma_mm",
          mask="world/camera/masks/cloud"),
)}

# classes of the grey overlays on the float images (world/camera/masks/*): the depth-uncertainty panel
# also says why a pixel that should have measured has no point, so nothing is dropped unseen
MASK_CLASSES: dict[int, tuple[str, tuple[int, int, int, int]]] = {
    0: ("value", (0, 0, 0, 0)),
    1: ("no value", (48, 48, 48, 255)),
    2: ("unresolved: no trustworthy fringe order", (230, 0, 200, 255)),
    3: ("mixed: blends two surfaces, dropped", (255, 140, 0, 255)),
}

# time-series plots, one per unit: stats subtree -> view title
PLOTS: dict[str, str] = {
    "turntable_deg": "turntable (deg)",
    "accuracy_rad": "phase accuracy vs truth (rad)",
    "cloud_mm": "cloud (mm)",
    "latency_ms": "latency per stage (ms)",
    "dropped": "dropped bursts (count)",
    "other": "other",
}


def stat_path(key: str) -> tuple[str, str]:
    """``(plot, entity)`` of a stats key: the plot is chosen by the key's unit suffix or prefix."""
    for prefix in ("latency_ms/", "dropped/"):
        if key.startswith(prefix):
            plot = prefix[:-1]
            return plot, f"stats/{plot}/{key[len(prefix):]}"
    for suffix, plot in (("_rad", "accuracy_rad"), ("_mm", "cloud_mm"), ("_deg", "turntable_deg")):
        if key.endswith(suffix):
            return plot, f"stats/{plot}/{key}"
    return "other", f"stats/other/{key}"


def colorbar_image(scale: Scale, height: int = 360) -> np.ndarray:
    """A vertical colour bar with ticks and the unit, rendered by matplotlib: ``(H, W, 3)`` uint8."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colorbar import ColorbarBase
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    dpi = 100
    fig = Figure(figsize=(1.1, height / dpi), dpi=dpi, facecolor="white")
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.08, 0.04, 0.28, 0.82))
    bar = ColorbarBase(ax, cmap=matplotlib.colormaps[scale.cmap], norm=Normalize(scale.lo, scale.hi))
    if scale.unit == "rad" and scale.lo < 0:
        bar.set_ticks([-np.pi, -np.pi / 2, 0, np.pi / 2, np.pi], labels=["-π", "-π/2", "0", "π/2", "π"])
    bar.ax.tick_params(labelsize=11)
    fig.text(0.5, 0.93, scale.unit, ha="center", va="bottom", fontsize=16, fontweight="bold")
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def _image_panel(rrb, scale: Scale):
    """The float image (hover reads values) with its colour bar to the right."""
    return rrb.Horizontal(
        rrb.Spatial2DView(name=f"{scale.title} ({scale.unit})", origin="world/camera",
                          contents=[scale.entity, scale.mask],
                          overrides={scale.mask: rrb.EntityBehavior(interactive=False)}),  # hover the values below
        rrb.Spatial2DView(name=scale.unit, origin=scale.legend),
        column_shares=[5, 1],
    )


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


def default_blueprint(rig: Rig | None = None, *, error: bool = False, plots: tuple[str, ...] = ("turntable_deg",),
                      warnings: bool = False):
    """Frames, phase (and its error vs truth, when there is truth) on the left, uncertainty in
    the middle, cloud and one plot per unit on the right; a warnings panel once one was logged.

    ``plots``: keys of :data:`PLOTS` with data (live: cloud, latency, dropped; replay: accuracy, cloud).
    """
    import rerun.blueprint as rrb

    left = [rrb.Spatial2DView(name="frame", origin="world/camera", contents="world/camera/frames/0"),
            _image_panel(rrb, SCALES["world/camera/phase"])]
    if error:
        left.append(_image_panel(rrb, SCALES["world/camera/error"]))
    if warnings:
        left.append(rrb.TextLogView(name="warnings", origin="log"))
    middle = [_image_panel(rrb, SCALES[e]) for e in
              ("world/camera/sigma/total", "world/camera/sigma_mm", "world/camera/sigma/model", "world/camera/sigma/data")]
    # the float images are depth images under a pinhole: keep them out of the 3D view (rerun would back-project them)
    cloud = rrb.Spatial3DView(name="point cloud", origin="world",
                              contents=["+ world/**", "- world/camera/phase", "- world/camera/error",
                                        "- world/camera/sigma/**", "- world/camera/sigma_mm",
                                        "- world/camera/masks/**"],
                              eye_controls=_eye_for(rig) if rig is not None else None)
    series = [rrb.TimeSeriesView(name=PLOTS[p], origin=f"stats/{p}") for p in PLOTS if p in plots]
    right = rrb.Vertical(cloud, *series, row_shares=[3 * max(len(series), 1), *([2] * len(series))]) \
        if series else cloud
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(*left),
            rrb.Vertical(*middle),
            right,
            column_shares=[1, 1, 2],
        ),
        collapse_panels=True,
    )


NO_FRINGE_MODULATION = 0.05  # normalised modulation 2B/S a fringe pixel reaches (recon.min_modulation's default)
NO_FRINGE_MIN_SHARE = 0.02  # fewer modulated pixels than this share of the image: no fringes (twin: 65 %, test ramp: 0.8 %)
NO_FRINGE_FLAT = 0.7  # modulated pixels whose phases agree this well (mean resultant length): no fringes (twin: 0.03, ramp: 0.86)


def fringe_problem(burst: Burst, step: int = 4) -> str | None:
    """Why this burst's frames show no fringes (``None``: they do).

    Judged on the frames themselves (three-step modulation and phase on every ``step``-th pixel),
    not on a decoder's output: a network may invent modulation where there is none. Fringes on a
    part give many modulated pixels whose phase runs through every value; a camera that does not
    see the projector (or the simulator's test ramp) gives almost none, or one phase everywhere.
    """
    i0, i1, i2 = (f.image[::step, ::step].astype(np.float32) for f in burst.frames)
    sin = np.float32(np.sqrt(3.0)) * (i1 - i2)
    cos = 2 * i0 - i1 - i2
    mod = (2.0 / 3.0) * np.hypot(sin, cos) / np.float32(burst.full_scale)  # 2B/S
    ok = mod >= NO_FRINGE_MODULATION
    share = float(ok.mean()) if ok.size else 0.0
    if share < NO_FRINGE_MIN_SHARE:
        return (f"no fringe modulation: {share:.2%} of the pixels reach 2B/S >= {NO_FRINGE_MODULATION:g} "
                "(does the camera see the projected fringes?); the phase shown is noise")
    z = (cos[ok] + 1j * sin[ok]) / np.hypot(sin[ok], cos[ok])
    flat = float(np.abs(z.mean()))
    if flat > NO_FRINGE_FLAT:
        return (f"no fringes: the modulated pixels' phase is flat (mean resultant length {flat:.2f} > "
                f"{NO_FRINGE_FLAT:g}; fringes run through every phase); the image is not a fringe pattern")
    return None


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


def deviation_legend(deviation: np.ndarray, range_mm: float, bursts: int, sigma: np.ndarray | None = None,
                     deviation_sigma: np.ndarray | None = None) -> str:
    """Markdown legend of the fused cloud's colours and the deviation it shows (with the deviation's own sigma, along
    the CAD's normal, where the frame fit gave one)."""
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
    if deviation_sigma is not None and len(deviation_sigma):
        lines += [f"Deviation sigma (along the CAD's normal): median {float(np.median(deviation_sigma)) * 1e3:.1f} µm."]
    return "\n".join(lines)


class RerunLogger:
    """Streams pipeline results to a rerun sink: a file, a remote viewer, or a spawned viewer.

    ``connect`` takes a gRPC URL (``rerun+http://HOST:9876/proxy``) of a viewer elsewhere on
    the shop floor. If the viewer goes away, rerun drops data for it; measurement goes on.
    The layout (:func:`default_blueprint`) follows what is logged and is sent again when it grows.
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
        self._rig: Rig | None = None
        self._layout: tuple[bool, tuple[str, ...], bool] = (False, ("turntable_deg",), False)
        self._legends_logged = False
        self.no_fringe_bursts = 0  # bursts that showed no fringes (warned about)
        self._fringe_state: str | None = None  # the last burst's fringe problem
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
        self.cloud_color = cloud_color

    def log_rig(self, rig: Rig) -> None:
        """Camera intrinsics and pose in the turntable frame, logged once (static).

        Also sends the blueprint again with the 3D view aimed at what this rig measures.
        """
        rr = self.rr
        self._rig = rig
        try:
            self._send_layout()
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

    def _send_layout(self) -> None:
        error, plots, warnings = self._layout
        self._blueprint = default_blueprint(self._rig, error=error, plots=plots, warnings=warnings)
        self.stream.send_blueprint(self._blueprint)

    def _grow_layout(self, *, error: bool = False, plots: set[str] = frozenset(), warnings: bool = False) -> None:
        """Send the blueprint again when a panel gets its first data (panels are never removed)."""
        old_error, old_plots, old_warnings = self._layout
        layout = (old_error or error, tuple(p for p in PLOTS if p in set(old_plots) | set(plots)),
                  old_warnings or warnings)
        if layout != self._layout:
            self._layout = layout
            self._send_layout()

    def _log_legends(self) -> None:
        """The colour bars and each image entity's unit (static, once)."""
        rr, s = self.rr, self.stream
        s.log("world/camera/masks", rr.AnnotationContext([(cls, label, rgba) for cls, (label, rgba) in MASK_CLASSES.items()]),
              static=True)
        done = set()
        for scale in SCALES.values():
            s.log(scale.entity, rr.AnyValues(unit=scale.unit), static=True)
            if scale.legend not in done:
                s.log(scale.legend, rr.Image(colorbar_image(scale)), static=True)
                done.add(scale.legend)
        self._legends_logged = True

    def warn(self, text: str) -> None:
        """A warning both in the viewer (``log/warnings``, a text log panel appears) and on the console."""
        log.warning("%s", text)
        self.stream.log("log/warnings", self.rr.TextLog(text, level=self.rr.TextLogLevel.WARN))
        self._grow_layout(warnings=True)

    def _check_fringes(self, burst: Burst) -> None:
        """Warn when a burst shows no fringes: on the first such burst, every 100th, and on recovery."""
        problem = fringe_problem(burst)
        if problem is not None:
            self.no_fringe_bursts += 1
            if self._fringe_state is None or self.no_fringe_bursts % 100 == 0:
                self.warn(f"burst {burst.index}: {problem} ({self.no_fringe_bursts} such burst(s) so far)")
        elif self._fringe_state is not None:
            self.warn(f"burst {burst.index}: fringes are back")
        self._fringe_state = problem

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
        unresolved: np.ndarray | None = None,
        mixed: np.ndarray | None = None,
    ) -> None:
        rr, s = self.rr, self.stream
        s.set_time("burst", sequence=burst.index)
        s.set_time("capture_time", duration=burst.timestamp_ns * 1e-9)
        for i, f in enumerate(burst.frames):
            s.log(f"world/camera/frames/{i}", rr.Image(f.image))
        if not self._legends_logged:
            self._log_legends()
        plots = {"turntable_deg"} | {stat_path(k)[0] for k in (stats or {})}
        self._grow_layout(error=error is not None, plots=plots)
        valid = mask if mask is not None else (result.modulation > 0.02) & np.isfinite(result.sigma_total)
        # float images in their unit (invalid pixels NaN), coloured by the viewer over fixed ranges
        s.log("world/camera/masks/phase", rr.SegmentationImage((~valid).astype(np.uint8), opacity=1.0))
        s.log("world/camera/phase", SCALES["world/camera/phase"].image(result.phase, valid))
        for name in ("model", "data", "total"):
            s.log(f"world/camera/sigma/{name}",
                  SCALES[f"world/camera/sigma/{name}"].image(getattr(result, f"sigma_{name}"), valid))
        depth_sigma = np.full(result.phase.shape, np.nan, np.float32)
        if cloud is not None and len(cloud):
            rows, cols = np.asarray(cloud.pixels, np.int64).T
            depth_sigma[rows, cols] = cloud.sigma
        no_point = np.isnan(depth_sigma).astype(np.uint8)  # class 1, or 2/3 where a point was expected
        for cls, where in ((2, unresolved), (3, mixed)):
            if where is not None:
                no_point[np.asarray(where, bool) & (no_point == 1)] = cls
        s.log("world/camera/masks/cloud", rr.SegmentationImage(no_point, opacity=1.0))
        s.log("world/camera/sigma_mm", SCALES["world/camera/sigma_mm"].image(depth_sigma))
        if error is not None:
            s.log("world/camera/error", SCALES["world/camera/error"].image(np.abs(error), valid))
        self._check_fringes(burst)
        if cloud is not None and len(cloud):
            if self.cloud_color == "deviation" and cloud.deviation is not None:
                colors = colorize(cloud.deviation, -0.1, 0.1, "coolwarm")  # mm, signed distance to CAD
            else:  # depth sigma on a log scale between its 1st and 99th percentile: it spans factors (the edge
                # band's scale alone is 2-4x the interior's, recon.depth_sigma), and a linear stretch would paint the
                # interior one colour
                log_sigma = np.log(np.maximum(cloud.sigma, 1e-9))
                lo, hi = np.percentile(log_sigma, [1, 99])
                colors = colorize(log_sigma, float(lo), max(float(hi), float(lo) + 1e-9), "viridis")
            # radius in screen points, not mm: sub-mm points vanish when the view is zoomed out
            s.log("world/cloud", rr.Points3D(cloud.points, colors=colors, radii=rr.Radius.ui_points(1.5)))
        s.log("stats/turntable_deg", rr.Scalars(np.degrees(burst.angles[0])))
        for k, v in (stats or {}).items():
            s.log(stat_path(k)[1], rr.Scalars(float(v)))

    def log_fused(self, points: np.ndarray, deviation: np.ndarray, *, bursts: int,
                  sigma: np.ndarray | None = None, deviation_sigma: np.ndarray | None = None,
                  range_mm: float = DEVIATION_RANGE_MM) -> None:
        """Log the fused model coloured by signed deviation from CAD (mm, fixed scale +-``range_mm``)
        with a text legend and a colour bar, and show it (:func:`fused_blueprint`)."""
        rr, s = self.rr, self.stream
        if not range_mm > 0:
            raise ValueError(f"range_mm: expected > 0, got {range_mm}")
        try:
            colors = colorize(deviation, -range_mm, range_mm, "coolwarm")
            s.log("world/fused", rr.Points3D(points, colors=colors, radii=rr.Radius.ui_points(1.5)), static=True)
            s.log("fused/legend", rr.TextDocument(deviation_legend(deviation, range_mm, bursts, sigma, deviation_sigma),
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
