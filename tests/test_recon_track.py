"""The frame fit of a fused model (recon/track.py), scored against the twin's true surface."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from gearscan.core.recording import RecordingError, RecordingReader
from gearscan.core.rig import default_rig
from gearscan.inference.decoder import Decoder
from gearscan.recon.fuse import CloudFuser
from gearscan.recon.track import FIT_SIGMA_SCALE, REST_SIGMA_SCALE, TrackRefiner
from gearscan.twin.defects import GearDefects, true_mesh
from gearscan.twin.recordings import render_recording


def _scene(mesh) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


def _signed(scene, points: np.ndarray) -> np.ndarray:
    return scene.compute_signed_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def _rms_um(d: np.ndarray) -> float:
    return 1e3 * float(np.sqrt(np.mean(np.square(d))))


@pytest.fixture(scope="module")
def off_cad_turn(tmp_path_factory):
    """16 bursts at 0.6 deg/frame of a gear cut at module 2.06 whose recording keeps the 2.0 CAD,
    decoded by three-step PS (its motion error is the first pass's), fused, frames kept."""
    from gearscan.replay import replay

    rec = tmp_path_factory.mktemp("track") / "rec"
    render_recording(rec, rig=default_rig(192, 192), defects=GearDefects(module=2.06), motion="uniform:0.6",
                     bursts=16, start_deg=2.0)
    reader = RecordingReader(rec)
    refiner = TrackRefiner(reader.rig, reader.patterns.periods[0])
    metrics = replay(rec, decoder=Decoder(classical=True), fuse=CloudFuser(0.1, 3), truth=False,
                     on_burst=lambda m, _row: refiner.add(m))
    fitted, stats = refiner.refine_fused(metrics.fused)
    truth = _scene(true_mesh(reader.gear, GearDefects.from_meta(reader.meta)))
    return reader, refiner, metrics.fused, fitted, stats, truth


def test_fit_moves_the_fused_points_onto_the_true_surface(off_cad_turn):
    _, _, fused, fitted, stats, truth = off_cad_turn
    r = fitted.refined
    rows = fitted.voxel_index if fitted.voxel_index is not None else np.arange(len(fitted))
    assert stats["refined"] == int(r.sum())
    assert r.mean() > 0.6, f"only {r.mean():.0%} of the points fitted"
    fused = fused.select(np.isin(np.arange(len(fused)), rows))  # the fused points the fit kept, same rows
    before, after = _signed(truth, fused.points[r]), _signed(truth, fitted.points[r])
    # three-step's motion error survives fusion; the fit leaves camera noise
    assert _rms_um(before) > 80
    assert _rms_um(after) < 30 and _rms_um(after) < _rms_um(before) / 4
    # points not fitted stay exactly where fusion put them, with their bursts' sigma (no averaging credit), scaled
    np.testing.assert_array_equal(fitted.points[~r], fused.points[~r])
    np.testing.assert_allclose(fitted.sigma[~r], REST_SIGMA_SCALE * fused.sigma[~r] * np.sqrt(fused.bursts[~r]))
    # the fit's sigma is the size of its error (median |z| of a Gaussian: 0.67)
    z = np.abs(after) / fitted.sigma[r]
    assert 0.3 < np.median(z) < 2.0
    # sigma comes from each fit's own covariance and ranks the points: the better-determined half
    # is closer to the true surface than the other half, and no accepted fit is above the bound
    s = fitted.sigma[r]
    assert s.max() <= TrackRefiner(off_cad_turn[0].rig, 40.0).max_sigma_mm
    low = s <= np.median(s)
    assert _rms_um(after[low]) < 0.8 * _rms_um(after[~low])


def test_fit_keeps_the_deviation_from_the_cad(off_cad_turn):
    """The fit uses no CAD: a gear 0.4 mm off its CAD is measured off it by what the true surface is."""
    reader, _, _, fitted, _, truth = off_cad_turn
    pts = fitted.points[fitted.refined]
    cad = _scene(reader.gear.mesh())
    true_points = truth.compute_closest_points(o3d.core.Tensor(pts.astype(np.float32)))["points"].numpy()
    measured, actual = _signed(cad, pts), _signed(cad, true_points)
    assert np.median(np.abs(actual)) > 0.25  # the test means something: the gear is far off its CAD
    assert _rms_um(measured - actual) < 30
    assert np.percentile(np.abs(measured), 95) == pytest.approx(np.percentile(np.abs(actual), 95), rel=0.05)


def test_the_deviations_sigma_is_the_rays_sigma_along_the_cads_normal(off_cad_turn):
    """A fitted point's sigma runs along its ray; its deviation is read along the CAD's normal, so its standard error
    is the share of the sigma by which the distance changes along the ray, and it holds against the deviation the true
    surface has there. An unfitted point keeps its own sigma."""
    from gearscan.recon.deviation import CadScorer

    reader, _, _, fitted, _, truth = off_cad_turn
    r = fitted.refined
    cad = CadScorer(reader.gear)
    dsig = cad.deviation_sigma(fitted.points, fitted.sigma, fitted.ray, r)
    # the share is how fast the distance changes along the ray: a finite difference of the CAD distance says so
    h = 5e-3
    p, ray = fitted.points[r], fitted.ray[r]
    rate = np.abs(cad.distances(p + h * ray) - cad.distances(p - h * ray)) / (2 * h)
    share = dsig[r] / fitted.sigma[r]
    assert np.mean(np.abs(share - rate) < 0.01) > 0.95
    assert 0.3 < np.median(share) < 0.95 and share.std() > 0.05  # a spread of view angles, not one factor
    np.testing.assert_array_equal(dsig[~r], fitted.sigma[~r])  # unfitted: their own sigma
    no_ray = fitted.ray.copy()
    no_ray[np.flatnonzero(r)[:5]] = np.nan
    np.testing.assert_array_equal(cad.deviation_sigma(fitted.points, fitted.sigma, no_ray, r)[np.flatnonzero(r)[:5]],
                                  fitted.sigma[np.flatnonzero(r)[:5]])
    # against the truth: the deviation's error over its sigma, overall and at the most oblique views
    true_points = truth.compute_closest_points(o3d.core.Tensor(p.astype(np.float32)))["points"].numpy()
    err = cad.distances(p) - cad.distances(true_points)
    z = np.abs(err) / dsig[r]
    assert 0.3 < np.median(z) < 1.2, np.median(z)  # 0.67 for a right Gaussian sigma
    oblique = share < np.quantile(share, 0.25)
    assert np.median(z[oblique]) < 1.5, np.median(z[oblique])
    # replay writes it beside the deviation; a refit forgets it with the deviation
    fused = fitted.with_deviation(cad.distances(fitted.points), dsig)
    assert fused.select(r).deviation_sigma.shape == (int(r.sum()),)
    with pytest.raises(ValueError, match="deviation sigma"):
        fitted.with_deviation(cad.distances(fitted.points), dsig[:-1])
    assert off_cad_turn[1].refine_fused(fused)[0].deviation_sigma is None


def test_points_seen_in_too_few_frames_stay_where_they_were(off_cad_turn):
    reader, refiner, fused, _, _, _ = off_cad_turn
    few = TrackRefiner(reader.rig, reader.patterns.periods[0])
    few.bursts = refiner.bursts[:2]  # six frames: fewer than the fit's nine
    res = few.refine(fused.points)
    assert not res.refined.any()
    np.testing.assert_array_equal(res.points, fused.points)
    assert np.isinf(res.sigma).all()


def test_bad_input_is_named(off_cad_turn):
    reader, _, _, _, _, _ = off_cad_turn
    ref = TrackRefiner(reader.rig, reader.patterns.periods[0])
    with pytest.raises(ValueError, match="no bursts added"):
        ref.refine(np.zeros((4, 3)))
    ref.bursts = off_cad_turn[1].bursts[:1]
    with pytest.raises(ValueError, match=r"points: expected \(N, 3\)"):
        ref.refine(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="period_px"):
        TrackRefiner(reader.rig, 0.0)
    for bound in (0.0, -0.01, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="max_sigma_mm"):
            TrackRefiner(reader.rig, 40.0, max_sigma_mm=bound)
    for scale in (0.5, float("nan")):  # a scale may not shrink a sigma
        with pytest.raises(ValueError, match="rest_sigma_scale"):
            TrackRefiner(reader.rig, 40.0, rest_sigma_scale=scale)
    for settle in (0.0, -0.1, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="settle_rad"):
            TrackRefiner(reader.rig, 40.0, settle_rad=settle)


def test_replay_refuses_refinement_it_cannot_hold_before_replaying(off_cad_turn, monkeypatch):
    import gearscan.replay as replay_mod

    reader = off_cad_turn[0]
    monkeypatch.setattr(replay_mod, "REFINE_MAX_BYTES", 1024)
    with pytest.raises(RecordingError, match="refining keeps every frame in memory"):
        replay_mod.replay(reader.path, decoder=Decoder(classical=True), fuse=CloudFuser(0.1, 3), truth=False, refine=True)
    with pytest.raises(ValueError, match="fuse the replay too"):
        replay_mod.replay(reader.path, decoder=Decoder(classical=True), truth=False, refine=True)


def test_replay_fuse_writes_which_points_were_fitted(off_cad_turn, tmp_path):
    from typer.testing import CliRunner

    from gearscan.cli import app

    reader = off_cad_turn[0]
    out = tmp_path / "fused.csv"
    res = CliRunner().invoke(app, ["replay", str(reader.path), "--classical", "--no-truth", "--fuse", str(out),
                                   "--save", str(tmp_path / "r.rrd")])
    assert res.exit_code == 0, res.output
    assert "fitted to the raw frames" in res.output
    lines = res.output.splitlines()
    fused_line = next(x for x in lines if x.startswith("fused model:"))
    assert fused_line.endswith(str(out))  # the path ends its line; what the fit left out follows on the next
    assert any(x.startswith("Left out (unfitted points):") for x in lines)
    assert "fits had not settled at their last iteration" in res.output  # the settle test's count, said
    header = out.read_text().splitlines()[0].split(",")
    assert "refined" in header
    table = np.loadtxt(out, delimiter=",", skiprows=1)
    assert 0.6 < table[:, header.index("refined")].mean() < 1.0
    dsig, sig = table[:, header.index("deviation_sigma")], table[:, header.index("sigma_mm")]
    fit = table[:, header.index("refined")] == 1
    assert (dsig <= sig * (1 + 1e-5)).all() and np.median(dsig[fit] / sig[fit]) < 0.95  # the cosine's share, fitted
    np.testing.assert_allclose(dsig[~fit], sig[~fit], rtol=1e-5)  # unfitted: their own sigma
    # the direction each sigma runs along, with it: unit vectors from the camera
    ray = table[:, [header.index(f"ray_{a}") for a in "xyz"]]
    seen = np.isfinite(ray).all(axis=1)  # NaN: no burst saw the point
    assert seen.mean() > 0.99
    np.testing.assert_allclose(np.linalg.norm(ray[seen], axis=1), 1.0, atol=1e-5)


def test_each_point_carries_the_ray_its_sigma_runs_along(off_cad_turn):
    """The fit moves a point along one camera ray and its sigma is the standard error along it: measured along
    that ray, the error is as large as the sigma says; normal to the surface it is smaller (by the cosine)."""
    reader, refiner, fused, fitted, _, truth = off_cad_turn
    r = fitted.refined
    ray = fitted.ray
    assert ray.shape == (len(fitted), 3)
    seen = np.isfinite(ray).all(axis=1)  # NaN only where no burst saw the point: never a fitted one
    assert seen[r].all()
    np.testing.assert_allclose(np.linalg.norm(ray[seen], axis=1), 1.0, atol=1e-9)
    rows = fitted.voxel_index if fitted.voxel_index is not None else np.arange(len(fitted))
    moved = fitted.points[r] - fused.points[rows][r]
    assert np.abs(np.cross(moved, ray[r])).max() < 1e-6  # the fit moved each point along its ray
    # each ray leaves the camera: followed back from its point it passes the camera centre of some turntable angle
    # (in the gear frame the centre turns on a circle about the axis at its height)
    centre = refiner.rig.camera.center_world
    t = (fitted.points[seen, 2] - centre[2]) / ray[seen, 2]
    assert (t > 0).all()
    radius = np.linalg.norm((fitted.points[seen] - t[:, None] * ray[seen])[:, :2], axis=1)
    np.testing.assert_allclose(radius, np.linalg.norm(centre[:2]), rtol=1e-6)
    back = 1.0
    hit = truth.cast_rays(o3d.core.Tensor(np.concatenate([fitted.points[r] - back * ray[r], ray[r]], 1)
                                          .astype(np.float32)))["t_hit"].numpy()
    along = back - hit
    ok = np.abs(along) < 0.5
    assert ok.mean() > 0.95
    z_ray = np.abs(along[ok]) / fitted.sigma[r][ok]
    z_normal = np.abs(_signed(truth, fitted.points[r][ok])) / fitted.sigma[r][ok]
    assert 0.4 < np.median(z_ray) < 1.2, np.median(z_ray)  # a right Gaussian sigma: 0.67
    assert np.median(z_normal) < np.median(z_ray)


def test_points_off_the_fitted_surface_are_dropped_and_counted():
    """A plane of fitted points with unfitted ones on it (kept), 0.3 mm off it (dropped) and far from
    any fitted point (kept: nothing contradicts it)."""
    from gearscan.recon.track import off_surface

    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(0, 2, (400, 2)), rng.normal(0, 0.003, 400)]
    unfitted = np.array([[1.0, 1.0, 0.04], [1.2, 0.8, -0.3], [1.5, 1.5, 0.3], [9.0, 9.0, 0.5]])
    pts = np.r_[plane, unfitted]
    fitted = np.r_[np.ones(400, bool), np.zeros(4, bool)]
    off = off_surface(pts, fitted)
    assert off.tolist()[400:] == [False, True, True, False] and not off[:400].any()


def test_refine_fused_drops_the_off_surface_points_with_their_rows(off_cad_turn):
    _, refiner, fused, fitted, stats, truth = off_cad_turn
    assert len(fitted) == len(fused) - stats["off_surface"] - stats["uncertain"]
    rows = fitted.voxel_index if fitted.voxel_index is not None else np.arange(len(fitted))
    np.testing.assert_array_equal(fitted.points[~fitted.refined], fused.points[rows][~fitted.refined])


def test_refined_cloud_holds_no_point_above_the_sigma_bound_and_counts_the_rest(off_cad_turn):
    """The same bursts refined with a tighter bound: every kept point (fitted or not) is within it,
    and the unfitted points above it are dropped and counted, not moved."""
    reader, refiner, fused, loose, loose_stats, _ = off_cad_turn
    tight = TrackRefiner(reader.rig, reader.patterns.periods[0], max_sigma_mm=0.005)
    tight.bursts = refiner.bursts
    out, stats = tight.refine_fused(fused)
    assert out.sigma.max() <= 0.005 and loose.sigma.max() > 0.005
    assert stats["uncertain"] > loose_stats["uncertain"]
    assert len(out) == len(fused) - stats["off_surface"] - stats["uncertain"]
    rows = out.voxel_index if out.voxel_index is not None else np.arange(len(out))
    np.testing.assert_array_equal(out.points[~out.refined], fused.points[rows][~out.refined])


def test_replay_and_cli_take_a_bound_on_every_points_sigma(off_cad_turn, tmp_path):
    """``replay(point_sigma_mm=)`` / ``--max-point-sigma-um``: the user's bound on the fitted cloud's points, from the
    CLI to the written file (every point within it, the dropped counted and the note naming the bound); refused,
    named, where no fit runs or the value is not a sigma."""
    from typer.testing import CliRunner

    from gearscan.cli import app
    from gearscan.recon.track import MAX_POINT_SIGMA_MM
    from gearscan.replay import replay

    reader, _, _, _, loose_stats, _ = off_cad_turn
    assert loose_stats["sigma_bound_mm"] == MAX_POINT_SIGMA_MM
    out = tmp_path / "fused.csv"
    res = CliRunner().invoke(app, ["replay", str(reader.path), "--classical", "--no-truth", "--fuse", str(out),
                                   "--max-point-sigma-um", "5", "--save", str(tmp_path / "r.rrd")])
    assert res.exit_code == 0, res.output
    assert "with a sigma above the fit's bound (5 µm)" in res.output
    header = out.read_text().splitlines()[0].split(",")
    table = np.loadtxt(out, delimiter=",", skiprows=1)
    sigma = table[:, header.index("sigma_mm")]
    assert sigma.max() <= 0.005 and len(sigma) > 100
    def said(res) -> str:  # the error box's text on one line
        return " ".join(res.output.replace("│", " ").split())

    for args, hint in ((["--max-point-sigma-um", "5"], "give --fuse FILE"),  # no --fuse: no fit
                       (["--fuse", str(out), "--no-refine", "--max-point-sigma-um", "5"], "give --fuse FILE"),
                       (["--fuse", str(out), "--max-point-sigma-um", "inf"], "expected a finite sigma")):
        res = CliRunner().invoke(app, ["replay", str(reader.path), "--classical", "--no-truth", *args,
                                       "--save", str(tmp_path / "r.rrd")])
        assert res.exit_code == 2 and "--max-point-sigma-um" in said(res) and hint in said(res), res.output
    res = CliRunner().invoke(app, ["inspect", str(reader.path), "--classical", "--no-refine", "--max-point-sigma-um",
                                   "5", "-o", str(tmp_path / "report")])
    assert res.exit_code == 2 and "leave the frame fit on (no --no-refine)" in said(res), res.output
    for kwargs, match in (({"point_sigma_mm": 0.005}, "needs the frame fit"),
                          ({"point_sigma_mm": 0.0, "fuse": CloudFuser(0.1, 3), "refine": True}, "finite sigma > 0"),
                          ({"point_sigma_mm": float("nan"), "fuse": CloudFuser(0.1, 3), "refine": True}, "finite"),
                          ({"point_sigma_mm": 0.005, "fuse": CloudFuser(0.1, 3), "refine": True,
                            "refiner_factory": TrackRefiner}, "refiner_factory")):
        with pytest.raises(ValueError, match=match):
            replay(reader.path, decoder=Decoder(classical=True), truth=False, **kwargs)


def test_unfitted_points_carry_the_scaled_sigma_and_fitted_points_keep_the_fits(off_cad_turn):
    """``rest_sigma_scale`` multiplies the sigma of the points the fit cannot take (their bursts' sigma without
    credit for averaging), so more of them fall above the bound; the fitted points do not change."""
    reader, refiner, fused, _, _, _ = off_cad_turn
    runs = {}
    for scale in (1.0, 3.0):
        ref = TrackRefiner(reader.rig, reader.patterns.periods[0], rest_sigma_scale=scale, max_sigma_mm=1.0)
        ref.bursts = refiner.bursts
        runs[scale] = ref.refine_fused(fused)
    (one, _), (three, _) = runs[1.0], runs[3.0]
    assert (~one.refined).sum() > 0 and one.refined.sum() > 0
    for out, scale in ((one, 1.0), (three, 3.0)):
        rows = out.voxel_index if out.voxel_index is not None else np.arange(len(out))
        rest = ~out.refined
        np.testing.assert_allclose(out.sigma[rest], scale * fused.sigma[rows][rest] * np.sqrt(fused.bursts[rows][rest]))
    np.testing.assert_array_equal(one.points[one.refined], three.points[three.refined])
    np.testing.assert_array_equal(one.sigma[one.refined], three.sigma[three.refined])
    # under the product's 30 um bound: the unfitted points kept at scale 1 whose sigma x the product's scale exceeds it
    # leave the cloud
    bound = TrackRefiner(reader.rig, 40.0).max_sigma_mm
    outs = {}
    for scale in (1.0, REST_SIGMA_SCALE):
        ref = TrackRefiner(reader.rig, reader.patterns.periods[0], rest_sigma_scale=scale)
        ref.bursts = refiner.bursts
        outs[scale] = ref.refine_fused(fused)
    (kept1, stats1), (kept35, stats35) = outs[1.0], outs[REST_SIGMA_SCALE]
    leaving = ~kept1.refined & (kept1.sigma * REST_SIGMA_SCALE > bound)
    assert leaving.any()
    assert stats35["uncertain"] == stats1["uncertain"] + int(leaving.sum())
    assert len(kept35) == len(kept1) - int(leaving.sum()) and kept35.sigma.max() <= bound


def test_fit_sigma_scale_multiplies_the_fits_sigma_and_the_bound_judges_the_scaled_one(off_cad_turn):
    """``fit_sigma_scale`` multiplies each fit's standard error; a fit whose scaled sigma passes the bound no more
    does not take its point, and a scale that would shrink a sigma is refused."""
    reader, refiner, fused, _, _, _ = off_cad_turn
    outs = {}
    for scale in (1.0, 2.0):
        ref = TrackRefiner(reader.rig, reader.patterns.periods[0], fit_sigma_scale=scale)
        ref.bursts = refiner.bursts
        outs[scale] = ref.refine(fused.points)
    one, two = outs[1.0], outs[2.0]
    both = one.refined & two.refined
    assert both.sum() > 100
    np.testing.assert_allclose(np.median(two.sigma[both] / one.sigma[both]), 2.0, rtol=1e-9)
    bound = refiner.max_sigma_mm
    assert two.sigma[two.refined].max() <= bound
    lost = one.refined & ~two.refined
    assert lost.any() and np.median(one.sigma[lost]) > bound / 2 > np.median(one.sigma[one.refined])
    for bad in (0.9, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="fit_sigma_scale"):
            TrackRefiner(reader.rig, 40.0, fit_sigma_scale=bad)


def test_the_product_scales_the_unfitted_points_sigma(tmp_path):
    """The refiner the replay builds carries the val-calibrated scale (benchmarks/rest_sigma_rule.md)."""
    from gearscan.replay import make_refiner

    render_recording(tmp_path / "rec", rig=default_rig(64, 64), motion="static", bursts=1)
    reader = RecordingReader(tmp_path / "rec")
    refiner = make_refiner(reader, reader.rig, reader.patterns.periods[0], CloudFuser(0.1, 3))
    assert refiner.rest_sigma_scale == REST_SIGMA_SCALE == 1.5
    assert refiner.fit_sigma_scale == FIT_SIGMA_SCALE



def test_settle_test_refuses_the_fits_still_moving_at_the_last_iteration(off_cad_turn):
    """The settle test acts at the last iteration only: the fits it refuses are exactly those counted unsettled, the
    fits it keeps are unchanged, and the refused points fall back to their fused position and the unfitted sigma.
    With a tight test, the points still moving are the ones farther from the true surface."""
    reader, refiner, fused, _, _, truth = off_cad_turn
    runs = {}
    for settle in (None, 0.3, 1e-3):  # the modulation test off: one test at a time
        ref = TrackRefiner(reader.rig, reader.patterns.periods[0], settle_rad=settle, modulation_ratio=None,
                           shading="drift")  # one model: the lambert one hands what it refuses to the drift fit
        ref.bursts = refiner.bursts
        runs[settle] = ref.refine(fused.points)
    free = runs[None]
    assert free.stats["unsettled"] == 0
    for settle in (0.3, 1e-3):
        res = runs[settle]
        assert res.stats["refined"] + res.stats["unsettled"] == free.stats["refined"]
        assert not (res.refined & ~free.refined).any()
        np.testing.assert_array_equal(res.points[res.refined], free.points[res.refined])
        np.testing.assert_array_equal(res.points[~res.refined], fused.points[~res.refined])
        assert np.isinf(res.sigma[~res.refined]).all()
    tight = runs[1e-3]
    refused = free.refined & ~tight.refined
    assert 0 < refused.sum() < free.refined.sum()
    err = np.abs(_signed(truth, free.points))
    # on this turn (session 47): 6.3 against 2.9 um
    assert np.median(err[refused]) > 1.5 * np.median(err[tight.refined])
    with pytest.raises(ValueError, match="iterations >= 2"):
        TrackRefiner(reader.rig, 40.0, settle_rad=0.1, iterations=1)


@pytest.mark.parametrize("shading", ["drift", "lambert"])
def test_settle_counts_add_up_over_chunks(off_cad_turn, monkeypatch, shading):
    """Chunked or whole, the same fits and counts (lambert's normals come from the whole cloud)."""
    import gearscan.recon.track as track

    reader, refiner, fused, _, _, _ = off_cad_turn
    ref = TrackRefiner(reader.rig, reader.patterns.periods[0], settle_rad=0.1, shading=shading)
    ref.bursts = refiner.bursts
    whole = ref.refine(fused.points)
    monkeypatch.setattr(track, "_CHUNK", len(fused) // 3 + 1)
    chunked = ref.refine(fused.points)
    assert whole.stats["unsettled"] > 0
    assert chunked.stats["unsettled"] == whole.stats["unsettled"]
    assert chunked.stats["drift_fallback"] == whole.stats["drift_fallback"]
    np.testing.assert_array_equal(chunked.refined, whole.refined)
    np.testing.assert_allclose(chunked.points, whole.points, atol=1e-9)


def test_replay_fits_with_the_refiner_its_factory_builds(off_cad_turn):
    """``replay(refiner_factory=)``: the rule scripts' candidates run through the same replay as the product."""
    from functools import partial

    from gearscan.replay import replay

    reader, _, _, _, _, _ = off_cad_turn
    runs = {settle: replay(reader.path, decoder=Decoder(classical=True), fuse=CloudFuser(0.1, 3), truth=False,
                           refine=True, refiner_factory=partial(TrackRefiner, settle_rad=settle,
                                                                modulation_ratio=None, shading="drift")).refine
            for settle in (None, 1e-3)}
    assert runs[None]["unsettled"] == 0 and runs[1e-3]["unsettled"] > 0
    assert runs[1e-3]["refined"] + runs[1e-3]["unsettled"] == runs[None]["refined"]


def test_modulation_test_refuses_fits_with_an_impossible_fringe(off_cad_turn):
    """``modulation_ratio``: a fit whose modulation exceeds that share of its mean intensity is refused and counted
    (``implausible``), the other fits are kept bit for bit; a ratio below what real fringes show (B/A about 0.85 on
    the twin) refuses most fits, which is how the test is seen to act."""
    reader, refiner, fused, _, _, _ = off_cad_turn
    runs = {}
    for ratio in (None, 0.5):
        ref = TrackRefiner(reader.rig, reader.patterns.periods[0], modulation_ratio=ratio, shading="drift")
        ref.bursts = refiner.bursts
        runs[ratio] = ref.refine(fused.points)
    free, tight = runs[None], runs[0.5]
    assert free.stats["implausible"] == 0 and tight.stats["implausible"] > free.stats["refined"] // 2
    assert tight.stats["refined"] + tight.stats["implausible"] == free.stats["refined"]
    np.testing.assert_array_equal(tight.points[tight.refined], free.points[tight.refined])
    np.testing.assert_array_equal(tight.points[~tight.refined], fused.points[~tight.refined])
    for ratio in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="modulation_ratio"):
            TrackRefiner(reader.rig, 40.0, modulation_ratio=ratio)


def test_replay_fits_with_the_decoding_models_rest_sigma_scale(off_cad_turn):
    """A model's own rest-sigma scale (its JSON's ``rest_sigma``, read by the Decoder) is what the frame fit of a fused
    replay multiplies its unfitted points' sigma by, with or without a point-sigma bound and through a rule script's
    factory; replay's metrics record it and whose it is (``model`` when chosen for this decode, ``stale`` when chosen
    for another, ``product`` when the model names none); the unfitted points' sigma scales with it."""
    from functools import partial

    from gearscan.recon.track import REST_SIGMA_SCALE
    from gearscan.replay import replay

    reader, _, _, _, _, _ = off_cad_turn

    class Own(Decoder):  # three-step PS's decode, with a model's own scale and the decode it was chosen for
        def __init__(self, scale, chosen_for):
            super().__init__(classical=True)
            self._scale, self._for = scale, chosen_for

        rest_sigma_scale = property(lambda self: self._scale)
        rest_sigma_chosen_for = property(lambda self: self._for)
        model_fingerprint = property(lambda self: "abc")

    def run(decoder, **kw):
        return replay(reader.path, decoder=decoder, fuse=CloudFuser(0.1, 3), truth=False, refine=True, **kw)

    product, own = run(Own(None, None)), run(Own(2.5, "abc"))
    assert (product.recon["rest_sigma_scale"], product.recon["rest_sigma_source"]) == (REST_SIGMA_SCALE, "product")
    assert (own.recon["rest_sigma_scale"], own.recon["rest_sigma_source"]) == (2.5, "model")
    assert run(Own(2.5, "other")).recon["rest_sigma_source"] == "stale"
    assert run(Own(2.5, None)).recon["rest_sigma_source"] == "model"  # naming no decode: trusted, as depth scales
    assert run(Own(2.5, "abc"), point_sigma_mm=0.05).recon["rest_sigma_scale"] == 2.5
    assert run(Own(2.5, "abc"), refiner_factory=partial(TrackRefiner, settle_rad=None)).recon["rest_sigma_scale"] == 2.5
    with pytest.raises(ValueError, match="may not set rest_sigma_scale"):  # it would be overridden silently
        run(Own(2.5, "abc"), refiner_factory=partial(TrackRefiner, rest_sigma_scale=1.0))
    # the unfitted points carry the model's scale: at 2.5 the fit's sigma bound keeps exactly those whose sigma at the
    # product's scale times 2.5 / 1.5 stays within it, with that sigma
    bound = TrackRefiner.__init__.__kwdefaults__["max_sigma_mm"]
    unfitted = {k: np.sort(m.fused.sigma[~m.fused.refined]) for k, m in (("product", product), ("own", own))}
    assert unfitted["product"].size > 0 and unfitted["own"].size > 0
    scaled = unfitted["product"] * 2.5 / REST_SIGMA_SCALE
    assert (scaled <= bound * (1 - 1e-6)).sum() <= unfitted["own"].size <= (scaled <= bound * (1 + 1e-6)).sum()
    np.testing.assert_allclose(unfitted["own"], scaled[:unfitted["own"].size], rtol=1e-5)


def test_lambert_shading_fits_the_phase_exactly_where_a_linear_drift_is_biased():
    """Samples of a point as the twin renders them, ``I = a + g (b + B cos(psi + eps))``, with the projector's
    irradiance ``g`` falling off as cos(incidence) over the frames that see the point: the ``"lambert"`` design
    (``g`` known per sample) recovers ``eps`` to rounding, while the linear drift model cannot follow ``g`` and
    leaves a phase bias of millirad (several um on the default rig), the same for every point sampled alike."""
    from gearscan.recon.track import _fit

    bursts = 16
    worst = {"drift": 0.0, "lambert": 0.0}
    for speed in (2.0, 9.0, 20.0):  # rad of fringe phase per rad of turn
        tau = np.repeat(np.linspace(-0.7, 0.7, bursts), 3) + np.tile([0.0, 0.0105, 0.021], bursts)
        psi = speed * tau + np.tile([0.0, 2 * np.pi / 3, 4 * np.pi / 3], bursts)
        g = np.clip(np.cos(1.6 * tau + 0.4), 0.0, None)
        for eps in np.linspace(0.0, 2 * np.pi, 8, endpoint=False):
            val = 6.0 + g * (100.0 + 95.0 * np.cos(psi + eps))
            for name, gain in (("drift", None), ("lambert", g)):
                sol, res_sd, count, spread, _ = _fit(np.zeros(len(psi), int), val, psi, tau, 1, 1, gain)
                assert count[0] == len(psi) and spread[0] > 0.5
                err = abs(np.angle(np.exp(1j * (np.arctan2(sol[0, 2], sol[0, 1]) - eps))))
                worst[name] = max(worst[name], err)
    assert worst["lambert"] < 1e-8
    assert worst["drift"] > 3e-3


def test_quadratic_shading_follows_a_curved_shading_without_a_surface_model():
    """The same samples, no normal known: a shading quadratic in the turn angle is fitted exactly by the
    ``"quadratic"`` design, and the twin's cos(incidence) fall-off leaves it a bias several times below the linear
    drift's (the cosine's curvature is what the line cannot follow)."""
    from gearscan.recon.track import _fit

    bursts = 16
    worst = {1: 0.0, 2: 0.0}
    for speed in (2.0, 9.0, 20.0):  # rad of fringe phase per rad of turn
        tau = np.repeat(np.linspace(-0.7, 0.7, bursts), 3) + np.tile([0.0, 0.0105, 0.021], bursts)
        psi = speed * tau + np.tile([0.0, 2 * np.pi / 3, 4 * np.pi / 3], bursts)
        for eps in np.linspace(0.0, 2 * np.pi, 8, endpoint=False):
            parabola = 1.0 - 0.5 * (1.6 * tau + 0.4) ** 2
            sol, *_ = _fit(np.zeros(len(psi), int), 6.0 + parabola * (100.0 + 95.0 * np.cos(psi + eps)), psi, tau, 1, 2)
            assert abs(np.angle(np.exp(1j * (np.arctan2(sol[0, 2], sol[0, 1]) - eps)))) < 1e-8
            val = 6.0 + np.clip(np.cos(1.6 * tau + 0.4), 0.0, None) * (100.0 + 95.0 * np.cos(psi + eps))
            for degree in worst:
                sol, *_ = _fit(np.zeros(len(psi), int), val, psi, tau, 1, degree)
                err = abs(np.angle(np.exp(1j * (np.arctan2(sol[0, 2], sol[0, 1]) - eps))))
                worst[degree] = max(worst[degree], err)
    assert worst[1] > 3e-3
    assert worst[2] < worst[1] / 4


def test_mixed_fit_is_each_points_own_degree():
    """``_fit_degrees``: the points chosen quadratic get exactly the degree-2 fit of their samples, the others the
    degree-1 fit (coefficients in degree 2's columns, zero beyond degree 1's six), whatever the other points' samples."""
    from gearscan.recon.track import _fit, _fit_degrees

    rng = np.random.default_rng(5)
    n, per = 6, 60
    idx = np.repeat(np.arange(n), per)
    tau = rng.uniform(-0.6, 0.6, idx.size)
    psi = rng.uniform(0, 2 * np.pi, idx.size)
    val = 80 + 30 * tau**2 + (60 - 20 * tau) * np.cos(psi + idx) + rng.normal(0, 1.0, idx.size)
    quad = np.array([True, False, True, False, False, True])
    coef, res_sd, count, spread, sig = _fit_degrees(idx, val, psi, tau, n, quad)
    for degree, mine in ((1, ~quad), (2, quad)):
        ref = _fit(idx, val, psi, tau, n, degree)
        width = ref[0].shape[1]
        np.testing.assert_allclose(coef[mine, :width], ref[0][mine], rtol=1e-9, atol=1e-9)
        assert not coef[mine, width:].any()
        for got, want in zip((res_sd, count, spread, sig), ref[1:], strict=True):
            np.testing.assert_allclose(got[mine], want[mine], rtol=1e-9)
    assert (sig[quad] > 0).all() and np.isfinite(sig).all()


def test_mixed_shading_takes_the_quadratic_fit_where_its_samples_carry_it(off_cad_turn):
    """``shading="mixed"`` on the same frames and fused cloud: each point is fitted with the quadratic shading where its
    phase's standard error stays within ``mixed_sigma_ratio`` of the drift fit's, the drift shading elsewhere. The
    points land on the true surface as drift's do, and a ratio no fit can meet leaves every point to drift."""
    reader, refiner, fused, _, _, truth = off_cad_turn

    def fit(**kwargs):
        ref = TrackRefiner(reader.rig, reader.patterns.periods[0], **kwargs)
        ref.bursts = refiner.bursts
        return ref.refine(fused.points)

    drift, mixed = fit(shading="drift"), fit(shading="mixed")
    r = mixed.refined
    assert r.mean() > 0.6, f"only {r.mean():.0%} of the points fitted"
    share = mixed.stats["quadratic_points"] / mixed.stats["refined"]
    assert 0.05 < share < 0.995, f"{share:.1%} of the fitted points quadratic: the choice chose nothing"
    both = r & drift.refined
    assert _rms_um(_signed(truth, mixed.points[both])) <= 1.05 * _rms_um(_signed(truth, drift.points[both]))
    z = np.abs(_signed(truth, mixed.points[r])) / mixed.sigma[r]
    assert 0.3 < np.median(z) < 2.0
    never = fit(shading="mixed", mixed_sigma_ratio=1e-6)  # the quadratic fit's sigma is never a millionth of drift's
    assert never.stats["quadratic_points"] == 0
    np.testing.assert_allclose(never.points, drift.points, atol=1e-9)
    np.testing.assert_array_equal(never.refined, drift.refined)
    assert drift.stats["quadratic_points"] == 0


def test_lambert_fit_moves_the_fused_points_onto_the_true_surface(off_cad_turn):
    """``shading="lambert"`` on the same frames and fused cloud: the points land on the true surface as the drift
    model's do, and its modulation test (taken at the point's mean irradiance) refuses next to none of them."""
    reader, refiner, fused, _, _, truth = off_cad_turn
    ref = TrackRefiner(reader.rig, reader.patterns.periods[0], shading="lambert")
    ref.bursts = refiner.bursts
    res = ref.refine(fused.points)
    r = res.refined
    assert r.mean() > 0.6, f"only {r.mean():.0%} of the points fitted"
    assert res.stats["implausible"] < 0.01 * res.stats["refined"]
    before, after = _signed(truth, fused.points[r]), _signed(truth, res.points[r])
    assert _rms_um(after) < 30 and _rms_um(after) < _rms_um(before) / 4
    z = np.abs(after) / res.sigma[r]
    assert 0.3 < np.median(z) < 2.0
    np.testing.assert_array_equal(res.points[~r], fused.points[~r])
    # the same cloud and frames, the drift model: lambert is no worse
    drift_fit = TrackRefiner(reader.rig, reader.patterns.periods[0], shading="drift")
    drift_fit.bursts = refiner.bursts
    drift = drift_fit.refine(fused.points)
    both = r & drift.refined
    assert _rms_um(_signed(truth, res.points[both])) <= 1.05 * _rms_um(_signed(truth, drift.points[both]))


def test_shading_settings_are_checked():
    rig = default_rig(64, 64)
    for bad in ("phong", "", None):
        with pytest.raises(ValueError, match="shading"):
            TrackRefiner(rig, 40.0, shading=bad)
    for radius in (0.0, -0.3, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="normal_radius_mm"):
            TrackRefiner(rig, 40.0, normal_radius_mm=radius)
    for cos in (-0.1, 1.0, float("nan")):
        with pytest.raises(ValueError, match="min_incidence_cos"):
            TrackRefiner(rig, 40.0, min_incidence_cos=cos)
    for ratio in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="mixed_sigma_ratio"):
            TrackRefiner(rig, 40.0, shading="mixed", mixed_sigma_ratio=ratio)
    with pytest.raises(ValueError, match="needs drift=True"):
        TrackRefiner(rig, 40.0, shading="mixed", drift=False)


def test_replay_and_cli_take_the_frame_fits_shading(off_cad_turn, tmp_path):
    """``replay(shading=)`` / ``--frame-fit-shading``: the fit runs with the named model (its stats say which) and
    together with a point-sigma bound; refused, named, before anything runs where no fit runs or the name is unknown."""
    from typer.testing import CliRunner

    from gearscan.cli import app
    from gearscan.recon.track import SHADING
    from gearscan.replay import replay

    reader, _, _, _, stats, _ = off_cad_turn
    assert stats["shading"] == SHADING
    for shading in ("drift", "lambert", "mixed"):
        m = replay(reader.path, decoder=Decoder(classical=True), truth=False, fuse=CloudFuser(0.1, 3), refine=True,
                   shading=shading, point_sigma_mm=0.02)
        assert m.refine["shading"] == shading and m.refine["sigma_bound_mm"] == 0.02
        assert m.fused.sigma.max() <= 0.02 and m.fused.refined.mean() > 0.5
        assert (m.refine["quadratic_points"] > 0) == (shading == "mixed")

    def said(res) -> str:
        return " ".join(res.output.replace("│", " ").split())

    out = tmp_path / "fused.csv"
    for args, hint in ((["--frame-fit-shading", "lambert"], "give --fuse FILE"),
                       (["--fuse", str(out), "--frame-fit-shading", "phong"], "expected one of drift, lambert")):
        res = CliRunner().invoke(app, ["replay", str(reader.path), "--classical", "--no-truth", *args,
                                       "--save", str(tmp_path / "r.rrd")])
        assert res.exit_code == 2 and "--frame-fit-shading" in said(res) and hint in said(res), res.output
        assert not out.exists() and not (tmp_path / "r.rrd").exists()  # refused before anything ran
    res = CliRunner().invoke(app, ["inspect", str(reader.path), "--classical", "--no-refine", "--frame-fit-shading",
                                   "drift", "-o", str(tmp_path / "report")])
    assert res.exit_code == 2 and "leave the frame fit on (no --no-refine)" in said(res), res.output
    for kwargs, match in (({"shading": "lambert"}, "needs the fit"),
                          ({"shading": "phong", "fuse": CloudFuser(0.1, 3), "refine": True}, "expected one of"),
                          ({"shading": "drift", "fuse": CloudFuser(0.1, 3), "refine": True,
                            "refiner_factory": TrackRefiner}, "refiner_factory")):
        with pytest.raises(ValueError, match=match):
            replay(reader.path, decoder=Decoder(classical=True), truth=False, **kwargs)


def test_lambert_gain_is_the_irradiance_the_twin_renders():
    """The fit's per-sample irradiance (``_samples`` with normals) is the twin's own: cos(incidence) of the projector
    ray on the true normal, over distance squared, at the burst's turn angle (gear frame to world by the encoder);
    a normal facing away, or a NaN one (no plane), gets none."""
    from gearscan.core.gear import GearSpec
    from gearscan.core.rig import rot_z
    from gearscan.recon.track import _BurstView
    from gearscan.twin.render import TwinRenderer

    rig, gear = default_rig(96, 96), GearSpec()
    renderer = TwinRenderer(rig, gear)
    angle = 0.4
    surf = renderer.surface(angle)
    pick = surf.lit & (surf.cos_incidence > 0.3)
    cam_pts = surf.points_cam[pick]
    gear_from_cam = np.linalg.inv(rig.camera.T_from_world @ rot_z(angle))
    pts = cam_pts @ gear_from_cam[:3, :3].T + gear_from_cam[:3, 3]
    mesh = o3d.t.geometry.TriangleMesh.from_legacy(gear.mesh())
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    normals = scene.compute_closest_points(o3d.core.Tensor(pts.astype(np.float32)))["primitive_normals"].numpy()
    normals = normals.astype(np.float64)
    ref = TrackRefiner(rig, 40.0, shading="lambert", min_incidence_cos=0.0)
    h, w = rig.camera.height, rig.camera.width
    ref.bursts = [_BurstView(np.zeros((3, h, w), np.uint8), np.full(3, angle), np.full((h, w), np.nan, np.float32),
                             np.zeros(3))]
    n = len(pts)
    bounds = np.array([0, n])
    rays = np.tile([1.0, 0.0, 0.0], (n, 1))
    gain = ref._samples(pts, np.arange(n), bounds, 0, rays, normals)[5]
    world = pts @ rot_z(angle)[:3, :3].T
    dist = np.linalg.norm(rig.projector.center_world - world, axis=1)
    d_ref = float(np.linalg.norm(rig.projector.center_world))
    assert n > 200
    np.testing.assert_allclose(gain * (dist / d_ref) ** 2, surf.cos_incidence[pick], atol=2e-3)
    assert not ref._samples(pts, np.arange(n), bounds, 0, rays, -normals)[5].any()
    assert not ref._samples(pts, np.arange(n), bounds, 0, rays, np.full_like(normals, np.nan))[5].any()


def test_lambert_hands_the_points_it_cannot_take_to_the_drift_fit(off_cad_turn):
    """A point the lambert fit leaves (too few steeply lit samples, no normal) is fitted exactly as the drift model
    alone fits it, so lambert fits every point drift does, and ``drift_fallback`` counts the handed-over ones."""
    reader, refiner, fused, _, _, _ = off_cad_turn
    runs = {}
    for shading in ("drift", "lambert"):
        ref = TrackRefiner(reader.rig, reader.patterns.periods[0], shading=shading)
        ref.bursts = refiner.bursts
        runs[shading] = ref.refine(fused.points)
    drift, lam = runs["drift"], runs["lambert"]
    assert not (drift.refined & ~lam.refined).any()
    assert drift.stats["drift_fallback"] == 0
    handed = lam.refined & drift.refined & (lam.points == drift.points).all(1) & (lam.sigma == drift.sigma)
    assert 0 < lam.stats["drift_fallback"] == handed.sum() < lam.stats["refined"]
