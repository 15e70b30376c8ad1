"""The default-rig model until session 54 (v6 fine-tuned on the product's rig): its val choice and its test numbers,
beside v6. Its successor (v9 fine-tuned on a GPU): ``default_rig/choice_rule_gpu.md``, ``generalization_default_rig.md``.

    .venv/bin/python benchmarks/default_rig_report.py

Reads what `scripts/default_rig_model.py`, `scripts/val_compare.py --orientation normal` (val, under
``benchmarks/default_rig/``) and `benchmarks/generalization.py --model inference/weights/default_rig.safetensors
--out benchmarks/generalization_default_rig` wrote, and v6's `generalization_report.json`; writes
``benchmarks/default_rig_report.md``. Val chose; test only reports.
"""

from __future__ import annotations

import csv
import json
import math
import subprocess
from pathlib import Path

HERE = Path(__file__).resolve().parent
RAW = HERE / "default_rig"
V6, NEW = "inference/weights/default.safetensors", "runs/default_rig/best.safetensors"
RIG = "CD-DCU-Net, rig orientation from a still burst"
FOLDERS = ("z25", "z32", "z46", "z62")


def _load(path: Path) -> dict:
    return json.loads(path.read_text())


# the test reports this report reads, at the revisions that held them (git history)
PREDECESSOR_TEST = ("602813a", "benchmarks/generalization_default_rig.json")  # the predecessor's, run at d1d2abc
V6_TEST = ("fdbf23c", "benchmarks/generalization_report.json")  # v6's, run at 6dc91a7


def _load_at(rev: str, path: str) -> dict | None:
    """``path`` as it was at ``rev`` (git show); None, said, where git or the revision is not at hand."""
    run = subprocess.run(["git", "show", f"{rev}:{path}"], cwd=HERE.parent, capture_output=True, text=True)
    if run.returncode:
        print(f"{path} at {rev}: not readable through git ({run.stderr.strip()}); the test section is left out")
        return None
    return json.loads(run.stdout)


def _pool(values: list[float]) -> float:
    """RMS over folders of equal burst counts."""
    return math.sqrt(sum(v * v for v in values) / len(values))


def _val_table(rows: dict[str, dict], names: tuple[str, ...], lead: str = "") -> tuple[list[str], dict, dict]:
    """Table rows per val gear and pooled (``lead``: cells before the gear's), and the pooled moving and still
    RMSE per name; the last name is the candidate, in bold on the pooled row."""
    out = []
    for z, d in rows.items():
        cells = [f"{d[kind][n]:.3f}" for kind in ("moving", "still") for n in names]
        out.append(f"{lead}| {z} | " + " | ".join(cells) + " |")
    pm = {n: _pool([rows[z]["moving"][n] for z in rows]) for n in names}
    ps = {n: _pool([rows[z]["still"][n] for z in rows]) for n in names}
    cells = [f"{pm[n]:.3f}" for n in names[:-1]] + [f"**{pm[names[-1]]:.3f}**"] + [f"{ps[n]:.3f}" for n in names]
    out.append(f"{lead}| **pooled** | " + " | ".join(cells) + " |")
    return out, pm, ps


def multi_section(multi: Path, v6: str) -> list[str]:
    """The candidate fine-tuned at 256x256 and 512x512 (rule: ``choice_rule_multi.md``), on val at both sizes."""
    run = _load(multi / "run.json")
    first, cand = "inference/weights/default_rig.safetensors", "runs/default_rig_multi/best.safetensors"
    out = ["", "## Candidate tuned at 256x256 and 512x512 (val; rule written before: `default_rig/choice_rule_multi.md`)",
           "", f"`{run['command']}`; {run['steps']} steps of 8, {run['cpu_min']:.1f} CPU min. "
           "`scripts/val_compare.py --orientation normal --items 48` per val gear and size (48 moving, 24 still); "
           "*first*: the 256x256-only model above.", "",
           "| size | gear | moving: three-step | v6 | first | candidate | still: three-step | v6 | first | candidate |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    verdict = []
    for size in (256, 512):
        rows = {z: _load(multi / f"val_{size}_{z}.json") for z in FOLDERS}
        table, pm, ps = _val_table(rows, ("three-step", v6, first, cand), f"| {size} ")
        out += table
        verdict.append(pm[cand] <= 0.9 * pm[v6] and ps[cand] <= ps[v6] + 0.005)
        if size == 256:
            verdict.append(pm[cand] <= 1.1 * pm[first])
    out += ["", f"Rule: **{'passed: it replaces the first model as the option' if all(verdict) else 'failed: the first model stays'}**."]
    return out


def continuation_section(raw: Path, cand: str, rule: str, title: str, names: tuple[str, str]) -> list[str]:
    """The option fine-tuned further (its rule: ``rule``, written before the run), on val against the option it
    started from. ``names``: the start's and the candidate's column names."""
    run = _load(raw / "run.json")
    start = "inference/weights/default_rig.safetensors"  # the option the run started from, when it was scored
    rows = {z: _load(raw / f"val_{z}.json") for z in FOLDERS}
    a, b = names
    out = ["", f"## {title} (val; rule written before: `default_rig/{rule}`)", "",
           f"`{run['command']}`; {run['steps']} more steps of 8, {run['cpu_min']:.1f} CPU min, from the option "
           f"(*{a}*). `scripts/val_compare.py --orientation normal` per val gear (96 moving, 36 still).", "",
           f"| gear | moving: three-step | v6 | {a} | {b} | still: three-step | v6 | {a} | {b} |",
           "|---|---|---|---|---|---|---|---|---|"]
    table, pm, ps = _val_table(rows, ("three-step", V6, start, cand))
    out += table
    gain = 1 - pm[cand] / pm[start]
    ok = gain >= 0.05 and ps[cand] <= ps[start] + 0.003
    out += ["", f"Rule: moving at least 5 % below the {a} model ({gain:.0%}) and still at most 0.003 rad above it "
            f"({ps[cand] - ps[start]:+.3f}): **{f'passed: it replaces the {a} model as the option' if ok else f'failed: the {a} model stays'}**."]
    return out


def ablation_section(raw: Path) -> list[str]:
    """The annealed run repeated on the first runs' 64 start points (``ablation_rule.md``): schedule or data?"""
    run = _load(raw / "run.json")
    cont, annealed, abl = ("runs/continued/default_rig.safetensors", "inference/weights/default_rig.safetensors",
                           "runs/default_rig_anneal64/best.safetensors")
    rows = {z: _load(raw / f"val_{z}.json") for z in FOLDERS}
    out = ["", "## Ablation: the annealed run on the first runs' data (val; read-out written before: "
           "`default_rig/ablation_rule.md`)", "",
           f"`{run['command']}`; {run['steps']} steps of 8, {run['cpu_min']:.1f} CPU min, from the continued model "
           "(the annealed run's start) with its schedule, on 64 start points instead of 192. Not a candidate.", "",
           "| gear | moving: three-step | v6 | continued | annealed, 192 start points | annealed, 64 | still: three-step | v6 "
           "| continued | annealed, 192 | annealed, 64 |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    table, pm, ps = _val_table(rows, ("three-step", V6, cont, annealed, abl))
    out += table
    a, b = pm[annealed], pm[abl]
    verdict = ("the schedule bought the gain; 3x the data added nothing measurable at this budget" if b <= a + 0.003
               else "the data bought most of it" if b >= 0.077 else "both did")
    out += ["", f"Read-out: moving {b:.3f} on 64 start points against {a:.3f} on 192 (continued model "
            f"{pm[cont]:.3f}): **{verdict}**."]
    return out


def main() -> None:
    run = _load(RAW / "run.json")
    val = {f: _load(RAW / f"val_{f}.json") for f in FOLDERS}
    rows = list(csv.DictReader((RAW / "training_metrics.csv").open()))
    lines = [
        "# The default-rig model until session 54: v6 fine-tuned on the product's own rig",
        "",
        "Replaced in session 54 by v9 fine-tuned on the same rig on a lent GPU (`default_rig/choice_rule_gpu.md`, "
        "`generalization_default_rig.md`, `inference/weights/DEFAULT_RIG_MODEL_CARD.md`); this report is its "
        "predecessor's, its test section read from the revisions that held those reports.",
        "",
        f"`{run['command']}`; {run['steps']} steps of 8 (128^2 crops), {run['cpu_min']:.1f} CPU min "
        f"({run['train_wall_s'] / 60:.0f} min wall on this host's 2 cores; the render {run['render_s']:.0f} s). "
        "Choice rule written before the run: `default_rig/choice_rule.md`.",
        "",
        f"- **Data**: the default rig (`twin.families.default_rig_scene`) aimed at train-split gears, teeth "
        f"{', '.join(map(str, run['train_teeth']))} (module 2, pressure angle and face width drawn as the test "
        f"family draws them, train seeds), up to 4 start angles each; {run['train_items']} training items (still bursts "
        "x20, both senses). Val: the same rig with val-split gears, teeth "
        f"{', '.join(map(str, run['val_teeth']))}, val seed 10005, 2 start angles each.",
        "- **What it is**: per-rig adaptation for the rig the product ships with. The default rig is one of the "
        "test split's rig families, so its default-family test numbers measure unseen gears on a rig it was "
        "trained on; the other families measure what the specialisation costs elsewhere.",
        "",
        "## Val (chose it): `scripts/val_compare.py --orientation normal`, 96 moving bursts (both senses) and "
        "the still ones per folder",
        "",
        "| val gear | moving: three-step | v6 | default-rig | still: three-step | v6 | default-rig |",
        "|---|---|---|---|---|---|---|",
    ]
    pooled = {"moving": {}, "still": {}}
    for f in FOLDERS:
        m, s = val[f]["moving"], val[f]["still"]
        lines.append(f"| {f} | {m['three-step']:.3f} | {m[V6]:.3f} | {m[NEW]:.3f} | {s['three-step']:.3f} "
                     f"({s['bursts']} bursts) | {s[V6]:.3f} | {s[NEW]:.3f} |")
    for kind in pooled:
        for name in ("three-step", V6, NEW):
            pooled[kind][name] = _pool([val[f][kind][name] for f in FOLDERS])
    pm, ps = pooled["moving"], pooled["still"]
    lines.append(f"| **pooled** | {pm['three-step']:.3f} | {pm[V6]:.3f} | **{pm[NEW]:.3f}** | {ps['three-step']:.3f} | "
                 f"{ps[V6]:.3f} | {ps[NEW]:.3f} |")
    gain = 1 - pm[NEW] / pm[V6]
    ok = gain >= 0.10 and ps[NEW] <= ps[V6] + 0.005
    lines += ["", f"Rule: moving at least 10 % below v6 ({gain:.0%}) and still at most 0.005 rad above it "
              f"({ps[NEW] - ps[V6]:+.3f}): **{'passed, shipped as an option' if ok else 'failed, not shipped'}**.",
              f"Training-time val RMSE (48 of the val items, `default_rig/training_metrics.csv`): "
              f"{float(rows[0]['val_rmse']):.3f} at the start (v6), {min(float(r['val_rmse']) for r in rows):.3f} at "
              f"best, {float(rows[-1]['val_rmse']):.3f} at the end."]
    multi = RAW / "multi"
    if (multi / "run.json").is_file():
        lines += multi_section(multi, V6)
    for raw, cand, rule, title, names in (
        ("continue", "runs/default_rig_cont/best.safetensors", "choice_rule_continue.md", "The option continued",
         ("first", "continued")),
        ("anneal", "runs/default_rig_anneal/best.safetensors", "choice_rule_anneal.md",
         "The option continued again: the rate annealed, 3x the start points", ("continued", "annealed")),
        ("cycle2", "runs/default_rig_cycle2/best.safetensors", "choice_rule_cycle2.md",
         "A second cosine cycle (warm restart)", ("annealed", "second-cycle")),
    ):
        if (RAW / raw / "run.json").is_file():
            lines += continuation_section(RAW / raw, cand, rule, title, names)
    if (RAW / "ablation" / "run.json").is_file():
        lines += ablation_section(RAW / "ablation")
    # the test reports as they were when this report was written: the files now hold the session-54 option's and
    # v9's, so the revisions that held the predecessor's and v6's are read through git
    new, v6 = (_load_at(rev, path) for rev, path in (PREDECESSOR_TEST, V6_TEST))
    if new is not None and v6 is not None:

        def cell(rep: dict, fam: str, group: str) -> dict:
            return next(c for c in rep["cells"] if c["family"] == fam and c["group"] == group)

        lines += ["", "## Test split (reports only): `benchmarks/generalization.py`, the same 800 bursts as v6's report",
                  "",
                  f"Default-rig model: `generalization_default_rig.md` (commit `{new['commit']}`); v6: "
                  f"`generalization_report.md` (commit `{v6['commit']}`). Fringe orientation set per rig (from the "
                  "scene's first still burst); RMSE in rad, ECE deterministic, keep-test coverage.", "",
                  "| family | bursts | three-step | v6 | default-rig | v6 ECE / coverage | default-rig ECE / coverage |",
                  "|---|---|---|---|---|---|---|"]
        fams = [c["family"] for c in new["cells"] if c["group"] == "moving"]
        for group in ("moving", "still"):
            for fam in fams:
                a, b = cell(v6, fam, group), cell(new, fam, group)
                lines.append(f"| {fam}, {group} | {b['bursts']} | {b['rmse']['three-step PS']:.3f} | {a['rmse'][RIG]:.3f} | "
                             f"**{b['rmse'][RIG]:.3f}** | {a['ece'][RIG]:.3f} / {a['coverage'][RIG]:.1%} | "
                             f"{b['ece'][RIG]:.3f} / {b['coverage'][RIG]:.1%} |")
        def paper(rep: dict, method: str) -> float:  # issue 13's default-rig target is read on these
            parts = [c for c in rep["cells"] if c["family"] == "default" and c["group"] in ("paper", "paper reversed")]
            return math.sqrt(sum(c["rmse"][method] ** 2 * c["pixels"] for c in parts) / sum(c["pixels"] for c in parts))

        three = paper(new, "three-step PS")
        lines += ["", f"Default rig, the paper's motions both ways (issue 13's target: <= 0.04 rad): v6 {paper(v6, RIG):.3f} "
                  f"rad, default-rig model **{paper(new, RIG):.3f}** ({three / paper(new, RIG):.1f}x below three-step PS's "
                  f"{three:.3f})."]
    (HERE / "default_rig_report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
