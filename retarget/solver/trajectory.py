"""The trajectory pass: the per-frame solution repaired, a few frames at a time, where its paths
jump or its joints accelerate beyond what the G1's motors give them.

Why a pass over several frames: the per-frame SQP sees one frame and the two before it, so it
can bound a jump only by pushing the correction into the frames after it, where the motion then
catches up faster (bounding the paths frame by frame raised the torques:
docs/results/feasibility.md, "Bounding the paths"). Here the frames around each flagged frame
move together, so a jump is spread evenly over its neighbours on both sides.

Each window [w₀, w₁] (the flagged frames of ``otr verify``'s jump and acceleration measures,
``pad_frames`` either side, overlapping windows merged) is one dense QP (ProxQP) on the
tangent corrections δₜ (base twist in the pelvis frame, then joints), the frames outside held:

    min   Σₜ Σ_b w_b ‖p_b(qₜ ⊕ δₜ) − p_b(q̄ₜ)‖² + w_q ‖(qₜ ⊕ δₜ) ⊖ q̄ₜ‖² + w_s ‖δₜ₊₁ − 2δₜ + δₜ₋₁‖²/dt⁴
    s.t.  |p_k,t − ½(p_k,t−1 + p_k,t+1)| ≤ b_k / √3 per axis   (pelvis, feet, hands)
          |q̈ₜ| ≤ κ τ_max / M_ii(qₜ)                              (each joint's motor alone)
          joint limits

q̄ is the per-frame solution (the interaction-fidelity optimum: the pass stays as close to it as
the limits allow; hands and feet, the contacts, dearest), positions linearised with Pinocchio's
frame Jacobians and re-linearised ``iterations`` times (Gauss–Newton). Accelerations are the
check's (twists low-passed at ``lowpass_hz``) plus the raw second differences of the correction,
which the cost keeps smooth. The rows are hard: where they conflict (a joint at its limit, the
linearisation far off) ProxQP does not converge within ``max_qp_iterations`` and the window keeps
its frames. Units: metres, radians, seconds.

Off by default (``trajectory.enabled``): measured on the five shared clips
(docs/results/feasibility.md, "A trajectory pass over windows of frames") it removes the limb
and pelvis jumps and most over-accelerations, but it has no collision rows, so it pushes links
into the ground and the objects (up to 16 mm), and standing feet slide more. Not here either: the torques and the base
wrench. With the contact forces as variables and the inverse dynamics linearised
(``pinocchio.computeRNEADerivatives``) the same QP became too ill-conditioned to solve at this
size: ProxQP's sparse solver did not return within 5 minutes on 30 frames, OSQP needed 6 s for
60 frames after scaling. Windows are dense ProxQP problems: its sparse solver took 60 s on a
120-frame kinematic window, the dense one 0.05–0.35 s on windows of up to 26 frames.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from otr_gym import robot
from otr_gym.flags import true_intervals
from retarget.geometry.dynamics import g1_dynamics, lowpass, twist_steps, velocity_acceleration

NV = 6 + robot.NUM_JOINTS
#: The points whose jumps are bounded: the pelvis, then the feet and hands (``otr verify``'s limbs).
JUMP_BODIES = (robot.ROOT_BODY,) + robot.FEET + robot.HANDS


def _default_body_weights() -> dict[str, float]:
    return {"left_wrist_yaw_link": 1e4, "right_wrist_yaw_link": 1e4,
            "left_ankle_roll_link": 1e4, "right_ankle_roll_link": 1e4,
            "pelvis": 1e3, "torso_link": 1e3,
            "left_knee_link": 1e2, "right_knee_link": 1e2, "left_elbow_link": 1e2, "right_elbow_link": 1e2}


@dataclass(frozen=True)
class TrajectoryCfg:
    """The trajectory pass (``smooth_trajectory``). Its bounds sit inside ``otr verify``'s limits
    (limbs 3 cm and pelvis 1 cm off their neighbours' line; 1× the motor-alone acceleration), so
    the check passes with the linearisation's slack."""

    enabled: bool = False  # off by default: docs/results/feasibility.md, "A trajectory pass over windows of frames"
    iterations: int = 3  # Gauss–Newton relinearisations
    limb_jump_m: float = 0.025  # feet and hands: bound per axis = this / √3 (m)
    pelvis_jump_m: float = 0.008
    accel_fraction: float = 0.85  # of τ_max / M_ii (``otr verify``'s joint-acceleration limit)
    lowpass_hz: float = 6.0  # accelerations as the check takes them
    pad_frames: int = 6  # frames either side of a flagged frame that move with it
    max_window_frames: int = 24  # longer windows are solved in pieces (dense QPs: time ∝ length³)
    #: A foot whose sole is on the floor (a sole corner within ``stance_height_m``) is held this
    #: much dearer (position per m², orientation per rad² × (0.1 m)²): a standing foot that moves
    #: a millimetre a frame already slides at 5 cm/s.
    stance_weight: float = 1e6
    stance_height_m: float = 0.02
    #: Cost per m² of moving a body from its per-frame position (hands and feet dearest: the contacts).
    body_weights: dict[str, float] = field(default_factory=_default_body_weights)
    posture_weight: float = 1.0  # per rad² (m² for the base) of change from the per-frame solution
    smooth_weight: float = 1e-4  # per (rad/s²)² of the correction's own acceleration
    eps_abs: float = 1e-6
    #: ProxQP's iteration cap per window; a window it cannot solve keeps its frames (jump, bounds
    #: and joint limits can conflict where a joint sits at its limit: OMOMO sub8_plasticbox_004
    #: ran for minutes without the cap).
    max_qp_iterations: int = 30  # ProxQP outer iterations (a failing window took ~4 s at 30, ~85 s at 1000)


@dataclass
class TrajectoryReport:
    """What the pass did: frames flagged before each iteration, the windows it solved, its time."""

    flagged: list[int]  # frames over a bound at each linearisation
    windows: list[tuple[int, int]]  # the first iteration's windows [first, last]
    unsolved: int  # windows left as they were because their QP did not converge (all iterations)
    seconds: float
    moved_m: float  # largest body displacement from the per-frame solution (m)

    def line(self) -> str:
        return (f"trajectory pass: frames over a bound {' -> '.join(map(str, self.flagged))}, "
                f"{len(self.windows)} windows ({self.unsolved} unsolved, kept), "
                f"bodies moved up to {100 * self.moved_m:.1f} cm, {self.seconds:.2f} s")


def smooth_trajectory(reference, cfg: TrajectoryCfg = TrajectoryCfg()):
    """(the reference repaired, ``TrajectoryReport``): see the module doc. Objects, contact
    annotations and metadata are carried over; body poses and velocities are recomputed from
    the new configurations (``Reference.from_qpos``)."""
    from otr_gym.reference import Reference

    start = time.perf_counter()
    q_ref = robot.qpos_mujoco_to_pinocchio(reference.qpos())
    q = q_ref.copy()
    flagged: list[int] = []
    first: list[tuple[int, int]] = []
    unsolved = 0
    for it in range(cfg.iterations + 1):
        lin = _linearise(q, q_ref, reference.fps, cfg)
        over = lin.over_bounds(cfg)
        flagged.append(int(over.sum()))
        if it == cfg.iterations or not over.any():
            break
        windows = _windows(over, cfg.pad_frames, cfg.max_window_frames)
        first = first or windows
        for w0, w1 in windows:
            solved = _solve_window(q, lin, w0, w1, cfg)
            if solved is None:
                unsolved += 1
            else:
                q[w0:w1 + 1] = solved
    out = Reference.from_qpos(robot.qpos_pinocchio_to_mujoco(q), reference.fps, objects=reference.objects,
                              contacts=reference.contacts, metadata=reference.metadata)
    out.source = reference.source
    moved = float(np.linalg.norm(out.body_pos_w - reference.body_pos_w, axis=-1).max())
    return out, TrajectoryReport(flagged, first, unsolved, time.perf_counter() - start, moved)


@dataclass
class _Linearisation:
    """Per frame: the bodies' positions and Jacobians, the filtered accelerations and their limits."""

    dt: float
    jump_p: np.ndarray  # (T, K, 3) JUMP_BODIES positions
    jump_j: np.ndarray  # (T, K, 3, NV)
    cost_r: np.ndarray  # (T, B, 3) cost bodies' offsets from the per-frame solution
    cost_j: np.ndarray  # (T, B, 3, NV)
    cost_w: np.ndarray  # (B,)
    posture: np.ndarray  # (T, NV) q ⊖ q̄
    accel: np.ndarray  # (T, 29) filtered joint accelerations (rad/s²)
    accel_limit: np.ndarray  # (T, 29) κ τ_max / M_ii
    jump_bound: np.ndarray  # (K,) per-axis bound (m)
    stance: np.ndarray  # (T, 2) bool: the per-frame solution's foot on the floor (robot.FEET)
    foot_r: np.ndarray  # (T, 2, 6) feet: position (m) and rotation (rad, world) off the per-frame solution
    foot_j: np.ndarray  # (T, 2, 6, NV)

    def off_line(self) -> np.ndarray:
        """(T, K, 3) p_t − ½(p_t−1 + p_t+1); zero at the ends."""
        e = np.zeros_like(self.jump_p)
        e[1:-1] = self.jump_p[1:-1] - 0.5 * (self.jump_p[:-2] + self.jump_p[2:])
        return e

    def over_bounds(self, cfg: TrajectoryCfg) -> np.ndarray:
        """(T,) frames whose jump (norm, against the bound × √3 · (1 + 1 %)) or joint acceleration
        (against its limit × 1.01) is over: the tolerance keeps a met row from reopening a window."""
        jump = np.linalg.norm(self.off_line(), axis=-1) > 1.01 * np.sqrt(3.0) * self.jump_bound
        accel = np.abs(self.accel) > 1.01 * self.accel_limit
        accel[[0, -1]] = False  # the check copies its neighbours' accelerations there
        return jump.any(axis=1) | accel.any(axis=1)


def _linearise(q: np.ndarray, q_ref: np.ndarray, fps: float, cfg: TrajectoryCfg) -> _Linearisation:
    import pinocchio as pin

    m = g1_dynamics().pin_model
    data, ref_data = m.createData(), m.createData()
    T = q.shape[0]
    dt = 1.0 / fps
    _, a = velocity_acceleration(lowpass(twist_steps(q, dt), cfg.lowpass_hz, fps), dt)
    cost_bodies = list(cfg.body_weights)
    cost_frames = [m.getFrameId(b) for b in cost_bodies]
    jump_frames = [m.getFrameId(b) for b in JUMP_BODIES]
    jump_p = np.zeros((T, len(jump_frames), 3))
    jump_j = np.zeros((T, len(jump_frames), 3, NV))
    cost_r = np.zeros((T, len(cost_frames), 3))
    cost_j = np.zeros((T, len(cost_frames), 3, NV))
    limit = np.zeros((T, robot.NUM_JOINTS))
    dyn = g1_dynamics()
    foot_frames = [m.getFrameId(f) for f in robot.FEET]
    stance = np.zeros((T, 2), bool)
    foot_r = np.zeros((T, 2, 6))
    foot_j = np.zeros((T, 2, 6, NV))
    world = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
    for t in range(T):
        limit[t] = cfg.accel_fraction * robot.EFFORT_LIMIT / np.diag(pin.crba(m, data, q[t]))[6:]
        pin.computeJointJacobians(m, data, q[t])
        pin.updateFramePlacements(m, data)
        pin.framesForwardKinematics(m, ref_data, q_ref[t])
        for k, fid in enumerate(jump_frames):
            jump_p[t, k] = data.oMf[fid].translation
            jump_j[t, k] = pin.getFrameJacobian(m, data, fid, world)[:3]
        for k, fid in enumerate(cost_frames):
            cost_r[t, k] = data.oMf[fid].translation - ref_data.oMf[fid].translation
            cost_j[t, k] = pin.getFrameJacobian(m, data, fid, world)[:3]
        for k, fid in enumerate(foot_frames):
            stance[t, k] = min(ref_data.oMf[s].translation[2] for s in dyn.sole_frames[k]) <= cfg.stance_height_m
            now, ref = data.oMf[fid], ref_data.oMf[fid]
            foot_r[t, k, :3] = now.translation - ref.translation
            foot_r[t, k, 3:] = pin.log3(now.rotation @ ref.rotation.T)
            foot_j[t, k] = pin.getFrameJacobian(m, data, fid, world)
    posture = np.stack([pin.difference(m, q_ref[t], q[t]) for t in range(T)])
    bound = np.array([cfg.pelvis_jump_m] + [cfg.limb_jump_m] * (len(JUMP_BODIES) - 1)) / np.sqrt(3.0)
    return _Linearisation(dt, jump_p, jump_j, cost_r, cost_j, np.array([cfg.body_weights[b] for b in cost_bodies]),
                          posture, a[:, 6:], limit, bound, stance, foot_r, foot_j)


def _windows(over: np.ndarray, pad: int, longest: int) -> list[tuple[int, int]]:
    """[(first, last)] frames to move: each flagged frame ± ``pad``, overlapping windows merged,
    then cut into pieces of at most ``longest`` frames (solved one after the other, each holding
    the last one's answer: a dense QP's time grows with the cube of its length; what a cut leaves
    over its bound opens a window about it at the next linearisation)."""
    T = over.size
    grown = np.zeros(T, bool)
    for f in np.flatnonzero(over):
        grown[max(0, f - pad):min(T, f + pad + 1)] = True
    out = []
    for a, b in true_intervals(grown, 0):
        pieces = -(-(b - a) // longest)
        edges = np.linspace(a, b, pieces + 1).round().astype(int)
        out += [(int(x), int(y) - 1) for x, y in zip(edges[:-1], edges[1:])]
    return out


def _solve_window(q: np.ndarray, lin: _Linearisation, w0: int, w1: int, cfg: TrajectoryCfg) -> np.ndarray | None:
    """(w1 − w0 + 1, nq) the window's new configurations: one dense QP (module doc), frames outside
    held; None when ProxQP does not converge within ``max_qp_iterations``."""
    import pinocchio as pin
    from proxsuite import proxqp

    m = g1_dynamics().pin_model
    T, nj = q.shape[0], robot.NUM_JOINTS
    frames = np.arange(w0, w1 + 1)
    W = frames.size
    n = W * NV

    def var(t: int) -> slice | None:  # frame t's variables, None outside the window (held: δ = 0)
        return slice((t - w0) * NV, (t - w0 + 1) * NV) if w0 <= t <= w1 else None

    # cost ½ xᵀ H x + gᵀ x
    h = np.zeros((n, n))
    g = np.zeros(n)
    for t in frames:
        v, jt = var(t), lin.cost_j[t]
        h[v, v] += np.einsum("b,bik,bil->kl", lin.cost_w, jt, jt) + cfg.posture_weight * np.eye(NV)
        g[v] += np.einsum("b,bik,bi->k", lin.cost_w, jt, lin.cost_r[t]) + cfg.posture_weight * lin.posture[t]
        for k in np.flatnonzero(lin.stance[t]):  # a standing foot stays where it stands
            w = cfg.stance_weight * np.array([1.0] * 3 + [0.01] * 3)
            fj = lin.foot_j[t, k]
            h[v, v] += fj.T @ (w[:, None] * fj)
            g[v] += fj.T @ (w * lin.foot_r[t, k])
    w2 = cfg.smooth_weight / lin.dt**4
    for t in range(w0 - 1, w1 + 2):  # the correction's second difference
        taps = [(var(s), c) for s, c in ((t - 1, 1.0), (t, -2.0), (t + 1, 1.0)) if var(s) is not None]
        for vi, a in taps:
            for vj, b in taps:
                h[vi, vj] += w2 * a * b * np.eye(NV)

    # rows lo ≤ C x ≤ hi, one block of rows at a time
    c_rows, lo, hi = [], [], []

    def add(blocks: list[tuple[int, np.ndarray]], low: np.ndarray, high: np.ndarray) -> None:
        row = np.zeros((len(low), n))
        for t, block in blocks:
            if var(t) is not None:
                row[:, var(t)] += block
        c_rows.append(row)
        lo.append(low)
        hi.append(high)

    off = lin.off_line()
    sel = np.zeros((nj, NV))
    sel[:, 6:] = np.eye(nj) / lin.dt**2
    for t in range(max(1, w0 - 1), min(T - 2, w1 + 1) + 1):  # rows touching a window frame
        for k, b in enumerate(lin.jump_bound):
            add([(t, lin.jump_j[t, k]), (t - 1, -0.5 * lin.jump_j[t - 1, k]), (t + 1, -0.5 * lin.jump_j[t + 1, k])],
                -b - off[t, k], b - off[t, k])
        a0, lim = lin.accel[t], lin.accel_limit[t]
        add([(t - 1, sel), (t, -2.0 * sel), (t + 1, sel)], -lim - a0, lim - a0)
    joints = np.zeros((nj, NV))
    joints[:, 6:] = np.eye(nj)
    for t in frames:
        add([(t, joints)], np.minimum(robot.JOINT_LOWER - q[t, 7:], 0.0), np.maximum(robot.JOINT_UPPER - q[t, 7:], 0.0))
    c = np.concatenate(c_rows)
    qp = proxqp.dense.QP(n, 0, c.shape[0])
    qp.settings.eps_abs = cfg.eps_abs
    qp.settings.verbose = False
    qp.settings.max_iter = cfg.max_qp_iterations
    qp.init(h, g, None, None, c, np.concatenate(lo), np.concatenate(hi))
    qp.solve()
    if qp.results.info.status != proxqp.QPSolverOutput.PROXQP_SOLVED:
        return None
    delta = qp.results.x.reshape(W, NV)
    return np.stack([pin.integrate(m, q[t], delta[i]) for i, t in enumerate(frames)])
