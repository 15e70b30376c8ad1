"""Fused single-frequency reconstruction equals the step-by-step path (recon/reconstruct.py)."""

from __future__ import annotations

import numpy as np
import pytest

from gearscan.core.gear import GearSpec
from gearscan.core.patterns import PatternSet
from gearscan.core.phase import decode_phase
from gearscan.core.rig import PinholeDevice, Rig, default_rig
from gearscan.recon.reconstruct import SingleFrequencyReconstructor
from gearscan.recon.triangulate import Triangulator
from gearscan.recon.unwrap import gear_depth_bounds, geometric_unwrap, phase_bounds
from gearscan.twin.render import Optics, TwinRenderer

PERIOD = 110.0


@pytest.mark.parametrize("threads", [1, 2])
def test_fused_matches_reference_and_truth(threads):
    rig, gear = default_rig(), GearSpec()
    renderer = TwinRenderer(rig, gear, Optics())
    patterns = PatternSet.three_step(PERIOD)
    images, truth = renderer.render(0.1, patterns, rng=5)
    phase, _, _ = decode_phase(images, patterns.shifts, 255)
    bounds = gear_depth_bounds(rig, gear.tip_radius, gear.root_radius, gear.face_width)
    with SingleFrequencyReconstructor(rig, PERIOD, bounds, margin=0.2, threads=threads, block_rows=40) as rec:
        buf = rec.allocate()
        tri, order = rec(phase, 0.02, out=buf)
        assert tri is buf[0]
    lo, hi = phase_bounds(rig, bounds, PERIOD)
    ref_unwrap = geometric_unwrap(phase, lo, hi, PERIOD, margin=0.2)
    ref = Triangulator(rig, PERIOD)(ref_unwrap.phase_abs, 0.02)
    # same decisions except where float32 rounding sits exactly on an order boundary
    assert (tri.valid != ref_unwrap.valid).mean() < 1e-4
    both = tri.valid & ref_unwrap.valid
    np.testing.assert_array_equal(order[both], ref_unwrap.order[both])
    np.testing.assert_allclose(tri.depth[both], ref.depth[both], rtol=1e-5)
    np.testing.assert_allclose(tri.sigma_depth[both], ref.sigma_depth[both], rtol=1e-3)
    np.testing.assert_allclose(tri.points[both], ref.points[both], rtol=1e-5, atol=1e-4)
    sel = both & truth.mask
    assert sel.sum() > 0.99 * truth.mask.sum()
    assert np.sqrt(np.mean((tri.depth[sel] - truth.depth[sel]) ** 2)) < 0.05  # mm, 3-step noisy


def test_fused_rejects_projector_distortion():
    rig = default_rig(32, 32)
    p = rig.projector
    bad = Rig(rig.camera, PinholeDevice(p.width, p.height, p.K, [0.01, 0, 0, 0, 0], p.T_from_world))
    gear = GearSpec()
    bounds = gear_depth_bounds(rig, gear.tip_radius, gear.root_radius, gear.face_width)
    with pytest.raises(ValueError, match="distortion"):
        SingleFrequencyReconstructor(bad, PERIOD, bounds)


def test_per_call_cad_bounds_match_reference_and_truth():
    """Fine default fringes with the CAD gear's bounds at the burst angle, given per call and
    cast only where the mask asks: same orders and points as phase_bounds + geometric_unwrap +
    Triangulator, and the truth's depth."""
    from gearscan.recon.unwrap import CadDepthBounds

    period = 40.0
    rig, gear = default_rig(256, 256), GearSpec()
    renderer = TwinRenderer(rig, gear, Optics())
    patterns = PatternSet.three_step(period)
    angle = np.radians(3.1)
    images, truth = renderer.render(angle, patterns, rng=2)
    phase, _, _ = decode_phase(images, patterns.shifts, 255)
    cad = CadDepthBounds(rig, gear.mesh(layer_mm=gear.face_width), 0.3)  # coarse-to-fine cast
    exact = CadDepthBounds(rig, gear.mesh(), 0.3, coarse=False)  # every ray, 20-layer mesh
    mask = truth.mask.copy()
    mask[:, :40] = False  # pixels outside the mask are not cast and come out invalid
    full, part = exact(angle), cad(angle, mask)
    # interpolated where the surface is smooth, cast elsewhere: same hits, depths to a few um
    np.testing.assert_array_equal(np.isfinite(part.t_min[mask]), np.isfinite(full.t_min[mask]))
    hit = mask & np.isfinite(full.t_min)
    assert np.abs(part.t_min[hit] - full.t_min[hit]).max() < 0.01  # mm, against a 0.3 mm tolerance
    assert np.isnan(part.t_min[~mask]).all() and np.isnan(part.t_max[~mask]).all()
    with SingleFrequencyReconstructor(rig, period, margin=0.3, threads=2, block_rows=48) as rec:
        tri, order = rec(phase, 0.02, bounds=part)
        with pytest.raises(ValueError, match="pass bounds= per call"):
            rec(phase, 0.02)
    lo, hi = phase_bounds(rig, part, period)
    ref_unwrap = geometric_unwrap(phase, lo, hi, period, margin=0.3)
    ref = Triangulator(rig, period)(ref_unwrap.phase_abs, 0.02)
    assert not tri.valid[~mask].any()
    assert (tri.valid != ref_unwrap.valid).mean() < 1e-4
    both = tri.valid & ref_unwrap.valid
    np.testing.assert_array_equal(order[both], ref_unwrap.order[both])
    np.testing.assert_allclose(tri.points[both], ref.points[both], rtol=1e-5, atol=1e-4)
    assert both.sum() > 0.99 * mask.sum()
    assert np.sqrt(np.mean((tri.depth[both] - truth.depth[both]) ** 2)) < 0.05  # mm


def test_reconstructor_with_a_distorted_projector_takes_the_fixed_point_path():
    """The pipeline's Reconstructor falls back to geometric_unwrap + Triangulator when the
    projector has lens distortion (the fused path cannot model it) and still gets the orders."""
    from gearscan.core.phase import classical_result
    from gearscan.core.types import Burst, Frame
    from gearscan.recon.measure import Reconstructor

    period = 40.0
    base = default_rig(160, 160)
    p = base.projector
    rig = Rig(base.camera, PinholeDevice(p.width, p.height, p.K, [0.02, 0, 0, 0, 0], p.T_from_world))
    gear = GearSpec()
    renderer = TwinRenderer(rig, gear, Optics())
    patterns = PatternSet.three_step(period)
    angle = np.radians(1.3)
    images, truth = renderer.render(angle, patterns, rng=4)
    burst = Burst(tuple(Frame(f, i, 1000 * i, i) for i, f in enumerate(images)), (angle,) * 3)
    rc = Reconstructor.for_gear(rig, period, gear)
    assert rc.fused is None
    m = rc(burst, classical_result(burst))
    ok = np.isfinite(m.phase_abs) & truth.mask
    assert ok.sum() >= 0.9 * truth.mask.sum()
    assert (np.abs(m.phase_abs[ok] - truth.phase_abs[ok]) < 0.5).all()
