"""Write the product calibration of the twin's default rig from its board views placed as a hand places them.

    .venv/bin/python scripts/hand_placed_rig.py SEED OUT.json

The shipped board views jittered by ``SEED`` (``benchmarks/calibration_accuracy.write_hand_placed_rig``), rendered with that
render seed, calibrated by ``recon.calibration.calibrate_rig`` and written as ``gearscan calibrate`` writes a rig.
Prints the 20 mm cylinder check against the truth and the calibration's stated radius uncertainty. Session 56 wrote
``SEED 68`` for ``benchmarks/inspect_calibrated_rig_worst_report.md`` (the worst of seeds 51-70).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from calibration_accuracy import write_hand_placed_rig  # noqa: E402


def main() -> None:
    if len(sys.argv) != 3:
        raise SystemExit(__doc__.split("\n\n")[1].strip())
    out = Path(sys.argv[2])
    got = write_hand_placed_rig(int(sys.argv[1]), out)
    print(f"wrote {out}: {got['cylinder']}; stated radius u {got['stated_radius_um']} um")


if __name__ == "__main__":
    main()
