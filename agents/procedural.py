"""Procedural G1 references: standing still, a straight walk with planted feet, and an in-place
sway (squats, side sway, waist twist and arm waves over planted feet).

For tests and for the training recipe when no retargeted walk is at hand. The walk is built
from a footstep plan, not from joint sinusoids, so stance feet do not slide:

1. footsteps alternate (right foot first), each step ``step_length_m`` ahead of the other
   foot, swing for ``swing_s`` then double support; the first and last steps are half steps
   so the clip starts and ends in the default stance;
2. the swing foot follows a smoothstep in x and a sine arc in z; stance feet stay put;
3. the pelvis follows the mean of the feet (smoothed) in x and sways towards the stance foot;
4. each leg's 6 joints solve the foot pose (position + flat orientation) by damped least
   squares on MuJoCo's body Jacobian, warm-started from the previous frame;
5. arms swing opposite to the legs; waist and wrists stay at the default pose.

The sway keeps both feet on the ground, so an open-loop joint-target player (the deployment's
"reference policy", ``otr reference-policy``) can follow it with stiff gains; the
walk needs a trained, closed-loop policy.

``otr procedural walk out.npz`` writes a walk (see ``otr procedural --help``).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np

from otr_gym import robot
from otr_gym.reference import Reference
from otr_gym.rotations import quat_conj, quat_mul, quat_to_rotvec
from otr_gym.scene import robot_model

_LEGS = {  # foot body -> its 6 joint columns in G1 order (= qvel index - 6)
    "left_ankle_roll_link": np.arange(0, 6),
    "right_ankle_roll_link": np.arange(6, 12),
}


#: How long a standing clip holds the pose unless told otherwise (s).
STAND_S = 2.0


def standing_reference(duration_s: float = STAND_S, fps: float = 50.0) -> Reference:
    """The default ("knees bent") pose held still, feet on the ground."""
    frames = int(round(duration_s * fps)) + 1
    qpos = np.tile(robot.default_qpos(), (frames, 1))
    return Reference.from_qpos(qpos, fps, metadata={"source": "procedural", "motion": "stand"})


@dataclass(frozen=True)
class WalkSpec:
    steps: int = 12  # number of footsteps (the last one closes the stance)
    step_length_m: float = 0.25  # foot-to-foot advance per step: speed ≈ step_length / step time
    step_height_m: float = 0.08
    swing_s: float = 0.4
    double_support_s: float = 0.1
    pelvis_height_m: float = 0.75  # a little below the default 0.76 so the legs never straighten
    sway_m: float = 0.03
    arm_swing_rad_per_m: float = 1.5  # shoulder pitch per metre of foot lead over the pelvis
    stand_s: float = 0.5  # still stance before and after the walk
    fps: float = 50.0


def walking_reference(spec: WalkSpec = WalkSpec()) -> Reference:
    """A straight walk along +x (world), planted feet; see the module docstring."""
    feet_xyz, stance_side = _footstep_trajectories(spec)
    T = feet_xyz.shape[0]
    qpos = np.tile(robot.default_qpos(), (T, 1))
    # the pelvis keeps its default offset from the feet's midpoint
    mean_x = _smooth(feet_xyz[:, :, 0].mean(axis=1), spec.fps, 0.15)
    qpos[:, 0] = mean_x - feet_xyz[0, :, 0].mean()
    qpos[:, 1] = _smooth(spec.sway_m * stance_side, spec.fps, 0.1)
    qpos[:, 2] = spec.pelvis_height_m
    joints = qpos[:, 7:]
    for foot_index, side in enumerate(("left", "right")):
        lead = feet_xyz[:, foot_index, 0] - mean_x
        joints[:, robot.JOINT_NAMES.index(f"{side}_shoulder_pitch_joint")] += spec.arm_swing_rad_per_m * lead
    _solve_legs(qpos, feet_xyz)
    return Reference.from_qpos(qpos, spec.fps, metadata={
        "source": "procedural", "motion": "walk", "step_length_m": spec.step_length_m,
        "step_time_s": spec.swing_s + spec.double_support_s, "steps": spec.steps})


@dataclass(frozen=True)
class SwaySpec:
    duration_s: float = 20.0
    # Amplitudes an open-loop player with stiff gains survives (measured, 500 Hz MuJoCo: these
    # for 64 s at 13 mm MPJPE; a 6 cm squat with a 3 cm sway topples it after 3.3 s).
    squat_m: float = 0.04  # pelvis dips this far below its standing height
    squat_period_s: float = 4.0
    sway_m: float = 0.02  # side to side over the feet
    sway_period_s: float = 3.0
    twist_rad: float = 0.2  # waist yaw amplitude
    twist_period_s: float = 5.0
    wave_rad: float = 0.4  # shoulder pitch / elbow amplitude
    wave_period_s: float = 2.0
    ease_s: float = 1.0  # amplitudes fade in and out over this time (still stance at both ends)
    fps: float = 50.0


def sway_reference(spec: SwaySpec = SwaySpec()) -> Reference:
    """Feet planted at the default stance; the pelvis squats and sways (legs solved for flat
    feet), the waist twists and the arms wave; still default pose at both ends."""
    t = np.arange(int(round(spec.duration_s * spec.fps)) + 1) / spec.fps
    ease = np.clip(np.minimum(t, t[-1] - t) / spec.ease_s, 0.0, 1.0)
    ease = ease * ease * (3 - 2 * ease)
    qpos = np.tile(robot.default_qpos(), (t.size, 1))
    qpos[:, 1] += ease * spec.sway_m * np.sin(2 * np.pi * t / spec.sway_period_s)
    qpos[:, 2] -= ease * spec.squat_m * 0.5 * (1 - np.cos(2 * np.pi * t / spec.squat_period_s))
    joints = qpos[:, 7:]
    joints[:, robot.JOINT_NAMES.index("waist_yaw_joint")] += ease * spec.twist_rad * np.sin(
        2 * np.pi * t / spec.twist_period_s)
    wave = ease * spec.wave_rad * np.sin(2 * np.pi * t / spec.wave_period_s)
    for side, sign in (("left", 1.0), ("right", -1.0)):
        joints[:, robot.JOINT_NAMES.index(f"{side}_shoulder_pitch_joint")] += sign * wave
        joints[:, robot.JOINT_NAMES.index(f"{side}_elbow_joint")] += 0.5 * np.abs(wave)
    _solve_legs(qpos, np.repeat(_default_feet()[None], t.size, axis=0))
    return Reference.from_qpos(qpos, spec.fps, metadata={"source": "procedural", "motion": "sway"})


def _footstep_trajectories(spec: WalkSpec) -> tuple[np.ndarray, np.ndarray]:
    """(T, 2, 3) left/right ankle_roll_link targets (m, world) and (T,) +1 while the left foot
    supports alone, −1 while the right does, 0 in double support."""
    dt = 1.0 / spec.fps
    step_s = spec.swing_s + spec.double_support_s
    duration = 2 * spec.stand_s + spec.steps * step_s
    t = np.arange(int(round(duration * spec.fps)) + 1) * dt
    home = _default_feet()
    feet = np.repeat(home[None], t.size, axis=0)
    stance = np.zeros(t.size)
    x = home[:, 0].copy()
    for k in range(spec.steps):
        side = 1 if k % 2 == 0 else 0  # right foot (index 1) swings first
        if k == spec.steps - 1:
            target = x[1 - side]  # close the stance: feet side by side
        else:
            target = x[1 - side] + (0.5 if k == 0 else 1.0) * spec.step_length_m
        start = spec.stand_s + k * step_s
        s = np.clip((t - start) / spec.swing_s, 0.0, 1.0)
        swinging = (t >= start) & (t < start + spec.swing_s)
        after = t >= start
        smooth = s * s * (3 - 2 * s)
        feet[after, side, 0] = x[side] + (target - x[side]) * smooth[after]
        feet[swinging, side, 2] += spec.step_height_m * np.sin(np.pi * s[swinging])
        stance[swinging] = 1.0 if side == 1 else -1.0
        x[side] = target
    return feet, stance


def _default_feet() -> np.ndarray:
    import mujoco

    model = robot_model(visual=False)
    data = mujoco.MjData(model)
    data.qpos[:] = robot.default_qpos()
    mujoco.mj_kinematics(model, data)
    return np.stack([data.xpos[model.body(b).id].copy() for b in _LEGS])


def _smooth(x: np.ndarray, fps: float, sigma_s: float) -> np.ndarray:
    """Gaussian smoothing with edge padding (keeps the still ends still)."""
    half = int(np.ceil(3 * sigma_s * fps))
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / (sigma_s * fps)) ** 2)
    return np.convolve(np.pad(x, half, mode="edge"), k / k.sum(), mode="valid")


def _solve_legs(qpos: np.ndarray, feet_xyz: np.ndarray, iterations: int = 50, damping: float = 1e-3) -> None:
    """In place: leg joints of every frame so each foot reaches its target position with the
    default (flat) foot orientation; damped least squares on the 6-D body Jacobian."""
    import mujoco

    model = robot_model(visual=False)
    data = mujoco.MjData(model)
    data.qpos[:] = robot.default_qpos()
    mujoco.mj_kinematics(model, data)
    ids = {b: model.body(b).id for b in _LEGS}
    flat = {b: data.xquat[i].copy() for b, i in ids.items()}
    lower, upper = robot.JOINT_LOWER, robot.JOINT_UPPER
    jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    q_prev = qpos[0, 7:].copy()
    for t in range(qpos.shape[0]):
        q = qpos[t].copy()
        q[7:][np.r_[_LEGS["left_ankle_roll_link"], _LEGS["right_ankle_roll_link"]]] = \
            q_prev[np.r_[_LEGS["left_ankle_roll_link"], _LEGS["right_ankle_roll_link"]]]
        for _ in range(iterations):
            data.qpos[:] = q
            mujoco.mj_kinematics(model, data)
            mujoco.mj_comPos(model, data)
            worst = 0.0
            for foot_index, (body, cols) in enumerate(_LEGS.items()):
                bid = ids[body]
                err_p = feet_xyz[t, foot_index] - data.xpos[bid]
                err_r = quat_to_rotvec(quat_mul(flat[body], quat_conj(data.xquat[bid])))
                err = np.concatenate([err_p, err_r])
                worst = max(worst, float(np.abs(err).max()))
                mujoco.mj_jacBody(model, data, jacp, jacr, bid)
                J = np.vstack([jacp, jacr])[:, 6 + cols]
                dq = J.T @ np.linalg.solve(J @ J.T + damping * np.eye(6), err)
                q[7 + cols] = np.clip(q[7 + cols] + dq, lower[cols], upper[cols])
            if worst < 1e-5:
                break
        qpos[t, 7:] = q[7:]
        q_prev = q[7:]


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """``otr procedural``'s arguments."""
    parser.add_argument("motion", choices=("walk", "stand", "sway"),
                        help="walk: a straight walk along +x with planted feet; stand: the default pose held; "
                        "sway: squats, side sway, waist twist and arm waves over planted feet")
    parser.add_argument("out", help="output reference .npz (written atomically)")
    parser.add_argument("--steps", type=int, default=WalkSpec.steps,
                        help="walk: number of footsteps (default: %(default)s)")
    parser.add_argument("--step-length", type=float, default=WalkSpec.step_length_m,
                        help="walk: foot-to-foot advance per step (m; default: %(default)s)")
    parser.add_argument("--duration", type=float, default=None,
                        help=f"stand / sway: length of the clip (s; default: {STAND_S:g} / {SwaySpec.duration_s:g})")


def main(args: argparse.Namespace) -> int:
    """``otr procedural MOTION OUT``: write the clip and print its length and travel."""
    if args.motion == "walk":
        ref = walking_reference(WalkSpec(steps=args.steps, step_length_m=args.step_length))
    elif args.motion == "sway":
        ref = sway_reference(SwaySpec(duration_s=args.duration or SwaySpec.duration_s))
    else:
        ref = standing_reference(args.duration or STAND_S)
    path = ref.save(args.out)
    print(f"wrote {path}: {ref.num_frames} frames at {ref.fps:g} fps ({ref.duration_s:.1f} s), "
          f"root travels {ref.root_pos_w[-1, 0] - ref.root_pos_w[0, 0]:.2f} m")
    return 0
