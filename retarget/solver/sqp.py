"""Trust-region SQP over the G1 configuration and every free object's pose (paper Sec. III-D).

Per frame t the solver minimises E_int + E_sty,r + E_sty,o + ‖q_t ⊖ q_{t−1}‖² subject to joint
limits, joint velocity limits, object displacement boxes, non-penetration of every probe–channel
pair and capsule self-collision (eq. m-program, m-qp). Each SQP iterate linearises everything
(Gauss–Newton Hessian, analytic Jacobians) into a dense QP solved by ProxQP, whose workspace is
reused across iterations and frames (``QPWorkspace``; ProxQP's own warm start from its previous
result is a switch, off because it measured slower). The SQP is warm-started: each frame starts
from the previous solution moved by the demonstrated displacement (``warm_start``).

Decision variables δ = (δv, δξ_1, …, δξ_O): δv ∈ R³⁵ the Pinocchio tangent of the G1 (base
twist in the base frame, then joints), δξ_o = (δτ, δθ) ∈ R⁶ per free object (retraction
τ ← τ + δτ, R ← exp(δθ)R). Every residual/constraint row is a pair of 6-vectors φ on the two
bodies it involves (``retarget.solver.residuals.Rows``); with one (6, n) Jacobian per body the QP is
assembled per run of rows sharing their bodies: H += Jᵀ(Σ w φφᵀ)J, so its cost grows with the
number of (link, channel) pairs, not with the number of probes.

Modules: ``retarget.solver.problem`` (the immutable problem), ``retarget.solver.targets`` (per-frame
demonstrated targets), ``retarget.solver.iterate`` (mutable state), ``retarget.solver.rows`` (linearisation),
``retarget.solver.qp`` (QP assembly and step), ``retarget.solver.contact_annotation``; this module is the
SQP loop over frames.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pinocchio as pin
from threadpoolctl import threadpool_limits

from otr_gym import robot
from otr_gym.rotations import so3_exp
from retarget.geometry.kinematics import NUM_LINKS
from retarget.solver.arm_seed import arm_links, seed_arms
from retarget.solver.contact_annotation import frame_contacts
from retarget.solver.iterate import FrameStats, SectionTimer, SolverState, frames_at, new_state, retract
from retarget.solver.leg_seed import carry_swing_feet, replant_feet, replant_trial
from retarget.solver.problem import Problem
from retarget.solver.qp import QPModel, assemble_model, body_jacobians, model_at, qp_step
from retarget.solver.rows import linearise
from retarget.solver.self_rows import self_mesh_rows
from retarget.solver.stance import stance_targets
from retarget.solver.targets import frame_targets


def solve_frame(problem: Problem, state: SolverState, t: int) -> FrameStats:
    """Trust-region SQP of frame t from the state's current iterate (warm start).

    Each iteration solves the QP, evaluates the merit (E plus an L1 penalty on violations
    beyond ε_col) at the trial point, and accepts the step if the merit decreases by at least
    a tenth of the model's prediction; otherwise the step is undone and the trust region
    shrinks (×``trust_shrink``), after good steps it grows back. The proximity residuals are
    not smooth everywhere (witnesses jump across box edges), so without this test the
    Gauss–Newton steps can wander at the full trust radius instead of converging. The budget
    (50 iterations on the first frame, 3 after) counts trial steps; it ends early when
    ‖δ‖∞ < 1e-4, when the model predicts too small a decrease (``model_tolerance``), or when a
    step predicted to gain little is rejected (``rejected_model_tolerance``). If the accepted
    point still violates ε_col, restoration steps follow (``SolverConfig.feasibility_iterations``).
    """
    stats = FrameStats()
    tm = SectionTimer(stats.timings)
    previous = frames_at(problem, state, state.prev[0]) if state.prev is not None else None
    targets = replace(frame_targets(problem, t),
                      stance=stance_targets(problem.stance, t, problem.feet, problem.soles,
                                            problem.surface_margin[problem.feet], previous, problem.stance_cfg,
                                            problem.turns, problem.sweep, state.stance))
    if problem.com_offset_rate > 0.0:  # the person's COM moved by the G1's own offset (none yet on frame 0)
        targets = replace(targets, com=None if state.com_offset is None else targets.com + state.com_offset)
    tm.lap("demo_triples")
    cfg = problem.solver
    eps = cfg.penetration_tolerance_m
    budget = cfg.first_frame_iterations if state.prev is None else cfg.iterations
    lin = linearise(problem, state, targets, stats.timings)
    counts, contact = lin.counts, lin.contact
    model = model_at(problem, state, lin, stats.timings)
    scale = 1.0
    for _ in range(budget):
        if model.H is None:  # an accepted trial's QP, assembled only once another step is asked of it
            assemble_model(problem, state, model, stats.timings)
        delta = qp_step(problem, state, targets, model, scale, stats)
        stats.iterations += 1
        step = float(np.abs(delta).max())
        # predicted merit decrease: the model's decrease of E, and the violations the QP removes
        predicted = -(2.0 * model.g @ delta + delta @ model.H @ delta) + model.penalty - model.hinge_predicted
        if step < cfg.step_tolerance or predicted < cfg.model_tolerance * model.merit:
            break
        saved = (state.q.copy(), state.obj_pos.copy(), state.obj_rot.copy())
        retract(problem, state, delta)
        if cfg.replant_trial:  # the step's second-order drop of a held toe is not the step's fault
            replant_trial(problem, state, targets.stance)
        trial = linearise(problem, state, targets, stats.timings, counts=counts, contact=contact)
        trial_model = model_at(problem, state, trial, stats.timings, assemble=False)
        gain = model.merit - trial_model.merit
        # a step that the linearised rows allowed but that lands deeper in a surface than the
        # iterate was (a thin part the grid cannot resolve, a witness jumping across an edge)
        # is the linearisation's failure, not progress, whatever the cost gains
        deeper = trial.min_distance < min(model.lin.min_distance, -eps) - cfg.step_penetration_m
        if gain > 0.1 * max(predicted, 0.0) and gain > 0.0 and not deeper:
            model = trial_model
            if gain > 0.75 * predicted:
                scale = min(1.0, 2.0 * scale)
        else:
            state.q, state.obj_pos, state.obj_rot = saved
            stats.rejected += 1
            if predicted < cfg.rejected_model_tolerance * model.merit:
                break
            # shrink around the rejected step (which may sit well inside the region)
            scale = cfg.trust_shrink * float(np.max(np.abs(delta) / problem.trust))
    lin = model.lin
    # Feasibility restoration: the smallest move that the linearised constraints accept, with a
    # trust region shrinking each time, until every pair is within ε_col (linearisation error
    # is second order in the step, so small steps converge).
    for k in range(cfg.feasibility_iterations):
        if lin.min_distance >= -eps and lin.min_self_distance >= -eps:
            break
        jac = body_jacobians(problem, lin.frames)
        n = problem.num_variables
        chosen = np.zeros(len(lin.constraints), dtype=bool)
        chosen[lin.initial] = True
        chosen |= lin.constraints.value < eps
        restore = QPModel(lin, 0.0, 0.0, jac, np.eye(n), np.zeros(n), chosen)
        delta = qp_step(problem, state, targets, restore, cfg.feasibility_trust_scale ** k, stats, price_hinges=False)
        stats.iterations += 1
        retract(problem, state, delta)
        lin = linearise(problem, state, targets, stats.timings, counts=counts, contact=contact)
    stats.active_pairs = lin.active_pairs
    stats.min_distance_m = lin.min_distance
    stats.min_self_distance_m = lin.min_self_distance
    state.prev = (state.q.copy(), state.obj_pos.copy(), state.obj_rot.copy())
    state.prev_demo = (targets.obj_pos.copy(), targets.obj_rot.copy())
    state.stance = targets.stance
    return stats


@dataclass
class Solution:
    """The solved sequence: MuJoCo-layout qpos, free-object poses, contacts and statistics."""

    qpos: np.ndarray  # (T, 36) [xyz, wxyz, joints]
    obj_pos: np.ndarray  # (T, O, 3)
    obj_rot: np.ndarray  # (T, O, 3, 3)
    contacts: np.ndarray  # (T, L, C)
    witness_c: np.ndarray  # (T, L, C, 3)
    stats: list[FrameStats]
    qp_failures: int


def warm_start(problem: Problem, state: SolverState, t: int, held: np.ndarray) -> None:
    """First iterate of frame t from the solution of t − 1, moved by the demonstration.

    The robot base and every object it holds (``held``, per free object) move together by the
    demonstrated pelvis's planar displacement (xy translation, yaw about the base): a rigid
    motion of the robot with its load keeps the previous solution's contacts and clearances,
    and a planar one keeps the soles on the ground. Objects not held move by their own
    demonstrated displacement.
    """
    pelvis = int(np.flatnonzero(problem.style.links == 0)[0])
    rot_prev, rot_now = problem.style.rot_w[t - 1, pelvis], problem.style.rot_w[t, pelvis]
    yaw = np.arctan2(rot_now[1, 0], rot_now[0, 0]) - np.arctan2(rot_prev[1, 0], rot_prev[0, 0])
    turn = so3_exp(np.array([0.0, 0.0, yaw]))
    shift = problem.part_pos_w[t, 0] - problem.part_pos_w[t - 1, 0]
    shift[2] = 0.0
    base = state.q[:3].copy()
    state.q[:3] = base + shift
    base_rot = pin.Quaternion(state.q[6], *state.q[3:6]).toRotationMatrix()
    state.q[3:7] = pin.Quaternion(turn @ base_rot).coeffs()  # xyzw
    for i, o in enumerate(problem.objects):
        if held[i]:
            state.obj_pos[i] = base + shift + turn @ (state.obj_pos[i] - base)
            state.obj_rot[i] = turn @ state.obj_rot[i]
        else:
            tr = problem.channels[o.channel]
            state.obj_pos[i] += tr.pos_w[t] - tr.pos_w[t - 1]
            state.obj_rot[i] = tr.rot_w[t] @ tr.rot_w[t - 1].T @ state.obj_rot[i]


def _seed_if_clear(problem: Problem, state: SolverState, seeded: np.ndarray) -> None:
    """Take the warm-start move ``seeded`` unless it brings the robot's meshes further into each
    other than they are (beyond the penetration tolerance). A seed whose meshes are clear to within
    the tolerance is taken without measuring the plain warm start's (the same test: the bar is
    min(plain, −tolerance))."""
    if np.array_equal(seeded, state.q):
        return
    clear = _self_clearance(problem, state, seeded)
    if clear >= -problem.solver.penetration_tolerance_m or clear >= _self_clearance(problem, state, state.q):
        state.q = seeded


def _self_clearance(problem: Problem, state: SolverState, q: np.ndarray) -> float:
    """Smallest self-collision row of the meshes at ``q`` (m; inf when no pair is close).

    An arm seed is a jump: when it lands a hand inside the thigh, the linearised rows of the
    two shells point both ways and the SQP cannot get it out again (deep squat: 2 cm deep for
    the rest of the clip). A seed is taken only if it leaves the meshes no deeper in each other
    than the plain warm start does."""
    fr = frames_at(problem, state, q)
    centre_w = np.einsum("lij,lj->li", fr.rot, problem.link_center) + fr.pos
    rows = self_mesh_rows(problem, fr, centre_w, problem.solver.constraint_margin_m)
    return float(rows.value.min()) if len(rows) else np.inf


def follow_com_offset(problem: Problem, state: SolverState, t: int) -> None:
    """After frame t: the offset of the G1's COM from the person's (``Problem.com_offset_rate``)."""
    if state.com_data is None:
        state.com_data = problem.kin.new_data()
    offset = pin.centerOfMass(problem.kin.model, state.com_data, state.q) - problem.com_target[t]
    if state.com_offset is None:
        state.com_offset = offset.copy()
    else:
        state.com_offset += problem.com_offset_rate * (offset - state.com_offset)


def solve_sequence(problem: Problem, progress=None) -> Solution:
    """Solve every frame in order, each warm-started from the previous solution.

    BLAS and OpenMP run on one thread meanwhile: the products are small, so threads cost more
    than they save, and the pipeline's workers give the parallelism.
    """
    with threadpool_limits(limits=1):
        return _solve_sequence(problem, progress)


def _solve_sequence(problem: Problem, progress) -> Solution:
    state = new_state(problem)
    T, n_obj = problem.num_frames, len(problem.objects)
    qpos = np.empty((T, 7 + robot.NUM_JOINTS))
    obj_pos, obj_rot = np.empty((T, n_obj, 3)), np.empty((T, n_obj, 3, 3))
    contacts = np.empty((T, NUM_LINKS, len(problem.channels)))
    witness = np.empty((T, NUM_LINKS, len(problem.channels), 3))
    stats = []
    held = np.zeros(n_obj, dtype=bool)
    object_channels = np.array([c for c, tr in enumerate(problem.channels) if not tr.is_ground], dtype=np.intp)
    arm_link_ids = {side: arm_links(side) for side in ("left", "right")}
    arms_free = (True, True)
    for t in range(T):
        if t > 0:
            warm_start(problem, state, t, held)
            replant_feet(problem, state, t)
            if problem.solver.carry_swing_feet:  # the person's swing, not the SQP's budget, moves them
                plain = state.q
                carry_swing_feet(problem, state, t)
                # a foot carried into the other leg (a narrow gait's swing past the standing
                # shin) stays there (Bandai: 3.8 cm deep, 81 failed QPs)
                carried, state.q = state.q, plain
                _seed_if_clear(problem, state, carried)
            # a local SQP cannot leave an arm branch pinned at joint limits (retarget.solver.arm_seed)
            _seed_if_clear(problem, state, seed_arms(state.q, state.prev[0], problem.style.rot_w[t], problem.fps,
                                                     free=arms_free))
        stats.append(solve_frame(problem, state, t))
        if problem.com_offset_rate > 0.0:
            follow_com_offset(problem, state, t)
        fc = frame_contacts(problem, state, t)
        held = np.array([fc.distance[:, o.channel].min() < problem.solver.hold_distance_m for o in problem.objects],
                        dtype=bool)
        arms_free = tuple(bool((fc.distance[arm_link_ids[side]][:, object_channels] >= problem.band_m).all())
                          for side in ("left", "right"))
        qpos[t] = robot.qpos_pinocchio_to_mujoco(state.q)
        obj_pos[t], obj_rot[t] = state.obj_pos, state.obj_rot
        contacts[t], witness[t] = fc.distance, fc.witness_c
        if progress is not None:
            progress(t)
    return Solution(qpos, obj_pos, obj_rot, contacts, witness, stats, state.qp.failures)
