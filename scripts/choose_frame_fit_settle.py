"""Choose the frame fit's settle test on VAL stretches.

    python scripts/choose_frame_fit_settle.py [--out benchmarks/frame_fit_settle_val.json]

Rule, written before this ran: ``benchmarks/frame_fit_settle_rule.md``. Eight val stretches (four seeds, both
pattern orders; two seeds fresh), two models: each cell is replayed once with fusion and the frame fit at the path's
shipped settings, then every candidate refits the same fused cloud on the same frames and is scored against the
twin's true surface as ``benchmarks/frame_fit_heldout.py`` scores. Cells already in ``--out`` are kept (a stopped run
resumes). The inspection revolution and the held-out stretches only report afterwards.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "scripts"))
from choose_fused_support import MODELS, VAL_STRETCHES, load_or_start, rest_scales  # noqa: E402  (the same val stretches and models)
from frame_fit_heldout import render_stretch, score_fused, truth_scene  # noqa: E402  (the held-out bench's own scoring)

from gearscan.recon.track import TrackRefiner  # noqa: E402

FRESH_STRETCHES = [  # rule table: used nowhere else
    {"seed": 61, "start_deg": 41.0, "pitch_errors": ["7:30"], "chips": ["11:0.3"]},
    {"seed": 79, "start_deg": 331.0, "pitch_errors": ["15:30"], "chips": ["3:0.3"]},
]
CANDIDATES: tuple[float | None, ...] = (None, 0.3, 0.1, 0.03)  # None: no test
INCUMBENT, COVERAGE_SLACK, RMS_SLACK, MARGIN = None, 0.005, 0.05, 0.03


def label(c: float | None) -> str:
    return "off" if c is None else c if isinstance(c, str) else f"{c:g}"


class _KeepingRefiner(TrackRefiner):
    """The product's frame fit that also keeps the fused cloud it was given, so each candidate can refit it."""

    fused = None

    def refine_fused(self, fused):
        self.fused = fused
        return super().refine_fused(fused)


def score_cell(rec: Path, decoder, field: str = "settle_rad", candidates=CANDIDATES, base: dict | None = None) -> list[dict]:
    """One replay of ``rec`` at the path's shipped settings, then a refit of its fused cloud per candidate value of the
    refiner's ``field`` (the others at ``base``, default: the settle and modulation tests off), each scored."""
    from gearscan.core.recording import RecordingReader
    from gearscan.recon.fuse import CloudFuser
    from gearscan.replay import replay

    kept: list[_KeepingRefiner] = []

    def factory(rig, period_px, rest_sigma_scale):  # the decoding model's scale, else the product's (replay says)
        # the settle rule's cells ran before the modulation test existed: its default base has neither test
        kept.append(_KeepingRefiner(rig, period_px, rest_sigma_scale=rest_sigma_scale,
                                    **({"settle_rad": None, "modulation_ratio": None} if base is None else base)))
        return kept[-1]

    m = replay(rec, decoder=decoder, fuse=CloudFuser(0.1, 3), truth=False, refine=True, refiner_factory=factory)
    ran = {"support_px_run": m.recon["network_support_px"], "max_sigma_rad_run": m.recon["max_sigma_rad"],
           "rest_sigma_scale_run": m.recon["rest_sigma_scale"]}
    refiner = kept[0]
    reader = RecordingReader(rec)
    scene = truth_scene(reader)
    rows = []
    for c in candidates:
        setattr(refiner, field, c)
        t = time.perf_counter()
        fused, stats = refiner.refine_fused(refiner.fused)
        # seconds: this candidate's refit alone
        rows.append({field: c, **ran, **score_fused(reader, scene, fused, stats, time.perf_counter() - t)})
    return rows


def geomean(xs) -> float:
    xs = list(xs)
    return math.exp(sum(math.log(x) for x in xs) / len(xs))


def choose(cells: list[dict], incumbent: float | None = INCUMBENT, models=None, field: str = "settle_rad",
           candidates=CANDIDATES, reference=None, metric: str = "rms_um") -> dict:
    """The rule: admissible candidates (on every cell coverage at least ``reference``'s minus COVERAGE_SLACK and RMS at
    most RMS_SLACK above its), geometric-mean scores of ``metric``, the pick (a change from ``incumbent`` needs a MARGIN
    lower score). Only ``models``' cells (default: this run's MODELS) are pooled; every candidate must have every cell.
    ``field``: the cells' key of the candidate value; ``reference`` (default None: no test) sets the floors."""
    models = set(MODELS if models is None else models)
    cells = [c for c in cells if c["model"] in models]
    keys = sorted({(c["model"], c["seed"], c["order"]) for c in cells})
    have = {(c[field], c["model"], c["seed"], c["order"]) for c in cells}
    missing = [(label(c), *k) for c in candidates for k in keys if (c, *k) not in have]
    if missing:
        raise ValueError(f"the rule scores every candidate on every cell; missing: {missing[:4]}")

    def cell(c, key):
        return next(x for x in cells if x[field] == c and (x["model"], x["seed"], x["order"]) == key)

    score = {c: geomean(cell(c, k)[metric] for k in keys) for c in candidates}
    admissible = {c: all(cell(c, k)["coverage"] >= cell(reference, k)["coverage"] - COVERAGE_SLACK
                         and cell(c, k)["rms_um"] <= (1 + RMS_SLACK) * cell(reference, k)["rms_um"] for k in keys)
                  for c in candidates}
    best = min((c for c in candidates if admissible[c]), key=lambda c: score[c])
    chosen = best if score[best] <= (1 - MARGIN) * score[incumbent] else incumbent
    fresh = {s["seed"] for s in FRESH_STRETCHES}
    report = {  # read out, not chosen on
        "fresh_score_um": {label(c): geomean(cell(c, k)[metric] for k in keys if k[1] in fresh) for c in candidates},
        "per_model_order_score_um": {f"{m} / {o}": {label(c): geomean(cell(c, k)[metric] for k in keys
                                                                     if (k[0], k[2]) == (m, o)) for c in candidates}
                                     for m in sorted({k[0] for k in keys}) for o in ("alternating", "fixed")},
    }
    return {"score_um": {label(c): s for c, s in score.items()}, "admissible": {label(c): a for c, a in admissible.items()},
            "best": best, "incumbent": incumbent, "chosen": chosen, **report}


def start_run(out: Path, rule: str, settings: dict, **fresh) -> dict:
    """A val run's json: resumed from ``out`` unless its cells ran with other ``settings`` (refused), else new."""
    done = load_or_start(out, rule=rule, split="val", **settings, **fresh)
    changed = {k: (done.get(k), v) for k, v in settings.items() if done.get(k) != v}
    if done["cells"] and changed:
        raise SystemExit(f"{out}: its cells ran with other frame-fit settings (recorded, now): {changed}; "
                         "write to another --out")
    return done


def run_rule(out: Path, recordings: Path, bursts: int, rule: str, field: str, candidates, base: dict | None,
             settings: dict, count_key: str, scorer=None, incumbent=INCUMBENT, reference=None,
             metric: str = "rms_um") -> dict:
    """A frame-fit rule's val run over the 16 cells: resumed from ``out`` (refused if its ``settings`` changed), each
    cell replayed once and every candidate value of ``field`` refitted (:func:`score_cell`, or ``scorer(rec,
    decoder)``), then :func:`choose` (``incumbent``, ``reference``, ``metric``); ``count_key``: the row's field printed
    beside the RMS and coverage."""
    from gearscan.inference.decoder import Decoder

    done = start_run(out, rule, settings)
    cells = done["cells"]
    for model, weights in MODELS.items():
        decoder = Decoder(weights)
        for s in VAL_STRETCHES + FRESH_STRETCHES:
            for alternate in (True, False):
                order = "alternating" if alternate else "fixed"
                if any((c["model"], c["seed"], c["order"]) == (model, s["seed"], order) for c in cells):
                    continue
                rec = render_stretch(recordings, s, alternate, bursts)
                rows = scorer(rec, decoder) if scorer is not None else score_cell(rec, decoder, field, candidates, base)
                for row in rows:
                    cells.append({"model": model, "seed": s["seed"], "order": order, **row})
                    print({k: cells[-1][k] for k in ("model", "seed", "order", field, "rms_um", "coverage", count_key)},
                          flush=True)
                out.write_text(json.dumps(done, indent=1))
    done["choice"] = choose(cells, incumbent, field=field, candidates=candidates, reference=reference, metric=metric)
    out.write_text(json.dumps(done, indent=1))
    return done


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "frame_fit_settle_val.json")
    ap.add_argument("--recordings", type=Path, default=ROOT / "out" / "fused_support_val")
    ap.add_argument("--bursts", type=int, default=60)
    args = ap.parse_args()

    from gearscan.recon.measure import FRAME_FIT_MAX_SIGMA_RAD, FRAME_FIT_NETWORK_SUPPORT_PX
    from gearscan.recon.track import REST_SIGMA_SCALE

    settings = {"max_sigma_rad": FRAME_FIT_MAX_SIGMA_RAD, "rest_sigma_scale": REST_SIGMA_SCALE,
                "rest_sigma_scale_by_model": rest_scales(), "product_support_px": FRAME_FIT_NETWORK_SUPPORT_PX}
    done = run_rule(args.out, args.recordings, args.bursts, "benchmarks/frame_fit_settle_rule.md", "settle_rad",
                    CANDIDATES, None, settings, "unsettled")
    print(json.dumps(done["choice"], indent=1))


if __name__ == "__main__":
    main()
