"""``gearscan verify``: what the instrument's ISO 1328-1 readings are worth, from a master gear measured repeatedly.

A master gear's certificate (``gearscan twin certificate`` writes one from a twin recording's truth; a lab's can be
typed into the same JSON where it states per-side profile slope and crowning and per-tooth positions) and several
``gearscan inspect`` reports of it, each after a fresh mounting, give each quantity's expanded uncertainty U by the
bound method of :mod:`gearscan.recon.substitution`. The statement is written as JSON (``gearscan inspect
--uncertainty`` reads it: each reading with its U and, with ``--grade``, the ISO 14253-1 decision) and Markdown. It
holds for gears of the master's type (teeth, module; checked: another is refused) decoded by the same model and
evaluated alike (checked: warned), on the same rig at the same speed (not checked: the user's part).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from gearscan.recon.inspect import pitch_deviations
from gearscan.recon.substitution import (
    BUDGETED,
    CONFORMS,
    MIN_READINGS,
    RECOMMENDED_READINGS,
    TOLERANCE_CONFIDENCE,
    TOLERANCE_COVERAGE,
    TOLERANCE_KEY,
    UNDECIDED,
    Evaluation,
    FlankTrace,
    QuantityBound,
    SubstitutionError,
    bound_uncertainty,
    conformity,
    error_functionals,
    profile_truth,
    runout_about_gear_axis,
)

STATEMENT_KIND = "gearscan uncertainty statement"
CERTIFICATE_KIND = "gearscan master gear certificate"
SIDES = ("left", "right")
# what a report from before session 59 (no "datum" in its settings) was read about: the flanks, one turn for all teeth
LEGACY_DATUM = "flanks (one turn for all teeth; before session 59)"
U_MEANING = (f"U bounds a headline's error over the flanks and teeth read (|fH_alpha| by magnitude) on "
             f"{TOLERANCE_COVERAGE:.0%} of mountings at {TOLERANCE_CONFIDENCE:.0%} confidence, from a master gear of "
             "this type (`gearscan verify`)")


class VerifyError(ValueError):
    """A certificate, report or statement that cannot be used; the message names the file and what was expected."""


class _GearType(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    teeth: int = Field(ge=6)
    module: float = Field(gt=0, allow_inf_nan=False)
    pressure_angle_deg: float = Field(20.0, ge=10, le=35)


class _Profile(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    slope: float = Field(0.0, allow_inf_nan=False, description="normal offset at the tip growing linearly from 0, µm")
    crown: float = Field(0.0, allow_inf_nan=False, description="crowning 4 c xi (1 - xi): c mid-flank, µm")

    def offset(self, xi) -> np.ndarray:
        xi = np.asarray(xi, np.float64)
        return self.slope * xi + self.crown * 4 * xi * (1 - xi)


class Certificate(BaseModel):
    """A master gear's certificate: its type, each flank side's profile (slope and crowning over the roll fraction from
    the involute's start to the tip), each flank's position on the pitch circle, and per headline quantity the
    certificate's own uncertainty as a bound on that headline (µm; for per-tooth positions known within +-u: fp and
    Fp 2u, Fr_gear_axis 2u / tan(alpha)). Form beyond slope and crowning is not modelled: a real master's ends up in
    the bound, as the instrument's error would."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: str = CERTIFICATE_KIND
    gear: _GearType
    profile_um: dict[Literal["left", "right"], _Profile]
    positions_um: dict[Literal["left", "right"], list[float]]
    U_um: dict[str, float]
    source: str = Field("", description="who certified it: a lab and its certificate number, or the twin's truth")

    @model_validator(mode="after")
    def _complete(self) -> Certificate:
        for name, part in (("profile_um", self.profile_um), ("positions_um", self.positions_um)):
            if set(part) != set(SIDES):
                raise ValueError(f"{name}: needs both sides (left, right), got {sorted(part)}")
        for side, pos in self.positions_um.items():
            if len(pos) != self.gear.teeth or not all(math.isfinite(v) for v in pos):
                raise ValueError(f"positions_um.{side}: expected {self.gear.teeth} finite positions (one per tooth)")
        if set(self.U_um) != set(BUDGETED) or not all(math.isfinite(v) and v >= 0 for v in self.U_um.values()):
            raise ValueError(f"U_um: expected a finite U >= 0 for each of {', '.join(BUDGETED)} (0 only where exact)")
        return self

    def headline_um(self, xi_start: float = 0.1, xi_end: float = 0.95, bins: int = 20) -> dict[str, float]:
        """The certified headline values, evaluated as the inspection does."""
        pitch = [pitch_deviations(self.positions_um[s]) for s in SIDES]
        prof = [profile_truth(self.profile_um[s].offset, xi_start, xi_end, bins) for s in SIDES]
        return {"fp": max(v[1] for v in pitch), "Fp": max(v[2] for v in pitch),
                "Fr_gear_axis": runout_about_gear_axis(self.positions_um, math.radians(self.gear.pressure_angle_deg)),
                **{k: max((p[k] for p in prof), key=abs) for k in ("F_alpha", "ff_alpha", "fH_alpha")}}


def load_certificate(path: str | Path) -> Certificate:
    """The certificate at ``path``; :class:`VerifyError` names the file and the field at fault."""
    path = Path(path)
    try:
        cert = Certificate.model_validate_json(path.read_bytes())
    except OSError as exc:
        raise VerifyError(f"certificate {path}: {exc.strerror or exc}") from exc
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "(top level)"
        raise VerifyError(f"certificate {path}: {where}: {first['msg']} (expected 'gear' {{teeth, module}}, "
                          "'profile_um' {side: {slope, crown}} and 'positions_um' {side: [one per tooth]}, 'U_um' "
                          f"{{{', '.join(BUDGETED)}}})") from exc
    if cert.kind != CERTIFICATE_KIND:
        raise VerifyError(f"certificate {path}: kind {cert.kind!r}, expected {CERTIFICATE_KIND!r}")
    return cert


def twin_certificate(meta: dict) -> Certificate:
    """The certificate of a twin recording's gear from its truth (``recording.json``'s content): exact, U 0.

    Profiles from the injected slope and crown, positions from the truth's flank positions. A master gear has no chip,
    no wear and its nominal module and pressure angle: a twin gear with any of those gets no certificate.
    """
    truth = meta.get("truth")
    if not truth:
        raise VerifyError("the recording holds no twin truth: only a twin recording rendered with defects has one "
                          "(`gearscan twin render --defects ...`)")
    try:
        d, gear = truth.get("defects") or {}, truth["gear"]
        if truth.get("chipped_teeth") or d.get("chips"):
            raise VerifyError("the twin gear has a chipped tooth: a master gear has none")
        if d.get("wear"):
            raise VerifyError("the twin gear has worn flanks: a master gear has none")
        for key in ("module", "pressure_angle_deg"):
            if d.get(key) is not None:
                raise VerifyError(f"the twin gear has an as-built {key} ({d[key]}): a master's is its nominal one")
        profile = _Profile(slope=float(d.get("profile_slope_um", 0.0)), crown=float(d.get("profile_crown_um", 0.0)))
        return Certificate(gear=_GearType(teeth=int(gear["teeth"]), module=float(gear["module"]),
                                          pressure_angle_deg=float(gear["pressure_angle_deg"])),
                           profile_um={s: profile for s in SIDES},
                           positions_um={s: [float(v) for v in truth["flank_position_um"][s]] for s in SIDES},
                           U_um=dict.fromkeys(BUDGETED, 0.0), source="the twin's truth (exact: U 0)")
    except VerifyError:
        raise
    except (KeyError, TypeError, ValueError) as exc:
        raise VerifyError(f"the recording's twin truth is incomplete or malformed ({exc!r})") from exc


@dataclass(frozen=True)
class MasterReading:
    """What one ``gearscan inspect`` report says that the bound method uses: headline readings (µm; None: not
    measured), flank traces, flank positions, where the profiles were evaluated, and what measured it."""

    path: str
    teeth: int
    module: float
    headline: dict[str, float | None]
    flanks: tuple[FlankTrace, ...]
    positions_um: dict[str, tuple[float, ...]]
    evaluation: Evaluation
    flanks_of: tuple[int, int]  # flanks measured, of all
    bins_left_out: int
    model: str | None
    model_fingerprint: str | None
    datum: str = LEGACY_DATUM  # the axis pitch and runout were read about (recon.inspect.DATUMS)


def _num(v) -> float | None:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        return None
    return float(v)


def _read_json(path: Path, label: str, expected: str = ""):
    """The JSON at ``path``; :class:`VerifyError` starting with ``label`` names the file and what went wrong."""
    try:
        return json.loads(path.read_text())
    except OSError as exc:
        raise VerifyError(f"{label} {path}: {exc.strerror or exc}{expected}") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise VerifyError(f"{label} {path}: not JSON ({exc})") from exc


def read_report(path: str | Path) -> MasterReading:
    """One ``gearscan inspect`` report (its folder or ``report.json``); :class:`VerifyError` names what is wrong."""
    path = Path(path)
    file = path / "report.json" if path.is_dir() else path
    report = _read_json(file, "report", " (expected a `gearscan inspect` report folder)")
    try:
        summary, insp, model = report["summary_um"], report["inspection"], report.get("model") or {}
        settings = insp["settings"]
        l_a, l_b = (float(v) for v in settings["evaluation_roll_mm"])
        flanks = [f for f in insp["flanks"] if f["measured"]]
        teeth = int(insp["teeth"])
        reading = MasterReading(
            path=str(path), teeth=teeth, module=float(insp["module"]),
            headline={k: _num(summary.get(k)) for k in BUDGETED if k != "Fr_gear_axis"}
            | {"Fr_gear_axis": _num(insp.get("runout_about_gear_axis_um"))},
            flanks=tuple(FlankTrace(int(f["tooth"]), str(f["side"]), tuple(float(v) for v in f["roll_mm"]),
                                    tuple(float(v) for v in f["trace_um"])) for f in flanks),
            positions_um={s: tuple(math.nan if v is None else float(v) for v in insp["position_um"][s]) for s in SIDES},
            evaluation=Evaluation(l_a, l_b, float(settings["xi_start"]), float(settings["xi_end"]), int(settings["bins"])),
            flanks_of=(len(flanks), 2 * teeth),
            bins_left_out=int(report.get("profile_bins_left_out") or insp.get("profile_bins_left_out") or 0),
            model=model.get("path"), model_fingerprint=model.get("fingerprint"),
            datum=str(settings.get("datum") or LEGACY_DATUM))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise VerifyError(f"report {file}: not a `gearscan inspect` report.json ({exc!r})") from exc
    short = [f"{f.tooth} {f.side}" for f in reading.flanks if len(f.roll_mm) != len(f.trace_um) or len(f.roll_mm) < 3]
    if short or any(len(v) != reading.teeth for v in reading.positions_um.values()):
        raise VerifyError(f"report {file}: flank traces ({', '.join(short) or 'fine'}) or positions (one per tooth, "
                          f"{reading.teeth}) do not match: not a whole `gearscan inspect` report")
    if any(s not in SIDES for s in (f.side for f in reading.flanks)):
        raise VerifyError(f"report {file}: flank sides must be left or right")
    return reading


def inspection_readings(insp) -> dict[str, float | None]:
    """An :class:`~gearscan.recon.inspect.Inspection`'s headline readings of :data:`BUDGETED` (µm; None: not measured)."""
    summary = insp.summary()
    return {k: _num(summary[k]) for k in BUDGETED if k != "Fr_gear_axis"} | {
        "Fr_gear_axis": _num(insp.runout_about_gear_axis_um)}


@dataclass(frozen=True)
class Statement:
    """What ``verify`` found: per quantity its bound and U, the headline readings and certified values beside them,
    the gear type, and how the master was measured."""

    gear: dict[str, float]
    certificate_source: str
    quantities: dict[str, QuantityBound]
    certified: dict[str, float]
    headline: dict[str, tuple[float | None, ...]]
    model: str | None
    model_fingerprint: str | None
    evaluation: dict[str, float]
    reports: tuple[str, ...]
    datum: str = LEGACY_DATUM

    def to_json(self) -> dict:
        return {"kind": STATEMENT_KIND, "method": "bound (gearscan.recon.substitution): per mounting of the master the "
                "largest error a headline can take from the traces' and positions' errors; U = mean + k s over the "
                f"mountings (one-sided normal tolerance bound: {TOLERANCE_COVERAGE:.0%} of mountings, "
                f"{TOLERANCE_CONFIDENCE:.0%} confidence) + the certificate's U",
                "gear": self.gear, "certificate_source": self.certificate_source,
                "measured_with": {"model": self.model, "model_fingerprint": self.model_fingerprint},
                "evaluation": self.evaluation, "datum": self.datum, "reports": list(self.reports),
                "quantities": {k: asdict(q) | {"certified": self.certified.get(k), "headline": list(self.headline[k])}
                               for k, q in self.quantities.items()}}


def verify(certificate: str | Path | Certificate, reports: list[str | Path]) -> Statement:
    """The uncertainty statement from a master's ``certificate`` and ``reports`` of its measurements, one per
    mounting. Refused: fewer than :data:`MIN_READINGS` reports, a report twice, another gear type, reports decoded
    by different models or evaluated differently, a master not measured on every flank."""
    cert = certificate if isinstance(certificate, Certificate) else load_certificate(certificate)
    if len(reports) < MIN_READINGS:
        raise VerifyError(f"{len(reports)} report(s) of the master: at least {MIN_READINGS} are needed, each after a "
                          f"fresh mounting (ISO 15530-3 asks for {RECOMMENDED_READINGS})")
    seen = [(Path(r) / "report.json" if Path(r).is_dir() else Path(r)).resolve() for r in reports]
    if len(set(seen)) < len(seen):
        raise VerifyError("a report is given twice: each must be its own measurement of the master")
    readings = [read_report(r) for r in reports]
    for r in readings:
        if r.teeth != cert.gear.teeth or not math.isclose(r.module, cert.gear.module, rel_tol=1e-6):
            raise VerifyError(f"report {r.path}: a gear of {r.teeth} teeth, module {r.module:g}; the certificate's "
                              f"master has {cert.gear.teeth}, module {cert.gear.module:g}")
        unread = sum(not np.isfinite(v).all() for v in map(np.asarray, r.positions_um.values()))
        if r.flanks_of[0] < r.flanks_of[1] or unread:
            raise VerifyError(f"report {r.path}: {r.flanks_of[0]} of {r.flanks_of[1]} flanks measured (positions "
                              f"{'incomplete' if unread else 'complete'}): a master reading must cover the whole gear "
                              "(measure a whole revolution)")
    for what, key in (("models", lambda r: r.model_fingerprint or "three-step PS"), ("datums", lambda r: r.datum),
                      ("evaluation settings", lambda r: (round(r.evaluation.xi_start, 6), round(r.evaluation.xi_end, 6),
                                                         r.evaluation.bins))):
        values = {key(r) for r in readings}
        if len(values) > 1:
            raise VerifyError(f"the reports differ in their {what} ({', '.join(map(str, sorted(values, key=str)))}): a "
                              "statement holds for one way of measuring; verify each apart")
    alpha = math.radians(cert.gear.pressure_angle_deg)
    try:
        samples = [error_functionals(r.flanks, r.positions_um, r.evaluation,
                                     lambda side, xi: cert.profile_um[side].offset(xi), cert.positions_um, alpha)
                   for r in readings]
        bounds = {k: bound_uncertainty(k, [s[k] for s in samples], cert.U_um[k]) for k in BUDGETED}
    except (SubstitutionError, ValueError) as exc:
        raise VerifyError(str(exc)) from exc
    first = readings[0]
    return Statement(
        gear={"teeth": cert.gear.teeth, "module": cert.gear.module}, certificate_source=cert.source,
        quantities=bounds,
        certified=cert.headline_um(first.evaluation.xi_start, first.evaluation.xi_end, first.evaluation.bins),
        headline={k: tuple(r.headline[k] for r in readings) for k in BUDGETED}, model=first.model,
        model_fingerprint=first.model_fingerprint,
        evaluation={"xi_start": first.evaluation.xi_start, "xi_end": first.evaluation.xi_end, "bins": first.evaluation.bins},
        reports=tuple(str(r) for r in reports), datum=first.datum)


def statement_markdown(st: Statement) -> str:
    """The statement for people: one row per quantity, and what it holds for."""
    n = len(st.reports)

    def cell(v: float | None) -> str:
        return "–" if v is None else f"{v:.1f}"

    rows = [f"| {k}: {BUDGETED[k]} | {cell(st.certified.get(k))} | {', '.join(cell(v) for v in st.headline[k])} | "
            f"{', '.join(f'{v:.2f}' for v in q.samples)} | {q.mean:.2f} | {q.s:.2f} | {q.k:.2f} | {q.U_cal:.2f} | "
            f"**{q.U:.2f}** |" for k, q in st.quantities.items()]
    few = (f" {n} mountings: fewer than the {RECOMMENDED_READINGS} ISO 15530-3 asks for; the tolerance factor k widens U "
           "for it.") if n < RECOMMENDED_READINGS else ""
    return "\n".join([
        f"# Measurement uncertainty from a master gear ({n} mountings)", "",
        f"Master: {st.gear['teeth']} teeth, module {st.gear['module']:g} mm; certificate: {st.certificate_source}. "
        f"Measured with: {st.model or 'three-step PS'} (decode fingerprint {st.model_fingerprint}); profiles evaluated "
        f"over xi {st.evaluation['xi_start']:g}-{st.evaluation['xi_end']:g} in {st.evaluation['bins']} bins.{few}", "",
        "Per mounting, the largest error each headline could take from the errors of the traces and positions read "
        "(the read minus the certified): a range bounds a range, the largest magnitude the largest magnitude. "
        f"U = mean + k s of those bounds (one-sided normal tolerance bound: {TOLERANCE_COVERAGE:.0%} of mountings at "
        f"{TOLERANCE_CONFIDENCE:.0%} confidence) + the certificate's U. All µm.", "",
        "| quantity | certified | headline readings | error bound per mounting | mean | s | k | U cert | **U** |",
        "|---|---|---|---|---|---|---|---|---|", *rows, "",
        "It holds for gears of this type (checked) decoded by the same model and evaluated alike (checked), on the same "
        "rig at the same speed (not checked), about the same datum axis (checked: the master's is "
        f"{st.datum!r}). `gearscan inspect --uncertainty` states each reading with it. Fr_gear_axis is the runout about "
        "that datum axis, not ISO 1328-1's Fr (which includes the teeth's eccentricity to the gear's datum surfaces): it "
        "gets no conformity decision.", ""])


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
    """A statement as ``inspect`` uses it: the gear type, U per quantity, the model and evaluation it holds for."""

    teeth: int
    module: float
    U_um: dict[str, float]
    model_fingerprint: str | None
    evaluation: dict[str, float]
    path: str
    datum: str = LEGACY_DATUM

    def require_gear(self, teeth: int, module: float) -> None:
        """Refuse a gear of another type than the master's: its U says nothing about it."""
        if teeth != self.teeth or not math.isclose(module, self.module, rel_tol=1e-6):
            raise VerifyError(f"--uncertainty {self.path}: taken on a master of {self.teeth} teeth, module "
                              f"{self.module:g}; this gear has {teeth}, module {module:g}: measure a master of its type")


def load_statement(path: str | Path) -> LoadedStatement:
    """The statement ``gearscan verify`` wrote; :class:`VerifyError` names the file and what is wrong."""
    path = Path(path)
    d = _read_json(path, "--uncertainty")
    if not isinstance(d, dict) or d.get("kind") != STATEMENT_KIND:
        raise VerifyError(f"--uncertainty {path}: not a statement `gearscan verify` wrote (kind {STATEMENT_KIND!r})")
    try:
        U = {k: _num(q["U"]) for k, q in d["quantities"].items() if k in BUDGETED}
        teeth, module = d["gear"]["teeth"], _num(d["gear"]["module"])
        fingerprint = (d.get("measured_with") or {}).get("model_fingerprint")
        evaluation = {k: float(v) for k, v in (d.get("evaluation") or {}).items()}
        datum = str(d.get("datum") or LEGACY_DATUM)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise VerifyError(f"--uncertainty {path}: malformed ({exc!r})") from exc
    if not isinstance(teeth, int) or isinstance(teeth, bool) or teeth < 6 or module is None or module <= 0:
        raise VerifyError(f"--uncertainty {path}: gear: expected whole teeth >= 6 and a module > 0")
    if not U or any(v is None or v < 0 for v in U.values()):
        raise VerifyError(f"--uncertainty {path}: quantities: expected finite U >= 0 for some of {', '.join(BUDGETED)}")
    return LoadedStatement(teeth, module, U, fingerprint, evaluation, str(path), datum)


@dataclass(frozen=True)
class StatedReading:
    """One headline reading with the statement's U and, graded, its tolerance and ISO 14253-1 decision (``why``: what
    kept a decision from "conforms"). For fH_alpha the reading is signed and U bounds its magnitude."""

    value: float | None
    U: float
    tolerance: float | None = None
    decision: str | None = None
    why: str | None = None


@dataclass(frozen=True)
class AppliedUncertainty:
    """A statement applied to one inspection: per quantity the reading with its U, and what to warn about."""

    statement: str
    readings: dict[str, StatedReading]
    warnings: tuple[str, ...] = ()

    def to_json(self) -> dict:
        return {"statement": self.statement, "meaning": U_MEANING,
                "quantities": {k: asdict(r) for k, r in self.readings.items()}, "warnings": list(self.warnings)}


COVERAGE_KEY = {"Fr_gear_axis": "Fr"}  # Inspection.coverage() keys where they differ from BUDGETED's
PROFILE_KEYS = ("F_alpha", "ff_alpha", "fH_alpha")


def applied_uncertainty(statement: LoadedStatement, readings: dict[str, float | None], teeth: int, module: float,
                        model_fingerprint: str | None, tolerances: dict[str, float] | None,
                        evaluation: dict[str, float] | None = None, coverage: dict[str, tuple[int, int]] | None = None,
                        bins_left_out: int = 0, datum: str | None = None) -> AppliedUncertainty:
    """Each reading with the statement's U and, with ``tolerances`` (an ISO 1328-1 class's), its ISO 14253-1 decision
    (Fr_gear_axis gets none: not ISO's Fr). U bounds the error of a headline over what was read: where ``coverage``
    (``Inspection.coverage()``) says part of the gear was not, or profile bins were left out, a value within the
    tolerance by U is "undecided", not "conforms" (the part unseen may deviate more). A gear of another type is
    refused; another model or evaluation warned about."""
    statement.require_gear(teeth, module)
    warnings = []
    if model_fingerprint != statement.model_fingerprint:
        warnings.append(f"the statement's master was decoded by {statement.model_fingerprint or 'three-step PS'}, this "
                        f"gear by {model_fingerprint or 'three-step PS'}: its U is not this measurement's")
    if evaluation and statement.evaluation and any(
            not math.isclose(float(evaluation.get(k, math.nan)), v, abs_tol=1e-9) for k, v in statement.evaluation.items()):
        warnings.append(f"the statement's profiles were evaluated with {statement.evaluation}, this gear's with "
                        f"{ {k: evaluation.get(k) for k in statement.evaluation} }: its U is not this measurement's")
    if datum is not None and datum != statement.datum:
        warnings.append(f"the statement's master was read about the datum {statement.datum!r}, this gear about "
                        f"{datum!r}: its U is not this measurement's")
    out = {}
    for key, U in statement.U_um.items():
        value = readings.get(key)
        tol = (tolerances or {}).get(TOLERANCE_KEY.get(key, ""))
        if tol is None or value is None:
            out[key] = StatedReading(value, U)
            continue
        decision, why = conformity(value, U, tol), None
        measured, of = (coverage or {}).get(COVERAGE_KEY.get(key, key), (1, 1))
        if decision == CONFORMS and measured < of:
            decision, why = UNDECIDED, f"measured on {measured} of {of}: the rest may deviate more"
        elif decision == CONFORMS and key in PROFILE_KEYS and bins_left_out:
            decision, why = UNDECIDED, f"{bins_left_out} profile bins left out: those flanks were not read whole"
        out[key] = StatedReading(value, U, tol, decision, why)
    return AppliedUncertainty(statement.path, out, tuple(warnings))


def reading_text(key: str, r: StatedReading, named: bool = True) -> str:
    """``fp 12.3 ± 1.1 µm`` (fH_alpha as its magnitude, which U bounds); without the name for a table cell (where a
    ``|`` would end the cell)."""
    name = (f"|{key}| " if key == "fH_alpha" else f"{key} ") if named else ""
    if r.value is None:
        return f"{name}not measured (U {r.U:.1f} µm)"
    if key == "fH_alpha":
        return f"{name}{abs(r.value):.1f} ± {r.U:.1f} µm{'' if named else ' in magnitude'} (reading {r.value:+.1f})"
    return f"{name}{r.value:.1f} ± {r.U:.1f} µm"
