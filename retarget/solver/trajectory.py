"""The trajectory pass: the per-frame solution repaired, a few frames at a time, where its paths
jump or its joints accelerate beyond what the G1's motors give them.

Why a pass over several frames: the per-frame SQP sees one frame and the two before it, so it
can bound a jump only by pushing the correction into the frames after it, where the motion then
catches up faster (bounding the paths frame by frame raised the torques:
docs/results/feasibility.md, "Bounding the paths"). Here the frames around each flagged frame
move together, so a jump is spread evenly over its neighbours on both sides.

Each window [w₀, w₁] (the flagged frames of ``otr verify``'s jump and acceleration measures,
``pad_frames`` either side, overlapping windows merged) is one sparse QP (ProxQP) on the
tangent corrections δₜ (base twist in the pelvis frame, then joints), the frames outside held:

    min   Σₜ Σ_b w_b ‖p_b(qₜ ⊕ δₜ) − p_b(q̄ₜ)‖² + w_q ‖(qₜ ⊕ δₜ) ⊖ q̄ₜ‖² + w_s ‖δₜ₊₁ − 2δₜ + δₜ₋₁‖²/dt⁴
          + Σ ρ s²                                                (the slacks of the elastic rows)
    s.t.  |p_k,t − ½(p_k,t−1 + p_k,t+1)| ≤ b_k / √3 + s           per axis (pelvis, feet, hands)
          |q̈ₜ| ≤ κ τ_max / M_ii(qₜ) · (1 + s)                     (each joint's motor alone)
          d_r(qₜ) ≥ −ε − s                                        (the SQP's collision rows: ground,
                                                                    objects, self; ``trajectory_rows``)
          |foot pose(qₜ) − foot pose(q̄ₜ)| ≤ tol + s               (a foot standing in q̄ stays: no sliding added)
          joint limits, |δ| ≤ trust region,  s ≥ 0

q̄ is the per-frame solution (the interaction-fidelity optimum: the pass stays as close to it as
the limits allow; hands and feet, the contacts, dearest), positions linearised with Pinocchio's
frame Jacobians and re-linearised ``iterations`` times (Gauss–Newton). Accelerations are the
check's (twists low-passed at ``lowpass_hz``) plus the raw second differences of the correction,
which the cost keeps smooth.

Every bound is elastic (one slack per frame and row group, priced per unit² beyond it): δ = 0 is
always feasible, so a window always has a solution, and where bounds conflict (a jump that only
a move into the floor would remove) the prices say which gives. Each step is a trust-region
step: it is taken only if the window's merit (the cost plus the priced excesses, measured on
the new configurations, the check's filtered accelerations included) falls, each standing foot
first put back on its leg's six joints (``_Pass.replant``, a second-order correction); otherwise the trust
region shrinks (×``trust_shrink``) and the window is solved again, and after ``trust_attempts``
the window keeps its frames. Units: metres, radians, seconds.

Off by default (``trajectory.enabled``): docs/results/feasibility.md, "The trajectory pass with
collision rows". Not here: the torques and the base wrench. With the contact forces as variables
and the inverse dynamics linearised (``pinocchio.computeRNEADerivatives``) the same QP became too
ill-conditioned to solve at this size: ProxQP's sparse solver did not return within 5 minutes on
30 frames, OSQP needed 6 s for 60 frames after scaling. Windows are at most ``max_window_frames``
long: ProxQP's sparse solver took 60 s on a 120-frame kinematic window; with the collision rows
and slacks a 23-frame window of the box carry (929 variables, 2,109 rows) takes it 0.3 s, its
dense solver 12 s.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from otr_gym import robot
from otr_gym.flags import true_intervals
from retarget.geometry.dynamics import g1_dynamics, lowpass, twist_steps, velocity_acceleration
from retarget.solver.trajectory_rows import FrameRows, Scene

NV = 6 + robot.NUM_JOINTS
#: The six leg joints of each foot of ``robot.FEET`` (indices into the 29 joints).
_LEG_JOINTS = [robot.joint_indices([f"{side}_{j}_joint" for j in ("hip_pitch", "hip_roll", "hip_yaw", "knee",
                                                                   "ankle_pitch", "ankle_roll")])
               for side in ("left", "right")]
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

    enabled: bool = False  # docs/results/feasibility.md, "The trajectory pass with collision rows"
    iterations: int = 3  # Gauss–Newton relinearisations
    limb_jump_m: float = 0.025  # feet and hands: bound per axis = this / √3 (m)
    pelvis_jump_m: float = 0.008
    accel_fraction: float = 0.85  # of τ_max / M_ii (``otr verify``'s joint-acceleration limit)
    lowpass_hz: float = 6.0  # accelerations as the check takes them
    pad_frames: int = 6  # frames either side of a flagged frame that move with it
    max_window_frames: int = 24  # longer windows are solved in pieces (a QP's time grows faster than its length)
    #: A foot whose sole is on the floor in the per-frame solution (a sole corner within
    #: ``stance_height_m``) keeps its pose there to within this (m per axis; its rotation × 0.1 m
    #: likewise): a standing foot that moves a millimetre a frame already slides at 5 cm/s.
    stance_tolerance_m: float = 5e-4
    stance_height_m: float = 0.02
    #: Cost per m² of moving a body from its per-frame position (hands and feet dearest: the contacts).
    body_weights: dict[str, float] = field(default_factory=_default_body_weights)
    posture_weight: float = 1.0  # per rad² (m² for the base) of change from the per-frame solution
    smooth_weight: float = 1e-4  # per (rad/s²)² of the correction's own acceleration
    #: Prices of the elastic rows' slacks, per unit² beyond the bound: a limb or pelvis jump (per
    #: m², per axis), a joint acceleration (per multiple² of its limit), a collision row (per m²
    #: beyond ``collision_tolerance_m``), a standing foot (per m²). Against the cost's 1e4 per m²
    #: of moving a hand: a centimetre of jump is worth moving the hand 30 cm, a millimetre of
    #: penetration a metre. Quadratic, not linear: with linear prices (an exact penalty) ProxQP
    #: needed thousands of iterations per window or called it infeasible.
    jump_price: float = 1e7
    accel_price: float = 1e5
    collision_price: float = 1e10
    stance_price: float = 1e9
    collision_tolerance_m: float = 3e-4  # the SQP's ε_col
    #: Trust region per step (translations of the base m, rotations and joints rad), shrunk by
    #: ``trust_shrink`` after a step that does not lower the window's merit, at most
    #: ``trust_attempts`` tries per window and iteration.
    trust_linear_m: float = 0.05
    trust_angular_rad: float = 0.25
    trust_shrink: float = 0.25
    trust_attempts: int = 3
    eps_abs: float = 1e-6
    #: ProxQP's iteration cap per window; a window it cannot solve is retried with a smaller
    #: trust region, then keeps its frames.
    max_qp_iterations: int = 200


@dataclass
class TrajectoryReport:
    """What the pass did: frames flagged before each iteration, the windows it solved, its time."""

    flagged: list[int]  # frames over a bound at each linearisation
    windows: list[tuple[int, int]]  # the first iteration's windows [first, last]
    unsolved: int  # windows left as they were (no step lowered their merit), over all iterations
    seconds: float
    moved_m: float  # largest body displacement from the per-frame solution (m)

    def line(self) -> str:
        return (f"trajectory pass: frames over a bound {' -> '.join(map(str, self.flagged))}, "
                f"{len(self.windows)} windows ({self.unsolved} unsolved, kept), "
                f"bodies moved up to {100 * self.moved_m:.1f} cm, {self.seconds:.2f} s")


def smooth_trajectory(reference, cfg: TrajectoryCfg = TrajectoryCfg(), problem=None):
    """(the reference repaired, ``TrajectoryReport``): see the module doc. ``problem`` (the clip's
    ``retarget.solver.problem.Problem``) gives the collision rows; without it the pass has none
    (only for motions with no scene, e.g. tests). Objects, contact annotations and metadata are
    carried over; body poses and velocities are recomputed (``Reference.from_qpos``)."""
    from otr_gym.reference import Reference

    start = time.perf_counter()
    q_ref = robot.qpos_mujoco_to_pinocchio(reference.qpos())
    q = q_ref.copy()
    pass_ = _Pass(q_ref, reference.fps, cfg, Scene.of(problem, reference) if problem is not None else None)
    flagged: list[int] = []
    first: list[tuple[int, int]] = []
    unsolved = 0
    for it in range(cfg.iterations + 1):
        lin = pass_.linearise(q)
        over = lin.over_bounds()
        flagged.append(int(over.sum()))
        if it == cfg.iterations or not over.any():
            break
        windows = _windows(over, cfg.pad_frames, cfg.max_window_frames)
        first = first or windows
        for w0, w1 in windows:
            solved = pass_.repair(q, lin, w0, w1)
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
class _Frames:
    """Per frame of a range: the bodies' poses off the per-frame solution, and (when asked) their
    Jacobians (world-aligned, at the frame origin)."""

    jump_p: np.ndarray  # (n, K, 3) JUMP_BODIES positions
    cost_r: np.ndarray  # (n, B, 3) cost bodies' offsets from the per-frame solution
    foot_r: np.ndarray  # (n, 2, 6) feet: position (m) and rotation × 0.1 m off the per-frame solution
    posture: np.ndarray  # (n, NV) q ⊖ q̄
    jump_j: np.ndarray | None = None  # (n, K, 3, NV)
    cost_j: np.ndarray | None = None  # (n, B, 3, NV)
    foot_j: np.ndarray | None = None  # (n, 2, 6, NV)


@dataclass
class _Linearisation:
    """The whole clip at one iterate: poses and Jacobians, the filtered accelerations and limits."""

    pass_: _Pass
    fr: _Frames
    accel: np.ndarray  # (T, 29) filtered joint accelerations (rad/s²)

    def off_line(self) -> np.ndarray:
        return _off_line(self.fr.jump_p)

    def over_bounds(self) -> np.ndarray:
        """(T,) frames whose jump (norm, against the bound × √3 · (1 + 1 %)) or joint acceleration
        (against its limit × 1.01) is over: the tolerance keeps a met row from reopening a window."""
        p = self.pass_
        jump = np.linalg.norm(self.off_line(), axis=-1) > 1.01 * np.sqrt(3.0) * p.jump_bound
        accel = np.abs(self.accel) > 1.01 * p.accel_limit
        accel[[0, -1]] = False  # the check copies its neighbours' accelerations there
        return jump.any(axis=1) | accel.any(axis=1)


def _off_line(p: np.ndarray) -> np.ndarray:
    """(n, K, 3) p_t − ½(p_t−1 + p_t+1); zero at the ends."""
    e = np.zeros_like(p)
    e[1:-1] = p[1:-1] - 0.5 * (p[:-2] + p[2:])
    return e


class _Pass:
    """The clip's fixed data (per-frame solution, limits, stance, scene) and the window steps."""

    def __init__(self, q_ref: np.ndarray, fps: float, cfg: TrajectoryCfg, scene: Scene | None) -> None:
        import pinocchio as pin

        self.cfg, self.scene, self.q_ref, self.fps = cfg, scene, q_ref, fps
        self.dt = 1.0 / fps
        dyn = g1_dynamics()
        m = self.model = dyn.pin_model
        self.data = m.createData()
        self.scene_data = scene.problem.kin.new_data() if scene is not None else None
        self.jump_frames = [m.getFrameId(b) for b in JUMP_BODIES]
        self.cost_frames = [m.getFrameId(b) for b in cfg.body_weights]
        self.cost_w = np.array(list(cfg.body_weights.values()))
        self.foot_frames = [m.getFrameId(f) for f in robot.FEET]
        T = q_ref.shape[0]
        self.accel_limit = np.zeros((T, robot.NUM_JOINTS))
        self.stance = np.zeros((T, 2), bool)
        self.foot_ref = []
        for t in range(T):
            mass = np.diag(pin.crba(m, self.data, q_ref[t]))[6:]
            self.accel_limit[t] = cfg.accel_fraction * robot.EFFORT_LIMIT / mass
            pin.framesForwardKinematics(m, self.data, q_ref[t])
            self.foot_ref.append([self.data.oMf[f].copy() for f in self.foot_frames])
            for k in range(2):
                sole = min(self.data.oMf[s].translation[2] for s in dyn.sole_frames[k])
                self.stance[t, k] = sole <= cfg.stance_height_m
        self.cost_ref = self._positions(q_ref, self.cost_frames)
        self.jump_bound = np.array([cfg.pelvis_jump_m] + [cfg.limb_jump_m] * (len(JUMP_BODIES) - 1)) / np.sqrt(3.0)

    def _positions(self, q: np.ndarray, frames: list[int]) -> np.ndarray:
        import pinocchio as pin

        out = np.zeros((q.shape[0], len(frames), 3))
        for i in range(q.shape[0]):
            pin.framesForwardKinematics(self.model, self.data, q[i])
            out[i] = [self.data.oMf[f].translation for f in frames]
        return out

    def frames(self, q: np.ndarray, ts: np.ndarray, jacobians: bool) -> _Frames:
        """``_Frames`` of frames ``ts`` at configurations q (T, nq)."""
        import pinocchio as pin

        m, data = self.model, self.data
        n, K, B = len(ts), len(self.jump_frames), len(self.cost_frames)
        out = _Frames(np.zeros((n, K, 3)), np.zeros((n, B, 3)), np.zeros((n, 2, 6)), np.zeros((n, NV)))
        if jacobians:
            out.jump_j, out.cost_j = np.zeros((n, K, 3, NV)), np.zeros((n, B, 3, NV))
            out.foot_j = np.zeros((n, 2, 6, NV))
        world = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
        for i, t in enumerate(ts):
            if jacobians:
                pin.computeJointJacobians(m, data, q[t])
                pin.updateFramePlacements(m, data)
            else:
                pin.framesForwardKinematics(m, data, q[t])
            for k, fid in enumerate(self.jump_frames):
                out.jump_p[i, k] = data.oMf[fid].translation
                if jacobians:
                    out.jump_j[i, k] = pin.getFrameJacobian(m, data, fid, world)[:3]
            for k, fid in enumerate(self.cost_frames):
                out.cost_r[i, k] = data.oMf[fid].translation - self.cost_ref[t, k]
                if jacobians:
                    out.cost_j[i, k] = pin.getFrameJacobian(m, data, fid, world)[:3]
            for k, fid in enumerate(self.foot_frames):
                now, ref = data.oMf[fid], self.foot_ref[t][k]
                out.foot_r[i, k, :3] = now.translation - ref.translation
                out.foot_r[i, k, 3:] = 0.1 * pin.log3(now.rotation @ ref.rotation.T)
                if jacobians:
                    fj = pin.getFrameJacobian(m, data, fid, world)
                    fj[3:] *= 0.1
                    out.foot_j[i, k] = fj
            out.posture[i] = pin.difference(m, self.q_ref[t], q[t])
        return out

    def accelerations(self, q: np.ndarray) -> np.ndarray:
        """(T, 29) the check's joint accelerations (twists low-passed at ``lowpass_hz``)."""
        _, a = velocity_acceleration(lowpass(twist_steps(q, self.dt), self.cfg.lowpass_hz, self.fps), self.dt)
        return a[:, 6:]

    def linearise(self, q: np.ndarray) -> _Linearisation:
        return _Linearisation(self, self.frames(q, np.arange(q.shape[0]), True), self.accelerations(q))

    def merit(self, q: np.ndarray, w0: int, w1: int, collisions: list[FrameRows] | None) -> float:
        """The window's merit at configurations q (T, nq): the QP's cost and the priced excesses
        over every bound the window's frames touch, measured (not linearised); ``collisions``:
        the window frames' collision rows at q."""
        cfg, T = self.cfg, q.shape[0]
        r0, r1 = max(0, w0 - 2), min(T - 1, w1 + 2)  # the positions the window's rows read
        fr = self.frames(q, np.arange(r0, r1 + 1), False)
        win = slice(w0 - r0, w1 - r0 + 1)
        cost = float(np.einsum("b,tbi,tbi->", self.cost_w, fr.cost_r[win], fr.cost_r[win]))
        cost += cfg.posture_weight * float(np.sum(fr.posture[win] ** 2))
        d = fr.posture
        cost += cfg.smooth_weight / self.dt**4 * float(np.sum((d[2:] - 2 * d[1:-1] + d[:-2]) ** 2))
        # jumps of the frames with both neighbours in range
        off = _off_line(fr.jump_p)[1:-1] if r1 - r0 >= 2 else np.zeros((0, len(JUMP_BODIES), 3))
        first = r0 + 1
        rows = np.arange(first, first + off.shape[0])
        off = off[(rows >= 1) & (rows <= T - 2)]
        excess = np.maximum(np.abs(off) - self.jump_bound[:, None], 0.0).max(axis=-1)
        merit = cost + cfg.jump_price * float((excess**2).sum())
        ratio = np.abs(self.accelerations(q)[1:-1]) / self.accel_limit[1:-1]
        merit += cfg.accel_price * float((np.maximum(ratio - 1.0, 0.0).max(axis=1) ** 2).sum())
        feet = np.abs(fr.foot_r[win]) - cfg.stance_tolerance_m
        merit += cfg.stance_price * float((np.maximum(feet, 0.0).max(axis=-1) ** 2 * self.stance[w0:w1 + 1]).sum())
        if collisions is not None:
            merit += cfg.collision_price * sum(_collision_excess(r.value, cfg) ** 2 for r in collisions)
        return merit

    def collision_rows(self, q: np.ndarray, w0: int, w1: int) -> list[FrameRows] | None:
        if self.scene is None:
            return None
        return [self.scene.rows(self.scene_data, q[t], t) for t in range(w0, w1 + 1)]

    def replant(self, t: int, q: np.ndarray, iterations: int = 2) -> np.ndarray:
        """q with frame t's standing feet put back where the per-frame solution has them: a
        few Gauss–Newton steps on each such leg's six joints, within the joint limits (a
        second-order correction). The stance rows are linear; a step that turns the base by a
        tenth of a radian leaves the foot millimetres off, which their price (1e9 per m²)
        rejects: without it three full steps in four on the snap test were refused."""
        import pinocchio as pin

        feet = np.flatnonzero(self.stance[t])
        m, data = self.model, self.data
        for _ in range(iterations if len(feet) else 0):
            pin.computeJointJacobians(m, data, q)
            pin.updateFramePlacements(m, data)
            q = q.copy()
            for k in feet:
                now, ref = data.oMf[self.foot_frames[k]], self.foot_ref[t][k]
                err = np.r_[ref.translation - now.translation, pin.log3(ref.rotation @ now.rotation.T)]
                cols = _LEG_JOINTS[k]
                jac = pin.getFrameJacobian(m, data, self.foot_frames[k], pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
                jac = jac[:, 6 + cols]
                step = np.linalg.solve(jac.T @ jac + 1e-8 * np.eye(6), jac.T @ err)
                q[7 + cols] = np.clip(q[7 + cols] + step, robot.JOINT_LOWER[cols], robot.JOINT_UPPER[cols])
        return q

    def repair(self, q: np.ndarray, lin: _Linearisation, w0: int, w1: int) -> np.ndarray | None:
        """(w1 − w0 + 1, nq) the window's new configurations, or None when no step within
        ``trust_attempts`` shrinking trust regions lowered its merit (module doc)."""
        import pinocchio as pin

        cfg = self.cfg
        collisions = self.collision_rows(q, w0, w1)
        before = self.merit(q, w0, w1, collisions)
        scale = 1.0
        for _ in range(cfg.trust_attempts):
            delta = _solve_window(self, q, lin, w0, w1, collisions, scale)
            if delta is not None:
                trial = q.copy()
                for i, t in enumerate(range(w0, w1 + 1)):
                    trial[t] = self.replant(t, pin.integrate(self.model, q[t], delta[i]))
                if self.merit(trial, w0, w1, self.collision_rows(trial, w0, w1)) < before:
                    return trial[w0:w1 + 1]
            scale *= cfg.trust_shrink
        return None


def _collision_excess(value: np.ndarray, cfg: TrajectoryCfg) -> float:
    """A frame's collision slack: its deepest row beyond the tolerance (m), 0 when none is."""
    return float(max(0.0, -cfg.collision_tolerance_m - value.min())) if len(value) else 0.0


def _windows(over: np.ndarray, pad: int, longest: int) -> list[tuple[int, int]]:
    """[(first, last)] frames to move: each flagged frame ± ``pad``, overlapping windows merged,
    then cut into pieces of at most ``longest`` frames (solved one after the other, each holding
    the last one's answer: a QP's time grows faster than its length; what a cut leaves
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


@dataclass
class _Group:
    """A block of elastic rows low − scale·s ≤ Σ_t block_t δ_t ≤ high + scale·s with one slack s
    (priced ``price`` per unit²), and which of its rows are in the QP (the others are checked
    against each solution)."""

    terms: list[tuple[int, np.ndarray]]  # (frame, (k, NV) block)
    low: np.ndarray  # (k,)
    high: np.ndarray  # (k,)
    price: float
    scale: np.ndarray  # (k,)
    chosen: np.ndarray  # (k,) bool

    def predict(self, delta: dict[int, np.ndarray]) -> np.ndarray:
        return sum(block @ delta[t] for t, block in self.terms)


class _Window:
    """One window's QP: x = (δ_w₀ … δ_w₁, the slacks of the groups with rows in it), its
    elastic row groups."""

    def __init__(self, w0: int, w1: int) -> None:
        self.w0, self.w1 = w0, w1
        self.n_delta = (w1 - w0 + 1) * NV
        self.groups: list[_Group] = []

    def var(self, t: int) -> slice | None:
        """Frame t's variables, None outside the window (held: δ = 0)."""
        return slice((t - self.w0) * NV, (t - self.w0 + 1) * NV) if self.w0 <= t <= self.w1 else None

    def add(self, terms: list[tuple[int, np.ndarray]], low: np.ndarray, high: np.ndarray, price: float,
            chosen: np.ndarray | bool = True, scale: np.ndarray | float = 1.0) -> None:
        """Elastic rows with a slack of their own; rows of frames outside the window read only
        its frames (the others are held)."""
        terms = [(t, b) for t, b in terms if self.var(t) is not None]
        if terms:
            self.groups.append(_Group(terms, low, high, price, np.broadcast_to(np.asarray(scale, float), low.shape),
                                      np.broadcast_to(chosen, low.shape).copy()))

    def in_qp(self) -> list[_Group]:
        """The groups with rows in the QP, in the order of their slacks."""
        return [gr for gr in self.groups if gr.chosen.any()]

    def matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """C, lo, hi of the chosen rows, each elastic row as one-sided rows (an infinite side has none)."""
        parts = []
        for slack, gr in enumerate(self.in_qp()):
            c = gr.chosen
            for sign, low, high in ((-1.0, np.full(int(c.sum()), -np.inf), gr.high[c]),
                                    (1.0, gr.low[c], np.full(int(c.sum()), np.inf))):
                if np.isfinite(low).any() or np.isfinite(high).any():
                    parts.append((gr, slack, c, sign, low, high))
        n = self.n_delta + len(self.in_qp())
        m = sum(len(part[4]) for part in parts)
        mat, lo, hi = np.zeros((m, n)), np.empty(m), np.empty(m)
        r = 0
        for gr, slack, c, sign, low, high in parts:
            k = len(low)
            for t, block in gr.terms:
                mat[r:r + k, self.var(t)] += block[c]
            mat[r:r + k, self.n_delta + slack] = sign * gr.scale[c]
            lo[r:r + k], hi[r:r + k] = low, high
            r += k
        return mat, lo, hi


def _solve_window(p: _Pass, q: np.ndarray, lin: _Linearisation, w0: int, w1: int,
                  collisions: list[FrameRows] | None, scale: float) -> np.ndarray | None:
    """(w1 − w0 + 1, NV) the window's step: one sparse QP (module doc) within the trust region ×
    ``scale``, the frames outside held; None when ProxQP does not converge within
    ``max_qp_iterations``. The QP starts from the rows near their bound (jumps and
    accelerations past half of it, the collision rows' seeds); rows the step violates are added
    and the QP solved again (at most ``_ACTIVE_SET_ROUNDS`` times)."""
    from proxsuite import proxqp
    from scipy import sparse

    cfg, fr = p.cfg, lin.fr
    T, nj = q.shape[0], robot.NUM_JOINTS
    frames = np.arange(w0, w1 + 1)
    win = _Window(w0, w1)
    n = win.n_delta

    # cost ½ xᵀ H x + gᵀ x on δ (the slacks' prices are added below)
    h = np.zeros((n, n))
    g = np.zeros(n)
    for t in frames:
        v, jt = win.var(t), fr.cost_j[t]
        h[v, v] += 2.0 * (np.einsum("b,bik,bil->kl", p.cost_w, jt, jt) + cfg.posture_weight * np.eye(NV))
        g[v] += 2.0 * (np.einsum("b,bik,bi->k", p.cost_w, jt, fr.cost_r[t]) + cfg.posture_weight * fr.posture[t])
    w2 = 2.0 * cfg.smooth_weight / p.dt**4
    centres = range(max(1, w0 - 1), min(T - 2, w1 + 1) + 1)
    for t in centres:  # the deviation's second difference
        taps = ((t - 1, 1.0), (t, -2.0), (t + 1, 1.0))
        dd = sum(c * fr.posture[s] for s, c in taps)
        for s, a in taps:
            vi = win.var(s)
            if vi is None:
                continue
            g[vi] += w2 * a * dd
            for u, b in taps:
                vj = win.var(u)
                if vj is not None:
                    h[vi, vj] += w2 * a * b * np.eye(NV)

    off = lin.off_line()
    sel = np.zeros((nj, NV))
    sel[:, 6:] = np.eye(nj) / p.dt**2
    jj = fr.jump_j
    for t in centres:  # rows touching a window frame
        for k, b in enumerate(p.jump_bound):
            win.add([(t, jj[t, k]), (t - 1, -0.5 * jj[t - 1, k]), (t + 1, -0.5 * jj[t + 1, k])],
                    -b - off[t, k], b - off[t, k], cfg.jump_price, np.abs(off[t, k]) > 0.5 * b)
        a0, lim = lin.accel[t], p.accel_limit[t]
        win.add([(t - 1, sel), (t, -2.0 * sel), (t + 1, sel)], -lim - a0, lim - a0, cfg.accel_price,
                np.abs(a0) > 0.5 * lim, lim)
    tol = cfg.stance_tolerance_m
    for t in frames:
        for k in np.flatnonzero(p.stance[t]):  # a standing foot stays where the per-frame solution has it
            win.add([(t, fr.foot_j[t, k])], -tol - fr.foot_r[t, k], tol - fr.foot_r[t, k], cfg.stance_price)
    for t, rows in zip(frames, collisions or []):
        if len(rows):
            win.add([(t, rows.jac)], -cfg.collision_tolerance_m - rows.value, np.full(len(rows), np.inf),
                    cfg.collision_price, rows.seed)

    # the box: trust region ∩ joint limits on δ (both hold δ = 0), slacks ≥ 0
    trust = scale * np.r_[np.full(3, cfg.trust_linear_m), np.full(NV - 3, cfg.trust_angular_rad)]
    box_lo, box_hi = np.tile(-trust, len(frames)), np.tile(trust, len(frames))
    for t in frames:
        v = win.var(t)
        box_lo[v][6:] = np.maximum(box_lo[v][6:], np.minimum(robot.JOINT_LOWER - q[t, 7:], 0.0))
        box_hi[v][6:] = np.minimum(box_hi[v][6:], np.maximum(robot.JOINT_UPPER - q[t, 7:], 0.0))
    for _ in range(_ACTIVE_SET_ROUNDS):
        groups = win.in_qp()
        n_slack = len(groups)
        H = np.zeros((n + n_slack, n + n_slack))
        H[:n, :n] = h
        H[np.arange(n, n + n_slack), np.arange(n, n + n_slack)] = [2.0 * gr.price for gr in groups]
        c_mat, lo, hi = win.matrices()
        # ProxQP's sparse solver: on a 23-frame window of the box carry (929 variables, 2,109
        # rows) 0.3 s, its dense one 12 s (1.4 s with the primal-dual backend)
        n_x = n + n_slack
        qp = proxqp.sparse.QP(n_x, 0, c_mat.shape[0] + n_x)
        qp.settings.eps_abs = cfg.eps_abs
        qp.settings.eps_rel = cfg.eps_abs
        qp.settings.verbose = False
        qp.settings.max_iter = cfg.max_qp_iterations
        qp.init(sparse.csc_matrix(H), np.concatenate([g, np.zeros(n_slack)]), None, None,
                sparse.vstack([sparse.csc_matrix(c_mat), sparse.identity(n_x)], format="csc"),
                np.maximum(np.concatenate([lo, box_lo, np.zeros(n_slack)]), -_BIG),
                np.minimum(np.concatenate([hi, box_hi, np.full(n_slack, np.inf)]), _BIG))
        qp.solve()
        if qp.results.info.status != proxqp.QPSolverOutput.PROXQP_SOLVED:
            return None
        x = qp.results.x
        delta = {int(t): x[win.var(t)] for t in frames}
        slack = dict(zip(map(id, groups), x[n:]))
        added = False
        for gr in win.groups:  # rows the step violates join the QP
            if gr.chosen.all():
                continue
            s = gr.scale * slack.get(id(gr), 0.0)
            pred = gr.predict(delta)
            violated = ~gr.chosen & ((pred < gr.low - s - 1e-5) | (pred > gr.high + s + 1e-5))
            if violated.any():
                gr.chosen |= violated
                added = True
        if not added:
            break
    return x[:n].reshape(len(frames), NV)


#: Infinite bounds as ProxQP's sparse solver takes them.
_BIG = 1e20
#: QP solves per window step: the first, and again while the step violates rows left out of it.
_ACTIVE_SET_ROUNDS = 3
