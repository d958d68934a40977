#!/usr/bin/env bash
# One trained run as a gzipped tar small enough for a device command to return (files of at most
# 16 MiB) or to carry to another machine: the LATEST_RUN file, the run folder without checkpoints
# or ONNX (config, env spec, event files) and its latest checkpoint only. Gzip because the event
# files grow with the run (a 19-minute jog's: 2.9 MB, 0.8 MB gzipped) while the checkpoint does
# not. Extract it where the paths are relative to (the repository root; `-C /` for an absolute
# RUNS_DIR) and the same `train` command resumes the run. Used by the `carry` stage of
# train_box.sh and train_library.sh.
#
# A run still training has no LATEST_RUN yet (the train stage writes it when its process ends),
# and a detached run that a lost machine would cut off is exactly what carry is for. So with
# TRAIN_LOG given and no LATEST_RUN, the run folder is the log's last `run folder:` line; once
# that folder holds a checkpoint, LATEST_RUN is written to name it (the train stage would resume
# it) and packed.
#
# With EVERY=N, a second archive, OUT_policies.tar.gz (OUT.tar.gz's name), holds policy-only
# copies of the run's checkpoints at multiples of N iterations (`python -m otr_gym.cli runs
# policy-only`: the actor without critic or optimizer, ~1 MB each), under the same paths: extract
# it beside the run and `otr evaluate RUN --plot P` measures every one, how the policy got there.
#
#   benchmarks/carry_run.sh LATEST_RUN_FILE OUT.tar.gz [PYTHON [TRAIN_LOG]]
set -euo pipefail
usage="usage: benchmarks/carry_run.sh LATEST_RUN_FILE OUT.tar.gz [PYTHON [TRAIN_LOG]]"
latest=${1:?$usage}
tar_out=${2:?$usage}
py=${3:-python3}
log=${4:-}
if [ -f "$latest" ]; then
  run=$(cat "$latest")
else
  run=$([ -n "$log" ] && [ -f "$log" ] && sed -n 's/^run folder: //p' "$log" | tail -1) || true
  [ -n "$run" ] && [ -d "$run" ] ||
    { echo "$latest: no trained run${log:+ and no run folder in $log} (run the train stage first)" >&2; exit 1; }
fi
last=$("$py" -m otr_gym.cli runs latest "$run")  # names a folder that has no checkpoint yet
[ -f "$latest" ] || echo "$run" > "$latest"  # only once it has one: the train stage resumes it
mkdir -p "$(dirname "$tar_out")"
# a file list, not --exclude: tar's exclusions would drop the checkpoint named on the command line too
{ echo "$latest"; find "$run" -type f ! -name '*.pt' ! -name '*.onnx'; echo "$last"; } |
  tar czf "$tar_out" --verbatim-files-from -T -
if [ "${EVERY:-0}" -gt 0 ]; then
  slim=$(mktemp -d)
  "$py" -m otr_gym.cli runs policy-only "$run" --every "$EVERY" --out "$slim" > /dev/null
  names=$(cd "$slim" && ls)
  policies="${tar_out%.tar.gz}_policies.tar.gz"
  if [ -n "$names" ]; then
    # shellcheck disable=SC2086  # file names of the form model_<it>.pt
    tar czf "$policies" -C "$slim" --transform "s,^,${run%/}/," $names
    echo "$policies: $(echo $names | wc -w) policy-only checkpoints every $EVERY iterations, $(du -h "$policies" | cut -f1)"
  else
    echo "EVERY=$EVERY: no checkpoint but the latest at a multiple of $EVERY iterations; no $policies" >&2
  fi
  rm -rf "$slim"
fi
where="in the repository root"
case "$run" in /*) where="with tar xf $(basename "$tar_out") -C /" ;; esac
echo "$tar_out: $run, checkpoint $(basename "$last"), $(du -h "$tar_out" | cut -f1); extract $where, then train resumes"
