"""``otr retarget``: demonstrations (files or folders) to G1 references.

    otr retarget INPUT… --out DIR [--object MESH] [--mode native|scaled|robot-only]
                 [--workers N] [--ray [ADDRESS]] [--fps 50] [--config YAML] [--overwrite]
                 [--max-flagged SHARE] [--skeleton-map YAML] [--units UNIT] [--up AXIS]

Inputs are AMASS ``.npz`` (SMPL-X / SMPL-H parameters), OMOMO InterMimic ``.pt`` clips, BVH
files and our demonstration ``.npz`` files, or folders of them (searched recursively). A batch
is resumable: finished outputs are skipped, keeping the figures their run recorded. A failing
clip, one whose worker process dies included, is reported with its file and error and the
batch goes on; the exit code is 1 if any clip failed. ``DIR/retarget_summary.json`` lists every
clip (status, frames, ms/frame, worker, feasibility and contact figures). ``--max-flagged``
also writes ``DIR/clips_passing.txt``, the references ``otr train --reference`` should learn
(``retarget.cli.clip_list``). Clips run in this process (default), ``--workers N`` local
processes, or ``--ray [ADDRESS]`` Ray tasks on a cluster; one bar shows clips/min and the ETA.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from retarget.cli.batch import (
    SUMMARY_NAME,
    Task,
    collect_jobs,
    earlier_records,
    lost_result,
    progress_bar,
    report,
    skipped_result,
    summary,
)
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
    p.add_argument("--max-flagged", type=float, default=None, metavar="SHARE",
                   help="also write DIR/clips_passing.txt for otr train --reference: every reference (made now or "
                        "before) with at most this share (0-1) of its frames over a feasibility limit, e.g. 0.02")
    add_arguments(p)

def main(args: argparse.Namespace) -> int:
    from otr_gym.io import write_json
    from retarget.cli.clip_list import write_clip_list
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
    if args.max_flagged is not None and not 0.0 <= args.max_flagged <= 1.0:
        print(f"error: --max-flagged is a share of frames in [0, 1], got {args.max_flagged}", file=sys.stderr)
        return 2
    task = Task(cfg, args.object, options_from_args(args))
    todo = [j for j in jobs if args.overwrite or not j.output.is_file()]
    done_before = [j for j in jobs if j not in todo]
    summary_path = Path(args.out) / SUMMARY_NAME
    if done_before:
        print(f"{len(done_before)} of {len(jobs)} outputs already exist: skipped (use --overwrite to redo them)")
    earlier = earlier_records(summary_path) if done_before else {}
    results = [skipped_result(j, earlier.get(j.output.resolve())) for j in done_before]
    executor = make_executor(args) if todo else SerialExecutor()
    if todo and isinstance(executor, SerialExecutor):  # a pool's processes keep every core busy already
        start_warmup()  # a first run compiles the solver's kernels beside its grids (retarget.geometry.kernel_warmup)
    start = time.perf_counter()
    bar = progress_bar(len(todo))
    finished: set = set()
    try:
        for result in executor.run(todo, task):
            results.append(result)
            finished.add(result.output)
            report(bar, result, sum(r.status == "done" for r in results))
            write_json(summary_path, summary(results, executor.name, time.perf_counter() - start))
    except Exception as exc:  # the executor itself broke (a Ray cluster lost): name every clip it left
        why = f"not retargeted: {executor.name} stopped ({type(exc).__name__}: {exc})"
        results += [lost_result(j, why) for j in todo if str(j.output) not in finished]
    finally:
        bar.close()
        executor.close()
        stop_warmup()
    write_json(summary_path, summary(results, executor.name, time.perf_counter() - start))
    failures = [r for r in results if r.status == "failed"]
    counts = {status: sum(r.status == status for r in results) for status in ("done", "skipped")}
    print(f"retargeted {counts['done']}, skipped {counts['skipped']}, failed {len(failures)} (of {len(jobs)}); "
          f"summary {summary_path}")
    if args.max_flagged is not None:
        clip_list, count = write_clip_list(results, Path(args.out), args.max_flagged)
        print(f"{count} of {len(jobs)} clips pass --max-flagged {args.max_flagged:g}: {clip_list}"
              + ("" if count else " (names no clip: otr train would refuse it)"))
    for r in failures:
        print(f"FAILED {r.message}", file=sys.stderr)
    return 1 if failures else 0
