"""Fit a model's uncertainty calibration on twin validation data and store it in its JSON.

Per mode (deterministic, and Monte Carlo when the model has Concrete Dropout) the network
predicts whole validation bursts, moving ones (both turning senses) and still ones: without
angles the network cannot tell them apart, so neither can its sigma. The wrapped phase errors
against the twin's truth, the predicted total sigmas, the departures from three-step PS and the
network's fringe density fit the map by the log score of the ECE's event: the power law
``sigma' = a * sigma**b * (departure + d0)**c`` (:func:`~gearscan.inference.uncertainty.fit_sigma_calibration`)
or the additive map (:func:`~gearscan.inference.uncertainty.fit_additive_map`, every validation family x kind
weighing the same). A validation family is one folder, or several folders pooled (the same rig, other gears).
To show that the map transfers, each family is first scored by a map fitted on the others (one family: on half
of its start points, scored on the other half); the stored map is then fitted on all of them.
:func:`calibrate_trained_model` fits the same maps (and the variance scale) on the validation
loader at the end of training.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Iterable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from gearscan.core.phase import phase_error
from gearscan.inference.concrete_dropout import set_stochastic
from gearscan.inference.model_io import read_config, write_config
from gearscan.inference.models import PhaseNet, classical_md
from gearscan.inference.predictor import (
    Predictor,
    apply_still_gates,
    model_path,
    still_burst_gate,
)
from gearscan.inference.uncertainty import (
    FORM_FEATURES,
    MAP_FEATURES,
    MAP_FORMS,
    MC_ONLY_FORMS,
    SigmaMap,
    departure,
    event_log_score,
    fit_additive_map,
    fit_sigma_calibration,
    fit_variance_scale,
    fringe_density,
    gaussian_nll,
    local_departure,
    map_form,
    mc_moments,
    phase_curvature,
    phase_sigma,
    plot_reliability,
    reliability,
    sigma_map_from_json,
)


@dataclass(frozen=True, slots=True)
class PixelErrors:
    """Per truth-mask pixel: wrapped phase error, uncalibrated total sigma, departure from
    three-step PS (rad), the pixel's validation family (``folder``), start point and still flag, whether the
    still-burst gate decoded its burst by three-step PS (its sigma is then three-step's own, which the map
    never touches at run time: such pixels are scored, not fitted), the fringe density of the network's
    phase (rad/px), its curvature (rad/px^2), the local departure (rad) and the uncalibrated aleatoric part of
    the sigma (rad; MC mode: the passes' mean data variance propagated at the reported M, D): every feature a sigma
    map may read."""

    error: np.ndarray
    sigma: np.ndarray
    departure: np.ndarray
    folder: np.ndarray
    group: np.ndarray
    still: np.ndarray
    gated: np.ndarray
    density: np.ndarray
    curvature: np.ndarray
    local_departure: np.ndarray
    sigma_data: np.ndarray

    def features(self) -> dict[str, np.ndarray]:
        """The map inputs besides the sigma, as :class:`~gearscan.inference.uncertainty.AdditiveSigmaMap` names them."""
        return {name: getattr(self, name) for name in MAP_FEATURES[1:]}

    def take(self, keep: np.ndarray) -> PixelErrors:
        return PixelErrors(*(getattr(self, f)[keep] for f in self.__slots__))

    @staticmethod
    def concat(parts: Sequence[PixelErrors]) -> PixelErrors:
        return PixelErrors(*(np.concatenate([getattr(p, f) for p in parts]) for f in PixelErrors.__slots__))


def collect_errors(
    predictor: Predictor, dataset, items: Sequence[int], mc: int = 0,
    progress: Callable[[int, int], None] | None = None, *, folder: int = 0, still: bool = False,
) -> PixelErrors:
    """Errors, sigmas (as ``predictor`` reports them) and departures over the truth masks.

    The departure is the network's own phase against three-step PS's, before any still gate, as
    the Predictor reads it at run time; the error is the gated output's (both gates, as the Predictor
    applies them).
    """
    ungated = copy.copy(predictor)
    ungated.still_gate_rad = ungated.still_burst_rad = 0.0
    calibration = predictor.calibration.get("mc" if mc > 0 else "deterministic")
    parts = []
    for n, i in enumerate(items):
        item = dataset[int(i)]
        x = torch.from_numpy(np.asarray(item["input"], np.float32))[None]
        net = ungated.predict_tensor(x, mc)
        classical = classical_md(x[:, :3])[0].numpy()
        frames = x[0, :3].numpy()
        taken = False
        if mc > 0 and predictor.still_burst_rad > 0:  # as the Predictor does: the deterministic pass decides
            gated, taken = still_burst_gate(ungated.predict_tensor(x, 0), classical, predictor.still_burst_rad,
                                            predictor.calibration.get("deterministic"), predictor.still_burst_sigma,
                                            frames=frames, max_motion=predictor.still_burst_motion)
        r = gated if taken else apply_still_gates(
            net, classical, pixel_rad=predictor.still_gate_rad, burst_rad=predictor.still_burst_rad if mc == 0 else 0.0,
            calibration=calibration, burst_sigma=predictor.still_burst_sigma, frames=frames,
            max_motion=predictor.still_burst_motion)[0]
        mask = np.asarray(item["mask"], bool)
        k = int(mask.sum())
        dep = departure(net.phase, np.arctan2(*classical))
        parts.append(PixelErrors(
            phase_error(r.phase, item["phase"])[mask].astype(np.float32), r.sigma_total[mask],
            dep[mask], np.full(k, folder, np.int16),
            np.full(k, int(item["group"]), np.int32), np.full(k, still, bool), np.full(k, r.mode == "three-step"),
            fringe_density(net.phase)[mask], phase_curvature(net.phase)[mask], local_departure(dep)[mask],
            r.sigma_data[mask]))
        if progress:
            progress(n + 1, len(items))
    return PixelErrors.concat(parts)


def _scores(px: PixelErrors, sigma: np.ndarray) -> dict[str, float]:
    """NLL, event score, RMSE, mean sigma, and the ECE of the moving and still pixels apart."""
    out = {"nll": gaussian_nll(px.error, sigma), "event_score": event_log_score(px.error, sigma),
           "ece": reliability(px.error, sigma).ece,
           "rmse": float(np.sqrt(np.mean(px.error.astype(np.float64) ** 2))),
           "mean_sigma": float(np.mean(sigma))}
    for name, keep in (("moving", ~px.still), ("still", px.still)):
        if keep.any():
            out[f"ece_{name}"] = reliability(px.error[keep], sigma[keep]).ece
    return out


def _fit(px: PixelErrors, form: str = "power") -> tuple[SigmaMap, dict]:
    """The map of ``form`` fitted on the pixels it applies to at run time (not those of gated bursts); the
    additive map with every family x kind weighing the same."""
    fit = px.take(~px.gated) if px.gated.any() and not px.gated.all() else px
    if form == "power":
        return fit_sigma_calibration(fit.error, fit.sigma, fit.departure)
    if form not in FORM_FEATURES:
        raise ValueError(f"form: expected one of {MAP_FORMS}, got {form!r}")
    cell = fit.folder.astype(np.int64) * 2 + fit.still
    counts = np.bincount(cell)
    cal, metrics = fit_additive_map(fit.error, fit.sigma, **fit.features(), weights=1.0 / counts[cell],
                                    features=FORM_FEATURES[form])
    # each family x kind weighs the same: say how many pixels carry each weight
    metrics["cell_pixels"] = {f"{k // 2}:{'still' if k % 2 else 'moving'}": int(n) for k, n in enumerate(counts) if n}
    return cal, metrics


def _calibrated(cal: SigmaMap, px: PixelErrors) -> np.ndarray:
    """Each pixel's sigma as the Predictor reports it with ``cal``: gated bursts keep three-step's."""
    return np.where(px.gated, px.sigma, cal(px.sigma, **px.features())).astype(np.float32)


def fit_mode(px: PixelErrors, folders: Sequence[str], form: str = "power") -> tuple[SigmaMap, dict]:
    """Fit a map of ``form`` on all pixels; report each held-out piece scored by a map fitted without it.

    Several families: leave one family out. One family: fit on half its start points, score the rest.
    """
    report: dict = {"held_out": []}
    if len(folders) >= 2:
        pieces = [(f"folder {name}", px.folder == k) for k, name in enumerate(folders)]
    else:
        ids = np.unique(px.group)
        pieces = ([(f"start points {[int(g) for g in ids[ids.size // 2:]]}", ~np.isin(px.group, ids[: ids.size // 2]))]
                  if ids.size >= 2 else [])
    for name, held in pieces:
        if held.all() or not held.any():
            continue
        part, _ = _fit(px.take(~held), form)
        test = px.take(held)
        report["held_out"].append({
            "scored": name, "map": part.to_json(),
            "before": _scores(test, test.sigma), "after": _scores(test, _calibrated(part, test)),
        })
    cal, metrics = _fit(px, form)
    report["all"] = metrics | {"after": _scores(px, _calibrated(cal, px)), "gated_pixels": int(px.gated.sum())}
    return cal, report


def family_folders(family: str | Path | Sequence[str | Path]) -> list[str]:
    """One validation family's folders: a folder, a list pooled as one, or comma-joined (as reports store them)."""
    group = str(family).split(",") if isinstance(family, str | Path) else [str(f) for f in family]
    if not group or not all(f.strip() for f in group):
        raise ValueError(f"val family {family!r}: expected one or more folder names (comma-joined: no empty one)")
    return group


def val_samples(folders: Sequence[str | Sequence[str]], items: int, seed: int,
                needs_angles: bool) -> list[tuple[int, object, list[int], bool]]:
    """Per validation family (a folder, or a list of folders pooled as one, or comma-joined), a seeded sample of
    ``items`` moving bursts (both senses) and ``items // 2`` still ones, shared out over its folders: ``(family
    index, dataset, picked items, still)``, whole images."""
    from gearscan.inference.data import MotionInput
    from gearscan.twin.dataset import TwinBurstDataset

    sets = []
    for k, family in enumerate(folders):
        group = family_folders(family)
        if items // 2 < len(group):
            raise ValueError(f"items: {items} moving and {items // 2} still bursts cannot be shared out over the "
                             f"{len(group)} folders of val family {family!r}; expected items >= {2 * len(group)}")
        for j, folder in enumerate(group):
            # one folder per family: the generator as before (seed, k), so a stored sample is drawn again
            rng = np.random.default_rng([seed, k] if len(group) == 1 else [seed, k, j])
            for still in (False, True):
                ds = (TwinBurstDataset(folder, crop=None, static=True, motion="uniform", max_span=0) if still
                      else TwinBurstDataset(folder, crop=None, reverse=True))
                if needs_angles:
                    ds = MotionInput(ds)
                want = (items // 2 if still else items) // len(group)
                n = min(want, len(ds))
                if n:
                    sets.append((k, ds, sorted(rng.choice(len(ds), n, replace=False).tolist()), still))
    return sets


def calibrate_model(
    model: str | Path | None, val: str | Path | Sequence[str | Path | Sequence[str | Path]], *, items: int = 64,
    mc: int = 20, seed: int = 0, output: str | Path | None = None, progress: Callable[[str], None] | None = None,
    orientation: str = "normal", modes: Sequence[str] = ("deterministic", "mc"), form: str | None = None,
) -> dict:
    """Fit and store the sigma calibration of ``model`` (default: the shipped one) on ``val``.

    ``val``: one or more validation families, each a twin validation folder or a list of folders pooled as one
    (e.g. one rig's gears; or comma-joined, as the report stores it); per family ``items`` moving bursts and
    ``items // 2`` still ones. ``form``: the map's form, ``"power"``, ``"additive"``, ``"additive-local"`` or, for
    the MC map alone, ``"additive-local-data"`` (:data:`~gearscan.inference.uncertainty.MAP_FORMS`); None: per mode,
    the form of the model's stored map (none stored: the power law). Writes ``sigma_calibration`` and an ``uncertainty_calibration`` report into the model's
    JSON (or into ``output``'s JSON, copying the weights there); returns
    that report. ``orientation``: the Predictor's fringe orientation on the val bursts; every twin
    rig's is ``"normal"``, as a user sets it for the rig (``"auto"``'s per-burst vote misreads some
    fast bursts, and their mirrored decode would enter the fit). ``modes``: which maps to refit; the JSON keeps
    the others and their reports (e.g. ``("mc",)`` after MC mode's phase changed: ``scripts/choose_mc_phase.py``).
    """
    unknown = set(modes) - {"deterministic", "mc"}
    if not modes or unknown:
        raise ValueError(f"modes: expected some of ('deterministic', 'mc'), got {tuple(modes)}")
    if form is not None and form not in MAP_FORMS:
        raise ValueError(f"form: expected one of {MAP_FORMS} or None (the model's), got {form!r}")
    if form in MC_ONLY_FORMS and "deterministic" in modes:
        raise ValueError(f"form {form!r} reads the aleatoric sigma apart, which in the deterministic pass is the "
                         f"total: MC mode only; pass --modes mc (modes=('mc',)), got {tuple(modes)}")
    path = model_path(model)
    if items < 2:
        raise ValueError(f"items: expected >= 2 validation bursts, got {items}")
    families = [family_folders(v) for v in ([val] if isinstance(val, str | Path) else val)]
    if not families:
        raise ValueError("val: expected at least one validation folder")
    folders = [",".join(f) for f in families]  # each family's name in the report
    predictor = Predictor.load(path, orientation=orientation)
    predictor.calibration = {}  # fit on the uncalibrated sigma (var_scale stays applied)
    sets = val_samples(families, items, seed, predictor.needs_angles)
    fitting = ([("deterministic", 0)] if "deterministic" in modes else []) + (
        [("mc", mc)] if "mc" in modes and mc > 0 and predictor.has_dropout else [])
    if not fitting:
        raise ValueError(f"modes {tuple(modes)}: nothing to fit (MC needs mc > 0 and a model with Concrete Dropout)")
    meta = read_config(path)
    stored = {k: sigma_map_from_json(v, f"sigma_calibration.{k}")
              for k, v in (meta.get("sigma_calibration") or {}).items()}
    refit = {name for name, _ in fitting}  # a mode not fitted (e.g. MC with mc=0) keeps its stored map
    calibration = {k: v for k, v in stored.items() if k not in refit}
    report = {"data": folders, "items": {"moving": sum(len(p) for _, _, p, s in sets if not s),
                                         "still": sum(len(p) for _, _, p, s in sets if s)}, "seed": seed,
              "orientation": orientation}
    before = meta.get("uncertainty_calibration") or {}
    sample = ("data", "items", "seed", "orientation")
    for k in calibration:  # a kept mode keeps its report; one written before modes named their sample gets the old one
        if k in before:
            report[k] = {**{f: before[f] for f in sample if f in before}, **before[k]}
    for name, passes in fitting:
        parts = []
        for k, ds, pick, still in sets:
            def tick(n: int, total: int, name: str = name, k: int = k, still: bool = still) -> None:
                if progress and (n == total or n % 8 == 0):
                    progress(f"{name}: {folders[k]} {'still' if still else 'moving'} {n}/{total} bursts")

            parts.append(collect_errors(predictor, ds, pick, passes, tick, folder=k, still=still))
        mode_form = form or map_form(stored.get(name))
        cal, rep = fit_mode(PixelErrors.concat(parts), folders, mode_form)
        calibration[name] = cal
        # each mode names its own sample: a later refit of one mode may use other data
        report[name] = {"passes": passes, "form": mode_form, "data": folders, "items": report["items"],
                        "seed": seed, "orientation": orientation, "map": cal.to_json(), **rep}
    report["fitted"] = [name for name, _ in fitting]  # the modes this run fitted; the others are kept as they were
    meta["sigma_calibration"] = {k: v.to_json() for k, v in calibration.items()}
    meta["uncertainty_calibration"] = report
    target = path
    if output is not None:
        import shutil

        target = Path(output)
        if target.suffix != ".safetensors":
            raise ValueError(f"output: expected a .safetensors path, got {target}")
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, target)
    write_config(target, meta)
    return report


@torch.no_grad()
def calibrate_trained_model(
    model: PhaseNet,
    val_loader: Iterable[dict],
    device: torch.device,
    autocast: Callable[[], AbstractContextManager[object]],
    mc: int = 0,
    reliability_png: str | Path | None = None,
) -> tuple[float, dict, dict]:
    """Fit a freshly trained model's uncertainty calibration on validation batches.

    Returns (var_scale, report, sigma maps): the deterministic-mode variance scale (kept only if
    ECE improves), then the sigma map ``a * sigma**b * (departure + d0)**c`` per mode by the
    event log score (:func:`fit_sigma_calibration`; MC mode with ``mc`` passes when ``mc`` > 0), as
    ``gearscan calibrate-uncertainty`` fits it. ``val_loader`` is iterated once per mode;
    ``reliability_png``: where to draw the deterministic reliability diagram (None: not drawn).
    """

    def collect(passes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        errs, sigs, deps = [], [], []
        for batch in val_loader:
            x = batch["input"].to(device)
            with autocast():
                if passes:
                    st = mc_moments(model, x, passes)
                    M, D = st.M.cpu().numpy(), st.D.cpu().numpy()
                    var_M = (st.model_var_M + st.data_var_M).cpu().numpy()
                    var_D = (st.model_var_D + st.data_var_D).cpu().numpy()
                else:
                    pred = model(x).float().cpu().numpy()
                    M, D, var_M, var_D = pred[:, 0], pred[:, 1], pred[:, 2], pred[:, 3]
            mask = batch["mask"].numpy().astype(bool)
            phase = np.arctan2(M, D)
            errs.append(phase_error(phase, batch["phase"].numpy())[mask])
            # model and data sigma add in quadrature: one propagation of the summed variances
            sigs.append(phase_sigma(M, D, var_M, var_D)[mask])
            md3 = classical_md(x[:, :3].float()).cpu().numpy()
            deps.append(departure(phase, np.arctan2(md3[:, 0], md3[:, 1]))[mask])
        return np.concatenate(errs), np.concatenate(sigs), np.concatenate(deps)

    model.eval()
    set_stochastic(model, False)
    err, sig, dep = collect(0)
    if err.size == 0:
        return 1.0, {}, {}
    k, before, after = fit_variance_scale(err, sig)
    sig = sig * math.sqrt(k)
    det_map, det_fit = fit_sigma_calibration(err, sig, dep)
    sigma_cal = {"deterministic": det_map.to_json()}
    report = {
        "mode": "deterministic",
        "var_scale": k,
        "ece_before": before,
        "ece_after": after,
        "pixels": int(err.size),
        "sigma_calibration": {"deterministic": det_fit},
    }
    if reliability_png is not None:
        plot_reliability(
            reliability(err, det_map(sig, dep)),
            reliability_png,
            f"validation, var scale {k:.3g}, sigma' = {det_map.a:.3g} sigma^{det_map.b:.2f} "
            f"(departure + {det_map.d0:g})^{det_map.c:.2f}",
        )
    if mc > 0:
        err, sig, dep = collect(mc)
        mc_map, mc_fit = fit_sigma_calibration(err, sig * math.sqrt(k), dep)
        sigma_cal["mc"] = mc_map.to_json()
        report["sigma_calibration"]["mc"] = mc_fit | {"passes": mc}
    model.eval()
    set_stochastic(model, False)
    return k, report, sigma_cal
