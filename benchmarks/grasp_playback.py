"""Can the reference's hands hold its object? Kinematic playback of box references.

The robot is put on the reference at every physics step (qpos interpolated between frames,
qvel from the reference; immovable within the step's contact solve) and only the objects are simulated:
MuJoCo on the CPU, the OTR-G1-BoxTrack-v0 model (fitted hand boxes, grasp-fitted box, nominal mass and friction, no
randomisation): what a policy that tracks perfectly, squeezing no harder than the reference's
hands, does to the box. A box that slips or tips here asks the policy for more than tracking
(a firmer squeeze, another hold). Prints one row per reference (frames
carried, box position error mean / p95 in cm, box orientation error mean / max in degrees, the
frame where the box passed the task's 25 cm object termination, then the reference's hold while no
support carries the box: frames held, the hands' height above the box centre in half-heights
(-1 its bottom face, +1 its top; below 0 the box hangs over its hands and tips unless squeezed):
that of the box point nearest each hand, then that of the hand geoms' centre (below -1: the hand
is under the box; a hand wrapping the bottom edge reads -1 by its nearest point only), then the
box centre's height and tilt), then per reference the robot collision geoms that the reference
itself puts inside the simulated objects (depth, frames; hands marked: their squeeze is the
grasp, any other link shoves the box), optionally a PNG of both errors per frame.

One playback is chaotic (a float rounding change once moved a put-down by a frame, and a few
millimetres of reference change the mean error by centimetres), so ``--draws N`` also plays each
reference N more times with the box's friction, mass and inertia drawn as in training
(``objects.randomization``; draw k seeded by ``--seed`` + k, the same draws for every reference)
and prints, per reference, the spread of the runs' mean box error: compare references by that,
not by one run.

    python benchmarks/grasp_playback.py out/omomo/sub3_largebox_003.npz \\
        ../shared/data/references/holosoma/sub3_largebox_003_mj_w_obj.npz \\
        --object-mesh largebox=../shared/data/objects/largebox.obj --png grasp_playback.png
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from agents.train import parse_sets
from envs.kinematic_playback import DRAWS_HEADER, Playback, draws_row, draws_summary, play_draws
from otr_gym.io import save_figure, write_json


def plot(results: list[Playback], out_png: str | Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
    for r in results:
        frames = np.arange(1, r.frames + 1)
        axes[0].plot(frames, r.pos_error_cm, lw=1.1, label=Path(r.reference).name)
        axes[1].plot(frames, r.ori_error_deg, lw=1.1, label=Path(r.reference).name)
    axes[0].axhline(100 * results[0].termination_m, color="k", lw=0.8, ls="--")
    for ax, title in zip(axes, ("box position error (cm)", "box orientation error (deg)"), strict=True):
        ax.set_title(f"robot on the reference, box simulated: {title}", fontsize=9)
        ax.set_xlabel("frame (50 fps)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, out_png)


def draws_table(drawn: dict[str, list[Playback]]) -> str:
    """Per reference: ``envs.kinematic_playback.draws_summary`` as a markdown table."""
    return "\n".join([DRAWS_HEADER] + [draws_row(Path(ref).name, draws_summary(runs)) for ref, runs in drawn.items()])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("references", nargs="+", help="box references (.npz), one clip each")
    parser.add_argument("--object-mesh", action="append", default=[], metavar="NAME=FILE",
                        help="mesh of an object the file does not embed (Holosoma's: largebox=…/largebox.obj)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="box config override by dotted path (configs/env/box.yaml), e.g. objects.grasp_fit=false")
    parser.add_argument("--draws", type=int, default=0, help="also play each reference this many times under "
                        "the training's object randomisation and print the spread (default 0)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first draw (draw k: seed + k)")
    parser.add_argument("--png", help="box position and orientation error per frame, every reference")
    parser.add_argument("--json", help="per-frame errors of every reference")
    args = parser.parse_args(argv)
    meshes = dict(item.split("=", 1) for item in args.object_mesh if "=" in item)
    if len(meshes) != len(args.object_mesh):
        parser.error("--object-mesh takes NAME=FILE")
    try:
        overrides = parse_sets(args.set)
    except ValueError as exc:
        parser.error(str(exc))
    if args.draws < 0:
        parser.error(f"--draws must be >= 0, got {args.draws}")
    results, drawn = [], {}
    for ref in tqdm(args.references, desc="references", disable=not args.draws):
        # a reference with objects it cannot place (no mesh, no objects) is named by the loader
        nominal, *draws = play_draws(ref, [None, *range(args.seed, args.seed + args.draws)], meshes, overrides)
        results.append(nominal)
        drawn[ref] = draws
        print(f"{ref}: {nominal.frames} frames played", file=sys.stderr)
    print("| reference | frames carried | box error cm mean / p95 | orientation error deg mean / max | box past 25 cm "
          "| frames held | hands above the box centre (half-heights) | hand centres above it | "
          "box centre height, tilt (held) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in results:
        print(r.row())
    for r in results:
        print(r.overlap_line())
    if args.draws:
        print(f"\nunder the training's object randomisation ({args.draws} draws, seeds {args.seed}–"
              f"{args.seed + args.draws - 1}):\n")
        print(draws_table(drawn))
    if args.png:
        print(f"wrote {plot(results, args.png)}")
    if args.json:
        out = {"nominal": [asdict(r) for r in results],
               "draws": {ref: [asdict(r) for r in runs] for ref, runs in drawn.items()}}
        print(f"wrote {write_json(args.json, out)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
