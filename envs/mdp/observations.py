"""Observation terms (docs/environment.md §3): plain functions of a ``TrackingState`` returning (N, d).

Frames: ``_b`` is the robot anchor (torso) frame for anchor/body terms, the pelvis frame for
base velocities. Orientations are given as the first two columns of a rotation matrix
(6 numbers, row-major), a continuous encoding.
"""

from __future__ import annotations

import torch

from envs.mdp.state import TrackingState
from otr_gym.rotations import matrix_first_two_columns, quat_apply_inverse, quat_conj, quat_mul


def command(s: TrackingState) -> torch.Tensor:
    """(N, 58) reference joint positions (rad) and velocities (rad/s) at the current frame."""
    return torch.cat([s.ref_joint_pos, s.ref_joint_vel], dim=-1)


def anchor_pos_b(s: TrackingState) -> torch.Tensor:
    """(N, 3) reference anchor position in the robot anchor frame (m)."""
    return quat_apply_inverse(s.anchor_quat_w, s.ref_anchor_pos_w - s.anchor_pos_w)


def anchor_ori_b(s: TrackingState) -> torch.Tensor:
    """(N, 6) reference anchor orientation relative to the robot anchor, R(q_robot⁻¹·q_ref)[:, :2]."""
    return matrix_first_two_columns(quat_mul(quat_conj(s.anchor_quat_w), s.ref_anchor_quat_w))


def body_pos_b(s: TrackingState) -> torch.Tensor:
    """(N, 3K) robot tracked-body positions in the robot anchor frame (m)."""
    q = s.anchor_quat_w[:, None].expand_as(s.body_quat_w)
    return quat_apply_inverse(q, s.body_pos_w - s.anchor_pos_w[:, None]).flatten(1)


def body_ori_b(s: TrackingState) -> torch.Tensor:
    """(N, 6K) robot tracked-body orientations relative to the robot anchor (2 matrix columns each)."""
    q = quat_conj(s.anchor_quat_w)[:, None].expand_as(s.body_quat_w)
    return matrix_first_two_columns(quat_mul(q, s.body_quat_w)).flatten(1)


def base_lin_vel_b(s: TrackingState) -> torch.Tensor:
    """(N, 3) pelvis linear velocity in the pelvis frame (m/s)."""
    return s.root_lin_vel_b


def base_ang_vel_b(s: TrackingState) -> torch.Tensor:
    """(N, 3) pelvis angular velocity in the pelvis frame (rad/s), i.e. the IMU gyro."""
    return s.root_ang_vel_b


def joint_pos_rel(s: TrackingState) -> torch.Tensor:
    """(N, 29) joint positions minus the (per-env biased) default pose (rad)."""
    return s.joint_pos - s.default_joint_pos


def joint_vel(s: TrackingState) -> torch.Tensor:
    """(N, 29) joint velocities (rad/s)."""
    return s.joint_vel


def last_action(s: TrackingState) -> torch.Tensor:
    """(N, 29) the raw action applied during the last step."""
    return s.action


# ------------------------------------------------------------------ objects (OTR-G1-BoxTrack-v0)
# M moving objects, H hands, S supports, K static objects; every term is (N, ··M) flattened.


def object_pos_b(s: TrackingState) -> torch.Tensor:
    """(N, 3M) object positions in the robot anchor frame (m)."""
    o = s.objects
    q = s.anchor_quat_w[:, None].expand(-1, o.pos_w.shape[1], -1)
    return quat_apply_inverse(q, o.pos_w - s.anchor_pos_w[:, None]).flatten(1)


def object_ori_b(s: TrackingState) -> torch.Tensor:
    """(N, 6M) object orientations relative to the robot anchor (2 matrix columns each)."""
    o = s.objects
    q = quat_conj(s.anchor_quat_w)[:, None].expand(-1, o.quat_w.shape[1], -1)
    return matrix_first_two_columns(quat_mul(q, o.quat_w)).flatten(1)


def object_lin_vel_b(s: TrackingState) -> torch.Tensor:
    """(N, 3M) object linear velocities rotated into the robot anchor frame (m/s; a pure
    rotation, docs/environment.md §3: not HS's Rᵀ(v − p))."""
    o = s.objects
    q = s.anchor_quat_w[:, None].expand(-1, o.lin_vel_w.shape[1], -1)
    return quat_apply_inverse(q, o.lin_vel_w).flatten(1)


def object_ang_vel_b(s: TrackingState) -> torch.Tensor:
    """(N, 3M) object angular velocities rotated into the robot anchor frame (rad/s)."""
    o = s.objects
    q = s.anchor_quat_w[:, None].expand(-1, o.ang_vel_w.shape[1], -1)
    return quat_apply_inverse(q, o.ang_vel_w).flatten(1)


def object_command(s: TrackingState) -> torch.Tensor:
    """(N, 15M) the reference's object state in the *reference* anchor frame: position (3),
    orientation (6), linear (3) and angular (3) velocity. It depends on the reference only, so a
    deployment runner computes it from the clip as it does ``command``."""
    o = s.objects
    q = s.ref_anchor_quat_w[:, None].expand(-1, o.ref_pos_w.shape[1], -1)
    pos = quat_apply_inverse(q, o.ref_pos_w - s.ref_anchor_pos_w[:, None])
    ori = matrix_first_two_columns(quat_mul(quat_conj(q), o.ref_quat_w))
    lin, ang = quat_apply_inverse(q, o.ref_lin_vel_w), quat_apply_inverse(q, o.ref_ang_vel_w)
    return torch.cat([pos, ori, lin, ang], dim=-1).flatten(1)


def object_pos_error_b(s: TrackingState) -> torch.Tensor:
    """(N, 3M) reference minus simulated object position, in the robot anchor frame (m)."""
    o = s.objects
    q = s.anchor_quat_w[:, None].expand(-1, o.pos_w.shape[1], -1)
    return quat_apply_inverse(q, o.ref_pos_w - o.pos_w).flatten(1)


def contact_schedule(s: TrackingState) -> torch.Tensor:
    """(N, H·M + M·S) the reference's contact gates at the current frame: hand–object windows,
    then object–support windows, each in [0, 1]."""
    o = s.objects
    return torch.cat([o.hand_gate.flatten(1), o.support_gate.flatten(1)], dim=-1)


def object_contact_forces(s: TrackingState) -> torch.Tensor:
    """(N, H·M + M·S) contact forces hand–object, then object–support, in units of 10 N (so
    that the ±100 observation clip is 1 kN)."""
    o = s.objects
    return 0.1 * torch.cat([o.hand_force_n.flatten(1), o.support_force_n.flatten(1)], dim=-1)


def static_object_pos_b(s: TrackingState) -> torch.Tensor:
    """(N, 3K) static objects' positions (the table) in the robot anchor frame (m)."""
    o = s.objects
    n, k = s.anchor_pos_w.shape[0], o.static_pos_w.shape[0]
    q = s.anchor_quat_w[:, None].expand(-1, k, -1)
    return quat_apply_inverse(q, o.static_pos_w[None].expand(n, -1, -1) - s.anchor_pos_w[:, None]).flatten(1)


def static_object_ori_b(s: TrackingState) -> torch.Tensor:
    """(N, 6K) static objects' orientations relative to the robot anchor."""
    o = s.objects
    n, k = s.anchor_pos_w.shape[0], o.static_quat_w.shape[0]
    q = quat_conj(s.anchor_quat_w)[:, None].expand(-1, k, -1)
    return matrix_first_two_columns(quat_mul(q, o.static_quat_w[None].expand(n, -1, -1))).flatten(1)
