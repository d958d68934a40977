"""Deployment stages and the safety rules that move between them.

Stages: WAIT (no LowState yet: nothing is sent) → RAMP (joint targets interpolate from the
measured pose to the default pose over ``ramp_s`` with the stiff start-up gains) → HOLD
(default pose, start-up gains, until the operator starts) → BLEND (targets from the default pose
to the reference's first frame and gains from the start-up ones to the policy's, a smoothstep over
``blend_s``: the policy starts on the pose and the gains it was trained on) → TRACK (the policy)
→ END (the reference's last frame held with the policy's gains for ``end_hold_s``) → DAMP.
``blend_s`` and ``end_hold_s`` 0 skip BLEND and END.

DAMP is latched: once entered, only a restart of the runner leaves it. Every DAMP command has
kp = 0 (q targets released), dq = 0, τ = 0 and the damping kd, so the joints only resist
motion. The runner damps on (``DampReason``):

- ``stale_state``: no new LowState for ``stale_cycles`` consecutive policy cycles;
- ``bad_crc`` / ``nan_state``: a LowState whose CRC is wrong or that carries NaN/inf;
- ``nan_action``: the policy returned NaN or inf;
- ``tilt``: the torso (anchor) tilts more than ``tilt_limit_rad`` from vertical;
- ``estop``: the operator's e-stop (keyboard or the remote's Select button);
- ``clip_end`` / ``duration`` / ``stop``: the end of the reference, of ``--duration``, or
  the operator's stop (Ctrl-C).

Start-up gains are Holosoma's (docs/environment.md §9); the damping gains are their kd.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from agents.deploy.messages import JointCommand
from otr_gym import robot


class Stage(IntEnum):
    WAIT = 0
    RAMP = 1
    HOLD = 2
    TRACK = 3
    DAMP = 4
    BLEND = 5  # numbered after DAMP: the logs of earlier versions keep their stage numbers
    END = 6


class DampReason:
    STALE_STATE = "stale_state"
    BAD_CRC = "bad_crc"
    NAN_STATE = "nan_state"
    NAN_ACTION = "nan_action"
    TILT = "tilt"
    ESTOP = "estop"
    CLIP_END = "clip_end"
    DURATION = "duration"
    STOP = "stop"


def _per_group(legs: tuple[float, ...], waist: float, arms: float) -> np.ndarray:
    return np.array([*legs, *legs, waist, waist, waist] + [arms] * 14, dtype=np.float64)


#: docs/environment.md §9 start-up gains: legs (hip pitch/roll/yaw, knee, ankle pitch/roll), waist, arms.
STARTUP_KP = _per_group((350, 200, 200, 300, 300, 150), 200, 40)
STARTUP_KD = _per_group((5, 5, 5, 10, 5, 5), 5, 3)


@dataclass
class SafetyCfg:
    stale_cycles: int = 3  # damp on this many consecutive cycles without a new LowState
    tilt_limit_rad: float = 0.8  # torso tilt from vertical (≈ 46°)
    soft_limit_factor: float = 0.9  # joint targets clamped to this fraction of the range (docs/environment.md §4)
    ramp_s: float = 2.0  # start-up ramp to the default pose
    blend_s: float = 1.0  # hold → track: default pose and start-up gains → the reference's first frame, policy gains
    end_hold_s: float = 1.0  # the reference's last frame held this long before damping
    damping_kd: np.ndarray = field(default_factory=lambda: STARTUP_KD.copy())

    def __post_init__(self) -> None:
        if self.stale_cycles < 1:
            raise ValueError(f"stale_cycles must be ≥ 1, got {self.stale_cycles}")
        if not 0.0 < self.tilt_limit_rad <= np.pi:
            raise ValueError(f"tilt_limit_rad must be in (0, π], got {self.tilt_limit_rad}")
        if not 0.0 < self.soft_limit_factor <= 1.0:
            raise ValueError(f"soft_limit_factor must be in (0, 1], got {self.soft_limit_factor}")
        for name in ("ramp_s", "blend_s", "end_hold_s"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be ≥ 0, got {getattr(self, name)}")
        self.damping_kd = np.broadcast_to(np.asarray(self.damping_kd, dtype=np.float64), (robot.NUM_JOINTS,)).copy()

    def soft_limits(self) -> tuple[np.ndarray, np.ndarray]:
        return robot.soft_joint_limits(self.soft_limit_factor)


@dataclass(frozen=True)
class Transition:
    cycle: int
    source: Stage
    target: Stage
    reason: str


class StageMachine:
    """The current stage and the transitions so far; DAMP is latched."""

    ALLOWED = {
        Stage.WAIT: {Stage.RAMP, Stage.DAMP},
        Stage.RAMP: {Stage.HOLD, Stage.TRACK, Stage.DAMP},
        Stage.HOLD: {Stage.BLEND, Stage.TRACK, Stage.DAMP},
        Stage.BLEND: {Stage.TRACK, Stage.DAMP},
        Stage.TRACK: {Stage.END, Stage.DAMP},
        Stage.END: {Stage.DAMP},
        Stage.DAMP: set(),
    }

    def __init__(self) -> None:
        self.stage = Stage.WAIT
        self.transitions: list[Transition] = []

    def go(self, target: Stage, cycle: int, reason: str) -> bool:
        """Move to ``target``; False (and no change) when the rules forbid it (e.g. out of DAMP)."""
        if target not in self.ALLOWED[self.stage]:
            return False
        self.transitions.append(Transition(cycle, self.stage, target, reason))
        self.stage = target
        return True

    @property
    def damp_reason(self) -> str | None:
        return self.transitions[-1].reason if self.stage == Stage.DAMP else None


# ------------------------------------------------------------------ checks (pure)


def state_fault(crc_ok: bool, finite: bool) -> str | None:
    if not crc_ok:
        return DampReason.BAD_CRC
    if not finite:
        return DampReason.NAN_STATE
    return None


def action_fault(action: np.ndarray) -> str | None:
    return None if np.isfinite(action).all() else DampReason.NAN_ACTION


def tilt_fault(tilt_rad: float, cfg: SafetyCfg) -> str | None:
    return DampReason.TILT if not tilt_rad <= cfg.tilt_limit_rad else None  # NaN tilt is a fault too


# ------------------------------------------------------------------ commands (pure)


def ramp_command(q_start: np.ndarray, q_goal: np.ndarray, progress: float) -> JointCommand:
    """Start-up gains, target a fraction ``progress`` ∈ [0, 1] of the way from start to goal."""
    a = float(np.clip(progress, 0.0, 1.0))
    zeros = np.zeros(robot.NUM_JOINTS)
    return JointCommand(q=(1.0 - a) * q_start + a * q_goal, dq=zeros, kp=STARTUP_KP.copy(), kd=STARTUP_KD.copy(),
                        tau=zeros.copy())


def smoothstep(x: float) -> float:
    """3x² − 2x³ on [0, 1] (clipped): starts and ends at rest."""
    x = float(np.clip(x, 0.0, 1.0))
    return x * x * (3.0 - 2.0 * x)


def blend_command(q_start: np.ndarray, q_goal: np.ndarray, kp: np.ndarray, kd: np.ndarray, progress: float,
                  cfg: SafetyCfg) -> JointCommand:
    """The hold → track blend at ``progress`` ∈ [0, 1]: targets from ``q_start`` to ``q_goal`` and
    gains from the start-up ones to ``kp``/``kd`` (the policy's), both along a smoothstep, so the
    targets and gains change continuously at both ends; targets clamped to the soft limits."""
    a = smoothstep(progress)
    lower, upper = cfg.soft_limits()
    zeros = np.zeros(robot.NUM_JOINTS)
    return JointCommand(q=np.clip((1.0 - a) * q_start + a * q_goal, lower, upper), dq=zeros,
                        kp=(1.0 - a) * STARTUP_KP + a * kp, kd=(1.0 - a) * STARTUP_KD + a * kd, tau=zeros.copy())


def damping_command(cfg: SafetyCfg) -> JointCommand:
    """kp = 0 (targets released), kd only."""
    zeros = np.zeros(robot.NUM_JOINTS)
    return JointCommand(q=zeros, dq=zeros.copy(), kp=zeros.copy(), kd=cfg.damping_kd.copy(), tau=zeros.copy())


def policy_command(targets: np.ndarray, kp: np.ndarray, kd: np.ndarray, cfg: SafetyCfg) -> JointCommand:
    """PD targets clamped to the soft joint limits, the policy's gains."""
    lower, upper = cfg.soft_limits()
    zeros = np.zeros(robot.NUM_JOINTS)
    return JointCommand(q=np.clip(targets, lower, upper), dq=zeros, kp=kp.copy(), kd=kd.copy(), tau=zeros.copy())
