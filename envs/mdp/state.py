"""The per-step snapshot every MDP term reads: robot state, reference at the current frame,
the anchor-aligned targets, and the policy's actions. Built once per step, so terms stay
plain functions of one argument (plus their config parameters) and nothing is computed twice.

Shapes: N envs, K tracked bodies (``body_names``), 29 joints, C contact-sensor bodies; with
objects (``ObjectState``) M moving objects, H hands, S supports.
Frames: ``_w`` world, ``_b`` robot body frame; quaternions wxyz; SI units.

Alignment (docs/environment.md §2): Δq = yaw(q_robotAnchor · q_refAnchor⁻¹); body target orientation
Δq·q_i; body target position [robotAnchor.xy, refAnchor.z] + Δq·(p_i − p_refAnchor). Anchor
terms use the unaligned world reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from otr_gym.rotations import quat_apply, quat_apply_inverse, quat_conj, quat_mul, quat_yaw


@dataclass(frozen=True)
class ObjectState:
    """Moving objects (M), hands (H) and supports (S) of OTR-G1-BoxTrack-v0 (``envs.mdp.objects``)."""

    names: tuple[str, ...]
    support_names: tuple[str, ...]
    pos_w: torch.Tensor  # (N, M, 3)
    quat_w: torch.Tensor  # (N, M, 4)
    lin_vel_w: torch.Tensor  # (N, M, 3) m/s, of the object origin
    ang_vel_w: torch.Tensor  # (N, M, 3) rad/s, world
    ref_pos_w: torch.Tensor  # (N, M, 3) reference at the current frame
    ref_quat_w: torch.Tensor  # (N, M, 4)
    ref_lin_vel_w: torch.Tensor  # (N, M, 3)
    ref_ang_vel_w: torch.Tensor  # (N, M, 3)
    hand_pos_w: torch.Tensor  # (N, H, 3) robot hand points p_eef
    hand_target_w: torch.Tensor  # (N, H, M, 3) reference hand point placed on the simulated object
    hand_gate: torch.Tensor  # (N, H, M) robot–object windows, [0, 1]
    hand_force_n: torch.Tensor  # (N, H, M) hand–object contact force (max over the step's substeps)
    support_gate: torch.Tensor  # (N, M, S) object–support windows, [0, 1]
    support_force_n: torch.Tensor  # (N, M, S) object–support contact force
    static_pos_w: torch.Tensor  # (K, 3) static objects (fixed)
    static_quat_w: torch.Tensor  # (K, 4)
    #: (N, M) N: the normal force each of the H hands must press with for friction alone to give
    #: the object its reference acceleration, m‖a_ref − g‖/(H μ), with this env's mass and friction
    grip_force_n: torch.Tensor | None = None


@dataclass(frozen=True)
class TrackingState:
    # names and indices (into the K tracked bodies / C contact bodies)
    body_names: tuple[str, ...]
    anchor: int
    end_effectors: torch.Tensor  # (E,) long, on the device (a Python list index would sync)
    contact_body_names: tuple[str, ...]
    # robot
    joint_pos: torch.Tensor  # (N, 29) rad
    joint_vel: torch.Tensor  # (N, 29) rad/s
    root_quat_w: torch.Tensor  # (N, 4) pelvis
    root_lin_vel_b: torch.Tensor  # (N, 3) m/s, pelvis frame
    root_ang_vel_b: torch.Tensor  # (N, 3) rad/s, pelvis frame
    body_pos_w: torch.Tensor  # (N, K, 3)
    body_quat_w: torch.Tensor  # (N, K, 4)
    body_lin_vel_w: torch.Tensor  # (N, K, 3)
    body_ang_vel_w: torch.Tensor  # (N, K, 3)
    contact_force_n: torch.Tensor  # (N, C) max net contact force over the last step's substeps
    # reference at each env's current frame
    ref_joint_pos: torch.Tensor  # (N, 29)
    ref_joint_vel: torch.Tensor  # (N, 29)
    ref_body_pos_w: torch.Tensor  # (N, K, 3)
    ref_body_quat_w: torch.Tensor  # (N, K, 4)
    ref_body_lin_vel_w: torch.Tensor  # (N, K, 3)
    ref_body_ang_vel_w: torch.Tensor  # (N, K, 3)
    ref_body_pos_aligned_w: torch.Tensor  # (N, K, 3) targets moved onto the robot anchor (xy, yaw)
    ref_body_quat_aligned_w: torch.Tensor  # (N, K, 4)
    # policy
    action: torch.Tensor  # (N, 29) raw action of the last step
    last_action: torch.Tensor  # (N, 29) the one before
    default_joint_pos: torch.Tensor  # (N, 29) PD zero (default pose + per-env bias)
    # OTR-G1-BoxTrack-v0 only
    objects: ObjectState | None = None

    @property
    def anchor_pos_w(self) -> torch.Tensor:
        return self.body_pos_w[:, self.anchor]

    @property
    def anchor_quat_w(self) -> torch.Tensor:
        return self.body_quat_w[:, self.anchor]

    @property
    def ref_anchor_pos_w(self) -> torch.Tensor:
        return self.ref_body_pos_w[:, self.anchor]

    @property
    def ref_anchor_quat_w(self) -> torch.Tensor:
        return self.ref_body_quat_w[:, self.anchor]


def aligned_targets(anchor_pos_w: torch.Tensor, anchor_quat_w: torch.Tensor, ref_body_pos_w: torch.Tensor,
                    ref_body_quat_w: torch.Tensor, anchor: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Reference bodies (N, K, ·) re-expressed about the robot anchor: same xy and yaw as the
    robot's anchor, the reference anchor's height (see module docstring)."""
    ref_anchor_pos, ref_anchor_quat = ref_body_pos_w[:, anchor], ref_body_quat_w[:, anchor]
    delta = quat_yaw(quat_mul(anchor_quat_w, quat_conj(ref_anchor_quat)))[:, None]  # (N, 1, 4)
    origin = torch.cat([anchor_pos_w[:, :2], ref_anchor_pos[:, 2:]], dim=-1)[:, None]
    pos = origin + quat_apply(delta.expand_as(ref_body_quat_w), ref_body_pos_w - ref_anchor_pos[:, None])
    quat = quat_mul(delta.expand_as(ref_body_quat_w), ref_body_quat_w)
    return pos, quat


def root_velocities_b(qpos: torch.Tensor, qvel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pelvis (linear, angular) velocity in the pelvis frame from MuJoCo qpos/qvel: the free
    joint's linear velocity is in world, its angular velocity already in the body frame."""
    return quat_apply_inverse(qpos[:, 3:7], qvel[:, :3]), qvel[:, 3:6]

