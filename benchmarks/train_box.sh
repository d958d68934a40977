#!/usr/bin/env bash
# GPU recipe for OTR-G1-BoxTrack-v0: train on a box reference within a wall-clock budget (one run
# resumed across several commands), then evaluate, plot and export.
#
#   benchmarks/train_box.sh train  OUT_DIR REFERENCE   # MINUTES more learning (resumes RUNS_DIR's run)
#   benchmarks/train_box.sh report OUT_DIR REFERENCE   # curves, evaluation, ONNX, video of that run
#   benchmarks/train_box.sh all    OUT_DIR REFERENCE   # train, then report
#   benchmarks/train_box.sh prune  OUT_DIR REFERENCE   # keep the latest checkpoint and every 500th
#   benchmarks/train_box.sh carry  OUT_DIR REFERENCE   # OUT_DIR/run.tar.gz: the run to resume on another machine
#
# A 30-minute run under a 10-minute-per-command limit: `train` with MINUTES=7 (the first call also
# builds the env and compiles MuJoCo-Warp's kernels, 2-3 min), then MINUTES=8 twice more, then
# `report` (same OUT_DIR and RUNS_DIR each time: the run folder survives between commands while
# the machine stays warm). To go on on another machine: `carry` writes OUT_DIR/run.tar.gz (RUNS_DIR's
# LATEST_RUN and the run folder with only its latest checkpoint, also of a run still training;
# benchmarks/carry_run.sh);
# `tar xf run.tar.gz` in the repository root there (`-C /` for an absolute RUNS_DIR such as
# /tmp/box/runs), then `train` with the same RUNS_DIR resumes.
#
# Knobs (environment):
#   NUM_ENVS (4096), MINUTES (8), DEVICE (cuda), SAVE_INTERVAL (250), SEED (42),
#   RUNS_DIR (runs/box: run folders; git-ignored, so they stay on a warm device machine),
#   ABLATION: none (default) | no_contact (hand and support contact rewards off) |
#             no_object_vel (object linear/angular velocity tracking off),
#   OBJECT_MESH: NAME=FILE for references that embed no object mesh (Holosoma's:
#             largebox=../shared/data/objects/largebox.obj),
#   SETS: more `--set KEY=VALUE` overrides, space-separated (e.g. "env.objects.mass_kg=2"),
#   EVAL_ENVS (1024: envs of the randomised evaluation), VIDEO (1: render one evaluation episode),
#   PYTHON (python3).
# Overrides are stored in the run (config.yaml), so resuming, evaluating and exporting use them.
#
# OUT_DIR receives (at most 8 files): train.log; from "report": training_curves.png (reward,
# episode length, FPS, MPJPE, success, object position/orientation error, object terminations,
# every reward term), eval.json (frame 0, no randomisation, mean action: success, MPJPE, object
# error mean/p95 (cm), orientation error (deg), box-table contact), eval_randomized.json
# (EVAL_ENVS envs keeping the training randomisation: the success *rate*), summary.md (both
# in one table), policy.onnx, play.mp4.
set -euo pipefail
usage="usage: benchmarks/train_box.sh all|train|report|prune|carry OUT_DIR REFERENCE"
stage=${1:?$usage}
out=${2:?$usage}
ref=${3:?$usage}
py=${PYTHON:-python3}
device=${DEVICE:-cuda}
runs_dir=${RUNS_DIR:-runs/box}
latest="$runs_dir/LATEST_RUN"
export PYTHONUNBUFFERED=1
mkdir -p "$out" "$runs_dir"

sets=()
case "${ABLATION:-none}" in
  none) ;;
  no_contact) sets+=(--set env.rewards.hand_contact.weight=0 --set env.rewards.support_contact.weight=0) ;;
  no_object_vel) sets+=(--set env.rewards.object_lin_vel.weight=0 --set env.rewards.object_ang_vel.weight=0) ;;
  *) echo "unknown ABLATION '${ABLATION}' (none | no_contact | no_object_vel)" >&2; exit 2 ;;
esac
if [ -n "${OBJECT_MESH:-}" ]; then
  sets+=(--set "env.objects.overrides.${OBJECT_MESH%%=*}.mesh=${OBJECT_MESH#*=}")
fi
for item in ${SETS:-}; do sets+=(--set "$item"); done

train() {
  local from=()
  [ -f "$latest" ] && from=(--resume "$(cat "$latest")")
  "$py" -m otr_gym.cli train --task OTR-G1-BoxTrack-v0 --reference "$ref" --num-envs "${NUM_ENVS:-4096}" \
    --device "$device" --max-minutes "${MINUTES:-8}" --save-interval "${SAVE_INTERVAL:-250}" --seed "${SEED:-42}" \
    --log-dir "$runs_dir" ${from[@]+"${from[@]}"} ${sets[@]+"${sets[@]}"} 2>&1 | tee -a "$out/train.log"
  local run
  run=$(sed -n 's/^run folder: //p' "$out/train.log" | tail -1)
  [ -d "$run" ] || { echo "no run folder in $out/train.log" >&2; exit 1; }
  echo "$run" > "$latest"
}

report() {
  [ -f "$latest" ] || { echo "$latest: no trained run (run the train stage first)" >&2; exit 1; }
  local run
  run=$(cat "$latest")
  "$py" -m otr_gym.cli plot "$run" --png "$out/training_curves.png" --json "$run/training_summary.json"
  "$py" -m otr_gym.cli evaluate "$run" --last --reference "$ref" --device "$device" --json "$out/eval.json"
  "$py" -m otr_gym.cli evaluate "$run" --last --randomize --reference "$ref" --device "$device" \
    --num-envs "${EVAL_ENVS:-1024}" --json "$out/eval_randomized.json"
  "$py" -m otr_gym.cli export "$run" --onnx "$out/policy.onnx"
  if [ "${VIDEO:-1}" = 1 ]; then
    MUJOCO_GL=${MUJOCO_GL:-egl} "$py" -m otr_gym.cli play "$run" --reference "$ref" --video "$out/play.mp4" \
      || echo "play: no video (offscreen rendering unavailable?)" >&2
  fi
  "$py" - "$run" "$out" <<'EOF'
import json, sys
from pathlib import Path
run, out = Path(sys.argv[1]), Path(sys.argv[2])
train = json.loads((run / "training_summary.json").read_text())
rows = []
for name in ("eval.json", "eval_randomized.json"):
    r = json.loads((out / name).read_text())["final"]
    contact = {k: v["contact_rate"] for k, v in r.get("support_contact", {}).items()}
    end = {k: v["contact_at_clip_end"] for k, v in r.get("support_contact", {}).items()}
    fmt = lambda v, f: "-" if v is None else format(v, f)
    rows.append(f"| {name[:-5]} | {r['envs']} | {100 * r['success_rate']:.1f} % | {r['mpjpe_mm']:.1f} | "
                f"{fmt(r.get('object_pos_error_cm'), '.1f')} | {fmt(r.get('object_pos_error_p95_cm'), '.1f')} | "
                f"{fmt(r.get('object_ori_error_deg'), '.1f')} | {fmt(r.get('object_final_pos_error_cm'), '.1f')} | "
                f"{contact} | {end} |")
text = (f"# {run.name}\n\n{train['iterations']} iterations, {train['learning_minutes']:.1f} min of learning, "
        f"median {train['median_fps']:,.0f} env steps/s\n\n"
        "| evaluation | envs | success | MPJPE (mm) | object error mean (cm) | p95 (cm) | orientation (deg) | "
        "error at clip end (cm) | support contact in window | support contact at clip end |\n"
        "|---|---|---|---|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n")
(out / "summary.md").write_text(text)
print(text)
EOF
  echo "run folder: $run"
}

prune() {
  [ -f "$latest" ] || { echo "$latest: no run" >&2; exit 1; }
  local run last
  run=$(cat "$latest")
  last=$("$py" -m otr_gym.cli runs latest "$run") || exit 1
  for f in "$run"/model_*.pt; do
    it=$(basename "$f" .pt); it=${it#model_}
    if [ "$(basename "$f")" != "$(basename "$last")" ] && [ $(( (it + 1) % 500 )) -ne 0 ]; then rm -f "$f"; fi
  done
  du -sh "$run"
}

carry() {  # a device command returns files of at most 16 MiB: the latest checkpoint only
  "$(dirname "$0")/carry_run.sh" "$latest" "$out/run.tar.gz" "$py" "$out/train.log"
}

case "$stage" in
  all) train; report ;;
  train) train ;;
  report) report ;;
  prune) prune ;;
  carry) carry ;;
  *) echo "unknown stage '$stage' (all | train | report | prune | carry)" >&2; exit 2 ;;
esac
