#!/usr/bin/env bash
# Commands that outlive a 10-minute device call: started detached (setsid, stdin closed) and
# waited on by process id in later calls. Never wait with `pgrep -f WORDS`: the waiting call's own
# shell has the same words on its command line, so such a loop never ends (2026-11-27 and again
# 2026-11-28 it held a 2-GPU machine until the call's limit, after the runs and their reports
# were done).
#
#   benchmarks/detached.sh start NAME COMMAND [ARG...]   # output in $DETACHED_DIR/NAME/log
#   benchmarks/detached.sh wait SECONDS NAME...          # until every NAME has ended, at most SECONDS
#   benchmarks/detached.sh status NAME...                # the same, without waiting
#
# wait and status print one line per NAME (running / exit code / ended without one, i.e.
# killed) and the last TAIL (3) lines of its log, and exit 0 when every NAME ended with 0, 1 when
# one ended otherwise, 3 while one still runs. So one call can chain the next stage:
#   benchmarks/detached.sh wait 540 jog box && benchmarks/detached.sh start report …
# DETACHED_DIR: /tmp/detached (a device machine's /tmp lasts as long as its lease).
set -uo pipefail
usage="usage: benchmarks/detached.sh start NAME COMMAND [ARG...] | wait SECONDS NAME... | status NAME..."
root=${DETACHED_DIR:-/tmp/detached}
stage=${1:?$usage}
shift

alive() {  # a zombie (killed, its parent gone, nobody reaping it: a container's PID 1) is not alive
  kill -0 "$1" 2>/dev/null || return 1
  [ -r "/proc/$1/status" ] || return 0
  ! grep -q '^State:[[:space:]]*Z' "/proc/$1/status"
}

state() {  # running | exit N | killed | unknown
  local dir=$root/$1
  if [ -f "$dir/rc" ]; then echo "exit $(cat "$dir/rc")"
  elif [ -f "$dir/pid" ] && alive "$(cat "$dir/pid")"; then echo running
  elif [ -f "$dir/pid" ]; then echo killed
  else echo unknown
  fi
}

report() {  # one line per job and its log's tail; the exit status of wait/status
  local name st code=0
  for name in "$@"; do
    st=$(state "$name")
    echo "== $name: $st ($root/$name/log)"
    [ -f "$root/$name/log" ] && tail -n "${TAIL:-3}" "$root/$name/log"
    case $st in
      running) code=3 ;;
      "exit 0") ;;
      *) [ $code -eq 3 ] || code=1 ;;
    esac
  done
  return $code
}

case $stage in
  start)
    name=${1:?$usage}
    shift
    [ $# -gt 0 ] || { echo "$usage" >&2; exit 2; }
    case $name in */*|.*|"") echo "job name '$name': a plain name, no '/'" >&2; exit 2 ;; esac
    if [ "$(state "$name")" = running ]; then
      echo "$name is still running (pid $(cat "$root/$name/pid")); wait on it or pick another name" >&2
      exit 1
    fi
    dir=$root/$name
    mkdir -p "$dir"
    rm -f "$dir/rc" "$dir/pid"
    # the inner shell writes its own pid and, when COMMAND ends, COMMAND's exit code
    setsid nohup bash -c 'echo $$ > "$0/pid"; "$@"; echo $? > "$0/rc"' "$dir" "$@" > "$dir/log" 2>&1 < /dev/null &
    for _ in $(seq 50); do [ -f "$dir/pid" ] && break; sleep 0.1; done
    echo "$name: started, pid $(cat "$dir/pid" 2>/dev/null || echo '?'), log $dir/log"
    ;;
  wait)
    seconds=${1:?$usage}
    shift
    [ $# -gt 0 ] || { echo "$usage" >&2; exit 2; }
    case $seconds in ''|*[!0-9]*) echo "wait: SECONDS must be a whole number, not '$seconds'" >&2; exit 2 ;; esac
    end=$((SECONDS + seconds))
    while [ $SECONDS -lt $end ]; do
      busy=0
      for name in "$@"; do [ "$(state "$name")" = running ] && busy=1; done
      [ $busy -eq 0 ] && break
      sleep 2
    done
    report "$@"
    ;;
  status)
    [ $# -gt 0 ] || { echo "$usage" >&2; exit 2; }
    report "$@"
    ;;
  *) echo "$usage" >&2; exit 2 ;;
esac
