"""The trajectory pass (retarget.solver.trajectory) on generated G1 motions with a known defect:
a foot that snaps for one frame, an elbow faster than its motor, and a clip with nothing to repair;
its elastic rows where the bounds cannot all be met; its collision rows (the SQP's own)."""

from __future__ import annotations

import numpy as np

from otr_gym import robot
from otr_gym.reference import Reference
from retarget.checks.feasibility import check_feasibility
from retarget.solver.problem import build_problem, resample_demonstration
from retarget.solver.trajectory import TrajectoryCfg, smooth_trajectory
from retarget.solver.trajectory_rows import Scene

from clips import clip

FPS = 50.0
ON = TrajectoryCfg(enabled=True, iterations=6)  # the trust region moves a joint at most 0.25 rad a step


def _standing(frames: int = 40) -> np.ndarray:
    return np.tile(robot.default_qpos(), (frames, 1))


def _ref(qpos: np.ndarray) -> Reference:
    return Reference.from_qpos(qpos, FPS)


def test_a_foot_that_the_old_solution_teleports_is_put_on_a_smooth_path():
    """The swing foot rises 8 cm (a knee bend) between frames 18 and 22 but snaps 12 cm at frame
    20: after the pass no limb or pelvis leaves its neighbours' line by more than verify's limits,
    the standing foot has not moved, and the frames away from the snap are exactly as they were."""
    qpos = _standing()
    knee = 7 + robot.JOINT_NAMES.index("left_knee_joint")
    hip = 7 + robot.JOINT_NAMES.index("left_hip_pitch_joint")
    qpos[18:23, knee] += np.array([0.2, 0.4, 0.9, 0.4, 0.2])
    qpos[18:23, hip] -= np.array([0.1, 0.2, 0.45, 0.2, 0.1])
    before = check_feasibility(_ref(qpos))
    assert before.limb_jump_m.max() > 0.05  # the snap
    ref = _ref(qpos)
    out, report = smooth_trajectory(ref, ON)
    after = check_feasibility(out)
    assert after.limb_jump_m.max() < 0.03 and after.root_jump_m.max() < 0.01
    assert after.frames_over()["limb jump"] == 0
    right = ref.body_index(["right_ankle_roll_link"])[0]
    assert np.abs(out.body_pos_w[:, right] - ref.body_pos_w[:, right]).max() < 2e-3  # the standing foot stays
    changed = np.abs(out.joint_pos - ref.joint_pos).max(axis=1) > 0
    lo, hi = report.windows[0]
    assert not changed[:lo].any() and not changed[hi + 1:].any() and lo > 0 and hi < 39


def test_a_shoulder_faster_than_its_motor_is_slowed_within_its_acceleration_limit():
    """The left shoulder rolls out 1 rad for five frames and back: twice what its motor alone can
    accelerate it (at the check's 6 Hz); after the pass, within it, and the arm still swings out."""
    qpos = _standing()
    shoulder = 7 + robot.JOINT_NAMES.index("left_shoulder_roll_joint")
    qpos[20:25, shoulder] += 1.0
    before = check_feasibility(_ref(qpos))
    assert before.joint_accel_ratio.max() > 1.5
    out, _ = smooth_trajectory(_ref(qpos), ON)
    after = check_feasibility(out)
    assert after.joint_accel_ratio.max() <= 1.0
    assert out.joint_pos[22, shoulder] - qpos[0, shoulder] > 0.3  # the path is slowed, not erased


def test_a_feasible_clip_is_left_exactly_as_it_was():
    qpos = _standing()
    ref = _ref(qpos)
    out, report = smooth_trajectory(ref, ON)
    np.testing.assert_array_equal(out.joint_pos, ref.joint_pos)
    assert report.flagged == [0] and report.windows == [] and report.moved_m == 0.0


def test_a_window_whose_qp_does_not_converge_keeps_its_frames():
    """With ProxQP allowed a single iteration no window converges, with any trust region: the
    pass reports them and leaves the clip as it was instead of applying an unfinished answer."""
    qpos = _standing()
    qpos[20:25, 7 + robot.JOINT_NAMES.index("left_shoulder_roll_joint")] += 1.0
    ref = _ref(qpos)
    out, report = smooth_trajectory(ref, TrajectoryCfg(enabled=True, max_qp_iterations=1))
    assert report.unsolved >= 1 and report.windows
    np.testing.assert_array_equal(out.joint_pos, ref.joint_pos)


def test_bounds_that_cannot_all_be_met_still_give_a_step_that_lowers_the_jump():
    """Jump bounds of 2 mm (limbs) and 1 mm (pelvis) are beyond any step of the trust region on
    the 12 cm snap: hard rows would make the window infeasible; the elastic rows give it a step,
    and the snap shrinks."""
    qpos = _standing()
    knee = 7 + robot.JOINT_NAMES.index("left_knee_joint")
    qpos[19:22, knee] += np.array([0.3, 0.9, 0.3])
    before = check_feasibility(_ref(qpos)).limb_jump_m.max()
    out, report = smooth_trajectory(_ref(qpos), TrajectoryCfg(enabled=True, limb_jump_m=0.002, pelvis_jump_m=0.001,
                                                              iterations=1))
    assert report.unsolved == 0 and report.windows
    assert check_feasibility(out).limb_jump_m.max() < 0.8 * before


def test_collision_rows_are_the_solvers_rows_against_the_ground_and_move_with_the_base():
    """A G1 standing on the floor, then sunk 1 cm: the scene's ground rows (the SQP's hull-guard
    rows) read about −1 cm deeper, and raising the base by δz raises them by δz."""
    problem = build_problem(resample_demonstration(clip("walk", 30, 36), 50.0), "robot-only")
    scene = Scene(problem, np.zeros((problem.num_frames, 0, 3)), np.zeros((problem.num_frames, 0, 3, 3)))
    data = problem.kin.new_data()
    q = robot.qpos_mujoco_to_pinocchio(robot.default_qpos()[None])[0]
    standing = scene.rows(data, q, 0)
    low = q.copy()
    low[2] -= 0.01
    sunk = scene.rows(data, low, 0)
    assert len(standing) and len(sunk) and sunk.seed.any()
    assert abs(sunk.value.min() - (standing.value.min() - 0.01)) < 2e-3
    up = np.zeros(problem.kin.nv)
    up[2] = 1.0  # the base twist's z (the pelvis upright: world z)
    ground = sunk.value < 0.005
    np.testing.assert_allclose(sunk.jac[ground] @ up, 1.0, atol=0.05)
