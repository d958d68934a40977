"""A corpus retarget reproduced (issue 54): the same folder through ``otr retarget`` serially,
with ``--workers 2`` and with ``--ray``, then resumed, and the table of what each gave.

    python benchmarks/corpus.py CORPUS... [--limit N] [--max-flagged 0.02] [--out /tmp/otr_corpus]
                                [--executors serial,workers2,ray] [OTR RETARGET OPTIONS]

CORPUS: folders or files, as ``otr retarget`` takes them (searched recursively); ``--limit N``
keeps the first N files (sorted), linked into ``OUT/corpus`` with their sub-folders. Options
this script does not know (``--mode robot-only``, ``--skeleton-map YAML``, …) go to every run.
Each executor is one ``python -m otr_gym.cli retarget`` process into its own folder
``OUT/<executor>``; its wall time includes process start, imports and, for Ray, starting a
local cluster. The *resume* row runs the serial command again on the serial folder: every clip
skipped, the figures carried over. Columns: clips done / failed / skipped, wall time, clips
retargeted per minute of wall time, and the share of the clips with a reference that pass
``--max-flagged`` (``OUT/<executor>/clips_passing.txt``, the list ``otr train --reference`` reads).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from retarget.cli.batch import INPUT_SUFFIXES, SUMMARY_NAME  # noqa: E402
from retarget.cli.clip_list import PASSING_NAME  # noqa: E402

#: label -> the ``otr retarget`` options of that executor
EXECUTORS = {"serial": [], "workers2": ["--workers", "2"], "ray": ["--ray", "--workers", "2"]}


def linked_corpus(inputs: list[Path], limit: int, folder: Path) -> Path:
    """The first ``limit`` demonstration files of ``inputs`` (sorted), linked into ``folder``
    with their paths below their input folder, so output names are those of the whole corpus."""
    files: list[tuple[Path, Path]] = []
    for item in inputs:
        if item.is_dir():
            files += [(p, p.relative_to(item)) for p in sorted(item.rglob("*"))
                      if p.suffix.lower() in INPUT_SUFFIXES and p.is_file()]
        else:
            files.append((item, Path(item.name)))
    for source, relative in files[:limit]:
        link = folder / relative
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(source.resolve())
    return folder


def run(inputs: list[Path], out: Path, options: list[str]) -> tuple[int, float, dict]:
    """One ``otr retarget`` process: exit code, wall time (s) and its summary."""
    command = [sys.executable, "-m", "otr_gym.cli", "retarget", *map(str, inputs), "--out", str(out), *options]
    start = time.perf_counter()
    code = subprocess.run(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode
    wall_s = time.perf_counter() - start
    return code, wall_s, json.loads((out / SUMMARY_NAME).read_text())


def row(label: str, code: int, wall_s: float, summary: dict, out: Path) -> str:
    kept = [line for line in (out / PASSING_NAME).read_text().splitlines() if line and not line.startswith("#")]
    with_reference = summary["done"] + summary["skipped"]
    passing = f"{len(kept)}/{with_reference} ({100 * len(kept) / with_reference:.0f} %)" if with_reference else "-"
    rate = f"{60 * summary['done'] / wall_s:.2f}" if summary["done"] else "-"
    return (f"{label:<10} {summary['clips']:>5} {summary['done']:>5} {summary['failed']:>6} {summary['skipped']:>7} "
            f"{wall_s:>7.1f} {rate:>9} {passing:>14} {code:>4}")


def cpu_model() -> str:
    """The CPU's name (Linux's /proc/cpuinfo), else the architecture."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        return next(line.split(":", 1)[1].strip() for line in lines if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.machine()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("corpus", nargs="+", type=Path, metavar="CORPUS")
    parser.add_argument("--limit", type=int, default=None, help="keep the first N files of the corpus")
    parser.add_argument("--max-flagged", type=float, default=0.02,
                        help="the filter's bound on the share of frames over a feasibility limit (default 0.02)")
    parser.add_argument("--out", type=Path, default=Path("/tmp/otr_corpus"))
    parser.add_argument("--executors", default=",".join(EXECUTORS), help=f"any of {', '.join(EXECUTORS)}")
    args, retarget_options = parser.parse_known_args()
    labels = args.executors.split(",")
    unknown = sorted(set(labels) - set(EXECUTORS))
    if unknown:
        parser.error(f"unknown executor(s) {unknown} (choose from {list(EXECUTORS)})")
    if "ray" in labels and importlib.util.find_spec("ray") is None:
        print("ray is not installed (pip install 'otr-gym[cluster]'): its row is left out", file=sys.stderr)
        labels.remove("ray")
    shutil.rmtree(args.out, ignore_errors=True)
    inputs = list(args.corpus)
    if args.limit is not None:
        inputs = [linked_corpus(inputs, args.limit, args.out / "corpus")]
    options = [*retarget_options, "--max-flagged", str(args.max_flagged)]
    rows = []
    for label in labels:
        code, wall_s, summary = run(inputs, args.out / label, [*options, *EXECUTORS[label]])
        rows.append(row(label, code, wall_s, summary, args.out / label))
    if "serial" in labels:
        code, wall_s, summary = run(inputs, args.out / "serial", options)
        rows.append(row("resume", code, wall_s, summary, args.out / "serial"))
    print(f"{' '.join(map(str, args.corpus))}{f' (first {args.limit} files)' if args.limit else ''}; "
          f"otr retarget {' '.join(retarget_options) or '(defaults)'}; filter --max-flagged {args.max_flagged:g}")
    print(f"{platform.node()}, {cpu_model()}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f} at the end, {time.strftime('%Y-%m-%d %H:%M')}")
    print(f"{'executor':<10} {'clips':>5} {'done':>5} {'failed':>6} {'skipped':>7} {'wall s':>7} {'clips/min':>9} "
          f"{'pass filter':>14} {'exit':>4}")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
