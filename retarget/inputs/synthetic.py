"""Procedural demonstrations: the project's embedded default and test data (no external files).

``generate(kind, seed, fps)`` poses the mannequin-x ``HumanModel`` from end-effector and
joint-angle curves, then solves small analytic corrections so that the result obeys contact:

* two-bone inverse kinematics plants the feet (walking) or the knees and hands (crawling)
  exactly where the gait puts them, so stance contacts neither slide nor leave the ground;
* the pelvis is lowered (smooth minimum) wherever a leg could not reach its foot;
* the height of a joint above a flat contact is the depth of its part's hull below the joint
  in the planned orientation, so the lowest vertex touches z = 0;
* hands are placed so the nearest vertex of the rigid hand touches the box side, and the box
  pose is the one the hands hold, so the box moves rigidly with them;
* while crawling, the pelvis height and roll are solved (2×2 Newton) so both thighs reach
  their knees, and the chest pitch so the shoulders sit over the hands.

Frames: z-up world, the subject starts near the origin facing +x. A part's world orientation
is written Q_k ⊗ C, where C = SMPLX_REST_QUAT_W is the T-pose orientation of every part
(``human_tpose``) and Q_k turns the T-pose segment in world axes. Randomness (body shape,
step lengths, timings) comes from ``seed`` only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.ndimage import gaussian_filter1d

from otr_gym.rotations import quat_apply, quat_from_rotvec, quat_from_vector_pairs, quat_mul, quat_slerp, quat_to_matrix
from otr_gym.scene import TableSpec
from retarget.inputs.demonstration import Demonstration, DemoObject
from retarget.inputs.human import PART_NAMES, PART_PARENTS, SMPLX_REST_QUAT_W, HumanModel, forward_kinematics

KINDS = ("walk", "box_carry", "crawl")
_P = {name: i for i, name in enumerate(PART_NAMES)}
_X, _Y, _Z = np.eye(3)


@dataclass(frozen=True)
class GaitConfig:
    """Walking: lengths in m, times in s. Seeds scale step length and time by ±10 %."""

    step_length_m: float = 0.60  # distance a swing foot travels in steady walking
    step_time_s: float = 0.50  # one swing
    double_support_s: float = 0.14
    swing_height_m: float = 0.07
    sway_m: float = 0.025  # pelvis shift towards the stance foot
    knee_soften_m: float = 0.03  # standing pelvis below the T-pose pelvis
    arm_swing_rad: float = 0.35  # upper-arm pitch per step of foot lead
    arm_abduction_rad: float = 0.1
    elbow_rad: float = 0.25
    trunk_lean_rad: float = 0.05
    pelvis_yaw_rad: float = 0.12  # per step of foot lead: the pelvis turns with the forward leg
    chest_yaw_rad: float = 0.06  # and the chest counter-turns
    reach_margin: float = 0.985  # legs never straighter than this fraction of their length


@dataclass(frozen=True)
class BoxCarryConfig:
    """The carried box, the table and the distances of the carry (m, s)."""

    box_extents_m: tuple[float, float, float] = (0.35, 0.40, 0.30)  # depth (x), width (y), height (z)
    box_start_x_m: float = 1.5
    table: TableSpec = TableSpec(pos=(3.6, 0.0, 0.75))
    pick_distance_legs: float = 0.64  # ankles to box centre while lifting, in leg lengths (knee room)
    place_distance_m: float = 0.32  # ankles to table edge while placing
    carry_ahead_m: float = 0.34  # pelvis to box centre while carrying
    carry_height_m: float = 1.0  # box centre while carrying
    squat_pelvis_fraction: float = 0.46  # pelvis height at the deepest squat / standing
    squat_lean_rad: float = 1.1  # trunk pitch while picking up
    squat_pelvis_back_m: float = 0.10
    place_lean_rad: float = 0.4
    place_knee_bend_m: float = 0.04  # pelvis drop while placing
    grasp_finger_pitch_rad: float = 0.9  # fingers point forward and this much down
    grasp_point_m: tuple[float, float] = (-0.05, 0.03)  # hand centroid on the side face, box (x, z)
    grasp_gap_m: float = 0.002  # nearest hand vertex to the box side
    pregrasp_offset_m: float = 0.07


@dataclass(frozen=True)
class CrawlConfig:
    """Hands-and-knees crawl in a lateral sequence (LK, LH, RK, RH), duty factor 0.75."""

    cycle_s: float = 1.6
    stride_m: float = 0.20
    cycles: int = 3
    knee_lift_m: float = 0.05
    hand_lift_m: float = 0.06
    pelvis_pitch_rad: float = 1.35  # pelvis pitched forward (upright = 0)
    shank_rise_rad: float = 0.08  # ankles slightly above the knees
    shoulder_height_fraction: float = 0.9  # shoulder above wrist / arm length
    hand_ahead_m: float = 0.03  # nominal hand foothold ahead of the shoulder
    head_pitch_rad: float = 0.6  # the head looks ahead and down


# ------------------------------------------------------------------ small maths


def _min_jerk(s):
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s**2)


def _ramp(t, t0: float, t1: float):
    """0 before t0, 1 after t1, minimum-jerk in between."""
    return _min_jerk((t - t0) / (t1 - t0))


def _rot(axis, angle):
    """Rotation (…, 4) of ``angle`` (…) rad about a world ``axis``."""
    return quat_from_rotvec(np.asarray(angle, np.float64)[..., None] * axis)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _smooth_min(values, sharpness: float = 300.0):
    """Smooth lower bound of ``values`` (k, …) along axis 0 (≤ the minimum, within log k / sharpness)."""
    lo = values.min(axis=0)
    return lo - np.log(np.exp(-sharpness * (values - lo)).sum(axis=0)) / sharpness


def _two_bone(root, target, pole, l1: float, l2: float, what: str):
    """Middle joint of a chain root -(l1)- mid -(l2)- target bent towards ``pole``; raises if out of reach."""
    d = target - root
    dist = np.linalg.norm(d, axis=-1, keepdims=True)
    if np.any(dist > l1 + l2 - 1e-6) or np.any(dist < abs(l1 - l2) + 1e-6):
        worst = float(np.max(dist / (l1 + l2)))
        raise RuntimeError(f"synthetic {what}: target out of reach ({worst:.3f} of the limb length)")
    e = d / dist
    a = (l1**2 - l2**2 + dist**2) / (2.0 * dist)
    bend = pole - np.sum(pole * e, axis=-1, keepdims=True) * e
    return root + a * e + np.sqrt(np.maximum(l1**2 - a**2, 0.0)) * _unit(bend)


# ------------------------------------------------------------------ the rig


class _Rig:
    """Rest geometry of one body in the T-pose world frame, and posing helpers."""

    def __init__(self, model: HumanModel) -> None:
        self.model = model
        parent = [max(p, 0) for p in PART_PARENTS]
        self.bone = quat_apply(SMPLX_REST_QUAT_W, model.rest_joints - model.rest_joints[parent])  # (22, 3)
        self.length = np.linalg.norm(self.bone, axis=-1)
        self.verts = [quat_apply(SMPLX_REST_QUAT_W, v) for v in model.surface.vertices]  # T-pose world, joint-relative

    def fk(self, q_world: np.ndarray, pelvis: np.ndarray) -> np.ndarray:
        return forward_kinematics(quat_mul(q_world, SMPLX_REST_QUAT_W), pelvis, self.model.rest_joints)

    def depth_below(self, parts, q: np.ndarray) -> np.ndarray:
        """How far (…,) the rigid chain ``parts`` reaches below its first joint when turned by q (…, 4)."""
        return -np.min(quat_to_matrix(q)[..., 2, :] @ self.rigid_verts(parts).T, axis=-1)

    def pose_leg(self, q: np.ndarray, side: str, hip, ankle, pole) -> None:
        """Thigh and shank orientations putting the ankle joint at ``ankle`` (knee towards ``pole``)."""
        hip_i, knee_i, ankle_i = _P[f"{side}_Hip"], _P[f"{side}_Knee"], _P[f"{side}_Ankle"]
        knee = _two_bone(hip, ankle, pole, self.length[knee_i], self.length[ankle_i], f"{side} leg")
        hinge = np.cross(pole, ankle - hip)
        q[:, hip_i] = quat_from_vector_pairs(self.bone[knee_i], np.cross(_X, self.bone[knee_i]), knee - hip, hinge)
        q[:, knee_i] = quat_from_vector_pairs(self.bone[ankle_i], np.cross(_X, self.bone[ankle_i]), ankle - knee,
                                              hinge)

    def pose_arm(self, q: np.ndarray, side: str, shoulder, wrist, pole) -> None:
        """Upper-arm and forearm orientations putting the wrist joint at ``wrist`` (elbow towards ``pole``).

        The T-pose elbow sticks out backwards (−x) when the arm bends, which fixes the roll.
        """
        sh_i, el_i, wr_i = _P[f"{side}_Shoulder"], _P[f"{side}_Elbow"], _P[f"{side}_Wrist"]
        elbow = _two_bone(shoulder, wrist, pole, self.length[el_i], self.length[wr_i], f"{side} arm")
        hinge = np.cross(pole, wrist - shoulder)
        q[:, sh_i] = quat_from_vector_pairs(self.bone[el_i], np.cross(-_X, self.bone[el_i]), elbow - shoulder, hinge)
        q[:, el_i] = quat_from_vector_pairs(self.bone[wr_i], np.cross(-_X, self.bone[wr_i]), wrist - elbow, hinge)

    def free_wrist(self, shoulder, pitch, abduction, elbow, side: str):
        """Wrist target and elbow pole (T, 3) of a hanging arm: upper arm pitched forward by ``pitch``
        and out by ``abduction``, elbow flexed forward by ``elbow`` (rad, (T,))."""
        outward = 1.0 if side == "L" else -1.0
        upper = quat_apply(quat_mul(_rot(_Y, -pitch), _rot(_X, outward * abduction)), -_Z)
        forward = _unit(_X - (upper @ _X)[:, None] * upper)
        fore = np.cos(elbow)[:, None] * upper + np.sin(elbow)[:, None] * forward
        wrist = shoulder + self.length[_P[f"{side}_Elbow"]] * upper + self.length[_P[f"{side}_Wrist"]] * fore
        return wrist, -forward

    def rigid_verts(self, parts) -> np.ndarray:
        """T-pose world vertices of a rigid chain of parts, relative to the first part's joint."""
        offset, out = np.zeros(3), []
        for k, part in enumerate(parts):
            if k:
                offset = offset + self.bone[_P[part]]
            out.append(self.verts[_P[part]] + offset)
        return np.concatenate(out)


def _trunk(q: np.ndarray, lean, yaw_pelvis, yaw_chest, head_lift) -> None:
    """Pelvis, spine, collars, neck and head: forward pitch ``lean`` spread up the spine (rad, (T,))."""
    share = {"Pelvis": 0.45, "Spine1": 0.65, "Spine2": 0.85, "Spine3": 1.0, "L_Collar": 1.0, "R_Collar": 1.0}
    for part, k in share.items():
        yaw = yaw_pelvis if part == "Pelvis" else yaw_chest
        q[:, _P[part]] = quat_mul(_rot(_Z, yaw), _rot(_Y, k * lean))
    for part, lift in (("Neck", 0.5 * head_lift), ("Head", head_lift)):
        q[:, _P[part]] = quat_mul(_rot(_Z, yaw_chest), _rot(_Y, lean - lift))


# ------------------------------------------------------------------ stepping feet


@dataclass(frozen=True)
class _Swing:
    side: str
    t0: float
    t1: float
    start: np.ndarray  # (2,) ankle xy
    end: np.ndarray


class _Feet:
    """Footholds of both feet (ankle joint xy) and the swings between them."""

    def __init__(self, half_width: float) -> None:
        self.start = {"L": np.array([0.0, half_width]), "R": np.array([0.0, -half_width])}
        self.xy = {side: xy.copy() for side, xy in self.start.items()}
        self.swings: list[_Swing] = []

    def walk_to(self, t0: float, x_goal: float, step_m: float, swing_s: float, double_s: float) -> float:
        """Alternate swings (left first) until both feet stand at x = x_goal; returns the end time."""
        t, side = t0, "L"
        while max(abs(self.xy[s][0] - x_goal) for s in "LR") > 1e-9:
            other = self.xy["R" if side == "L" else "L"]
            end = np.array([min(other[0] + 0.5 * step_m, x_goal), self.xy[side][1]])
            self.swings.append(_Swing(side, t, t + swing_s, self.xy[side].copy(), end))
            self.xy[side] = end
            t += swing_s + double_s
            side = "R" if side == "L" else "L"
        return t - double_s

    def track(self, t: np.ndarray, side: str, lift_m: float):
        """Ankle xy (T, 2), lift above stance (T,) and stance flags (T,) of one foot."""
        xy = np.broadcast_to(self.start[side], (len(t), 2)).copy()
        lift, stance = np.zeros(len(t)), np.ones(len(t), dtype=bool)
        for s in (s for s in self.swings if s.side == side):
            phase = np.clip((t - s.t0) / (s.t1 - s.t0), 0.0, 1.0)
            moving = (t > s.t0) & (t < s.t1)
            after = t >= s.t0
            xy[after] = s.start + (s.end - s.start) * _min_jerk(phase[after])[:, None]
            lift += np.where(moving, lift_m * np.sin(np.pi * phase) ** 2, 0.0)
            stance &= ~moving
        return xy, lift, stance


# ------------------------------------------------------------------ clips


@dataclass
class _Clip:
    """Everything a clip designs, frame by frame, before the body is posed."""

    t: np.ndarray
    pelvis_xy: np.ndarray  # (T, 2)
    pelvis_z: np.ndarray  # (T,) before the leg-reach limit
    lean: np.ndarray
    yaw_pelvis: np.ndarray
    yaw_chest: np.ndarray
    ankle: dict  # side -> (T, 3) ankle joint targets


def _walking_body(rig: _Rig, gait: GaitConfig, feet: _Feet, t: np.ndarray, step_m: float, fps: float):
    """Pelvis path, ankle targets, stance flags and the left foot's lead (in steps) that drives the
    pelvis yaw and the arm swing; shared by the walking clips."""
    tpose_ankle_z = {s: rig.depth_below((f"{s}_Ankle", f"{s}_Foot"), np.array([1.0, 0, 0, 0])) for s in "LR"}
    ankle, stance, foot_x = {}, {}, {}
    for side in "LR":
        xy, lift, stance[side] = feet.track(t, side, gait.swing_height_m)
        ankle[side] = np.column_stack([xy, tpose_ankle_z[side] + lift])
        foot_x[side] = xy[:, 0]
    sigma = 0.12 * fps  # pelvis follows the support with a smooth lag
    mid = 0.5 * (ankle["L"][:, :2] + ankle["R"][:, :2])
    sway = gait.sway_m * ((stance["L"] & ~stance["R"]).astype(float) - (stance["R"] & ~stance["L"]))
    pelvis_xy = np.column_stack([gaussian_filter1d(mid[:, 0], sigma, mode="nearest"),
                                 gaussian_filter1d(mid[:, 1] + sway, 1.5 * sigma, mode="nearest")])
    lead = (foot_x["L"] - foot_x["R"]) / step_m  # +1/2 when the left foot is half a step ahead
    return pelvis_xy, ankle, stance, lead


def _pose_body(rig: _Rig, clip: _Clip, gait: GaitConfig) -> tuple[np.ndarray, np.ndarray]:
    """Trunk and legs: world rotations Q (T, 22, 4) and pelvis positions (T, 3); arms left at rest."""
    frames = len(clip.t)
    q = np.zeros((frames, len(PART_NAMES), 4))
    q[..., 0] = 1.0
    _trunk(q, clip.lean, clip.yaw_pelvis, clip.yaw_chest, 0.8 * clip.lean)
    hip_offset = {s: quat_apply(q[:, _P["Pelvis"]], rig.bone[_P[f"{s}_Hip"]]) for s in "LR"}
    reach = gait.reach_margin * np.array([rig.length[_P[f"{s}_Knee"]] + rig.length[_P[f"{s}_Ankle"]] for s in "LR"])
    highest = []
    for side, r in zip("LR", reach, strict=True):
        horizontal = clip.ankle[side][:, :2] - clip.pelvis_xy - hip_offset[side][:, :2]
        highest.append(clip.ankle[side][:, 2] - hip_offset[side][:, 2]
                       + np.sqrt(np.maximum(r**2 - np.sum(horizontal**2, axis=-1), 0.0)))
    pelvis = np.column_stack([clip.pelvis_xy, _smooth_min(np.stack([clip.pelvis_z, *highest]))])
    for side in "LR":
        out = 0.1 if side == "L" else -0.1
        pole = np.broadcast_to(quat_apply(_rot(_Z, clip.yaw_pelvis), _X + out * _Y), (frames, 3))
        rig.pose_leg(q, side, pelvis + hip_offset[side], clip.ankle[side], pole)
    return q, pelvis


def _free_arms(rig: _Rig, q: np.ndarray, pelvis: np.ndarray, lead: np.ndarray, gait: GaitConfig):
    """Wrist targets and elbow poles (side -> ((T, 3), (T, 3))) of arms swinging against the legs."""
    shoulder = rig.fk(q, pelvis)
    targets = {}
    for side, sign in (("L", -1.0), ("R", 1.0)):
        pitch = sign * gait.arm_swing_rad * lead
        elbow = gait.elbow_rad + 0.3 * np.maximum(pitch, 0.0)
        abduction = np.full(len(lead), gait.arm_abduction_rad)
        targets[side] = rig.free_wrist(shoulder[:, _P[f"{side}_Shoulder"]], pitch, abduction, elbow, side)
    return targets


def _finish_arms(rig: _Rig, q, pelvis, wrists: dict, hand_q: dict | None = None, hand_weight=None) -> None:
    """Arm IK to the wrist targets; hands follow the forearm, or slerp to ``hand_q`` by ``hand_weight``."""
    shoulder = rig.fk(q, pelvis)
    for side in "LR":
        target, pole = wrists[side]
        rig.pose_arm(q, side, shoulder[:, _P[f"{side}_Shoulder"]], target, pole)
        fore = q[:, _P[f"{side}_Elbow"]]
        q[:, _P[f"{side}_Wrist"]] = fore if hand_q is None else quat_slerp(fore, hand_q[side], hand_weight)


def _demonstration(name: str, rig: _Rig, q, pelvis, fps: float, objects=(), annotations=None) -> Demonstration:
    model = rig.model
    return Demonstration(
        name=name, fps=float(fps), part_names=PART_NAMES, part_parents=PART_PARENTS,
        part_pos_w=rig.fk(q, pelvis), part_quat_w=quat_mul(q, SMPLX_REST_QUAT_W), surface=model.surface,
        shape=model.shape, stature_m=model.stature_m, objects=list(objects),
        source={"format": "synthetic", "kind": name}, annotations=annotations or {})


def _walk(rig: _Rig, rng: np.random.Generator, fps: float) -> Demonstration:
    gait = GaitConfig()
    step_m = gait.step_length_m * rng.uniform(0.9, 1.1)
    swing_s = gait.step_time_s * rng.uniform(0.9, 1.1)
    feet = _Feet(_stance_half_width(rig))
    t_end = feet.walk_to(0.6, 2.5 * step_m, step_m, swing_s, gait.double_support_s) + 0.6
    t = np.arange(int(round(t_end * fps)) + 1) / fps
    pelvis_xy, ankle, stance, lead = _walking_body(rig, gait, feet, t, step_m, fps)
    clip = _Clip(t, pelvis_xy, np.full(len(t), _standing_pelvis_z(rig, gait)), np.full(len(t), gait.trunk_lean_rad),
                 -gait.pelvis_yaw_rad * lead, gait.chest_yaw_rad * lead, ankle)
    q, pelvis = _pose_body(rig, clip, gait)
    _finish_arms(rig, q, pelvis, _free_arms(rig, q, pelvis, lead, gait))
    return _demonstration("walk", rig, q, pelvis, fps, annotations={
        "stance_L_Ankle": stance["L"], "stance_R_Ankle": stance["R"]})


def _stance_half_width(rig: _Rig) -> float:
    """Half the lateral distance between the ankles of the T-pose."""
    ankle_y = [np.sum(rig.bone[[_P[f"{s}_Hip"], _P[f"{s}_Knee"], _P[f"{s}_Ankle"]], 1]) for s in "LR"]
    return 0.5 * (abs(ankle_y[0]) + abs(ankle_y[1]))


def _standing_pelvis_z(rig: _Rig, gait: GaitConfig) -> float:
    """T-pose pelvis height above the soles, less the soft-knee drop."""
    legs = [-np.sum(rig.bone[[_P[f"{s}_Hip"], _P[f"{s}_Knee"], _P[f"{s}_Ankle"]], 2]) for s in "LR"]
    ankle = [rig.depth_below((f"{s}_Ankle", f"{s}_Foot"), np.array([1.0, 0, 0, 0])) for s in "LR"]
    return float(min(leg + a for leg, a in zip(legs, ankle, strict=True))) - gait.knee_soften_m


def _box_mesh(extents) -> tuple[np.ndarray, np.ndarray]:
    box = trimesh.creation.box(extents=extents)
    return np.asarray(box.vertices, np.float64), np.asarray(box.faces, np.int64)


def _table_mesh(table: TableSpec) -> tuple[np.ndarray, np.ndarray]:
    """Top slab on four legs in the table frame (origin on the floor under the top's centre),
    the same geometry ``otr_gym.scene`` builds for ``table``."""
    hx, hy = table.half_extents
    top_z = table.pos[2]
    pieces = [trimesh.creation.box(extents=(2 * hx, 2 * hy, 0.04),
                                   transform=trimesh.transformations.translation_matrix((0, 0, top_z - 0.02)))]
    for sx in (-1, 1):
        for sy in (-1, 1):
            pieces.append(trimesh.creation.box(extents=(0.04, 0.04, top_z - 0.04),
                                               transform=trimesh.transformations.translation_matrix(
                                                   (sx * (hx - 0.04), sy * (hy - 0.04), 0.5 * (top_z - 0.04)))))
    mesh = trimesh.util.concatenate(pieces)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def _grasp(rig: _Rig, cfg: BoxCarryConfig) -> tuple[dict, dict]:
    """Hand orientations (side -> (4,)) and wrist positions in the box frame (side -> (3,)) that put the
    palms on the box sides, fingers forward and down, the nearest hand vertex ``grasp_gap_m`` away."""
    pitch = cfg.grasp_finger_pitch_rad
    fingers = np.array([np.cos(pitch), 0.0, -np.sin(pitch)])
    half_width = 0.5 * cfg.box_extents_m[1]
    hand_q, wrist = {}, {}
    for side, out in (("L", 1.0), ("R", -1.0)):
        # T-pose hand: fingers point outwards (±y), the palm faces down (−z)
        hand_q[side] = quat_from_vector_pairs(out * _Y, -_Z, fingers, -out * _Y)
        verts = quat_apply(hand_q[side], rig.verts[_P[f"{side}_Wrist"]])
        inner = verts[:, 1].min() if out > 0 else verts[:, 1].max()  # the side touching the box
        centre = verts.mean(axis=0)
        gx, gz = cfg.grasp_point_m
        wrist[side] = np.array([gx - centre[0], out * (half_width + cfg.grasp_gap_m) - inner, gz - centre[2]])
    return hand_q, wrist


def _pick_lean(rig: _Rig, cfg: BoxCarryConfig, pelvis: np.ndarray, wrists: list[np.ndarray]) -> float:
    """Trunk pitch at the deepest squat: the configured one, or more for short arms, so that both
    wrists reach the box sides with 5 % of arm length to spare."""
    leans = cfg.squat_lean_rad + np.linspace(0.0, 0.5, 26)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(leans), len(PART_NAMES), 1))
    zeros = np.zeros(len(leans))
    _trunk(q, leans, zeros, zeros, 0.8 * leans)
    joints = rig.fk(q, np.broadcast_to(pelvis, (len(leans), 3)))
    arm = {s: rig.length[_P[f"{s}_Elbow"]] + rig.length[_P[f"{s}_Wrist"]] for s in "LR"}
    ratio = np.max([np.linalg.norm(w - joints[:, _P[f"{s}_Shoulder"]], axis=-1) / arm[s]
                    for s, w in zip("LR", wrists, strict=True)], axis=0)
    if not np.any(ratio <= 0.95):
        raise RuntimeError(f"synthetic box_carry: the box sides stay out of reach ({ratio.min():.3f} of the arm)")
    return float(leans[np.argmax(ratio <= 0.95)])


def _box_carry(rig: _Rig, rng: np.random.Generator, fps: float,
               cfg: BoxCarryConfig = BoxCarryConfig()) -> Demonstration:
    gait = GaitConfig()
    step_m = gait.step_length_m * rng.uniform(0.9, 1.1)
    swing_s = gait.step_time_s * rng.uniform(0.9, 1.1)
    box_x = cfg.box_start_x_m + rng.uniform(-0.1, 0.1)
    depth, width, height = cfg.box_extents_m
    table_edge = cfg.table.pos[0] - cfg.table.half_extents[0]
    feet = _Feet(_stance_half_width(rig))
    # timeline (s): walk, squat and reach, close the hands, stand up with the box, walk, place, let go
    leg = min(rig.length[_P[f"{s}_Knee"]] + rig.length[_P[f"{s}_Ankle"]] for s in "LR")
    t_walk1 = feet.walk_to(0.5, box_x - cfg.pick_distance_legs * leg, step_m, swing_s, gait.double_support_s)
    t_squat = (t_walk1 + 0.2, t_walk1 + 1.6)
    t_reach = (t_squat[0] + 0.2 * (t_squat[1] - t_squat[0]), t_squat[1])
    t_close = (t_squat[1], t_squat[1] + 0.35)
    t_lift = (t_close[1] + 0.1, t_close[1] + 1.6)
    t_walk2 = feet.walk_to(t_lift[1] + 0.3, table_edge - cfg.place_distance_m, step_m, swing_s, gait.double_support_s)
    t_place = (t_walk2 + 0.2, t_walk2 + 1.8)
    t_open = (t_place[1] + 0.1, t_place[1] + 0.4)
    t_retract = (t_open[1], t_open[1] + 1.2)
    t = np.arange(int(round((t_retract[1] + 0.6) * fps)) + 1) / fps

    pelvis_xy, ankle, stance, lead = _walking_body(rig, gait, feet, t, step_m, fps)
    squat = _ramp(t, *t_squat) - _ramp(t, *t_lift)
    place = _ramp(t, t_place[0], t_place[0] + 1.0) - _ramp(t, *t_retract)
    pelvis_xy[:, 0] -= cfg.squat_pelvis_back_m * squat
    z_stand = _standing_pelvis_z(rig, gait)
    pelvis_z = z_stand - (1.0 - cfg.squat_pelvis_fraction) * z_stand * squat - cfg.place_knee_bend_m * place
    hand_q, wrist_in_box = _grasp(rig, cfg)
    on_floor = np.array([box_x, 0.0, 0.5 * height])
    deepest = np.argmax(squat)
    pick_lean = _pick_lean(rig, cfg, np.append(pelvis_xy[deepest], pelvis_z[deepest]),
                           [on_floor + wrist_in_box[s] for s in "LR"])
    lean = gait.trunk_lean_rad + pick_lean * squat + cfg.place_lean_rad * place
    clip = _Clip(t, pelvis_xy, pelvis_z, lean, -gait.pelvis_yaw_rad * lead, gait.chest_yaw_rad * lead, ankle)
    q, pelvis = _pose_body(rig, clip, gait)

    # the box: on the floor, lifted to the carry pose (up first, then in), carried, put on the table
    carried = np.column_stack([pelvis[:, 0] + cfg.carry_ahead_m, np.zeros(len(t)), np.full(len(t), cfg.carry_height_m)])
    on_table = np.array([table_edge + 0.5 * depth + 0.05, 0.0, cfg.table.pos[2] + 0.5 * height])
    lift_len = t_lift[1] - t_lift[0]
    up = _ramp(t, t_lift[0], t_lift[0] + 0.7 * lift_len)[:, None]
    inward = _ramp(t, t_lift[0] + 0.5 * lift_len, t_lift[1])[:, None]
    place_len = t_place[1] - t_place[0]
    over = _ramp(t, t_place[0], t_place[0] + 0.7 * place_len)[:, None]
    down = _ramp(t, t_place[0] + 0.5 * place_len, t_place[1])[:, None]
    box = on_floor + np.column_stack([inward[:, 0] * (carried[:, 0] - on_floor[0]), np.zeros(len(t)),
                                      up[:, 0] * (carried[:, 2] - on_floor[2])])
    box = box + over * (np.column_stack([on_table[0] - carried[:, 0], np.zeros(len(t)), np.zeros(len(t))]))
    box = box + down * np.array([0.0, 0.0, on_table[2] - cfg.carry_height_m])

    # hands: free swing -> above-outside the sides -> on the sides, and back
    free = _free_arms(rig, q, pelvis, lead, gait)
    reach = (_ramp(t, *t_reach) - _ramp(t, *t_retract))[:, None]
    hold = (_ramp(t, *t_close) - _ramp(t, *t_open))[:, None]
    wrists = {}
    joints = rig.fk(q, pelvis)
    for side, out in (("L", 1.0), ("R", -1.0)):
        contact = box + wrist_in_box[side]
        pre = contact + np.array([0.0, out * cfg.pregrasp_offset_m, 1.5 * cfg.pregrasp_offset_m])
        # reaching hands go as far towards the box as the arm allows until the squat brings it close
        shoulder = joints[:, _P[f"{side}_Shoulder"]]
        arm = 0.97 * (rig.length[_P[f"{side}_Elbow"]] + rig.length[_P[f"{side}_Wrist"]])
        target = free[side][0] + reach * (pre - free[side][0])
        offset = target - shoulder
        target = shoulder + offset * np.minimum(1.0, arm / np.linalg.norm(offset, axis=-1))[:, None]
        target = target + hold * (contact - target)
        pole = _unit((1.0 - reach) * free[side][1] + reach * _unit(np.array([-1.0, out * 0.8, -0.3])))
        wrists[side] = (target, pole)
    _finish_arms(rig, q, pelvis, wrists, hand_q, reach[:, 0])

    box_v, box_f = _box_mesh(cfg.box_extents_m)
    table_v, table_f = _table_mesh(cfg.table)
    identity = np.tile([1.0, 0.0, 0.0, 0.0], (len(t), 1))
    objects = [
        DemoObject("box", box_v, box_f, box, identity.copy()),
        DemoObject("table", table_v, table_f, np.tile([cfg.table.pos[0], cfg.table.pos[1], 0.0], (len(t), 1)),
                   identity.copy(), static=True),
    ]
    return _demonstration("box_carry", rig, q, pelvis, fps, objects, annotations={
        "stance_L_Ankle": stance["L"], "stance_R_Ankle": stance["R"], "box_held": hold[:, 0] > 1.0 - 1e-9})


def _crawl_schedule(t: np.ndarray, cfg: CrawlConfig, t_start: float, stride_m: float):
    """Pelvis x (T,) and, per limb, swing windows of the lateral-sequence crawl."""
    speed = stride_m / cfg.cycle_s
    t_stop = t_start + (cfg.cycles + 0.25) * cfg.cycle_s
    grid = np.linspace(0.0, t[-1], 20 * len(t))
    velocity = speed * (_ramp(grid, t_start, t_start + 0.5) - _ramp(grid, t_stop - 0.5, t_stop))
    pelvis_grid = np.concatenate([[0.0], np.cumsum(0.5 * (velocity[1:] + velocity[:-1]) * np.diff(grid))])
    phase = {"L_Knee": 0.0, "L_Wrist": 0.25, "R_Knee": 0.5, "R_Wrist": 0.75}
    swings = {limb: [(t_start + (p + j) * cfg.cycle_s, t_start + (p + j + 0.25) * cfg.cycle_s)
                     for j in range(cfg.cycles)] for limb, p in phase.items()}
    return (lambda tt: np.interp(tt, grid, pelvis_grid)), swings


def _limb_track(t, pelvis_x, swings, offset_xy, height: float, lift_m: float, cycle_s: float):
    """Planted joint positions (T, 3) and stance flags of one limb: each swing lands where the limb's
    nominal place (``offset_xy`` from the pelvis) will be at the middle of its next stance."""
    def nominal(tt):
        return np.array([pelvis_x(tt) + offset_xy[0], offset_xy[1]])

    xy = np.broadcast_to(nominal(0.0), (len(t), 2)).copy()
    lift, stance = np.zeros(len(t)), np.ones(len(t), dtype=bool)
    start = nominal(0.0)
    for t0, t1 in swings:
        end = nominal(t1 + 0.375 * cycle_s)
        phase = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
        after = t >= t0
        xy[after] = start + (end - start) * _min_jerk(phase[after])[:, None]
        moving = (t > t0) & (t < t1)
        lift += np.where(moving, lift_m * np.sin(np.pi * phase) ** 2, 0.0)
        stance &= ~moving
        start = end
    return np.column_stack([xy, height + lift]), stance


def _solve_pelvis_height_roll(rig: _Rig, knees: dict, pelvis_x, pitch: float):
    """Pelvis z and roll (T,) such that each thigh exactly reaches its knee (2×2 Newton per frame)."""
    thigh = {s: rig.length[_P[f"{s}_Knee"]] for s in "LR"}

    def residual(z, roll):
        q = quat_mul(_rot(_X, roll), _rot(_Y, np.full_like(roll, pitch)))
        pelvis = np.column_stack([pelvis_x, np.zeros_like(z), z])
        return np.stack([np.sum((knees[s] - pelvis - quat_apply(q, rig.bone[_P[f"{s}_Hip"]])) ** 2, axis=-1)
                         - thigh[s] ** 2 for s in "LR"], axis=-1)

    z = 0.5 * (knees["L"][:, 2] + knees["R"][:, 2]) + 0.9 * thigh["L"]
    roll = np.zeros_like(z)
    step = 1e-6
    for _ in range(20):
        f = residual(z, roll)
        jac = np.stack([(residual(z + step, roll) - f) / step, (residual(z, roll + step) - f) / step], axis=-1)
        delta = np.linalg.solve(jac, -f[..., None])[..., 0]
        z, roll = z + delta[:, 0], roll + delta[:, 1]
        if np.abs(delta).max() < 1e-12:
            break
    if np.abs(residual(z, roll)).max() > 1e-9:
        raise RuntimeError("synthetic crawl: no pelvis height and roll let both thighs reach their knees")
    return z, roll


def _crawl(rig: _Rig, rng: np.random.Generator, fps: float) -> Demonstration:
    cfg = CrawlConfig()
    stride = cfg.stride_m * rng.uniform(0.9, 1.1)
    t = np.arange(int(round((0.8 + (cfg.cycles + 0.25) * cfg.cycle_s + 0.8) * fps)) + 1) / fps
    pelvis_x, swings = _crawl_schedule(t, cfg, 0.8, stride)
    frames = len(t)
    q = np.zeros((frames, len(PART_NAMES), 4))
    q[..., 0] = 1.0

    # shins lie on the ground pointing back, ankles a little higher; the feet point back, soles up
    shank_q = _rot(_Y, np.pi / 2 + cfg.shank_rise_rad)
    foot_q = _rot(_Y, np.pi - 0.2)
    pelvis_q0 = _rot(_Y, cfg.pelvis_pitch_rad)
    knees, stance = {}, {}
    for side in "LR":
        knee_z = rig.depth_below((f"{side}_Knee",), shank_q)
        hip = quat_apply(pelvis_q0, rig.bone[_P[f"{side}_Hip"]])
        knees[side], stance[f"{side}_Knee"] = _limb_track(t, pelvis_x, swings[f"{side}_Knee"], hip[:2], knee_z,
                                                         cfg.knee_lift_m, cfg.cycle_s)
        q[:, _P[f"{side}_Knee"]] = shank_q
        q[:, _P[f"{side}_Ankle"]] = foot_q
        q[:, _P[f"{side}_Foot"]] = foot_q
    z, roll = _solve_pelvis_height_roll(rig, knees, pelvis_x(t), cfg.pelvis_pitch_rad)
    pelvis = np.column_stack([pelvis_x(t), np.zeros(frames), z])
    q[:, _P["Pelvis"]] = quat_mul(_rot(_X, roll), _rot(_Y, np.full(frames, cfg.pelvis_pitch_rad)))
    for side in "LR":
        hip = pelvis + quat_apply(q[:, _P["Pelvis"]], rig.bone[_P[f"{side}_Hip"]])
        q[:, _P[f"{side}_Hip"]] = quat_from_vector_pairs(rig.bone[_P[f"{side}_Knee"]],
                                                         np.cross(_X, rig.bone[_P[f"{side}_Knee"]]), knees[side] - hip,
                                                         np.broadcast_to(_Y, (frames, 3)))

    # palms flat, fingers forward; the chest pitches so the shoulders stay over the hands
    hand_q = {"L": _rot(_Z, -np.pi / 2), "R": _rot(_Z, np.pi / 2)}
    wrist_z = {s: rig.depth_below((f"{s}_Wrist",), hand_q[s]) for s in "LR"}
    arm = {s: rig.length[_P[f"{s}_Elbow"]] + rig.length[_P[f"{s}_Wrist"]] for s in "LR"}
    spine1 = pelvis + quat_apply(q[:, _P["Pelvis"]], rig.bone[_P["Spine1"]])
    to_shoulders = rig.bone[_P["Spine2"]] + rig.bone[_P["Spine3"]] + 0.5 * sum(
        rig.bone[_P[f"{s}_Collar"]] + rig.bone[_P[f"{s}_Shoulder"]] for s in "LR")
    height = np.mean([wrist_z[s] + cfg.shoulder_height_fraction * arm[s] for s in "LR"]) - spine1[:, 2]
    # R_y(θ) s has height s_z cos θ − s_x sin θ = r cos(θ + φ)
    radius, phi = np.hypot(to_shoulders[0], to_shoulders[2]), np.arctan2(to_shoulders[0], to_shoulders[2])
    chest = np.arccos(np.clip(height / radius, -1.0, 1.0)) - phi
    for part in ("Spine1", "Spine2", "Spine3", "L_Collar", "R_Collar"):
        q[:, _P[part]] = _rot(_Y, chest)
    q[:, _P["Neck"]] = _rot(_Y, 0.5 * (chest + cfg.head_pitch_rad))
    q[:, _P["Head"]] = _rot(_Y, np.full(frames, cfg.head_pitch_rad))

    shoulders = rig.fk(q, pelvis)
    wrists = {}
    for side in "LR":
        shoulder0 = shoulders[0, _P[f"{side}_Shoulder"]] - pelvis[0]
        hands, stance[f"{side}_Wrist"] = _limb_track(t, pelvis_x, swings[f"{side}_Wrist"],
                                                     shoulder0[:2] + np.array([cfg.hand_ahead_m, 0.0]),
                                                     wrist_z[side], cfg.hand_lift_m, cfg.cycle_s)
        wrists[side] = (hands, np.broadcast_to(-_X, (frames, 3)))
    _finish_arms(rig, q, pelvis, wrists, {s: np.broadcast_to(hand_q[s], (frames, 4)) for s in "LR"},
                 np.ones(frames))
    return _demonstration("crawl", rig, q, pelvis, fps,
                          annotations={f"stance_{limb}": flags for limb, flags in stance.items()})


_CLIPS = {"walk": _walk, "box_carry": _box_carry, "crawl": _crawl}


def generate(kind: str, seed: int = 0, fps: float = 30.0) -> Demonstration:
    """A procedural demonstration of ``kind`` (one of KINDS), deterministic in ``seed``.

    The seed draws the body shape (coefficients ~ N(0, 0.5²), clipped to ±1) and ±10 %
    variations of step length, timing and distances. ``annotations`` hold the planned contact
    phases: ``stance_<part>`` (the part rests on the ground) and, for box_carry, ``box_held``.
    """
    if kind not in _CLIPS:
        raise ValueError(f"unknown synthetic demonstration {kind!r}; choose one of {KINDS}")
    if not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    rng = np.random.default_rng(seed)
    shape = np.clip(rng.normal(0.0, 0.5, size=10), -1.0, 1.0)
    demo = _CLIPS[kind](_Rig(HumanModel(shape)), rng, float(fps))
    demo.source["seed"] = int(seed)
    demo.validate()
    return demo
