"""``otr retarget``: demonstrations (files or folders) to G1 references.

    otr retarget INPUT… --out DIR [--object MESH] [--mode native|scaled|robot-only]
                 [--workers N] [--ray [ADDRESS]] [--fps 50] [--config YAML] [--overwrite]
                 [--skeleton-map YAML] [--units UNIT] [--up AXIS]

Inputs are AMASS ``.npz`` (SMPL-X / SMPL-H parameters), OMOMO InterMimic ``.pt`` clips, BVH
files and our demonstration ``.npz`` files, or folders of them (searched recursively). A batch
is resumable: finished outputs are skipped, a failing clip is reported with its file and error
and the batch goes on; the exit code is 1 if any clip failed. ``DIR/retarget_summary.json``
lists every clip (status, frames, ms/frame, worker). Clips run in this process (default),
``--workers N`` local processes, or ``--ray [ADDRESS]`` Ray tasks on a cluster.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from retarget.cli.batch import SUMMARY_NAME, ClipResult, Task, collect_jobs, report, summary
from retarget.cli.executors import SerialExecutor, make_executor
from retarget.config import ConfigError, load_config


def configure_parser(p: argparse.ArgumentParser) -> None:
    from retarget.inputs.bvh import add_arguments

    p.add_argument("inputs", nargs="+", type=Path, metavar="INPUT",
                   help="demonstration files (AMASS .npz, OMOMO .pt, BVH .bvh, our .npz) or folders of them")
    p.add_argument("--out", type=Path, required=True, help="output folder for the references (.npz)")
    p.add_argument("--object", type=Path, default=None, metavar="MESH",
                   help="object mesh for OMOMO clips (default: looked up next to the clip)")
    p.add_argument("--mode", choices=("native", "scaled", "robot-only"), default=None,
                   help="native scene (default), scaled with the object fixed, or ground only")
    p.add_argument("--fps", type=float, default=None, help="output and solve rate in Hz (default: 50)")
    p.add_argument("--workers", type=int, default=None,
                   help="parallel worker processes (default: 1); with --ray, tasks in flight (default: the "
                        "cluster's CPUs)")
    p.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="run the clips as Ray tasks: on the cluster at ADDRESS (e.g. 10.0.0.1:6379, 'auto'), "
                        "or on a local Ray started for this run when no address is given")
    p.add_argument("--config", type=Path, default=None, help="YAML configuration (default: the built-in defaults)")
    p.add_argument("--overwrite", action="store_true", help="redo clips whose output already exists")
    add_arguments(p)

def main(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from otr_gym.io import write_json
    from retarget.geometry.kernel_warmup import start_warmup, stop_warmup
    from retarget.inputs.bvh import options_from_args

    try:
        cfg = load_config(args.config, mode=args.mode, fps=args.fps)
        jobs = collect_jobs(list(args.inputs), Path(args.out))
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.workers is not None and args.workers < 1:
        print(f"error: --workers must be >= 1, got {args.workers}", file=sys.stderr)
        return 2
    task = Task(cfg, args.object, options_from_args(args))
    todo = [j for j in jobs if args.overwrite or not j.output.is_file()]
    done_before = [j for j in jobs if j not in todo]
    if done_before:
        print(f"{len(done_before)} of {len(jobs)} outputs already exist: skipped (use --overwrite to redo them)")
    results = [ClipResult(str(j.source), str(j.output), "skipped", "output exists") for j in done_before]
    summary_path = Path(args.out) / SUMMARY_NAME
    executor = make_executor(args) if todo else SerialExecutor()
    if todo and isinstance(executor, SerialExecutor):  # a pool's processes keep every core busy already
        start_warmup()  # a first run compiles the solver's kernels beside its grids (retarget.geometry.kernel_warmup)
    start = time.perf_counter()
    bar = tqdm(total=len(todo), desc="retarget", unit="clip")
    try:
        for result in executor.run(todo, task):
            results.append(result)
            report(bar, result)
            write_json(summary_path, summary(results, executor.name, time.perf_counter() - start))
    finally:
        bar.close()
        executor.close()
        stop_warmup()
    write_json(summary_path, summary(results, executor.name, time.perf_counter() - start))
    failures = [r for r in results if r.status == "failed"]
    print(f"retargeted {len(todo) - len(failures)}, skipped {len(done_before)}, failed {len(failures)} "
          f"(of {len(jobs)}); summary {summary_path}")
    for r in failures:
        print(f"FAILED {r.message}", file=sys.stderr)
    return 1 if failures else 0
