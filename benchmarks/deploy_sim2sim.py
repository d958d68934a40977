"""Sim2sim on loopback DDS: ``otr sim-robot`` + ``otr deploy`` for DURATION s of tracking, then a
table of the runner's loop timing, the tracking error and the sim robot's real-time figures.

    python benchmarks/deploy_sim2sim.py [--policy P.onnx --reference R.npz] [--duration 60] [--rt-priority 80]
                                        [--busy 2]

Without ``--policy`` it builds the open-loop "reference policy" (``agents/deploy/reference_policy.py``,
stiff start-up gains) and a 64 s procedural sway (``agents/procedural.py``) to track. Both
processes run on this machine; the CycloneDDS traffic stays on ``lo``. ``--busy N`` loads the
machine with N CPU-bound processes for the whole run (the issue's "busy 2-core machine").
Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--policy", type=Path, default=None)
    p.add_argument("--reference", type=Path, default=None)
    p.add_argument("--duration", type=float, default=60.0, help="seconds of tracking")
    p.add_argument("--domain-id", type=int, default=200)
    p.add_argument("--rt-priority", type=int, default=0, help="SCHED_FIFO priority for both loops (0: off)")
    p.add_argument("--out", type=Path, default=None, help="folder for the log and stats (default: a temp folder)")
    p.add_argument("--busy", type=int, default=0, help="CPU-bound processes running beside the two loops")
    args = p.parse_args()

    from agents.deploy.log import DeployLog, log_timing
    from agents.deploy.safety import Stage

    out = args.out or Path(tempfile.mkdtemp(prefix="sim2sim_"))
    out.mkdir(parents=True, exist_ok=True)
    reference, policy = args.reference, args.policy
    if reference is None:
        from agents.procedural import SwaySpec, sway_reference

        reference = sway_reference(SwaySpec(duration_s=args.duration + 4.0)).save(out / "sway.npz")
    if policy is None:
        from agents.deploy.reference_policy import write_reference_policy

        policy = write_reference_policy(out / "reference_policy.onnx", reference)
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    rt = ["--rt-priority", str(args.rt_priority)] if args.rt_priority else []
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy)]
    cli = [sys.executable, "-m", "otr_gym.cli"]
    common = ["--interface", "lo", "--domain-id", str(args.domain_id)]
    sim = subprocess.Popen([*cli, "sim-robot", *common, "--reference", str(reference), "--duration",
                            str(args.duration + 12.0), "--stats", str(out / "sim.json"), *rt], env=env, cwd=REPO)
    time.sleep(2.0)
    run = subprocess.run([*cli, "deploy", *common, "--policy", str(policy), "--reference", str(reference),
                          "--auto-start", "--duration", str(args.duration), "--damp-s", "1", "--log",
                          str(out / "run.npz"), *rt], env=env, cwd=REPO)
    sim.wait()
    for b in busy:
        b.kill()
    load = os.getloadavg()[0]
    log = DeployLog.load(out / "run.npz")
    stats = json.loads((out / "sim.json").read_text())
    a = log.arrays
    track = a["stage"] == Stage.TRACK
    tm = log_timing(log)
    p_, e, late, comp = tm["period_ms"], tm["period_error_ms"], tm["lateness_ms"], tm["compute_ms"]
    rows = [
        ("tracking", f"{track.sum() / 50:.1f} s ({int(track.sum())} cycles), ended "
                     f"{log.transitions()[-1][3]}, runner exit {run.returncode}"),
        ("cycle period p50 / p99 / max", f"{p_['p50']:.3f} / {p_['p99']:.3f} / {p_['max']:.3f} ms"),
        ("period error p99 / max (goal p99 < 1 ms)", f"{e['p99']:.3f} / {e['max']:.3f} ms"),
        ("jitter (std of period)", f"{tm['jitter_ms']:.3f} ms"),
        ("wake lateness p50 / p99 / max", f"{late['p50']:.3f} / {late['p99']:.3f} / {late['max']:.3f} ms"),
        ("cycle compute p50 / p99 / max", f"{comp['p50']:.3f} / {comp['p99']:.3f} / {comp['max']:.3f} ms"),
        ("missed deadlines (goal 0)", str(tm["missed_deadlines"])),
        ("LowState fresh / bad CRC", f"{a['fresh'].mean():.2%} / {int((~a['crc_ok']).sum())}"),
        ("MPJPE mean / max (root-relative, 14 bodies)",
         f"{np.nanmean(a['mpjpe_m'][track]) * 1e3:.1f} / {np.nanmax(a['mpjpe_m'][track]) * 1e3:.1f} mm"),
        ("upright (pelvis min / torso tilt max)", f"{stats['upright']} ({stats['min_pelvis_z_m']:.3f} m / "
                                                 f"{np.degrees(stats['max_torso_tilt_rad']):.1f}°)"),
        ("sim robot real-time factor", f"{stats['realtime_factor']:.4f} ({stats['physics_hz']:g} Hz physics, "
                                       f"{stats['resyncs']} resyncs)"),
        ("sim step p50 / p99 / max", f"{stats['step_ms']['p50']:.3f} / {stats['step_ms']['p99']:.3f} / "
                                     f"{stats['step_ms']['max']:.3f} ms (budget {1e3 / stats['physics_hz']:g} ms)"),
        ("sim wake lateness p99 / max", f"{stats['lateness_ms']['p99']:.3f} / {stats['lateness_ms']['max']:.3f} ms"),
        ("LowCmd accepted / dropped (bad CRC)", f"{stats['accepted']} / {stats['dropped_bad_crc']}"),
    ]
    print(f"\n{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, {time.strftime('%Y-%m-%d')}, "
          f"policy {policy.name}, rt-priority {args.rt_priority or 'off'}, {args.busy} busy processes, "
          f"1-min load {load:.1f}, files in {out}\n")
    print("| quantity | value |\n|---|---|")
    for k, v in rows:
        print(f"| {k} | {v} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
