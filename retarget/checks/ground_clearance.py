"""Hands out of the ground: a reference's arms re-solved, frame by frame, so that the G1's
collision geometry stays on its ground.

Why: a reference can put our hands inside the ground. Holosoma's crawl, on its slope, has the
G1's rubber hands (the simulation's three boxes per hand) up to 8.9 cm into the ramp and
platform, more than 3 cm on two thirds of its frames (``otr verify --terrain``,
*penetration*). The simulation pushes them out, so a policy tracking it has to leave the
reference's wrist angles wherever the hands are down.

``clear_ground(reference, ground)`` changes only the arm joints (shoulder, elbow, wrist; 7 a
side) of the frames where an arm's collision geometry lies below the ground, as little as
possible: min ‖W(q − q_ref)‖² with the wrists cheapest (``ClearanceCfg.weights``), subject to
every collision point of the arm (``otr_gym.robot_geometry.collision_points``: capsule end
spheres, the hands' box corners) lying ``clearance_m`` or more above the ground
(``retarget.checks.ground.Ground``: the floor, and a terrain's upward faces along their normals) and to
the joint limits. A trust-region SQP per frame: the constraints linearised with Pinocchio's
frame Jacobians, each step a ProxQP solve (``retarget.solver.qp_workspace``, elastic when the step
cannot reach them all). Root, legs and waist, and every frame whose arms are clear, keep their
configurations exactly; body poses and velocities are recomputed from the configurations
(``Reference.from_qpos``), objects and contact annotations carried over.

    otr clear-ground IN.npz OUT.npz [--terrain MESH] [--clearance-m 0.002]
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from otr_gym import robot
from otr_gym.robot_geometry import collision_points
from retarget.checks.ground import Ground

#: The arm joints the solve may move, and the bodies whose collision geometry it keeps clear.
ARM_JOINTS = tuple(j for j in robot.JOINT_NAMES if j.split("_")[1] in ("shoulder", "elbow", "wrist"))
ARM_BODIES = tuple(f"{side}_{link}" for side in ("left", "right")
                   for link in ("shoulder_yaw_link", "elbow_link", "wrist_roll_link", "wrist_pitch_link",
                                "wrist_yaw_link"))


@dataclass(frozen=True)
class ClearanceCfg:
    clearance_m: float = 0.002  # every arm collision point this far above the ground (m)
    #: Cost per rad² of moving a joint, by the part of its name: the wrists cheapest, so the
    #: solve turns a hand before it moves the arm (and with it the wrist's tracked position).
    weights: dict[str, float] = field(default_factory=lambda: {"wrist": 1.0, "elbow": 10.0, "shoulder": 10.0})
    iterations: int = 8  # SQP steps per frame at most
    step_rad: float = 0.4  # trust region per step and joint (rad)
    tolerance_m: float = 1e-4  # a frame is done once no point is deeper than clearance − this


@dataclass
class ClearanceReport:
    """What ``clear_ground`` changed: per frame, the deepest arm point below its clearance
    before and after (m, 0 when clear), and the largest joint change (rad)."""

    depth_before_m: np.ndarray  # (T,)
    depth_after_m: np.ndarray  # (T,)
    joint_change_rad: np.ndarray  # (T,) max |q − q_ref| over the arm joints
    qp_failures: int  # steps re-solved in elastic mode

    @property
    def frames_changed(self) -> int:
        return int((self.joint_change_rad > 0).sum())

    def lines(self) -> list[str]:
        changed = self.joint_change_rad > 0
        out = [f"frames with an arm point below its clearance: {int((self.depth_before_m > 0).sum())} of "
               f"{self.depth_before_m.size}, deepest {100 * self.depth_before_m.max():.1f} cm; after: "
               f"{int((self.depth_after_m > 0).sum())}, deepest {100 * self.depth_after_m.max():.2f} cm"]
        if changed.any():
            median_rad = np.median(self.joint_change_rad[changed])
            out.append(f"arm joints changed on {int(changed.sum())} frames: by {median_rad:.2f} "
                       f"rad (median), {self.joint_change_rad.max():.2f} rad at most")
        return out


@dataclass(frozen=True)
class _Arms:
    pin_model: object
    joints_v: np.ndarray  # (A,) velocity indices of ARM_JOINTS
    joints_q: np.ndarray  # (A,) configuration indices
    frames: tuple[int, ...]  # one operational frame per arm collision point
    radius: np.ndarray  # (P,) m


@lru_cache(maxsize=1)
def _arms() -> _Arms:
    model = robot.load_pinocchio_model()
    arm_points = [p for p in collision_points() if p.body in ARM_BODIES]
    frames = tuple(robot.add_point_frame(model, p.body, p.point, f"{p.geom}_clearance{k}")
                   for k, p in enumerate(arm_points))
    index = np.array([robot.JOINT_NAMES.index(j) for j in ARM_JOINTS])
    return _Arms(model, 6 + index, 7 + index, frames, np.array([p.radius for p in arm_points]))


def _clearances(arms: _Arms, data, q: np.ndarray, ground: Ground, cfg: ClearanceCfg) -> tuple[np.ndarray, np.ndarray]:
    """(g (P,) m: each point's lowest reach above ``clearance_m`` over the ground, negative
    below; the ground's normal under each point (P, 3)) at configuration ``q``."""
    import pinocchio as pin

    pin.forwardKinematics(arms.pin_model, data, q)
    pin.updateFramePlacements(arms.pin_model, data)
    height, normal = ground.under(np.array([data.oMf[f].translation for f in arms.frames]))
    return height - arms.radius - cfg.clearance_m, normal


def _clearance_rows(arms: _Arms, data, q: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """dg/dq_arm (P, A) at ``q``: each point's velocity along its ground normal per arm joint."""
    import pinocchio as pin

    m = arms.pin_model
    pin.computeJointJacobians(m, data, q)
    rows = np.stack([normal[i] @ pin.getFrameJacobian(m, data, f, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[:3]
                     for i, f in enumerate(arms.frames)])
    return rows[:, arms.joints_v]


def clear_ground(reference, ground: Ground | None = None, cfg: ClearanceCfg | None = None):
    """(the reference with its arms out of ``ground`` (default: the floor z = 0), ClearanceReport)."""
    from otr_gym.reference import Reference
    from retarget.solver.qp_workspace import QPWorkspace

    cfg = cfg or ClearanceCfg()
    ground = ground or Ground.floor()
    arms = _arms()
    m = arms.pin_model
    data = m.createData()
    q_all = robot.qpos_mujoco_to_pinocchio(reference.qpos())
    lo, hi = m.lowerPositionLimit[arms.joints_q], m.upperPositionLimit[arms.joints_q]
    w = np.array([next(v for k, v in cfg.weights.items() if f"_{k}_" in j) for j in ARM_JOINTS])
    H = np.diag(2.0 * w)
    workspace = QPWorkspace(eps_abs=1e-7)
    T = q_all.shape[0]
    before, after, change = np.zeros(T), np.zeros(T), np.zeros(T)
    for t in range(T):
        q_ref = q_all[t].copy()
        q = q_ref.copy()
        for step_count in range(cfg.iterations + 1):
            g, normal = _clearances(arms, data, q, ground, cfg)
            if step_count == 0:
                before[t] = max(0.0, -g.min())
            if g.min() >= -cfg.tolerance_m or step_count == cfg.iterations:
                break
            x = q[arms.joints_q]
            # the trust region, inside the joint limits; a reference already beyond a limit may
            # stay there (the boxes always hold 0) but not go farther
            box_lo = np.minimum(np.maximum(lo - x, -cfg.step_rad), 0.0)
            box_hi = np.maximum(np.minimum(hi - x, cfg.step_rad), 0.0)
            step = workspace.solve(H, 2.0 * w * (x - q_ref[arms.joints_q]), _clearance_rows(arms, data, q, normal),
                                   -g, box_lo, box_hi)
            q[arms.joints_q] = x + step
        if step_count == 0:  # clear as it was: the frame keeps its configuration
            continue
        after[t] = max(0.0, -g.min())
        change[t] = np.abs(q[arms.joints_q] - q_ref[arms.joints_q]).max()
        q_all[t] = q
    qpos = robot.qpos_pinocchio_to_mujoco(q_all)
    metadata = {**reference.metadata, "ground_clearance": {
        "clearance_m": cfg.clearance_m, "ground": ground.describe(), "frames_changed": int((change > 0).sum())}}
    out = Reference.from_qpos(qpos, reference.fps, objects=reference.objects, contacts=reference.contacts,
                              metadata=metadata)
    return out, ClearanceReport(before, after, change, workspace.failures)


def configure_parser(p) -> None:
    p.add_argument("reference", help="reference .npz whose arms go into the ground")
    p.add_argument("out", help="where to write the cleared reference (.npz; written atomically)")
    p.add_argument("--terrain", help="terrain mesh the clip was recorded on (its world frame, metres; the file "
                   "given to env.terrain.meshes)")
    p.add_argument("--clearance-m", type=float, default=ClearanceCfg.clearance_m,
                   help="height every arm collision point keeps above the ground (m, default %(default)s)")


def main(args) -> int:
    """``otr clear-ground REFERENCE OUT [--terrain MESH] [--clearance-m M]``. A missing or unreadable
    reference or terrain: a message naming the file, exit code 2."""
    import sys

    from retarget.checks.ground import load_clip_on_ground

    if args.clearance_m < 0:
        print("clear-ground: --clearance-m must be >= 0", file=sys.stderr)
        return 2
    try:
        reference, ground = load_clip_on_ground(args.reference, args.terrain)
    except ValueError as exc:  # InvalidReferenceError, InvalidMeshError: the file named
        print(f"clear-ground: {exc}", file=sys.stderr)
        return 2
    cleared, report = clear_ground(reference, ground, ClearanceCfg(clearance_m=args.clearance_m))
    print("\n".join(report.lines()))
    print(f"wrote {cleared.save(Path(args.out))}")
    return 0

