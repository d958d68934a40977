"""Tracking error metrics shared by logging and evaluation."""

from __future__ import annotations

import torch

from envs.mdp.state import TrackingState


def mpjpe_root_relative(s: TrackingState, root: str = "pelvis") -> torch.Tensor:
    """(N,) mean per-joint position error (m) over the tracked bodies after subtracting each
    side's ``root`` body position (world frame, no rotation alignment)."""
    r = s.body_names.index(root)
    robot_rel = s.body_pos_w - s.body_pos_w[:, r : r + 1]
    ref_rel = s.ref_body_pos_w - s.ref_body_pos_w[:, r : r + 1]
    return torch.linalg.norm(robot_rel - ref_rel, dim=-1).mean(-1)
