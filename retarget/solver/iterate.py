"""The SQP's mutable state: the iterate (G1 configuration and free-object poses), the previous
frame's solution, the QP workspace, per-frame statistics; the retraction q ← q ⊕ δ."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from otr_gym.rotations import so3_exp
from retarget.geometry.kinematics import NUM_LINKS, LinkFrames
from retarget.solver.problem import ChannelTrack, Problem
from retarget.solver.qp_workspace import QPWorkspace
from retarget.solver.residuals import FIXED
from retarget.solver.stance import StanceTargets


@dataclass
class SolverState:
    """The mutable part: the iterate, the previous frame's solution and the QP workspace."""

    data: pin.Data
    q: np.ndarray  # (nq,) Pinocchio
    obj_pos: np.ndarray  # (O, 3)
    obj_rot: np.ndarray  # (O, 3, 3)
    qp: QPWorkspace
    prev: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (q, obj_pos, obj_rot) of t − 1
    prev_demo: tuple[np.ndarray, np.ndarray] | None = None  # demonstrated object poses at t − 1
    stance: StanceTargets | None = None  # planted-foot targets of t − 1 (their anchors)
    recent_frames: list[tuple[bytes, LinkFrames]] = field(default_factory=list)  # ``frames_at``'s last answers
    com_data: pin.Data | None = None  # scratch of the COM term (``retarget.solver.flight``), apart from ``data``
    #: (3,) m: the G1's COM less the person's, followed slowly (``Problem.com_offset_rate``); None before frame 0
    com_offset: np.ndarray | None = None


@dataclass
class FrameStats:
    iterations: int = 0  # QP steps tried
    rejected: int = 0  # of which undone by the trust-region test
    qp_rows: list[int] = field(default_factory=list)
    active_pairs: int = 0
    min_distance_m: float = np.inf  # smallest probe/guard distance to any collidable channel
    min_self_distance_m: float = np.inf
    timings: dict[str, float] = field(default_factory=dict)


class SectionTimer:
    """Accumulates wall time per section into a dict (the benchmark's profile)."""

    def __init__(self, stats: dict[str, float]) -> None:
        self.stats = stats
        self.t = time.perf_counter()

    def lap(self, key: str) -> None:
        now = time.perf_counter()
        self.stats[key] = self.stats.get(key, 0.0) + now - self.t
        self.t = now


#: How many configurations ``frames_at`` remembers: a frame asks for the same one up to 4
#: calls apart (the replanted feet, then the first linearisation; the solution, then its
#: contact annotation, then the next frame's stance targets).
RECENT_FRAMES = 4


def frames_at(problem: Problem, state: SolverState, q: np.ndarray) -> LinkFrames:
    """``problem.kin.frames`` at configuration q, answered again without recomputation when q
    is one of the last ``RECENT_FRAMES`` asked (the same bits in, the same frames out). The
    arrays are read-only: they may be shared by several callers."""
    key = q.tobytes()
    for k, fr in state.recent_frames:
        if k == key:
            return fr
    fr = problem.kin.frames(state.data, q)
    for a in (fr.rot, fr.pos, fr.jac):
        a.flags.writeable = False
    state.recent_frames = [(key, fr), *state.recent_frames[:RECENT_FRAMES - 1]]
    return fr


def channel_pose(state: SolverState, track: ChannelTrack, t: int) -> tuple[np.ndarray, np.ndarray]:
    if track.body == FIXED:
        return track.rot_w[t], track.pos_w[t]
    i = track.body - NUM_LINKS
    return state.obj_rot[i], state.obj_pos[i]


def new_state(problem: Problem) -> SolverState:
    pos = np.array([problem.channels[o.channel].pos_w[0] for o in problem.objects]).reshape(-1, 3)
    rot = np.array([problem.channels[o.channel].rot_w[0] for o in problem.objects]).reshape(-1, 3, 3)
    return SolverState(problem.kin.new_data(), problem.q_init.copy(), pos.copy(), rot.copy(),
                       QPWorkspace(problem.solver.qp_eps_abs, problem.solver.qp_warm_start))


def retract(problem: Problem, state: SolverState, delta: np.ndarray) -> None:
    """q ← q ⊕ δv; τ ← τ + δτ, R ← exp(δθ) R for every free object."""
    nv = problem.kin.nv
    state.q = problem.kin.integrate(state.q, delta[:nv])
    for i in range(len(problem.objects)):
        d = delta[nv + 6 * i:nv + 6 * i + 6]
        state.obj_pos[i] = state.obj_pos[i] + d[:3]
        state.obj_rot[i] = so3_exp(d[3:]) @ state.obj_rot[i]
