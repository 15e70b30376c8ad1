#!/usr/bin/env bash
# The one command of a GPU lease: install .lease (scripts/lease_carry.sh), render the twin data, continue the
# shipped model on the GPU with the project's one command (scripts/reproduce_model.py), and leave in $OUT what
# comes back. Sized for the device tool's limits: a command runs at most 600 s, what comes back is at most 8 files
# of 16 MiB two folders down, and a session has 15 device minutes in all (a machine's start included), so there is
# one try:
#
#   bash scripts/lease_carry.sh                                   # here, once (about 2 min)
#   run(command="bash scripts/lease_train.sh", carry=[".lease"], timeout_s=600)
#
# What it trains (each a LEASE_* variable; the defaults are the plan in inference/weights/V6_MODEL_CARD.md, "The next
# GPU lease"; MODEL_CARD.md says what session 39's run of it taught): the shipped default
# (inference/weights/default.safetensors: v6 until session 39, v9 since) continued on v6's data (scale 0.7) plus one repeat of the dense radial
# set, with the outside-mask term (--outside-weight 0.05 --val-objective full, benchmarks/outside_loss_val.md),
# training bursts drawn on the GPU (--bank; inference/burst_bank.py) at batch 128. The sigma map is not fitted
# there (--no-calibrate): `gearscan calibrate-uncertainty` refits it here on val, as for every shipped model.
#
# LEASE_TASK=default-rig runs the default-rig option's command instead (scripts/default_rig_model.py: v9 fine-tuned on
# the product's default rig, rendered there with train gears, by the same deadline; no step profile, not compiled):
# back come lease.log, best.*, metrics.csv and default_rig.json (the run's record).
#
# Comes back in $OUT (8 files): lease.log (everything printed, written as it goes, so a killed run still
# reports), best.* (the run's final model: stage 2's best; reproduce.json's stages_run says whether stage 2 ran),
# stage1_best.*, metrics.csv, reproduce.json and train_step_profile.md (step time by width and batch without a
# loader, eager and compiled: what bounds a step there; the compiled row also decides whether the training is
# compiled). Exit 2: the install failed; 3: the preflight did, or no time was left; 4: the
# backstop timeout stopped the training (its last and stage1_best weights come back).
set -uo pipefail
T0=$(date +%s)
TASK=${LEASE_TASK:-shipped}
case "$TASK" in shipped|default-rig) ;; *) echo "LEASE_TASK=$TASK: expected shipped or default-rig"; exit 3 ;; esac
: "${OUT:?OUT: expected the folder whose files come back (the device tool sets it)}"
LIMIT_S=${LEASE_LIMIT_S:-575}  # this script's whole run, under run()'s 600 s
PY=${LEASE_PYTHON:-python3}
DEVICE=${LEASE_DEVICE:-cuda}
WORK=${LEASE_WORK:-/tmp/lease}
mkdir -p "$OUT" "$WORK"
exec > >(tee "$OUT/lease.log") 2>&1
tee_pid=$!
finish() {  # the log is complete before the tool collects $OUT; 124 (the backstop timeout) is not the tool's own
  local code=$1
  [ "$code" = 124 ] && code=4
  exec >&- 2>&-
  wait "$tee_pid" 2>/dev/null
  exit "$code"
}
cd "$(dirname "$0")/.."
left() { echo $((LIMIT_S - ($(date +%s) - T0))); }
say() { echo "[lease $(($(date +%s) - T0)) s] $*"; }

# 1. what the machine lacks: open3d (CPU build), pydantic, triangle, the libraries open3d links, gearscan itself
site="$WORK/site"  # python -P below: the tree's own gearscan/ lacks the mapped subpackages and must not shadow them
if ! "$PY" -P -c "import open3d" 2>/dev/null; then
  [ -f .lease/open3d.tar.xz ] || { say "no .lease/open3d.tar.xz: run scripts/lease_carry.sh and carry .lease"; finish 2; }
  mkdir -p "$site" "$WORK/libs"
  "$PY" -m pip install -q --no-index --no-deps --no-compile --target "$site" .lease/whl/*.whl || finish 2
  # Python's own lzma, not the machine's xz (which its image need not have)
  "$PY" -P -c 'import sys, tarfile; [tarfile.open(a).extractall(d, filter="data") for a, d in zip(sys.argv[1::2], sys.argv[2::2])]' \
    .lease/open3d.tar.xz "$site" .lease/lib.tar.xz "$WORK" || finish 2
  known=$(ldconfig -p)  # read once: grep -q on a pipe can cut ldconfig off (SIGPIPE) and read as "missing"
  for lib in "$WORK"/lib/*; do  # only those the machine lacks: its own stay first
    grep -q "^[[:space:]]$(basename "$lib") " <<< "$known" || ln -sf "$lib" "$WORK/libs/"
  done
  export LD_LIBRARY_PATH="$WORK/libs${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  say "carried libraries used (the machine lacks them): $(ls "$WORK/libs" | tr '\n' ' ')"
fi
export PYTHONPATH="$site${PYTHONPATH:+:$PYTHONPATH}"
if [ -n "${LEASE_LINK:-}" ] || ! "$PY" -P -c "import gearscan.twin.render" 2>/dev/null; then
  # gearscan from this tree, laid out by pyproject's package map as links (no build on the machine)
  say "gearscan laid out as links in $site"
  "$PY" -P scripts/lease_layout.py "$site" || finish 2
fi
# preflight: the renderer casts, the device is there, the weights to continue load
"$PY" -P - "$DEVICE" <<'EOF' || { say "preflight failed: nothing trained"; finish 3; }
import sys
import torch
from gearscan.core.gear import GearSpec
from gearscan.twin.dataset import DatasetSpec, scene_for
from gearscan.twin.render import TwinRenderer
device = sys.argv[1]
if device == "cuda" and not torch.cuda.is_available():
    raise SystemExit("preflight: --device cuda but torch sees no GPU")
spec = DatasetSpec(gears=[GearSpec(teeth=30)], width=64, height=64)  # the default rig
rig, optics, gear, _ = scene_for(spec, 0)
hit = TwinRenderer(rig, gear, optics).surface(0.0)
import gearscan
print(f"preflight: torch {torch.__version__}, {torch.cuda.get_device_name() if device == 'cuda' else 'cpu'}, "
      f"{sys.version.split()[0]}; gearscan from {gearscan.__path__[0]}; the twin casts rays ({type(hit).__name__})")
EOF
say "installed, $(left) s left"

# 1b. what bounds a training step on this GPU, without any loader, eager and compiled at the training's width, batch
# and crop (benchmarks/train_step_profile.py; about 120 s at most; the rows are written as they come, so a cut-off
# profile still reports)
batch=${LEASE_BATCH:-128}
compile=${LEASE_COMPILE:-auto}
if [ "$TASK" = default-rig ]; then
  # the option's fine-tune: render the default rig with train gears, continue v9 on it to the deadline
  total=$(($(left) - 25))
  [ "$total" -ge 120 ] || { say "only $total s left for render and training: nothing trained"; finish 3; }
  minutes=$(awk "BEGIN { printf \"%.3f\", $total / 60 }")
  run="$WORK/run"
  timeout --signal=TERM --kill-after=5 "$((total + 15))" "$PY" -P scripts/default_rig_model.py \
    --device "$DEVICE" --bank --jobs "${LEASE_JOBS:-16}" --data "$WORK/data" --out "$run" \
    --init "${LEASE_INIT:-inference/weights/default.safetensors}" --gears "${LEASE_GEARS:-32}" \
    --start-points "${LEASE_START_POINTS:-16}" --seed 3301 --batch "$batch" --lr "${LEASE_LR:-1e-3}" \
    --schedule cosine-time --deadline-minutes "$minutes" --steps-per-epoch "${LEASE_STEPS_PER_EPOCH:-200}" \
    --precision auto --threads "${LEASE_THREADS:-4}" ${LEASE_EXTRA:-}
  status=$?
  say "default_rig_model.py exited $status, $(left) s left"
  for f in best.safetensors best.json metrics.csv default_rig.json; do [ -f "$run/$f" ] && cp "$run/$f" "$OUT/"; done
  [ -f "$run/best.safetensors" ] || cp "$run/last.safetensors" "$run/last.json" "$OUT/" 2>/dev/null
  ls -l "$OUT"
  finish $status
fi
case "$compile" in auto|0|1) ;; *) say "LEASE_COMPILE=$compile: expected auto, 0 or 1"; finish 3 ;; esac
read -r pw pb <<< "${LEASE_PROFILE:-8,32 32,128,512}"
timeout -k 5 120 "$PY" benchmarks/train_step_profile.py --device "$DEVICE" --widths "$pw" --batches "$pb" \
  --crop "${LEASE_CROP:-128}" $([ "$compile" = auto ] && echo --compiled "8x$batch") \
  --threads "${LEASE_THREADS:-4}" --out "$WORK/train_step_profile" \
  || say "step profile failed or was cut off; training goes on"
cp "$WORK/train_step_profile.md" "$OUT/" 2>/dev/null  # its rows are in the log too
# train compiled if the profile measured it worth it: a compiled step >= 1.25x faster whose saving over the training
# (what is left less about 150 s for render, probe and close) pays for its 3 compiles (the probe, stage 1 and the
# dropout stage, whose graph differs). LEASE_COMPILE=1 or 0 decides instead.
if [ "$compile" = auto ]; then
  compile=$("$PY" benchmarks/train_step_profile.py --worth-compiling "$WORK/train_step_profile.json" \
    --compiled "8x$batch" --train-seconds "$(($(left) - 150))") || { say "no compile decision: training eagerly"; compile=0; }
fi
say "training compiled: $([ "$compile" = 1 ] && echo yes || echo no) (LEASE_COMPILE=${LEASE_COMPILE:-auto})"

# 2. render + train within what is left: the command ends its training by a deadline 20 s before its own end
# (--total-minutes), 25 s before this script's; the timeout 15 s later is only the backstop
run="$WORK/run"
total=$(($(left) - 25))
[ "$total" -ge 120 ] || { say "only $total s left for render and training: nothing trained"; finish 3; }
minutes=$(awk "BEGIN { printf \"%.3f\", $total / 60 }")
timeout --signal=TERM --kill-after=5 "$((total + 15))" "$PY" scripts/reproduce_model.py \
  --device "$DEVICE" --data "$WORK/data" --out "$run" --jobs "${LEASE_JOBS:-16}" \
  --scale "${LEASE_SCALE:-0.7}" --dense-radial "${LEASE_DENSE:-1}" --size "${LEASE_SIZE:-256}" \
  --crop "${LEASE_CROP:-128}" --width 8 --batch "$batch" --lr "${LEASE_LR:-1e-3}" \
  --init "${LEASE_INIT:-inference/weights/default.safetensors}" --outside-weight 0.05 --val-objective full \
  --threads "${LEASE_THREADS:-4}" --workers 0 --bank --no-calibrate --total-minutes "$minutes" \
  --probe-steps "${LEASE_PROBE_STEPS:-50}" $([ "$compile" = 1 ] && echo --compile) ${LEASE_EXTRA:-}
status=$?
say "reproduce_model.py exited $status, $(left) s left"

# 3. what comes back (at most 8 files; each model with its JSON, which loading needs)
for f in best.safetensors best.json stage1_best.safetensors stage1_best.json metrics.csv reproduce.json; do
  [ -f "$run/$f" ] && cp "$run/$f" "$OUT/"
done
[ -f "$run/best.safetensors" ] || cp "$run/last.safetensors" "$run/last.json" "$OUT/" 2>/dev/null
ls -l "$OUT"
finish $status
