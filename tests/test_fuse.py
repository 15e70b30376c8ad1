"""Fusion of gear-frame clouds: inverse-variance weighting by hand, and a fused twin revolution
against the true (as-built) surface of the gear, not against the CAD that guided the unwrapping."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from gearscan.core.types import Cloud
from gearscan.recon.fuse import CloudFuser, fuse, load_fused, save_fused


def _cloud(points, sigma, burst=0, frame="world") -> Cloud:
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    return Cloud(points=points, sigma=np.asarray(sigma, dtype=float).reshape(-1),
                 pixels=np.zeros((len(points), 2), np.int32), frame=frame, burst_index=burst)


def test_point_seen_by_two_bursts_gets_the_inverse_variance_mean():
    p1, p2, s1, s2 = np.array([1.01, 2.02, 3.03]), np.array([1.05, 2.06, 3.01]), 0.01, 0.03
    f = fuse([_cloud(p1, s1, 0), _cloud(p2, s2, 1)], voxel_mm=0.1)
    w1, w2 = 1 / s1**2, 1 / s2**2
    assert len(f) == 1
    np.testing.assert_allclose(f.points[0], (w1 * p1 + w2 * p2) / (w1 + w2), rtol=0, atol=1e-12)
    assert f.sigma[0] == pytest.approx(1 / np.sqrt(w1 + w2))
    assert (f.bursts[0], f.samples[0]) == (2, 2)


def test_bursts_count_once_per_voxel_and_min_bursts_filters():
    a = _cloud([[0.01, 0, 0], [0.02, 0, 0], [5.0, 5, 5]], [0.01, 0.01, 0.01], 0)  # two points of one burst in a voxel
    b = _cloud([[0.03, 0, 0]], [0.02], 1)
    fuser = CloudFuser(0.1, batch_points=1)  # merge after every burst: streaming = one shot
    fuser.add(a)
    fuser.add(b)
    f = fuser.result()
    order = np.argsort(f.points[:, 0])
    assert f.bursts[order].tolist() == [2, 1] and f.samples[order].tolist() == [3, 1]
    assert len(fuser.result(min_bursts=2)) == 1
    assert f.bursts_added == 2
    # the burst's two pixels share its error: one observation of their mean weight, not two
    assert f.sigma[order][0] == pytest.approx(1 / np.sqrt(1 / 0.01**2 + 1 / 0.02**2))


def test_sigma_counts_bursts_not_pixels():
    """Many pixels of one burst in a voxel do not shrink sigma; another burst does."""
    one = fuse([_cloud(np.full((9, 3), 0.05), np.full(9, 0.02), 0)], voxel_mm=0.1)
    assert one.sigma[0] == pytest.approx(0.02) and one.samples[0] == 9
    two = fuse([_cloud(np.full((9, 3), 0.05), np.full(9, 0.02), 0), _cloud([[0.05] * 3], [0.02], 1)], voxel_mm=0.1)
    assert two.sigma[0] == pytest.approx(0.02 / np.sqrt(2))
    mixed = fuse([_cloud(np.full((2, 3), 0.05), [0.01, 0.03], 0)], voxel_mm=0.1)
    assert mixed.sigma[0] == pytest.approx(1 / np.sqrt((1 / 0.01**2 + 1 / 0.03**2) / 2))


def test_bad_points_are_skipped_and_bad_input_named():
    fuser = CloudFuser(0.1)
    fuser.add(_cloud([[0, 0, 0], [np.nan, 0, 0], [1, 1, 1]], [0.01, 0.01, 0.0]))
    assert fuser.skipped == 2 and len(fuser.result()) == 1
    with pytest.raises(ValueError, match="frame"):
        fuser.add(_cloud([[0, 0, 0]], [0.01], frame="camera"))
    with pytest.raises(ValueError, match="voxel_mm"):
        CloudFuser(0.0)
    with pytest.raises(ValueError, match="nothing to fuse"):
        CloudFuser(0.1).result()


@pytest.fixture(scope="module")
def revolution(tmp_path_factory):
    """A twin gear (eccentric, one tooth off) in 24 still bursts 15 deg apart, 160 px."""
    from gearscan.core.rig import default_rig
    from gearscan.twin.defects import GearDefects
    from gearscan.twin.recordings import render_recording

    out = tmp_path_factory.mktemp("fuse") / "rec"
    defects = GearDefects(eccentricity_um=50, pitch_errors_um={3: 30})
    render_recording(out, rig=default_rig(160, 160), defects=defects, motion="nonuniform:0,0,15", bursts=24)
    return out


def test_replay_fuse_writes_a_cloud_on_the_true_surface(revolution, tmp_path):
    import open3d as o3d

    from gearscan.cli import app
    from gearscan.core.recording import RecordingReader
    from gearscan.recon.cloud import load_cloud
    from gearscan.twin.defects import GearDefects, true_mesh

    ply = tmp_path / "fused.ply"
    res = CliRunner().invoke(app, ["replay", str(revolution), "--classical", "--no-truth", "--fuse", str(ply),
                                   "--voxel-mm", "0.2", "--min-bursts", "2", "--save", str(tmp_path / "r.rrd")])
    assert res.exit_code == 0, res.output
    cloud = load_cloud(ply)
    pcd = o3d.t.io.read_point_cloud(str(ply))
    assert {"sigma", "deviation", "bursts"} <= set(pcd.point)
    assert pcd.point["bursts"].numpy().min() >= 2
    reader = RecordingReader(revolution)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(true_mesh(reader.gear, GearDefects.from_meta(reader.meta))))
    dist = scene.compute_distance(o3d.core.Tensor(cloud.points.astype(np.float32))).numpy()
    assert np.sqrt(np.mean(dist**2)) < 0.02  # mm; still three-step bursts at 160 px
    assert np.percentile(dist, 95) < 0.03
    # every tooth of the revolution is in it: points all round the gear
    angles = np.degrees(np.arctan2(cloud.points[:, 1], cloud.points[:, 0]))
    assert np.histogram(angles, bins=36, range=(-180, 180))[0].min() > 0


def test_save_fused_names_a_bad_suffix(tmp_path):
    f = fuse([_cloud([[0, 0, 0]], [0.01])])
    with pytest.raises(ValueError, match="suffix"):
        save_fused(f, tmp_path / "x.txt")


def test_fused_cloud_exports_as_ply_and_csv_with_the_same_numbers(tmp_path):
    """PLY (open3d) and CSV hold the same x, y, z (mm), sigma, deviation, burst and sample counts; the PLY reads back
    as the fused cloud."""
    import open3d as o3d

    from gearscan.recon.cloud import load_cloud

    rng = np.random.default_rng(0)
    pts = (rng.choice(400, (50, 3), replace=False) - 199.5) * 0.1  # voxel centres, no two in one voxel
    f = fuse([_cloud(pts, np.full(50, 0.01), 0), _cloud(pts + 0.001, np.full(50, 0.02), 1)], voxel_mm=0.1)
    f = f.with_deviation(rng.normal(0, 0.05, len(f)))
    ply, csv = save_fused(f, tmp_path / "f.ply"), save_fused(f, tmp_path / "f.csv")
    assert csv.read_text().splitlines()[0] == "x_mm,y_mm,z_mm,sigma_mm,deviation_mm,bursts,samples"
    a, b = load_cloud(ply), load_cloud(csv)
    np.testing.assert_allclose(b.points, f.points, atol=1e-6)
    np.testing.assert_allclose(a.points, f.points, atol=1e-5)  # float32 in the PLY
    np.testing.assert_allclose(b.sigma, f.sigma, rtol=1e-5)
    assert f.sigma[0] == pytest.approx(1 / np.sqrt(1 / 0.01**2 + 1 / 0.02**2))  # both bursts in each voxel
    np.testing.assert_allclose(b.deviation, f.deviation, atol=1e-6)
    np.testing.assert_allclose(a.deviation, f.deviation, atol=1e-6)
    counts = np.loadtxt(csv, delimiter=",", skiprows=1)[:, 5]
    assert counts.tolist() == o3d.t.io.read_point_cloud(str(ply)).point["bursts"].numpy().ravel().tolist() == [2] * len(f)
    back = load_fused(ply, 0.1, f.bursts_added)  # what `inspect --from-report` reads: the same cloud, float32 aside
    np.testing.assert_allclose(back.points, f.points, atol=1e-5)
    np.testing.assert_allclose(back.sigma, f.sigma, rtol=1e-6)
    np.testing.assert_allclose(back.deviation, f.deviation, atol=1e-6)
    assert back.bursts.tolist() == f.bursts.tolist() and back.samples.tolist() == f.samples.tolist()
    assert back.refined is None and back.ray is None and len(back) == len(f)
    with pytest.raises(ValueError, match="expected a .ply or .pcd"):
        load_fused(csv, 0.1, 2)
