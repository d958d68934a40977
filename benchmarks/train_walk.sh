#!/usr/bin/env bash
# GPU recipe: train a walking tracker within a wall-clock budget, then evaluate and plot.
#
#   benchmarks/train_walk.sh all    OUT_DIR [REFERENCE]   # train, then report
#   benchmarks/train_walk.sh train  OUT_DIR [REFERENCE]   # train MINUTES more (resumes RUNS_DIR's run)
#   benchmarks/train_walk.sh report OUT_DIR [REFERENCE]   # figures, evaluation, ONNX of that run
#
# REFERENCE: a walking reference .npz (or a folder of clips); without it a procedural walk
# (agents/procedural.py: 12 steps of 25 cm, 7 s) is generated into RUNS_DIR.
# "train" twice = one run trained in two sessions (same curves): use it where one command may
# not last MINUTES plus the 2-3 min of first warp compilation.
#
# Knobs (environment): NUM_ENVS (4096), MINUTES (10: the learning loop of this session; env
# build and compilation come on top), DEVICE (cuda), SAVE_INTERVAL (100), EVAL_ENVS (envs of
# the randomised evaluation, default 256 per clip), RUNS_DIR (run
# folders with all checkpoints, default OUT_DIR/runs; put it outside OUT_DIR to fetch only the
# figures), PYTHON (python3).
#
# OUT_DIR receives: train.log; from "report": training_curves.png (reward, episode length, FPS,
# MPJPE, success vs iteration), training_summary.json (iterations, median FPS, learning
# minutes), eval.json + eval_mpjpe.png (every checkpoint; frame 0, no randomisation, mean
# action), eval_randomized.json (last checkpoint, 256 envs keeping the training randomisation:
# a success *rate*), policy.onnx.
set -euo pipefail
stage=${1:?usage: benchmarks/train_walk.sh all|train|report OUT_DIR [REFERENCE]}
out=${2:?usage: benchmarks/train_walk.sh all|train|report OUT_DIR [REFERENCE]}
ref=${3:-}
py=${PYTHON:-python3}
device=${DEVICE:-cuda}
runs_dir=${RUNS_DIR:-$out/runs}
latest="$runs_dir/LATEST_RUN"
export PYTHONUNBUFFERED=1
mkdir -p "$out" "$runs_dir"

if [ -z "$ref" ]; then
  ref="$runs_dir/walk_procedural.npz"
  [ -f "$ref" ] || "$py" -m otr_gym.cli procedural walk "$ref"
fi

train() {
  local from=()
  [ -f "$latest" ] && from=(--resume "$(cat "$latest")")
  "$py" -m otr_gym.cli train --reference "$ref" --num-envs "${NUM_ENVS:-4096}" --device "$device" \
    --max-minutes "${MINUTES:-10}" --save-interval "${SAVE_INTERVAL:-100}" --log-dir "$runs_dir" \
    ${from[@]+"${from[@]}"} 2>&1 | tee -a "$out/train.log"
  local run
  run=$(sed -n 's/^run folder: //p' "$out/train.log" | tail -1)
  [ -d "$run" ] || { echo "no run folder in $out/train.log" >&2; exit 1; }
  echo "$run" > "$latest"
}

report() {
  [ -f "$latest" ] || { echo "$latest: no trained run (run the train stage first)" >&2; exit 1; }
  local run
  run=$(cat "$latest")
  "$py" -m otr_gym.cli plot "$run" --png "$out/training_curves.png" --json "$out/training_summary.json"
  "$py" -m otr_gym.cli evaluate "$run" --reference "$ref" --device "$device" \
    --json "$out/eval.json" --plot "$out/eval_mpjpe.png"
  "$py" -m otr_gym.cli evaluate "$run" --last --randomize --reference "$ref" --device "$device" \
    ${EVAL_ENVS:+--num-envs "$EVAL_ENVS"} --json "$out/eval_randomized.json"
  "$py" -m otr_gym.cli export "$run" --onnx "$out/policy.onnx"
  echo "run folder: $run"
}

case "$stage" in
  all) train; report ;;
  train) train ;;
  report) report ;;
  *) echo "unknown stage '$stage' (all | train | report)" >&2; exit 2 ;;
esac
