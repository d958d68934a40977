"""``otr demo``: the pipeline end to end on the embedded default.

Today: a G1 reference built from joint configurations (forward kinematics, finite-difference
velocities), saved atomically in the Holosoma layout, summarised and pictured.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from otr_gym import robot
from otr_gym.reference import Reference
from otr_gym.rotations import quat_from_rotvec


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")


def squat_reference(seconds: float = 3.0, fps: float = 50.0) -> Reference:
    t = np.linspace(0.0, 1.0, int(seconds * fps) + 1)
    q = np.tile(robot.default_qpos(), (len(t), 1))
    depth = np.sin(np.pi * t) ** 2
    j = robot.JOINT_NAMES.index
    for side in ("left", "right"):
        q[:, 7 + j(f"{side}_hip_pitch_joint")] -= 0.8 * depth
        q[:, 7 + j(f"{side}_knee_joint")] += 1.3 * depth
        q[:, 7 + j(f"{side}_ankle_pitch_joint")] -= 0.5 * depth
    q[:, 2] -= 0.25 * depth
    q[:, 3:7] = quat_from_rotvec(np.stack([0 * t, 0.15 * depth, 0 * t], axis=1))
    return Reference.from_qpos(q, fps, metadata={"source": "otr demo squat"})


def main(args: argparse.Namespace) -> int:
    from otr_gym.render import save_reference_strip
    from otr_gym.summary import reference_summary

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ref = squat_reference()
    path = ref.save(out / "squat.npz")
    picture = save_reference_strip(ref, out / "squat.png")
    print(f"reference: {path}")
    for key, value in reference_summary(Reference.load(path)):
        print(f"  {key:<18} {value}")
    print(f"picture:   {picture}")
    return 0
