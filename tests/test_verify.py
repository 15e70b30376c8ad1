"""The substitution method (recon.substitution) and `gearscan verify` / `twin certificate` (gearscan.verify)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import stats
from typer.testing import CliRunner

from gearscan.recon.substitution import (
    CONFORMS,
    DOES_NOT_CONFORM,
    QUANTITIES,
    UNDECIDED,
    SubstitutionError,
    conformity,
    profile_truth,
    quantity_uncertainty,
    runout_about_gear_axis,
    substitution_uncertainty,
)


def test_budget_by_hand():
    """Readings 1, 2, 3 of a master certified 1 +- 0: bias 1, u_p 1 with 2 degrees of freedom, so k is Student's
    95.45 % factor at 2 dof (4.53, not 2), and U = k u_p + |bias|."""
    q = quantity_uncertainty("fp", 1.0, 0.0, [1.0, 2.0, 3.0])
    assert (q.mean, q.bias, q.u_p, q.dof) == (2.0, 1.0, 1.0, 2.0)
    assert q.k == pytest.approx(4.527, abs=1e-3)
    assert q.U == pytest.approx(q.k * 1.0 + 1.0)
    # a certificate's own U (k = 2) enters as u_cal = U / 2, and raises the degrees of freedom (Welch-Satterthwaite)
    q2 = quantity_uncertainty("fp", 1.0, 4.0, [1.0, 2.0, 3.0])
    assert q2.u_cal == 2.0 and q2.dof == pytest.approx((4 + 1) ** 2 / (1 / 2))
    assert q2.U == pytest.approx(q2.k * math.sqrt(5.0) + 1.0) and q2.k < q.k
    # readings that agree exactly: no repeatability term, k = 2, U = the certificate's plus the bias
    q3 = quantity_uncertainty("fp", 0.0, 1.0, [0.5, 0.5, 0.5])
    assert q3.dof == math.inf and q3.U == pytest.approx(1.0 + 0.5)


def test_stated_U_covers_a_fresh_reading_of_another_gear():
    """What U promises: a single reading of a gear of the type, by the same instrument, lies within U of its truth at
    least 95 % of the time. Simulated instrument: bias 1.5 um, noise 2 um; five master readings per statement. With
    Student's k the promise holds; with k = 2 at five readings it does not (so this test can fail)."""
    rng = np.random.default_rng(7)
    bias, noise, n, trials = 1.5, 2.0, 5, 4000
    held, held_k2 = 0, 0
    for _ in range(trials):
        readings = 10.0 + bias + noise * rng.standard_normal(n)
        q = quantity_uncertainty("F_alpha", 10.0, 0.0, readings)
        err = abs(bias + noise * rng.standard_normal())  # another gear's reading minus its truth
        held += err <= q.U
        held_k2 += err <= 2.0 * q.u_p + abs(q.bias)
    assert held / trials >= 0.95
    # without the bias a biased instrument's U would not hold either
    zero_bias = quantity_uncertainty("F_alpha", 0.0, 0.0, [0.0, 2.0, -2.0, 1.0, -1.0])
    assert zero_bias.bias == 0.0
    assert held_k2 / trials < held / trials


def test_refusals_name_what_is_wrong():
    with pytest.raises(SubstitutionError, match="at least 3"):
        quantity_uncertainty("fp", 0.0, 0.0, [1.0, 2.0])
    with pytest.raises(SubstitutionError, match="finite readings"):
        quantity_uncertainty("fp", 0.0, 0.0, [1.0, 2.0, math.nan])
    with pytest.raises(SubstitutionError, match="U >= 0"):
        quantity_uncertainty("fp", 0.0, -1.0, [1.0, 2.0, 3.0])
    with pytest.raises(SubstitutionError, match="unknown quantities"):
        substitution_uncertainty({"Fx": (0.0, 0.0)}, [{"Fx": 1.0}] * 3)
    with pytest.raises(SubstitutionError, match=r"Fp: not measured in reading\(s\) \[1\]"):
        substitution_uncertainty({"Fp": (0.0, 0.0)}, [{"Fp": 1.0}, {"Fp": None}, {"Fp": 2.0}])


@pytest.mark.parametrize(("value", "U", "T", "decision"), [
    (10.0, 2.0, 14.0, CONFORMS), (12.0, 2.0, 14.0, CONFORMS), (12.5, 2.0, 14.0, UNDECIDED),
    (16.0, 2.0, 14.0, UNDECIDED), (16.5, 2.0, 14.0, DOES_NOT_CONFORM), (-13.0, 2.0, 14.0, UNDECIDED),
    (-10.0, 2.0, 14.0, CONFORMS)])
def test_conformity_iso14253(value, U, T, decision):
    assert conformity(value, U, T) == decision


def test_profile_truth_of_slope_and_crown():
    """Over xi 0.1-0.95 in 20 bins: a slope s rises s * 0.85 along the mean line and has no form; a crown c
    (4 c xi (1 - xi)) has the mean line's rise 4 c (1 - 0.1 - 0.95) * 0.85 and a form range of about c's parabola."""
    s = profile_truth(lambda xi: 8.0 * xi, 0.1, 0.95, 20)
    assert s["fH_alpha"] == pytest.approx(8.0 * 0.85) and s["ff_alpha"] == pytest.approx(0.0, abs=1e-9)
    assert s["F_alpha"] == pytest.approx(8.0 * 0.85 * 19 / 20)  # between the first and the last bin's centre
    c = profile_truth(lambda xi: 4 * 4.0 * xi * (1 - xi), 0.1, 0.95, 20)
    assert c["fH_alpha"] == pytest.approx(4 * 4.0 * (1 - 1.05) * 0.85, rel=1e-9)
    assert 0.6 < c["ff_alpha"] < 1.0 * 4 * 4.0 * (0.425**2)  # a parabola's range about its chord over half-width 0.425


def test_runout_about_gear_axis_of_one_turned_tooth():
    """Tooth 3 turned +30 um along the pitch circle narrows one tooth space and widens the next: a ball sits 30 / (2
    tan 20 deg) = 41.2 um out and in, a range of 82.4 um (the inspection benchmark reads 82.1)."""
    pos = np.zeros(20)
    pos[3] = 30.0
    fr = runout_about_gear_axis({"right": pos, "left": pos}, math.radians(20.0))
    assert fr == pytest.approx(2 * 30 / (2 * math.tan(math.radians(20))))


# ----------------------------------------------------------------------------------------- gearscan.verify


def _truth(**defects):
    from gearscan.core.gear import GearSpec
    from gearscan.twin.defects import GearDefects

    return {"truth": GearDefects(**defects).truth(GearSpec())}


def test_twin_certificate_from_the_truth():
    from gearscan.verify import twin_certificate

    cert = twin_certificate(_truth(profile_slope_um=8.0, profile_crown_um=4.0, pitch_errors_um={5: 15.0},
                                   eccentricity_um=20.0))
    q = {k: v.value for k, v in cert.quantities_um.items()}
    assert set(q) == set(QUANTITIES) and all(v.U == 0 for v in cert.quantities_um.values())
    assert q["fp"] == pytest.approx(15.0) and q["Fp"] == pytest.approx(15.0)
    assert q["Fr_gear_axis"] == pytest.approx(2 * 15 / (2 * math.tan(math.radians(20))))
    assert q["fH_alpha"] == pytest.approx((8.0 + 4 * 4.0 * (1 - 1.05)) * 0.85)
    # wear on one flank makes the worst flank's form: a sine dip of 6 um
    worn = twin_certificate(_truth(wear=[{"tooth": 2, "depth_um": 6.0, "side": "right"}]))
    assert worn.quantities_um["ff_alpha"].value > 3.0  # (the wear also moves that flank on the pitch circle: fp)


@pytest.mark.parametrize(("defects", "match"), [
    ({"chips": [{"tooth": 1, "size_mm": 0.3}]}, "chipped"), ({"pressure_angle_deg": 21.0}, "pressure_angle_deg")])
def test_twin_certificate_refuses_what_it_cannot_certify(defects, match):
    from gearscan.verify import VerifyError, twin_certificate

    with pytest.raises(VerifyError, match=match):
        twin_certificate(_truth(**defects))
    with pytest.raises(VerifyError, match="no twin truth"):
        twin_certificate({})


def _report(folder, readings: dict, teeth=20, module=2.0, fingerprint="abc"):
    folder.mkdir(parents=True)
    summary = {k: v for k, v in readings.items() if k != "Fr_gear_axis"} | {"Fr": 99.0}
    (folder / "report.json").write_text(json.dumps({
        "summary_um": summary, "model": {"path": "m.safetensors", "fingerprint": fingerprint},
        "inspection": {"teeth": teeth, "module": module, "runout_about_gear_axis_um": readings["Fr_gear_axis"]}}))
    return folder


def test_verify_writes_a_statement_inspect_can_use(tmp_path):
    """Three readings of a twin master through the CLI: the statement's U is the budget's, `inspect` takes it for a
    gear of the type (graded: ISO 14253-1 decisions) and refuses one of another type before any replay."""
    from gearscan.cli import app
    from gearscan.verify import applied_uncertainty, load_statement

    cert = tmp_path / "cert.json"
    from gearscan.verify import twin_certificate

    c = twin_certificate(_truth(profile_slope_um=8.0, pitch_errors_um={5: 15.0}))
    cert.write_text(c.model_dump_json())
    truth = {k: v.value for k, v in c.quantities_um.items()}
    rng = np.random.default_rng(3)
    reports = [_report(tmp_path / f"r{i}", {k: v + 1.0 + rng.normal() for k, v in truth.items()}) for i in range(3)]
    out = tmp_path / "st" / "uncertainty.json"
    res = CliRunner().invoke(app, ["verify", str(cert), *map(str, reports), "-o", str(out), "--u-w", "fp=0.5"])
    assert res.exit_code == 0, res.output
    assert "fewer than the 20 ISO 15530-3 asks for" in res.output
    st = json.loads(out.read_text())
    readings = [json.loads((r / "report.json").read_text()) for r in reports]
    fp = [r["summary_um"]["fp"] for r in readings]
    expect = quantity_uncertainty("fp", truth["fp"], 0.0, fp, 0.5)
    assert st["quantities"]["fp"]["U"] == pytest.approx(expect.U) and st["u_w_um"] == {"fp": 0.5}
    assert (tmp_path / "st" / "uncertainty.md").read_text().count("|") > 20
    loaded = load_statement(out)
    applied = applied_uncertainty(loaded, {k: 10.0 for k in QUANTITIES}, 20, 2.0, "abc", {"fp": 17.0, "Fp": 48.0,
                                  "Fr": 43.0, "F_alpha": 22.0, "ff_alpha": 17.0, "fH_alpha": 14.0})
    assert "warning" not in applied
    row = applied["quantities"]["fp"]
    assert row["U"] == pytest.approx(expect.U) and row["decision"] == conformity(10.0, expect.U, 17.0)
    other = applied_uncertainty(loaded, {}, 20, 2.0, "other", None)
    assert "decoded by model abc" in other["warning"] and other["quantities"]["fp"]["value"] is None
    from gearscan.verify import VerifyError

    with pytest.raises(VerifyError, match="master of 20 teeth, module 2; this gear has 30"):
        applied_uncertainty(loaded, {}, 30, 2.0, "abc", None)


def test_verify_refusals(tmp_path):
    from gearscan.cli import app

    runner = CliRunner()
    cert = tmp_path / "cert.json"
    cert.write_text(json.dumps({"gear": {"teeth": 20, "module": 2.0}, "quantities_um": {"fp": {"value": 3.0}}}))
    r = [_report(tmp_path / f"r{i}", {k: 1.0 for k in QUANTITIES}) for i in range(3)]
    res = runner.invoke(app, ["verify", str(cert), *map(str, r), "-o", str(tmp_path / "u.json")])
    assert res.exit_code == 2 and "quantities_um.fp.U: Field required" in res.output
    cert.write_text(json.dumps({"gear": {"teeth": 20, "module": 2.0}, "quantities_um": {"fp": {"value": 3.0, "U": 1}}}))
    res = runner.invoke(app, ["verify", str(cert), *map(str, r[:2]), "-o", str(tmp_path / "u.json")])
    assert res.exit_code == 2 and "at least 3" in res.output
    odd = _report(tmp_path / "odd", {k: 1.0 for k in QUANTITIES}, teeth=31)
    res = runner.invoke(app, ["verify", str(cert), *map(str, r[:2]), str(odd), "-o", str(tmp_path / "u.json")])
    assert res.exit_code == 2 and "31 teeth" in res.output
    other = _report(tmp_path / "other", {k: 1.0 for k in QUANTITIES}, fingerprint="zzz")
    res = runner.invoke(app, ["verify", str(cert), *map(str, r[:2]), str(other), "-o", str(tmp_path / "u.json")])
    assert res.exit_code == 2 and "different models" in res.output
    res = runner.invoke(app, ["verify", str(cert), *map(str, r), "--u-w", "fp=-1"])
    assert res.exit_code == 2 and "--u-w 'fp=-1'" in res.output
    res = runner.invoke(app, ["verify", str(cert), *map(str, r), str(tmp_path / "missing")])
    assert res.exit_code == 2 and "missing: No such file" in res.output
    assert not (tmp_path / "u.json").exists()


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
    assert cert.quantities_um["fH_alpha"].value == pytest.approx(5.0 * 0.85)
    plain = tmp_path / "plain"
    render_recording(plain, rig=default_rig(64, 64), bursts=1)
    res = CliRunner().invoke(app, ["twin", "certificate", str(plain), "-o", str(tmp_path / "d.json")])
    assert res.exit_code == 2 and "no twin truth" in res.output


def test_student_factor_matches_scipy():
    """k at 4 dof is Student's two-sided 95.45 % quantile (2.87), as the budget states it."""
    q = quantity_uncertainty("fp", 0.0, 0.0, [0.0, 1.0, 2.0, 3.0, 4.0])
    assert q.dof == pytest.approx(4) and q.k == pytest.approx(stats.t.ppf(0.5 + 0.9545 / 2, 4), abs=2e-3)
