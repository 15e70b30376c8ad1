#!/usr/bin/env bash
# Set up, then run the main job on the embedded default: render a small twin recording of a
# rotating gear and replay it through the default decoder into out/demo.rrd.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export MPLBACKEND=Agg
if [ ! -f out/demo-recording/recording.json ] || ! grep -q '"finished": true' out/demo-recording/recording.json; then
  .venv/bin/gearscan twin render out/demo-recording --motion nonuniform:0.1,1.6 --bursts 6 --overwrite
fi
.venv/bin/gearscan replay out/demo-recording --save out/demo.rrd --metrics out/demo-metrics.json
echo "open the result with: .venv/bin/rerun out/demo.rrd"
