"""Side-by-side evaluation on OMOMO largebox sub3_003 (the paper's running example).

Rows: OmniRetarget's released reference (Holosoma, scaled world), our references when given
(native with the box free; scaled with the box fixed), and two naive baselines built here so
that the table always shows what the metrics do with a poor retarget:

- ``naive native``: OmniRetarget's joint angles moved into the native world (root path ÷ sc,
  root height kept) with the box on its demonstrated path: right joints, wrong world;
- ``naive standing``: the G1 default pose walking the human pelvis path (heading from the
  pelvis), box on its demonstrated path: no interaction at all.

Usage (from the repository root; our references come from ``otr retarget``)::

    python benchmarks/compare_largebox.py \\
        [--ours-native OURS_NATIVE.npz] [--ours-scaled OURS_SCALED_FIXED.npz] \\
        [--data ../shared/data] [--json out/largebox.json] [--plots out/largebox_plots]

Prints the table (paper Table III layout) followed by the paper's own rows for comparison.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from otr_gym import robot
from otr_gym.io import write_json
from otr_gym.reference import ObjectTrack, Reference
from otr_gym.rotations import (
    linear_velocity_from_positions,
    quat_from_yaw,
    quat_to_matrix,
)
from retarget.evaluation.alignment import demo_at_times
from retarget.evaluation.plots import plot_contact_timeline, plot_metric_distributions
from retarget.evaluation.report import format_scale_notes, format_table
from retarget.evaluation.sequence import evaluate_sequence, json_safe
from retarget.inputs.demonstration import Demonstration
from retarget.inputs.readers import load_demonstration

#: The paper's rows for this clip (Sec. IV-B, Fig. "largebox"; docs/method.md "Headline numbers of the paper").
PAPER_ROWS = (
    "paper, OmniRetarget: sc 0.68, object dd 5.7 mm, dw 54 mm, R 95 %, P 58 %, J 56 %",
    "paper, OTRetarget (ours): object dd 10.0 mm, dw 42 mm, R 94 %, P 89 %, J 85 %",
)


def _box_track(demo: Demonstration, times: np.ndarray, fps: float) -> ObjectTrack:
    box = demo_at_times(demo, times).objects[0]
    return ObjectTrack(box.name, box.pos_w, box.quat_w, linear_velocity_from_positions(box.pos_w, 1.0 / fps),
                       np.zeros_like(box.pos_w))


def naive_native(holosoma: Reference, demo: Demonstration, sc: float) -> Reference:
    """OmniRetarget's joints in the native world, box on its demonstrated path."""
    qpos = holosoma.qpos()
    qpos[:, :2] /= sc
    times = np.arange(holosoma.num_frames) / holosoma.fps
    return Reference.from_qpos(qpos, holosoma.fps, objects=[_box_track(demo, times, holosoma.fps)],
                               metadata={"baseline": "naive native", "scale": 1.0})


def naive_standing(demo: Demonstration, fps: float = 50.0) -> Reference:
    """The G1 default pose on the human pelvis path (heading only), box on its demonstrated path."""
    times = np.arange(int(np.floor(demo.duration_s * fps + 1e-9)) + 1) / fps
    at = demo_at_times(demo, times)
    root = at.part_parents.index(-1)
    qpos = np.zeros((len(times), 7 + robot.NUM_JOINTS))
    qpos[:, :2] = at.part_pos_w[:, root, :2]
    qpos[:, 2] = robot.DEFAULT_ROOT_HEIGHT_M
    # SMPL-X part frames face +z of the part; the G1 faces +x: the pelvis' forward axis gives the heading
    forward = quat_to_matrix(at.part_quat_w[:, root])[..., :, 2]
    qpos[:, 3:7] = quat_from_yaw(np.arctan2(forward[:, 1], forward[:, 0]))
    qpos[:, 7:] = robot.DEFAULT_JOINT_POS
    return Reference.from_qpos(qpos, fps, objects=[_box_track(demo, times, fps)],
                               metadata={"baseline": "naive standing", "scale": 1.0})


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    p.add_argument("--ours-native", type=Path, help="our native-scale reference (box free)")
    p.add_argument("--ours-scaled", type=Path, help="our scaled-world reference (box fixed)")
    p.add_argument("--json", type=Path)
    p.add_argument("--plots", type=Path)
    args = p.parse_args(argv)

    demo_path = args.data / "omomo" / "sub3_largebox_003.pt"
    holosoma = Reference.load(args.data / "references" / "holosoma" / "sub3_largebox_003_mj_w_obj.npz")
    demo = load_demonstration(demo_path)
    rows: list[tuple[str, Reference]] = [("OmniRetarget (Holosoma)", holosoma)]
    for label, path in (("ours native, box free", args.ours_native), ("ours scaled, box fixed", args.ours_scaled)):
        if path is not None:
            rows.append((label, Reference.load(path)))
        else:
            print(f"({label}: not given, row skipped)", file=sys.stderr)
    sc_holosoma = robot.HEIGHT_M / demo.stature_m
    rows += [("naive native (OmniRetarget joints)", naive_native(holosoma, demo, sc_holosoma)),
             ("naive standing (default pose)", naive_standing(demo))]

    records = []
    for label, ref in rows:
        start = time.perf_counter()
        rec = evaluate_sequence(ref, demo, demo_source=str(demo_path)).as_dict()
        rec["seconds"] = time.perf_counter() - start
        rec["name"] = label
        records.append(rec)
    print(format_table(records, medians=False))
    print()
    print(format_scale_notes(records))
    print("\n".join(f"{r['name']}: {r['frames']} frames in {r['seconds']:.1f} s" for r in records))
    print()
    print("\n".join(PAPER_ROWS))
    if args.json:
        write_json(args.json, json_safe({"clip": str(demo_path), "sequences": records}))
    if args.plots:
        for r in records:
            plot_contact_timeline(r, args.plots / f"{r['name'].split(' (')[0].replace(' ', '_').replace(',', '')}.png")
        plot_metric_distributions(records, args.plots / "metric_distributions.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
