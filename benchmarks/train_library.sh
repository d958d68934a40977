#!/usr/bin/env bash
# GPU recipes of the motion-library issue: real mocap clips, one policy per clip or one for a
# library, and the 1- vs N-GPU comparison. Every stage runs unattended from the repository root.
#
#   benchmarks/train_library.sh prepare REFS_DIR                # the library's references (CPU, ~3 min, resumable)
#   benchmarks/train_library.sh train   OUT_DIR REFERENCE...    # MINUTES more learning (resumes OUT_DIR's run)
#   benchmarks/train_library.sh report  OUT_DIR REFERENCE...    # curves (overall + per clip), evaluation, ONNX
#   benchmarks/train_library.sh scaling OUT_DIR REFERENCE...    # 1 vs GPUS GPUs: env steps/s, iteration time
#   benchmarks/train_library.sh carry   OUT_DIR                 # OUT_DIR/run.tar.gz: the run with its latest checkpoint
#
# REFERENCE: one clip (.npz), a folder of clips, or a clip list (.txt); several are one library.
#
# prepare writes into REFS_DIR (skipping what exists): the two AMASS clips retargeted by us
# (smplh_walk_jog_turn, smplx_steps_deep_squat), the three OMOMO clips retargeted by us with
# their objects (OTR-G1-Track-v0 tracks their robot motion; the box task uses them whole),
# Holosoma's crawl reference (a copy, holosoma_crawl.npz, so the folder travels whole to a GPU
# machine), and the procedural walk and crawl
# retargeted by `otr demo` — 8 clips, the library of the issue. The crawl was recorded on a
# slope: prepare copies it (terrain_slope.obj) to REFS_DIR/holosoma_crawl_terrain.obj and writes
# REFS_DIR/terrain.sets, one `--set` per line giving the crawl its terrain
# (env.terrain.meshes.holosoma_crawl=REFS_DIR/holosoma_crawl_terrain.obj, README "Terrain"),
# and prints it. train and scaling add the terrain.sets of every REFERENCE that is a folder to
# SETS, so `train OUT_DIR REFS_DIR` simulates the slope (the run records it, absolute, so report,
# evaluate and play do too). The crawl alone:
#   SETS="$(cat REFS_DIR/terrain.sets)" benchmarks/train_library.sh train out/crawl REFS_DIR/holosoma_crawl.npz
# Single clips for (a) are then REFS_DIR/smplh_walk_jog_turn.npz and REFS_DIR/smplx_steps_deep_squat.npz.
#
# (a) One AMASS clip, 20 minutes of learning under a 10-minute limit per command: the first call
#     also builds the env and compiles MuJoCo-Warp (2-3 min), so
#       MINUTES=7 benchmarks/train_library.sh train out/jog REFS/smplh_walk_jog_turn.npz
#       MINUTES=8 benchmarks/train_library.sh train out/jog REFS/smplh_walk_jog_turn.npz   # twice
#       benchmarks/train_library.sh report out/jog REFS/smplh_walk_jog_turn.npz
# (b) The library: the same with REFS_DIR as REFERENCE (30 minutes: MINUTES=7, then 8 three times).
#     On to another machine, or back from one (a device command returns files of at most 16 MiB):
#     `carry` writes OUT_DIR/run.tar.gz (RUNS_DIR's LATEST_RUN, the run folder without checkpoints,
#     its latest checkpoint; 7.7 MB for the 8-clip library at 30 min); `tar xf` it in the repository root.
#     It also packs a run that is still training (detached: benchmarks/detached.sh), from train.log.
# (c) Issue 16 (a 2-GPU host): benchmarks/train_library.sh scaling out/scaling REFS/smplh_walk_jog_turn.npz
#
# Knobs (environment): NUM_ENVS (4096, per GPU), MINUTES (8), GPUS (1 for train; 2 for scaling),
# DEVICE (cuda), SAVE_INTERVAL (100), SEED (42), SETS (space-separated `--set KEY=VALUE` overrides,
# e.g. "env.terminations.anchor_height.params.threshold_m=0.5"), EVAL_ENVS (randomised
# evaluation envs in all, spread evenly over the clips; default 256 per clip), ITERS (scaling: iterations per GPU count, 150),
# SCALING_MINUTES (scaling: also train this long on each GPU count and evaluate both; 0 = skip),
# DATA (../shared/data, or shared/data in the checkout), RUNS_DIR (OUT_DIR/runs), PYTHON (python3),
# EVERY (carry: also OUT_DIR/run_policies.tar.gz, policy-only copies of every EVERY-th checkpoint, ~1 MB
# each; extract both and `otr evaluate RUN --plot P` shows when each clip was learned; 0 = off; report:
# with EVERY, eval.json holds those checkpoints and the latest, from frame 0, drawn in progress.png).
# BeyondMimic's default actor (with state estimation: + reference-anchor position and pelvis
# linear velocity, 160 dims; not deployable by agents.deploy, which has no state estimator):
#   SETS="$(cat benchmarks/state_estimation.sets)" NUM_ENVS=8192 MINUTES=5.5 benchmarks/train_library.sh train …
#
# OUT_DIR receives: train.log; from report: training_curves.png, clip_curves.png (success,
# MPJPE, segment length, start probability per clip), training_summary.json, failure_bins.png and
# failure_bins.json (where in each clip the training episodes fail), eval.json (frame 0,
# no randomisation, mean action; per clip and overall), eval_randomized.json, summary.md (both,
# per clip), policy.onnx; from scaling: scaling.md and scaling.json.
set -euo pipefail
usage="usage: benchmarks/train_library.sh prepare REFS_DIR | train|report|scaling OUT_DIR REFERENCE... | carry OUT_DIR"
stage=${1:?$usage}
out=${2:?$usage}
shift 2
refs=("$@")
py=${PYTHON:-python3}
device=${DEVICE:-cuda}
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}

sets=()
for item in ${SETS:-}; do sets+=(--set "$item"); done
for ref in ${refs[@]+"${refs[@]}"}; do  # a folder's terrain.sets (written by prepare)
  [ -f "$ref/terrain.sets" ] || continue
  while read -r item; do
    if [ -n "$item" ]; then sets+=(--set "$item"); fi
  done < "$ref/terrain.sets"
done

prepare() {
  local data=${DATA:-}
  if [ -z "$data" ]; then
    for d in ../shared/data shared/data; do [ -f "$d/README.md" ] && data=$d && break; done
  fi
  [ -n "$data" ] || { echo "no data folder (set DATA=/path/to/shared/data)" >&2; exit 1; }
  mkdir -p "$out"
  "$py" -m otr_gym.cli retarget "$data/amass/smplh_walk_jog_turn.npz" "$data/amass/smplx_steps_deep_squat.npz" \
    --out "$out"
  for clip in sub3_largebox_003:largebox sub2_largetable_004:largetable sub2_woodchair_000:woodchair; do
    "$py" -m otr_gym.cli retarget "$data/omomo/${clip%%:*}.pt" --object "$data/objects/${clip##*:}.obj" --out "$out"
  done
  local holosoma
  holosoma=$(cd "$data/references/holosoma" && pwd)
  [ -f "$out/holosoma_crawl.npz" ] || cp "$holosoma/motion_crawl_slope.npz" "$out/holosoma_crawl.npz"
  cp "$holosoma/terrain_slope.obj" "$out/holosoma_crawl_terrain.obj"
  echo "env.terrain.meshes.holosoma_crawl=$out/holosoma_crawl_terrain.obj" > "$out/terrain.sets"
  local tmp
  tmp=$(mktemp -d)
  for kind in walk crawl; do
    [ -f "$out/synthetic_$kind.npz" ] && continue
    "$py" -m otr_gym.cli demo --kind "$kind" --out "$tmp/$kind" > "$tmp/$kind.log"
    cp "$tmp/$kind/$kind.npz" "$out/synthetic_$kind.npz"
  done
  rm -rf "$tmp"
  ls -1 "$out"/*.npz
  echo "terrain ($out/terrain.sets, added to SETS by train and scaling): $(cat "$out/terrain.sets")"
}

runs_dir=${RUNS_DIR:-$out/runs}
latest="$runs_dir/LATEST_RUN"

run_folder_of() {  # the last "run folder:" line of a log
  sed -n 's/^run folder: //p' "$1" | tail -1
}

train() {
  mkdir -p "$out" "$runs_dir"
  local from=()
  [ -f "$latest" ] && from=(--resume "$(cat "$latest")")
  "$py" -m otr_gym.cli train --reference "${refs[@]}" --num-envs "${NUM_ENVS:-4096}" --device "$device" \
    --gpus "${GPUS:-1}" --max-minutes "${MINUTES:-8}" --save-interval "${SAVE_INTERVAL:-100}" --seed "${SEED:-42}" \
    --log-dir "$runs_dir" ${from[@]+"${from[@]}"} ${sets[@]+"${sets[@]}"} 2>&1 | tee -a "$out/train.log"
  local run
  run=$(run_folder_of "$out/train.log")
  [ -d "$run" ] || { echo "no run folder in $out/train.log" >&2; exit 1; }
  echo "$run" > "$latest"
}

report() {
  [ -f "$latest" ] || { echo "$latest: no trained run (run the train stage first)" >&2; exit 1; }
  local run
  run=$(cat "$latest")
  "$py" -m otr_gym.cli plot "$run" --png "$out/training_curves.png" --clips-png "$out/clip_curves.png" \
    --json "$out/training_summary.json"
  "$py" -m otr_gym.cli failure-map "$run" --png "$out/failure_bins.png" --json "$out/failure_bins.json"
  if [ "${EVERY:-0}" -gt 0 ]; then  # how the policy got there: every EVERY-th checkpoint and the latest, from frame 0
    "$py" -m otr_gym.cli evaluate "$run" --every "$EVERY" --device "$device" --json "$out/eval.json" \
      --plot "$out/progress.png"
  else
    "$py" -m otr_gym.cli evaluate "$run" --last --device "$device" --json "$out/eval.json"
  fi
  "$py" -m otr_gym.cli evaluate "$run" --last --randomize --device "$device" ${EVAL_ENVS:+--num-envs "$EVAL_ENVS"} \
    --json "$out/eval_randomized.json"
  "$py" -m otr_gym.cli export "$run" --onnx "$out/policy.onnx"
  "$py" - "$out" <<'EOF'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
frame0 = json.loads((out / "eval.json").read_text())["final"]
rand = json.loads((out / "eval_randomized.json").read_text())["final"]
summary = json.loads((out / "training_summary.json").read_text())
rows = {c["clip"]: c for c in rand["clips"]}
def ended(c):  # the terminations that ended a clip's episodes (frame 0 / randomised)
    return ", ".join(f"{name} {n}" for name, n in c.get("ended_by", {}).items()) or "–"
lines = [f"run {summary['run']}: {summary['iterations']} iterations, {summary['learning_minutes']:.1f} min of learning, "
         f"median {summary['median_fps']:,.0f} env steps/s", "",
         "| clip | frames | success (frame 0) | MPJPE mm | heading-aligned mm | randomised success | randomised MPJPE mm "
         "| ended by (frame 0 / randomised) |",
         "|---|---|---|---|---|---|---|---|"]
for c in frame0["clips"]:
    r = rows.get(c["clip"], {})
    lines.append(f"| {c['clip']} | {c['frames']} | {100 * c['success_rate']:.1f} % | {c['mpjpe_mm']:.1f} | "
                 f"{c.get('mpjpe_heading_aligned_mm', float('nan')):.1f} | "
                 f"{100 * r.get('success_rate', float('nan')):.1f} % | {r.get('mpjpe_mm', float('nan')):.1f} | "
                 f"{ended(c)} / {ended(r)} |")
lines.append(f"| **all** | {frame0['frames']} | {100 * frame0['success_rate']:.1f} % | {frame0['mpjpe_mm']:.1f} | "
             f"{frame0.get('mpjpe_heading_aligned_mm', float('nan')):.1f} | "
             f"{100 * rand['success_rate']:.1f} % | {rand['mpjpe_mm']:.1f} | {ended(frame0)} / {ended(rand)} |")
(out / "summary.md").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
EOF
  echo "run folder: $run"
}

scaling() {
  mkdir -p "$out" "$runs_dir"
  local gpus=${GPUS:-2} iters=${ITERS:-150} minutes=${SCALING_MINUTES:-0}
  local counts=(1 "$gpus")
  for g in "${counts[@]}"; do
    local log="$out/scaling_g$g.log"
    : > "$log"
    "$py" -m otr_gym.cli train --reference "${refs[@]}" --num-envs "${NUM_ENVS:-4096}" --device "$device" --gpus "$g" \
      --iterations "$iters" --save-interval 100000 --seed "${SEED:-42}" --log-dir "$runs_dir/throughput_g$g" \
      ${sets[@]+"${sets[@]}"} 2>&1 | tee -a "$log"
    run_folder_of "$log" > "$out/throughput_g$g.run"
    if [ "$minutes" != 0 ]; then
      local tlog="$out/learning_g$g.log"
      : > "$tlog"
      "$py" -m otr_gym.cli train --reference "${refs[@]}" --num-envs "${NUM_ENVS:-4096}" --device "$device" \
        --gpus "$g" --max-minutes "$minutes" --save-interval "${SAVE_INTERVAL:-100}" --seed "${SEED:-42}" \
        --log-dir "$runs_dir/learning_g$g" ${sets[@]+"${sets[@]}"} 2>&1 | tee -a "$tlog"
      local run
      run=$(run_folder_of "$tlog")
      echo "$run" > "$out/learning_g$g.run"
      "$py" -m otr_gym.cli evaluate "$run" --last --device "$device" --json "$out/eval_g$g.json"
    fi
  done
  "$py" - "$out" "${NUM_ENVS:-4096}" "${counts[@]}" <<'EOF'
import json, statistics, sys
from pathlib import Path
from agents.plots import read_scalars
out, envs, counts = Path(sys.argv[1]), int(sys.argv[2]), [int(g) for g in sys.argv[3:]]
rows, base = [], None
for g in counts:
    s = read_scalars((out / f"throughput_g{g}.run").read_text().strip())
    it = [c + l for c, l in zip(s["Perf/collection_time"][1], s["Perf/learning_time"][1])][2:]  # warm-up left out
    fps = statistics.median(s["Perf/total_fps"][1][2:])
    base = base or fps
    row = {"gpus": g, "envs_per_gpu": envs, "envs_total": g * envs, "env_steps_per_s": fps,
           "iteration_s": statistics.median(it), "collection_s": statistics.median(s["Perf/collection_time"][1][2:]),
           "learning_s": statistics.median(s["Perf/learning_time"][1][2:]), "scaling": fps / base}
    ev = out / f"eval_g{g}.json"
    if ev.is_file():
        final = json.loads(ev.read_text())["final"]
        row.update(success=final["success_rate"], mpjpe_mm=final["mpjpe_mm"])
    rows.append(row)
(out / "scaling.json").write_text(json.dumps(rows, indent=2))
lines = ["| GPUs | envs (total) | env steps/s | iteration s (collect + learn) | scaling | success | MPJPE mm |",
         "|---|---|---|---|---|---|---|"]
for r in rows:
    extra = (f"{100 * r['success']:.1f} % | {r['mpjpe_mm']:.1f}" if "success" in r else "– | –")
    lines.append(f"| {r['gpus']} | {r['envs_total']} | {r['env_steps_per_s']:,.0f} | {r['iteration_s']:.3f} "
                 f"({r['collection_s']:.3f} + {r['learning_s']:.3f}) | {r['scaling']:.2f}x | {extra} |")
(out / "scaling.md").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
EOF
}

case "$stage" in
  prepare) prepare ;;
  train) train ;;
  report) report ;;
  scaling) scaling ;;
  carry) "$(dirname "$0")/carry_run.sh" "$latest" "$out/run.tar.gz" "$py" "$out/train.log" ;;
  *) echo "unknown stage '$stage' ($usage)" >&2; exit 2 ;;
esac
