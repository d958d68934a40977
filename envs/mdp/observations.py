"""Observation terms (RL_SPEC §3): plain functions of a ``TrackingState`` returning (N, d).

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
