"""The web viewer (``--serve``) during replay, seen by headless Chromium: assertions on pixels.

A twin recording is replayed into ``serve_web()``; Chromium opens the web viewer and the
screenshot must show the wrapped phase in the cyclic ``twilight`` colours in the "wrapped
phase (rad)" view, uncertainty-coloured (``viridis``) cloud points in the "point cloud" view,
and beside the phase, error and uncertainty panels their colour bars: the colormap running
from high (top) to low, titled with the unit (rad or mm, found by template matching).
Where each view sits on screen is computed from the default blueprint's shares, so a layout
change moves the regions with it. The screenshot is kept as ``tests/artifacts/web_viewer.png``.

Colour matching is brightness-invariant: rerun shades 3D points (a pixel is ``s * colour``
with ``s`` about 0.6-1), images are drawn unshaded (``s = 1``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from webshot import Chromium  # noqa: E402

ARTIFACTS = Path(__file__).parent / "artifacts"
WIDTH, HEIGHT = 1600, 1000
# Viewer chrome outside the blueprint's viewport (CSS px, panels collapsed): the top bar and the
# collapsed time panel. Only a fallback: the separator lines are looked for first.
TOP_BAR_PX, TIME_PANEL_PX = 36, 29
TITLE_BAR_PX = 26  # each view's tab/title strip


Rect = tuple[int, int, int, int]  # x0, y0, x1, y1 in screenshot pixels


# -- where the views are ------------------------------------------------------------------------
def blueprint_rects(container, rect: tuple[float, float, float, float]) -> dict[str, tuple[float, ...]]:
    """View key -> ``(x0, y0, x1, y1)`` by splitting ``rect`` along the blueprint's containers.

    A view's key is its name; a colour bar's is ``bar:`` + its origin + its place among bars of
    that origin (``bar:legend/sigma_rad#1``), as several panels share one bar.
    """
    from rerun.blueprint.containers import Horizontal, Vertical

    if not isinstance(container, (Horizontal, Vertical)):
        if str(container.origin).startswith("legend/"):
            return {f"bar:{container.origin}#0": rect}
        return {container.name: rect}
    horizontal = isinstance(container, Horizontal)
    n = len(container.contents)
    shares = np.asarray((container.column_shares if horizontal else container.row_shares) or [1] * n, float)
    edges = np.concatenate([[0.0], np.cumsum(shares) / shares.sum()])
    x0, y0, x1, y1 = rect
    out: dict[str, tuple[float, ...]] = {}
    for child, a, b in zip(container.contents, edges[:-1], edges[1:], strict=True):
        sub = (x0 + a * (x1 - x0), y0, x0 + b * (x1 - x0), y1) if horizontal else \
              (x0, y0 + a * (y1 - y0), x1, y0 + b * (y1 - y0))
        for key, r in blueprint_rects(child, sub).items():
            while key in out:  # another panel's copy of the same bar
                base, n = key.rsplit("#", 1)
                key = f"{base}#{int(n) + 1}"
            out[key] = r
    return out


def viewport_rows(rgb: np.ndarray) -> tuple[int, int]:
    """First and last row of the blueprint viewport: between the top bar and the time panel.

    The viewer draws a one-pixel separator line across the full width under its top bar and
    above its time panel; such a row is uniform and darker than the panel background.
    """
    h = rgb.shape[0]
    rows = rgb.astype(np.float32)
    uniform = (rows.std(axis=(1, 2)) < 4) & (rows.mean(axis=(1, 2)) < 240) & (rows.mean(axis=(1, 2)) > 60)
    top = [y for y in range(10, 80) if uniform[y]]
    bottom = [y for y in range(h - 80, h - 10) if uniform[y]]
    return (top[0] + 1 if top else TOP_BAR_PX), (bottom[-1] if bottom else h - TIME_PANEL_PX)


# the layout a replay with truth ends up with: error panel, and plots of what TruthScorer rows give the logger
REPLAY_LAYOUT = {"error": True, "plots": ("turntable_deg", "accuracy_rad", "cloud_mm")}


def view_regions(rgb: np.ndarray) -> dict[str, Rect]:
    """Content rectangle (title strip and separators removed) of each view in the replay's blueprint."""
    from gearscan.viewer.log import default_blueprint

    top, bottom = viewport_rows(rgb)
    width = rgb.shape[1]
    rects = blueprint_rects(default_blueprint(**REPLAY_LAYOUT).root_container,
                            (0.0, float(top), float(width), float(bottom)))
    out = {}
    for name, (x0, y0, x1, y1) in rects.items():
        out[name] = (int(x0) + 4, int(y0) + TITLE_BAR_PX, int(x1) - 4, int(y1) - 4)
    return out


# -- colour evidence ----------------------------------------------------------------------------
def colormap_hits(rgb: np.ndarray, cmap: str, tol: float = 10.0, min_chroma: int = 30) -> np.ndarray:
    """Colormap positions (0..1) of the pixels of ``rgb`` that are a shade of a ``cmap`` colour.

    A pixel ``p`` matches LUT colour ``c`` when ``|p - s c| < tol`` for the best shade
    ``s = p.c / c.c`` in [0.5, 1.1]; greys (chroma below ``min_chroma``) never match, so the
    UI, grid lines and grayscale images do not count. Every second pixel in each direction is
    tested (the (P, L) residual dominates the cost). Returns one position per matching pixel.
    """
    from gearscan.viewer.log import _lut

    lut = _lut(cmap)[1::2].astype(np.float32)  # 128 colours (entry 0 is the black of masked pixels)
    px = rgb[::2, ::2].reshape(-1, 3).astype(np.float32)
    px = px[(px.max(1) - px.min(1)) >= min_chroma]
    if len(px) == 0:
        return np.zeros(0)
    s = np.clip(px @ lut.T / (lut * lut).sum(1), 0.5, 1.1)  # (P, L)
    resid = np.linalg.norm(px[:, None, :] - s[..., None] * lut[None], axis=-1)
    best = resid.argmin(1)
    ok = resid[np.arange(len(px)), best] < tol
    return best[ok] / (len(lut) - 1)


def colormap_failures(rgb: np.ndarray, region: Rect, cmap: str, *, min_pixels: int, min_bins: int,
                      need_upper: bool = False, what: str) -> list[str]:
    """Why ``region`` does not show ``cmap`` colours spread over the map (empty list: it does).

    The colormap is cut into 8 equal bins; a bin counts when it holds at least 2 % of the
    matching (sub-sampled) pixels. ``need_upper`` also asks for some pixels in the last three bins
    (viridis green/yellow, which no other colour in the viewer comes near; the most uncertain points).
    """
    x0, y0, x1, y1 = region
    pos = colormap_hits(rgb[y0:y1, x0:x1], cmap)
    hist = np.histogram(pos, bins=8, range=(0.0, 1.0))[0]
    bins = int((hist >= max(0.02 * len(pos), 1)).sum())
    failures = []
    if len(pos) < min_pixels:
        failures.append(f"{what}: {len(pos)} {cmap}-coloured pixels in {region}, expected >= {min_pixels}")
    if bins < min_bins:
        failures.append(f"{what}: {cmap} colours fill {bins}/8 bins of the map {hist.tolist()}, "
                        f"expected >= {min_bins}")
    if need_upper and hist[5:].sum() < max(10, 0.005 * len(pos)):
        failures.append(f"{what}: no upper-{cmap} colours (bins 6-8) {hist.tolist()}")
    return failures


PHASE_VIEW = "wrapped phase (rad)"


def phase_failures(rgb: np.ndarray, regions: dict[str, Rect]) -> list[str]:
    return colormap_failures(rgb, regions[PHASE_VIEW], "twilight", min_pixels=500, min_bins=6,
                             what="wrapped phase view")


def cloud_failures(rgb: np.ndarray, regions: dict[str, Rect]) -> list[str]:
    return colormap_failures(rgb, regions["point cloud"], "viridis", min_pixels=200, min_bins=4,
                             need_upper=True, what="point cloud view")


# -- colour bars ------------------------------------------------------------------------------
def _unit_template(unit: str) -> np.ndarray:
    """Grey crop of the unit title of a colour bar, as :func:`colorbar_image` draws it."""
    import cv2

    from gearscan.viewer.log import SCALES, colorbar_image

    scale = next(s for s in SCALES.values() if s.unit == unit)
    gray = cv2.cvtColor(colorbar_image(scale), cv2.COLOR_RGB2GRAY)
    top = gray[: gray.shape[0] // 8]  # the title sits above the bar
    rows, cols = np.nonzero(top < 128)
    return top[max(rows.min() - 2, 0):rows.max() + 3, max(cols.min() - 2, 0):cols.max() + 3]


def unit_score(rgb: np.ndarray, region: Rect, unit: str) -> float:
    """Best normalised correlation of ``unit``'s title with the region, over the scales the
    viewer may have drawn the bar at (it fits the bar image into the view)."""
    import cv2

    x0, y0, x1, y1 = region
    screen = cv2.cvtColor(np.ascontiguousarray(rgb[y0:y1, x0:x1]), cv2.COLOR_RGB2GRAY)
    template = _unit_template(unit)
    best = -1.0
    for s in np.arange(0.3, 1.6, 0.02):
        t = cv2.resize(template, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
        if t.shape[0] < 6 or t.shape[0] > screen.shape[0] or t.shape[1] > screen.shape[1]:
            continue
        best = max(best, float(cv2.matchTemplate(screen, t, cv2.TM_CCOEFF_NORMED).max()))
    return best


def colorbar_failures(rgb: np.ndarray, region: Rect, cmap: str, unit: str, *, what: str) -> list[str]:
    """Why ``region`` does not show a vertical ``cmap`` colour bar, high values on top, titled ``unit``."""
    x0, y0, x1, y1 = region
    failures = colormap_failures(rgb, region, cmap, min_pixels=100, min_bins=5, what=what)
    bands = np.linspace(y0, y1, 9).astype(int)
    medians = [np.median(p) for a, b in zip(bands[:-1], bands[1:], strict=True)
               if len(p := colormap_hits(rgb[a:b, x0:x1], cmap)) >= 5]
    if len(medians) < 4:
        failures.append(f"{what}: {cmap} colours in only {len(medians)}/8 horizontal bands")
    elif np.corrcoef(np.arange(len(medians)), medians)[0, 1] > -0.8:
        failures.append(f"{what}: colours do not run from the top of the map down {np.round(medians, 2).tolist()}")
    score = unit_score(rgb, region, unit)
    other = max(unit_score(rgb, region, u) for u in UNITS if u != unit)
    if score < 0.6 or score < other + 0.1:
        failures.append(f"{what}: unit {unit!r} not found (match {score:.2f}, other units {other:.2f})")
    return failures


UNITS = ("rad", "mm")
# colour bar key -> (colormap, unit, description)
COLOR_BARS = {
    "bar:legend/phase#0": ("twilight", "rad", "phase colour bar"),
    "bar:legend/error#0": ("magma", "rad", "error colour bar"),
    "bar:legend/sigma_rad#0": ("viridis", "rad", "phase uncertainty colour bar"),
    "bar:legend/sigma_mm#0": ("viridis", "mm", "depth uncertainty colour bar"),
}


def colorbars_failures(rgb: np.ndarray, regions: dict[str, Rect]) -> list[str]:
    return [f for key, (cmap, unit, what) in COLOR_BARS.items()
            for f in colorbar_failures(rgb, regions[key], cmap, unit, what=what)]


def viewer_failures(rgb: np.ndarray) -> list[str]:
    regions = view_regions(rgb)
    return phase_failures(rgb, regions) + cloud_failures(rgb, regions) + colorbars_failures(rgb, regions)


# -- the test -----------------------------------------------------------------------------------
@pytest.fixture
def rerun_home(tmp_path, monkeypatch):
    """rerun writes analytics under ``~/.config``: keep them in the test's temp dir."""
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv("RERUN_ANALYTICS", "0")  # not honoured by every version; HOME is what counts
    return home


def test_web_viewer_shows_phase_cloud_and_colour_bars_with_units(tmp_path, rerun_home):
    from gearscan.core.rig import default_rig
    from gearscan.inference.decoder import Decoder
    from gearscan.replay import replay
    from gearscan.twin.recordings import render_recording
    from gearscan.viewer.serve import serve_web

    recording = render_recording(tmp_path / "rec", rig=default_rig(256, 256), bursts=3, motion="uniform:0.6")
    viewer = serve_web()
    try:
        metrics = replay(recording, decoder=Decoder(classical=True), connect=viewer.grpc_url)
        assert metrics.bursts == 3
        assert all(row.get("cloud_points", 0) > 1000 for row in metrics.per_burst), metrics.per_burst
        with Chromium(WIDTH, HEIGHT) as browser:
            browser.navigate(viewer.web_url)
            rgb, png, failures, waited = browser.screenshot_until(viewer_failures, timeout=45.0, interval=4.0)
            ARTIFACTS.mkdir(exist_ok=True)
            (ARTIFACTS / "web_viewer.png").write_bytes(png)
            assert not failures, f"after {waited:.0f} s (screenshot {ARTIFACTS / 'web_viewer.png'}): " \
                                 f"{failures}; chromium log: {browser.log_tail(800)}"
    finally:
        viewer.close()
    assert viewer.process.poll() is not None

    # the checks discriminate: the same tests on other views of the same screenshot fail
    regions = view_regions(rgb)
    assert rgb.shape == (HEIGHT, WIDTH, 3)
    assert phase_failures(rgb, {PHASE_VIEW: regions["frame"]}), "grayscale frame view passed as phase"
    assert phase_failures(rgb, {PHASE_VIEW: regions["turntable (deg)"]})
    assert cloud_failures(rgb, {"point cloud": regions[PHASE_VIEW]}), "twilight phase passed as cloud"
    assert cloud_failures(rgb, {"point cloud": regions["total uncertainty (rad)"]})
    mm_bar, rad_bar = regions["bar:legend/sigma_mm#0"], regions["bar:legend/sigma_rad#0"]
    assert colorbar_failures(rgb, mm_bar, "viridis", "rad", what="mm bar"), "the mm bar passed as rad"
    assert colorbar_failures(rgb, rad_bar, "viridis", "mm", what="rad bar"), "the rad bar passed as mm"
    assert colorbar_failures(rgb, regions["bar:legend/phase#0"], "viridis", "rad", what="phase bar")
    assert colorbar_failures(rgb, regions["total uncertainty (rad)"], "viridis", "rad", what="image")
    # and a blank page fails them all
    blank = np.full_like(rgb, 255)
    assert phase_failures(blank, regions) and cloud_failures(blank, regions)
    assert len(colorbars_failures(blank, regions)) >= 3 * len(COLOR_BARS)
