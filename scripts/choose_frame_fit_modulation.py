"""Choose the frame fit's modulation test on VAL stretches.

    python scripts/choose_frame_fit_modulation.py [--out benchmarks/frame_fit_modulation_val.json]

Rule, written before this ran: ``benchmarks/frame_fit_modulation_rule.md``. The 16 cells of the settle rule
(``scripts/choose_frame_fit_settle.py``: four seeds, both pattern orders, two models), each replayed once at the path's
shipped settings (the settle test included); every candidate refits the same fused cloud, scored against the twin's
true surface as ``benchmarks/frame_fit_heldout.py`` scores. Cells already in ``--out`` are kept (a stopped run resumes).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "scripts"))
from choose_frame_fit_settle import rest_scales, run_rule  # noqa: E402  (the settle rule's cells, scoring and decision)

FIELD = "modulation_ratio"
CANDIDATES: tuple[float | None, ...] = (None, 1.0)  # None: no test; 1.0: the physical bound B <= A


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "frame_fit_modulation_val.json")
    ap.add_argument("--recordings", type=Path, default=ROOT / "out" / "fused_support_val")
    ap.add_argument("--bursts", type=int, default=60)
    args = ap.parse_args()

    from gearscan.recon.measure import FRAME_FIT_MAX_SIGMA_RAD, FRAME_FIT_NETWORK_SUPPORT_PX
    from gearscan.recon.track import REST_SIGMA_SCALE, SETTLE_RAD

    settings = {"max_sigma_rad": FRAME_FIT_MAX_SIGMA_RAD, "rest_sigma_scale": REST_SIGMA_SCALE,
                "rest_sigma_scale_by_model": rest_scales(), "product_support_px": FRAME_FIT_NETWORK_SUPPORT_PX,
                "settle_rad": SETTLE_RAD}
    done = run_rule(args.out, args.recordings, args.bursts, "benchmarks/frame_fit_modulation_rule.md", FIELD,
                    CANDIDATES, {FIELD: None}, settings, "implausible")
    print(json.dumps(done["choice"], indent=1))


if __name__ == "__main__":
    main()
