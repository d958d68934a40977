"""The procedural references used by tests and the training recipe."""

from __future__ import annotations

import numpy as np
import pytest

from agents.procedural import WalkSpec, standing_reference, walking_reference
from otr_gym import robot


@pytest.fixture(scope="module")
def walk():
    return walking_reference(WalkSpec(steps=6))


def test_standing_reference_holds_the_default_pose(tmp_path):
    ref = standing_reference(duration_s=1.0)
    assert ref.num_frames == 51 and ref.fps == 50.0
    np.testing.assert_allclose(ref.qpos(), np.tile(robot.default_qpos(), (51, 1)))
    assert np.abs(ref.body_lin_vel_w).max() < 1e-9


def test_walk_advances_by_its_footstep_plan(walk):
    spec = WalkSpec(steps=6)
    planned = 0.5 * spec.step_length_m + (spec.steps - 2) * spec.step_length_m
    assert walk.root_pos_w[-1, 0] - walk.root_pos_w[0, 0] == pytest.approx(planned, abs=0.01)
    assert np.abs(walk.root_pos_w[:, 1]).max() <= spec.sway_m + 1e-9


def test_walk_feet_reach_their_targets_and_never_go_below_the_ground(walk):
    feet = walk.body_index(["left_ankle_roll_link", "right_ankle_roll_link"])
    z = walk.body_pos_w[:, feet, 2]
    ground_z = walk.body_pos_w[0, feet, 2]  # the default stance, soles on the ground
    assert z.min() >= ground_z.min() - 1e-4
    assert z.max() == pytest.approx(ground_z.max() + WalkSpec.step_height_m, abs=2e-3)


def test_walk_stance_feet_do_not_slide(walk):
    feet = walk.body_index(["left_ankle_roll_link", "right_ankle_roll_link"])
    on_ground = walk.body_pos_w[:, feet, 2] < walk.body_pos_w[0, feet, 2] + 1e-4
    planted = on_ground[1:] & on_ground[:-1]  # down on two consecutive frames
    step_xy = np.linalg.norm(np.diff(walk.body_pos_w[:, feet, :2], axis=0), axis=-1)
    assert planted.sum() > walk.num_frames  # both feet are down most of the time
    assert step_xy[planted].max() < 1e-4  # < 5 mm/s at 50 fps


def test_walk_respects_joint_limits(walk):
    q = walk.dof_pos
    assert (q >= robot.JOINT_LOWER - 1e-9).all() and (q <= robot.JOINT_UPPER + 1e-9).all()


def test_sway_keeps_both_feet_planted_while_the_pelvis_squats_and_sways():
    from agents.procedural import SwaySpec, sway_reference

    spec = SwaySpec(duration_s=6.0)
    ref = sway_reference(spec)
    feet = ref.body_pos_w[:, ref.body_index(list(robot.FEET))]  # (T, 2, 3)
    assert np.abs(feet - feet[:1]).max() < 2e-3  # planted (IK tolerance)
    z = ref.root_pos_w[:, 2]
    assert z[0] == pytest.approx(robot.DEFAULT_ROOT_HEIGHT_M) and z[-1] == pytest.approx(robot.DEFAULT_ROOT_HEIGHT_M)
    assert 0.5 * spec.squat_m < z.max() - z.min() <= spec.squat_m + 1e-9
    assert np.ptp(ref.root_pos_w[:, 1]) > spec.sway_m
