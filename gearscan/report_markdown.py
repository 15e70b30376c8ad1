"""The Markdown of ``gearscan evaluate``: the summary against the targets and each part's tables.

Reads only the results dictionary (``results.json``), so a report can be rendered again from it.
"""

from __future__ import annotations

from pathlib import Path

from gearscan.evaluate import PAPER_MOTIONS

POOLED = "both paper motions pooled"  # the uncertainty part's label of both paper motions together


def summarise(r: dict) -> dict:
    """The issue's acceptance numbers: network vs the best classical peer, cloud error in span."""
    cls = r["classical"]["scores"]

    def rmse(method: str, motion: str) -> float:
        return next(s["rmse_rad"] for s in cls if s["method"] == method and s["motion"] == motion)

    motion = "non-uniform 0.1/1.6"
    peers = ["three-step PS", "AIA (per region)", "Hilbert"]
    best = min(peers, key=lambda m: rmse(m, motion))
    ratio = rmse(best, motion) / rmse("CD-DCU-Net", motion)
    in_span = [s for s in cls if s["method"] == "CD-DCU-Net" and s["motion"] in PAPER_MOTIONS]
    cloud = max(s["cloud_rms_mm"] for s in in_span)
    coverage = min(s["coverage"] for s in in_span)
    return {
        "best_classical_non_uniform": best,
        "network_vs_best_classical_non_uniform": ratio,
        "ratio_target_5x_met": ratio >= 5.0,
        "cloud_rms_mm_paper_motions_max": cloud,
        "coverage_paper_motions_min": coverage,
        "cloud_target_0_05_mm_met": cloud < 0.05,
    }


def render_markdown(r: dict) -> str:
    def rows(d: dict) -> str:
        lines = ["| | " + " | ".join(next(iter(d.values())).keys()) + " |", "|---" * (1 + len(next(iter(d.values())))) + "|"]
        for k, v in d.items():
            lines.append(f"| {k} | " + " | ".join(f"{x:.4f}" for x in v.values()) + " |")
        return "\n".join(lines)

    def figures(part: str) -> list[str]:  # only what the part wrote
        return [f"![{Path(f).stem}]({f})" for f in r[part].get("figures", [])]

    tr = r["transfer"]["per_gear_rmse"]
    transfer_rows = {f"{label}, {gear}": v for label, g in tr.items() for gear, v in g.items()}
    u = r["uncertainty"]
    options = ["| option | value |", "|---|---|"] + [f"| {k} | {'' if v in ('None', '[]') else v} |"
                                                     for k, v in r["options"].items()]
    peers = [] if "fig12_loss_curves.png" in r["networks"].get("figures", []) else [
        "Loss curves (Fig. 12) need the peers' training runs (`gearscan evaluate --peers DIR`); none were given.", ""]
    return "\n".join([
        "# gearscan evaluation report",
        "",
        f"Scenes: {', '.join(r['scenes'])} (tooth count never trained on). Total time {r['seconds']:.0f} s.",
        "",
        *options,
        "",
        "## Summary against the targets",
        "",
        f"- Non-uniform motion (0.1/1.6 deg): CD-DCU-Net is {r['summary']['network_vs_best_classical_non_uniform']:.1f}x "
        f"better in phase RMSE than the best classical peer ({r['summary']['best_classical_non_uniform']}); target >= 5x: "
        f"{'met' if r['summary']['ratio_target_5x_met'] else 'NOT met'}.",
        f"- Point-cloud RMS vs the true surface (twin truth, not the CAD that chose the fringe orders) on the "
        f"paper's motions (span within training): at most {r['summary']['cloud_rms_mm_paper_motions_max']:.4f} mm "
        f"at a coverage of at least {100 * r['summary']['coverage_paper_motions_min']:.1f} % of the truth mask; "
        f"target < 0.05 mm: "
        f"{'met' if r['summary']['cloud_target_0_05_mm_met'] else 'NOT met'}.",
        "- Spans beyond training (section 6, 2 deg and more) lose accuracy, as the paper reports.",
        "",
        "## 1. Transfer learning (Fig. 11)",
        "",
        "Fine-tuning on a target domain (another rig, a dim, noisy, blurred camera; gears z=25 and z=18) with the same",
        f"small budget ({budget_text(r['transfer']['budget'])}): from the twin-pretrained model vs from Kaiming",
        "initialisation. The figure shows the validation RMSE while fine-tuning; the table the phase RMSE (rad)",
        "on held-out target bursts:",
        "",
        rows(transfer_rows),
        "",
        *figures("transfer"),
        "",
        "## 2. Networks (Figs. 12-14)",
        "",
        r["networks"]["table"],
        "",
        *peers,
        *figures("networks"),
        "",
        "## 3. Loss ablation (Figs. 15-17)",
        "",
        f"Both variants trained from Kaiming init with the same budget ({budget_text(r['loss_ablation']['budget'])}).",
        "Phase RMSE (rad):",
        "",
        rows(r["loss_ablation"]["rmse"]),
        "",
        *figures("loss_ablation"),
        "",
        "## 4. Uncertainty (Figs. 18-19)",
        "",
        f"CD-DCU-Net MC T={u['mc']}, ECE with 30 bins and eps 0.03 rad. The figures show the same predictions as this",
        "table (the MC rows of section 5 are another draw of the dropout masks):",
        "",
        *uncertainty_table(u),
        "",
        *figures("uncertainty"),
        "",
        "## 5. Against classical phase shifting (Figs. 20-21)",
        "",
        r["classical"]["table"],
        "",
        *figures("classical"),
        "",
        "## 6. Generalisation to unseen frame intervals (Fig. 22)",
        "",
        r["generalisation"]["table"],
        "",
        *figures("generalisation"),
        "",
    ])


def uncertainty_table(u: dict) -> list[str]:
    """Section 4's numbers per paper motion and pooled (older results: the pooled line only)."""
    per = u.get("per_motion") or {POOLED: {"bursts": "", "rmse_rad": u["rmse_rad"], "mean_sigma_rad": u["mean_sigma_rad"],
                                           "ece": u["ece"]}}
    return ["| motion | bursts | phase RMSE (rad) | mean predicted sigma (rad) | ECE |", "|---|---|---|---|---|"] + [
        f"| {m} | {v['bursts']} | {v['rmse_rad']:.4f} | {v['mean_sigma_rad']:.4f} | {v['ece']:.3f} |" for m, v in per.items()]


def budget_text(b: dict[str, int]) -> str:
    """A training budget in words (the report's reader does not know the option names)."""
    return (f"{b['epochs']} epochs of {b['steps']} steps, batches of {b['batch']} crops of {b['crop']} px "
            f"from {b['size']} px scenes with {b['poses']} poses each")
