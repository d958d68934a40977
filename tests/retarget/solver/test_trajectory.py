"""The trajectory pass (retarget.solver.trajectory) on generated G1 motions with a known defect:
a foot that snaps for one frame, an elbow faster than its motor, and a clip with nothing to repair."""

from __future__ import annotations

import numpy as np

from otr_gym import robot
from otr_gym.reference import Reference
from retarget.checks.feasibility import check_feasibility
from retarget.solver.trajectory import TrajectoryCfg, smooth_trajectory

FPS = 50.0
ON = TrajectoryCfg(enabled=True)


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
    """With ProxQP allowed a single iteration no window converges: the pass reports them and
    leaves the clip as it was instead of applying an unfinished answer."""
    qpos = _standing()
    qpos[20:25, 7 + robot.JOINT_NAMES.index("left_shoulder_roll_joint")] += 1.0
    ref = _ref(qpos)
    out, report = smooth_trajectory(ref, TrajectoryCfg(enabled=True, max_qp_iterations=1))
    assert report.unsolved >= 1 and report.windows
    np.testing.assert_array_equal(out.joint_pos, ref.joint_pos)
