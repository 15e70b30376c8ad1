"""Fit a model's uncertainty calibration on twin validation data and store it in its JSON.

Per mode (deterministic, and Monte Carlo when the model has Concrete Dropout) the network
predicts whole validation bursts; the wrapped phase errors against the twin's truth and the
predicted total sigmas fit ``sigma' = a * sigma**b`` by Gaussian NLL
(:func:`~gearscan.inference.uncertainty.fit_sigma_calibration`). To show that the map transfers,
it is first fitted on half of the start points and scored on the other half; the stored map is
then fitted on all of them. :func:`calibrate_trained_model` fits the same maps (and the variance
scale) on the validation loader at the end of training.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from contextlib import AbstractContextManager
from pathlib import Path

import numpy as np
import torch

from gearscan.core.phase import phase_error
from gearscan.inference.concrete_dropout import set_stochastic
from gearscan.inference.model_io import read_config, write_config
from gearscan.inference.models import PhaseNet
from gearscan.inference.predictor import Predictor, model_path
from gearscan.inference.uncertainty import (
    SigmaCalibration,
    fit_sigma_calibration,
    fit_variance_scale,
    gaussian_nll,
    mc_moments,
    phase_sigma,
    plot_reliability,
    reliability,
)


def collect_errors(
    predictor: Predictor, dataset, items: Sequence[int], mc: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wrapped phase errors, predicted total sigmas and start-point ids over the truth masks."""
    errs, sigmas, groups = [], [], []
    for n, i in enumerate(items):
        item = dataset[int(i)]
        x = torch.from_numpy(np.asarray(item["input"], np.float32))[None]
        r = predictor.predict_tensor(x, mc)
        mask = np.asarray(item["mask"], bool)
        errs.append(phase_error(r.phase, item["phase"])[mask].astype(np.float32))
        sigmas.append(r.sigma_total[mask])
        groups.append(np.full(int(mask.sum()), int(item["group"])))
        if progress:
            progress(n + 1, len(items))
    return np.concatenate(errs), np.concatenate(sigmas), np.concatenate(groups)


def _scores(err: np.ndarray, sigma: np.ndarray) -> dict[str, float]:
    return {"nll": gaussian_nll(err, sigma), "ece": reliability(err, sigma).ece,
            "rmse": float(np.sqrt(np.mean(err.astype(np.float64) ** 2))),
            "mean_sigma": float(np.mean(sigma))}


def fit_mode(err: np.ndarray, sigma: np.ndarray, groups: np.ndarray) -> tuple[SigmaCalibration, dict]:
    """Fit on all pixels; report a fit on half the start points scored on the other half."""
    ids = np.unique(groups)
    report: dict = {}
    if ids.size >= 2:
        fit_ids = ids[: ids.size // 2]
        fit = np.isin(groups, fit_ids)
        half, _ = fit_sigma_calibration(err[fit], sigma[fit])
        report["held_out"] = {
            "fitted_on_start_points": [int(g) for g in fit_ids],
            "before": _scores(err[~fit], sigma[~fit]),
            "after": _scores(err[~fit], half(sigma[~fit])),
            "map": half.to_json(),
        }
    cal, metrics = fit_sigma_calibration(err, sigma)
    report["all"] = metrics
    return cal, report


def calibrate_model(
    model: str | Path | None, val: str | Path, *, items: int = 64, mc: int = 20,
    seed: int = 0, output: str | Path | None = None, progress: Callable[[str], None] | None = None,
) -> dict:
    """Fit and store the sigma calibration of ``model`` (default: the shipped one) on ``val``.

    Writes ``sigma_calibration`` and an ``uncertainty_calibration`` report into the model's JSON
    (or into ``output``'s JSON, copying the weights there); returns that report.
    """
    from gearscan.inference.data import MotionInput
    from gearscan.twin.dataset import TwinBurstDataset

    path = model_path(model)
    if items < 2:
        raise ValueError(f"items: expected >= 2 validation bursts, got {items}")
    predictor = Predictor.load(path)
    predictor.calibration = {}  # fit on the uncalibrated sigma (var_scale stays applied)
    # the bursts the network decodes in use: moving ones (the pipeline's Decoder sends still
    # bursts to three-step PS), turning either way
    dataset = TwinBurstDataset(val, crop=None, reverse=True)
    if predictor.needs_angles:
        dataset = MotionInput(dataset)
    rng = np.random.default_rng(seed)
    pick = sorted(rng.choice(len(dataset), min(items, len(dataset)), replace=False).tolist())
    modes = [("deterministic", 0)] + ([("mc", mc)] if mc > 0 and predictor.has_dropout else [])
    calibration, report = {}, {"data": str(val), "items": len(pick), "seed": seed}
    for name, passes in modes:
        def tick(n: int, total: int, name: str = name) -> None:
            if progress and (n == total or n % 8 == 0):
                progress(f"{name}: {n}/{total} bursts")

        err, sigma, groups = collect_errors(predictor, dataset, pick, passes, tick)
        cal, rep = fit_mode(err, sigma, groups)
        calibration[name] = cal
        report[name] = {"passes": passes, "map": cal.to_json(), **rep}
    meta = read_config(path)
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
    ECE improves), then the sigma map ``a * sigma**b`` per mode by Gaussian NLL
    (:func:`fit_sigma_calibration`; MC mode with ``mc`` passes when ``mc`` > 0), as
    ``gearscan calibrate-uncertainty`` fits it. ``val_loader`` is iterated once per mode;
    ``reliability_png``: where to draw the deterministic reliability diagram (None: not drawn).
    """

    def collect(passes: int) -> tuple[np.ndarray, np.ndarray]:
        errs, sigs = [], []
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
            errs.append(phase_error(np.arctan2(M, D), batch["phase"].numpy())[mask])
            # model and data sigma add in quadrature: one propagation of the summed variances
            sigs.append(phase_sigma(M, D, var_M, var_D)[mask])
        return np.concatenate(errs), np.concatenate(sigs)

    model.eval()
    set_stochastic(model, False)
    err, sig = collect(0)
    if err.size == 0:
        return 1.0, {}, {}
    k, before, after = fit_variance_scale(err, sig)
    sig = sig * math.sqrt(k)
    det_map, det_fit = fit_sigma_calibration(err, sig)
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
            reliability(err, det_map(sig)),
            reliability_png,
            f"validation, var scale {k:.3g}, sigma' = {det_map.a:.3g} sigma^{det_map.b:.2f}",
        )
    if mc > 0:
        err, sig = collect(mc)
        mc_map, mc_fit = fit_sigma_calibration(err, sig * math.sqrt(k))
        sigma_cal["mc"] = mc_map.to_json()
        report["sigma_calibration"]["mc"] = mc_fit | {"passes": mc}
    model.eval()
    set_stochastic(model, False)
    return k, report, sigma_cal
