#!/usr/bin/env bash
# A lent GPU machine's inference benchmark (benchmarks/inference_speed_gpu.py), for a lease's time left after
# training. The machine has torch, numpy, scipy and OpenCV, which is all inference needs: nothing is carried.
#
#   run(command="bash scripts/lease_bench.sh", timeout_s=200)
#
# Comes back in $OUT: inference_speed_gpu.md, inference_speed_gpu.json and bench.log (written as it goes).
set -uo pipefail
: "${OUT:?OUT: expected the folder whose files come back (the device tool sets it)}"
PY=${LEASE_PYTHON:-python3}
WORK=${LEASE_WORK:-/tmp/lease}
mkdir -p "$OUT" "$WORK"
cd "$(dirname "$0")/.."
{
  "$PY" -P scripts/lease_layout.py "$WORK/site" || exit 2
  PYTHONPATH="$WORK/site${PYTHONPATH:+:$PYTHONPATH}" timeout -k 5 "${LEASE_BENCH_S:-170}" "$PY" -P \
    benchmarks/inference_speed_gpu.py --device "${LEASE_DEVICE:-cuda}" --out "$OUT" ${LEASE_BENCH_ARGS:-}
} 2>&1 | tee "$OUT/bench.log"
exit "${PIPESTATUS[0]}"
