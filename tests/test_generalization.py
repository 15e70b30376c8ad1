"""The generalization benchmark's machinery against physics, on a tiny clean test-split scene."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gearscan.core.gear import GearSpec
from gearscan.core.rig import default_rig
from gearscan.core.types import PhaseResult
from gearscan.evaluate import Method, classical_method
from gearscan.generalization import (
    ALL,
    AXES,
    BASELINE,
    MOVING,
    MOVING_ONLY,
    NETWORK,
    STILL,
    Axis,
    GeneralizationScorer,
    Motion,
    image_motion_px,
    render_family_cases,
    run_methods,
    scene_motions,
    strata_tables,
    weak_strata_table,
)
from gearscan.twin.families import FamilyScene
from gearscan.twin.randomize import balance_projector_power
from gearscan.twin.render import Optics, TwinRenderer
from gearscan.twin.splits import SPLITS

STILL_M = Motion("still 0", "still", (0.0, 0.0))
ONE_DEG = Motion("sweep 1 deg", "sweep", (0.5, 0.5))
BACK = Motion("reversed uniform 0.6/0.6", "paper reversed", (-0.6, -0.6))


def offset(method: Method, rad: float) -> Method:
    """A deliberately bad stand-in network: ``method`` plus a constant phase offset (test only)."""

    def run(frames: np.ndarray, full_scale: float, angles: np.ndarray | None = None) -> PhaseResult:
        r = method(frames, full_scale, angles)
        return dataclasses.replace(r, phase=np.angle(np.exp(1j * (r.phase + rad))).astype(np.float32))

    return run


@pytest.fixture(scope="module")
def scene() -> FamilyScene:
    """A clean (noise-free) 96x96 default-rig scene with a test gear and a test seed."""
    gear = GearSpec(teeth=35)
    rig = default_rig(96, 96, working_radius=gear.pitch_radius)
    optics = balance_projector_power(rig, Optics().noise_free())
    seed = SPLITS["test"].seed(999)
    return FamilyScene("tiny", "default", seed, rig, optics, gear, 120.0, (), TwinRenderer(rig, gear, optics))


@pytest.fixture(scope="module")
def cases(scene: FamilyScene):
    return render_family_cases(scene, [STILL_M, ONE_DEG, BACK])


def _rmse(case, result: PhaseResult) -> float:
    from gearscan.core.phase import wrapped_rmse

    return wrapped_rmse(result.phase, case.truth.phase, case.truth.mask)


def test_three_step_is_at_the_noise_floor_still_and_far_above_it_moving(cases) -> None:
    still, moving, back = (_rmse(c, classical_method(c.frames, c.full_scale)) for c in cases)
    assert still < 0.02
    assert moving > 10 * still
    assert back > 10 * still


def test_strata_partition_the_pixels_and_flag_a_worse_network(cases) -> None:
    bad = GeneralizationScorer([BASELINE, NETWORK])
    same = GeneralizationScorer([BASELINE, NETWORK])
    methods = {BASELINE: classical_method, NETWORK: offset(classical_method, 0.3)}
    for motion, case in zip([STILL_M, ONE_DEG, BACK], cases, strict=True):
        bad.add("tiny", motion, case, run_methods(case, methods))
        same.add("tiny", motion, case, run_methods(case, {BASELINE: classical_method, NETWORK: classical_method}))
    strata = bad.strata()
    for fam in ("tiny", ALL):
        for kind in (MOVING, STILL):
            pooled = bad.pooled_pixels(fam, kind)
            assert pooled > 0
            for axis in AXES:
                counts = [s.pixels for s in strata if s.family == fam and s.kind == kind and s.axis == axis.name]
                if kind == STILL and axis.name in MOVING_ONLY:
                    assert not counts
                else:
                    assert sum(counts) == pooled, (fam, kind, axis.name)
    # the stub is worse everywhere (0.3 rad bias on a near-exact still decode)
    still = [s for s in strata if s.kind == STILL]
    assert still and all(s.worse for s in still)
    assert "WORSE" in strata_tables(strata, ["tiny", ALL])
    assert "still" in weak_strata_table(strata)
    cells = {(c.family, c.group): c for c in bad.cells()}
    assert cells[("tiny", "still")].gain(NETWORK) < 0.2
    assert cells[("tiny", MOVING)].bursts == 2 and cells[("tiny", "sweep")].bursts == 1
    assert not any(s.worse for s in same.strata())
    assert weak_strata_table(same.strata()).startswith("No stratum")


def test_shipped_network_runs_through_the_scorer(cases) -> None:
    from gearscan.evaluate import network_method
    from gearscan.inference.predictor import Predictor

    methods = {BASELINE: classical_method, NETWORK: network_method(Predictor.load())}
    scorer = GeneralizationScorer(list(methods))
    scorer.add("tiny", ONE_DEG, cases[1], run_methods(cases[1], methods))
    tiny = {c.group: c for c in scorer.cells() if c.family == "tiny"}
    assert set(tiny) == {"sweep", MOVING}
    cell = tiny["sweep"]
    assert 0 < cell.rmse[NETWORK] < 1.0 and 0 <= cell.ece[NETWORK] <= 1 and 0 < cell.coverage[NETWORK] <= 1
    with pytest.raises(ValueError, match="no result"):
        scorer.add("tiny", STILL_M, cases[0], {BASELINE: classical_method(cases[0].frames, 255)})


def test_axis_bins_are_right_closed_with_an_na_bin() -> None:
    axis = Axis("x", "px", (2.0, 4.0))
    assert axis.labels == ("<= 2", "2-4", "> 4", "n/a")
    assert axis.bins(np.array([1.0, 2.0, 2.5, 4.0, 9.0, np.nan, np.inf])).tolist() == [0, 0, 1, 1, 2, 3, 3]


def test_scene_motions_cover_both_senses_spans_and_stills() -> None:
    ms = scene_motions(np.random.default_rng(0), sweeps=20)
    assert {m.group for m in ms} == {"paper", "paper reversed", "sweep", "still"}
    sweeps = [m for m in ms if m.group == "sweep"]
    assert all(0 < m.span_deg <= 2.0 for m in sweeps)
    assert {np.sign(sum(m.steps_deg)) for m in sweeps} == {-1.0, 1.0}
    assert [m.steps_deg for m in ms if m.group == "paper"] == [(0.6, 0.6), (0.1, 1.6), (0.5, 1.0)]


def test_image_motion_is_the_rim_displacement(scene: FamilyScene, cases) -> None:
    # 1 deg on a 35 mm pitch radius: 0.61 mm, 96 px over the default rig's 26 mm field: ~2.3 px
    px = image_motion_px(cases[1])
    assert 1.5 < float(np.median(px)) < 3.5
    assert float(np.median(image_motion_px(cases[2]))) == pytest.approx(1.2 * float(np.median(px)), rel=0.1)


def test_fringe_phase_change_is_zero_still_and_orders_the_three_step_error(cases) -> None:
    """The stratum's physics: a still burst moves no fringe; on a moving one, three-step PS's error
    (noise-free scene) grows with how far the fringe phase at the pixel moved across the burst."""
    from gearscan.core.phase import phase_error

    still, moving, _ = cases
    m = still.truth.mask
    np.testing.assert_allclose(still.fringe_phase_change()[m], 0.0, atol=1e-4)  # float32 storage of the phase
    change = moving.fringe_phase_change()[moving.truth.mask] / (2 * np.pi)
    err = np.abs(phase_error(classical_method(moving.frames, moving.full_scale).phase, moving.truth.phase))[moving.truth.mask]
    small, large = change < 0.05, (change > 0.1) & (change < 0.5)
    assert small.sum() > 50 and large.sum() > 50, (small.sum(), large.sum())
    assert np.median(err[large]) > 3 * np.median(err[small]), (np.median(err[large]), np.median(err[small]))


def test_kept_rmse_is_the_error_of_the_pixels_the_keep_test_passes(cases) -> None:
    """RMSE of the kept pixels: over the truth-mask pixels whose own keep test passes (a method that
    marks its bad pixels uncertain is scored on the rest), checked against a direct computation."""
    from gearscan.core.phase import phase_error
    from gearscan.generalization import covered

    def flag_half(frames, full_scale, angles=None):  # three-step PS, its left half declared useless
        r = classical_method(frames, full_scale, angles)
        sigma = r.sigma_total.copy()
        sigma[:, : sigma.shape[1] // 2] = 10.0
        return dataclasses.replace(r, sigma_total=sigma)

    scorer = GeneralizationScorer([BASELINE, NETWORK])
    sse = n = 0.0
    for motion, case in zip([STILL_M, ONE_DEG, BACK], cases, strict=True):
        res = run_methods(case, {BASELINE: classical_method, NETWORK: flag_half})
        scorer.add("tiny", motion, case, res)
        if motion.kind == MOVING:
            keep = covered(res[NETWORK], case.frames, case.full_scale) & case.truth.mask
            sse += float(np.sum(phase_error(res[NETWORK].phase, case.truth.phase)[keep].astype(np.float64) ** 2))
            n += int(keep.sum())
    cell = {(c.family, c.group): c for c in scorer.cells()}[("tiny", MOVING)]
    assert 0 < n < cell.pixels
    assert cell.rmse_kept[NETWORK] == pytest.approx(np.sqrt(sse / n), rel=1e-9)
    assert cell.coverage[NETWORK] == pytest.approx(n / cell.pixels)
    assert cell.rmse[NETWORK] == pytest.approx(cell.rmse[BASELINE])  # same phase: only what is kept differs


def test_a_tie_between_two_three_step_routines_is_not_a_loss() -> None:
    """A still burst the gate decodes by three-step PS and the baseline's three-step PS differ in float32's last
    digits; the report must not call that stratum worse, but a 1 % loss it must."""
    from gearscan.generalization import StratumScore, loses

    def stratum(net: float) -> StratumScore:
        return StratumScore("default", STILL, "modulation", "> 0.5", 1000, {NETWORK: net, "three-step PS": 0.0282},
                            NETWORK, "three-step PS")

    assert not stratum(0.0282 * (1 + 1e-6)).worse and not loses(0.0282, 0.0282)
    assert stratum(0.0282 * 1.01).worse and loses(0.0285, 0.0282)
    assert not stratum(0.0200).worse


def test_coverage_runs_the_decoding_models_own_support_test(cases) -> None:
    """The keep test behind coverage is the one the app runs for the model (its JSON's ``network_support``): a
    model naming a 4 px ring keeps fewer pixels of a network-decoded burst than one naming no test, and exactly what
    ``keep_candidates`` keeps at 4 px."""
    from gearscan.inference.predictor import NetworkSupport
    from gearscan.recon.measure import keep_candidates

    def as_network(frames, full_scale, angles=None):  # three-step PS's phase, reported as a network's
        return dataclasses.replace(classical_method(frames, full_scale, angles), mode="deterministic")

    coverage = {}
    for px in (4, None):
        scorer = GeneralizationScorer([BASELINE, NETWORK], supports={NETWORK: NetworkSupport(px, None)})
        case = cases[1]
        res = run_methods(case, {BASELINE: classical_method, NETWORK: as_network})
        assert res[NETWORK].from_network
        scorer.add("tiny", ONE_DEG, case, res)
        coverage[px] = {(c.family, c.group): c for c in scorer.cells()}[("tiny", MOVING)].coverage[NETWORK]
    kept = keep_candidates(res[NETWORK], case.frames, case.full_scale, network_support_px=4)[0] & case.truth.mask
    assert coverage[4] == pytest.approx(kept.sum() / case.truth.mask.sum())
    assert 0 < coverage[4] < coverage[None]


def test_evaluate_scores_each_models_cloud_with_its_own_support_test(cases, monkeypatch) -> None:
    """``gearscan evaluate``'s cloud column keeps a network's pixels by the decoding model's own fringe-support test
    and scales its clouds' sigma by the model's own depth-sigma scales: ``network_method`` carries the predictor's
    ``network_support`` and ``depth_sigma_scales`` and ``score`` hands them to ``cloud_accuracy``."""
    import gearscan.evaluate as ev
    from gearscan.inference.predictor import NetworkSupport

    class Stub:  # a predictor: three-step PS's phase, and a model record of 3 px and its own scales
        network_support = NetworkSupport(3, None)
        depth_sigma_scales = (2.0, 2.0, 2.0, 2.0, 2.0)

        def predict(self, frames, mc=0, *, full_scale, angles=None):
            return classical_method(frames, full_scale, angles)

    seen = []

    def spy(case, result, model=None, depth_sigma_scales=None):
        seen.append((model, depth_sigma_scales))
        return np.zeros(1), 1, np.zeros(1)

    monkeypatch.setattr(ev, "cloud_accuracy", spy)
    ev.score({BASELINE: classical_method, NETWORK: ev.network_method(Stub())}, cases[:1], clouds=True)
    from gearscan.recon.depth_sigma import DEPTH_SIGMA_SCALES_MC, check_scales

    assert seen[0] == (None, None) and seen[1][0] == NetworkSupport(3, None)
    assert check_scales(seen[1][1]) == check_scales((2.0,) * 5)  # its own, as the app picks them
    # a model without its own: the product's deterministic table (None, the reconstructor's default), or in MC mode
    # the product's MC table (recon.depth_sigma.run_depth_sigma_scales, as replay and live pick them through decoder_depth_sigma)
    Stub.depth_sigma_scales = None
    seen.clear()
    ev.score({NETWORK: ev.network_method(Stub()), "mc": ev.network_method(Stub(), 2)}, cases[:1], clouds=True)
    assert [s for _, s in seen] == [None, DEPTH_SIGMA_SCALES_MC]


def test_val_cloud_samples_name_their_motions() -> None:
    """The reconstruction's val choices score a named sample of motions: the paper's (still, the two paper motions
    both ways) or "wide", which adds the 0.5-3 deg steps users bring; an unknown name is refused before any work."""
    from gearscan.evaluate import (
        GENERALISATION,
        PAPER_MOTIONS,
        REVERSED,
        STATIC,
        VAL_MOTIONS,
        val_cloud_table,
    )

    assert VAL_MOTIONS["paper"] == {**STATIC, **PAPER_MOTIONS, **REVERSED}
    assert VAL_MOTIONS["wide"] == {**VAL_MOTIONS["paper"], **GENERALISATION}
    assert max(sum(steps) for steps in VAL_MOTIONS["wide"].values()) == 5.0  # 2 + 3 deg
    with pytest.raises(ValueError, match="motions: expected one of paper, wide, got 'fast'"):
        val_cloud_table(None, [], {}, seed=0, per_motion=1, three_step="none", motions="fast")
