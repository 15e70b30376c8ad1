"""``gearscan evaluate``: the paper's section 3 as a rerunnable report (Markdown + PNG + JSON).

Parts (paper figure numbers in brackets):

1. transfer learning [11]: fine-tuning from the twin-pretrained model vs from Kaiming init on a
   target domain (another rig, a noisier camera), same budget, per gear;
2. networks [12-14]: CD-DCU-Net vs U-Net, TS-U-Net, DR-U-Net: loss curves, RMSE, error maps;
3. loss ablation [15-17]: with vs without the temperature constant and MSE weight;
4. uncertainty [18-19]: mean M/D and model/data/total uncertainty maps, reliability diagram,
   ECE, sparsification against the oracle;
5. classical [20-21]: three-step PS, AIA and Hilbert compensation vs the network (det, MC):
   phase RMSE and point-cloud error vs CAD;
6. generalisation [22]: unseen frame intervals, RMSE and cloud error vs the frame 1-3 span.

All scenes are twin gears the model did not train on (tooth count 25).

This module runs the parts and scores the methods on burst cases; the small training runs of
parts 1 and 3 are :mod:`gearscan.inference.experiments`, the figures
:mod:`gearscan.report_figures`, the Markdown and the summary :mod:`gearscan.report_markdown`.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from gearscan import report_figures as figures
from gearscan.core.gear import GearSpec
from gearscan.core.phase import phase_error
from gearscan.core.rig import default_rig
from gearscan.evaluate import (
    GENERALISATION,
    PAPER_MOTIONS,
    STATIC,
    BurstCase,
    Scene,
    builtin_scenes,
    classical_method,
    network_method,
    render_cases,
    scenes_from_dataset,
    score,
    scores_table,
)
from gearscan.report_markdown import POOLED, render_markdown, summarise
from gearscan.twin.render import Optics

PEER_NAMES = ("cd-dcu-net", "unet", "ts-unet", "dr-unet")  # run folders under --peers
PEER_LABELS = {"cd-dcu-net": "cd-dcu-net (peer budget)"}  # how the networks table names a peer run


@dataclass
class EvalOptions:
    model: Path | None
    data: list[Path]
    out: Path
    quick: bool = False
    peers: Path | None = None
    mc: int = 20
    per_motion: int = 3
    seed: int = 0
    train_data: Path | None = None  # twin dataset for the ablation runs (rendered small if None)

    @property
    def budget(self) -> dict[str, int]:
        """Training budget of the small runs of parts 1 and 3 (epochs x steps, crop)."""
        if self.quick:
            return {"epochs": 2, "steps": 4, "crop": 64, "batch": 4, "size": 160, "poses": 6}
        return {"epochs": 8, "steps": 30, "crop": 128, "batch": 8, "size": 256, "poses": 18}

    def training_budget(self):
        """:attr:`budget` as the experiments' :class:`~gearscan.inference.experiments.Budget`."""
        from gearscan.inference.experiments import Budget

        b = self.budget
        return Budget(epochs=b["epochs"], steps=b["steps"], batch=b["batch"])


# --- parts -------------------------------------------------------------------------------------
def target_scenes(size: int = 256) -> list[Scene]:
    """A target domain unlike pre-training: another rig geometry, a noisy, dim, blurred camera."""
    optics = Optics(full_well=2500.0, read_noise=2.5, ambient=0.15, albedo=0.5, camera_defocus_px=1.0)
    scenes = []
    for teeth in (25, 18):
        gear = GearSpec(teeth=teeth, module=2.0)
        rig = default_rig(size, size, working_radius=gear.pitch_radius, standoff=180.0, triangulation_deg=28.0,
                          field_mm=4 * 2 * math.pi * gear.pitch_radius / teeth)
        scenes.append(Scene(f"target z={teeth}", rig, optics, gear, 48.0))
    return scenes


def part_transfer(opt: EvalOptions, work: Path) -> dict:
    """Fine-tune vs train from Kaiming init on the target domain; phase RMSE per target gear."""
    from gearscan.inference.experiments import render_target_datasets, target_split, transfer

    b = opt.budget
    scenes = target_scenes(b["size"])
    roots = render_target_datasets(work / "target", [(s.rig, s.optics, s.gear, s.period_px) for s in scenes],
                                   points=2, seed=opt.seed, poses=b["poses"])
    train_set, val_set = target_split(roots, b["crop"])  # start point 0 trains, 1 validates
    runs = transfer(train_set, val_set, pretrained=opt.model, budget=opt.training_budget(), work=work)
    motions = {"non-uniform 0.1/1.6": (0.1, 1.6), "uniform 0.6/0.6": (0.6, 0.6)}
    cases = {sc.name: render_cases(sc, motions, opt.per_motion, seed=opt.seed + 7) for sc in scenes}
    results = {label: {gear: {s.motion: s.rmse_rad for s in score({label: network_method(run.predictor)}, c)}
                       for gear, c in cases.items()}
               for label, run in runs.items()}
    curves = {label: run.curve for label, run in runs.items()}
    fig = figures.validation_curves(opt.out, "fig11_transfer.png", curves, xlabel="fine-tuning epoch",
                                    title="fine-tuning on the target domain (validation crops)")
    return {"per_gear_rmse": results, "curves": curves, "budget": b, "figures": [fig]}


def peer_runs(peers: Path | None) -> dict[str, Path]:
    """The peer networks' run folders under ``--peers`` (``NAME/``, as ``gearscan train --out``)."""
    return {name: Path(peers) / name for name in PEER_NAMES} if peers else {}


def part_networks(opt: EvalOptions, methods: dict, cases: list[BurstCase]) -> dict:
    sel = [c for c in cases if c.motion in PAPER_MOTIONS]
    scores = score(methods, sel)
    figs = [figures.error_maps(opt.out, "fig13_14_networks.png", methods, sel, scores)]
    curves = {}
    for name, run in peer_runs(opt.peers).items():
        f = run / "metrics.json"
        if f.exists():  # labelled as the table labels the peer's network
            curves[PEER_LABELS.get(name, name)] = json.loads(f.read_text())
    if curves:
        figs.insert(0, figures.loss_curves(opt.out, "fig12_loss_curves.png", curves))
    return {"scores": [asdict(s) for s in scores], "table": scores_table(scores, baseline="three-step PS"),
            "figures": figs}


def part_loss_ablation(opt: EvalOptions, work: Path, cases: list[BurstCase]) -> dict:
    """Both losses trained from Kaiming init; phase RMSE per paper motion."""
    from gearscan.inference.experiments import ablation_split, loss_ablation
    from gearscan.inference.predictor import Predictor

    b = opt.budget
    train_set, val_set = ablation_split(opt.train_data, work, size=b["size"], poses=b["poses"], crop=b["crop"],
                                        seed=opt.seed + 3)
    runs = loss_ablation(train_set, val_set, model=Predictor.load(opt.model).model.config,
                         budget=opt.training_budget(), work=work)
    sel = [c for c in cases if c.motion in PAPER_MOTIONS]
    out = {label: {s.motion: s.rmse_rad for s in score({label: network_method(run.predictor)}, sel)}
           for label, run in runs.items()}
    curves = {label: run.curve for label, run in runs.items()}
    fig = figures.validation_curves(opt.out, "fig15_loss_ablation.png", curves, xlabel="epoch (from Kaiming init)",
                                    legend_fontsize=7)
    return {"rmse": out, "curves": curves, "budget": b, "figures": [fig]}


def part_uncertainty(opt: EvalOptions, predictor, cases: list[BurstCase]) -> dict:
    from gearscan.inference.uncertainty import plot_reliability, reliability

    sel = [c for c in cases if c.motion in PAPER_MOTIONS]
    errs, sig, maps = {m: [] for m in PAPER_MOTIONS}, {m: [] for m in PAPER_MOTIONS}, None
    for c in sel:
        res = predictor.predict(c.frames, opt.mc, full_scale=c.full_scale, angles=c.angles_rad)
        m = c.truth.mask
        e = phase_error(res.phase, c.truth.phase)
        errs[c.motion].append(e[m])
        sig[c.motion].append(res.sigma_total[m])
        if maps is None:
            maps = (c, res, e)
    per_motion = {}
    for motion in [*PAPER_MOTIONS, POOLED]:
        keys = list(PAPER_MOTIONS) if motion == POOLED else [motion]
        err = np.concatenate([x for k in keys for x in errs[k]])
        sigma = np.maximum(np.concatenate([x for k in keys for x in sig[k]]), 1e-6)
        rel = reliability(err, sigma)
        per_motion[motion] = {"bursts": sum(len(errs[k]) for k in keys), "rmse_rad": float(np.sqrt(np.mean(err**2))),
                              "mean_sigma_rad": float(sigma.mean()), "ece": rel.ece}
    name = f"CD-DCU-Net MC T={opt.mc}"
    plot_reliability(rel,  # the loop's last: the pooled one, as in the table's last row
                     opt.out / "fig18_reliability.png", title=f"{name}, {POOLED}: ECE {rel.ece:.3f}")
    # sparsification: RMSE of the remaining pixels as the most uncertain are removed, vs the oracle
    fractions = np.linspace(0, 0.9, 19)
    by_sigma, by_err = np.argsort(-sigma), np.argsort(-np.abs(err))
    n = err.size
    spars = [float(np.sqrt(np.mean(err[by_sigma[int(f * n):]] ** 2))) for f in fractions]
    oracle = [float(np.sqrt(np.mean(err[by_err[int(f * n):]] ** 2))) for f in fractions]
    figs = ["fig18_reliability.png",
            figures.sparsification(opt.out, "fig19_sparsification.png", fractions, spars, oracle, f"{name}, {POOLED}")]
    c, res, e = maps
    figs.insert(0, figures.uncertainty_maps(opt.out, "fig18_uncertainty_maps.png", c, res, e,
                                            f"{name}, one burst: {c.motion} ({c.scene.name})"))
    pooled = per_motion[POOLED]
    return {"ece": pooled["ece"], "mc": opt.mc, "sparsification": {"fraction": fractions.tolist(), "model": spars, "oracle": oracle},
            "mean_sigma_rad": pooled["mean_sigma_rad"], "rmse_rad": pooled["rmse_rad"], "per_motion": per_motion,
            "figures": figs}


def part_classical(opt: EvalOptions, methods: dict, cases: list[BurstCase]) -> dict:
    sel = [c for c in cases if c.motion in {**PAPER_MOTIONS, **STATIC}]
    scores = score(methods, sel, clouds=True)
    figs = [figures.error_maps(opt.out, "fig20_classical.png", methods, sel, scores)]
    return {"scores": [asdict(s) for s in scores], "table": scores_table(scores), "figures": figs}


def part_generalisation(opt: EvalOptions, methods: dict, cases: list[BurstCase]) -> dict:
    sel = [c for c in cases if c.motion in GENERALISATION]
    scores = score(methods, sel, clouds=True)
    spans = {k: v[0] + v[1] for k, v in GENERALISATION.items()}
    return {"scores": [asdict(s) for s in scores], "table": scores_table(scores), "spans_deg": spans,
            "figures": [figures.generalisation(opt.out, "fig22_generalisation.png", methods, scores, spans)]}


def run_evaluation(opt: EvalOptions, progress: Callable[[str], None] | None = None) -> dict:
    """Run all six parts; write OUT/report.md, OUT/results.json and the figures."""
    import torch

    from gearscan.inference.predictor import Predictor
    from gearscan.recon.compensation import aia_compensate, hilbert_compensate

    torch.set_num_threads(2)
    import shutil
    import tempfile

    opt.out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="gearscan-eval-"))  # datasets and checkpoints of parts 1, 3
    say = progress or (lambda s: None)
    t0 = time.perf_counter()
    # the paper compares networks: no still-burst gate, and MC mode's phase the mean of the passes, as in the paper
    # (the shipped model reports the deterministic pass's: benchmarks/mc_phase_rule.md)
    predictor = Predictor.load(opt.model, still_burst_rad=0.0, mc_phase="mean")
    scenes = [s for d in opt.data for s in scenes_from_dataset(d, limit=1 if opt.quick else None)]
    if not scenes:
        scenes = builtin_scenes(160 if opt.quick else 256)[: 1 if opt.quick else None]
    motions = {**STATIC, **PAPER_MOTIONS, **GENERALISATION}
    per = 1 if opt.quick else opt.per_motion
    mc = 4 if opt.quick else opt.mc
    say("rendering test bursts")
    cases = [c for i, s in enumerate(scenes) for c in render_cases(s, motions, per, seed=opt.seed + 100 + i)]
    net = network_method(predictor)
    mc_net = network_method(predictor, mc)

    def aia(frames, s, angles=None):
        return _compensated(aia_compensate, frames, s)

    def hilbert(frames, s, angles=None):
        return _compensated(hilbert_compensate, frames, s)

    options = {k: str(v) for k, v in asdict(opt).items()}
    if opt.quick:  # what the run used, where --quick overrides the option
        options.update(mc=f"{mc} (--quick; asked {opt.mc})", per_motion=f"{per} (--quick; asked {opt.per_motion})")
    results: dict[str, object] = {"options": options, "scenes": [s.name for s in scenes]}
    say("part 5: classical methods")
    results["classical"] = part_classical(opt, {"three-step PS": classical_method, "AIA (per region)": aia, "Hilbert": hilbert,
                                                "CD-DCU-Net": net, f"CD-DCU-Net MC T={mc}": mc_net}, cases)
    say("part 6: generalisation")
    results["generalisation"] = part_generalisation(opt, {"three-step PS": classical_method, "CD-DCU-Net": net}, cases)
    say("part 4: uncertainty")
    opt_mc = EvalOptions(**{**asdict(opt), "mc": mc})
    results["uncertainty"] = part_uncertainty(opt_mc, predictor, cases)
    say("part 2: networks")
    nets = {"three-step PS": classical_method, "CD-DCU-Net": net}
    for name, run in peer_runs(opt.peers).items():  # the peers' equal, smaller budget
        p = run / "best.safetensors"
        if p.exists():
            nets[PEER_LABELS.get(name, name)] = network_method(Predictor.load(p, still_burst_rad=0.0))
    results["networks"] = part_networks(opt, nets, cases)
    say("part 1: transfer learning")
    results["transfer"] = part_transfer(opt, work)
    say("part 3: loss ablation")
    results["loss_ablation"] = part_loss_ablation(opt, work, cases)
    shutil.rmtree(work, ignore_errors=True)
    results["summary"] = summarise(results)
    results["seconds"] = time.perf_counter() - t0
    (opt.out / "results.json").write_text(json.dumps(results, indent=2, default=str))
    (opt.out / "report.md").write_text(render_markdown(results))
    return results


def _compensated(fn, frames: np.ndarray, full_scale: float):
    from gearscan.core.types import PhaseResult

    phase, m, d = fn(frames, full_scale)
    z = np.zeros_like(phase, dtype=np.float32)
    return PhaseResult(phase.astype(np.float32), m, d, z, z, z, mode=fn.__name__)
