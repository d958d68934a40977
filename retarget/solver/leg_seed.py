"""Warm-start moves of the G1 legs: each foot link brought to a pose on its leg's six joints.

The warm start (``retarget.solver.sqp.warm_start``) moves the whole robot rigidly with the
person's pelvis. Two kinds of feet then start the frame away from where they belong:

* a **planted** foot (in stance at t − 1 and t) moved with the base: ``replant_feet`` puts it
  back where it stood;
* a **swinging** foot (not in stance at t − 1 or at t) kept its place relative to the pelvis,
  while the person's foot moved relative to the pelvis (in a walk's swing, 4-8 cm a frame at
  50 fps; a dash, more). ``carry_swing_feet`` moves it by the person's foot displacement.

Why the second one matters (issue 52, limb jumps; docs/results/feasibility.md, *Why a swing
foot jumps*): a warm-started frame has a budget of three trust-region steps, and its first full
step is often rejected because the stiff floor and stance rows (1e5-1e6 per m²) see the
second-order drop of a pitched foot's toe as a penetration; the steps after it move the foot
2-3 cm each. A swing foot that the warm start leaves behind therefore falls behind the frame's
optimum by a few centimetres every frame (Bandai's walk: 30-40 cm by the end of a swing) and
catches up in one frame as soon as a stance or roll-off flag changes the rows: the 16-17 cm
jumps of that clip. Started from the person's displacement, the SQP only corrects.
``SolverConfig.carry_swing_feet`` switches the carry on; it is off by default (its cost in
time and contact fidelity: the same section).

``replant_trial`` works inside a frame instead: it puts a standing foot's held points back on
their targets in each trial iterate before the trust-region test (``SolverConfig.replant_trial``,
off: docs/results/feasibility.md, *The carry, 2026-12-07 evening*).
"""

from __future__ import annotations

import numpy as np

from otr_gym import robot
from otr_gym.rotations import so3_log
from retarget.solver.iterate import SolverState, frames_at
from retarget.solver.problem import Problem

#: The six leg joints of each G1 foot link (indices into the 29 joints), by name from the spec.
LEG_JOINTS = {f"{side}_ankle_roll_link": robot.joint_indices(
    [f"{side}_{j}_joint" for j in ("hip_pitch", "hip_roll", "hip_yaw", "knee", "ankle_pitch", "ankle_roll")])
    for side in ("left", "right")}


def _step_leg(problem: Problem, q: np.ndarray, link: int, jac: np.ndarray, residual: np.ndarray) -> None:
    """One damped least-squares step of ``link``'s six leg joints in ``q`` (in place) towards
    ``residual`` through ``jac`` (rows × 6 leg columns): at most 0.1 rad per joint (the SQP's
    trust region), within the joint limits."""
    joints = LEG_JOINTS[robot.BODY_NAMES[link]]
    step = np.clip(np.linalg.solve(jac.T @ jac + 1e-4 * np.eye(6), jac.T @ residual), -0.1, 0.1)
    q[7 + joints] = np.clip(q[7 + joints] + step, problem.kin.joint_lower[joints], problem.kin.joint_upper[joints])


def move_legs(problem: Problem, state: SolverState, targets: dict[int, tuple[np.ndarray, np.ndarray]],
              iterations: int = 2) -> None:
    """Bring each foot link of ``targets`` (link → (world rotation (3, 3), world position (3,) m))
    towards its pose: a few damped Gauss–Newton steps on its leg's six joints (link Jacobians),
    at most 0.1 rad per joint and step (the SQP's trust region), within the joint limits. A step
    that does not lower the summed squared error (m², rad²) is not taken."""
    if not targets:
        return

    def errors(q: np.ndarray) -> tuple[object, dict]:
        fr = frames_at(problem, state, q)
        return fr, {link: np.concatenate([pos - fr.pos[link], so3_log(rot @ fr.rot[link].T)])
                    for link, (rot, pos) in targets.items()}

    now, err = errors(state.q)
    for _ in range(iterations):
        q = state.q.copy()
        for link in targets:
            # (6, 6): the leg's columns (world-aligned, link origin)
            _step_leg(problem, q, link, now.jac[link][:, 6 + LEG_JOINTS[robot.BODY_NAMES[link]]], err[link])
        trial, trial_err = errors(q)
        if sum(float(e @ e) for e in trial_err.values()) >= sum(float(e @ e) for e in err.values()):
            break  # keep the better configuration
        state.q, now, err = q, trial, trial_err


def replant_feet(problem: Problem, state: SolverState, t: int, iterations: int = 2) -> None:
    """Bring the feet planted at t − 1 and still in stance at t back to their previous poses
    after the warm start moved the base (``move_legs``).

    The warm start moves the robot rigidly with the person's pelvis, planted feet included; the
    stance rows then open each frame centimetres off their targets (a merit of ~10² at 10⁶ per
    m²), which took the SQP its whole iteration budget in one frame out of two."""
    if state.prev is None or t == 0:
        return
    feet = [link for f, link in enumerate(problem.feet) if problem.stance[t - 1, f] and problem.stance[t, f]]
    if not feet:
        return
    before = frames_at(problem, state, state.prev[0])
    move_legs(problem, state, {link: (before.rot[link].copy(), before.pos[link].copy()) for link in feet},
              iterations)


def carry_swing_feet(problem: Problem, state: SolverState, t: int, iterations: int = 2) -> None:
    """Move every foot not in stance at both t − 1 and t by the person's displacement of the
    same foot: its pose at t − 1's solution, translated by the foot's style target's displacement
    (m, world) and turned by its rotation (``move_legs``; the module doc says why)."""
    if state.prev is None or t == 0:
        return
    slots = {int(link): k for k, link in enumerate(problem.style.links)}
    feet = [int(link) for f, link in enumerate(problem.feet)
            if not (problem.stance[t - 1, f] and problem.stance[t, f]) and int(link) in slots]
    if not feet:
        return
    before = frames_at(problem, state, state.prev[0])
    pos_w, rot_w = problem.style.pos_w, problem.style.rot_w
    targets = {}
    for link in feet:
        k = slots[link]
        turn = rot_w[t, k] @ rot_w[t - 1, k].T
        targets[link] = (turn @ before.rot[link], before.pos[link] + pos_w[t, k] - pos_w[t - 1, k])
    move_legs(problem, state, targets, iterations)


def replant_trial(problem: Problem, state: SolverState, stance, iterations: int = 2,
                  tolerance_m: float = 1e-4) -> None:
    """Put the held sole points of a standing foot (every coordinate held) back on their targets
    (``StanceTargets``) in a trial iterate, before the trust-region test judges the step: damped
    Gauss–Newton steps per foot on its leg's six joints (point Jacobians), at most 0.1 rad per
    joint, within the joint limits, each kept only if it lowers the foot's summed squared miss;
    a foot within ``tolerance_m`` everywhere is left alone, and so is a foot held only in height
    (sweeping), whose free x, y the correction would move unpriced.

    The QP's step is first order: a full step that pitches a held foot drops its toe by the
    second-order term, which the stiff stance rows (1e6 per m²) price at many times the
    predicted gain, and the step is refused. Re-planting before the merit is measured is a
    second-order correction of that refusal. ``SolverConfig.replant_trial``; off (measured in
    docs/results/feasibility.md, *The carry, 2026-12-07 evening*: it moves the standing leg
    unchecked against the swinging one)."""
    if len(stance.link) == 0:
        return

    def misses(fr):
        out = {}
        for link in np.unique(stance.link):
            sel = stance.link == link
            x = stance.points[sel] @ fr.rot[link].T + fr.pos[link]
            target = stance.target_w[sel]
            out[int(link)] = (x, np.where(np.isfinite(target), target - x, 0.0), np.isfinite(target))
        return out

    fr = frames_at(problem, state, state.q)
    now = misses(fr)
    for _ in range(iterations):
        q = state.q.copy()
        moving = [link for link, (_, miss, held) in now.items()
                  if held.all() and np.abs(miss).max() >= tolerance_m]  # standing feet only
        if not moving:
            return
        for link in moving:
            x, miss, held = now[link]
            joints = LEG_JOINTS[robot.BODY_NAMES[link]]
            jac = fr.jac[link][:, 6 + joints]  # (6, 6) world-aligned at the link origin
            # a point's velocity v + ω × r: J_v − r × J_ω
            point_jac = jac[None, :3, :] - np.cross((x - fr.pos[link])[:, :, None], jac[None, 3:, :],
                                                    axisa=1, axisb=1, axisc=1)
            _step_leg(problem, q, link, point_jac[held], miss[held])
        trial_fr = frames_at(problem, state, q)
        trial = misses(trial_fr)
        better = [link for link in moving if float(np.sum(trial[link][1] ** 2)) < float(np.sum(now[link][1] ** 2))]
        if len(better) < len(moving):  # keep only the feet that came closer
            for link in set(moving) - set(better):
                joints = LEG_JOINTS[robot.BODY_NAMES[link]]
                q[7 + joints] = state.q[7 + joints]
            if not better:
                return
            trial_fr = frames_at(problem, state, q)
            trial = misses(trial_fr)
        state.q, fr, now = q, trial_fr, trial
