"""The twin as a run-time prior (issue 13, item 6), measured on the test split.

Per burst, four decodes of the same frames against the twin's analytic phase at the first frame:
three-step PS; the shipped network (with the burst's angles); the twin prior alone (the three
frames solved with the CAD-predicted per-pixel shifts and shading, :mod:`gearscan.twin.prior`);
and the blend (the prior where its model holds, the network elsewhere). Errors are split by
where the prior is usable, so what physics fixes and what it cannot are both visible.

Second part: gears that deviate from their CAD (oversize, eccentric mounting, a chipped tooth) on
the default rig. The prior comes from the nominal CAD, the truth from the as-built gear: the
prior must not pull the measurement toward the CAD, so the deviation vs CAD of the blend's cloud
is compared with the true one.

    python benchmarks/twin_prior.py [--scenes 3] [--families default,side]

With ``--prior-model`` (a ``prior_input`` network, fed the prior's phase changes and shading
ratios as input channels) and ``--control`` (the same fine-tuning without them), both are decoded
too and the report goes to ``prior_input_report.md`` instead.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import time
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from gearscan.core.gear import GearSpec
from gearscan.core.phase import classical_result, phase_error
from gearscan.core.rig import default_rig
from gearscan.core.types import Burst, Frame
from gearscan.evaluate import Scene, render_cases
from gearscan.generalization import PAPER, PAPER_REVERSED, rig_orientation, scene_motions
from gearscan.inference.models import prior_channels
from gearscan.inference.predictor import Predictor
from gearscan.provenance import code_edits
from gearscan.recon.deviation import CadScorer
from gearscan.recon.measure import Reconstructor
from gearscan.recon.triangulate import to_turntable
from gearscan.twin.defects import Chip, GearDefects
from gearscan.twin.families import FAMILIES, draw_gear, family_scenes, family_seed
from gearscan.twin.prior import TwinPrior, blend
from gearscan.twin.render import Optics, TwinRenderer

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
METHODS = ("three-step PS", "CD-DCU-Net", "twin prior", "prior + net")
MAX_GAIN = 2.0
CONTROL_NET = "control net"
PRIOR_NET = "net + prior input"


def host() -> str:
    cpu, flags = "unknown", set()
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name") and cpu == "unknown":
            cpu = line.split(":", 1)[1].strip()
        elif line.startswith("flags"):
            flags = set(line.split(":", 1)[1].split())
    isa = ", ".join(f for f in ("avx512f", "avx512_bf16", "amx_bf16") if f in flags) or "no AVX-512"
    return f"{cpu}, {os.cpu_count()} cores ({isa}), load {os.getloadavg()[0]:.2f} at start"


def burst_of(case) -> Burst:
    return Burst(tuple(Frame(f, i, 0, i) for i, f in enumerate(case.frames)), tuple(case.angles_rad))


def decode_all(case, prior: TwinPrior, net: Predictor, extra: dict[str, Predictor] | None = None):
    """Every method's PhaseResult for one burst, and where the prior is usable. ``extra``: more
    networks by name; a ``prior_input`` one is fed the prior's channels of the burst."""
    three = classical_result(burst_of(case))
    maps = prior.maps(case.angles_rad)
    needed = any(p.needs_prior for p in (net, *(extra or {}).values()))
    channels = prior_channels(maps.phase_change(), maps.ratio[1:], maps.clean) if needed else None

    def run(p: Predictor):
        res = p.predict(case.frames, full_scale=case.full_scale, angles=case.angles_rad,
                        prior=channels if p.needs_prior else None)
        return replace(res, angle=float(case.angles_rad[0]))

    network = run(net)
    alone, usable = prior.decode(case.frames, case.full_scale, case.angles_rad, max_gain=MAX_GAIN, maps=maps)
    out = {METHODS[0]: three, METHODS[1]: network, METHODS[2]: alone, METHODS[3]: blend(alone, usable, network)}
    return out | {name: run(p) for name, p in (extra or {}).items()}, usable


class Sums:
    """Squared-error sums per key (family, kind, method, pixel set)."""

    def __init__(self) -> None:
        self.sse: dict[tuple, float] = defaultdict(float)
        self.n: dict[tuple, int] = defaultdict(int)

    def add(self, key: tuple, err: np.ndarray) -> None:
        self.sse[key] += float(np.sum(np.asarray(err, np.float64) ** 2))
        self.n[key] += int(err.size)

    def rmse(self, key: tuple) -> float:
        return math.sqrt(self.sse[key] / self.n[key]) if self.n[key] else float("nan")


def families_part(args, net: Predictor, sums: Sums, timing: dict, extra: dict[str, Predictor]) -> list[dict]:
    scenes = []
    for fam in args.families:
        for scene in family_scenes(fam, args.scenes):
            prior = TwinPrior(scene.rig, scene.gear, scene.period_px)
            motions = scene_motions(np.random.default_rng([scene.seed, 1]), sweeps=0, stills=2)
            sc = Scene(scene.name, scene.rig, scene.optics, scene.gear, scene.period_px, _renderer=scene.renderer)
            cases = render_cases(sc, {m.name: m.steps_deg for m in motions}, 1, seed=scene.seed)
            if args.orientation == "rig":  # set once per rig, as a user does, from the scene's first still burst
                net.orientation = rig_orientation(motions, cases)
                for p in extra.values():
                    p.orientation = net.orientation
            for motion, case in zip(motions, cases, strict=True):
                t0 = time.perf_counter()
                results, usable = decode_all(case, prior, net, extra)
                timing["decode_s"] += time.perf_counter() - t0
                timing["bursts"] += 1
                m = case.truth.mask
                for name, res in results.items():
                    err = phase_error(res.phase, case.truth.phase)
                    for fam_key in (fam, "all", *(() if fam == "default" else ("unseen",))):
                        base = (fam_key, motion.kind, name)
                        sums.add(base + ("all",), err[m])
                        sums.add(base + ("usable",), err[m & usable])
                        sums.add(base + ("not usable",), err[m & ~usable])
            scenes.append({"name": scene.name, "family": fam, "seed": scene.seed, "params": dict(scene.params)})
            print(f"{scene.name}: {len(cases)} bursts", flush=True)
    return scenes


DEVIATIONS = {
    "oversize: module 2.03 vs CAD 2.0": GearDefects(module=2.03),
    "eccentric mounting 50 um": GearDefects(eccentricity_um=50.0),
    "every tip chipped 0.3 mm": GearDefects(chips=tuple(Chip(tooth=t, size_mm=0.3) for t in range(35))),
}
DEV_GEAR = GearSpec(teeth=35, module=2.0)  # a test-split tooth count at the default rig's module


def deviation_part(args, net: Predictor, extra: dict[str, Predictor]) -> list[dict]:
    """Default rig, a test gear built off its CAD: phase errors vs the as-built truth, and how the
    deviation vs CAD that each decode's cloud reports follows the true deviation on the same pixels
    (slope 1: the deviation survives; 0: the measurement was pulled onto the CAD)."""
    rng = np.random.default_rng(family_seed("default", 900))
    gear = DEV_GEAR
    rig = default_rig(args.size, args.size, working_radius=gear.pitch_radius)
    prior = TwinPrior(rig, gear, 40.0)
    rc = Reconstructor.for_gear(rig, 40.0, gear)
    cad = CadScorer(gear)
    rows = []
    for label, defects in DEVIATIONS.items():
        renderer = TwinRenderer(rig, gear, Optics(), defects=defects)
        scene = Scene(label, rig, Optics(), gear, 40.0, _renderer=renderer)
        motions = {**PAPER, **PAPER_REVERSED, "still": (0.0, 0.0)}
        sums, pairs = Sums(), defaultdict(list)
        for case in render_cases(scene, motions, 1, seed=int(rng.integers(1 << 30))):
            kind = "still" if case.motion == "still" else "moving"
            results, usable = decode_all(case, prior, net, extra)
            m = case.truth.mask
            for name, res in results.items():
                err = phase_error(res.phase, case.truth.phase)
                sums.add((kind, name, "all"), err[m])
                sums.add((kind, name, "usable"), err[m & usable])
                meas = rc(burst_of(case), res)
                if meas.cloud is None or not len(meas.cloud):
                    continue
                r, c = meas.cloud.pixels.T
                on = m[r, c]
                true_pts = to_turntable(case.truth.points[r[on], c[on]].astype(np.float64), rig, case.angles_rad[0])
                pairs[(name, kind)].append(np.stack([cad.distances(true_pts), cad.distances(meas.cloud.points[on])]))
        row = {"deviation": label, "gear": f"z={gear.teeth} m={gear.module:g}", "rmse": {}, "dev": {}}
        for kind in ("moving", "still"):
            for name in (*METHODS, *extra):
                row["rmse"][f"{kind}/{name}"] = sums.rmse((kind, name, "all"))
                row["rmse"][f"{kind}/{name} usable"] = sums.rmse((kind, name, "usable"))
                if not pairs[(name, kind)]:
                    continue
                true, meas = np.concatenate(pairs[(name, kind)], axis=1)
                row["dev"][f"{kind}/{name}"] = {
                    "points": int(true.size),
                    "true_p95_mm": float(np.percentile(np.abs(true), 95)),
                    "measured_p95_mm": float(np.percentile(np.abs(meas), 95)),
                    "slope": float(np.cov(meas, true)[0, 1] / np.var(true, ddof=1)) if np.var(true) > 0 else float("nan"),
                    "rms_diff_mm": float(np.sqrt(np.mean((meas - true) ** 2))),
                    "true_median_mm": float(np.median(true)), "measured_median_mm": float(np.median(meas)),
                }
        rows.append(row)
        print(f"deviation: {label}", flush=True)
    return rows


def timing_prior(size: int) -> float:
    gear = draw_gear(np.random.default_rng(family_seed("default", 901)), module=2.0)
    rig = default_rig(size, size, working_radius=gear.pitch_radius)
    prior = TwinPrior(rig, gear, 40.0)
    prior.maps((0.0, 0.01, 0.02))
    t0 = time.perf_counter()
    for k in range(3):
        prior.maps((0.1 * k, 0.1 * k + 0.01, 0.1 * k + 0.02))
    return (time.perf_counter() - t0) / 3


def write_report(args, sums: Sums, scenes: list, dev_rows: list, timing: dict, total_s: float, machine: str,
                 extra: dict[str, str]) -> None:
    """``extra``: the further networks' names and weight files (``--prior-model``, ``--control``)."""
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    dirty = code_edits(REPO)
    fams = [*args.families, "all"]
    methods = (*METHODS, *extra)
    flags = "".join(f" --{'prior-model' if n == PRIOR_NET else 'control'} {f}" for n, f in extra.items())
    lines = [
        "# The twin's prediction as network input, test split (issue 13, item 6)" if extra
        else "# The twin as a run-time prior (issue 13, item 6)",
        "",
        f"`python benchmarks/twin_prior.py --scenes {args.scenes} --families {','.join(args.families)} "
        f"--orientation {args.orientation}{flags}`; commit "
        f"`{commit}`{' (working tree had uncommitted edits by others)' if dirty else ''}; {total_s / 60:.1f} min.",
        "",
        f"- **Host**: {machine}; 2 torch threads; network precision {timing['precision']}.",
        "- **Split**: test (`twin/families.py` scenes from fixed test seeds; nothing here chose anything: the "
        f"prior has one setting, `max_gain = {MAX_GAIN}`, fixed before this run).",
        f"- **Bursts**: {timing['bursts']} ({args.scenes} scenes per family; per scene the paper's three motions both "
        "ways and 2 still bursts). RMSE over the truth mask (analytic wrapped phase at the first frame's pose).",
        "- **Methods**: three-step PS; CD-DCU-Net (shipped, deterministic, with the burst angles; fringe orientation "
        + ("set once per scene from the vote on its first still burst, as a user sets it per rig" if args.orientation == "rig"
           else "voted per burst") + "); *twin prior*: "
        "the three frames solved per pixel with the shifts and shading changes that the CAD at the encoder angles "
        "predicts (`gearscan.twin.prior`); *prior + net*: the prior where it is usable (the CAD sees one smooth lit "
        f"surface in every frame's blur footprint and the solve's noise gain is <= {MAX_GAIN}), the network elsewhere.",
        f"- **Cost**: the prior's three ray casts take {timing['prior_s'] * 1e3:.0f} ms per burst at "
        f"{args.size}x{args.size} on this host (on top of the network's pass for the blend).",
        *([f"- **Further networks**: {', '.join(f'*{n}* `{f}`' for n, f in extra.items())}; *{PRIOR_NET}* is fed "
           "the prior's phase changes and shading ratios (`inference.models.prior_channels` of "
           "`TwinPrior.maps` at the burst's encoder angles) beside the frames; same orientation as the network."]
          if extra else []),
        "",
        *(_extra_table(sums, [*args.families, "unseen", "all"], extra) if extra else []),
        "## Test families: RMSE (rad) by where the prior is usable",
        "",
        "| family | motion | pixels usable | three-step | network | twin prior | prior + net "
        "| network on usable | prior on usable | network on not usable |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for fam in fams:
        for kind in ("moving", "still"):
            def r(name, part="all", fam=fam, kind=kind):
                return sums.rmse((fam, kind, name, part))
            n_all = sums.n[(fam, kind, METHODS[0], "all")]
            if not n_all:
                continue
            share = sums.n[(fam, kind, METHODS[0], "usable")] / n_all
            lines.append(
                f"| {fam} | {kind} | {100 * share:.0f} % | {r(METHODS[0]):.4f} | {r(METHODS[1]):.4f} | "
                f"{r(METHODS[2]):.4f} | {r(METHODS[3]):.4f} | {r(METHODS[1], 'usable'):.4f} | "
                f"{r(METHODS[2], 'usable'):.4f} | {r(METHODS[1], 'not usable'):.4f} |")
    lines += [
        "",
        "## Gears off their CAD (default rig, prior from the nominal CAD, truth from the as-built gear)",
        "",
        f"Gear {DEV_GEAR.teeth} teeth, module {DEV_GEAR.module:g} (CAD), default rig {args.size}x{args.size}, 40 px "
        "fringes. Phase RMSE (rad) over the truth mask; then, on the points each decode's cloud keeps, the deviation "
        "vs CAD it reports against the true surface's deviation on the same pixels: p95 of |deviation| (mm) and "
        "the slope of measured on true deviation (1: the deviation survives; 0: pulled onto the CAD). The twin "
        "prior alone keeps only its usable pixels (sigma is infinite elsewhere).",
        "",
        "| gear as built | motion | method | phase RMSE | points | dev p95 true | dev p95 measured | median true / measured "
        "| slope | RMS (measured - true) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in dev_rows:
        for kind in ("moving", "still"):
            for name in methods:
                d = row["dev"].get(f"{kind}/{name}")
                if d is None:
                    continue
                lines.append(
                    f"| {row['deviation']} | {kind} | {name} | {row['rmse'][f'{kind}/{name}']:.4f} | {d['points']} | "
                    f"{d['true_p95_mm']:.3f} | {d['measured_p95_mm']:.3f} | {d['true_median_mm']:+.3f} / "
                    f"{d['measured_median_mm']:+.3f} | {d['slope']:.2f} | {d['rms_diff_mm']:.3f} |")
    lines += ["", "## Reading", "", "(written by hand after the run; see the closing note of issue 13)", ""]
    stem = "prior_input_report" if extra else "twin_prior_report"
    (HERE / f"{stem}.md").write_text("\n".join(lines) + "\n")
    data = {"scenes": scenes, "deviation": dev_rows, "timing": timing, "host": machine, "commit": commit,
            "rmse": {"|".join(k): sums.rmse(k) for k in sums.n}}
    data["networks"] = {"CD-DCU-Net": "inference/weights/default.safetensors", **extra}
    (HERE / f"{stem}.json").write_text(json.dumps(data, indent=1))


def _extra_table(sums: Sums, fams: list[str], extra: dict[str, str]) -> list[str]:
    """RMSE of the further networks beside three-step PS and the shipped one, by where the prior holds."""
    names = [METHODS[0], METHODS[1], *extra]
    head = " | ".join(names)
    lines = [
        "## Networks with and without the twin's prediction as input: RMSE (rad)",
        "",
        "*unseen*: every family but the default rig, pooled by pixels. *usable*: where the prior alone is usable.",
        "",
        f"| family | motion | {head} | " + " | ".join(f"{n}, usable" for n in names[1:]) + " | "
        + " | ".join(f"{n}, not usable" for n in names[1:]) + " |",
        "|---|---|" + "---|" * (3 * len(names) - 2),
    ]
    for fam in fams:
        for kind in ("moving", "still"):
            if not sums.n[(fam, kind, METHODS[0], "all")]:
                continue
            cells = [f"{sums.rmse((fam, kind, n, 'all')):.4f}" for n in names]
            cells += [f"{sums.rmse((fam, kind, n, 'usable')):.4f}" for n in names[1:]]
            cells += [f"{sums.rmse((fam, kind, n, 'not usable')):.4f}" for n in names[1:]]
            lines.append(f"| {fam} | {kind} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=3, help="test scenes per family")
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--size", type=int, default=256, help="default-rig resolution (the other families draw theirs)")
    ap.add_argument("--orientation", choices=("rig", "auto"), default="rig",
                    help="the network's fringe orientation: rig = set once per scene from its first still burst (as a "
                         "user sets it per rig); auto = the per-burst vote (reports before session 26)")
    ap.add_argument("--prior-model", type=Path, default=None,
                    help="a prior_input network (.safetensors): decoded fed the prior's channels")
    ap.add_argument("--control", type=Path, default=None,
                    help="a plain network to compare it with (the same fine-tuning without the prior's channels)")
    args = ap.parse_args()
    args.families = [f.strip() for f in args.families.split(",") if f.strip()]
    bad = [f for f in args.families if f not in FAMILIES]
    if bad:
        ap.error(f"--families: unknown {bad}; expected some of {', '.join(FAMILIES)}")
    torch.set_num_threads(2)
    machine = host()
    t0 = time.perf_counter()
    # rig: the default rig of the deviation part is the twin's, "normal"; the families set theirs per scene
    net = Predictor.load(None, orientation="normal" if args.orientation == "rig" else "auto",
                         still_burst_rad=0.0)  # every network without the still-burst gate, as the extra ones
    extra_files = {n: f for n, f in ((CONTROL_NET, args.control), (PRIOR_NET, args.prior_model)) if f is not None}
    extra = {n: Predictor.load(f, orientation=net.orientation, precision=net.precision, still_burst_rad=0.0) for n, f in extra_files.items()}
    if PRIOR_NET in extra and not extra[PRIOR_NET].needs_prior:
        ap.error(f"--prior-model {args.prior_model}: not a prior_input network (its config has prior_input false)")
    timing = {"decode_s": 0.0, "bursts": 0, "precision": net.precision, "prior_s": timing_prior(args.size)}
    sums = Sums()
    scenes = families_part(args, net, sums, timing, extra)
    if args.orientation == "rig":
        for p in (net, *extra.values()):  # the deviation part's default rig is the twin's (families_part set the last scene's)
            p.orientation = "normal"
    dev_rows = deviation_part(args, net, extra)
    write_report(args, sums, scenes, dev_rows, timing, time.perf_counter() - t0, machine,
                 {n: str(f) for n, f in extra_files.items()})


if __name__ == "__main__":
    main()
