"""``gearscan verify``: what the instrument's ISO 1328-1 readings are worth, from a master gear measured repeatedly.

A master gear's certificate (``gearscan twin certificate`` writes one from a twin recording's truth; a calibration
lab's is typed into the same JSON) and several ``gearscan inspect`` reports of it, each a fresh mounting, give each
quantity's bias, repeatability and expanded uncertainty U (:mod:`gearscan.recon.substitution`). The statement is
written as JSON (``gearscan inspect --uncertainty`` reads it: each reading with its U and, with ``--grade``, the
ISO 14253-1 decision) and Markdown. It holds for gears of the master's type (teeth, module) measured as the master
was (rig, model); ``inspect`` refuses another type and warns on another model.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from gearscan.recon.substitution import (
    K_COVERAGE,
    QUANTITIES,
    RECOMMENDED_READINGS,
    TOLERANCE_KEY,
    QuantityUncertainty,
    SubstitutionError,
    conformity,
    profile_truth,
    runout_about_gear_axis,
    substitution_uncertainty,
)

STATEMENT_KIND = "gearscan uncertainty statement"
CERTIFICATE_KIND = "gearscan master gear certificate"


class VerifyError(ValueError):
    """A certificate, report or statement that cannot be used; the message names the file and what was expected."""


class _Certified(BaseModel):
    model_config = ConfigDict(extra="forbid")
    value: float = Field(allow_inf_nan=False, description="certified value, µm")
    U: float = Field(ge=0, allow_inf_nan=False, description="its expanded uncertainty (k = 2), µm")


class _GearType(BaseModel):
    model_config = ConfigDict(extra="forbid")
    teeth: int = Field(ge=6)
    module: float = Field(gt=0, allow_inf_nan=False)


class Certificate(BaseModel):
    """A master gear's certificate: the gear type and each certified quantity (:data:`QUANTITIES` keys), µm."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: str = CERTIFICATE_KIND
    gear: _GearType
    quantities_um: dict[str, _Certified]
    source: str = Field("", description="who certified it: a lab and its certificate number, or the twin's truth")
    evaluation: dict[str, float] = Field(default_factory=dict, description="profile evaluation range (xi_start, xi_end)")


def load_certificate(path: str | Path) -> Certificate:
    """The certificate at ``path``; :class:`VerifyError` names the file and the field at fault."""
    path = Path(path)
    try:
        cert = Certificate.model_validate_json(path.read_text())
    except OSError as exc:
        raise VerifyError(f"certificate {path}: {exc.strerror or exc}") from exc
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "(top level)"
        raise VerifyError(f"certificate {path}: {where}: {first['msg']} (a JSON object with 'gear' {{teeth, module}} "
                          f"and 'quantities_um' {{key: {{value, U}}}}; keys: {', '.join(QUANTITIES)})") from exc
    if cert.kind != CERTIFICATE_KIND:
        raise VerifyError(f"certificate {path}: kind {cert.kind!r}, expected {CERTIFICATE_KIND!r}")
    unknown = sorted(set(cert.quantities_um) - set(QUANTITIES))
    if unknown or not cert.quantities_um:
        raise VerifyError(f"certificate {path}: quantities_um: unknown {unknown or 'none given'}; expected some of "
                          f"{', '.join(QUANTITIES)}")
    return cert


def twin_certificate(meta: dict, xi_start: float = 0.1, xi_end: float = 0.95, bins: int = 20) -> Certificate:
    """The certificate of a twin recording's gear from its truth (``recording.json``'s ``meta``): exact values, U 0.

    Pitch and runout from the flanks' true positions, the profile quantities from the injected slope, crown and wear
    evaluated as the inspection does (:func:`~gearscan.recon.substitution.profile_truth`). A gear with a chip, or an
    as-built module or pressure angle, has no certificate here: those change the profile in ways not modelled.
    """
    truth = meta.get("truth")
    if not truth:
        raise VerifyError("the recording holds no twin truth: only a twin recording rendered with defects has one "
                          "(`gearscan twin render --defects ...`)")
    d, gear = truth.get("defects") or {}, truth.get("gear") or {}
    if truth.get("chipped_teeth") or d.get("chips"):
        raise VerifyError("the twin gear has a chipped tooth: a master gear has none (its profile there is not certified)")
    for key in ("module", "pressure_angle_deg"):
        if d.get(key) is not None:
            raise VerifyError(f"the twin gear has an as-built {key} ({d[key]}): its profile truth is not modelled here")
    teeth = int(gear["teeth"])
    slope, crown = float(d.get("profile_slope_um", 0.0)), float(d.get("profile_crown_um", 0.0))
    wear = d.get("wear") or []
    profiles = []
    for tooth in range(teeth):
        for side in ("right", "left"):
            depth = sum(float(w["depth_um"]) for w in wear if int(w["tooth"]) == tooth and w.get("side", "left") == side)
            profiles.append(profile_truth(
                lambda xi, dep=depth: slope * xi + crown * 4 * xi * (1 - xi) - dep * np.sin(np.pi * xi),
                xi_start, xi_end, bins))
    single = {s: np.asarray(truth["single_pitch_um"][s], np.float64) for s in ("left", "right")}
    values = {
        "fp": max(float(np.abs(v).max()) for v in single.values()),
        "Fp": max(float(truth["total_cumulative_pitch_um"][s]) for s in ("left", "right")),
        "Fr_gear_axis": runout_about_gear_axis(truth["flank_position_um"], math.radians(float(gear["pressure_angle_deg"]))),
        **{k: max((p[k] for p in profiles), key=abs) for k in ("F_alpha", "ff_alpha", "fH_alpha")},
    }
    return Certificate(gear=_GearType(teeth=teeth, module=float(gear["module"])),
                       quantities_um={k: _Certified(value=v, U=0.0) for k, v in values.items()},
                       source="the twin's truth (exact: U 0)", evaluation={"xi_start": xi_start, "xi_end": xi_end})


def inspection_readings(insp) -> dict[str, float | None]:
    """An :class:`~gearscan.recon.inspect.Inspection`'s readings of :data:`QUANTITIES` (µm; None: not measured)."""
    summary = insp.summary()
    values = {k: summary[k] for k in QUANTITIES if k != "Fr_gear_axis"} | {"Fr_gear_axis": insp.runout_about_gear_axis_um}
    return {k: (float(v) if v is not None and math.isfinite(v) else None) for k, v in values.items()}


def report_readings(path: str | Path) -> tuple[dict[str, float | None], dict]:
    """One ``gearscan inspect`` report's readings of :data:`QUANTITIES` (µm; None: not measured) and its report JSON.
    ``path``: the report folder or its ``report.json``."""
    path = Path(path)
    file = path / "report.json" if path.is_dir() else path
    try:
        report = json.loads(file.read_text())
        summary, insp = report["summary_um"], report["inspection"]
    except OSError as exc:
        raise VerifyError(f"report {file}: {exc.strerror or exc} (expected a `gearscan inspect` report folder)") from exc
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise VerifyError(f"report {file}: not a `gearscan inspect` report.json ({exc})") from exc
    readings = {k: summary.get(k) for k in QUANTITIES if k != "Fr_gear_axis"}
    readings["Fr_gear_axis"] = insp.get("runout_about_gear_axis_um")
    return readings, report


@dataclass(frozen=True)
class Statement:
    """What ``verify`` found: per quantity its budget, the gear type and what the readings were measured with."""

    gear: dict
    certificate_source: str
    quantities: dict[str, QuantityUncertainty]
    measured_with: dict
    reports: tuple[str, ...]
    u_w_um: dict[str, float]

    def to_json(self) -> dict:
        return {"kind": STATEMENT_KIND, "method": "substitution (after ISO 15530-3): U = k sqrt(u_cal^2 + u_p^2 + u_w^2) "
                "+ |bias|, k the 95.45 % Student factor at the Welch-Satterthwaite degrees of freedom",
                "gear": self.gear, "certificate_source": self.certificate_source, "measured_with": self.measured_with,
                "reports": list(self.reports), "u_w_um": self.u_w_um,
                "quantities": {k: _jsonable(asdict(q)) for k, q in self.quantities.items()}}


def _jsonable(d: dict) -> dict:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}


def verify(certificate: str | Path | Certificate, reports: list[str | Path],
           u_w_um: dict[str, float] | None = None) -> Statement:
    """The uncertainty statement from a master's ``certificate`` and ``reports`` of its measurements."""
    cert = certificate if isinstance(certificate, Certificate) else load_certificate(certificate)
    readings, used = [], []
    for r in reports:
        values, report = report_readings(r)
        insp = report["inspection"]
        if int(insp.get("teeth", -1)) != cert.gear.teeth or not math.isclose(float(insp.get("module", -1)),
                                                                                cert.gear.module, rel_tol=1e-6):
            raise VerifyError(f"report {r}: a gear of {insp.get('teeth')} teeth, module {insp.get('module')}; the "
                              f"certificate's master has {cert.gear.teeth}, module {cert.gear.module:g}")
        readings.append(values)
        used.append(report.get("model") or {})
    fingerprints = {(m.get("fingerprint") or "three-step PS") for m in used}
    if len(fingerprints) > 1:
        raise VerifyError(f"the reports were decoded by different models ({', '.join(sorted(fingerprints))}): a "
                          "statement holds for one way of measuring; verify each apart")
    try:
        budgets = substitution_uncertainty({k: (q.value, q.U) for k, q in cert.quantities_um.items()}, readings, u_w_um)
    except SubstitutionError as exc:
        raise VerifyError(str(exc)) from exc
    model = used[0] if used else {}
    return Statement(gear={"teeth": cert.gear.teeth, "module": cert.gear.module}, certificate_source=cert.source,
                     quantities=budgets, measured_with={"model": model.get("path"),
                                                         "model_fingerprint": model.get("fingerprint")},
                     reports=tuple(str(r) for r in reports), u_w_um=dict(u_w_um or {}))


def statement_markdown(st: Statement) -> str:
    """The statement for people: one row per quantity, and what it holds for."""
    n = len(st.reports)
    rows = [f"| {k} | {q.certified:.2f} ± {q.U_cal:.2f} | {q.mean:.2f} | {q.bias:+.2f} | {q.u_p:.2f} | "
            f"{q.dof:.0f} | {q.k:.2f} | **{q.U:.2f}** |" for k, q in st.quantities.items()]
    few = (f" {n} readings: fewer than the {RECOMMENDED_READINGS} ISO 15530-3 asks for; the Student factor k widens U "
           "for it, but a few readings can still miss a rare large error.") if n < RECOMMENDED_READINGS else ""
    return "\n".join([
        f"# Measurement uncertainty by the substitution method ({n} measurements of a master gear)", "",
        f"Master: {st.gear['teeth']} teeth, module {st.gear['module']:g} mm; certificate: {st.certificate_source}. "
        f"Measured with: {st.measured_with.get('model') or 'three-step PS'} "
        f"(fingerprint {st.measured_with.get('model_fingerprint')}).{few}", "",
        "U = k sqrt(u_cal² + u_p² + u_w²) + |bias| (after ISO 15530-3; the bias added, not corrected), "
        "k the two-sided 95.45 % Student factor at the Welch-Satterthwaite degrees of freedom (u_p has n - 1). "
        f"u_w (what a user's gear adds beyond the master): {st.u_w_um or 'none stated'}. All µm.", "",
        "| quantity | certified ± U (k = 2) | mean reading | bias | u_p (repeatability) | dof | k | U |",
        "|---|---|---|---|---|---|---|---|", *rows, "",
        "It holds for gears of this type measured as the master was (the same rig, model, speed and settings). "
        "`gearscan inspect --uncertainty` states each reading with it.", ""])


def write_statement(st: Statement, out: str | Path) -> tuple[Path, Path]:
    """``out`` (.json) and its Markdown twin (.md)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(st.to_json(), indent=2))
    md = out.with_suffix(".md")
    md.write_text(statement_markdown(st))
    return out, md


@dataclass(frozen=True)
class LoadedStatement:
    """A statement as ``inspect`` uses it: the gear type, U per quantity and the model it was measured with."""

    teeth: int
    module: float
    U_um: dict[str, float]
    model_fingerprint: str | None
    path: str

    def require_gear(self, teeth: int, module: float) -> None:
        """Refuse a gear of another type than the master's: its U says nothing about it."""
        if teeth != self.teeth or not math.isclose(module, self.module, rel_tol=1e-6):
            raise VerifyError(f"--uncertainty {self.path}: taken on a master of {self.teeth} teeth, module "
                              f"{self.module:g}; this gear has {teeth}, module {module:g}: measure a master of its type")


def load_statement(path: str | Path) -> LoadedStatement:
    """The statement ``gearscan verify`` wrote; :class:`VerifyError` names the file and what is wrong."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except OSError as exc:
        raise VerifyError(f"--uncertainty {path}: {exc.strerror or exc}") from exc
    except json.JSONDecodeError as exc:
        raise VerifyError(f"--uncertainty {path}: not JSON ({exc})") from exc
    if not isinstance(d, dict) or d.get("kind") != STATEMENT_KIND:
        raise VerifyError(f"--uncertainty {path}: not a statement `gearscan verify` wrote (kind {STATEMENT_KIND!r})")
    try:
        U = {k: float(q["U"]) for k, q in d["quantities"].items() if k in QUANTITIES}
        teeth, module = int(d["gear"]["teeth"]), float(d["gear"]["module"])
    except (KeyError, TypeError, ValueError) as exc:
        raise VerifyError(f"--uncertainty {path}: malformed ({exc})") from exc
    if not U or not all(math.isfinite(v) and v >= 0 for v in U.values()):
        raise VerifyError(f"--uncertainty {path}: quantities: expected finite U >= 0 for some of {', '.join(QUANTITIES)}")
    return LoadedStatement(teeth, module, U, (d.get("measured_with") or {}).get("model_fingerprint"), str(path))


def applied_uncertainty(statement: LoadedStatement, readings: dict[str, float | None], teeth: int, module: float,
                        model_fingerprint: str | None, tolerances: dict[str, float] | None) -> dict:
    """Each reading with the statement's U and, with ``tolerances`` (an ISO 1328-1 class's), its ISO 14253-1 decision.
    A gear of another type is refused: the master's U says nothing about it."""
    statement.require_gear(teeth, module)
    out: dict = {"statement": statement.path, "k": K_COVERAGE, "quantities": {}}
    if model_fingerprint != statement.model_fingerprint:
        out["warning"] = (f"the statement's readings were decoded by model {statement.model_fingerprint}, this one by "
                          f"{model_fingerprint}: its U is not this measurement's")
    for key, U in statement.U_um.items():
        value = readings.get(key)
        row: dict = {"value": value, "U": U}
        if tolerances is not None and value is not None and math.isfinite(value):
            T = tolerances[TOLERANCE_KEY[key]]
            row |= {"tolerance": T, "decision": conformity(value, U, T)}
        out["quantities"][key] = row
    return out
