"""Termination terms (docs/environment.md §5, MJ thresholds): plain functions of a ``TrackingState``
returning (N,) bool. Any true term ends the episode as a failure (not a time-out)."""

from __future__ import annotations

import torch

from envs.mdp.metrics import anchor_horizontal_error_m, end_effector_height_offset_m, object_orientation_error_rad
from envs.mdp.state import TrackingState
from otr_gym.rotations import projected_gravity


def anchor_height_error(s: TrackingState, threshold_m: float) -> torch.Tensor:
    """|z_refAnchor − z_robotAnchor| > threshold (m)."""
    return torch.abs(s.ref_anchor_pos_w[:, 2] - s.anchor_pos_w[:, 2]) > threshold_m


def anchor_horizontal_error(s: TrackingState, threshold_m: float) -> torch.Tensor:
    """‖xy_refAnchor − xy_robotAnchor‖ > threshold (m, world): a robot trailing its reference
    (the demo box carry's walk to the box lags 70 cm without ending an episode under §5's
    height and tilt tests). Not in the default set."""
    return anchor_horizontal_error_m(s) > threshold_m


def anchor_gravity_error(s: TrackingState, threshold: float) -> torch.Tensor:
    """|Δ projected-gravity z| of the anchor > threshold (a tilt test that ignores yaw)."""
    g_ref = projected_gravity(s.ref_anchor_quat_w)[:, 2]
    g = projected_gravity(s.anchor_quat_w)[:, 2]
    return torch.abs(g_ref - g) > threshold


def end_effector_height_error(s: TrackingState, threshold_m: float) -> torch.Tensor:
    """Any end-effector (ankle_roll, wrist_yaw) height off its aligned target by > threshold (m)."""
    return torch.any(torch.abs(end_effector_height_offset_m(s)) > threshold_m, dim=-1)


def object_position_error(s: TrackingState, threshold_m: float) -> torch.Tensor:
    """Any moving object farther than threshold (m) from its reference position (§5 HS: 0.25 m)."""
    o = s.objects
    return torch.any(torch.linalg.norm(o.ref_pos_w - o.pos_w, dim=-1) > threshold_m, dim=-1)


def object_orientation_error(s: TrackingState, threshold_rad: float) -> torch.Tensor:
    """Any moving object turned more than threshold (rad) from its reference orientation: a box
    tipped over in the hands ends the episode instead of drifting where the orientation reward
    (σ 0.4 rad) no longer pulls. Not in the default set."""
    return torch.any(object_orientation_error_rad(s) > threshold_rad, dim=-1)
