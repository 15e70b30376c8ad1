"""Choose the fringe-support test for the path that fuses and fits to the frames, on VAL stretches.

    python scripts/choose_fused_support.py [--out benchmarks/fused_support_val.json]

Rule, written before this ran: ``benchmarks/fused_support_rule.md``. Four 60-burst stretches (two seeds, both
pattern orders) that nothing else uses, two models (the shipped one and the default-rig option), four candidates
(off, 0, 1, 2 px): each cell is replayed with fusion and the frame fit and scored against the twin's true
surface exactly as ``benchmarks/frame_fit_heldout.py`` scores its held-out stretches. Cells already in ``--out``
are kept (a stopped run resumes; not across a change of ``recon.track.REST_SIGMA_SCALE``, which the json records:
the recorded run, at 24e4fa9, predates that scale and ran at 1). Since session 54 a model's own scale (its JSON's
``rest_sigma``) replaces the product's for its cells, and the recorded option cells are its predecessor's (v6 fine-tuned):
a rerun for the option starts a new ``--out``. The held-out stretches and the inspection revolution only report
afterwards.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from frame_fit_heldout import render_stretch, score_stretch  # noqa: E402  (the held-out bench's own scoring)
from inspect_bench import commit, host  # noqa: E402

VAL_STRETCHES = [  # rule table: used nowhere else
    {"seed": 31, "start_deg": 113.0, "pitch_errors": ["9:30"], "chips": ["4:0.3"]},
    {"seed": 47, "start_deg": 277.0, "pitch_errors": ["17:30"], "chips": ["13:0.3"]},
]


def shipped_label() -> str:
    """The shipped model's cell label, by its version (``v6 (shipped)`` in the runs before session 39)."""
    from gearscan.inference.model_io import read_config
    from gearscan.inference.predictor import DEFAULT_MODEL

    return f"{read_config(DEFAULT_MODEL).get('training', {}).get('version', 'default')} (shipped)"


MODELS = {shipped_label(): None, "default-rig option": ROOT / "inference" / "weights" / "default_rig.safetensors"}


def rest_scales() -> dict[str, float]:
    """The unfitted points' sigma scale each model's cells run at (its JSON's ``rest_sigma``, else the product's,
    ``recon.track.REST_SIGMA_SCALE``): recorded by the rule scripts, whose resumes are refused where it changed."""
    from gearscan.inference.model_io import read_config
    from gearscan.inference.predictor import DEFAULT_MODEL, model_rest_sigma_scale
    from gearscan.recon.track import REST_SIGMA_SCALE

    return {m: model_rest_sigma_scale(read_config(w or DEFAULT_MODEL)) or REST_SIGMA_SCALE for m, w in MODELS.items()}
CANDIDATES: tuple[int | None, ...] = (None, 0, 1, 2)  # None: no test
# a change from the incumbent needs a MARGIN lower score. The incumbent: 2 px in the rule's first run (24e4fa9) and in
# its v9 rerun (session 39, the rule's text read literally); since the rule's amendment, what ships when a run starts
# (recon.measure.FRAME_FIT_NETWORK_SUPPORT_PX), recorded in the run's json as incumbent_px
FIRST_INCUMBENT, COVERAGE_SLACK, MARGIN = 2, 0.005, 0.03


def val_cells(recordings: Path, bursts: int):
    """The rule's val cells, model by model: (model, decoder, seed, order, recording), each stretch rendered once."""
    from gearscan.inference.decoder import Decoder

    for model, weights in MODELS.items():
        decoder = Decoder(weights)
        for s in VAL_STRETCHES:
            for alternate in (True, False):
                yield (model, decoder, s["seed"], "alternating" if alternate else "fixed",
                       render_stretch(recordings, s, alternate, bursts))


def shipped_sha256() -> str:
    """The shipped model a run scores as "the shipped model" (the default changes between sessions): since session 43
    its :func:`~gearscan.inference.model_io.model_fingerprint` (weights and sigma maps), so a run with refitted maps is
    never resumed into cells scored with others; before, the weights' sha alone."""
    from gearscan.inference.model_io import model_fingerprint
    from gearscan.inference.predictor import DEFAULT_MODEL

    return model_fingerprint(DEFAULT_MODEL)


def load_or_start(out: Path, **fresh) -> dict:
    """The run's json: resumed from ``out`` (its resumes stamped) or a new one with this commit, host and the shipped
    model's fingerprint (:func:`shipped_sha256`); a json whose cells were scored with another shipped decode (other
    weights or sigma maps) is refused."""
    sha = shipped_sha256()
    if not out.exists():
        return {"commit": commit(), "host": host(), "shipped_sha256": sha, "cells": [], **fresh}
    done = json.loads(out.read_text())
    if done["cells"] and done.get("shipped_sha256") != sha:
        raise SystemExit(f"{out}: its shipped model's cells were scored with another decode (weights or sigma maps) "
                         f"({done.get('shipped_sha256', 'not recorded')}, now {sha}); write to another --out")
    if done["cells"]:
        done.setdefault("resumed_at", []).append(commit())
    return done


def label(e: int | None) -> str:
    return "off" if e is None else f"{e} px"


def choose(cells: list[dict], incumbent: int | None) -> dict:
    """The rule's choice from the cells of this run's MODELS: admissible candidates, geometric means, the pick (a
    change from ``incumbent``, a candidate, needs a MARGIN lower score)."""
    cells = [c for c in cells if c["model"] in MODELS]  # a json's cells of other weights are never pooled in
    def cell(e, key):
        return next(c for c in cells if c["E"] == e and (c["model"], c["seed"], c["order"]) == key)

    keys = sorted({(c["model"], c["seed"], c["order"]) for c in cells})
    score, admissible = {}, {}
    for e in CANDIDATES:
        score[label(e)] = math.exp(sum(math.log(cell(e, k)["rms_um"]) for k in keys) / len(keys))
        admissible[label(e)] = all(cell(e, k)["coverage"] >= cell(None, k)["coverage"] - COVERAGE_SLACK for k in keys)
    best = min((e for e in CANDIDATES if admissible[label(e)]), key=lambda e: score[label(e)])
    chosen = best if score[label(best)] <= (1 - MARGIN) * score[label(incumbent)] else incumbent
    per_model = {}
    for model in MODELS:
        mk = [k for k in keys if k[0] == model]
        per_model[model] = {label(e): math.exp(sum(math.log(cell(e, k)["rms_um"]) for k in mk) / len(mk))
                            for e in CANDIDATES}
    return {"score_um": score, "admissible": admissible, "best": label(best), "incumbent": label(incumbent),
            "chosen": label(chosen), "chosen_px": chosen, "per_model_score_um": per_model}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "fused_support_val.json")
    ap.add_argument("--recordings", type=Path, default=ROOT / "out" / "fused_support_val")
    ap.add_argument("--bursts", type=int, default=60)
    args = ap.parse_args()

    from gearscan.recon.measure import FRAME_FIT_NETWORK_SUPPORT_PX
    from gearscan.recon.track import REST_SIGMA_SCALE

    scales = rest_scales()
    done = load_or_start(args.out, rest_sigma_scale=REST_SIGMA_SCALE, rest_sigma_scale_by_model=scales)
    ran_at = done.setdefault("rest_sigma_scale", 1.0)  # a json without the key was written before the scale existed
    # before session 54 every model's cells ran at the product's scale
    ran_by_model = done.setdefault("rest_sigma_scale_by_model", dict.fromkeys(MODELS, ran_at))
    if done["cells"] and (ran_at != REST_SIGMA_SCALE or ran_by_model != scales):
        raise SystemExit(f"{args.out}: its cells were scored with the unfitted points' sigma scales {ran_by_model}, "
                         f"this code runs {scales}; write to another --out")
    # what shipped when the run began; a json scored before the key existed ran with the first incumbent
    incumbent = done.setdefault("incumbent_px", FIRST_INCUMBENT if done["cells"] else FRAME_FIT_NETWORK_SUPPORT_PX)
    cells = done["cells"]
    for model, decoder, seed, order, rec in val_cells(args.recordings, args.bursts):
        for e in CANDIDATES:
            if any((c["model"], c["seed"], c["order"], c["E"]) == (model, seed, order, e) for c in cells):
                continue
            cells.append({"model": model, "seed": seed, "order": order, "E": e, **score_stretch(rec, decoder, e)})
            print({k: cells[-1][k] for k in ("model", "seed", "order", "E", "rms_um", "coverage")}, flush=True)
            args.out.write_text(json.dumps(done, indent=1))
    done["choice"] = choose(cells, incumbent)
    args.out.write_text(json.dumps(done, indent=1))
    print(json.dumps(done["choice"], indent=1))


if __name__ == "__main__":
    main()
