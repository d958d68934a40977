#!/usr/bin/env bash
# The issue-11 comparison on ONE GPU: five OTR-G1-BoxTrack-v0 runs trained concurrently (each its own
# benchmarks/train_box.sh process, 4096 envs, seed 42, RUNS_DIR runs/b5/JOB, OUT_DIR out/b5/JOB):
#   ours           our OMOMO sub3_largebox_003 reference (OURS_REF, default out/refs2/sub3_largebox_003.npz)
#   holo           Holosoma's reference of the same clip ($IN/sub3_largebox_003_mj_w_obj.npz, mesh $IN/largebox.obj)
#   no_contact     ours, ABLATION=no_contact      no_object_vel   ours, ABLATION=no_object_vel
#   demo           the `otr demo` box carry ($IN/demo_box_carry.npz)
#   mocap          ours with the privileged actor (env.observations.actor=mocap: object pose and the
#                  robot's world position observed) — the default actor is perception-free
#
#   benchmarks/train_box_compare.sh TOTAL_MINUTES TRAIN_DEADLINE_S [report [REPORT_DEADLINE_S]]
#
# Each run trains (resuming its run) until it has TOTAL_MINUTES of learning (TOTAL_MINUTES minus
# what it already learned); the trainers get SIGINT (checkpoint saved) TRAIN_DEADLINE_S after the
# start, so one command stays inside a 10-minute limit. With "report": train_box.sh report for all
# five concurrently (EVAL_ENVS=512, VIDEO=0). Everything goes to $OUT/summary.txt and
# $OUT/results.tgz: per job its logs, evaluations, curves, config and TensorBoard event files (JOB/run,
# so `python -m otr_gym.cli plot ours/run holo/run … --labels …` draws the runs on one figure). The
# device machine sees only the working tree, so the inputs are copied into a git-ignored folder IN
# (default out/b5in) carried with the call:
#   mkdir -p out/b5in; otr demo --out out/demo_box; cp out/demo_box/box_carry.npz out/b5in/demo_box_carry.npz
#   cp ../shared/data/references/holosoma/sub3_largebox_003_mj_w_obj.npz ../shared/data/objects/largebox.obj out/b5in/
# Used for docs/results/box.md's "five runs on one GPU" table: `... 6 550` then `... 10 420 report 585`.
# 2026-11-29 (the state-estimation actor): JOBS="ours holo no_contact no_object_vel", `... 6 545`,
# then `... 10 400 report 585` (four ways, ~39k env steps/s each on one H200).
# Knobs: JOBS (subset), OURS_REF (the reference of ours and the ablations), NUM_ENVS (4096),
# EVAL_ENVS (512), DEVICE (cuda), OMP_NUM_THREADS (3), IN.
set -uo pipefail
total=$1; train_deadline=$2; do_report=${3:-}; report_deadline=${4:-590}
t0=$(date +%s)
IN=${IN:-out/b5in}
export DEVICE=${DEVICE:-cuda} PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-3} NUM_ENVS=${NUM_ENVS:-4096} SEED=42
JOBS=${JOBS:-ours holo no_contact no_object_vel demo}
OURS_REF=${OURS_REF:-out/refs2/sub3_largebox_003.npz}
declare -A REF=([ours]=$OURS_REF [no_contact]=$OURS_REF [no_object_vel]=$OURS_REF [mocap]=$OURS_REF
                [holo]=$IN/sub3_largebox_003_mj_w_obj.npz
                [demo]=$IN/demo_box_carry.npz)
declare -A ABL=([no_contact]=no_contact [no_object_vel]=no_object_vel)
declare -A SET=([mocap]=env.observations.actor=mocap)
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null; date -u

descendants() {  # pids below $1 (recursive)
  local c
  for c in $(ps -o pid= --ppid "$1" 2>/dev/null); do echo "$c"; descendants "$c"; done
}
learned() {  # learning minutes of a job's run so far (0 if none)
  local f=runs/b5/$1/LATEST_RUN
  [ -f "$f" ] || { echo 0; return; }
  python3 -c "import sys; from agents.plots import training_summary as t; print(t(sys.argv[1])['learning_minutes'])" \
    "$(cat "$f")" 2>/dev/null || echo 0
}
fix_latest() {  # train_box.sh exits before writing LATEST_RUN when the trainer was SIGINTed
  local run
  run=$(sed -n 's/^run folder: //p' out/b5/$1/train.log 2>/dev/null | tail -1)
  [ -n "$run" ] && [ -d "$run" ] && mkdir -p runs/b5/$1 && echo "$run" > runs/b5/$1/LATEST_RUN
}

declare -A PID
for j in $JOBS; do
  m=$(python3 -c "import sys; print(round(max(0.25, float(sys.argv[1]) - float(sys.argv[2])), 2))" "$total" "$(learned $j)")
  echo "$j: MINUTES=$m (learned so far $(learned $j))"
  if [ "$m" != "0.25" ] || [ ! -f runs/b5/$j/LATEST_RUN ]; then
    ( env ABLATION=${ABL[$j]:-none} SETS="${SET[$j]:-}" \
        $( [ $j = holo ] && echo OBJECT_MESH=largebox=$IN/largebox.obj ) \
        MINUTES=$m RUNS_DIR=runs/b5/$j benchmarks/train_box.sh train out/b5/$j "${REF[$j]}" \
        > /tmp/b5.$j.$t0.log 2>&1 ) &
    PID[$j]=$!
    sleep 5
  fi
done
while :; do
  alive=0
  for j in "${!PID[@]}"; do kill -0 "${PID[$j]}" 2>/dev/null && alive=1; done
  [ $alive = 0 ] && break
  if [ $(( $(date +%s) - t0 )) -ge "$train_deadline" ]; then
    for j in "${!PID[@]}"; do
      for c in $(descendants "${PID[$j]}"); do
        if ps -o args= -p "$c" 2>/dev/null | grep -q "otr_gym.cli train"; then echo "deadline: SIGINT $j ($c)"; kill -INT "$c"; fi
      done
    done
    break
  fi
  sleep 3
done
wait
echo "training done at +$(( $(date +%s) - t0 )) s"
nvidia-smi --query-gpu=memory.used --format=csv,noheader 2>/dev/null
for j in $JOBS; do
  fix_latest $j
  echo "== $j: learned $(learned $j) min; $(grep -E 'training stopped|latest checkpoint|Error|error' /tmp/b5.$j.$t0.log 2>/dev/null | tail -3)"
  grep -E "Learning iteration|Mean reward|Mean episode length|Computation" /tmp/b5.$j.$t0.log 2>/dev/null | tail -4
done

if [ "$do_report" = report ]; then
  declare -A RP
  for j in $JOBS; do
    ( env $( [ $j = holo ] && echo OBJECT_MESH=largebox=$IN/largebox.obj ) EVAL_ENVS=${EVAL_ENVS:-512} VIDEO=0 \
        RUNS_DIR=runs/b5/$j benchmarks/train_box.sh report out/b5/$j "${REF[$j]}" > out/b5/$j/report.log 2>&1 ) &
    RP[$j]=$!
  done
  while :; do
    alive=0
    for j in "${!RP[@]}"; do kill -0 "${RP[$j]}" 2>/dev/null && alive=1; done
    [ $alive = 0 ] && break
    if [ $(( $(date +%s) - t0 )) -ge "$report_deadline" ]; then echo "report deadline reached"; break; fi
    sleep 3
  done
  echo "report done at +$(( $(date +%s) - t0 )) s"
fi

for j in $JOBS; do
  mkdir -p /tmp/res/$j
  cp /tmp/b5.$j.*.log /tmp/res/$j/ 2>/dev/null
  run=$(cat runs/b5/$j/LATEST_RUN 2>/dev/null)
  for f in summary.md eval.json eval_randomized.json training_curves.png report.log policy.onnx; do
    cp out/b5/$j/$f /tmp/res/$j/ 2>/dev/null
  done
  if [ -n "$run" ]; then
    cp "$run/training_summary.json" "$run/config.yaml" /tmp/res/$j/ 2>/dev/null
    mkdir -p /tmp/res/$j/run && cp "$run"/events.out.tfevents.* /tmp/res/$j/run/ 2>/dev/null
  fi
  { echo "### $j (run $run)"; cat out/b5/$j/summary.md 2>/dev/null || echo "(no summary)"; tail -3 out/b5/$j/report.log 2>/dev/null; } >> "$OUT/summary.txt"
done
tar czf "$OUT/results.tgz" -C /tmp/res .
cat "$OUT/summary.txt"
echo "all done at +$(( $(date +%s) - t0 )) s"
