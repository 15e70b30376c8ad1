"""The per-burst depth sigma, scaled by distance to the cloud's edge (recon/depth_sigma.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gearscan.core.patterns import PatternSet
from gearscan.core.phase import classical_result
from gearscan.core.types import Burst, Frame
from gearscan.recon.depth_sigma import (
    DEPTH_SIGMA_SCALES,
    EDGE_BANDS_PX,
    MOTION_CLASSES,
    NO_SCALES,
    TRAINED_SPAN_DEG,
    DepthSigmaScales,
    band_index,
    band_labels,
    check_scales,
    edge_distance,
    motion_class,
    scale_depth_sigma,
)
from gearscan.recon.measure import Reconstructor

PERIOD = 40.0


def test_edge_distance_is_euclidean_and_the_image_border_is_an_edge() -> None:
    keep = np.zeros((11, 11), bool)
    keep[2:9, 2:9] = True  # a 7 x 7 square
    d = edge_distance(keep)
    assert d[5, 5] == pytest.approx(4.0)  # the centre: four pixels to the first one outside
    assert d[2, 5] == pytest.approx(1.0) and d[0, 0] == 0.0
    assert d[3, 3] == pytest.approx(2.0, abs=1e-3)  # the diagonal is farther, but the edge is straight
    full = np.ones((5, 9), bool)
    assert edge_distance(full)[0, 4] == pytest.approx(1.0) and edge_distance(full)[2, 4] == pytest.approx(3.0)
    with pytest.raises(ValueError, match="2-D"):
        edge_distance(np.ones(5, bool))


def test_bands_split_at_their_bounds() -> None:
    d = np.array([0.0, 1.0, 1.4999, 1.5, 2.0, 2.5, 4.4, 4.5, 8.4, 8.5, 100.0])
    np.testing.assert_array_equal(band_index(d), [0, 0, 0, 1, 1, 2, 2, 3, 3, 4, 4])
    assert band_labels() == ["0-1.5 px", "1.5-2.5 px", "2.5-4.5 px", "4.5-8.5 px", "8.5-inf px"]
    assert check_scales(DEPTH_SIGMA_SCALES) == DEPTH_SIGMA_SCALES and set(DEPTH_SIGMA_SCALES.by_class) == set(MOTION_CLASSES)
    for scales in DEPTH_SIGMA_SCALES.by_class.values():
        assert len(scales) == len(EDGE_BANDS_PX) + 1
        assert all(s >= 1 for s in scales)  # a calibration may not shrink a sigma


@pytest.mark.parametrize("bad", [(1.0, 1.0), (1.0, 1.0, 1.0, 1.0, -2.0), (1.0, 1.0, math.nan, 1.0, 1.0),
                                 (1.0, 1.0, 1.0, 0.5, 1.0)])
def test_scales_that_are_not_one_positive_factor_per_band_are_refused(bad) -> None:
    with pytest.raises(ValueError, match="5 finite factors >= 1"):
        check_scales(bad)
    with pytest.raises(ValueError, match=r"\(network\): expected 5 finite factors >= 1"):
        check_scales({**DEPTH_SIGMA_SCALES.as_dict(), "network": bad})


def test_scales_per_class_name_every_class_and_a_flat_set_serves_all() -> None:
    flat = check_scales([2, 2, 1.5, 1, 1])
    assert flat == DepthSigmaScales.uniform((2.0, 2.0, 1.5, 1.0, 1.0)) and flat.is_uniform
    assert flat.describe() == "2/2/1.5/1/1"
    with pytest.raises(ValueError, match="one entry per motion class"):
        check_scales({"network": (1.0,) * 5})
    with pytest.raises(ValueError, match="expected factors"):
        check_scales("2,2,2,2,2")
    assert "network_fast" in DepthSigmaScales({c: (float(i + 1),) * 5 for i, c in enumerate(MOTION_CLASSES)}).describe()


def test_a_bursts_motion_class_is_its_decode_and_its_encoder_span() -> None:
    deg = math.radians
    assert motion_class((0.0, deg(0.6), deg(1.2)), from_network=False) == "three_step"  # a classical run too
    assert motion_class((0.0, 0.0, 0.0), from_network=True) == "network"
    assert motion_class((0.0, deg(0.1), deg(1.7)), from_network=True) == "network"  # the paper's, within training
    assert motion_class((deg(10), deg(9.4), deg(10 - TRAINED_SPAN_DEG)), from_network=True) == "network"  # backwards
    assert motion_class((0.0, deg(1), deg(2)), from_network=True) == "network_fast"
    assert motion_class((0.0, deg(1), deg(2 * TRAINED_SPAN_DEG)), from_network=True) == "network_fast"
    assert motion_class((0.0, deg(2), deg(4)), from_network=True) == "network_faster"
    assert motion_class((0.0, deg(-2), deg(-5)), from_network=True) == "network_faster"


def test_each_pixel_takes_its_bands_scale() -> None:
    keep = np.zeros((20, 20), bool)
    keep[1:19, 1:19] = True
    sigma = np.full(keep.shape, 0.01, np.float32)
    scales = (5.0, 4.0, 3.0, 2.0, 1.5)
    out = scale_depth_sigma(sigma, keep, scales)
    band = band_index(edge_distance(keep))
    np.testing.assert_allclose(out[keep], 0.01 * np.asarray(scales)[band[keep]], rtol=1e-6)
    assert {int(b) for b in band[keep]} == {0, 1, 2, 3, 4}  # every band is on this square
    assert scale_depth_sigma(sigma, keep, NO_SCALES) is sigma  # all ones: the raw sigma, untouched


def test_the_reconstructor_scales_each_points_sigma_by_its_band(clean_renderer, gear) -> None:
    """The same points with or without the scales; each sigma times its band's factor, the band read from the
    burst's own kept cloud."""
    angle = math.radians(3.0)
    frames, _ = clean_renderer.render(angle, PatternSet.three_step(PERIOD))
    burst = Burst(tuple(Frame(f, i, 1000 * i, i) for i, f in enumerate(frames)), (angle, angle, angle))
    result = classical_result(burst)
    scales = (3.0, 2.0, 1.5, 1.25, 1.1)
    raw = Reconstructor.for_gear(clean_renderer.rig, PERIOD, gear, depth_sigma_scales=NO_SCALES)(burst, result)
    scaled = Reconstructor.for_gear(clean_renderer.rig, PERIOD, gear, depth_sigma_scales=scales)(burst, result)
    np.testing.assert_array_equal(raw.cloud.pixels, scaled.cloud.pixels)
    np.testing.assert_array_equal(raw.cloud.points, scaled.cloud.points)
    keep = np.zeros(raw.valid.shape, bool)
    keep[raw.cloud.pixels[:, 0], raw.cloud.pixels[:, 1]] = True
    band = band_index(edge_distance(keep))[raw.cloud.pixels[:, 0], raw.cloud.pixels[:, 1]]
    np.testing.assert_allclose(scaled.cloud.sigma, raw.cloud.sigma * np.asarray(scales)[band], rtol=1e-5)
    assert (band == 0).any() and (band == 4).any()
    shipped = Reconstructor.for_gear(clean_renderer.rig, PERIOD, gear)(burst, result)  # three-step PS's class
    np.testing.assert_allclose(shipped.cloud.sigma,
                               raw.cloud.sigma * np.asarray(DEPTH_SIGMA_SCALES.by_class["three_step"])[band], rtol=1e-5)


def test_the_reconstructor_takes_the_scales_of_the_bursts_motion_class(clean_renderer, gear) -> None:
    """One phase map, read as the network's at three encoder spans and as three-step PS's: the same points, each
    sigma times its band's factor for the class the decode and the span name."""
    from dataclasses import replace

    angle = math.radians(3.0)
    frames, _ = clean_renderer.render(angle, PatternSet.three_step(PERIOD))
    per_class = {c: tuple(float(i + 1) + 0.1 * b for b in range(5)) for i, c in enumerate(MOTION_CLASSES)}
    rc = Reconstructor.for_gear(clean_renderer.rig, PERIOD, gear, depth_sigma_scales=per_class, network_support_px=None)
    raw_rc = Reconstructor.for_gear(clean_renderer.rig, PERIOD, gear, depth_sigma_scales=NO_SCALES, network_support_px=None)
    cases = {"three_step": (0.0, False), "network": (1.2, True), "network_fast": (3.0, True),
             "network_faster": (5.0, True)}
    for cls, (span_deg, net) in cases.items():
        angles = (angle, angle + math.radians(span_deg / 2), angle + math.radians(span_deg))
        burst = Burst(tuple(Frame(f, i, 1000 * i, i) for i, f in enumerate(frames)), angles)
        result = classical_result(burst)
        if net:
            result = replace(result, mode="deterministic")
        raw, scaled = raw_rc(burst, result), rc(burst, result)
        np.testing.assert_array_equal(raw.cloud.points, scaled.cloud.points)
        keep = np.zeros(raw.valid.shape, bool)
        keep[raw.cloud.pixels[:, 0], raw.cloud.pixels[:, 1]] = True
        band = band_index(edge_distance(keep))[raw.cloud.pixels[:, 0], raw.cloud.pixels[:, 1]]
        np.testing.assert_allclose(scaled.cloud.sigma, raw.cloud.sigma * np.asarray(per_class[cls])[band], rtol=1e-5,
                                   err_msg=cls)


def test_a_models_json_may_carry_its_own_scales() -> None:
    from gearscan.inference.model_io import ModelFileError
    from gearscan.inference.predictor import model_depth_sigma_scales

    assert model_depth_sigma_scales({}) is None
    assert model_depth_sigma_scales({"depth_sigma": {"scales": [3, 2.5, 2, 1.5, 1.0]}}) == (3.0, 2.5, 2.0, 1.5, 1.0)
    per_class = {c: [2, 2, 1.5, 1, 1] for c in MOTION_CLASSES}
    own = model_depth_sigma_scales({"depth_sigma": {"scales": per_class}})
    assert check_scales(own) == DepthSigmaScales.uniform((2.0, 2.0, 1.5, 1.0, 1.0))
    for bad in ({"scales": [2, 0.5]}, {"scales": "2"}, {"scales": [True, 2]}, [2, 2], {"scales": []},
                {"scales": {"network": [2, 0.5]}}, {"scales": {}}):
        with pytest.raises(ModelFileError, match="depth_sigma"):
            model_depth_sigma_scales({"depth_sigma": bad})


def test_replay_reconstructs_with_the_decoding_models_scales(tmp_path) -> None:
    """A model whose JSON names scales has its bursts' sigma scaled by them; three-step PS (no model) by the
    product's."""
    import shutil

    from gearscan.core.rig import default_rig
    from gearscan.inference.decoder import Decoder
    from gearscan.inference.model_io import read_config, write_config
    from gearscan.inference.predictor import DEFAULT_MODEL
    from gearscan.replay import replay
    from gearscan.twin.recordings import render_recording

    own = tmp_path / "own.safetensors"
    shutil.copy(DEFAULT_MODEL, own)
    meta = read_config(DEFAULT_MODEL)
    meta["depth_sigma"] = {"scales": [2.0, 2.0, 2.0, 2.0, 2.0], "edge_bands_px": list(EDGE_BANDS_PX), "chosen_by": "a test"}
    write_config(own, meta)
    rec = render_recording(tmp_path / "rec", rig=default_rig(64, 64), motion="uniform:0.6", bursts=1)
    mine = replay(rec, decoder=Decoder(own), truth=False)
    assert mine.recon["depth_sigma_scales"] == {c: [2.0] * 5 for c in MOTION_CLASSES}
    classical = replay(rec, decoder=Decoder(classical=True), truth=False)
    assert classical.recon["depth_sigma_scales"] == DEPTH_SIGMA_SCALES.as_dict()


def test_bursts_spanning_beyond_the_calibrated_span_are_counted_and_warned(clean_renderer, gear, caplog) -> None:
    """A network burst spanning more than CALIBRATED_SPAN_DEG gets network_faster's scales, which no val run measured
    there: the reconstructor counts it and warns once; three-step PS and the network within the span are not counted."""
    import logging
    from dataclasses import replace

    from gearscan.recon.depth_sigma import CALIBRATED_SPAN_DEG, sigma_calibrated

    angle = math.radians(3.0)
    frames, _ = clean_renderer.render(angle, PatternSet.three_step(PERIOD))
    rc = Reconstructor.for_gear(clean_renderer.rig, PERIOD, gear, network_support_px=None)

    def burst(span_deg: float) -> Burst:
        return Burst(tuple(Frame(f, i, 1000 * i, i) for i, f in enumerate(frames)),
                     (angle, angle + math.radians(span_deg / 2), angle + math.radians(span_deg)))

    with caplog.at_level(logging.WARNING, logger="gearscan.recon.measure"):
        for span, net in ((CALIBRATED_SPAN_DEG, True), (7.0, False), (6.0, True), (-8.0, True)):
            b = burst(span)
            result = classical_result(b)
            rc(b, replace(result, mode="deterministic") if net else result)
    assert rc.uncalibrated_bursts == 2
    assert len([r for r in caplog.records if "calibrated on val" in r.getMessage()]) == 1  # once, then counted
    assert sigma_calibrated((0.0, 0.0, math.radians(CALIBRATED_SPAN_DEG)), True)
    assert not sigma_calibrated((0.0, 0.0, math.radians(5.1)), True) and sigma_calibrated((0.0, 0.0, 1.0), False)


def test_the_products_scales_name_the_decode_they_were_chosen_for():
    """SCALES_CHOSEN_FOR is the shipped decode's fingerprint and the one the rule's run recorded; a network decode
    with its own scales uses those, another without borrows the product's, three-step PS reads no network."""
    import json
    from pathlib import Path

    from gearscan.inference.model_io import model_fingerprint
    from gearscan.inference.predictor import DEFAULT_MODEL
    from gearscan.recon.depth_sigma import SCALES_CHOSEN_FOR, depth_sigma_source

    run = json.loads((Path(__file__).resolve().parents[1] / "benchmarks" / "depth_sigma_val.json").read_text())
    assert SCALES_CHOSEN_FOR == run["model_fingerprint"] == model_fingerprint(DEFAULT_MODEL)
    other = "0123456789ab"
    assert depth_sigma_source(network=True, decode=SCALES_CHOSEN_FOR) == "product"
    assert depth_sigma_source(network=False) == "product"  # three-step PS reads no network
    assert depth_sigma_source(network=True, decode=other, own=True, own_chosen_for=other) == "model"
    assert depth_sigma_source(network=True, decode=other, own=True) == "model"  # a JSON that names no decode
    assert depth_sigma_source(network=True, decode=other, own=True, own_chosen_for=SCALES_CHOSEN_FOR) == "stale"
    assert depth_sigma_source(network=True, decode=other) == "borrowed"
    assert depth_sigma_source(network=True, decode=None) == "borrowed"  # a network decode of unknown files
    assert depth_sigma_source(network=True, mc=20, decode=SCALES_CHOSEN_FOR) == "product"  # the product's MC table
    assert depth_sigma_source(network=True, mc=20, decode=other, own=True, own_chosen_for=other) == "mc"
    assert depth_sigma_source(network=True, mc=20, decode=other) == "borrowed"
    # the default-rig option names the decode its own scales were chosen for
    option = DEFAULT_MODEL.with_name("default_rig.safetensors")
    entry = json.loads(option.with_suffix(".json").read_text())["depth_sigma"]
    assert entry["model_fingerprint"] == model_fingerprint(option)
