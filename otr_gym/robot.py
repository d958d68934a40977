"""The 29-DoF Unitree G1: the one place that states its specification.

Joint order is the MJCF depth-first order, which equals the motor index order of the
low-level interface (``unitree_hg`` LowCmd/LowState, slots 0..28; slots 29..34 unused).

PD gains follow the mjlab derivation (docs/environment.md §1): kp = J·ω², kd = 2ζ·J·ω with
ω = 2π·10 rad/s, ζ = 2, where J is the reflected inertia of the motor's two-stage
planetary gearbox, J = I₁(g₂g₃)² + I₂g₃² + I₃. The ankle and waist roll/pitch joints are
4-bar linkages driven by two 5020 motors, so their kp, kd, effort and armature are doubled.
Action scale = 0.25 · effort / kp; the PD target is q* = q_default + scale · a.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ASSETS_DIR = Path(__file__).resolve().parent / "assets"
G1_MJCF = ASSETS_DIR / "g1" / "g1.xml"

NUM_JOINTS = 29

JOINT_NAMES: tuple[str, ...] = (
    "left_hip_pitch_joint", "left_hip_roll_joint", "left_hip_yaw_joint",
    "left_knee_joint", "left_ankle_pitch_joint", "left_ankle_roll_joint",
    "right_hip_pitch_joint", "right_hip_roll_joint", "right_hip_yaw_joint",
    "right_knee_joint", "right_ankle_pitch_joint", "right_ankle_roll_joint",
    "waist_yaw_joint", "waist_roll_joint", "waist_pitch_joint",
    "left_shoulder_pitch_joint", "left_shoulder_roll_joint", "left_shoulder_yaw_joint",
    "left_elbow_joint", "left_wrist_roll_joint", "left_wrist_pitch_joint", "left_wrist_yaw_joint",
    "right_shoulder_pitch_joint", "right_shoulder_roll_joint", "right_shoulder_yaw_joint",
    "right_elbow_joint", "right_wrist_roll_joint", "right_wrist_pitch_joint", "right_wrist_yaw_joint",
)

#: Rigid bodies of the MJCF in model order (world excluded).
BODY_NAMES: tuple[str, ...] = (
    "pelvis",
    "left_hip_pitch_link", "left_hip_roll_link", "left_hip_yaw_link", "left_knee_link",
    "left_ankle_pitch_link", "left_ankle_roll_link",
    "right_hip_pitch_link", "right_hip_roll_link", "right_hip_yaw_link", "right_knee_link",
    "right_ankle_pitch_link", "right_ankle_roll_link",
    "waist_yaw_link", "waist_roll_link", "torso_link",
    "left_shoulder_pitch_link", "left_shoulder_roll_link", "left_shoulder_yaw_link",
    "left_elbow_link", "left_wrist_roll_link", "left_wrist_pitch_link", "left_wrist_yaw_link",
    "right_shoulder_pitch_link", "right_shoulder_roll_link", "right_shoulder_yaw_link",
    "right_elbow_link", "right_wrist_roll_link", "right_wrist_pitch_link", "right_wrist_yaw_link",
)

ROOT_BODY = "pelvis"
ANCHOR_BODY = "torso_link"
#: The 14 bodies tracked by rewards and MPJPE (docs/environment.md §2, paper Sec. IV-E).
TRACKED_BODIES: tuple[str, ...] = (
    "pelvis",
    "left_hip_roll_link", "right_hip_roll_link",
    "left_knee_link", "right_knee_link",
    "left_ankle_roll_link", "right_ankle_roll_link",
    "torso_link",
    "left_shoulder_roll_link", "right_shoulder_roll_link",
    "left_elbow_link", "right_elbow_link",
    "left_wrist_yaw_link", "right_wrist_yaw_link",
)
FEET: tuple[str, str] = ("left_ankle_roll_link", "right_ankle_roll_link")
HANDS: tuple[str, str] = ("left_wrist_yaw_link", "right_wrist_yaw_link")
END_EFFECTORS: tuple[str, ...] = FEET + HANDS
#: Height of the G1 standing upright (m); used for the scaled ablation (docs/method.md "Modes").
HEIGHT_M = 1.32
#: Root height of the default ("knees bent") standing pose (m).
DEFAULT_ROOT_HEIGHT_M = 0.76

# ------------------------------------------------------------------ actuators


@dataclass(frozen=True)
class Motor:
    """A Unitree joint motor: rotor inertias (kg·m²) and gear ratios of its 2 stages."""

    name: str
    rotor_inertia: tuple[float, float, float]
    gears: tuple[float, float, float]
    effort_limit: float  # N·m
    velocity_limit: float  # rad/s

    @property
    def armature(self) -> float:
        """Reflected inertia J = I₁(g₂g₃)² + I₂g₃² + I₃ (kg·m²)."""
        (i1, i2, i3), (_, g2, g3) = self.rotor_inertia, self.gears
        return i1 * (g2 * g3) ** 2 + i2 * g3**2 + i3


MOTOR_5020 = Motor("5020", (0.139e-4, 0.017e-4, 0.169e-4), (1, 1 + 46 / 18, 1 + 56 / 16), 25.0, 37.0)
MOTOR_7520_14 = Motor("7520-14", (0.489e-4, 0.098e-4, 0.533e-4), (1, 4.5, 1 + 48 / 22), 88.0, 32.0)
MOTOR_7520_22 = Motor("7520-22", (0.489e-4, 0.109e-4, 0.738e-4), (1, 4.5, 5), 139.0, 20.0)
MOTOR_4010 = Motor("4010", (0.068e-4, 0.0, 0.0), (1, 5, 5), 5.0, 22.0)

NATURAL_FREQUENCY = 2.0 * math.pi * 10.0  # ω (rad/s)
DAMPING_RATIO = 2.0  # ζ


def _motor_of(joint: str) -> tuple[Motor, int]:
    """(motor, count): count = 2 for the 4-bar linkages driven by two 5020 motors."""
    if "ankle" in joint or joint in ("waist_roll_joint", "waist_pitch_joint"):
        return MOTOR_5020, 2
    if "hip_roll" in joint or "knee" in joint:
        return MOTOR_7520_22, 1
    if "hip_pitch" in joint or "hip_yaw" in joint or joint == "waist_yaw_joint":
        return MOTOR_7520_14, 1
    if "wrist_pitch" in joint or "wrist_yaw" in joint:
        return MOTOR_4010, 1
    return MOTOR_5020, 1  # shoulders, elbows, wrist roll


def _per_joint(fn) -> np.ndarray:
    return np.array([fn(*_motor_of(j)) for j in JOINT_NAMES], dtype=np.float64)


ARMATURE = _per_joint(lambda m, n: n * m.armature)
KP = ARMATURE * NATURAL_FREQUENCY**2
KD = 2.0 * DAMPING_RATIO * ARMATURE * NATURAL_FREQUENCY
EFFORT_LIMIT = _per_joint(lambda m, n: n * m.effort_limit)
#: Joint velocity limits (rad/s); linkage joints keep the single motor's speed.
VELOCITY_LIMIT = _per_joint(lambda m, n: m.velocity_limit)
ACTION_SCALE = 0.25 * EFFORT_LIMIT / KP

# ------------------------------------------------------------------ kinematics

#: Joint position limits (rad), as in the MJCF (left/right roll limits mirrored).
_LIMITS = {
    "hip_pitch": (-2.5307, 2.8798),
    "left_hip_roll": (-0.5236, 2.9671),
    "right_hip_roll": (-2.9671, 0.5236),
    "hip_yaw": (-2.7576, 2.7576),
    "knee": (-0.087267, 2.8798),
    "ankle_pitch": (-0.87267, 0.5236),
    "ankle_roll": (-0.2618, 0.2618),
    "waist_yaw": (-2.618, 2.618),
    "waist_roll": (-0.52, 0.52),
    "waist_pitch": (-0.52, 0.52),
    "shoulder_pitch": (-3.0892, 2.6704),
    "left_shoulder_roll": (-1.5882, 2.2515),
    "right_shoulder_roll": (-2.2515, 1.5882),
    "shoulder_yaw": (-2.618, 2.618),
    "elbow": (-1.0472, 2.0944),
    "wrist_roll": (-1.97222, 1.97222),
    "wrist_pitch": (-1.61443, 1.61443),
    "wrist_yaw": (-1.61443, 1.61443),
}


def _limit(joint: str) -> tuple[float, float]:
    stem = joint.removesuffix("_joint")
    if stem in _LIMITS:
        return _LIMITS[stem]
    return _LIMITS[stem.split("_", 1)[1]]


JOINT_LOWER = np.array([_limit(j)[0] for j in JOINT_NAMES])
JOINT_UPPER = np.array([_limit(j)[1] for j in JOINT_NAMES])

#: Default "knees bent" pose (rad), root at z = DEFAULT_ROOT_HEIGHT_M, identity orientation.
_DEFAULT = {
    "hip_pitch": -0.312, "knee": 0.669, "ankle_pitch": -0.363,
    "shoulder_pitch": 0.2, "left_shoulder_roll": 0.2, "right_shoulder_roll": -0.2, "elbow": 0.6,
}


def _default(joint: str) -> float:
    stem = joint.removesuffix("_joint")
    if stem in _DEFAULT:
        return _DEFAULT[stem]
    return _DEFAULT.get(stem.split("_", 1)[1], 0.0)


DEFAULT_JOINT_POS = np.array([_default(j) for j in JOINT_NAMES])

#: Policy joint index -> low-level motor index (identity for the 29-DoF G1; slots 29..34 unused).
MOTOR_INDEX = np.arange(NUM_JOINTS)
NUM_MOTOR_SLOTS = 35


def soft_joint_limits(factor: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
    """Limits shrunk about their midpoint to ``factor`` of the range (docs/environment.md §4: 90 %)."""
    mid, half = 0.5 * (JOINT_UPPER + JOINT_LOWER), 0.5 * (JOINT_UPPER - JOINT_LOWER)
    return mid - factor * half, mid + factor * half


def indices_by_name(names, known, what: str) -> np.ndarray:
    """Indices of ``names`` in the sequence ``known``; unknown names raise KeyError listing them."""
    index = {n: i for i, n in enumerate(known)}
    unknown = [n for n in names if n not in index]
    if unknown:
        raise KeyError(f"unknown {what} names: {unknown}")
    return np.array([index[n] for n in names], dtype=np.int64)


def joint_indices(names) -> np.ndarray:
    """Indices of ``names`` in the G1 joint order."""
    return indices_by_name(names, JOINT_NAMES, "G1 joint")


def body_indices(names) -> np.ndarray:
    """Indices of ``names`` in BODY_NAMES."""
    return indices_by_name(names, BODY_NAMES, "G1 body")


def default_qpos() -> np.ndarray:
    """MuJoCo qpos of the default pose: root xyz, root quat wxyz, 29 joints."""
    return np.concatenate([[0.0, 0.0, DEFAULT_ROOT_HEIGHT_M, 1.0, 0.0, 0.0, 0.0], DEFAULT_JOINT_POS])


def load_pinocchio_model():
    """Pinocchio model of the G1 MJCF; the MJCF's ``freejoint`` becomes the free-flyer root.

    Pinocchio's configuration is [xyz, quat xyzw, 29 joints] in the same joint order.
    (pin 4.1 reads the freejoint itself; passing ``JointModelFreeFlyer()`` as well is refused.)
    """
    import pinocchio as pin

    model = pin.buildModelFromMJCF(str(G1_MJCF))
    if model.joints[1].shortname() != "JointModelFreeFlyer" or model.nq != 7 + NUM_JOINTS:
        raise RuntimeError(f"{G1_MJCF}: expected a free-flyer root and {7 + NUM_JOINTS} configuration variables")
    names = [model.names[i] for i in range(2, model.njoints)]
    if tuple(names) != JOINT_NAMES:
        raise RuntimeError(f"{G1_MJCF}: Pinocchio joint order {names} differs from JOINT_NAMES")
    return model


def add_point_frame(model, body: str, point_b, name: str) -> int:
    """Add to the Pinocchio ``model`` (``load_pinocchio_model``) an operational frame named
    ``name`` at ``point_b`` (3,) m in the frame of ``body`` (the MJCF body frame); returns its id."""
    import pinocchio as pin

    parent_id = model.getFrameId(body)
    parent = model.frames[parent_id]
    placement = parent.placement * pin.SE3(np.eye(3), np.asarray(point_b, dtype=np.float64))
    return model.addFrame(pin.Frame(name, parent.parentJoint, parent_id, placement, pin.FrameType.OP_FRAME))


def qpos_mujoco_to_pinocchio(qpos: np.ndarray) -> np.ndarray:
    """[xyz, wxyz, q] -> [xyz, xyzw, q] on the last axis."""
    out = np.array(qpos, dtype=np.float64, copy=True)
    out[..., 3:7] = qpos[..., [4, 5, 6, 3]]
    return out


def qpos_pinocchio_to_mujoco(q: np.ndarray) -> np.ndarray:
    """[xyz, xyzw, q] -> [xyz, wxyz, q] on the last axis."""
    out = np.array(q, dtype=np.float64, copy=True)
    out[..., 3:7] = q[..., [6, 3, 4, 5]]
    return out
