"""MC moments, propagation to phase (vs finite differences), reliability / ECE, variance scale."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from gearscan.inference.concrete_dropout import concrete_layers, set_stochastic
from gearscan.inference.models import build_model, dropout_on_shared_input
from gearscan.inference.uncertainty import (
    DEPARTURE_FLOOR,
    MomentStats,
    SigmaCalibration,
    confidence,
    deterministic_moments,
    fit_sigma_calibration,
    fit_variance_scale,
    mc_moments,
    phase_sigma,
    plot_reliability,
    reliability,
    to_phase_result,
)

torch.set_num_threads(1)


def test_propagation_matches_finite_differences():
    rng = np.random.default_rng(0)
    M = rng.uniform(-0.8, 0.8, 200)
    D = rng.uniform(-0.8, 0.8, 200)
    keep = np.hypot(M, D) > 0.1
    M, D = M[keep], D[keep]
    h = 1e-6
    dphi_dM = (np.arctan2(M + h, D) - np.arctan2(M - h, D)) / (2 * h)
    dphi_dD = (np.arctan2(M, D + h) - np.arctan2(M, D - h)) / (2 * h)
    np.testing.assert_allclose(dphi_dM, D / (M**2 + D**2), rtol=1e-5)
    np.testing.assert_allclose(dphi_dD, -M / (M**2 + D**2), rtol=1e-5)
    vm, vd = rng.uniform(1e-6, 1e-4, M.size), rng.uniform(1e-6, 1e-4, M.size)
    expected = np.sqrt(dphi_dM**2 * vm + dphi_dD**2 * vd)
    np.testing.assert_allclose(phase_sigma(M, D, vm, vd), expected, rtol=1e-4)


def test_propagation_matches_sampling():
    """For small noise the first-order sigma equals the std of sampled atan2."""
    rng = np.random.default_rng(1)
    M, D, sm, sd = 0.3, -0.4, 0.004, 0.006
    phi = np.arctan2(M + sm * rng.standard_normal(200000), D + sd * rng.standard_normal(200000))
    s = phase_sigma(np.array([M]), np.array([D]), np.array([sm**2]), np.array([sd**2]))[0]
    assert np.std(phi) == pytest.approx(s, rel=0.02)


class _Scripted(torch.nn.Module):
    """Returns a pre-set sequence of outputs, one per sample in each batch (fake MC passes)."""

    def __init__(self, outs: torch.Tensor) -> None:
        super().__init__()
        self.outs = outs  # (T, 4, H, W)
        self.i = 0
        self.p = torch.nn.Parameter(torch.zeros(1))

    def forward(self, x):
        k = x.shape[0]
        out = self.outs[self.i : self.i + k]
        self.i += k
        return out


def test_mc_moments_formulas_and_chunking():
    rng = np.random.default_rng(2)
    outs = torch.from_numpy(rng.uniform(0.01, 1, size=(5, 4, 3, 3)).astype(np.float32))
    stats = mc_moments(_Scripted(outs), torch.zeros(1, 3, 3, 3), passes=5, chunk=2)
    o = outs.double().numpy()
    np.testing.assert_allclose(stats.M[0].numpy(), o[:, 0].mean(0), rtol=1e-6)
    np.testing.assert_allclose(stats.model_var_M[0].numpy(), o[:, 0].var(0), rtol=1e-4, atol=1e-8)
    np.testing.assert_allclose(stats.model_var_D[0].numpy(), o[:, 1].var(0), rtol=1e-4, atol=1e-8)
    np.testing.assert_allclose(stats.data_var_M[0].numpy(), o[:, 2].mean(0), rtol=1e-6)
    np.testing.assert_allclose(stats.data_var_D[0].numpy(), o[:, 3].mean(0), rtol=1e-6)


def test_mc_with_dropout_disabled_equals_deterministic():
    torch.manual_seed(0)
    x = torch.rand(1, 3, 24, 40)
    # a model without dropout layers: every MC pass is the deterministic pass
    plain = build_model("cd-dcu-net", width=4, dropout=False).eval()
    det = deterministic_moments(plain, x)
    mc = mc_moments(plain, x, passes=4, chunk=3)
    torch.testing.assert_close(mc.M, det.M, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(mc.data_var_D, det.data_var_D, atol=1e-6, rtol=1e-5)
    assert mc.model_var_M.max().item() < 1e-10
    # Concrete Dropout with rates driven to ~0: masks keep everything
    cd = build_model("cd-dcu-net", width=4).eval()
    with torch.no_grad():
        for layer in concrete_layers(cd):
            layer.p_logit.fill_(-40.0)
    det, mc = deterministic_moments(cd, x), mc_moments(cd, x, passes=3, chunk=2)
    torch.testing.assert_close(mc.M, det.M, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(mc.D, det.D, atol=1e-5, rtol=1e-4)
    assert all(not layer.stochastic for layer in concrete_layers(cd)), (
        "MC must switch masks back off"
    )


def test_mc_with_dropout_gives_model_uncertainty():
    torch.manual_seed(0)
    m = build_model("cd-dcu-net", width=4).eval()
    mc = mc_moments(m, torch.rand(1, 3, 32, 32), passes=6, chunk=2)
    assert mc.model_var_M.mean().item() > 0


def _randomise_bn(model):
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.3, 0.3)
            m.running_var.uniform_(0.5, 2.0)
    return model.eval()


@pytest.mark.parametrize(
    "options",
    [
        dict(name="cd-dcu-net", classical_input=True, residual=True),  # the shipped kind
        dict(name="cd-dcu-net"),
        dict(name="ts-unet", dropout=True),  # no split of its own: the generic prefix
    ],
)
@pytest.mark.parametrize("batch, chunk", [(1, 1), (1, 3), (2, 2)])
@pytest.mark.parametrize("channels_last", [False, True])
def test_mc_reusing_the_prefix_gives_the_plain_paths_samples(options, batch, chunk, channels_last):
    """Stem once + first dropout as one conv + float32 moments: the same masks (same seed) give
    the same moments as running the whole network per pass, up to float rounding."""
    torch.manual_seed(0)
    model = _randomise_bn(build_model(width=4, init_min=0.1, init_max=0.3, **options))
    x = torch.rand(batch, 3, 21, 38)  # padded to 32 x 48 inside
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
        x = x.contiguous(memory_format=torch.channels_last)
    torch.manual_seed(11)
    plain = mc_moments(model, x, passes=7, chunk=chunk, reuse_prefix=False)
    torch.manual_seed(11)
    split = mc_moments(model, x, passes=7, chunk=chunk)
    assert plain.model_var_M.mean() > 1e-9  # the masks do something
    for name in (f.name for f in dataclasses.fields(MomentStats)):
        a, b = getattr(plain, name), getattr(split, name)
        scale = a.abs().max().item()
        torch.testing.assert_close(b, a, atol=1e-5 * scale, rtol=1e-4, msg=name)
    assert all(not layer.stochastic for layer in concrete_layers(model))


def test_mc_reusing_the_prefix_under_bf16_autocast_stays_close():
    torch.manual_seed(1)
    model = build_model(width=4, classical_input=True, residual=True, init_min=0.1, init_max=0.3).eval()
    model = model.to(memory_format=torch.channels_last)
    x = torch.rand(1, 3, 32, 40).contiguous(memory_format=torch.channels_last)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        torch.manual_seed(4)
        plain = mc_moments(model, x, passes=6, chunk=2, reuse_prefix=False)
        torch.manual_seed(4)
        split = mc_moments(model, x, passes=6, chunk=2)
    # bf16 rounds x*m (plain) and W*m (split) differently: |M| <= ~1, bf16 eps 2^-8
    torch.testing.assert_close(split.M, plain.M, atol=2e-2, rtol=0)
    torch.testing.assert_close(split.data_var_D, plain.data_var_D, atol=2e-2, rtol=5e-2)
    assert split.model_var_M.mean().item() == pytest.approx(plain.model_var_M.mean().item(), rel=0.2)


@pytest.mark.parametrize("chunk", [1, 2, 5])
def test_mc_moments_of_a_tiny_model_are_the_moments_of_its_passes(chunk):
    """Model variance = population variance of the T means, data variance = mean of the T
    variances, against the T passes of the plain network (same masks), in float64 numpy."""
    torch.manual_seed(2)
    model = build_model(width=2, classical_input=True, residual=True, init_min=0.2, init_max=0.4).eval()
    x = torch.rand(1, 3, 16, 24)
    passes = 5
    torch.manual_seed(9)
    set_stochastic(model, True)
    with torch.no_grad():
        outs = [model(x.repeat(min(chunk, passes - d), 1, 1, 1)) for d in range(0, passes, chunk)]
    set_stochastic(model, False)
    o = torch.cat(outs).double().numpy()  # (T, 4, H, W)
    torch.manual_seed(9)
    st = mc_moments(model, x, passes=passes, chunk=chunk)
    assert o[:, 0].var(0).mean() > 1e-9
    np.testing.assert_allclose(st.M[0].numpy(), o[:, 0].mean(0), atol=1e-6)
    np.testing.assert_allclose(st.D[0].numpy(), o[:, 1].mean(0), atol=1e-6)
    np.testing.assert_allclose(st.model_var_M[0].numpy(), o[:, 0].var(0), rtol=1e-3, atol=1e-9)
    np.testing.assert_allclose(st.model_var_D[0].numpy(), o[:, 1].var(0), rtol=1e-3, atol=1e-9)
    np.testing.assert_allclose(st.data_var_M[0].numpy(), o[:, 2].mean(0), rtol=1e-5)
    np.testing.assert_allclose(st.data_var_D[0].numpy(), o[:, 3].mean(0), rtol=1e-5)


@pytest.mark.parametrize("channels_last", [False, True])
def test_dropout_on_a_shared_input_is_the_layer_on_its_repeats(channels_last):
    """k masked passes of one input as a single conv with k scaled weight sets (k * C_out outputs)."""
    from gearscan.inference.concrete_dropout import ConcreteDropout2d

    torch.manual_seed(3)
    layer = ConcreteDropout2d(6, 5, init_min=0.2, init_max=0.4)
    layer.stochastic = True
    x = torch.randn(1, 6, 12, 9)
    if channels_last:
        layer = layer.to(memory_format=torch.channels_last)
        x = x.contiguous(memory_format=torch.channels_last)
    torch.manual_seed(5)
    ref = layer(x.repeat(4, 1, 1, 1))
    torch.manual_seed(5)
    got = dropout_on_shared_input(layer, x, 4)
    assert got.shape == (4, 5, 12, 9)
    assert got.is_contiguous(memory_format=torch.channels_last if channels_last else torch.contiguous_format)
    torch.testing.assert_close(got, ref, atol=1e-5, rtol=1e-5)
    layer.stochastic = False  # deterministic: the plain layer
    torch.testing.assert_close(dropout_on_shared_input(layer, x, 2), layer(x).repeat(2, 1, 1, 1))


def test_to_phase_result_combines_by_eq19_and_scales():
    M = torch.tensor([[[0.3, -0.2]]])
    D = torch.tensor([[[0.4, 0.5]]])
    mv = torch.tensor([[[1e-4, 4e-4]]])
    dv = torch.tensor([[[9e-4, 1e-4]]])
    stats = MomentStats(M, D, mv, mv, dv, dv)
    r = to_phase_result(stats, mode="mc20")
    np.testing.assert_allclose(r.phase, np.arctan2(M[0].numpy(), D[0].numpy()), rtol=1e-6)
    np.testing.assert_allclose(r.sigma_total, np.hypot(r.sigma_model, r.sigma_data), rtol=1e-6)
    # equal variances on M and D: sigma_phi = sqrt(var) / modulation
    np.testing.assert_allclose(
        r.sigma_model, np.sqrt(mv[0].numpy()) / np.hypot(M[0].numpy(), D[0].numpy()), rtol=1e-5
    )
    r4 = to_phase_result(stats, var_scale=4.0)
    np.testing.assert_allclose(r4.sigma_total, 2 * r.sigma_total, rtol=1e-5)
    assert r.mode == "mc20" and r.phase.dtype == np.float32


def test_reliability_hand_example():
    sigma = np.array([0.01, 0.01, 1.0, 1.0])
    err = np.array([0.0, 0.05, 0.0, 0.5])
    c_hi, c_lo = math.erf(0.03 / (0.01 * math.sqrt(2))), math.erf(0.03 / math.sqrt(2))
    rel = reliability(err, sigma, eps=0.03, bins=30)
    expected = (2 * abs(0.5 - c_hi) + 2 * abs(0.5 - c_lo)) / 4
    assert rel.ece == pytest.approx(expected, rel=1e-9)
    assert rel.count.sum() == 4 and rel.count[29] == 2 and rel.count[0] == 2


def test_calibrated_gaussian_errors_have_small_ece_and_scale_fit_recovers_factor():
    rng = np.random.default_rng(3)
    sigma = rng.uniform(0.005, 0.1, 200000)
    err = sigma * rng.standard_normal(sigma.size)
    assert reliability(err, sigma).ece < 0.01
    np.testing.assert_allclose(confidence(np.array([0.03]), 0.03), math.erf(1 / math.sqrt(2)))
    k, before, after = fit_variance_scale(err, sigma / 3)  # overconfident by 3x
    assert before > 0.1 and after < 0.01
    assert k == pytest.approx(9.0, rel=0.15)
    k1, b1, a1 = fit_variance_scale(err, sigma)
    assert a1 <= b1 and 0.8 < k1 < 1.25


def test_plot_reliability(tmp_path):
    rng = np.random.default_rng(4)
    sigma = rng.uniform(0.005, 0.1, 1000)
    p = plot_reliability(reliability(sigma * rng.standard_normal(1000), sigma), tmp_path / "r.png")
    assert p.stat().st_size > 1000


def test_sigma_calibration_fit_recovers_a_power_law_by_nll():
    rng = np.random.default_rng(7)
    raw = rng.uniform(0.02, 0.5, 200000)
    true = 0.2 * raw**0.5  # the network's sigma spreads too much, like the shipped one's
    err = true * rng.standard_normal(raw.size)
    cal, m = fit_sigma_calibration(err, raw, score="nll")
    assert cal.a == pytest.approx(0.2, rel=0.05) and cal.b == pytest.approx(0.5, abs=0.03)
    assert m["nll_after"] < m["nll_before"] and m["ece_after"] < 0.01 < m["ece_before"]
    np.testing.assert_allclose(cal(raw), cal.a * raw**cal.b, rtol=1e-5)
    ident, _ = fit_sigma_calibration(err, true, score="nll")  # already calibrated: stays (near) identity
    assert ident.a == pytest.approx(1.0, rel=0.1) and ident.b == pytest.approx(1.0, abs=0.03)


def test_sigma_calibration_is_one_factor_on_every_sigma_and_variance():
    M = torch.tensor([[[0.3, -0.2, 0.05]]])
    D = torch.tensor([[[0.4, 0.5, -0.1]]])
    mv = torch.tensor([[[1e-4, 4e-4, 2e-5]]])
    dv = torch.tensor([[[9e-4, 1e-4, 3e-4]]])
    stats = MomentStats(M, D, mv, mv, dv, dv)
    cal = SigmaCalibration(0.3, 0.6)
    r, c = to_phase_result(stats, mode="mc20"), to_phase_result(stats, mode="mc20", calibration=cal)
    np.testing.assert_allclose(c.sigma_total, 0.3 * r.sigma_total**0.6, rtol=1e-5)
    np.testing.assert_allclose(c.sigma_model / c.sigma_data, r.sigma_model / r.sigma_data, rtol=1e-5)
    # the calibrated M, D variances propagate to the calibrated total sigma
    np.testing.assert_allclose(phase_sigma(c.M, c.D, c.var_M, c.var_D), c.sigma_total, rtol=1e-4)
    np.testing.assert_array_equal(c.phase, r.phase)
    det = to_phase_result(MomentStats(M, D, 0 * mv, 0 * mv, dv, dv), calibration=cal)
    assert np.all(det.sigma_model == 0)
    np.testing.assert_allclose(det.sigma_total, det.sigma_data, rtol=1e-6)


def test_sigma_calibration_rejects_bad_values_by_name():
    with pytest.raises(ValueError, match="a > 0, 0 < b <= 3"):
        SigmaCalibration(-1.0, 0.5)
    with pytest.raises(ValueError, match=r"sigma_calibration.mc: expected \{'a': float, 'b': float\}"):
        SigmaCalibration.from_json({"a": 1.0}, "sigma_calibration.mc")
    with pytest.raises(ValueError, match="d0 > 0"):
        SigmaCalibration.from_json({"a": 1.0, "b": 1.0, "c": 0.3, "d0": 0.0})
    assert SigmaCalibration.from_json({"a": 0.5, "b": 0.4}) == SigmaCalibration(0.5, 0.4)
    full = SigmaCalibration(0.5, 0.4, 0.3, 0.02)
    assert SigmaCalibration.from_json(full.to_json()) == full
    with pytest.raises(ValueError, match="expected a departure map of shape"):
        full(np.ones(3, np.float32))


def _departure_world(n: int, seed: int):
    """Raw sigmas, departures and Gaussian errors whose true sigma grows with both."""
    rng = np.random.default_rng(seed)
    raw = rng.uniform(0.03, 0.4, n)
    dep = np.exp(rng.uniform(np.log(0.002), np.log(1.0), n))  # still-like to strongly corrected
    true = 0.15 * raw**0.6 * (dep + DEPARTURE_FLOOR) ** 0.35
    return raw, dep, true * rng.standard_normal(n)


def test_event_score_fit_recovers_a_departure_dependence_the_power_law_cannot():
    raw, dep, err = _departure_world(300000, 11)
    plain, _ = fit_sigma_calibration(err, raw)
    cal, m = fit_sigma_calibration(err, raw, dep)
    assert cal.a == pytest.approx(0.15, rel=0.15) and cal.b == pytest.approx(0.6, abs=0.06)
    assert cal.c == pytest.approx(0.35, abs=0.04) and not plain.needs_departure
    assert m["event_score_after"] < m["event_score_before"] and m["ece_after"] < 0.01
    # on fresh pixels, split where it matters: small departures (still-like) and large ones
    raw2, dep2, err2 = _departure_world(200000, 12)
    for part in (dep2 < 0.02, dep2 > 0.3):
        assert reliability(err2[part], cal(raw2[part], dep2[part])).ece < 0.02
        assert reliability(err2[part], plain(raw2[part])).ece > 0.05


def test_to_phase_result_reads_the_departure_from_the_classical_phase():
    M = torch.tensor([[[0.3, -0.2]]])
    D = torch.tensor([[[0.4, 0.5]]])
    dv = torch.tensor([[[9e-4, 1e-4]]])
    z = torch.zeros_like(dv)
    stats = MomentStats(M, D, z, z, dv, dv)
    cal = SigmaCalibration(0.3, 0.6, 0.5)
    raw = to_phase_result(stats)
    classical = raw.phase + np.array([[0.0, 0.5]], np.float32)  # three-step agrees at one pixel only
    r = to_phase_result(stats, calibration=cal, classical_phase=classical)
    np.testing.assert_allclose(r.sigma_total, 0.3 * raw.sigma_total**0.6 * (np.array([[0.0, 0.5]]) + 0.01) ** 0.5,
                               rtol=1e-4)
    with pytest.raises(ValueError, match="pass classical_phase"):
        to_phase_result(stats, calibration=cal)


def _density_world(n: int, seed: int):
    """Synthetic pixels whose true sigma doubles where the fringes are dense (density > 0.5 rad/px), which no power
    law in the sigma and departure can see."""
    rng = np.random.default_rng(seed)
    raw = np.exp(rng.uniform(np.log(0.01), np.log(0.5), n)).astype(np.float32)
    dep = np.exp(rng.uniform(np.log(0.001), np.log(1.0), n)).astype(np.float32)
    den = np.exp(rng.uniform(np.log(0.05), np.log(2.0), n)).astype(np.float32)
    true = 0.4 * raw**0.7 * (dep + 0.01) ** 0.2 * np.where(den > 0.5, 2.0, 1.0)
    return rng.normal(0, true), raw, dep, den, true


def test_the_additive_map_learns_what_the_fringe_density_says():
    """fit_additive_map on one draw, scored on another: calibrated in the dense and the sparse fringes apart, where
    the power law fitted on the same pixels is off in both (it averages them)."""
    from gearscan.inference.uncertainty import fit_additive_map

    err, raw, dep, den, _ = _density_world(60_000, 0)
    cal, metrics = fit_additive_map(err, raw, dep, den)
    power, _ = fit_sigma_calibration(err, raw, dep)
    assert metrics["ece_after"] < 0.02 < metrics["ece_before"] and metrics["form"] == "additive"
    err2, raw2, dep2, den2, true2 = _density_world(60_000, 1)
    for part in (den2 > 0.6, den2 < 0.4):
        assert reliability(err2[part], cal(raw2, dep2, den2)[part]).ece < 0.02
        assert reliability(err2[part], power(raw2, dep2)[part]).ece > 0.05
    np.testing.assert_allclose(np.median(cal(raw2, dep2, den2) / true2), 1.0, atol=0.05)
    with pytest.raises(ValueError, match="features"):
        fit_additive_map(err, raw, dep, den, features=("departure",))
    with pytest.raises(ValueError, match="need a map"):
        fit_additive_map(err, raw, None, den)
    with pytest.raises(ValueError, match="weights"):
        fit_additive_map(err, raw, dep, den, weights=-np.ones(err.size))


def test_the_additive_map_round_trips_and_bad_entries_are_named():
    from gearscan.inference.uncertainty import AdditiveSigmaMap, HingeTerm, sigma_map_from_json

    cal = AdditiveSigmaMap(-1.0, (HingeTerm("sigma", 0.6, (-3.0, -2.0), (0.1, -0.2)), HingeTerm("density", 0.3)))
    assert sigma_map_from_json(cal.to_json()) == cal and not cal.needs_departure and cal.needs_density
    assert sigma_map_from_json({"a": 0.5, "b": 0.4}) == SigmaCalibration(0.5, 0.4)  # a stored power law
    s, den = np.array([0.05, 0.2], np.float32), np.array([0.1, 1.5], np.float32)
    x = np.log(s)
    expected = np.exp(-1.0 + 0.6 * x + 0.1 * np.maximum(x + 3, 0) - 0.2 * np.maximum(x + 2, 0)
                      + 0.3 * np.log(den + 0.02))
    np.testing.assert_allclose(cal(s, None, den), expected, rtol=1e-5)
    np.testing.assert_allclose(cal.factor(s, None, den) * s, expected, rtol=1e-5)
    np.testing.assert_allclose(cal.departure_factor(np.ones(2)), 1.0)  # no departure term
    with pytest.raises(ValueError, match="reads the density"):
        cal(s)
    bad = cal.to_json()
    with pytest.raises(ValueError, match="sigma_calibration.mc"):
        sigma_map_from_json(bad | {"form": "spline"}, "sigma_calibration.mc")
    with pytest.raises(ValueError, match="sigma's"):
        sigma_map_from_json(bad | {"terms": bad["terms"][1:]})
    with pytest.raises(ValueError, match="sorted knots"):
        sigma_map_from_json(bad | {"terms": [bad["terms"][0] | {"knots": [-2.0, -3.0]}]})
    with pytest.raises(ValueError, match="expected"):
        sigma_map_from_json(bad | {"extra": 1})


def test_fringe_density_reads_the_local_fringe_period():
    """A wrapped ramp of period P px has |grad phase| = 2 pi / P, across the wraps; a mirrored phase, the mirrored
    map."""
    from gearscan.inference.uncertainty import fringe_density

    for period in (5.0, 17.0, 60.0):
        ramp = np.angle(np.exp(1j * 2 * np.pi * np.arange(64)[None, :] / period)) * np.ones((8, 1))
        np.testing.assert_allclose(fringe_density(ramp)[:, 1:-1], 2 * np.pi / period, rtol=1e-5)
        bent = ramp + 0.3 * np.sin(np.arange(8)[:, None] * np.arange(64)[None, :] / 40)
        np.testing.assert_allclose(fringe_density(-bent[:, ::-1])[:, ::-1], fringe_density(bent), atol=1e-6)


def test_the_event_score_gradient_matches_the_loss_also_where_it_saturates():
    """event_loss_grad against finite differences on pixels from tiny to huge sigma (P near 0 and 1) and past the
    map's clip, where the gradient is 0."""
    from scipy.optimize import approx_fprime

    from gearscan.inference.uncertainty import LOG_SIGMA_RANGE, event_loss_grad

    rng = np.random.default_rng(4)
    n = 400
    X = np.stack([np.ones(n), rng.uniform(-9, 1.5, n), rng.normal(0, 1, n)], 1)
    hit = rng.random(n) < 0.5
    w = rng.random(n)
    w /= w.sum()
    for p in (np.array([0.0, 1.0, 0.2]), np.array([-2.0, 0.7, -0.4])):
        _, g = event_loss_grad(p, X, hit, w)
        np.testing.assert_allclose(g, approx_fprime(p, lambda q: event_loss_grad(q, X, hit, w)[0], 1e-7),
                                   rtol=1e-4, atol=1e-7)
    clipped = np.array([LOG_SIGMA_RANGE[1] + 5.0, 0.0, 0.0])  # every pixel past the clip: flat loss, no slope
    np.testing.assert_allclose(event_loss_grad(clipped, X, hit, w)[1], 0.0)
    assert np.isfinite(event_loss_grad(np.array([-20.0, 0.0, 0.0]), X, hit, w)[0])  # z huge: no log(0)


def test_the_additive_fit_names_non_finite_input():
    from gearscan.inference.uncertainty import fit_additive_map, sigma_map_from_json

    err, raw, dep, den, _ = _density_world(500, 2)
    den[3] = np.nan
    with pytest.raises(ValueError, match="density has 1 non-finite"):
        fit_additive_map(err, raw, dep, den)
    with pytest.raises(ValueError, match="a power law names no form"):
        sigma_map_from_json({"form": "power", "a": 1.0, "b": 1.0})


def test_phase_curvature_and_local_departure_read_known_fields():
    """The curvature of a wrapped ramp is 0 across its wraps and that of a parabola its Laplacian; a mirrored phase
    gives the mirrored map. The local departure of a constant map is that constant; a single spike spreads as its
    RMS over the 7x7 window."""
    from gearscan.inference.uncertainty import LOCAL_WINDOW, local_departure, phase_curvature

    ramp = np.angle(np.exp(1j * 2 * np.pi * np.arange(64)[None, :] / 9.0)) * np.ones((16, 1))
    np.testing.assert_allclose(phase_curvature(ramp)[1:-1, 1:-1], 0.0, atol=1e-5)
    yy, xx = np.mgrid[:16, :64].astype(np.float64)
    parabola = np.angle(np.exp(1j * (0.01 * xx**2 + 0.03 * yy**2)))
    np.testing.assert_allclose(phase_curvature(parabola)[1:-1, 1:-1], 2 * 0.01 + 2 * 0.03, rtol=1e-4)
    np.testing.assert_allclose(phase_curvature(-parabola[:, ::-1])[:, ::-1], phase_curvature(parabola), atol=1e-6)
    np.testing.assert_allclose(local_departure(np.full((20, 20), 0.2, np.float32)), 0.2, rtol=1e-5)
    spike = np.zeros((21, 21), np.float32)
    spike[10, 10] = 0.7
    loc = local_departure(spike)
    h = LOCAL_WINDOW // 2
    np.testing.assert_allclose(loc[10 - h:11 + h, 10 - h:11 + h], 0.7 / LOCAL_WINDOW, rtol=1e-4)
    assert loc[10, 10 + h + 1] < 1e-6
    with pytest.raises(ValueError, match="departure map"):
        local_departure(np.zeros(5))
    holed = np.full((30, 60), 0.1, np.float32)
    holed[10, 10] = np.nan  # a bad pixel stays within its window, not along the filter's rows
    loc = local_departure(holed)
    assert np.isnan(loc).sum() == LOCAL_WINDOW**2
    np.testing.assert_allclose(loc[20:, 20:], 0.1, rtol=1e-5)


def _local_world(n: int, seed: int):
    """Synthetic pixels whose true sigma grows with the local departure (as its 0.6th power) whatever the pixel's
    own departure: what a map in the sigma, departure and density cannot see."""
    rng = np.random.default_rng(seed)
    raw = np.exp(rng.uniform(np.log(0.01), np.log(0.5), n)).astype(np.float32)
    dep = np.exp(rng.uniform(np.log(0.001), np.log(1.0), n)).astype(np.float32)
    den = np.exp(rng.uniform(np.log(0.05), np.log(2.0), n)).astype(np.float32)
    curv = np.exp(rng.uniform(np.log(0.001), np.log(2.0), n)).astype(np.float32)
    loc = np.exp(rng.uniform(np.log(0.01), np.log(1.0), n)).astype(np.float32)
    true = 0.4 * raw**0.7 * (loc / 0.1) ** 0.6
    return rng.normal(0, true), raw, dep, den, curv, loc


def test_the_local_form_learns_what_the_local_departure_says():
    """fit_additive_map in the additive-local form on one draw, scored on another: calibrated where the
    neighbourhood is corrected hard and where it is not, where the plain additive form is off in both."""
    from gearscan.inference.uncertainty import (
        FORM_FEATURES,
        fit_additive_map,
        map_form,
        sigma_map_from_json,
    )

    err, raw, dep, den, curv, loc = _local_world(60_000, 0)
    cal, _ = fit_additive_map(err, raw, dep, den, curvature=curv, local_departure=loc,
                              features=FORM_FEATURES["additive-local"])
    plain, _ = fit_additive_map(err, raw, dep, den)
    assert map_form(cal) == "additive-local" and map_form(plain) == "additive" and cal.needs_local
    assert sigma_map_from_json(cal.to_json()) == cal
    err2, raw2, dep2, den2, curv2, loc2 = _local_world(60_000, 1)
    local = cal(raw2, dep2, den2, curvature=curv2, local_departure=loc2)
    for part in (loc2 > 0.3, loc2 < 0.03):
        assert reliability(err2[part], local[part]).ece < 0.02
        assert reliability(err2[part], plain(raw2, dep2, den2)[part]).ece > 0.05
    with pytest.raises(ValueError, match="reads the curvature"):
        cal(raw2, dep2, den2, local_departure=loc2)
    with pytest.raises(ValueError, match="need a map"):
        fit_additive_map(err, raw, dep, den, features=FORM_FEATURES["additive-local"])
    # a still-burst gate reads the map at zero departure, its own and the local one
    zero = np.zeros_like(dep2)
    ratio = cal.departure_factor(zero, zero) / cal.departure_factor(dep2, loc2)
    at_zero = cal(raw2, zero, den2, curvature=curv2, local_departure=zero)
    np.testing.assert_allclose(local * ratio, at_zero, rtol=1e-4)
    with pytest.raises(ValueError, match="local departure"):
        cal.departure_factor(dep2)


def _split_world(n: int, seed: int):
    """Synthetic MC pixels whose error follows the aleatoric part of the sigma alone, while the total adds a spread
    of the passes that tells nothing about the error: what a map in the total cannot see."""
    rng = np.random.default_rng(seed)
    data = np.exp(rng.uniform(np.log(0.01), np.log(0.3), n)).astype(np.float32)
    spread = np.exp(rng.uniform(np.log(0.001), np.log(0.5), n)).astype(np.float32)
    total = np.sqrt(data**2 + spread**2).astype(np.float32)
    ones = np.ones(n, np.float32)
    return rng.normal(0, 0.8 * data), total, data, {"departure": 0.01 * ones, "density": 0.3 * ones,
                                                    "curvature": 0.01 * ones, "local_departure": 0.01 * ones}


def test_the_data_form_reads_the_aleatoric_sigma_apart():
    """fit_additive_map in the additive-local-data form (MC mode, sigma_map_data_mc_rule.md) on one draw, scored on
    another: calibrated where the passes spread wide and where they agree, where the form reading only the total is
    off in both; the map round-trips through JSON and refuses a call without the aleatoric sigma."""
    from gearscan.inference.uncertainty import (
        FORM_FEATURES,
        fit_additive_map,
        map_form,
        sigma_map_from_json,
    )

    err, total, data, rest = _split_world(60_000, 0)
    cal, _ = fit_additive_map(err, total, sigma_data=data, features=FORM_FEATURES["additive-local-data"], **rest)
    local, _ = fit_additive_map(err, total, features=FORM_FEATURES["additive-local"], **rest)
    assert map_form(cal) == "additive-local-data" and cal.needs_sigma_data and not local.needs_sigma_data
    assert sigma_map_from_json(cal.to_json()) == cal
    err2, total2, data2, rest2 = _split_world(60_000, 1)
    ratio = total2 / data2
    for part in (ratio > 5, ratio < 1.2):  # the passes spread far beyond the data sigma / agree
        assert reliability(err2[part], cal(total2, sigma_data=data2, **rest2)[part]).ece < 0.02
        assert reliability(err2[part], local(total2, **rest2)[part]).ece > 0.05
    with pytest.raises(ValueError, match="reads the sigma_data"):
        cal(total2, **rest2)


def test_a_data_map_reads_the_propagated_data_sigma_of_the_passes():
    """to_phase_result hands the map the aleatoric sigma it propagated: a map that is the data sigma alone
    (slope 1 on it, 0 on the total) reports it whatever the passes' spread."""
    from gearscan.inference.uncertainty import (
        AdditiveSigmaMap,
        HingeTerm,
        MomentStats,
        phase_sigma,
        to_phase_result,
    )

    rng = np.random.default_rng(0)
    M, D = (torch.from_numpy(rng.normal(0, 1, (1, 8, 8)).astype(np.float32)) for _ in range(2))
    dv, mv = (torch.from_numpy(rng.uniform(1e-4, 1e-2, (1, 8, 8)).astype(np.float32)) for _ in range(2))
    stats = MomentStats(M, D, mv, mv, dv, dv)
    only_data = AdditiveSigmaMap(0.0, (HingeTerm("sigma", 0.0), HingeTerm("sigma_data", 1.0)))
    r = to_phase_result(stats, mode="mc20", calibration=only_data)
    expected = phase_sigma(M[0].numpy(), D[0].numpy(), dv[0].numpy(), dv[0].numpy())
    np.testing.assert_allclose(r.sigma_total, expected, rtol=1e-4)
    plain = to_phase_result(stats, mode="mc20")
    assert np.all(plain.sigma_total > r.sigma_total)  # the total carries the passes' spread too
