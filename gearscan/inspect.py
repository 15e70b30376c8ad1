"""``gearscan inspect``: a recording of a revolution -> fused gear model -> ISO 1328-1 report.

The recording is replayed through the measurement pipeline (:func:`gearscan.replay.replay`)
with a :class:`~gearscan.recon.fuse.CloudFuser`; the fused model is inspected with
:func:`gearscan.recon.inspect.inspect_gear` and written as ``report.json``, ``report.md``,
``pitch.png``, ``runout.png``, ``profiles.png`` and ``fused.ply`` (sigma, deviation and its sigma, bursts, refined and,
with the frame fit, the camera ray each sigma runs along).
With ``grade`` the ISO 1328-1:2013 tolerances of that class are stated next to each value.
A twin recording with injected defects also gets its truth beside the measurement (labelled).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from gearscan.core.recording import RecordingError, RecordingReader
from gearscan.core.rig import CalibrationStatement, Rig
from gearscan.recon.depth_sigma import REST_STALE_NOTE, UNMEASURED_NOTES, turning_three_step_note
from gearscan.recon.fuse import CloudFuser, FusedCloud, load_fused, save_fused
from gearscan.recon.inspect import (
    DATUM,
    DATUMS,
    Inspection,
    inspect_gear,
    iso1328_class,
    iso1328_tolerances,
    jsonable,
)
from gearscan.recon.measure import PRODUCT_SUPPORT
from gearscan.recon.substitution import BUDGETED
from gearscan.verify import (
    U_MEANING,
    AppliedUncertainty,
    applied_uncertainty,
    inspection_readings,
    load_statement,
    reading_text,
)

QUANTITIES = {  # key in Inspection.summary() -> (symbol, description)
    "fp": ("fp", "single pitch deviation (the largest in magnitude)"),
    "Fp": ("Fp", "total cumulative pitch deviation"),
    "Fr": ("Fr", "runout (ball probe on the pitch circle, about the rotation axis)"),
    "F_alpha": ("Fα", "total profile deviation (worst flank)"),
    "ff_alpha": ("ffα", "profile form deviation (worst flank)"),
    "fH_alpha": ("fHα", "profile slope deviation (the largest in magnitude)"),
}


@dataclass(frozen=True)
class InspectionReport:
    """What ``gearscan inspect`` produced: the inspection, the fused model and the files written."""

    inspection: Inspection
    fused: FusedCloud
    grade: int | None
    tolerances: dict[str, float] | None
    classes: dict[str, int | None]
    revolution_deg: float
    files: dict[str, Path]
    truth: dict | None = None
    refine: dict | None = None  # the frame fit's counts (recon.track.TrackRefiner.refine_fused), if it ran
    depth_sigma_source: str | None = None  # whose depth-sigma scales the unfitted points carry (recon.depth_sigma)
    turning_three_step: int = 0  # bursts that turned and were decoded by three-step PS (--classical): sigma unmeasured
    rest_sigma_scale: float | None = None  # what the frame fit multiplied its unfitted points' sigma by, if it ran
    rest_sigma_source: str | None = None  # whose that scale is: model, stale (the model's, another decode) or product
    model: str | None = None  # the network's weights that decoded the bursts (None: three-step PS)
    model_fingerprint: str | None = None  # that decode's fingerprint (weights, sigma maps, gates)
    rig: str | None = None  # the rig calibration it was measured with, where not the recording's own (--rig)
    calibration: CalibrationStatement | None = None  # that rig's calibration's stated uncertainty, where it states one
    # each reading with the U of a `gearscan verify` statement and its ISO 14253-1 decision
    uncertainty: AppliedUncertainty | None = None
    fused_from: str | None = None  # the earlier report whose fused cloud was inspected again (None: replayed here)


def partial(insp: Inspection, key: str) -> str:
    """``"k of n"`` where a headline quantity rests on fewer values than a whole gear has (its value is then a lower
    bound and its class the finest the gear can be); "" where every one was measured."""
    k, n = insp.coverage()[key]
    return f"{k} of {n}" if k < n else ""


def class_text(insp: Inspection, key: str, value: float, cls: int | None, graded: bool) -> str:
    """The ISO 1328-1 class as the report states it: "n/a" for a quantity not measured, "> 11" beyond the coarsest
    class, "C or coarser" where the value is a lower bound (:func:`partial`), "–" where no class applies."""
    if not graded:
        return "–"
    if not np.isfinite(value):
        return "n/a"
    if cls is None:
        return "> 11"
    return f"{cls} or coarser" if partial(insp, key) else str(cls)


def quantity_line(insp: Inspection, key: str, value: float, tolerance: str = "") -> str:
    """One headline quantity for the console: its value, ``tolerance`` (e.g. " (class 6: 12")") and, where it rests on
    part of the gear, that it is a lower bound."""
    sym, text = QUANTITIES[key]
    if not np.isfinite(value):
        return f"{sym}: not measured (too little of it was seen)  {text}"
    part = partial(insp, key)
    bound = f" on {part} only: a lower bound, those not measured may deviate more" if part else ""
    return f"{sym}: {value:.1f} µm{tolerance}{bound}  {text}"


def _unfitted(report: InspectionReport) -> int:
    """Points of the fused model the frame fit did not take (all of them where no fit ran): they keep their fused
    sigma, which the bursts' decode and depth scales made."""
    refined = report.fused.refined
    return len(report.fused) if refined is None else int((~refined).sum())


def unmeasured_sigma_note(report: InspectionReport) -> str | None:
    """What to say where the points the frame fit did not take carry depth-sigma scales not measured for this decode
    (``recon.depth_sigma.depth_sigma_source``; a fitted point carries the fit's own sigma); None where none do."""
    unfitted = _unfitted(report)
    notes = [n for n in (UNMEASURED_NOTES.get(report.depth_sigma_source),
                         REST_STALE_NOTE if report.rest_sigma_source == "stale" else None) if n]
    return f"sigma of the {unfitted:,} point(s) the frame fit did not take: {'; '.join(notes)}" if unfitted and notes else None


def spec_note(report: InspectionReport) -> str | None:
    """A warning where a whole revolution measured fewer than half of the gear's pitches: most often the gear spec
    (teeth, module, pressure angle) or the rig calibration does not match the gear on the turntable; None otherwise."""
    insp = report.inspection
    k, n = insp.coverage()["fp"]
    if report.revolution_deg < 360 - 360 / insp.teeth or k >= n / 2:
        return None
    return (f"a whole revolution measured only {k} of the {n} flank pitches (both flanks of {insp.teeth} teeth): "
            f"check that the gear spec (z = {insp.teeth}, "
            f"m = {insp.module:g} mm) and the rig calibration match the gear on the turntable (the fitted gear axis is "
            f"{insp.eccentricity_um:.0f} µm from the turntable axis)")


def turning_note(report: InspectionReport) -> str | None:
    """What to say where three-step PS decoded bursts that turned (``--classical``): the unfitted points from them carry
    a sigma that is no measured bound; None where it decoded none."""
    unfitted = _unfitted(report)
    if not report.turning_three_step or not unfitted:
        return None
    return (f"sigma of the {unfitted:,} point(s) the frame fit did not take (some from other bursts): "
            f"{turning_three_step_note(report.turning_three_step)}")


def shading_share(refine: dict) -> str:
    """With "mixed" shading, how many of the fits it took quadratic, in words (empty for the other models)."""
    if refine.get("shading") != "mixed" or refine.get("quadratic_points") is None or not refine.get("refined"):
        return ""
    return f": {100 * refine['quadratic_points'] / refine['refined']:.0f} % of the fits quadratic"


def dropped_note(refine: dict | None) -> str:
    """What the frame fit left out of the fused model, in words (empty if it dropped nothing)."""
    if not refine:
        return ""
    parts = [f"{refine[k]:,} {what}" for k, what in (
        ("off_surface", "off the surface their fitted neighbours measured"),
        ("uncertain", "with a sigma above the fit's bound" + (f" ({1e3 * refine['sigma_bound_mm']:g} µm)"
                                                               if refine.get("sigma_bound_mm") else ""))) if refine.get(k)]
    note = f" Left out (unfitted points): {'; '.join(parts)}." if parts else ""
    if refine.get("unsettled"):  # unfitted too: each kept at its fused position or among those left out
        note += (f" {refine['unsettled']:,} fits had not settled at their last iteration (recon.track.SETTLE_RAD) "
                 "and were not taken (those points are counted above or kept at their fused position).")
    if refine.get("implausible"):  # the same: fits explained by a fringe brighter than the light it rides on
        note += (f" {refine['implausible']:,} fits had a modulation above their mean intensity (an impossible fringe, "
                 "recon.track.MODULATION_RATIO) and were not taken (counted above or kept at their fused position).")
    return note


def chip_verdict(insp) -> str:
    """The chip check's answer in words: the flagged teeth, none, or why it cannot tell."""
    if not insp.chip_check_conclusive:
        chip_mm = insp.settings.get("chip_mm", 0.05)
        if not np.isfinite(insp.chip_noise_um):  # no tip cell seen by enough teeth to compare (a partial turn)
            return "inconclusive: too few teeth's tips were measured to compare them with the median tooth"
        return (f"inconclusive: the tip cells stray {insp.chip_noise_um:.0f} µm (95th percentile) from the median "
                f"tooth, too close to the {1e3 * chip_mm:.0f} µm chip threshold to tell a chip from noise")
    return ", ".join(str(t) for t in insp.chipped_teeth) or "none"

def revolution_deg(reader: RecordingReader) -> float:
    """Turntable angle the recording's frames cover, degrees (360 or more: every tooth seen)."""
    angles = np.array([r.encoder_angle for r in reader.records if r.encoder_angle is not None], dtype=float)
    # in frame order, unwrapped: angles stored modulo a turn must not read as a whole revolution (no turntable turns
    # half a turn between two frames)
    angles = np.unwrap(angles)
    return float(np.degrees(angles.max() - angles.min())) if len(angles) else 0.0


def truth_comparison(meta: dict, insp: Inspection) -> dict | None:
    """The twin's injected answer next to the measurement (None for a recording without defects)."""
    truth = meta.get("truth")
    if not truth:
        return None
    ecc = 1e3 * float(np.hypot(*truth.get("eccentricity_mm", [0.0, 0.0])))
    out = {
        "eccentricity_um": {"truth": ecc, "measured": insp.eccentricity_um},
        "runout_from_eccentricity_um": {"truth": truth.get("runout_from_eccentricity_um"),
                                        "measured": insp.runout_from_eccentricity_um},
        "chipped_teeth": {"truth": truth.get("chipped_teeth", []), "measured": list(insp.chipped_teeth)},
    }
    for side in ("left", "right"):
        t_fp = np.asarray(truth["single_pitch_um"][side], dtype=float)
        m_fp = np.asarray(insp.single_pitch_um[side], dtype=float)
        out[f"Fp_um_{side}"] = {"truth": truth["total_cumulative_pitch_um"][side], "measured": insp.Fp_um[side]}
        err = np.abs(m_fp - t_fp)
        out[f"fp_um_{side}"] = {"truth": float(np.max(np.abs(t_fp))), "measured": insp.fp_um[side],
                                "largest_per_tooth_error": float(np.nanmax(err)) if np.isfinite(err).any() else math.nan}
    return out


def run_inspection(
    recording: str | Path,
    out: str | Path,
    *,
    decoder: Callable | None = None,
    grade: int | None = None,
    voxel_mm: float = 0.1,
    min_bursts: int = 3,
    unwrap: str = "cad",
    save: str | Path | None = None,
    refine: bool = True,
    progress: Callable[[str], None] | None = None,
    network_support_px: int | None | Literal["product"] = PRODUCT_SUPPORT,
    max_sigma: float | None = None,
    point_sigma_mm: float | None = None,
    rig: str | Path | Rig | None = None,
    uncertainty: str | Path | None = None,
    shading: str | None = None,
    from_report: str | Path | None = None,
    **inspect_options,
) -> InspectionReport:
    """Replay ``recording`` with fusion, inspect the fused gear and write the report into ``out``.

    ``decoder``: as for :func:`~gearscan.replay.replay` (default three-step PS); ``save``: also
    write the rerun stream (bursts and the fused model) there; ``refine``: fit the fused points
    to the raw frames (:class:`~gearscan.recon.track.TrackRefiner`); ``network_support_px``: the reconstructor's
    fringe-support test for a network's pixels (None: none; ``"product"``: the decoding model's own for the path,
    else the product's, as :func:`~gearscan.replay.replay` resolves it with ``refine``); ``max_sigma``: the keep bound,
    rad (None: the product's for the path, as :func:`~gearscan.replay.replay` resolves it); ``point_sigma_mm``: the
    fitted cloud's bound on every point's sigma, mm (None: the fit's own; needs ``refine``); ``rig``: the calibration
    to measure with (a file or a Rig; None: the recording's own); ``uncertainty``: a ``gearscan verify`` statement
    for this gear type, stated with each reading (:func:`gearscan.verify.applied_uncertainty`); ``shading``: the frame
    fit's shading model (None: the product's, ``recon.track.SHADING``; needs ``refine``); ``from_report``: an earlier
    report folder of the same recording whose fused cloud is inspected again instead of replaying (other evaluation
    settings, datum, grade or uncertainty statement in seconds, not minutes; the replay's own settings are that
    report's). ``inspect_options`` go to :func:`~gearscan.recon.inspect.inspect_gear`.
    """
    from gearscan.replay import recording_rig, replay

    say = progress or (lambda s: None)
    reader = RecordingReader(recording)
    gear = reader.gear
    if gear is None:
        raise RecordingError(f"{reader.path}/recording.json: no 'gear' section: inspection needs the gear's nominal spec")
    if grade is not None:
        iso1328_tolerances(gear.module, 2 * gear.pitch_radius, grade)  # refuse a bad grade before the replay
    truth_teeth = len(((reader.meta.get("truth") or {}).get("single_pitch_um") or {}).get("left", [])) or None
    if truth_teeth is not None and truth_teeth != gear.teeth:
        raise RecordingError(f"{reader.path}/recording.json: its gear states {gear.teeth} teeth, its twin truth holds "
                             f"{truth_teeth}: the gear spec does not match the gear that was recorded")
    if point_sigma_mm is not None and not refine:
        raise ValueError("point_sigma_mm: the bound on the fitted cloud's points needs the frame fit (refine)")
    replay_only = {"save": save, "max_sigma": max_sigma, "point_sigma_mm": point_sigma_mm, "rig": rig, "shading": shading}
    if from_report is not None and any(v is not None for v in replay_only.values()):
        raise ValueError(f"from_report: the fused cloud was measured with that report's replay; "
                         f"{', '.join(k for k, v in replay_only.items() if v is not None)} would change a replay that does not run")
    if inspect_options.get("datum", DATUM) not in DATUMS:  # refused before the replay
        raise ValueError(f"datum: expected one of {', '.join(DATUMS)}, got {inspect_options['datum']!r}")
    if shading is not None and not refine:
        raise ValueError("shading: the shading model is the frame fit's; it needs the fit (refine)")
    statement = None
    if uncertainty is not None:  # refused before the replay: a bad file or another gear type costs no minutes
        statement = load_statement(uncertainty)
        statement.require_gear(gear.teeth, gear.module)
    span = revolution_deg(reader)
    if from_report is not None:
        earlier = earlier_measurement(from_report, reader)
        fused, metrics, rig, calibration = earlier.fused, earlier, earlier.rig, earlier.calibration
        say(f"inspecting again the fused cloud of {from_report} ({len(fused):,} points; no replay)")
    else:
        used = recording_rig(reader, rig)  # once: the replay measures with it and the report states its calibration
        say(f"replaying {len(reader)} frames ({span:.0f} deg of the turntable) with fusion")
        fuser = CloudFuser(voxel_mm, min_bursts)
        metrics = replay(recording, decoder=decoder, fuse=fuser, truth=False, unwrap=unwrap, save=save, refine=refine,
                         network_support_px=network_support_px, max_sigma=max_sigma, point_sigma_mm=point_sigma_mm,
                         shading=shading,
                         rig=None if rig is None else used)
        if metrics.fused is None or not len(metrics.fused):
            raise RecordingError(f"{reader.path}: no points were measured (or none seen by {min_bursts} bursts): nothing to inspect")
        fused = metrics.fused
        rig = None if rig is None else str(rig if not isinstance(rig, Rig) else f"Rig {rig.name!r}")
        calibration = used.calibration
    fitted = f", {int(fused.refined.sum()):,} fitted to the raw frames" if fused.refined is not None else ""
    say(f"fused {len(fused):,} points from {fused.bursts_added} bursts{fitted}; inspecting")
    insp = inspect_gear(fused.points, fused.sigma, gear, voxel_mm=voxel_mm, **inspect_options)
    d = 2 * gear.pitch_radius
    tolerances = iso1328_tolerances(gear.module, d, grade) if grade is not None else None
    try:
        classes = iso1328_class(insp.summary(), gear.module, d)
    except ValueError:  # module or diameter outside ISO 1328-1's range: no class to state
        classes = {}
    truth = truth_comparison(reader.meta, insp)
    stated = None
    if statement is not None:
        stated = applied_uncertainty(statement, inspection_readings(insp), insp.teeth, insp.module,
                                     (metrics.decoder or {}).get("model_fingerprint"), tolerances,
                                     {k: insp.settings[k] for k in ("xi_start", "xi_end", "bins")}, insp.coverage(),
                                     insp.profile_bins_left_out, insp.settings.get("datum"))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {"fused": save_fused(fused, out / "fused.ply")}
    files.update(write_plots(insp, out, tolerances))
    report = InspectionReport(insp, fused, grade, tolerances, classes, span, files, truth, metrics.refine or None,
                              (metrics.recon or {}).get("depth_sigma_source"),
                              (metrics.decoder or {}).get("turning_three_step", 0),
                              (metrics.recon or {}).get("rest_sigma_scale"), (metrics.recon or {}).get("rest_sigma_source"),
                              (metrics.decoder or {}).get("model"), (metrics.decoder or {}).get("model_fingerprint"),
                              rig, calibration, stated, None if from_report is None else str(from_report))
    files["json"] = out / "report.json"
    files["json"].write_text(json.dumps(report_json(report, reader.path), indent=2))
    files["markdown"] = out / "report.md"
    files["markdown"].write_text(report_markdown(report, reader.path))
    return report


# how the report names each datum (recon.inspect.DATUMS); a report from before session 59 has none: the flank fit
DATUM_TEXT = {"tip": "the tip lands' circle", "teeth": "placed by the flanks' radial part, each tooth turned freely"}


@dataclass(frozen=True)
class EarlierMeasurement:
    """What an earlier report of a recording holds of its replay: the fused cloud and the replay's facts the report
    states (the ``metrics`` of :func:`~gearscan.replay.replay` that :func:`run_inspection` reads)."""

    fused: FusedCloud
    decoder: dict
    recon: dict
    refine: dict | None
    rig: str | None
    calibration: CalibrationStatement | None


def earlier_measurement(folder: str | Path, reader: RecordingReader) -> EarlierMeasurement:
    """The fused cloud and replay facts of the report in ``folder`` (``report.json`` and its ``fused.ply``), which
    must be of ``reader``'s recording; refused, naming the file, where it is not a whole report of it."""
    folder = Path(folder)
    file = folder / "report.json"
    try:
        old = json.loads(file.read_text())
        fused_meta, model = old["fused"], old.get("model") or {}
        recording_name = Path(old["recording"]).name
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise RecordingError(f"--from-report {file}: not a `gearscan inspect` report ({exc!r})") from exc
    if recording_name != reader.path.name:
        raise RecordingError(f"--from-report {folder}: a report of the recording {recording_name!r}, not of "
                             f"{reader.path.name!r}")
    try:
        fused = load_fused(folder / "fused.ply", fused_meta["voxel_mm"], fused_meta["bursts"])
    except (OSError, ValueError, KeyError) as exc:
        raise RecordingError(f"--from-report {folder}: its fused cloud cannot be read ({exc})") from exc
    if len(fused) != fused_meta.get("points"):
        raise RecordingError(f"--from-report {folder}: fused.ply holds {len(fused):,} points, its report "
                             f"{fused_meta.get('points')}: not the cloud that report measured")
    refine = None
    if fused.refined is not None:
        bound = fused_meta.get("sigma_bound_um")
        refine = {"off_surface": fused_meta.get("dropped_off_surface"), "uncertain": fused_meta.get("dropped_uncertain"),
                  "sigma_bound_mm": None if bound is None else 1e-3 * bound, "unsettled": fused_meta.get("unsettled_fits"),
                  "implausible": fused_meta.get("implausible_fits"), "shading": fused_meta.get("frame_fit_shading"),
                  "quadratic_points": fused_meta.get("quadratic_fits"), "drift_fallback": fused_meta.get("drift_fallback_fits"),
                  "refined": fused_meta.get("refined_points")}
    calibration = old.get("rig_calibration")
    return EarlierMeasurement(
        fused=fused, decoder={"model": model.get("path"), "model_fingerprint": model.get("fingerprint"),
                              "turning_three_step": fused_meta.get("turning_three_step_bursts") or 0},
        recon={"depth_sigma_source": fused_meta.get("depth_sigma_source"),
               "rest_sigma_scale": fused_meta.get("rest_sigma_scale"),
               "rest_sigma_source": fused_meta.get("rest_sigma_source")},
        refine=refine, rig=old.get("rig"),
        calibration=None if calibration is None else CalibrationStatement.from_json(calibration, str(file)))


def profile_bins_note(insp: Inspection) -> str:
    """What the profile traces left out: bins with too few points or too loose a mean to count, which shorten the roll
    length a flank's Fα and ffα span (mostly at the root end, where bins hold the fewest points)."""
    n = insp.profile_bins_left_out
    if not n:
        return ""
    total = 2 * insp.teeth * int(insp.settings.get("bins", 20))
    return (f" {n} of {total} profile bins held points too few (under {insp.settings.get('min_bin_points', 3)}) or too "
            f"loose (a mean's standard error over {insp.settings.get('bin_se_max_um', 3):g} µm) to count; their flanks' "
            "Fα and ffα span a shorter roll length (`gearscan.recon.inspect.MIN_BIN_POINTS`).")


def calibration_sentence(rig: str | None, calibration: CalibrationStatement | None) -> str:
    """The report's line on the rig measured with (``rig``: its label where not the recording's own) and its
    calibration's stated uncertainty."""
    head = ("Measured with the recording's own rig calibration" if rig is None else
            f"Measured with the rig calibration `{rig}` (not the recording's own)")
    if calibration is None:
        return (head + ", which states no uncertainty of its own (written before gearscan stated one, or not by "
                "`gearscan calibrate`'s joint adjustment).")
    return f"{head}: {calibration.line()}. The values below do not include it."


def report_json(report: InspectionReport, recording: Path) -> dict:
    """The report as JSON (NaN as null)."""
    insp = report.inspection
    summary = insp.summary()
    return {
        "recording": str(recording),
        # what decoded the bursts: the network's weights and its decode's fingerprint (None: three-step PS)
        "model": {"path": report.model, "fingerprint": report.model_fingerprint},
        "rig": report.rig,  # the calibration measured with, where not the recording's own (null: the recording's)
        # that calibration's own stated uncertainty (gearscan calibrate's joint adjustment; null: it states none)
        "rig_calibration": None if report.calibration is None else report.calibration.to_json(),
        "profile_bins_left_out": insp.profile_bins_left_out,
        "revolution_deg": report.revolution_deg,
        # the earlier report whose fused cloud this inspection read again, without a replay (null: replayed for it)
        "fused_from": report.fused_from,
        "fused": {"points": len(report.fused), "bursts": report.fused.bursts_added, "voxel_mm": report.fused.voxel_mm,
                  "median_sigma_um": 1e3 * float(np.median(report.fused.sigma)),
                  # the deviation's own: the sigma's share along the CAD's normal (None: no deviation computed)
                  "median_deviation_sigma_um": (None if report.fused.deviation_sigma is None
                                                else 1e3 * float(np.median(report.fused.deviation_sigma))),
                  "median_bursts_per_point": float(np.median(report.fused.bursts)),
                  "refined_points": None if report.fused.refined is None else int(report.fused.refined.sum()),
                  "dropped_off_surface": (report.refine or {}).get("off_surface"),
                  "dropped_uncertain": (report.refine or {}).get("uncertain"),
                  "sigma_bound_um": (1e3 * report.refine["sigma_bound_mm"]
                                     if (report.refine or {}).get("sigma_bound_mm") else None),
                  "unsettled_fits": (report.refine or {}).get("unsettled"),
                  "implausible_fits": (report.refine or {}).get("implausible"),
                  "frame_fit_shading": (report.refine or {}).get("shading"),
                  # "mixed": the fits it took quadratic; "lambert" and "mixed": the points fitted with drift instead
                  "quadratic_fits": (report.refine or {}).get("quadratic_points"),
                  "drift_fallback_fits": (report.refine or {}).get("drift_fallback"),
                  # whose depth-sigma scales an unfitted point's sigma carries: model, product or unmeasured
                  "depth_sigma_source": report.depth_sigma_source,
                  # the scale an unfitted point's sigma carried (the decoding model's own, else the product's) and whose
                  "rest_sigma_scale": report.rest_sigma_scale, "rest_sigma_source": report.rest_sigma_source,
                  # bursts that turned, decoded by three-step PS (--classical): their unfitted points' sigma unmeasured
                  "turning_three_step_bursts": report.turning_three_step},
        "summary_um": insp.to_json()["profile_um"] | {k: _num(v) for k, v in summary.items()},
        "grade": report.grade,
        "tolerances_um": report.tolerances,
        "iso1328_class": report.classes,  # None: beyond class 11 or not measured (the text below tells which)
        # the class as the report states it: "n/a" (not measured), "> 11", "C or coarser" (a lower bound), "C"
        "iso1328_class_text": {k: class_text(insp, k, summary[k], report.classes.get(k), bool(report.classes))
                               for k in QUANTITIES},
        # per quantity, how many of a whole gear's values were measured: short of all, the value is a lower bound
        "coverage": {k: {"measured": m, "of": n} for k, (m, n) in insp.coverage().items()},
        "spec_warning": spec_note(report),
        # each reading with the U of the `gearscan verify` statement given (--uncertainty) and, graded, its ISO
        # 14253-1 decision (null: no statement given)
        "uncertainty": None if report.uncertainty is None else report.uncertainty.to_json(),
        "inspection": insp.to_json(),
        "twin_truth": jsonable(report.truth),
        "files": {k: str(v) for k, v in report.files.items()},
    }


def _num(v: float) -> float | None:
    return float(v) if v is not None and np.isfinite(v) else None


def _fmt(v: float | None, digits: int = 1) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"


def uncertainty_lines(stated: AppliedUncertainty | None) -> list[str]:
    """The console's lines on the measurement uncertainty (none without a statement)."""
    if stated is None:
        return []
    lines = [reading_text(key, r) + (f", tolerance {r.tolerance:g}: {r.decision}" if r.decision else "")
             + (f" ({r.why})" if r.why else "") for key, r in stated.readings.items()]
    return [*lines, f"({U_MEANING})", *(f"warning: {w}" for w in stated.warnings)]


def uncertainty_markdown(stated: AppliedUncertainty | None) -> list[str]:
    """The report's lines on the measurement uncertainty: each reading with the statement's U and its decision, or
    that no statement was given (the readings then carry no uncertainty)."""
    if stated is None:
        return ["", "No measurement uncertainty is stated (`--uncertainty`: a `gearscan verify` statement from a master "
                "gear of this type): the values above are readings, and a decision on them ignores what the instrument "
                "adds."]
    graded = any(r.decision for r in stated.readings.values())
    lines = ["", f"## Measurement uncertainty (`{stated.statement}`)", "", f"{U_MEANING}.", "",
             "| quantity | reading ± U |" + (" tolerance (µm) | ISO 14253-1 |" if graded else ""),
             "|---|---|" + ("---|---|" if graded else "")]
    for key, r in stated.readings.items():
        decision = f"{r.decision} ({r.why})" if r.why else r.decision
        lines.append(f"| {key}: {BUDGETED[key]} | {reading_text(key, r, named=False)} |"
                     + (f" {r.tolerance:g} | {decision} |" if r.decision else " – | – |" if graded else ""))
    if graded:
        lines += ["", "Conforms: |reading| + U within the tolerance; does not conform: |reading| - U beyond it; "
                  "undecided: in between, or a value within the tolerance read on part of the gear (ISO 14253-1). "
                  "Fr_gear_axis (about the inspection's datum axis) is not ISO's Fr and is not judged."]
    lines += [f"\n**Warning:** {w}." for w in stated.warnings]
    return lines


def report_markdown(report: InspectionReport, recording: Path) -> str:
    """A human-readable report: summary with tolerances, per-tooth table, plots."""
    insp, tol = report.inspection, report.tolerances
    summary = insp.summary()
    lines = [
        f"# Gear inspection: {recording.name}",
        "",
        ("Decoded by three-step PS." if report.model is None else
         f"Decoded by the network `{report.model}` (decode fingerprint {report.model_fingerprint})."),
        calibration_sentence(report.rig, report.calibration)
        + ("" if report.fused_from is None else f" The fused cloud is `{report.fused_from}`'s, inspected again "
           "without a replay."),
        "",
        f"Gear: z = {insp.teeth}, m = {insp.module:g} mm, pitch diameter {insp.pitch_diameter_mm:.2f} mm. "
        f"Fused model: {len(report.fused):,} points from {report.fused.bursts_added} bursts over "
        f"{report.revolution_deg:.0f}° of the turntable (voxel {report.fused.voxel_mm:g} mm, median "
        f"{np.median(report.fused.bursts):.0f} bursts and σ {1e3 * np.median(report.fused.sigma):.1f} µm per point"
        + ("" if report.fused.deviation_sigma is None or report.fused.ray is None else
           f" along its camera ray, {1e3 * np.median(report.fused.deviation_sigma):.1f} µm along the CAD's normal, "
           "the deviation's")
        + ")"
        + (f"; {100 * report.fused.refined.mean():.0f} % of the points fitted to the raw frames that saw them"
           + (f" ({report.refine['shading']} shading{shading_share(report.refine)})"
              if (report.refine or {}).get("shading") else "")
           + (f", every point's σ within {1e3 * report.refine['sigma_bound_mm']:g} µm (the fit's bound)."
              if (report.refine or {}).get("sigma_bound_mm") else ".")
           if report.fused.refined is not None else ".") + dropped_note(report.refine),
        "",
        f"Datum axis ({DATUM_TEXT.get(insp.settings.get('datum'), 'fitted to the flanks, one turn for all teeth')}): "
        f"{insp.eccentricity_um:.1f} µm from the turntable axis towards "
        f"{insp.eccentricity_deg:.1f}°; transverse section z = {insp.section_mm[0]:.1f} to {insp.section_mm[1]:.1f} mm.",
    ]
    for note in (unmeasured_sigma_note(report), turning_note(report)):
        if note:
            lines += ["", f"**{note}.**"]
    if note := spec_note(report):
        lines += ["", f"**Warning:** {note}."]
    if report.revolution_deg < 360 - 360 / insp.teeth:
        lines += ["", f"**Warning:** the recording covers {report.revolution_deg:.0f}° only: teeth never seen have no "
                  "pitch or profile, and Fp covers the teeth that were."]
    head = "| quantity | measured (µm) |" + (f" tolerance class {report.grade} (µm) | within |" if tol else "") + " ISO 1328-1 class |"
    lines += ["", "## Summary", "", head, "|---|---|" + ("---|---|" if tol else "") + "---|"]
    for key, (sym, text) in QUANTITIES.items():
        v = summary.get(key, math.nan)
        part = partial(insp, key) if np.isfinite(v) else ""
        row = f"| {sym}: {text} | {_fmt(v) if np.isfinite(v) else 'not measured'}{f' (on {part})' if part else ''} |"
        if tol:
            # a lower bound beyond the tolerance fails it; within it, it shows nothing about the values not measured
            within = ("n/a" if not np.isfinite(v) else "NO" if abs(v) > tol[key] else
                      f"not shown (on {part})" if part else "yes")
            row += f" {tol[key]:g} | {within} |"
        lines.append(row + f" {class_text(insp, key, v, report.classes.get(key), bool(report.classes))} |")
    if any(partial(insp, k) for k in QUANTITIES if np.isfinite(summary.get(k, math.nan))):
        lines += ["", "A value measured on fewer pitches, tooth spaces or flanks than the gear has (\"on k of n\") is a "
                  "lower bound: those not measured may deviate more, so its class is the finest the gear can be."]
    lines += uncertainty_markdown(report.uncertainty)
    lines += ["", f"Runout: {_fmt(insp.runout_from_eccentricity_um)} µm from the eccentricity (≈ 2e), "
              f"{_fmt(insp.runout_about_gear_axis_um)} µm from the tooth spaces about the gear's own axis.", ""]
    lines += [f"**Chipped / damaged teeth:** {chip_verdict(insp)}.", ""]
    lines += ["## Per tooth", "",
              "| tooth | fp left | fp right | Fp,k left | Fp,k right | runout (space k/k+1) | Fα left | Fα right | tip: missing mm² | flag |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    fl = {(f.tooth, f.side): f for f in insp.flanks}
    for k in range(insp.teeth):
        tip = insp.tips[k]
        lines.append(
            f"| {k} | {_fmt(insp.single_pitch_um['left'][k])} | {_fmt(insp.single_pitch_um['right'][k])} | "
            f"{_fmt(insp.cumulative_pitch_um['left'][k])} | {_fmt(insp.cumulative_pitch_um['right'][k])} | "
            f"{_fmt(insp.runout_curve_um[k])} | {_fmt(fl[(k, 'left')].F_alpha_um)} | {_fmt(fl[(k, 'right')].F_alpha_um)} | "
            f"{tip.missing_mm2:.2f} | {'CHIPPED' if tip.chipped else ''} |")
    if report.truth:
        lines += ["", "## Twin truth (injected defects) vs measured", "", "| quantity | truth | measured |", "|---|---|---|"]
        for key, val in report.truth.items():
            t, m = val["truth"], val["measured"]
            lines.append(f"| {key} | {t if isinstance(t, list) else _fmt(t)} | {m if isinstance(m, list) else _fmt(m)} |")
    lines += ["", "## Plots", "", "![pitch](pitch.png)", "", "![runout](runout.png)", "", "![profiles](profiles.png)", "",
              "Definitions: `gearscan.recon.inspect` (fp, Fp about the fitted gear axis on the pitch circle; Fr ball "
              "probe; Fα, ffα, fHα over the evaluation range "
              f"{insp.settings['evaluation_roll_mm'][0]:.2f}-{insp.settings['evaluation_roll_mm'][1]:.2f} mm of roll "
              "length); tolerances ISO 1328-1:2013 eq. 5-9, F_rT = 0.9 F_pT." + profile_bins_note(insp), ""]
    return "\n".join(lines)


def write_plots(insp: Inspection, out: Path, tolerances: dict[str, float] | None) -> dict[str, Path]:
    """pitch.png, runout.png and profiles.png (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    teeth = np.arange(insp.teeth)
    files = {}
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for i, side in enumerate(("left", "right")):
        a1.bar(teeth + (i - 0.5) * 0.4, insp.single_pitch_um[side], width=0.4, label=f"{side} flanks")
        a2.plot(teeth, insp.cumulative_pitch_um[side], "o-", label=f"{side} flanks")
    if tolerances:
        for a, key in ((a1, "fp"), (a2, "Fp")):
            for sgn in (-1, 1):
                a.axhline(sgn * tolerances[key], color="r", ls="--", lw=0.8)
    a1.set_ylabel("single pitch fp (µm)")
    a2.set_ylabel("cumulative pitch Fp,k (µm)")
    a2.set_xlabel("tooth (pitch k: from tooth k-1 to k)")
    a1.set_title(f"Pitch: Fp left {_fmt(insp.Fp_um['left'])} µm, right {_fmt(insp.Fp_um['right'])} µm")
    a1.legend()
    a2.set_xticks(teeth)
    fig.tight_layout()
    files["pitch"] = out / "pitch.png"
    fig.savefig(files["pitch"], dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(9, 4))
    gaps = teeth + 0.5
    ax.plot(gaps, insp.runout_curve_um, "o-", label="ball probe radial position")
    fine = np.linspace(0, insp.teeth, 200)
    ecc = insp.eccentricity_um * np.cos(np.radians(fine * 360 / insp.teeth + insp.rotation_deg - insp.eccentricity_deg))
    ax.plot(fine, ecc, "--", label=f"eccentricity {insp.eccentricity_um:.1f} µm")
    ax.set_xlabel("tooth space (between tooth k and k+1)")
    ax.set_ylabel("radial position (µm)")
    ax.set_title(f"Runout Fr = {_fmt(insp.Fr_um)} µm")
    if tolerances:
        ax.axhline(np.nanmin(insp.runout_curve_um) + tolerances["Fr"], color="r", ls="--", lw=0.8, label="F_rT")
    ax.legend()
    fig.tight_layout()
    files["runout"] = out / "runout.png"
    fig.savefig(files["runout"], dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(12, 5), sharey=True)
    for ax, side in zip(axes, ("left", "right"), strict=True):
        for f in insp.flanks:
            if f.side == side and f.measured:
                chipped = f.tooth in insp.chipped_teeth
                ax.plot(f.roll_mm, f.trace_um, lw=2 if chipped else 0.8, color="r" if chipped else None,
                        label=f"tooth {f.tooth} (chipped)" if chipped else None)
        ax.set_title(f"{side} flanks: profile deviation")
        ax.set_xlabel("roll length (mm)")
        ax.axhline(0, color="k", lw=0.5)
    axes[0].set_ylabel("deviation along the normal (µm, + material)")
    if insp.chipped_teeth:
        axes[0].legend()
    fig.tight_layout()
    files["profiles"] = out / "profiles.png"
    fig.savefig(files["profiles"], dpi=110)
    plt.close(fig)
    return files
