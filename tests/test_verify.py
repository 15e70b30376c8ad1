"""Measurement uncertainty from a master gear (recon.substitution) and `gearscan verify` / `twin certificate`."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from gearscan.recon.inspect import profile_quantities
from gearscan.recon.substitution import (
    BUDGETED,
    CONFORMS,
    DOES_NOT_CONFORM,
    UNDECIDED,
    Evaluation,
    FlankTrace,
    SubstitutionError,
    bound_uncertainty,
    conformity,
    error_functionals,
    profile_truth,
    quantity_uncertainty,
    runout_about_gear_axis,
    tolerance_factor,
)

EVAL = Evaluation(l_a=1.0, l_b=9.5, xi_start=0.1, xi_end=0.95)  # roll length 0 at the involute start, 10 at the tip
ALPHA = math.radians(20.0)


def test_iso15530_budget_by_hand():
    """The ISO 15530-3 headline form (kept for comparison): readings 1, 2, 3 of a master certified 1 +- 0: bias 1,
    u_p 1 at 2 dof, Student's 95.45 % k at 2 dof = 4.53, U = k u_p + |bias|; a certificate's U (k = 2) raises the
    degrees of freedom (Welch-Satterthwaite)."""
    q = quantity_uncertainty("fp", 1.0, 0.0, [1.0, 2.0, 3.0])
    assert (q.mean, q.bias, q.u_p, q.dof) == (2.0, 1.0, 1.0, 2.0)
    assert q.k == pytest.approx(4.527, abs=1e-3) and q.U == pytest.approx(q.k + 1.0)
    q2 = quantity_uncertainty("fp", 1.0, 4.0, [1.0, 2.0, 3.0])
    assert q2.u_cal == 2.0 and q2.dof == pytest.approx(50.0) and q2.U == pytest.approx(q2.k * math.sqrt(5.0) + 1.0)
    assert quantity_uncertainty("fp", 0.0, 0.0, [0.0, 1.0, 2.0, 3.0, 4.0]).k == pytest.approx(2.869, abs=1e-3)


def test_iso15530_form_holds_only_when_the_error_does_not_depend_on_the_gear():
    """Simulated instrument: bias 1.5 um, noise 2 um, five master readings per statement. With Student's k a fresh
    reading of a gear with the SAME bias lies within U (>= 95 %); k = 2 at five readings, or U without the bias,
    falls short. A gear whose reading carries another bias (a side-dependent slope error read on the other side)
    escapes U far more often: why the headline form is not shipped."""
    rng = np.random.default_rng(7)
    bias, noise, n, trials = 1.5, 2.0, 5, 4000
    held = held_k2 = held_nobias = held_other = 0
    for _ in range(trials):
        q = quantity_uncertainty("F_alpha", 10.0, 0.0, 10.0 + bias + noise * rng.standard_normal(n))
        err = bias + noise * rng.standard_normal()
        held += abs(err) <= q.U
        held_k2 += abs(err) <= 2.0 * q.u_p + abs(q.bias)
        held_nobias += abs(err) <= q.k * q.u_p
        held_other += abs(err - 8.0) <= q.U
    assert held / trials >= 0.95
    assert held_k2 / trials < 0.95 and held_nobias / trials < 0.95
    assert held_other / trials < 0.9  # (0.55 here) far from the 95 % it promises


def test_tolerance_factor_and_bound_by_hand():
    """One-sided 95 %/95 % normal tolerance factors (ISO 16269-6 tables: 4.203 at n = 5, 2.911 at 10, 2.396 at 20);
    U = mean + k s + the certificate's U."""
    assert [round(tolerance_factor(n), 3) for n in (5, 10, 20)] == [4.203, 2.911, 2.396]
    b = bound_uncertainty("fp", [1.0, 2.0, 3.0, 2.0, 2.0], U_cal=0.5)
    assert b.mean == 2.0 and b.s == pytest.approx(math.sqrt(0.5)) and b.n == 5
    assert b.U == pytest.approx(2.0 + 4.2034 * math.sqrt(0.5) + 0.5, abs=1e-3)
    with pytest.raises(SubstitutionError, match="at least 3"):
        bound_uncertainty("fp", [1.0, 2.0])
    with pytest.raises(SubstitutionError, match="finite numbers >= 0"):
        bound_uncertainty("fp", [1.0, 2.0, math.nan])


def _flank_data(rng, teeth, profile_um, err_um, pos_true, pos_err, drop=0):
    """Flank traces and positions as an inspection reports them, from true offsets plus errors; each flank misses up
    to ``drop`` bins at the root end (bins with too few points)."""
    full = EVAL.centres_mm()  # 20 bin centres over the evaluation range

    def trace(t, s):
        roll = full[rng.integers(0, drop + 1):]
        xi = EVAL.xi(roll)
        return FlankTrace(t, s, tuple(roll), tuple(profile_um(s, xi) + err_um(t, s, xi) + rng.normal() * 50))

    flanks = [trace(t, s) for t in range(teeth) for s in ("left", "right")]
    const = rng.normal() * 100  # the inspection's datum is its own: a constant cancels
    positions = {s: tuple(np.asarray(pos_true[s]) + np.asarray(pos_err[s]) + const) for s in ("left", "right")}
    return flanks, positions


def _headlines(flanks, positions):
    """The inspection's headline definitions on traces and positions (recon.inspect.inspect_gear)."""
    prof = [profile_quantities(np.asarray(f.roll_mm), np.asarray(f.trace_um), EVAL.l_b - EVAL.l_a) for f in flanks]
    p = {s: np.asarray(v) for s, v in positions.items()}
    return {"F_alpha": max(v[0] for v in prof), "ff_alpha": max(v[1] for v in prof),
            "fH_alpha": max((v[2] for v in prof), key=abs),
            "fp": max(float(np.abs(v - np.roll(v, 1)).max()) for v in p.values()),
            "Fp": max(float(v.max() - v.min()) for v in p.values()),
            "Fr_gear_axis": runout_about_gear_axis(p, ALPHA)}


def test_every_headline_error_is_within_its_bound():
    """The bound method's premise, on random gears and random instrument errors (side-dependent slopes, form noise,
    position noise, root-end bins not read on some flanks): |Q(read) - Q(true)| <= Q'(read - true) for every headline,
    |fH_alpha| by magnitude, the truth over every bin. It is tight: somewhere each bound is nearly reached. A reading
    equal to the truth (up to the datum's constants) has every bound 0."""
    rng = np.random.default_rng(11)
    teeth = 12
    ratio = dict.fromkeys(BUDGETED, 0.0)
    for trial in range(200):
        slope, crown = rng.normal(0, 10, 2)
        side_slope = {"left": rng.normal(0, 5), "right": rng.normal(0, 5)}

        def profile(side, xi, slope=slope, crown=crown):
            return slope * xi + crown * 4 * xi * (1 - xi)

        def error(tooth, side, xi, amp=rng.uniform(0, 3), seed=trial, side_slope=side_slope):
            r = np.random.default_rng([seed, tooth, side == "left"])
            return side_slope[side] * xi + amp * r.standard_normal(xi.size)

        pos_true = {s: rng.normal(0, 10, teeth) for s in ("left", "right")}
        pos_err = {s: rng.normal(0, 2, teeth) for s in ("left", "right")}
        flanks, positions = _flank_data(rng, teeth, profile, error, pos_true, pos_err, drop=3 * (trial % 2))
        read = _headlines(flanks, positions)
        true_flanks, true_pos = _flank_data(rng, teeth, profile, lambda t, s, xi: 0 * xi, pos_true,
                                            {s: np.zeros(teeth) for s in pos_true})
        true = _headlines(true_flanks, true_pos)
        bound = error_functionals(flanks, positions, EVAL, profile, pos_true, ALPHA)
        for key in BUDGETED:
            gap = abs(abs(read[key]) - abs(true[key]))
            assert gap <= bound[key] + 1e-9, (trial, key, read[key], true[key])
            ratio[key] = max(ratio[key], gap / bound[key])
        zero = error_functionals(true_flanks, true_pos, EVAL, profile, pos_true, ALPHA)
        assert max(zero.values()) < 1e-9
    assert min(ratio.values()) > 0.9, ratio


@pytest.mark.parametrize(("value", "U", "T", "decision"), [
    (10.0, 2.0, 14.0, CONFORMS), (12.0, 2.0, 14.0, CONFORMS), (12.5, 2.0, 14.0, UNDECIDED),
    (16.0, 2.0, 14.0, UNDECIDED), (16.5, 2.0, 14.0, DOES_NOT_CONFORM), (-13.0, 2.0, 14.0, UNDECIDED),
    (-10.0, 2.0, 14.0, CONFORMS)])
def test_conformity_iso14253(value, U, T, decision):
    assert conformity(value, U, T) == decision


def test_profile_truth_of_slope_and_crown():
    """Over xi 0.1-0.95 in 20 bins: a slope s rises s * 0.85 along the mean line and has no form; a crown c
    (4 c xi (1 - xi)) rises 4 c (1 - 0.1 - 0.95) * 0.85 and its form is the parabola's range about its chord."""
    s = profile_truth(lambda xi: 8.0 * xi, 0.1, 0.95, 20)
    assert s["fH_alpha"] == pytest.approx(8.0 * 0.85) and s["ff_alpha"] == pytest.approx(0.0, abs=1e-9)
    assert s["F_alpha"] == pytest.approx(8.0 * 0.85 * 19 / 20)  # between the first and the last bin's centre
    c = profile_truth(lambda xi: 4 * 4.0 * xi * (1 - xi), 0.1, 0.95, 20)
    assert c["fH_alpha"] == pytest.approx(4 * 4.0 * (1 - 1.05) * 0.85, rel=1e-9)
    assert c["ff_alpha"] == pytest.approx(2.60, abs=0.01)


def test_runout_about_gear_axis_of_one_turned_tooth():
    """Tooth 3 turned +30 um along the pitch circle narrows one tooth space and widens the next: a ball sits 30 / (2
    tan 20 deg) = 41.2 um out and in, a range of 82.4 um (the inspection benchmark reads 82.1)."""
    pos = np.zeros(20)
    pos[3] = 30.0
    assert runout_about_gear_axis({"right": pos, "left": pos}, ALPHA) == pytest.approx(30 / math.tan(ALPHA))


# ----------------------------------------------------------------------------------------- gearscan.verify


MASTER = {"profile_slope_um": 8.0, "profile_crown_um": 4.0, "pitch_errors_um": {5: 15.0}}


def _truth(**defects):
    from gearscan.core.gear import GearSpec
    from gearscan.twin.defects import GearDefects

    return {"truth": GearDefects(**defects).truth(GearSpec())}


def test_twin_certificate_from_the_truth():
    from gearscan.verify import twin_certificate

    cert = twin_certificate(_truth(**MASTER, eccentricity_um=20.0))
    q = cert.headline_um()
    assert set(q) == set(BUDGETED) and cert.U_um == dict.fromkeys(BUDGETED, 0.0)
    assert q["fp"] == pytest.approx(15.0) and q["Fp"] == pytest.approx(15.0)
    assert q["Fr_gear_axis"] == pytest.approx(15 / math.tan(ALPHA))
    assert q["fH_alpha"] == pytest.approx((8.0 + 4 * 4.0 * (1 - 1.05)) * 0.85)
    assert cert.profile_um["left"].slope == 8.0 and cert.positions_um["left"][5] - cert.positions_um["left"][4] == pytest.approx(15.0)


@pytest.mark.parametrize(("defects", "match"), [
    ({"chips": [{"tooth": 1, "size_mm": 0.3}]}, "chipped"), ({"pressure_angle_deg": 21.0}, "pressure_angle_deg"),
    ({"wear": [{"tooth": 2, "depth_um": 6.0}]}, "worn")])
def test_twin_certificate_refuses_what_a_master_is_not(defects, match):
    from gearscan.verify import VerifyError, twin_certificate

    with pytest.raises(VerifyError, match=match):
        twin_certificate(_truth(**defects))
    with pytest.raises(VerifyError, match="no twin truth"):
        twin_certificate({})
    with pytest.raises(VerifyError, match="incomplete or malformed"):
        twin_certificate({"truth": {"gear": {"teeth": 20}}})


def test_a_perfect_cloud_reads_the_certificate():
    """The certificate is what the inspection reads on a perfect measurement: a noise-free cloud of the as-built
    master (slope, crown, a turned tooth) through `inspect_gear` gives its headline values within 0.3 um, and the
    error bounds of that reading are as small."""
    import open3d as o3d

    from gearscan.core.gear import GearSpec
    from gearscan.recon.inspect import inspect_gear
    from gearscan.twin.defects import GearDefects
    from gearscan.verify import inspection_readings, twin_certificate

    nominal = GearSpec(teeth=20, module=2.0)
    defects = GearDefects(**MASTER)
    o3d.utility.random.seed(3)
    mesh = defects.mesh(nominal, flank_points=400, layer_mm=5.0)
    pts = np.asarray(mesh.sample_points_uniformly(600_000).points)
    pts = pts[np.abs(pts[:, 2]) < 3.0]  # the inspection's mid-face band
    insp = inspect_gear(pts, np.full(len(pts), 0.001), nominal)
    cert = twin_certificate({"truth": defects.truth(nominal)})
    read = inspection_readings(insp)
    for key, value in cert.headline_um().items():
        assert read[key] == pytest.approx(value, abs=0.3), key
    flanks = [FlankTrace(f.tooth, f.side, f.roll_mm, f.trace_um) for f in insp.flanks if f.measured]
    l_a, l_b = insp.settings["evaluation_roll_mm"]
    bounds = error_functionals(flanks, insp.position_um, Evaluation(l_a, l_b, 0.1, 0.95),
                               lambda side, xi: cert.profile_um[side].offset(xi), cert.positions_um, ALPHA)
    assert max(bounds.values()) < 0.3, bounds


def _report(folder, truth_meta, module=2.0, fingerprint="abc", slope_err=1.0, pos_err=0.5, seed=0, datum=None):
    """A `gearscan inspect` report.json of a master whose flanks read the truth plus a slope error and noise."""
    from gearscan.verify import twin_certificate

    cert = twin_certificate(truth_meta)
    rng = np.random.default_rng(seed)
    teeth, roll = 20, EVAL.centres_mm()
    flanks = [{"tooth": t, "side": s, "measured": True, "roll_mm": roll.tolist(),
               "trace_um": (cert.profile_um[s].offset(EVAL.xi(roll)) + slope_err * EVAL.xi(roll)
                            + 0.3 * rng.standard_normal(20)).tolist()} for t in range(teeth) for s in ("left", "right")]
    pos = {s: (np.asarray(cert.positions_um[s]) + pos_err * rng.standard_normal(teeth)).tolist()
           for s in ("left", "right")}
    folder.mkdir(parents=True)
    (folder / "report.json").write_text(json.dumps({
        "summary_um": {"fp": 15.5, "Fp": 15.2, "Fr": 99.0, "F_alpha": 9.0, "ff_alpha": 3.0, "fH_alpha": 7.0},
        "model": {"path": "m.safetensors", "fingerprint": fingerprint},
        "inspection": {"teeth": teeth, "module": module, "runout_about_gear_axis_um": 41.0, "flanks": flanks,
                       "position_um": pos, "settings": {"evaluation_roll_mm": [EVAL.l_a, EVAL.l_b], "xi_start": 0.1,
                                                        "xi_end": 0.95, "bins": 20}
                                                       | ({} if datum is None else {"datum": datum})}}))
    return folder


def test_verify_writes_a_statement_inspect_can_use(tmp_path):
    """Five mountings of a twin master through the CLI: each quantity's U is the tolerance bound of its error bounds;
    `inspect` takes the statement for a gear of the type (graded: ISO 14253-1 decisions, none for Fr_gear_axis) and
    refuses one of another type; another model or evaluation is warned about."""
    from gearscan.cli import app
    from gearscan.verify import VerifyError, applied_uncertainty, load_statement, twin_certificate

    meta = _truth(**MASTER)
    cert = tmp_path / "cert.json"
    cert.write_text(twin_certificate(meta).model_dump_json())
    reports = [_report(tmp_path / f"r{i}", meta, seed=i) for i in range(5)]
    out = tmp_path / "st" / "uncertainty.json"
    res = CliRunner().invoke(app, ["verify", str(cert), *map(str, reports), "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert "fewer than the 20 ISO 15530-3 asks for" in res.output
    st = json.loads(out.read_text())
    fh = st["quantities"]["fH_alpha"]
    # every flank carries the instrument's +1 um slope error (0.85 um over the range) and 0.3 um noise
    assert all(0.5 < v < 1.6 for v in fh["samples"])
    assert fh["U"] == pytest.approx(np.mean(fh["samples"]) + 4.2034 * np.std(fh["samples"], ddof=1), abs=1e-3)
    assert st["quantities"]["Fr_gear_axis"]["headline"] == [41.0] * 5  # the runout about the gear axis, not Fr's 99
    assert (tmp_path / "st" / "uncertainty.md").read_text().count("|") > 20
    loaded = load_statement(out)
    tol8 = {"fp": 17.0, "Fp": 48.0, "Fr": 43.0, "F_alpha": 22.0, "ff_alpha": 17.0, "fH_alpha": 14.0}
    applied = applied_uncertainty(loaded, {k: 10.0 for k in BUDGETED}, 20, 2.0, "abc", tol8,
                                  {"xi_start": 0.1, "xi_end": 0.95, "bins": 20})
    assert applied.warnings == ()
    row = applied.readings["fH_alpha"]
    assert row.U == pytest.approx(fh["U"]) and row.decision == conformity(10.0, fh["U"], 14.0)
    assert applied.readings["Fr_gear_axis"].decision is None
    other = applied_uncertainty(loaded, {}, 20, 2.0, "zzz", None, {"xi_start": 0.2, "xi_end": 0.95, "bins": 20})
    assert len(other.warnings) == 2 and other.readings["fp"].value is None
    with pytest.raises(VerifyError, match="master of 20 teeth, module 2; this gear has 30"):
        applied_uncertainty(loaded, {}, 30, 2.0, "abc", None)


def test_a_reading_on_part_of_the_gear_never_conforms(tmp_path):
    """U bounds a headline over what was read: a value within the tolerance by U but read on part of the gear, or a
    profile with bins left out, is undecided, and says why; one beyond the tolerance by U still does not conform."""
    from gearscan.verify import LoadedStatement, applied_uncertainty

    st = LoadedStatement(20, 2.0, dict.fromkeys(BUDGETED, 1.0), None, {}, "s.json")
    tol = {"fp": 17.0, "Fp": 48.0, "F_alpha": 22.0, "ff_alpha": 17.0, "fH_alpha": 14.0}
    whole = {k: (40, 40) for k in ("fp", "Fp", "F_alpha", "ff_alpha", "fH_alpha")} | {"Fr": (20, 20)}
    read = dict.fromkeys(BUDGETED, 5.0) | {"Fp": 60.0}
    full = applied_uncertainty(st, read, 20, 2.0, None, tol, coverage=whole)
    assert {k: r.decision for k, r in full.readings.items() if r.decision} == {
        "fp": CONFORMS, "Fp": DOES_NOT_CONFORM, "F_alpha": CONFORMS, "ff_alpha": CONFORMS, "fH_alpha": CONFORMS}
    part = applied_uncertainty(st, read, 20, 2.0, None, tol, coverage=whole | {"fp": (38, 40), "Fp": (38, 40)})
    assert part.readings["fp"].decision == UNDECIDED and "38 of 40" in part.readings["fp"].why
    assert part.readings["Fp"].decision == DOES_NOT_CONFORM  # beyond by U on what was read: the rest cannot help
    bins = applied_uncertainty(st, read, 20, 2.0, None, tol, coverage=whole, bins_left_out=3)
    assert all(bins.readings[k].decision == UNDECIDED for k in ("F_alpha", "ff_alpha", "fH_alpha"))
    assert bins.readings["fp"].decision == CONFORMS


def test_verify_refusals(tmp_path):
    from gearscan.cli import app
    from gearscan.verify import twin_certificate

    runner = CliRunner()
    meta = _truth(**MASTER)
    cert = tmp_path / "cert.json"
    body = json.loads(twin_certificate(meta).model_dump_json())
    r = [_report(tmp_path / f"r{i}", meta, seed=i) for i in range(3)]
    u = str(tmp_path / "u.json")

    def run(*args):
        return runner.invoke(app, ["verify", *map(str, args), "-o", u])

    cert.write_text(json.dumps(body | {"positions_um": {"left": [0.0] * 20}}))
    res = run(cert, *r)
    assert res.exit_code == 2 and "needs both sides" in res.output
    cert.write_text(json.dumps(body | {"U_um": {"fp": 1.0}}))
    res = run(cert, *r)
    assert res.exit_code == 2 and "U_um: " in res.output
    cert.write_bytes(b"\xff\xfe not json")
    assert run(cert, *r).exit_code == 2
    cert.write_text(json.dumps(body))
    res = run(cert, *r[:2])
    assert res.exit_code == 2 and "at least 3" in res.output
    res = run(cert, r[0], r[1], r[0])
    assert res.exit_code == 2 and "given twice" in res.output
    odd = _report(tmp_path / "odd", _truth(), module=2.5)
    res = run(cert, *r[:2], odd)
    assert res.exit_code == 2 and "module 2.5" in res.output
    other = _report(tmp_path / "other", meta, fingerprint="zzz")
    res = run(cert, *r[:2], other)
    assert res.exit_code == 2 and "differ in their models" in res.output
    res = run(cert, *r[:2], tmp_path / "missing")
    assert res.exit_code == 2 and "missing: No such file" in res.output
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "report.json").write_text(json.dumps({"summary_um": [], "inspection": 3}))
    res = run(cert, *r[:2], broken)
    assert res.exit_code == 2 and "not a `gearscan inspect` report.json" in res.output
    partial = _report(tmp_path / "partial", meta)
    d = json.loads((partial / "report.json").read_text())
    d["inspection"]["flanks"][0]["measured"] = False
    (partial / "report.json").write_text(json.dumps(d))
    res = run(cert, *r[:2], partial)
    assert res.exit_code == 2 and "39 of 40 flanks" in res.output
    assert not (tmp_path / "u.json").exists()


@pytest.mark.parametrize(("body", "match"), [
    ({"kind": "x"}, "not a statement"), ({"kind": "gearscan uncertainty statement", "quantities": []}, "malformed"),
    ({"kind": "gearscan uncertainty statement", "quantities": {"fp": {"U": 1.0}}, "gear": {"teeth": 20.7, "module": 2}},
     "whole teeth"),
    ({"kind": "gearscan uncertainty statement", "quantities": {"fp": {"U": -1.0}}, "gear": {"teeth": 20, "module": 2}},
     "finite U >= 0")])
def test_a_malformed_statement_is_refused_by_name(tmp_path, body, match):
    from gearscan.verify import VerifyError, load_statement

    path = tmp_path / "s.json"
    path.write_text(json.dumps(body))
    with pytest.raises(VerifyError, match=match):
        load_statement(path)


def test_twin_certificate_cli(tmp_path):
    """`gearscan twin certificate` on a rendered twin recording writes what `verify` loads."""
    from gearscan.cli import app
    from gearscan.core.rig import default_rig
    from gearscan.twin.defects import GearDefects
    from gearscan.twin.recordings import render_recording
    from gearscan.verify import load_certificate

    rec = tmp_path / "rec"
    render_recording(rec, rig=default_rig(64, 64), defects=GearDefects(profile_slope_um=5.0), bursts=1)
    res = CliRunner().invoke(app, ["twin", "certificate", str(rec), "-o", str(tmp_path / "c.json")])
    assert res.exit_code == 0, res.output
    cert = load_certificate(tmp_path / "c.json")
    assert cert.headline_um()["fH_alpha"] == pytest.approx(5.0 * 0.85)
    plain = tmp_path / "plain"
    render_recording(plain, rig=default_rig(64, 64), bursts=1)
    res = CliRunner().invoke(app, ["twin", "certificate", str(plain), "-o", str(tmp_path / "d.json")])
    assert res.exit_code == 2 and "no twin truth" in res.output


def test_a_statement_holds_for_one_datum(tmp_path):
    """Pitch and runout are read about the inspection's datum axis: reports about different datums make no statement,
    the statement names its datum (a report from before the datum was recorded: the flank fit it was read about),
    and a gear read about another datum gets the statement's U with a warning."""
    from gearscan.cli import app
    from gearscan.verify import (
        LEGACY_DATUM,
        applied_uncertainty,
        load_statement,
        twin_certificate,
        verify,
    )

    meta = _truth(**MASTER)
    cert = twin_certificate(meta)
    tip = [_report(tmp_path / f"t{i}", meta, seed=i, datum="tip") for i in range(3)]
    assert verify(cert, tip).datum == "tip"
    assert verify(cert, [_report(tmp_path / f"old{i}", meta, seed=i) for i in range(3)]).datum == LEGACY_DATUM
    cert_file = tmp_path / "cert.json"
    cert_file.write_text(cert.model_dump_json())
    mixed = [*tip[:2], _report(tmp_path / "teeth", meta, datum="teeth")]
    res = CliRunner().invoke(app, ["verify", str(cert_file), *map(str, mixed), "-o", str(tmp_path / "u.json")])
    assert res.exit_code == 2 and "differ in their datums" in res.output
    out = tmp_path / "st.json"
    res = CliRunner().invoke(app, ["verify", str(cert_file), *map(str, tip), "-o", str(out)])
    assert res.exit_code == 0, res.output
    loaded = load_statement(out)
    assert loaded.datum == "tip" and "the master's is 'tip'" in out.with_suffix(".md").read_text()
    same = applied_uncertainty(loaded, {}, 20, 2.0, "abc", None, datum="tip")
    other = applied_uncertainty(loaded, {}, 20, 2.0, "abc", None, datum="teeth")
    assert same.warnings == () and len(other.warnings) == 1 and "datum 'tip'" in other.warnings[0]
