"""Retargeting speed: median ms per output frame on one CPU core, and where the time goes.

Two clips, as in the paper's runtime paragraph (Sec. IV-B: 21.5 ms/frame locomotion,
63.8 ms/frame carrying, unoptimised Python on one Threadripper core):

- locomotion: AMASS ``smplh_walk_jog_turn.npz`` (shared data), else the synthetic walk;
- carrying: OMOMO ``sub3_largebox_003.pt`` with the box free (native scale), else the
  synthetic box carry.

Each clip is resampled to 50 fps and solved with the default configuration; the time of a frame
is its SQP (demonstrated targets included) plus its contact annotation, summed over both passes
when the configuration solves twice (``balance.enabled``, ``retarget.solver.balance``, or a
flight with ``flight.enabled``: ``passes`` in the output says which). Setup (probes, optimal
transport, grids: cached on disk after the first run) is reported apart. The script pins itself
to core 0 (``taskset -c 0``) with one BLAS/OpenMP thread unless ``--no-pin``.

Usage::

    python benchmarks/retarget_speed.py [--frames N] [--json out/retarget_speed.json] [--config YAML]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
SHARED = Path(os.environ.get("OTR_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))

#: Profile sections (solver timers) grouped as reported.
GROUPS = {
    "FK + link Jacobians": ("kinematics",),
    "proximity (pose probes, SDF queries)": ("robot_channels", "object_guards"),
    "residual + constraint rows": ("robot_rows", "object_rows", "style_rows", "self_collision",
                                   "constraint_selection"),
    "self-collision of the meshes": ("self_meshes",),
    "QP assembly (H, g, C, bounds)": ("qp_assembly",),
    "ProxQP solve": ("qp_solve",),
    "demonstration targets (per frame)": ("demo_triples",),
}


def _pin() -> None:
    """Re-run this script on core 0 with one BLAS thread, unless that is already the case."""
    if os.environ.get("OTR_BENCH_PINNED") == "1" or shutil.which("taskset") is None:
        return
    env = dict(os.environ, OTR_BENCH_PINNED="1", **{k: "1" for k in THREAD_VARS})
    os.execvpe("taskset", ["taskset", "-c", "0", sys.executable, *sys.argv], env)


def _clips():
    from retarget.inputs import synthetic
    from retarget.inputs.readers import load_demonstration

    amass = SHARED / "amass" / "smplh_walk_jog_turn.npz"
    omomo = SHARED / "omomo" / "sub3_largebox_003.pt"
    walk = (("AMASS smplh_walk_jog_turn", lambda: load_demonstration(amass)) if amass.is_file()
            else ("synthetic walk (seed 0)", lambda: synthetic.generate("walk", 0)))
    carry = (("OMOMO sub3_largebox_003 (box free)",
              lambda: load_demonstration(omomo, SHARED / "objects" / "largebox.obj")) if omomo.is_file()
             else ("synthetic box carry (seed 0)", lambda: synthetic.generate("box_carry", 0)))
    if not (amass.is_file() and omomo.is_file()):
        # say so: the synthetic clips are far cheaper per frame than the real ones, and a checkout
        # that is not next to ../shared (a git worktree) would otherwise time them without a word
        print(f"note: {SHARED} lacks the real clips (set OTR_SHARED_DATA); timing the synthetic ones instead",
              file=sys.stderr, flush=True)
    return [("locomotion",) + walk, ("carrying",) + carry]


def run_clip(label: str, load, frames: int | None, config: Path | None = None) -> dict:
    import numpy as np

    from retarget.clip import problem_from_config
    from retarget.config import load_config
    from retarget.solver.balance import balance_problem
    from retarget.solver.problem import resample_demonstration
    from retarget.solver.sqp import solve_sequence

    cfg = load_config(config)
    demo = resample_demonstration(load(), cfg.fps)
    if frames is not None and frames < demo.num_frames:
        from dataclasses import replace

        s = slice(0, frames)
        demo = replace(demo, part_pos_w=demo.part_pos_w[s], part_quat_w=demo.part_quat_w[s],
                       objects=[replace(o, pos_w=o.pos_w[s], quat_w=o.quat_w[s]) for o in demo.objects],
                       annotations={k: v[s] for k, v in demo.annotations.items()})
    start = time.perf_counter()
    problem = problem_from_config(demo, cfg)
    setup = time.perf_counter() - start
    stamps = [time.perf_counter()]
    cpu0 = time.process_time()
    sol = solve_sequence(problem, lambda t: stamps.append(time.perf_counter()))
    per_frame = np.diff(stamps) * 1000.0
    stats = sol.stats[1:]
    # the default pipeline solves again with the COM smoothed (retarget.solver.balance): a
    # frame's time is then both passes' (target building counted in the second's first frame)
    second = balance_problem(problem, sol, cfg.balance, cfg.flight)
    if second is not None:
        stamps = [time.perf_counter()]
        sol = solve_sequence(second[0], lambda t: stamps.append(time.perf_counter()))
        per_frame = per_frame + np.diff(stamps) * 1000.0
        stats = stats + sol.stats[1:]
    cpu = time.process_time() - cpu0
    warm = per_frame[1:]
    timings: dict[str, float] = {}
    for st in stats:
        for k, v in st.timings.items():
            timings[k] = timings.get(k, 0.0) + v
    rows = np.concatenate([s.qp_rows for s in stats if s.qp_rows])
    profile = {name: 1000.0 * sum(timings.get(k, 0.0) for k in keys) / len(warm) for name, keys in GROUPS.items()}
    profile["other (annotation, retraction, bookkeeping)"] = float(warm.mean()) - sum(profile.values())
    return {
        "clip": label, "frames": int(demo.num_frames), "fps": demo.fps, "setup_s": setup,
        "cold_frame_ms": float(per_frame[0]),
        "median_ms": float(np.median(warm)), "p90_ms": float(np.percentile(warm, 90)), "mean_ms": float(warm.mean()),
        "cpu_ms_per_frame": 1000.0 * cpu / len(per_frame),
        "passes": 1 if second is None else 2,
        "iterations_mean": float(np.mean([s.iterations for s in stats])),
        "qp_variables": problem.num_variables, "qp_rows_mean": float(rows.mean()), "qp_rows_max": int(rows.max()),
        "probes": len(problem.robot), "profile_ms": profile,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=None, help="solve only the first N frames of each clip")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    parser.add_argument("--no-pin", action="store_true", help="do not pin to core 0")
    parser.add_argument("--config", type=Path, default=None,
                        help="retarget YAML overriding the defaults (e.g. balance: {enabled: false})")
    args = parser.parse_args(argv)
    if not args.no_pin:
        _pin()
    results = []
    for kind, label, load in _clips():
        print(f"[{kind}] {label} …", flush=True)
        results.append({"kind": kind, **run_clip(label, load, args.frames, args.config)})

    cpu = platform.processor() or platform.machine()
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                   if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    affinity = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "?"
    print(f"\n{cpu}; cores in use {affinity}; load average {os.getloadavg()[0]:.2f}; "
          f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC")
    header = (f"{'clip':<36} {'frames':>6} {'median':>8} {'p90':>8} {'cpu/fr':>8} {'iters':>6} {'QP n×m':>10} "
              f"{'setup':>7}")
    print(header)
    print("-" * len(header))
    for r in results:
        print(f"{r['clip']:<36} {r['frames']:>6} {r['median_ms']:>6.1f}ms {r['p90_ms']:>6.1f}ms "
              f"{r['cpu_ms_per_frame']:>6.1f}ms {r['iterations_mean']:>6.2f} "
              f"{r['qp_variables']:>3}×{r['qp_rows_mean']:<6.0f} {r['setup_s']:>6.1f}s")
    print("\nprofile, ms per warm frame (share)")
    for r in results:
        print(f"  {r['clip']}")
        for name, ms in r["profile_ms"].items():
            print(f"    {name:<46} {ms:>7.2f}  {100 * ms / r['mean_ms']:>5.1f} %")
    print("\npaper (unoptimised Python, Threadripper core): 21.5 ms locomotion, 63.8 ms carrying; "
          "targets (issue 54): <= 5 and <= 12 ms")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"cpu": cpu, "results": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
