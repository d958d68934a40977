"""``otr demo``: the pipeline end to end on the embedded default.

The embedded default is a procedurally generated demonstration (``retarget.synthetic``): a
person walks to a box on the floor, squats, lifts it, carries it and places it on a table.
The demo writes, under ``--out``:

- ``box_carry_demo.npz``: the demonstration (our format; ``otr inspect`` reads it),
- ``box_carry.png``: a picture strip of the demonstration,
and prints a summary of each.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default: out/demo)")
    p.add_argument("--kind", default="box_carry", choices=("box_carry", "walk", "crawl"),
                   help="which embedded demonstration to run (default: box_carry)")
    p.add_argument("--seed", type=int, default=0, help="seed of the procedural generator")


def _print_rows(rows) -> None:
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"  {key:<{width}}  {value}")


def main(args: argparse.Namespace) -> int:
    from otr_gym.summary import demonstration_summary
    from retarget.pictures import save_comparison
    from retarget.synthetic import generate

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    demo = generate(args.kind, seed=args.seed)
    demo_path = demo.save(out / f"{args.kind}_demo.npz")
    print(f"[1/2] demonstration {demo_path} ({time.perf_counter() - start:.1f} s)")
    _print_rows(demonstration_summary(demo_path, None))

    start = time.perf_counter()
    picture = save_comparison(demo, None, out / f"{args.kind}.png")
    print(f"[2/2] picture {picture} ({time.perf_counter() - start:.1f} s)")
    return 0
