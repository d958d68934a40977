"""The QP of one SQP iterate (eq. m-qp): Gauss–Newton cost assembled per run of rows sharing
their bodies, constraint rows, variable boxes (joint limits, velocity limits, object boxes,
trust region) and the step solved by ProxQP, with violated candidate rows added after each
solve."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from otr_gym import robot
from otr_gym.rotations import so3_log
from retarget.geometry.kinematics import NUM_LINKS, LinkFrames
from retarget.solver.iterate import FrameStats, SectionTimer, SolverState
from retarget.solver.problem import Problem
from retarget.solver.residuals import FIXED, Rows
from retarget.solver.rows import Linearisation, rows_take
from retarget.solver.targets import FrameTargets


def body_jacobians(problem: Problem, frames: LinkFrames) -> np.ndarray:
    """(L + O + 1, 6, n): link Jacobians, object selectors, and zeros for FIXED (index −1)."""
    n = problem.num_variables
    nv = problem.kin.nv
    jac = np.zeros((NUM_LINKS + len(problem.objects) + 1, 6, n))
    jac[:NUM_LINKS, :, :nv] = frames.jac
    for i in range(len(problem.objects)):
        jac[NUM_LINKS + i, :, nv + 6 * i:nv + 6 * i + 6] = np.eye(6)
    return jac


def _runs(code: np.ndarray) -> np.ndarray:
    return np.flatnonzero(np.concatenate([[True], code[1:] != code[:-1]]))


def assemble_cost(rows: Rows, jac: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Newton H = Σ w JᵀJ and g = Σ w J r, merged per run of rows on the same bodies.

    A run's rows share their bodies, hence their Jacobians: its block is
    [J_A; J_B]ᵀ (Φᵀ W Φ) [J_A; J_B] (J_B = 0 for a fixed channel). The 12×12 Φᵀ W Φ of each
    run is accumulated in one pass over the rows, then all runs go through one batched product
    with their Jacobians: the cost grows with the number of (body, channel) runs, not of probes.
    """
    n = jac.shape[2]
    if len(rows) == 0:
        return np.zeros((n, n)), np.zeros(n)
    starts = _runs(rows.body_a * (jac.shape[0] + 1) + rows.body_b)
    m = np.empty((len(starts), 12, 12))
    v = np.empty((len(starts), 12))
    _run_moments(rows.value, rows.weight, rows.phi, np.append(starts, len(rows)), rows.body_b[starts] == FIXED, m, v)
    j = np.concatenate([jac.take(rows.body_a[starts], axis=0), jac.take(rows.body_b[starts], axis=0)],
                       axis=1).reshape(-1, n)
    mj = (m @ j.reshape(len(starts), 12, n)).reshape(-1, n)
    return j.T @ mj, j.T @ v.ravel()


@numba.njit(cache=True)
def _run_moments(value, weight, phi, bounds, fixed_b, m, v):
    """Per run r (rows bounds[r]:bounds[r + 1]): m[r] = Σ w φφᵀ (12, 12), v[r] = Σ w r φ (12,).
    Runs against a fixed body B (J_B = 0) only need the upper-left 6×6 block."""
    for r in range(m.shape[0]):
        size = 6 if fixed_b[r] else 12
        m[r] = 0.0
        v[r] = 0.0
        for k in range(bounds[r], bounds[r + 1]):
            w = weight[k]
            for a in range(size):
                wa = w * phi[k, a]
                v[r, a] += wa * value[k]
                for b in range(a, size):
                    m[r, a, b] += wa * phi[k, b]
        for a in range(size):
            for b in range(a):
                m[r, a, b] = m[r, b, a]


def constraint_matrix(rows: Rows, jac: np.ndarray) -> np.ndarray:
    """(k, n) rows φ_Aᵀ J_A + φ_Bᵀ J_B."""
    return (np.einsum("kc,kcn->kn", rows.phi[:, :6], jac[rows.body_a])
            + np.einsum("kc,kcn->kn", rows.phi[:, 6:], jac[rows.body_b]))


def _interval(lo: np.ndarray, hi: np.ndarray, trust: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[lo, hi] ∩ [−trust, trust]; when empty (the iterate violates a bound by more than one
    step), the step that moves furthest towards [lo, hi]."""
    a, b = np.maximum(lo, -trust), np.minimum(hi, trust)
    empty = a > b
    toward = np.clip(np.where(lo > 0, lo, hi), -trust, trust)
    return np.where(empty, toward, a), np.where(empty, toward, b)


def variable_bounds(problem: Problem, state: SolverState, targets: FrameTargets) -> tuple[np.ndarray, np.ndarray]:
    """Per-variable boxes on the step at the iterate, trust region aside: joint limits ∩
    velocity limits ∩ object boxes (eq. m-qp-lim, m-qp-vel, m-qp-box)."""
    cfg = problem.solver
    nv = problem.kin.nv
    lo = np.full(problem.num_variables, -np.inf)
    hi = np.full(problem.num_variables, np.inf)
    qj = state.q[7:]
    lo[6:nv] = problem.kin.joint_lower - qj
    hi[6:nv] = problem.kin.joint_upper - qj
    if state.prev is not None:
        reach = robot.VELOCITY_LIMIT / problem.fps
        qj_prev = state.prev[0][7:]
        lo[6:nv] = np.maximum(lo[6:nv], qj_prev - reach - qj)
        hi[6:nv] = np.minimum(hi[6:nv], qj_prev + reach - qj)
    n_obj = len(problem.objects)
    if n_obj:
        # deviation from the demonstrated pose (b_cor), and from the predicted pose: the last
        # solution moved by the demonstrated displacement (b_env)
        ref_pos, ref_rot, boxes = [targets.obj_pos], [targets.obj_rot], [cfg.object_deviation_box]
        if state.prev is not None and state.prev_demo is not None:
            dp, dr = state.prev_demo
            ref_pos.append(state.prev[1] + targets.obj_pos - dp)
            ref_rot.append(targets.obj_rot @ np.swapaxes(dr, -1, -2) @ state.prev[2])
            boxes.append(cfg.object_step_box)
        k = len(boxes)
        ref_rot = np.concatenate(ref_rot)
        error = np.concatenate([np.tile(state.obj_pos, (k, 1)) - np.concatenate(ref_pos),
                                so3_log(np.tile(state.obj_rot, (k, 1, 1)) @ np.swapaxes(ref_rot, -1, -2))],
                               axis=1).reshape(k, n_obj * 6)
        box = np.array([np.tile(np.repeat(b, 3), n_obj) for b in boxes])  # (k, 6 O)
        lo[nv:] = np.max(-box - error, axis=0)
        hi[nv:] = np.min(box - error, axis=0)
    return lo, hi


def step_bounds(problem: Problem, bounds: tuple[np.ndarray, np.ndarray],
                trust_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Per-variable boxes: trust region × ``trust_scale`` ∩ ``variable_bounds``."""
    return _interval(bounds[0], bounds[1], trust_scale * problem.trust)


@dataclass
class QPModel:
    """The Gauss–Newton model of one accepted iterate, reused when a trial step is rejected.

    A trial iterate first gets its merit only; ``jac``, ``H``, ``g`` and ``chosen`` are filled
    by :func:`assemble_model` once the trust-region test has accepted it and another step is
    asked of it (the last accepted trial of a frame's budget is never assembled)."""

    lin: Linearisation
    energy: float  # E at the iterate
    penalty: float  # L1 penalty of its violations beyond ε_col
    jac: np.ndarray | None = None
    H: np.ndarray | None = None
    g: np.ndarray | None = None
    chosen: np.ndarray | None = None  # constraint rows in the QP
    bounds: tuple[np.ndarray, np.ndarray] | None = None  # ``variable_bounds`` at the iterate, once asked
    #: the contact-state rows the last step crossed, priced at that step (``qp_step``)
    hinge_predicted: float = 0.0

    @property
    def merit(self) -> float:
        return self.energy + self.penalty


def merit(problem: Problem, state: SolverState, lin: Linearisation) -> tuple[float, float]:
    """(E = Σ w r² + ‖q ⊖ q_{t−1}‖² [+ W‖com − c*‖²], L1 penalty on the violations beyond ε_col)."""
    cfg = problem.solver
    energy = float(np.dot(lin.cost.weight, lin.cost.value ** 2))
    if lin.com is not None:
        r = lin.com[0]
        energy += float(r @ (problem.com_weights * r))
    if state.prev is not None:
        e = problem.kin.difference(state.prev[0], state.q)
        energy += cfg.previous_frame_weight * float(e @ e)
    excess = np.maximum(0.0, -cfg.penetration_tolerance_m - lin.constraints.value)
    return energy, cfg.violation_penalty * float(excess.sum())


def model_at(problem: Problem, state: SolverState, lin: Linearisation, timings: dict[str, float],
             assemble: bool = True) -> QPModel:
    """The model at the state's iterate (linearised as ``lin``); without ``assemble``, its merit only."""
    tm = SectionTimer(timings)
    model = QPModel(lin, *merit(problem, state, lin))
    tm.lap("qp_assembly")
    if assemble:
        assemble_model(problem, state, model, timings)
    return model


def assemble_model(problem: Problem, state: SolverState, model: QPModel, timings: dict[str, float]) -> None:
    """Fill the model's QP (H, g, Jacobians, first constraint rows); the state must be at its iterate."""
    tm = SectionTimer(timings)
    cfg, lin = problem.solver, model.lin
    chosen = np.zeros(len(lin.constraints), dtype=bool)
    chosen[lin.initial] = True
    tm.lap("constraint_selection")
    jac = body_jacobians(problem, lin.frames)
    H, g = assemble_cost(lin.cost, jac)
    nv = problem.kin.nv
    if state.prev is not None:
        e = problem.kin.difference(state.prev[0], state.q)  # q ⊖ q_{t−1}
        H[:nv, :nv] += cfg.previous_frame_weight * np.eye(nv)
        g[:nv] += cfg.previous_frame_weight * e
    if lin.com is not None:  # the COM term (retarget.solver.balance)
        r, jc = lin.com
        w = problem.com_weights
        H[:nv, :nv] += jc.T @ (w[:, None] * jc)
        g[:nv] += jc.T @ (w * r)
    H[np.diag_indices_from(H)] += cfg.damping
    model.jac, model.H, model.g, model.chosen = jac, H, g, chosen
    tm.lap("qp_assembly")


def qp_step(problem: Problem, state: SolverState, targets: FrameTargets, model: QPModel, trust_scale: float,
            stats: FrameStats, price_hinges: bool = True) -> np.ndarray:
    """The QP step of eq. m-qp at the model's iterate, trust region × ``trust_scale``.

    Constraint rows start from ``model.chosen``; after each solve every candidate row is
    predicted through the bodies' twists and the violated ones are added (at most 3 times, and
    not after a QP that ProxQP could not solve).
    """
    cfg = problem.solver
    eps = cfg.penetration_tolerance_m
    tm = SectionTimer(stats.timings)
    if model.bounds is None:
        model.bounds = variable_bounds(problem, state, targets)
    box_lo, box_hi = step_bounds(problem, model.bounds, trust_scale)
    rows, chosen, jac = model.lin.constraints, model.chosen, model.jac
    price = price_hinges and cfg.price_contact_state and model.lin.hinge is not None
    hinge = model.lin.hinge if price else Rows.empty()
    priced = np.zeros(len(hinge), dtype=bool)
    H, g = model.H, model.g
    model.hinge_predicted = 0.0
    for _ in range(4):
        sub = rows_take(rows, np.flatnonzero(chosen))
        # Rows aim at d ≥ 0 (ε_col is the slack for linearisation error); a penetrating pair
        # asks to get out by at most one step, so the QP stays feasible.
        lower = np.minimum(-sub.value, trust_scale * cfg.trust_linear_m)
        C = constraint_matrix(sub, jac)
        tm.lap("qp_assembly")
        failures = state.qp.failures
        delta = state.qp.solve(H, g, C, lower, box_lo, box_hi)
        tm.lap("qp_solve")
        if state.qp.failures > failures:
            break  # the rows conflict already: more rows cannot help, the relaxed step stands
        twist = jac @ delta
        violated = np.empty(len(rows), dtype=bool)
        _violated_rows(rows.value, rows.phi, rows.body_a, rows.body_b, twist, chosen, -eps, violated)
        # a contact-state row that the step would carry out of its demonstrated state (a foot
        # lowered into the floor's clearance) costs from there on: without it in the model the
        # trust-region test refused the step (Bandai walk: 177 of 222 refusals)
        crossed = np.zeros(len(hinge), dtype=bool)
        if len(hinge):
            after = hinge.value + _rates(hinge, twist)
            crossed = ~priced & (model.lin.hinge_side * after < 0.0)
            model.hinge_predicted = float(np.sum(hinge.weight * np.minimum(model.lin.hinge_side * after, 0.0) ** 2))
        tm.lap("qp_assembly")
        if not (violated.any() or crossed.any()):
            break
        chosen |= violated
        if crossed.any():
            priced |= crossed
            dH, dg = assemble_cost(rows_take(hinge, np.flatnonzero(priced)), jac)
            H, g = model.H + dH, model.g + dg
    stats.qp_rows.append(int(chosen.sum()))
    return delta


def _rates(rows: Rows, twist: np.ndarray) -> np.ndarray:
    """(k,) φ_A·ν_A + φ_B·ν_B of ``rows`` at the bodies' twists (bodies, 6; FIXED the last, zero)."""
    fixed = twist.shape[0] - 1
    a = np.where(rows.body_a == FIXED, fixed, rows.body_a)
    b = np.where(rows.body_b == FIXED, fixed, rows.body_b)
    return np.einsum("kc,kc->k", rows.phi[:, :6], twist[a]) + np.einsum("kc,kc->k", rows.phi[:, 6:], twist[b])


@numba.njit(cache=True)
def _violated_rows(value, phi, body_a, body_b, twist, chosen, threshold, out):
    """out[k] ← row k is not chosen and its prediction r + φ_A·ν_A + φ_B·ν_B at the bodies'
    twists ``twist`` (bodies, 6; FIXED the last, zero) is below ``threshold``. The 12-term dot
    product in the order of numpy's einsum (its baseline SSE2 kernel: two lanes, each summing
    its products of a block of eight last first, the rest in pairs, then lane 0 + lane 1)."""
    fixed = twist.shape[0] - 1
    for k in range(value.shape[0]):
        a = body_a[k] if body_a[k] != FIXED else fixed
        b = body_b[k] if body_b[k] != FIXED else fixed
        p0, p1, p2 = phi[k, 0] * twist[a, 0], phi[k, 1] * twist[a, 1], phi[k, 2] * twist[a, 2]
        p3, p4, p5 = phi[k, 3] * twist[a, 3], phi[k, 4] * twist[a, 4], phi[k, 5] * twist[a, 5]
        p6, p7, p8 = phi[k, 6] * twist[b, 0], phi[k, 7] * twist[b, 1], phi[k, 8] * twist[b, 2]
        p9, p10, p11 = phi[k, 9] * twist[b, 3], phi[k, 10] * twist[b, 4], phi[k, 11] * twist[b, 5]
        lane0 = p10 + (p8 + (p0 + (p2 + (p4 + (p6 + 0.0)))))
        lane1 = p11 + (p9 + (p1 + (p3 + (p5 + (p7 + 0.0)))))
        out[k] = not chosen[k] and value[k] + (0.0 + (lane0 + lane1)) < threshold
