"""Tracking error metrics shared by logging and evaluation (robot and, for the box task, objects)."""

from __future__ import annotations

import torch

from envs.mdp.state import TrackingState
from otr_gym.rotations import quat_apply_inverse, quat_error_angle, quat_yaw


def _root_relative_error(s: TrackingState, ref_body_pos_w: torch.Tensor, root: str) -> torch.Tensor:
    """(N, B) ‖(p_b − p_root) − (p̂_b − p̂_root)‖ (m) against reference positions (N, B, 3)."""
    r = s.body_names.index(root)
    robot_rel = s.body_pos_w - s.body_pos_w[:, r : r + 1]
    ref_rel = ref_body_pos_w - ref_body_pos_w[:, r : r + 1]
    return torch.linalg.norm(robot_rel - ref_rel, dim=-1)


def body_position_error_root_relative(s: TrackingState, root: str = "pelvis") -> torch.Tensor:
    """(N, B) position error (m) of each tracked body (``s.body_names`` order) after subtracting
    each side's ``root`` body position (world frame, no rotation alignment)."""
    return _root_relative_error(s, s.ref_body_pos_w, root)


def mpjpe_root_relative(s: TrackingState, root: str = "pelvis") -> torch.Tensor:
    """(N,) mean per-joint position error (m) over the tracked bodies after subtracting each
    side's ``root`` body position (world frame, no rotation alignment)."""
    return body_position_error_root_relative(s, root).mean(-1)


def mpjpe_root_relative_heading_aligned(s: TrackingState, root: str = "pelvis") -> torch.Tensor:
    """(N,) the same MPJPE with the reference first turned by the anchors' yaw difference (the
    reward's aligned targets): posture only, heading drift not charged. A diagnostic beside
    ``mpjpe_root_relative`` (the paper's metric), which charges heading drift in full."""
    return _root_relative_error(s, s.ref_body_pos_aligned_w, root).mean(-1)


def anchor_horizontal_error_m(s: TrackingState) -> torch.Tensor:
    """(N,) horizontal distance (m, world x–y) of the robot's anchor from the reference's."""
    return torch.linalg.norm(s.ref_anchor_pos_w[:, :2] - s.anchor_pos_w[:, :2], dim=-1)


def end_effector_height_offset_m(s: TrackingState) -> torch.Tensor:
    """(N, E) height (m) of each end effector (``s.end_effectors``: ankle rolls, wrist yaws) above
    its aligned reference (negative: below), the quantity of the ``ee_height`` termination."""
    ee = s.end_effectors
    return s.body_pos_w[:, ee, 2] - s.ref_body_pos_aligned_w[:, ee, 2]


def horizontal_offset_in_heading(offset_w: torch.Tensor, heading_quat_w: torch.Tensor) -> torch.Tensor:
    """(..., 2) the horizontal part of world offsets (..., 3) in the frame of a heading (the yaw of
    unit quaternions (..., 4), wxyz): x forward, y to the left. A turn about z keeps the height
    apart, so x–y of the turned offset is the turned horizontal part."""
    return quat_apply_inverse(quat_yaw(heading_quat_w), offset_w)[..., :2]


def anchor_offset_heading_m(s: TrackingState) -> torch.Tensor:
    """(N, 2) the robot's anchor minus the reference's (m), horizontal, in the reference anchor's
    heading frame: x forward (negative: the robot is behind its reference), y to the left. Its
    norm is ``anchor_horizontal_error_m``; the split tells trailing from running ahead or
    drifting sideways."""
    return horizontal_offset_in_heading(s.anchor_pos_w - s.ref_anchor_pos_w, s.ref_anchor_quat_w)


def object_offset_heading_m(s: TrackingState) -> torch.Tensor:
    """(N, M, 2) each moving object minus its reference position (m), horizontal, in the
    reference anchor's heading frame (x forward, y left): where a carried object is off its mark
    as the reference person sees it."""
    o = s.objects
    heading = s.ref_anchor_quat_w[:, None].expand(-1, o.pos_w.shape[1], -1)
    return horizontal_offset_in_heading(o.pos_w - o.ref_pos_w, heading)


def object_position_error_m(s: TrackingState) -> torch.Tensor:
    """(N, M) distance (m, world) of each moving object from its reference position."""
    return torch.linalg.norm(s.objects.ref_pos_w - s.objects.pos_w, dim=-1)


def object_orientation_error_rad(s: TrackingState) -> torch.Tensor:
    """(N, M) rotation angle (rad) between each moving object and its reference orientation."""
    return quat_error_angle(s.objects.ref_quat_w, s.objects.quat_w)
