"""Arm seeds: style-only inverse kinematics of the G1 arms on every branch of their Euler chains.

The G1 shoulder (pitch Y, roll X, yaw Z) and wrist (roll X, pitch Y, yaw Z) are Euler chains:
an orientation has two joint solutions (branches), related by (a, b, c) → (a + π, π − b, c + π),
which meet only at the gimbal singularity (middle angle ±90°). The SQP is local and warm-started,
so it follows one branch continuously; when the demonstrated arm leaves what that branch can
reach (an arm raised overhead beyond the 129° shoulder-roll limit), the iterate slides onto
the other branch against the joint limits and the warm start carries it there after the arm
comes down: on AMASS ``smplh_walk_jog_turn`` (a hop with the arms overhead at 1.2 s) both
shoulders stayed pinned at roll, pitch and yaw limits for the remaining 3 s, 48° of upper-arm
error where the best limit-respecting arm pose is 13° away.

``seed_arms`` fixes this at the warm start of a frame: per arm, when the style error of its
tracked links is large, it solves the arm's style targets alone in closed form on both branches
(shoulder and wrist, 4 candidates, joint limits respected), polishes them with a few projected
Gauss–Newton steps, and moves the arm towards the best candidate within the joint velocity
limits when that lowers the arm's style cost. The SQP then refines as usual.

Frames: rotations are link → world; joint angles in rad; the style targets are those of
``retarget.solver.style`` (R̂_ℓ = R_h(ℓ) O_ℓ, world).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from otr_gym import robot
from otr_gym.rotations import quat_to_matrix, so3_log, xyzw_to_wxyz

#: Per arm, the tracked links of ``retarget.inputs.human.STYLE_LINKS`` that the seed matches.
_TRACKED = ("shoulder_yaw_link", "elbow_link", "wrist_yaw_link")
_ARM_JOINTS = ("shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow", "wrist_roll", "wrist_pitch",
               "wrist_yaw")
_WAIST_JOINTS = ("waist_yaw_joint", "waist_roll_joint", "waist_pitch_joint")


@dataclass(frozen=True)
class SeedConfig:
    """When and how far ``seed_arms`` moves an arm (our choice, measured on the AMASS walk).

    * ``trigger_rad2`` 0.5: an arm is re-solved only when the summed squared style error of its
      three tracked links exceeds 0.5 rad² (e.g. one link 40° off); arms that track well (the
      synthetic clips, held boxes) are left to the SQP untouched.
    * ``gain`` 0.5: the candidate is taken only if it at least halves that cost, so a grasp
      that the interaction terms hold against the style is not thrown away for a small gain.
    * ``velocity_fraction`` 0.8: the move towards the candidate stays within 80 % of the joint
      velocity limit from the previous frame, leaving the SQP room inside its velocity bounds.
    * ``polish_iterations`` 4 projected Gauss–Newton steps after the closed form trade the
      upper-arm and forearm errors (the G1 elbow has one axis, the human elbow three).
    """

    trigger_rad2: float = 0.5
    gain: float = 0.5
    velocity_fraction: float = 0.8
    polish_iterations: int = 4


@dataclass(frozen=True)
class ArmChain:
    """One arm from the pelvis: waist (3) then arm (7) revolute joints, immutable."""

    joints: np.ndarray  # (10,) indices into the 29 joints: waist yaw/roll/pitch, then the arm's 7
    placement: np.ndarray  # (10, 3, 3) joint frame in its parent's frame
    axis: np.ndarray  # (10,) 0/1/2: the joint axis (x/y/z) in its own frame
    slots: np.ndarray  # (3,) indices into StyleTargets.links of shoulder yaw, elbow, wrist yaw
    lower: np.ndarray  # (7,) arm joint limits (rad)
    upper: np.ndarray  # (7,)
    velocity: np.ndarray  # (7,) arm joint velocity limits (rad/s)


def _axis_rotations(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotations (…, n, 3, 3) about the coordinate axes ``axis`` (n,) by ``angle`` (…, n)."""
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros(angle.shape + (3, 3))
    i, j = (axis + 1) % 3, (axis + 2) % 3
    n = np.arange(len(axis))
    out[..., n, axis, axis] = 1.0
    out[..., n, i, i] = c
    out[..., n, j, j] = c
    out[..., n, j, i] = s
    out[..., n, i, j] = -s
    return out


def arm_links(side: str) -> np.ndarray:
    """Indices into ``robot.BODY_NAMES`` of one arm's links (shoulder to hand), side 'left'/'right'."""
    parts = ("shoulder", "elbow", "wrist", "hand")
    return np.array([i for i, n in enumerate(robot.BODY_NAMES)
                     if n.startswith(f"{side}_") and any(p in n for p in parts)], dtype=np.intp)


@lru_cache(maxsize=1)
def arm_chains() -> tuple[ArmChain, ArmChain]:
    """The left and right arm chains of the G1 model (Pinocchio), with their style slots."""
    from retarget.inputs.human import STYLE_LINKS
    from retarget.solver.problem import kinematics

    model = kinematics().model
    style = list(STYLE_LINKS)
    chains = []
    for side in ("left", "right"):
        names = list(_WAIST_JOINTS) + [f"{side}_{j}_joint" for j in _ARM_JOINTS]
        ids = [model.getJointId(n) for n in names]
        kinds = [model.joints[i].shortname() for i in ids]
        if any(k not in ("JointModelRX", "JointModelRY", "JointModelRZ") for k in kinds):
            raise RuntimeError(f"G1 {side} arm: expected revolute joints about x/y/z, got {kinds}")
        for parent, child in zip(ids[:-1], ids[1:], strict=True):
            if model.parents[child] != parent:
                raise RuntimeError(f"G1 {side} arm: {model.names[child]} does not hang from {model.names[parent]}")
        joints = robot.joint_indices(names)
        arm = joints[3:]
        chains.append(ArmChain(
            joints=joints, placement=np.array([model.jointPlacements[i].rotation for i in ids]),
            axis=np.array(["XYZ".index(k[-1]) for k in kinds]),
            slots=np.array([style.index(f"{side}_{link}") for link in _TRACKED]),
            lower=robot.JOINT_LOWER[arm].copy(), upper=robot.JOINT_UPPER[arm].copy(),
            velocity=robot.VELOCITY_LIMIT[arm].copy()))
    return chains[0], chains[1]


def arm_rotations(chain: ArmChain, base_rot: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """World rotations (n, 10, 3, 3) of every chain link, for n angle sets (n, 10) from the
    pelvis rotation ``base_rot`` (3, 3)."""
    local = chain.placement @ _axis_rotations(chain.axis, angles)  # (n, 10, 3, 3)
    out = np.empty_like(local)
    r = np.broadcast_to(base_rot, (len(angles), 3, 3))
    for k in range(local.shape[1]):
        r = r @ local[:, k]
        out[:, k] = r
    return out


def _tracked(rot: np.ndarray) -> np.ndarray:
    """The tracked links (shoulder yaw, elbow, wrist yaw) among a chain's 10 rotations."""
    return rot[:, [5, 6, 9]]


def style_cost(chain: ArmChain, base_rot: np.ndarray, angles: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Σ over the 3 tracked links of ‖log(R_ℓ R̂_ℓᵀ)‖² (rad²), for n angle sets (n, 10)."""
    rel = _tracked(arm_rotations(chain, base_rot, angles)) @ np.swapaxes(targets, -1, -2)
    theta = np.arccos(np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0))
    return np.sum(theta ** 2, axis=-1)


def _wrap_into(angle: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The 2π-equivalent of ``angle`` inside [lower, upper] when one exists, else the closest
    limit to the wrapped angle."""
    a = (angle + np.pi) % (2.0 * np.pi) - np.pi
    for shift in (2.0 * np.pi, -2.0 * np.pi):
        b = a + shift
        a = np.where((a < lower) | (a > upper), np.where((b >= lower) & (b <= upper), b, a), a)
    return np.clip(a, lower, upper)


def _euler_branches(m: np.ndarray, axes: tuple[int, int, int]) -> np.ndarray:
    """Both solutions (…, 2, 3) of m = R_i(a) R_j(b) R_k(c) (m: (…, 3, 3), axes i, j, k distinct):
    (a, b, c) with |b| ≤ π/2, and (a + π, π − b, c + π)."""
    i, j, k = axes
    eps = 1.0 if (j - i) % 3 == 1 else -1.0  # +1 for the cyclic orders xyz, yzx, zxy
    b = np.arctan2(eps * m[..., i, k], np.hypot(m[..., i, i], m[..., i, j]))
    a = np.arctan2(-eps * m[..., j, k], m[..., k, k])
    c = np.arctan2(-eps * m[..., i, j], m[..., i, i])
    return np.stack([np.stack([a, b, c], axis=-1), np.stack([a + np.pi, np.pi - b, c + np.pi], axis=-1)], axis=-2)


def _middle_offset(chain: ArmChain, first: int) -> float:
    """Angle of the placement of joint ``first + 1`` about its own axis; the Euler triple
    ``first … first + 2`` needs that placement to turn about that axis and the last to be I."""
    p, ax = chain.placement[first + 1], chain.axis[first + 1]
    if not np.allclose(chain.placement[first + 2], np.eye(3), atol=1e-9) or not np.isclose(p[ax, ax], 1.0):
        raise RuntimeError("G1 arm: joint placements do not form an Euler chain")
    i, j = (ax + 1) % 3, (ax + 2) % 3
    return float(np.arctan2(p[j, i], p[i, i]))


def _closed_form(chain: ArmChain, base_rot: np.ndarray, waist: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """The 4 candidate arm angle sets (4, 7): shoulder on either branch matching the upper-arm
    target exactly, the elbow angle closest to the forearm target, the wrist on either branch
    matching the hand target; each angle wrapped into (else clipped to) its limits."""
    lo, hi = chain.lower, chain.upper
    angles = np.zeros((1, 10))
    angles[0, :3] = waist
    torso = arm_rotations(chain, base_rot, angles)[0, 2]
    m = chain.placement[3].T @ torso.T @ targets[0]
    shoulder = _euler_branches(m, tuple(chain.axis[3:6]))  # (2, 3)
    shoulder[:, 1] -= _middle_offset(chain, 3)
    shoulder = _wrap_into(shoulder, lo[:3], hi[:3])
    out = np.zeros((4, 7))
    for s in range(2):
        angles = np.zeros((1, 10))
        angles[0, :3], angles[0, 3:6] = waist, shoulder[s]
        upper_arm = arm_rotations(chain, base_rot, angles)[0, 5]
        # elbow about y: the angle maximising tr(R_y(e)ᵀ B) is atan2(B02 − B20, B00 + B22)
        if chain.axis[6] != 1:
            raise RuntimeError("G1 arm: the elbow is expected to turn about y")
        b = (upper_arm @ chain.placement[6]).T @ targets[1]
        elbow = np.clip(np.arctan2(b[0, 2] - b[2, 0], b[0, 0] + b[2, 2]), lo[3], hi[3])
        forearm = upper_arm @ chain.placement[6] @ _axis_rotations(chain.axis[6:7], np.array([elbow]))[0]
        m = chain.placement[7].T @ forearm.T @ targets[2]
        wrist = _euler_branches(m, tuple(chain.axis[7:10]))
        wrist[:, 1] -= _middle_offset(chain, 7)
        wrist = _wrap_into(wrist, lo[4:], hi[4:])
        out[2 * s:2 * s + 2] = np.concatenate([np.tile(shoulder[s], (2, 1)), np.full((2, 1), elbow), wrist], axis=1)
    return out


def _polish(chain: ArmChain, base_rot: np.ndarray, waist: np.ndarray, targets: np.ndarray, arm: np.ndarray,
            iterations: int, damping: float = 1e-3) -> np.ndarray:
    """Projected Gauss–Newton on the arm angles (n, 7) for Σ‖log(R_ℓ R̂_ℓᵀ)‖² (waist fixed).

    A world rotation δθ of link ℓ changes its error by ≈ δθ, and joint m turns every link
    after it about its world axis: column m of the Jacobian of link ℓ is that axis.
    """
    n = len(arm)
    angles = np.concatenate([np.broadcast_to(waist, (n, 3)), arm], axis=1)
    below = np.array([[m <= k for m in range(7)] for k in (2, 3, 6)], dtype=float)  # (3 links, 7 joints)
    for _ in range(iterations):
        rot = arm_rotations(chain, base_rot, angles)
        err = so3_log(_tracked(rot) @ np.swapaxes(targets, -1, -2)).reshape(n, 9)
        axes = rot[:, 3:, :, :][np.arange(n)[:, None], np.arange(7)[None], :, chain.axis[3:]]  # (n, 7, 3) world
        jac = np.einsum("lm,nmi->nlim", below, axes).reshape(n, 9, 7)
        jtj = np.einsum("nri,nrj->nij", jac, jac) + damping * np.eye(7)
        step = -np.linalg.solve(jtj, np.einsum("nri,nr->ni", jac, err)[..., None])[..., 0]
        angles[:, 3:] = np.clip(angles[:, 3:] + step, chain.lower, chain.upper)
    return angles[:, 3:]


def best_arm(chain: ArmChain, base_rot: np.ndarray, waist: np.ndarray, targets: np.ndarray,
             iterations: int = SeedConfig.polish_iterations) -> tuple[np.ndarray, float]:
    """Style-only arm IK: the arm angles (7,) of least Σ‖log(R_ℓ R̂_ℓᵀ)‖² over the 4 polished
    closed-form candidates, and that cost (rad²). ``targets`` (3, 3, 3): shoulder yaw, elbow
    and wrist yaw link orientations (world); ``base_rot`` the pelvis rotation, ``waist`` (3,)."""
    arm = _polish(chain, base_rot, waist, targets, _closed_form(chain, base_rot, waist, targets), iterations)
    cost = style_cost(chain, base_rot, np.concatenate([np.broadcast_to(waist, (len(arm), 3)), arm], axis=1), targets)
    k = int(np.argmin(cost))
    return arm[k], float(cost[k])


def seed_arms(q: np.ndarray, q_prev: np.ndarray | None, targets_rot: np.ndarray, fps: float,
              cfg: SeedConfig = SeedConfig(), free: tuple[bool, bool] = (True, True)) -> np.ndarray:
    """The warm start ``q`` (Pinocchio, nq) with each badly tracked arm moved towards its best
    style-only pose (see the module doc). ``targets_rot`` (S, 3, 3): the frame's style target
    rotations (StyleTargets.rot_w[t]); ``q_prev`` the previous frame's solution (None on the
    first frame: no velocity limit). ``free`` (left, right): arms near an object are left alone —
    a style-only jump of an arm that holds or touches something drives it into the object and
    leaves the SQP with conflicting non-penetration rows."""
    out = q.copy()
    base_rot = quat_to_matrix(xyzw_to_wxyz(q[3:7]))
    for chain, arm_free in zip(arm_chains(), free, strict=True):
        if not arm_free:
            continue
        targets = targets_rot[chain.slots]
        waist, arm = q[7 + chain.joints[:3]], q[7 + chain.joints[3:]]
        now = float(style_cost(chain, base_rot, np.concatenate([waist, arm])[None], targets)[0])
        if now <= cfg.trigger_rad2:
            continue
        best, cost = best_arm(chain, base_rot, waist, targets, cfg.polish_iterations)
        if cost > cfg.gain * now:
            continue
        if q_prev is not None:
            reach = cfg.velocity_fraction * chain.velocity / fps
            prev = q_prev[7 + chain.joints[3:]]
            best = np.clip(best, prev - reach, prev + reach)
        out[7 + chain.joints[3:]] = best
    return out
