"""What the viewer logger writes, read back from the .rrd: float images in their units with
colormap and range (hover reads values), stats split by unit, a layout per mode, and a
warning for bursts without fringes."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from gearscan.core.types import Burst, Frame
from gearscan.inference.decoder import Decoder
from gearscan.viewer.log import (
    PLOTS,
    SCALES,
    RerunLogger,
    default_blueprint,
    fringe_problem,
    stat_path,
)


def read_rrd(path) -> dict[str, list[dict]]:
    """Entity path -> rows (column name -> python value) of the recording in an .rrd."""
    from rerun.chunk import RrdReader

    out: dict[str, list[dict]] = {}
    for chunk in RrdReader(str(path)).stream():
        batch = chunk.to_record_batch()
        rows = batch.to_pylist()
        out.setdefault(chunk.entity_path.lstrip("/"), []).extend(rows)
    return out


def depth_image(row: dict) -> np.ndarray:
    """The float32 values of a logged ``rr.DepthImage`` row."""
    fmt = row["DepthImage:format"][0]
    assert fmt["channel_datatype"] == 34  # rerun.encodings.ChannelDatatype.F32
    buf = np.frombuffer(bytes(row["DepthImage:buffer"][0]), np.float32)
    return buf.reshape(fmt["height"], fmt["width"])


def view_names(container) -> list[str]:
    from rerun.blueprint.containers import Horizontal, Vertical

    if isinstance(container, (Horizontal, Vertical)):
        return [n for child in container.contents for n in view_names(child)]
    return [container.name]


def ramp_burst(index: int, size: int = 128) -> Burst:
    """What Aravis's camera simulator sends: a diagonal ramp moving one grey level per frame."""
    y, x = np.mgrid[:size, :size]
    frames = tuple(Frame(((x + y + index + k) % 255).astype(np.uint8), index + k, (index + k) * 10**7,
                         pattern_index=k) for k in range(3))
    return Burst(frames, (0.0, 0.0, 0.0), index=index)


@pytest.fixture(scope="module")
def replayed(tmp_path_factory):
    """A 3-burst twin recording replayed into an .rrd, with what each burst measured."""
    from gearscan.core.rig import default_rig
    from gearscan.replay import replay
    from gearscan.twin.recordings import render_recording

    tmp = tmp_path_factory.mktemp("rrd")
    rec = render_recording(tmp / "rec", rig=default_rig(128, 128), bursts=3, motion="uniform:0.6")
    seen = {}
    replay(rec, decoder=Decoder(classical=True), save=tmp / "r.rrd",
           on_burst=lambda m, row: seen.__setitem__(m.burst.index, (m, row)))
    return read_rrd(tmp / "r.rrd"), seen


def test_rrd_holds_float_phase_and_sigma_in_their_units(replayed):
    data, seen = replayed
    assert len(seen) == 3
    units = {e: next(r["unit"][0] for r in data[e] if r.get("unit")) for e in SCALES}
    assert units["world/camera/phase"] == "rad" and units["world/camera/sigma/total"] == "rad"
    assert units["world/camera/sigma_mm"] == "mm" and units["world/camera/error"] == "rad"
    rows = {e: {r["burst"]: r for r in data[e] if r.get("DepthImage:buffer")} for e in SCALES}
    for index, (m, _) in seen.items():
        phase = depth_image(rows["world/camera/phase"][index])
        valid = np.isfinite(phase)
        assert 0.05 < valid.mean() < 0.95  # the gear's pixels; the rest is NaN (no value), not a colour
        np.testing.assert_array_equal(phase[valid], m.result.phase[valid].astype(np.float32))
        assert np.all(np.abs(phase[valid]) <= np.pi + 1e-6)
        sigma = depth_image(rows["world/camera/sigma/total"][index])
        np.testing.assert_array_equal(sigma[valid], m.result.sigma_total[valid].astype(np.float32))
        sigma_mm = depth_image(rows["world/camera/sigma_mm"][index])
        r, c = m.cloud.pixels.T
        np.testing.assert_allclose(sigma_mm[r, c], m.cloud.sigma, rtol=1e-6)  # each point's sigma at its pixel
        assert np.isfinite(sigma_mm).sum() == len(np.unique(r * 10**6 + c))
        assert 0 < np.nanmedian(sigma_mm) < 0.1  # mm: microns-to-tens-of-microns, not rad
    row = rows["world/camera/phase"][0]
    np.testing.assert_allclose(row["DepthImage:depth_range"][0], [-np.pi, np.pi])  # fixed range for the colormap
    assert row["DepthImage:colormap"][0] == 9  # rerun Colormap.Twilight (cyclic)
    assert rows["world/camera/sigma/total"][0]["DepthImage:colormap"][0] == 6  # Viridis
    # colour bars are logged (static images) and stats go to one plot per unit
    assert {"legend/phase", "legend/sigma_rad", "legend/sigma_mm", "legend/error"} <= set(data)
    stats = {e for e in data if e.startswith("stats/")}
    assert "stats/turntable_deg" in stats
    assert any(e.startswith("stats/accuracy_rad/") and e.endswith("_rad") for e in stats), stats
    assert any(e.startswith("stats/cloud_mm/") and e.endswith("_mm") for e in stats), stats
    assert not stats - {"stats/turntable_deg"} - {e for e in stats if e.startswith(("stats/accuracy_rad/",
                                                                                        "stats/cloud_mm/"))}
    assert "log/warnings" not in data  # fringes everywhere: no warning


def test_stats_are_split_by_unit():
    assert stat_path("rmse_rad") == ("accuracy_rad", "stats/accuracy_rad/rmse_rad")
    assert stat_path("cad_rms_mm") == ("cloud_mm", "stats/cloud_mm/cad_rms_mm")
    assert stat_path("latency_ms/infer") == ("latency_ms", "stats/latency_ms/infer")
    assert stat_path("dropped/infer") == ("dropped", "stats/dropped/infer")
    assert stat_path("points")[0] == "other"
    assert set(PLOTS) >= {"turntable_deg", "accuracy_rad", "cloud_mm", "latency_ms", "dropped"}


def test_layout_per_mode_live_has_no_error_panel(tmp_path, replayed):
    from gearscan.core.rig import default_rig

    _, seen = replayed
    m, _ = seen[0]
    logger = RerunLogger(save=tmp_path / "live.rrd")
    logger.log_rig(default_rig(128, 128))
    live_stats = {"cad_rms_mm": 0.01, "latency_ms/infer": 12.0, "dropped/infer": 0}
    logger.log_burst(m.burst, m.result, cloud=m.cloud, stats=live_stats)  # live: no truth, no error
    names = view_names(logger._blueprint.root_container)
    assert not any("error" in n for n in names), names
    assert [n for n in names if n in PLOTS.values()] == [PLOTS[p] for p in ("turntable_deg", "cloud_mm",
                                                                              "latency_ms", "dropped")]
    assert "wrapped phase (rad)" in names and "depth uncertainty (mm)" in names
    logger.log_burst(m.burst, m.result, cloud=m.cloud, error=np.zeros_like(m.result.phase), stats={"rmse_rad": 0.1})
    names = view_names(logger._blueprint.root_container)
    assert "|phase error| vs truth (rad)" in names and PLOTS["accuracy_rad"] in names
    logger.close()
    # each image panel is the float image next to its colour bar
    bp = view_names(default_blueprint(error=True).root_container)
    assert bp.count("rad") == 5 and bp.count("mm") == 1  # bars: phase, error, 3 x sigma (rad); depth sigma (mm)


def test_bursts_without_fringes_warn_in_the_viewer_and_on_the_console(tmp_path, replayed, caplog):
    _, seen = replayed
    decoder = Decoder(classical=True)
    assert "no fringe modulation" in fringe_problem(ramp_burst(7))
    assert all(fringe_problem(m.burst) is None for m, _ in seen.values())  # real fringes pass
    # modulated everywhere, but one phase everywhere (a lamp flickering with the patterns): no fringes either
    level = [np.full((64, 64), 128 + 100 * np.cos(0.3 + 2 * np.pi * k / 3)).astype(np.uint8) for k in range(3)]
    flat = Burst(tuple(Frame(img, k, k * 10**7, pattern_index=k) for k, img in enumerate(level)), (0.0, 0.0, 0.0))
    assert "phase is flat" in fringe_problem(flat)

    logger = RerunLogger(save=tmp_path / "sim.rrd")
    with caplog.at_level(logging.WARNING, logger="gearscan.viewer.log"):
        for i in range(3):
            b = ramp_burst(i)
            logger.log_burst(b, decoder(b))
        m, _ = seen[0]
        logger.log_burst(m.burst, m.result, cloud=m.cloud)
    logger.close()
    console = [r.getMessage() for r in caplog.records]
    assert len(console) == 2, console  # the first no-fringe burst, then the recovery (not one per burst)
    assert "burst 0: no fringe modulation" in console[0] and "fringes are back" in console[1]
    assert logger.no_fringe_bursts == 3
    assert "warnings" in view_names(logger._blueprint.root_container)
    logged = read_rrd(tmp_path / "sim.rrd")["log/warnings"]
    texts = [r["TextLog:text"][0] for r in logged]
    assert texts == console and all(r["TextLog:level"][0] == "WARN" for r in logged)


def test_pixels_without_a_point_are_shown_by_cause(replayed):
    """The depth panel's overlay marks unresolved and mixed pixels in their own classes: the pixels the
    reconstruction counted (Measurement.unwrap) are exactly the ones the viewer shows, none dropped unseen."""
    from gearscan.viewer.log import MASK_CLASSES

    data, seen = replayed
    rows = {r["burst"]: r for r in data["world/camera/masks/cloud"] if r.get("SegmentationImage:buffer")}
    mixed_total = 0
    for index, (m, _) in seen.items():
        fmt = rows[index]["SegmentationImage:format"][0]
        seg = np.frombuffer(bytes(rows[index]["SegmentationImage:buffer"][0]), np.uint8).reshape(fmt["height"], fmt["width"])
        assert set(np.unique(seg)) <= set(MASK_CLASSES)
        np.testing.assert_array_equal(seg == 2, m.unresolved)
        np.testing.assert_array_equal(seg == 3, m.mixed)
        assert (seg == 2).sum() == m.unwrap["unresolved"] and (seg == 3).sum() == m.unwrap["mixed"]
        r, c = m.cloud.pixels.T
        assert np.all(seg[r, c] == 0)  # a pixel with a point has a value
        mixed_total += m.unwrap["mixed"]
    assert mixed_total > 0  # the scene has silhouettes: the check sees something


def test_the_fused_legend_says_the_deviation_and_its_own_sigma():
    from gearscan.viewer.log import deviation_legend

    dev = np.array([-0.01, 0.0, 0.02, 0.03])
    text = deviation_legend(dev, 0.1, 12, sigma=np.full(4, 0.004), deviation_sigma=np.full(4, 0.003))
    assert "4 points fused from 12 bursts" in text and "Fused sigma: median 4.0 µm" in text
    assert "Deviation sigma (along the CAD's normal): median 3.0 µm" in text
    assert "Deviation sigma" not in deviation_legend(dev, 0.1, 12, sigma=np.full(4, 0.004))  # without the fit: none
