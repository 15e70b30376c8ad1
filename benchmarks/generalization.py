"""Generalization of the shipped network on the TEST split: families a user would bring, stratified.

    .venv/bin/python benchmarks/generalization.py [--scenes 16] [--mc-scenes 2] [--quick]

Scenes come from :mod:`gearscan.twin.families` (fixed test seeds, rendered on the fly: nothing on
disk); per scene the paper's three motions both ways, two random spans in (0, 2] deg (random
sense and split) and two still bursts. Scored with :mod:`gearscan.generalization` against the
twin's analytic phase at the first frame: per family and motion group RMSE of the network
(deterministic; MC T=20 on the first ``--mc-scenes`` scenes of each family, ``--mc-motions all``: on every burst) and of three-step PS,
their ratio, ECE and coverage, and the error by stratum of camera fringe period, modulation,
distance to the mask edge, burst span, image motion (px) and fringe phase change (periods). Writes benchmarks/generalization_report.{md,json,png}
(``--quick``: a tiny run into the temp folder).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from gearscan.core.phase import phase_error, still_three_step_result
from gearscan.core.rig import fringe_orientation
from gearscan.evaluate import classical_method, network_method
from gearscan.generalization import (
    ALL,
    AXES,
    BASELINE,
    GROUPS,
    MOVING,
    MOVING_ONLY,
    NETWORK,
    STILL,
    TIE_MARGIN,
    GeneralizationScorer,
    cells_table,
    loses,
    plot_strata,
    render_family_cases,
    rig_orientation,
    run_methods,
    scene_motions,
    strata_tables,
    vote_mirrored,
    weak_strata_table,
)
from gearscan.inference.predictor import THREE_STEP_NOISE, Predictor, model_path
from gearscan.inference.uncertainty import reliability
from gearscan.provenance import code_edits
from gearscan.recon.measure import MAX_SIGMA_RAD, network_support_option
from gearscan.twin.families import FAMILIES, family_scenes
from gearscan.twin.splits import SHIPPED, SHIPPED_DEFAULT_RIG, SHIPPED_V5, SHIPPED_V6, describe

HERE = Path(__file__).parent
REPO = HERE.parent


PROBE_RAD = 0.1  # the still gate shown next to the shipped setting (scripts/choose_still_gate.py)


def shipped_saw(model: str | None) -> str:
    """What the benchmarked model was trained and validated on, when the project knows it."""
    path = model_path(model).resolve()
    if path == model_path(None).resolve():
        return SHIPPED.summary()
    if path.name == "v5.safetensors":
        return SHIPPED_V5.summary()
    if path.name == "v6.safetensors":
        return SHIPPED_V6.summary()
    if path.name == "default_rig.safetensors":
        return SHIPPED_DEFAULT_RIG.summary()
    return f"{path} (not a shipped model: its training data is its own record)"


RIG_NAME = f"{NETWORK}, rig orientation from a still burst"


def gate_name(rad: float) -> str:
    return f"{NETWORK} with a {rad:g} rad still gate" if rad > 0 else f"{NETWORK} without still gate"


NO_BURST_GATE = f"{NETWORK}, rig orientation, no still-burst gate"


def orientation_misreads(scenes: list[dict]) -> str:
    """Per family: bursts whose own vote disagrees with the scene's orientation, of all bursts."""
    out = []
    for fam in dict.fromkeys(s["family"] for s in scenes):
        rows = [s for s in scenes if s["family"] == fam]
        bad = sum(v != (s["rig_orientation"] == "mirrored") for s in rows for v in s["burst_votes_mirrored"])
        out.append(f"{fam} {bad} of {sum(len(s['burst_votes_mirrored']) for s in rows)}")
    return ", ".join(out)


def mc_rig_name(mc_name: str) -> str:
    """The MC method decoded with the rig's orientation."""
    return f"{mc_name}, rig orientation"


def calibration_agreement(scenes: list[dict]) -> str:
    """How many scenes' rig calibrations give the orientation their first still burst's vote gives
    (:func:`gearscan.core.rig.fringe_orientation`: what ``live``, ``replay``, ``inspect`` and ``predict --rig`` use)."""
    rows = [s for s in scenes if "calibration_orientation" in s]
    same = sum(s["calibration_orientation"] == s["rig_orientation"] for s in rows)
    odd = [f"{s['name']} ({s['calibration_orientation']} vs {s['rig_orientation']})" for s in rows
           if s["calibration_orientation"] != s["rig_orientation"]]
    return f"{same} of {len(rows)} scenes" + (f"; disagree: {', '.join(odd)}" if odd else "")


def rig_weak_strata(strata) -> str:
    """One line per motion kind: strata (any family, axis, bin) where each network decode is worse than three-step PS."""
    out = []
    for kind in (MOVING, STILL):
        rows = [s for s in strata if s.kind == kind and s.pixels > 0]
        vote = sum(loses(s.rmse[NETWORK], s.rmse[BASELINE]) for s in rows)
        rig = [s for s in rows if loses(s.rmse[RIG_NAME], s.rmse[BASELINE])]
        ties = sum(not loses(s.rmse[RIG_NAME], s.rmse[BASELINE]) and not loses(s.rmse[BASELINE], s.rmse[RIG_NAME])
                   for s in rows)
        worst = max(rig, key=lambda s: s.rmse[RIG_NAME] / s.rmse[BASELINE], default=None)
        tail = "" if worst is None else (f"; the worst: {worst.family}, {worst.axis} {worst.label}, "
                                         f"{worst.rmse[RIG_NAME] / worst.rmse[BASELINE]:.2f}x")
        out.append(f"- {kind} bursts: of {len(rows)} strata, the network is worse than three-step PS in {vote} with "
                   f"the per-burst vote and in {len(rig)} with the rig orientation (tied within {TIE_MARGIN:.1%} with it: "
                   f"{ties}){tail}.")
    return "\n".join(out)


def gate_table(cells, other: str, shipped: str = NETWORK, names: tuple[str, str] = ("shipped", "other")) -> str:
    """Markdown: the ``shipped`` network next to ``other``, moving and still bursts per family."""
    a, o = names
    head = f"{NETWORK} as shipped (rad)" if shipped == NETWORK else f"{shipped}, {a} (rad)"
    lines = [f"| family | motions | {head} | {other} | {BASELINE} | {a} / three-step | "
             f"{o} / three-step | ECE {a} / {o} |", "|---|---|---|---|---|---|---|---|"]
    for c in cells:
        if c.group not in ("moving", "still"):
            continue
        g, u, b = c.rmse[shipped], c.rmse[other], c.rmse[BASELINE]
        lines.append(f"| {c.family} | {c.group} | {g:.4f} | {u:.4f} | {b:.4f} | {g / b:.2f}x | {u / b:.2f}x | "
                     f"{c.ece.get(shipped, float('nan')):.3f} / {c.ece.get(other, float('nan')):.3f} |")
    return "\n".join(lines)


def gate_section(predictor: Predictor, cells) -> list[str]:
    """Markdown lines: the rig-orientation network with and without its still-burst gate."""
    entry = predictor.meta.get("still_burst_gate") or {}
    rule = str(entry.get("rule", "benchmarks/still_burst_gate_rule.md")).split(":")[0]
    motion = ("" if predictor.still_burst_motion == math.inf else
              f" and its frames show motion on fewer than {predictor.still_burst_motion:g} of the lit pixels "
              "(`inference.predictor.frame_motion_share`: the three-step amplitude above the frames' mean)")
    sigma = ("three-step's noise propagation of the frames' measured noise" if predictor.still_burst_sigma == THREE_STEP_NOISE
             else "the gate's fitted map" if predictor.still_burst_sigma is not None else "the model's map at departure 0")
    limit = "" if predictor.still_burst_motion == math.inf else f", motion share {predictor.still_burst_motion:g}"
    return [
        f"## The still-burst gate (shipped: {predictor.still_burst_rad:g} rad{limit}, chosen on val by "
        f"`scripts/choose_still_burst_gate.py`, rule `{rule}`), test split",
        "",
        "A burst whose network phase departs from three-step PS's by a median below the gate over its interior"
        f"{motion} (`inference.predictor.still_burst_gate`) is decoded by three-step PS, with {sigma} as its sigma. "
        "The same bursts, the rig's orientation set, with and without it (RMSE ratios to three-step PS: < 1 is "
        "better than three-step):",
        "",
        gate_table(cells, NO_BURST_GATE, RIG_NAME, ("gated", "not gated")),
    ]


def host() -> dict[str, object]:
    """CPU model, the bf16/AMX flags that decide the precision, cores and load."""
    cpu, flags = platform.processor() or "unknown", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and cpu in ("unknown", "x86_64", ""):
                cpu = line.split(":", 1)[1].strip()
            elif line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "avx512f": "avx512f" in flags,
            "avx512_bf16": "avx512_bf16" in flags, "amx_bf16": "amx_bf16" in flags,
            "loadavg_start": os.getloadavg()}


def git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True).stdout.strip()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=16, help="scenes per family")
    ap.add_argument("--mc-scenes", type=int, default=2, help="scenes per family also decoded with MC dropout")
    ap.add_argument("--mc", type=int, default=20)
    ap.add_argument("--mc-motions", choices=("paper", "all"), default="paper",
                    help="MC on the paper's motions forwards and still bursts (paper) or on every burst (all)")
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--model", default=None, help="default: the shipped model")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="1 scene per family, paper motions off: a smoke run")
    ap.add_argument("--out", type=Path, default=None, help="path prefix of the report files")
    args = ap.parse_args()
    if args.quick:
        args.scenes, args.mc_scenes = 1, min(args.mc_scenes, 1)
    out = args.out or (Path(tempfile.gettempdir()) / "generalization_quick_report" if args.quick
                       else HERE / "generalization_report")
    families = [f.strip() for f in args.families.split(",") if f.strip()]
    bad = [f for f in families if f not in FAMILIES]
    if bad:
        ap.error(f"--families: unknown {bad}; expected some of {', '.join(FAMILIES)}")
    torch.set_num_threads(args.threads)
    machine = host()
    t_start = time.perf_counter()
    predictor = Predictor.load(args.model)
    # the rig's orientation set once, as a user would from a still burst of the scene (Predictor orientation)
    rig = Predictor.load(args.model, orientation="normal")
    if predictor.still_burst_rad > 0:  # the probe: the same rig-orientation network without its still-burst gate
        other, other_name = Predictor.load(args.model, orientation="normal", still_burst_rad=0.0), NO_BURST_GATE
    else:
        other = Predictor.load(args.model, still_gate_rad=0.0 if predictor.still_gate_rad > 0 else PROBE_RAD)
        other_name = gate_name(other.still_gate_rad)
    methods = {BASELINE: classical_method, NETWORK: network_method(predictor), other_name: network_method(other),
               RIG_NAME: network_method(rig)}
    mc_name = f"{NETWORK} MC T={args.mc}"
    own = predictor.network_support  # every network method here is this model: its own per-burst keep test
    det = GeneralizationScorer([BASELINE, NETWORK, other_name, RIG_NAME],
                               supports={NETWORK: own, other_name: own, RIG_NAME: own})
    mc_rig = mc_rig_name(mc_name)
    mc = GeneralizationScorer([BASELINE, NETWORK, RIG_NAME, mc_name, mc_rig],
                              supports={NETWORK: own, RIG_NAME: own, mc_name: own, mc_rig: own})
    mc_groups = ("paper", "still") if args.mc_motions == "paper" else GROUPS
    scenes_json, timing = [], {"render_s": 0.0, "decode_s": 0.0, "mc_s": 0.0, "bursts": 0, "mc_bursts": 0}
    still_sigma: dict[str, dict[str, list[np.ndarray]]] = {}
    for fam in families:
        for k, scene in enumerate(family_scenes(fam, args.scenes)):
            rng = np.random.default_rng([scene.seed, 1])
            motions = scene_motions(rng, sweeps=1 if args.quick else 2, stills=1 if args.quick else 2,
                                    paper=not args.quick)
            t0 = time.perf_counter()
            cases = render_family_cases(scene, motions)
            timing["render_s"] += time.perf_counter() - t0
            rig.orientation = rig_orientation(motions, cases)
            if other_name == NO_BURST_GATE:
                other.orientation = rig.orientation
            votes = [vote_mirrored(c) for c in cases]
            for j, (motion, case) in enumerate(zip(motions, cases, strict=True)):
                t0 = time.perf_counter()
                res = run_methods(case, methods)
                timing["decode_s"] += time.perf_counter() - t0
                det.add(fam, motion, case, res)
                timing["bursts"] += 1
                if motion.kind == STILL:
                    add_still_sigma(still_sigma, fam, case, res[BASELINE])
                if k < args.mc_scenes and motion.group in mc_groups:
                    t0 = time.perf_counter()
                    # the dropout draws of a rerun are this run's, and each burst of a scene draws its own masks
                    torch.manual_seed(1000 * scene.seed + j)
                    res[mc_name] = predictor.predict(case.frames, args.mc, full_scale=case.full_scale,
                                                     angles=case.angles_rad)
                    torch.manual_seed(1000 * scene.seed + j)  # the same draws with the rig's orientation
                    res[mc_rig] = rig.predict(case.frames, args.mc, full_scale=case.full_scale, angles=case.angles_rad)
                    timing["mc_s"] += time.perf_counter() - t0
                    timing["mc_bursts"] += 1
                    mc.add(fam, motion, case, res)
            scenes_json.append({"name": scene.name, "family": fam, "seed": scene.seed, "period_px": scene.period_px,
                                "params": dict(scene.params), "motions": [asdict(m) for m in motions],
                                "start_deg": [c.angles_deg[0] for c in cases], "rig_orientation": rig.orientation,
                                "burst_votes_mirrored": votes,
                                "calibration_orientation": fringe_orientation(scene.rig).orientation})
            print(f"{scene.name}: {len(cases)} bursts, {time.perf_counter() - t_start:.0f} s", flush=True)
    machine["loadavg_end"] = os.getloadavg()
    total_s = time.perf_counter() - t_start
    write_report(out, args, machine, predictor, det, mc, mc_name, scenes_json, timing, total_s, families, still_sigma)


def add_still_sigma(acc: dict, family: str, case, assumed) -> None:
    """Accumulate a still burst's three-step errors over the truth mask with its sigma for an assumed 1 DN of noise
    (``assumed``, what :func:`classical_method` gives) and for the noise measured on the burst (the pipeline's
    still route, :func:`~gearscan.core.phase.still_three_step_result`)."""
    m = case.truth.mask
    measured = still_three_step_result(case.frames, case.full_scale)
    for fam in (family, ALL):
        a = acc.setdefault(fam, {"error": [], "assumed": [], "measured": [], "route": []})
        a["error"].append(phase_error(assumed.phase, case.truth.phase)[m].astype(np.float32))
        a["route"].append(phase_error(measured.phase, case.truth.phase)[m].astype(np.float32))
        a["assumed"].append(assumed.sigma_total[m])
        a["measured"].append(measured.sigma_total[m])


def still_sigma_section(acc: dict, order: list[str]) -> list[str]:
    """Markdown lines: ECE of three-step PS's noise sigma on the still bursts, assumed vs measured noise."""
    lines = ["## Three-step PS's sigma on still bursts: 1 DN assumed or the noise measured on the burst, test split", "",
             "The pipeline decodes a burst the encoder saw standing still by three-step PS (`live`, `replay`, `predict` "
             "with angles). Its sigma is the noise propagation `sqrt(2/3) s_n / B`; since session 30 `s_n` is measured "
             "on the burst's own frame sum (`gearscan.core.phase.still_frame_noise`) instead of assumed to be 1 DN. "
             "The same still bursts as above (three-step's phase; RMSE and ECE over the truth mask). Since session 31 the "
             "still route also removes three-step's non-sinusoidal-fringe error (`gearscan.core.phase.still_phase`, "
             "adopted on val: `benchmarks/still_harmonic_rule.md`); its phase with the measured-noise sigma in the last "
             "columns:", "",
             "| family | bursts' pixels | three-step RMSE (rad) | ECE, 1 DN assumed | ECE, noise measured | "
             "still route RMSE (rad) | still route / three-step | still route ECE |",
             "|---|---|---|---|---|---|---|---|"]
    for fam in (f for f in order if f in acc):
        a = acc[fam]
        err = np.concatenate(a["error"])
        ece = {k: reliability(err, np.maximum(np.concatenate(a[k]), 1e-6)).ece for k in ("assumed", "measured")}
        route = np.concatenate(a["route"])
        r3, rr = (float(np.sqrt(np.mean(v.astype(np.float64) ** 2))) for v in (err, route))
        ece_route = reliability(route, np.maximum(np.concatenate(a["measured"]), 1e-6)).ece
        lines.append(f"| {fam} | {err.size} | {r3:.4f} | {ece['assumed']:.3f} | {ece['measured']:.3f} | {rr:.4f} | "
                     f"{rr / r3:.3f}x | {ece_route:.3f} |")
    return [*lines, ""]


def write_report(out: Path, args, machine: dict, predictor: Predictor, det: GeneralizationScorer,
                 mc: GeneralizationScorer, mc_name: str, scenes_json: list, timing: dict, total_s: float,
                 families: list[str], still_sigma: dict | None = None) -> None:
    support_px = network_support_option(None, model=predictor.network_support)  # the coverage's keep test
    cells, strata = det.cells(), det.strata()
    mc_cells = mc.cells()
    fams = [*families, ALL]
    weights = model_path(args.model)
    commit, dirty = git("rev-parse", "--short", "HEAD"), bool(code_edits(REPO))
    counts_ok = all(
        sum(s.pixels for s in strata if s.family == f and s.kind == kind and s.axis == a.name)
        == det.pooled_pixels(f, kind)
        for f in fams for kind in (MOVING, STILL) for a in AXES if not (kind == STILL and a.name in MOVING_ONLY)
    )
    report = {
        "split": "test", "split_definition": describe("test"), "shipped_model_saw": shipped_saw(args.model),
        "commit": commit, "working_tree_dirty": dirty, "host": machine, "precision": predictor.precision,
        "torch_threads": args.threads, "model": str(weights), "args": {k: str(v) for k, v in vars(args).items()},
        "timing": timing | {"total_s": total_s}, "strata_partition_checked": counts_ok,
        "cells": [asdict(c) for c in cells], "strata": [asdict(s) | {"worse": s.worse} for s in strata],
        "mc_cells": [asdict(c) for c in mc_cells], "scenes": scenes_json,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(report, indent=1, default=str))
    png = out.with_suffix(".png")
    plot_strata(strata, fams, png, "test split: RMSE by stratum, shipped network (solid) vs three-step PS (dashed)")
    mc_rows = mc_cells if args.mc_motions == "all" else [c for c in mc_cells if c.group in ("paper", "still")]
    h = machine
    lines = [
        "# Generalization on the test split: families a user would bring, stratified",
        "",
        f"`python benchmarks/generalization.py --scenes {args.scenes} --mc-scenes {args.mc_scenes} --mc {args.mc}"
        f"{' --mc-motions all' if args.mc_motions == 'all' else ''}"
        f"{' --quick' if args.quick else ''}{f' --model {args.model}' if args.model else ''}"
        f"{f' --out {args.out}' if args.out else ''}`; commit `{commit}`{' (working tree had uncommitted edits)' if dirty else ''}; "
        f"{total_s / 60:.1f} min.",
        "",
        f"- **Host**: {h['cpu']}, {h['cores']} cores, AVX-512 {'yes' if h['avx512f'] else 'no'}, "
        f"AVX512-BF16 {'yes' if h['avx512_bf16'] else 'no'}, AMX-BF16 {'yes' if h['amx_bf16'] else 'no'}; "
        f"load average {h['loadavg_start'][0]:.2f} at start, {h['loadavg_end'][0]:.2f} at the end; "
        f"{args.threads} torch threads.",
        f"- **Model**: `{weights.relative_to(REPO) if weights.is_relative_to(REPO) else weights}` "
        f"(the shipped one unless named), precision **{predictor.precision}** (Predictor's automatic choice: bf16 "
        f"on CPUs with native bf16), still gate {predictor.still_gate_rad:g} rad per pixel and {predictor.still_burst_rad:g} "
        "rad per burst (from the model's JSON, chosen on val; 0: none); MC mode's phase: "
        f"{'the deterministic pass' if predictor.mc_phase == 'deterministic' else 'the mean of the passes'} "
        "(`mc_phase`, from the model's JSON).",
        f"- **Split**: every number below is from the **test** split ({describe('test')}), rendered on the fly "
        "from fixed seeds; nothing here chose anything. Families: `twin/families.py`; splits: `twin/splits.py`.",
        f"- **What the model saw**: {shipped_saw(args.model)}. So every test gear and seed is unseen"
        + ("; the test split's `default` rig is the one exception by rig: v5 was validated on it (data/val_default, "
           "gear 25) and its still threshold was chosen there." if shipped_saw(args.model) == SHIPPED_V5.summary()
           else "."),
        f"- **Bursts**: {timing['bursts']} ({len(scenes_json)} scenes: per scene the paper's motions uniform "
        "0.6/0.6, non-uniform 0.1/1.6 and 0.5/1.0 deg, each also turning backwards; 2 random spans 0-2 deg, "
        f"random sense; 2 still bursts); MC T={args.mc} on {timing['mc_bursts']} of them (dropout draws seeded per burst "
        f"from the scene's seed, so a rerun on the same precision path repeats them). Render "
        f"{timing['render_s']:.0f} s, deterministic decode (both methods) {timing['decode_s']:.0f} s, MC "
        f"{timing['mc_s']:.0f} s.",
        "- RMSE over the truth's valid pixels (analytic wrapped phase at the first frame's pose); gain = "
        "three-step RMSE / network RMSE (< 1: the network is worse); ECE: 30 bins, eps 0.03 rad "
        "(`inference.uncertainty.reliability`); coverage: share of the truth mask passing the reconstructor's "
        f"keep test (modulation >= 0.05, sigma <= {MAX_SIGMA_RAD} rad; a network's pixel also needs fringes in its frames within "
        f"E px: {'no such test' if support_px is None else f'E = {support_px}'}, the model's own per-burst setting or else the product's, `recon.measure.network_support_option`); RMSE of the kept pixels: over the truth-mask pixels "
        "that each method's own keep test passes (what reaches the cloud; three-step PS's sigma is its noise "
        "propagation, blind to motion).",
        "",
        "## Per family (deterministic network, test split)",
        "",
        cells_table(cells),
        "",
        *(gate_section(predictor, cells) if predictor.still_burst_rad > 0 else [
            f"## The still gate (shipped: {predictor.still_gate_rad:g} rad, chosen on val by `scripts/choose_still_gate.py`), test split",
            "",
            "A gate replaces, per pixel, the network's phase by three-step PS's where the two differ by less than "
            "the gate (`inference.predictor.still_gate`). Same bursts with the shipped setting and the other one "
            "(RMSE ratios to three-step PS: < 1 is better than three-step):",
            "",
            gate_table(cells, gate_name(PROBE_RAD if predictor.still_gate_rad == 0 else 0.0)),
        ]),
        "",
        *(still_sigma_section(still_sigma, fams) if still_sigma else []),
        "## The fringe orientation: voted per burst (shipped default) or set once per rig, test split",
        "",
        "The Predictor mirrors a burst whose fringe phase falls along the camera's columns. Voted per burst "
        "(`orientation=\"auto\"`, the default) the vote misreads fast bursts on large gears; set once per rig "
        "(`orientation=\"normal\"`/`\"mirrored\"`, here from the vote on the scene's first still burst, as a "
        "user would at set-up) it cannot. "
        f"Bursts whose vote disagrees with their scene's still-burst orientation: {orientation_misreads(scenes_json)}. "
        "The rig's calibration gives the orientation without any burst (`gearscan.core.rig.fringe_orientation`; "
        "`live`, `replay` and `inspect` adopt it, `predict --rig` too); it equals the still-burst vote's in "
        f"{calibration_agreement(scenes_json)}.",
        "",
        gate_table(cells, RIG_NAME),
        "",
        rig_weak_strata(strata),
        "",
        f"## MC dropout T={args.mc} (first {args.mc_scenes} scenes of each family: "
        f"{'every burst' if args.mc_motions == 'all' else 'paper motions forwards and still'}, test split)",
        "",
        "Deterministic and MC on the same bursts:",
        "",
        cells_table(mc_rows).replace(f"{NETWORK} RMSE", "det RMSE"),
        "",
        "MC as shipped (`predict` without `--rig`: the per-burst orientation vote) and with the rig's orientation "
        "(the scene's still-burst orientation, as in the tables above; it equals the rig calibration's, what `live`, "
        "`replay` and `inspect` use, in every scene where the section above says so; the same dropout draws):",
        "",
        "| family | motions | MC RMSE (rad) | gain | ECE MC | MC RMSE, rig orientation (rad) | gain | ECE MC, rig orientation "
        "| ECE det, rig orientation (same bursts) |",
        "|---|---|---|---|---|---|---|---|---|",
        *[f"| {c.family} | {c.group} | {c.rmse[mc_name]:.4f} | {c.gain(mc_name):.2f}x | {c.ece.get(mc_name, float('nan')):.3f} "
          f"| {c.rmse[mc_rig_name(mc_name)]:.4f} | {c.gain(mc_rig_name(mc_name)):.2f}x "
          f"| {c.ece.get(mc_rig_name(mc_name), float('nan')):.3f} | {c.ece.get(RIG_NAME, float('nan')):.3f} |"
          for c in mc_rows],
        "",
        "## Weak strata: every stratum where the network is worse than three-step PS (test split)",
        "",
        weak_strata_table(strata),
        "",
        "## Strata (test split)",
        "",
        "Cells: network RMSE / three-step RMSE = gain (pixels). Bins are right-closed; each axis partitions the "
        f"pixels of its family and motion kind (checked: {'yes' if counts_ok else 'NO'}). The camera fringe "
        "period is 2 pi / |grad phi| of the truth's absolute phase; the edge distance is the Euclidean distance "
        "to the nearest pixel outside the truth mask; the image motion is how far the surface point seen at frame 1 "
        "moves in the camera by frame 3; the fringe phase change is |phi_3 - phi_1| / 2 pi of the truth at each pixel "
        "(what three-step PS suffers; NaN: the pixel does not see the lit surface in frame 3). Figure: "
        f"`{png.name}`.",
        "",
        strata_tables(strata, fams),
        "",
        "## Scenes",
        "",
        "| scene | projector period (px) | parameters |",
        "|---|---|---|",
        *[f"| {s['name']} | {s['period_px']:.1f} | {', '.join(f'{k} {v}' for k, v in s['params'].items())} |"
          for s in scenes_json],
    ]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines[:40]))
    print(f"wrote {out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
