"""Throughput of ``otr retarget`` over a corpus: serial, ``--workers 2`` and a local Ray with 1
and 2 workers, on the same clips; and whether the four give the same references.

    python benchmarks/ray_throughput.py [--clips 20] [--seconds 1.0] [--out /tmp/otr_ray_bench]

The corpus is short slices of the procedural walk (``retarget.inputs.synthetic``, seed 0, 30 fps),
retargeted at native scale. Each configuration is one ``python -m otr_gym.cli retarget`` run
into its own folder; wall time includes process start, imports and, for Ray, starting the
local cluster. References are compared with the serial run's: identical bytes, else the
largest difference of any float array.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

CONFIGS = (("serial", []), ("--workers 2", ["--workers", "2"]), ("Ray, 1 worker", ["--ray", "--workers", "1"]),
           ("Ray, 2 workers", ["--ray", "--workers", "2"]))


def make_corpus(folder: Path, clips: int, seconds: float) -> None:
    from dataclasses import replace

    from retarget.inputs.synthetic import generate

    demo = generate("walk", seed=0, fps=30.0)
    length = int(round(seconds * demo.fps))
    starts = np.linspace(0, demo.num_frames - length - 1, clips).astype(int)
    folder.mkdir(parents=True, exist_ok=True)
    for i, s in enumerate(starts):
        part = slice(s, s + length)
        replace(demo, name=f"walk_{i:02d}", part_pos_w=demo.part_pos_w[part], part_quat_w=demo.part_quat_w[part],
                annotations={}).save(folder / f"walk_{i:02d}.npz")


def max_difference(a: Path, b: Path) -> float:
    with np.load(a) as x, np.load(b) as y:
        return max((float(np.abs(x[k] - y[k]).max()) for k in x.files if x[k].dtype.kind == "f" and x[k].size),
                   default=0.0)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", type=int, default=20)
    parser.add_argument("--seconds", type=float, default=1.0, help="length of each clip (s)")
    parser.add_argument("--out", type=Path, default=Path("/tmp/otr_ray_bench"))
    args = parser.parse_args()
    shutil.rmtree(args.out, ignore_errors=True)
    corpus = args.out / "corpus"
    make_corpus(corpus, args.clips, args.seconds)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    rows = []
    for label, extra in CONFIGS:
        out = args.out / label.replace(" ", "_").replace(",", "")
        start = time.perf_counter()
        code = subprocess.run([sys.executable, "-m", "otr_gym.cli", "retarget", str(corpus), "--out", str(out),
                               *extra], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode
        wall = time.perf_counter() - start
        summary = json.loads((out / "retarget_summary.json").read_text())
        rows.append((label, out, wall, code, summary))
    serial = rows[0][1]
    print(f"{args.clips} clips of {args.seconds:g} s (procedural walk, native scale); {platform.node()}, "
          f"{os.cpu_count()} cores, {time.strftime('%Y-%m-%d')}")
    print(f"{'executor':<16} {'exit':>4} {'wall s':>7} {'clips/min':>9} {'frames/s':>8} {'ms/frame':>8} "
          f"{'workers':>7}  same bytes as serial / max diff")
    for label, out, wall, code, summary in rows:
        done = [r for r in summary["results"] if r["status"] == "done"]
        frames = sum(r["frames"] for r in done)
        workers = len({r["worker"] for r in done})
        names = sorted(p.name for p in serial.glob("*.npz"))
        same = sum((out / n).read_bytes() == (serial / n).read_bytes() for n in names)
        diff = max(max_difference(out / n, serial / n) for n in names)
        print(f"{label:<16} {code:>4} {wall:>7.1f} {60 * len(done) / wall:>9.1f} {frames / wall:>8.1f} "
              f"{np.median([r['ms_per_frame'] for r in done]):>8.1f} {workers:>7}  {same}/{len(names)} / {diff:.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
