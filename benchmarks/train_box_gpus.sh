#!/usr/bin/env bash
# Issue 11's OTR-G1-BoxTrack-v0 runs on a machine of several GPUs: one queue of jobs per GPU, each
# job a benchmarks/train_box.sh run (8192 envs, seed 42) alone on its card, then its report.
# `start` detaches the queues (setsid), so they outlive a 10-minute device command; later commands
# `wait` on them and `pack` what they wrote.
#
#   benchmarks/train_box_gpus.sh start DEADLINE_MIN GPU:JOB[@MIN][,JOB[@MIN]...] ...
#   benchmarks/train_box_gpus.sh wait  SECONDS     # until every queue is done, at most SECONDS; progress
#   benchmarks/train_box_gpus.sh pack  TGZ         # summaries, evaluations, curves, logs, event files;
#                                                  # TGZ_checkpoint_JOB.tar: a deadline run's latest checkpoint
#   benchmarks/train_box_gpus.sh show  JOB...      # a job's reference, train_box.sh knobs and --set overrides
#
# A job learns MIN minutes (rsl-rl's learning time; without @MIN: until the deadline). Every trainer
# still running REPORT_S (240) before the deadline, DEADLINE_MIN after `start`, gets SIGINT (its
# checkpoint is saved), so reports finish in time; a job that could not learn 2 minutes is skipped.
# Jobs (inputs in IN, default out/gin, a git-ignored folder carried with the call):
#   ours           our OMOMO sub3_largebox_003 reference, $IN/sub3_largebox_003.npz (`otr retarget`)
#   ours_ori       ours with a coarse object orientation term (σ 1 rad): a variant, for direction
#   ours_tip       ours_ori plus a termination when the box turns > 1 rad from its reference
#   JOB_q0         any job with the grasp fit's narrowing off (objects.grasp_fit_quantile=0): the demo
#                  is learned that way (docs/results/box.md), not with the fit. E.g. ours_q0, holo_q0, no_contact_q0
#   JOB_xy         any job plus a termination when the torso is > XY_M (0.5) m from its reference horizontally
#                  (anchor_horizontal_error; the demo's walk-in trails by up to 70 cm). E.g. ours_q0_xy
#   ours_wrist     ours with each hand's wrist box counted as the hand (objects.hand_contact_roots: the
#                  wrist_pitch links; their contacts no longer undesired): force pairs, grasp fit, windows
#   holo           Holosoma's reference of the clip, $IN/sub3_largebox_003_mj_w_obj.npz + $IN/largebox.obj
#   no_contact     ours, ABLATION=no_contact          no_object_vel   ours, ABLATION=no_object_vel
#   demo           the `otr demo` box carry, $IN/demo_box_carry.npz (floor to table)
#   throughput     benchmarks/env_throughput.py, OTR-G1-BoxTrack-v0 against OTR-G1-Track-v0, 8192 envs
# Jobs that learn until the deadline also save every 25 iterations and are evaluated at the last
# checkpoint within 10 minutes of learning (eval10*.json): the issue's 10-minute comparison.
# Outputs: out/gpus/JOB (train.log, report.log, summary.md, eval*.json, training_curves.png),
# run folders under runs/gpus/JOB.
#   mkdir -p out/gin; otr retarget ../shared/data/omomo/sub3_largebox_003.pt --object \
#     ../shared/data/objects/largebox.obj --out out/omomo; cp out/omomo/sub3_largebox_003.npz out/gin/
#   otr demo --out out/demo_box; cp out/demo_box/box_carry.npz out/gin/demo_box_carry.npz
#   cp ../shared/data/references/holosoma/sub3_largebox_003_mj_w_obj.npz ../shared/data/objects/largebox.obj out/gin/
# Knobs: SETS (--set overrides for every job, space-separated), NUM_ENVS (8192), EVAL_ENVS (1024),
# SEED (42), REPORT_S (240), DEVICE (cuda), IN (out/gin), OMP_NUM_THREADS (4), XY_M (0.5, the _xy jobs').
# docs/results/box.md's four-GPU table: SETS="$(cat benchmarks/box_anchor_fine.sets)" benchmarks/train_box_gpus.sh start 25 \
#   0:ours 1:holo@10,demo@10 2:no_contact@10,ours_ori 3:no_object_vel@10,throughput
set -uo pipefail
usage="usage: benchmarks/train_box_gpus.sh start DEADLINE_MIN QUEUE... | wait SECONDS | pack TGZ | show JOB..."
IN=${IN:-out/gin}
state=runs/gpus
mkdir -p "$state" out/gpus
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-4} NUM_ENVS=${NUM_ENVS:-8192} SEED=${SEED:-42}
export EVAL_ENVS=${EVAL_ENVS:-1024} VIDEO=0 DEVICE=${DEVICE:-cuda}
report_s=${REPORT_S:-240}
ours=$IN/sub3_largebox_003.npz

base_job() {  # a job without its _q0 / _xy suffixes (they compose with every base job)
  local job=${1%_xy}
  echo "${job%_q0}"
}

reference() {
  case $(base_job "$1") in
    holo) echo "$IN/sub3_largebox_003_mj_w_obj.npz" ;;
    demo) echo "$IN/demo_box_carry.npz" ;;
    *) echo "$ours" ;;
  esac
}

job_env() {  # the train_box.sh knobs of a job (no spaces in a value)
  local base
  base=$(base_job "$1")
  case $base in
    ours|ours_ori|ours_tip|ours_wrist|demo) ;;
    throughput) [ "$1" = throughput ] || { echo "job '$1': throughput takes no suffix" >&2; return 1; } ;;
    holo) echo "OBJECT_MESH=largebox=$IN/largebox.obj" ;;
    no_contact|no_object_vel) echo "ABLATION=$base" ;;
    *) echo "unknown job '$1'" >&2; return 1 ;;
  esac
}

job_sets() {  # the job's --set overrides, after the caller's SETS
  local base
  base=$(base_job "$1")
  echo "${SETS:-}"
  case $base in ours_ori|ours_tip) echo "env.rewards.object_ori_coarse.fn=object_orientation_error_exp \
env.rewards.object_ori_coarse.weight=1.0 env.rewards.object_ori_coarse.params.sigma=1.0" ;; esac
  [ "$base" = ours_tip ] && echo "env.terminations.object_ori.fn=object_orientation_error \
env.terminations.object_ori.params.threshold_rad=1.0"
  case ${1%_xy} in *_q0) echo "env.objects.grasp_fit_quantile=0" ;; esac  # as base_job reads it
  case $1 in *_xy) echo "env.terminations.anchor_xy.fn=anchor_horizontal_error \
env.terminations.anchor_xy.params.threshold_m=${XY_M:-0.5}" ;; esac
  [ "$base" = ours_wrist ] && echo "env.objects.hand_contact_roots=[left_wrist_pitch_link,right_wrist_pitch_link] \
env.rewards.undesired_contacts.params.exclude=[ankle_roll,wrist_yaw,wrist_pitch]"
  return 0
}

learned_iteration() {  # RUN SECONDS: the last checkpoint within SECONDS of learning
  python3 - "$1" "$2" <<'EOF'
import re, sys
from pathlib import Path
from agents.plots import learning_minutes, read_scalars
run, budget = Path(sys.argv[1]), float(sys.argv[2]) / 60
its, minutes = learning_minutes(read_scalars(run))
within = [it for it, m in zip(its, minutes) if m <= budget]
saved = [int(re.sub(r"\D", "", p.stem)) for p in run.glob("model_*.pt")]
print(max((it for it in saved if within and it <= within[-1]), default=""))
EOF
}

run_job() {  # GPU JOB MINUTES(empty: until the deadline)
  local gpu=$1 job=$2 want=$3 deadline out ref left minutes run it
  deadline=$(cat "$state/DEADLINE")
  out=out/gpus/$job; ref=$(reference "$job"); mkdir -p "$out" "runs/gpus/$job"
  left=$(( deadline - report_s - $(date +%s) ))
  if [ "$job" = throughput ]; then
    [ $left -gt 150 ] || { echo "$job: skipped, ${left} s left"; return; }
    CUDA_VISIBLE_DEVICES=$gpu python3 benchmarks/env_throughput.py --task OTR-G1-BoxTrack-v0 --num-envs 8192 \
      --cpu-steps 0 --reference "$ours" --out "$out/env_throughput.json" > "$out/throughput.log" 2>&1
    return
  fi
  # the first job on a card builds the env and compiles MuJoCo-Warp's kernels (~2.5 min), later ones ~1 min
  minutes=$(python3 -c "import sys; l = (int(sys.argv[1]) - int(sys.argv[2])) / 60; \
w = sys.argv[3]; print(round(min(float(w), l) if w else l, 2) if l >= 2 else '')" "$left" "$([ -e "$state/compiled" ] && echo 60 || echo 150)" "$want")
  [ -n "$minutes" ] || { echo "$job: skipped, ${left} s left"; return; }
  echo "$job: GPU $gpu, MINUTES=$minutes, $(date -u +%T)"
  local save=250
  [ -z "$want" ] && save=25 && touch "runs/gpus/$job/RESUMABLE"
  env $(job_env "$job") SETS="$(job_sets "$job")" CUDA_VISIBLE_DEVICES=$gpu MINUTES=$minutes SAVE_INTERVAL=$save RUNS_DIR=runs/gpus/$job \
    benchmarks/train_box.sh train "$out" "$ref" > "$out/train.stdout" 2>&1
  touch "$state/compiled"
  run=$(sed -n 's/^run folder: //p' "$out/train.log" | tail -1)  # also when the deadline's SIGINT cut train_box.sh short
  [ -n "$run" ] && [ -d "$run" ] || { echo "$job: no run folder"; return; }
  echo "$run" > runs/gpus/$job/LATEST_RUN
  echo "$job: trained, $(date -u +%T)"
  env $(job_env "$job") SETS="$(job_sets "$job")" CUDA_VISIBLE_DEVICES=$gpu RUNS_DIR=runs/gpus/$job \
    benchmarks/train_box.sh report "$out" "$ref" > "$out/report.log" 2>&1 &
  if [ -z "$want" ]; then
    it=$(learned_iteration "$run" 600)
    if [ -n "$it" ]; then
      CUDA_VISIBLE_DEVICES=$gpu python3 -m otr_gym.cli evaluate "$run/model_$it.pt" --reference "$ref" --device "$DEVICE" \
        --json "$out/eval10.json" > "$out/eval10.log" 2>&1
      CUDA_VISIBLE_DEVICES=$gpu python3 -m otr_gym.cli evaluate "$run/model_$it.pt" --randomize --reference "$ref" \
        --device "$DEVICE" --num-envs "$EVAL_ENVS" --json "$out/eval10_randomized.json" >> "$out/eval10.log" 2>&1
    fi
  fi
  wait
  echo "$job: reported, $(date -u +%T)"
}

queue() {  # GPU:JOB[@MIN],...
  local gpu=${1%%:*} spec job
  IFS=, read -ra specs <<< "${1#*:}"
  for spec in "${specs[@]}"; do
    job=${spec%@*}
    run_job "$gpu" "$job" "$([ "$spec" = "$job" ] || echo "${spec#*@}")"
  done
}

watchdog() {  # SIGINT to every trainer REPORT_S before the deadline
  local deadline
  deadline=$(cat "$state/DEADLINE")
  while [ "$(date +%s)" -lt $(( deadline - report_s )) ]; do sleep 5; done
  pkill -INT -f "otr_gym.cli train" && echo "deadline: SIGINT to the trainers, $(date -u +%T)"
}

case ${1:-} in
  start)
    [ $# -ge 3 ] || { echo "$usage" >&2; exit 2; }
    echo $(( $(date +%s) + ${2} * 60 )) > "$state/DEADLINE"; shift 2
    rm -f "$state/compiled"
    for q in "$@"; do for spec in $(tr , ' ' <<< "${q#*:}"); do job_env "${spec%@*}" > /dev/null || exit 2; done; done
    # a new session: the device machine ends a command's other processes when it returns
    setsid "$0" _queues "$@" > "$state/queues.log" 2>&1 < /dev/null &
    echo "started $# queues; deadline $(date -u -d @"$(cat "$state/DEADLINE")" +%T)"
    ;;
  _queues)
    shift
    watchdog & dog=$!
    pids=()
    for q in "$@"; do queue "$q" & pids+=($!); done
    wait "${pids[@]}"
    kill "$dog" 2>/dev/null
    echo "all queues done, $(date -u +%T)"
    ;;
  wait)
    t0=$(date +%s)
    while ! grep -q "all queues done" "$state/queues.log" 2>/dev/null && [ $(( $(date +%s) - t0 )) -lt "${2:?$usage}" ]; do
      sleep 10
    done
    cat "$state/queues.log"
    for d in out/gpus/*/; do
      echo "== $d $(grep -E 'Learning iteration|Time elapsed' "$d/train.log" 2>/dev/null | tail -2 | tr -s ' ' | tr '\n' ' ')"
    done
    nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader 2>/dev/null || true
    ;;
  pack)
    # results without checkpoints and ONNX files, plus one tar per run that learned until the
    # deadline holding its latest checkpoint, to resume it elsewhere: a device command returns files
    # of at most 16 MiB each, and one tar of four checkpoints (21 MB) did not come back
    tgz=${2:?$usage}
    mkdir -p "$(dirname "$tgz")"
    tar czf "$tgz" --exclude='*.stdout' --exclude='*.pt' --exclude='*.onnx' out/gpus runs/gpus || exit 1
    for d in runs/gpus/*/; do
      [ -f "$d/RESUMABLE" ] && [ -f "$d/LATEST_RUN" ] || continue
      run=$(cat "$d/LATEST_RUN")
      last=$(python3 -m otr_gym.cli runs latest "$run" 2>/dev/null)  # highest-numbered; nothing when none
      [ -n "$last" ] || { echo "pack: no checkpoint in $run" >&2; continue; }
      tar cf "${tgz%.tgz}_checkpoint_$(basename "$d").tar" "$last" || exit 1
    done
    ls -la "$tgz" "${tgz%.tgz}"_checkpoint_*.tar 2>/dev/null
    for d in out/gpus/*/; do echo "### $d"; cat "$d/summary.md" 2>/dev/null; done
    ;;
  show)  # what a job would train on, without training: reference, train_box.sh knobs, --set overrides
    shift
    [ $# -ge 1 ] || { echo "$usage" >&2; exit 2; }
    for job in "$@"; do
      knobs=$(job_env "$job") || exit 2
      echo "$job"
      echo "  reference: $(reference "$job")"
      echo "  knobs: ${knobs:--}"
      echo "  sets: $(job_sets "$job" | tr '\n' ' ' | tr -s ' ' | sed 's/^ //; s/ $//')"
    done
    ;;
  *) echo "$usage" >&2; exit 2 ;;
esac
