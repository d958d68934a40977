"""Reward terms (docs/environment.md §4): plain functions of a ``TrackingState`` returning (N,).

The environment sums weight · value · dt over the terms listed in the config. Tracking terms
are exp(−e/σ²) kernels; body terms average e over the K tracked bodies, compare orientations
and positions with the anchor-aligned targets and velocities in the world frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cache

import torch

from envs.mdp.state import ObjectState, TrackingState
from otr_gym import robot
from otr_gym.rotations import quat_error_angle


def anchor_position_error_exp(s: TrackingState, sigma: float) -> torch.Tensor:
    """exp(−‖p_ref − p‖²/σ²) for the anchor, unaligned world reference (σ in m)."""
    err = torch.sum(torch.square(s.ref_anchor_pos_w - s.anchor_pos_w), dim=-1)
    return torch.exp(-err / sigma**2)


def anchor_orientation_error_exp(s: TrackingState, sigma: float) -> torch.Tensor:
    """exp(−angle²/σ²) between the anchor and the world reference anchor (σ in rad)."""
    err = torch.square(quat_error_angle(s.ref_anchor_quat_w, s.anchor_quat_w))
    return torch.exp(-err / sigma**2)


def body_position_error_exp(s: TrackingState, sigma: float) -> torch.Tensor:
    """exp(−mean_k ‖p̂_k − p_k‖²/σ²) with the aligned targets p̂."""
    err = torch.sum(torch.square(s.ref_body_pos_aligned_w - s.body_pos_w), dim=-1)
    return torch.exp(-err.mean(-1) / sigma**2)


def body_orientation_error_exp(s: TrackingState, sigma: float) -> torch.Tensor:
    """exp(−mean_k angle(q̂_k, q_k)²/σ²) with the aligned targets q̂."""
    err = torch.square(quat_error_angle(s.ref_body_quat_aligned_w, s.body_quat_w))
    return torch.exp(-err.mean(-1) / sigma**2)


def body_linear_velocity_error_exp(s: TrackingState, sigma: float) -> torch.Tensor:
    """exp(−mean_k ‖v_ref − v‖²/σ²), world frame (σ in m/s)."""
    err = torch.sum(torch.square(s.ref_body_lin_vel_w - s.body_lin_vel_w), dim=-1)
    return torch.exp(-err.mean(-1) / sigma**2)


def body_angular_velocity_error_exp(s: TrackingState, sigma: float) -> torch.Tensor:
    """exp(−mean_k ‖ω_ref − ω‖²/σ²), world frame (σ in rad/s)."""
    err = torch.sum(torch.square(s.ref_body_ang_vel_w - s.body_ang_vel_w), dim=-1)
    return torch.exp(-err.mean(-1) / sigma**2)


def action_rate_l2(s: TrackingState) -> torch.Tensor:
    """Σ_j (a_t − a_{t−1})²."""
    return torch.sum(torch.square(s.action - s.last_action), dim=-1)


def joint_pos_limits(s: TrackingState, soft_limit_factor: float) -> torch.Tensor:
    """Σ_j radians beyond the soft limits (``soft_limit_factor`` of each range about its middle)."""
    lower, upper = _soft_limits(soft_limit_factor, s.joint_pos.device)
    below = (lower - s.joint_pos).clamp_min(0.0)
    above = (s.joint_pos - upper).clamp_min(0.0)
    return torch.sum(below + above, dim=-1)


def undesired_contacts(s: TrackingState, threshold_n: float, exclude: Sequence[str]) -> torch.Tensor:
    """Number of contact-sensor bodies pushed harder than ``threshold_n`` (max over the step's
    substeps), skipping bodies whose name contains any of ``exclude`` (feet, hands)."""
    keep = _kept_columns(s.contact_body_names, tuple(exclude), s.contact_force_n.device)
    return torch.sum((s.contact_force_n > threshold_n) & keep, dim=-1).float()


@cache
def _soft_limits(factor: float, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    lower, upper = robot.soft_joint_limits(factor)
    return (torch.as_tensor(lower, dtype=torch.float32, device=device),
            torch.as_tensor(upper, dtype=torch.float32, device=device))


@cache
def _kept_columns(names: tuple[str, ...], exclude: tuple[str, ...], device: torch.device) -> torch.Tensor:
    return torch.tensor([not any(e in n for e in exclude) for n in names], dtype=torch.bool, device=device)


# ------------------------------------------------------------------ objects (OTR-G1-BoxTrack-v0)
# Means over the M moving objects; world frame (the reference object pose is not re-aligned).


def object_position_error_exp(s: TrackingState, sigma: float) -> torch.Tensor:
    """exp(−mean_m ‖p_ref − p‖²/σ²) (§4 HS object position, σ in m)."""
    o = s.objects
    return torch.exp(-torch.sum(torch.square(o.ref_pos_w - o.pos_w), dim=-1).mean(-1) / sigma**2)


def object_orientation_error_exp(s: TrackingState, sigma: float) -> torch.Tensor:
    """exp(−mean_m angle²/σ²) (§4 HS object orientation, σ in rad)."""
    o = s.objects
    return torch.exp(-torch.square(quat_error_angle(o.ref_quat_w, o.quat_w)).mean(-1) / sigma**2)


def object_linear_velocity_error_exp(s: TrackingState, sigma: float) -> torch.Tensor:
    """exp(−mean_m ‖v_ref − v‖²/σ²), world (§4 FK object velocity tracking, σ in m/s)."""
    o = s.objects
    return torch.exp(-torch.sum(torch.square(o.ref_lin_vel_w - o.lin_vel_w), dim=-1).mean(-1) / sigma**2)


def object_angular_velocity_error_exp(s: TrackingState, sigma: float) -> torch.Tensor:
    """exp(−mean_m ‖ω_ref − ω‖²/σ²), world (§4 FK object velocity tracking, σ in rad/s)."""
    o = s.objects
    return torch.exp(-torch.sum(torch.square(o.ref_ang_vel_w - o.ang_vel_w), dim=-1).mean(-1) / sigma**2)


def hand_contact_force_setpoint(s: TrackingState, sigma_pos_m: float, tolerance_m: float, force_threshold_n: float,
                                sigma_force_n: float, gain: float) -> torch.Tensor:
    """HDMI's contact reward (§4 HDMI original), per hand h and object m, averaged:

    r = exp(−max(‖p_eef − p_tgt‖ − tol, 0)/σ_pos) · exp(min(‖F‖ − F_th, 0)/σ_F), value
    r·c·gain + (1 − c), with c the robot–object gate. The force factor is a set-point: 1 once
    the hand–object force reaches F_th. p_tgt is the reference hand point placed on the
    simulated object; outside a window (c = 0) the value is 1 whatever the hand does.
    """
    return _hand_setpoint(s.objects, force_threshold_n, sigma_pos_m, tolerance_m, sigma_force_n, gain)


def _hand_setpoint(o: ObjectState, f_th: float | torch.Tensor, sigma_pos_m: float, tolerance_m: float,
                   sigma_force_n: float, gain: float) -> torch.Tensor:
    """The HDMI value r·c·gain + (1 − c) for a set-point ``f_th`` (N; a number or (N, 1, M))."""
    dist = torch.linalg.norm(o.hand_pos_w[:, :, None] - o.hand_target_w, dim=-1)  # (N, H, M)
    r = torch.exp(-(dist - tolerance_m).clamp_min(0.0) / sigma_pos_m) * \
        torch.exp((o.hand_force_n - f_th).clamp_max(0.0) / sigma_force_n)
    c = o.hand_gate
    return (r * c * gain + (1.0 - c)).flatten(1).mean(-1)


def hand_grip_force_setpoint(s: TrackingState, sigma_pos_m: float, tolerance_m: float, sigma_force_n: float,
                             gain: float, min_force_n: float, max_force_n: float, safety: float) -> torch.Tensor:
    """``hand_contact_force_setpoint`` with the set-point sized to hold the object by friction:
    F_th = clip(safety · m‖a_ref − g‖/(H μ), min_force_n, max_force_n) per env and object, with
    this env's object mass m and friction μ and the reference object's acceleration a_ref
    (``ObjectState.grip_force_n``). A fixed 10 N is less than friction needs to hold a 3 kg box
    (2 × 0.5 × 10 N < 3 kg · 9.81 m/s²)."""
    f_th = (safety * s.objects.grip_force_n).clamp(min_force_n, max_force_n)[:, None]  # (N, 1, M)
    return _hand_setpoint(s.objects, f_th, sigma_pos_m, tolerance_m, sigma_force_n, gain)


def support_contact_force_setpoint(s: TrackingState, force_threshold_n: float, sigma_force_n: float,
                                   gain: float) -> torch.Tensor:
    """The same set-point for objects on their supports (table, ground): per object m and
    support k, r = exp(min(‖F_mk‖ − F_th, 0)/σ_F), value r·c·gain + (1 − c) with c the
    object–support gate, averaged over pairs (1 when there are none)."""
    o = s.objects
    if o.support_gate.shape[-1] == 0:
        return torch.ones(o.pos_w.shape[0], device=o.pos_w.device)
    r = torch.exp((o.support_force_n - force_threshold_n).clamp_max(0.0) / sigma_force_n)
    c = o.support_gate
    return (r * c * gain + (1.0 - c)).flatten(1).mean(-1)
