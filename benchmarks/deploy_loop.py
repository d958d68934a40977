"""The deploy loop under load (issue 53 item 6): ``otr sim-robot`` + ``otr deploy`` on loopback
DDS while N CPU-bound processes load the machine, normal scheduling (no real-time priority),
one or more runner versions side by side; a table of the loop's period error, missed deadlines
and where each cycle's compute goes.

    python benchmarks/deploy_loop.py [--duration 30] [--busy 0 2] [--rounds 2] [--load-session same|own]
                                     [--variant NAME=CHECKOUT[:DEPLOY ARGS]] ... [--out DIR]

A *variant* is a checkout of this repository (``git worktree add --detach /tmp/base COMMIT``)
whose ``otr deploy`` runs, with optional extra ``otr deploy`` arguments after a colon
(``--variant "wide=.:--spin-us 2000"``); the default is this checkout. The sim robot is always
this checkout's, so every variant sees the same load. Runs go round by round, each round every
busy level, the variants in alternating order within it, so a change in the machine's other
load (a shared VM) falls on all variants alike. Each run: sway clip, the open-loop reference
policy (``agents/deploy/reference_policy.py``), ``--auto-start``, DURATION s of tracking.

Statistics over the tracking cycles of all rounds pooled (``agents.deploy.log``): *period error*
|wake_k − wake_{k−1} − 20 ms| (goal p99 < 1 ms), *missed* deadlines (slots skipped plus commands
sent after the next slot), wake *lateness* (wake − slot), and the cycle's compute split
(``log.SPLIT``: receive = take + decode + CRC of the LowState; controller = stages, kinematics
and observation; policy = the ONNX run; send = LowCmd build, CRC, serialise, write). Also the
1-min load average before each run and the CPU time the hypervisor stole during it (a VM's
stalls no scheduling inside it can avoid). Prints Markdown; ``OUT/results.json`` keeps the rows.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def parse_variant(text: str) -> tuple[str, Path, list[str]]:
    name, sep, rest = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"--variant {text!r}: expected NAME=CHECKOUT[:DEPLOY ARGS]")
    path, _, args = rest.partition(":")
    checkout = Path(path or ".").resolve()
    if not (checkout / "agents" / "deploy" / "runner.py").is_file():
        raise argparse.ArgumentTypeError(f"--variant {text!r}: {checkout} is not a checkout of this repository")
    return name, checkout, shlex.split(args)


def cpu_steal() -> tuple[int, int]:
    """(steal, total) jiffies of all CPUs so far (/proc/stat; (0, 1) where there is none)."""
    try:
        fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    except (OSError, ValueError):
        return 0, 1
    return (fields[7] if len(fields) > 7 else 0), sum(fields[:8])


def one_run(variant: tuple[str, Path, list[str]], busy: int, reference: Path, policy: Path, out: Path,
            duration: float, domain: int, load_session: bool = False) -> dict:
    from agents.deploy.log import DeployLog, cycle_split_ms, timing_stats
    from agents.deploy.safety import Stage

    name, checkout, extra = variant
    tag = f"{name}_busy{busy}_{time.strftime('%H%M%S')}"
    load = os.getloadavg()[0]
    load_procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=load_session)
                  for _ in range(busy)]
    steal0 = cpu_steal()
    cli = [sys.executable, "-m", "otr_gym.cli"]
    common = ["--interface", "lo", "--domain-id", str(domain)]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    try:
        sim = subprocess.Popen([*cli, "sim-robot", *common, "--reference", str(reference), "--duration",
                                str(duration + 30.0), "--idle-exit", "1", "--stats", str(out / f"{tag}_sim.json")],
                               env=dict(env, PYTHONPATH=str(REPO)), cwd=REPO, stdout=subprocess.DEVNULL)
        time.sleep(2.0)
        log_path = out / f"{tag}.npz"
        run = subprocess.run([*cli, "deploy", *common, "--policy", str(policy), "--reference", str(reference),
                              "--auto-start", "--ramp", "1", "--duration", str(duration), "--damp-s", "0.5",
                              "--log", str(log_path), *extra],
                             env=dict(env, PYTHONPATH=str(checkout)), cwd=checkout, capture_output=True, text=True)
        sim.wait(timeout=60)
    finally:
        for p in load_procs:
            p.kill()
            p.wait()
    steal1 = cpu_steal()
    if run.returncode not in (0,):
        print(run.stdout[-2000:], run.stderr[-2000:], file=sys.stderr)
    log = DeployLog.load(log_path)
    a = log.arrays
    track = np.flatnonzero(a["stage"] == Stage.TRACK)
    sel = slice(track[0], track[-1] + 1) if track.size else slice(0, 0)
    period_ns = int(log.meta["period_ns"])
    period = np.diff(a["wake_ns"][sel]) * 1e-6
    split = cycle_split_ms(log, sel)
    tm = timing_stats(a["deadline_ns"][sel], a["wake_ns"][sel], a["publish_ns"][sel], period_ns)
    return {
        "variant": name, "checkout": str(checkout), "deploy_args": extra, "busy": busy, "load_1min": load,
        "load_session": "own" if load_session else "same",
        "steal_pct": 100.0 * (steal1[0] - steal0[0]) / max(steal1[1] - steal0[1], 1), "log": str(log_path),
        "runner_rc": run.returncode, "ended": log.transitions()[-1][3] if log.transitions() else "",
        "tracking_cycles": int(track.size), "missed": tm["missed_deadlines"],
        "period_error_ms": np.abs(period - period_ns * 1e-6).tolist(),
        "lateness_ms": ((a["wake_ns"][sel] - a["deadline_ns"][sel]) * 1e-6).tolist(),
        "compute_ms": ((a["publish_ns"][sel] - a["wake_ns"][sel]) * 1e-6).tolist(),
        "split_ms": None if split is None else {k: v.tolist() for k, v in split.items()},
    }


def pct(values: list[float], qs=(50, 95, 99)) -> list[float]:
    x = np.asarray(values, dtype=float)
    return [float(v) for v in np.percentile(x, qs)] + [float(x.max())] if x.size else [float("nan")] * (len(qs) + 1)


def table(rows: list[dict]) -> str:
    from agents.deploy.log import SPLIT

    lines = ["| variant | busy | runs | 1-min load | steal | tracking cycles | period error p50 / p95 / p99 / max "
             "(ms) | p99 < 1 ms | missed | wake lateness p99 (ms) | compute p50 / p99 (ms) | "
             + " | ".join(f"{k} p50 / p99 (ms)" for k in SPLIT) + " |",
             "|---|---|---|---|---|---|---|---|---|---|---|" + "---|" * len(SPLIT)]
    names = [r["variant"] for r in rows]
    keys = sorted({(r["variant"], r["busy"]) for r in rows}, key=lambda k: (k[1], names.index(k[0])))
    for name, busy in keys:
        rs = [r for r in rows if r["variant"] == name and r["busy"] == busy]
        pool = {k: sum((r[k] for r in rs), []) for k in ("period_error_ms", "lateness_ms", "compute_ms")}
        e, late, comp = pct(pool["period_error_ms"]), pct(pool["lateness_ms"]), pct(pool["compute_ms"])
        loads = [r["load_1min"] for r in rs]
        steal = [r["steal_pct"] for r in rs]
        cells = [name, str(busy), str(len(rs)), f"{min(loads):.1f}–{max(loads):.1f}", f"{max(steal):.1f} %",
                 str(sum(r["tracking_cycles"] for r in rs)),
                 " / ".join(f"{v:.3f}" for v in e), "✓" if e[2] < 1.0 else "✗",
                 " + ".join(str(r["missed"]) for r in rs), f"{late[2]:.3f}", f"{comp[0]:.3f} / {comp[2]:.3f}"]
        for k in SPLIT:
            if any(r["split_ms"] is None for r in rs):
                cells.append("—")
            else:
                s = pct(sum((r["split_ms"][k] for r in rs), []))
                cells.append(f"{s[0]:.3f} / {s[2]:.3f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--variant", type=parse_variant, action="append", default=None,
                   help="NAME=CHECKOUT[:DEPLOY ARGS] (repeatable; default: this checkout)")
    p.add_argument("--busy", type=int, nargs="+", default=[0, 2], help="CPU-bound processes beside the loops")
    p.add_argument("--load-session", choices=("same", "own"), default="same",
                   help="the busy processes in the benchmark's session, with the runner and the sim robot "
                        "(default), or each in its own, as another program's (Linux's autogroups then share the "
                        "CPU between sessions first)")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--duration", type=float, default=30.0, help="seconds of tracking a run")
    p.add_argument("--domain-id", type=int, default=210)
    p.add_argument("--out", type=Path, default=None, help="folder for logs and results (default: a temp folder)")
    args = p.parse_args()
    variants = args.variant or [("this", REPO, [])]
    out = args.out or Path(tempfile.mkdtemp(prefix="deploy_loop_"))
    out.mkdir(parents=True, exist_ok=True)

    from agents.deploy.reference_policy import write_reference_policy
    from agents.procedural import SwaySpec, sway_reference

    reference = sway_reference(SwaySpec(duration_s=args.duration + 8.0)).save(out / "sway.npz")
    policy = write_reference_policy(out / "reference_policy.onnx", reference)
    rows: list[dict] = []
    for r in range(args.rounds):
        for busy in args.busy:
            order = variants if r % 2 == 0 else variants[::-1]
            for v in order:
                row = one_run(v, busy, reference, policy, out, args.duration, args.domain_id,
                              args.load_session == "own")
                e = pct(row["period_error_ms"])
                print(f"round {r} busy {busy} {v[0]}: load {row['load_1min']:.1f}, steal {row['steal_pct']:.1f} %, "
                      f"{row['tracking_cycles']} cycles, period error p99 {e[2]:.3f} max {e[3]:.3f} ms, "
                      f"missed {row['missed']}, ended {row['ended']}", flush=True)
                rows.append(row)
                (out / "results.json").write_text(json.dumps(rows))
    print(f"\n{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, kernel {platform.release()}, "
          f"{time.strftime('%Y-%m-%d')}, normal scheduling, busy processes in the {args.load_session} session, "
          f"{args.duration:g} s tracking a run, {args.rounds} round(s); files in {out}\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
