"""Choose the keep bound of the path that fuses and fits to the frames, on VAL stretches.

    python scripts/choose_frame_fit_keep_bound.py [--out benchmarks/frame_fit_keep_bound_val.json]

Rule, written before this ran: ``benchmarks/frame_fit_keep_bound_rule.md``. The four val stretches of
``scripts/choose_fused_support.py`` (two seeds, both pattern orders; they chose only that path's support test), the
shipped model, three candidate bounds: each cell is replayed with fusion and the frame fit and scored against the
twin's true surface as ``benchmarks/frame_fit_heldout.py`` scores its held-out stretches. The held-out stretches and
the inspection revolution only report afterwards.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "scripts"))
from choose_fused_support import VAL_STRETCHES  # noqa: E402  (the same val stretches)
from frame_fit_heldout import render_stretch, score_stretch  # noqa: E402  (the held-out bench's own scoring)

from gearscan.provenance import run_stamp  # noqa: E402

CANDIDATES: tuple[float, ...] = (0.3, 0.5, 0.7)
INCUMBENT, COVERAGE_SLACK, MARGIN = 0.7, 0.005, 0.03


def choose(cells: list[dict], incumbent: float = INCUMBENT) -> dict:
    """The rule: admissible bounds (coverage on every cell at least the loosest candidate's minus COVERAGE_SLACK),
    geometric-mean scores, and the pick (a change from ``incumbent`` needs a MARGIN lower score)."""
    keys = sorted({(c["seed"], c["order"]) for c in cells})

    def cell(b, key):
        return next(c for c in cells if c["max_sigma"] == b and (c["seed"], c["order"]) == key)

    loosest = max(CANDIDATES)
    score = {b: math.exp(sum(math.log(cell(b, k)["rms_um"]) for k in keys) / len(keys)) for b in CANDIDATES}
    admissible = {b: all(cell(b, k)["coverage"] >= cell(loosest, k)["coverage"] - COVERAGE_SLACK for k in keys)
                  for b in CANDIDATES}
    best = min((b for b in CANDIDATES if admissible[b]), key=lambda b: score[b])
    chosen = best if score[best] <= (1 - MARGIN) * score[incumbent] else incumbent
    return {"score_um": {str(b): s for b, s in score.items()}, "admissible": {str(b): a for b, a in admissible.items()},
            "best": best, "incumbent": incumbent, "chosen": chosen}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "frame_fit_keep_bound_val.json")
    ap.add_argument("--recordings", type=Path, default=ROOT / "out" / "fused_support_val")
    ap.add_argument("--bursts", type=int, default=60)
    args = ap.parse_args()

    from gearscan.inference.decoder import Decoder
    from gearscan.inference.model_io import model_fingerprint
    from gearscan.inference.predictor import DEFAULT_MODEL
    from gearscan.recon.measure import network_support_option, unwrapper_sees

    decoder = Decoder(None)
    support = network_support_option(None, frame_fit=True, model=decoder.network_support)
    cells = []
    for s in VAL_STRETCHES:
        for alternate in (True, False):
            rec = render_stretch(args.recordings, s, alternate, args.bursts)
            for b in CANDIDATES:
                cells.append({"seed": s["seed"], "order": "alternating" if alternate else "fixed", "max_sigma": b,
                              **score_stretch(rec, decoder, support, max_sigma=b)})
                print({k: cells[-1][k] for k in ("seed", "order", "max_sigma", "rms_um", "coverage")}, flush=True)
    res = {"rule": "benchmarks/frame_fit_keep_bound_rule.md", "split": "val", "model_fingerprint":
           model_fingerprint(DEFAULT_MODEL), "network_support_px": support,
           "unwrapper_sees": {str(b): unwrapper_sees(max_sigma=b) for b in CANDIDATES},
           "cells": cells, "choice": choose(cells), **run_stamp()}
    args.out.write_text(json.dumps(res, indent=1))
    print(json.dumps(res["choice"], indent=1))


if __name__ == "__main__":
    main()
