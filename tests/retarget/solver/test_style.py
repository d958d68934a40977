"""Style targets: the human T-pose maps onto the G1 T-pose; style rows differentiate correctly."""

from __future__ import annotations

import numpy as np
import pytest

from otr_gym import robot
from otr_gym.rotations import quat_to_matrix, so3_exp
from retarget.geometry.kinematics import NUM_LINKS, RobotKinematics
from retarget.inputs.human import HumanModel, g1_tpose_body_poses, g1_tpose_qpos, human_tpose
from retarget.solver.style import (
    StyleConfig,
    object_style_rows,
    pelvis_height_ratio,
    robot_style_rows,
    robot_style_targets,
)


@pytest.fixture(scope="module")
def kin() -> RobotKinematics:
    return RobotKinematics()


def test_human_tpose_gives_the_g1_tpose_as_targets(kin):
    pos, quat = human_tpose(HumanModel())
    targets = robot_style_targets(pos[None], quat[None], kin)
    g1_pos, g1_quat = g1_tpose_body_poses()
    g1_rot = quat_to_matrix(g1_quat)
    np.testing.assert_allclose(targets.rot_w[0], g1_rot[targets.links], atol=1e-9)
    # positions: the G1's own link offsets from the aligned pelvis
    pelvis = g1_pos[0]
    np.testing.assert_allclose(targets.pos_w[0] - pos[0], g1_pos[targets.links] - pelvis, atol=1e-9)



def test_pelvis_height_ratio_puts_the_human_tpose_pelvis_at_the_g1_tpose_pelvis(kin):
    model = HumanModel()
    pos, quat = human_tpose(model)
    stature = model.stature_m
    ratio = pelvis_height_ratio(stature)
    targets = robot_style_targets(pos[None], quat[None], kin, ratio)
    pelvis = int(np.flatnonzero(targets.links == 0)[0])
    np.testing.assert_allclose(targets.pos_w[0, pelvis, 2], g1_tpose_body_poses()[0][0, 2], atol=1e-9)
    np.testing.assert_allclose(targets.pos_w[0, pelvis, :2], pos[0, :2], atol=1e-12)  # horizontal kept
    assert 0.7 < ratio < 0.95 and pelvis_height_ratio(2 * stature) == pytest.approx(ratio / 2)

def test_style_rows_vanish_at_the_targets_and_match_finite_differences(kin):
    q = robot.qpos_mujoco_to_pinocchio(g1_tpose_qpos())
    data = kin.new_data()
    fr = kin.frames(data, q)
    pos, quat = human_tpose(HumanModel())
    targets = robot_style_targets(pos[None], quat[None], kin)
    shift = fr.pos[0] - targets.pos_w[0, 0]
    at_target = robot_style_rows(fr, targets.links, targets.pos_w[0] + shift, targets.rot_w[0], StyleConfig())
    assert np.abs(at_target.value).max() < 1e-9

    rng = np.random.default_rng(0)
    q0 = kin.integrate(q, rng.normal(0.0, 0.2, kin.nv))
    goal_rot = targets.rot_w[0] @ so3_exp(rng.normal(0.0, 0.5, (len(targets.links), 3)))
    goal_pos = targets.pos_w[0] + rng.normal(0.0, 0.1, targets.pos_w[0].shape)

    def rows_at(qq):
        return robot_style_rows(kin.frames(data, qq), targets.links, goal_pos, goal_rot, StyleConfig())

    fr0 = kin.frames(data, q0)
    rows = rows_at(q0)
    dv, h = rng.normal(size=kin.nv), 1e-6
    fd = (rows_at(kin.integrate(q0, h * dv)).value - rows_at(kin.integrate(q0, -h * dv)).value) / (2 * h)
    analytic = np.einsum("kc,kc->k", rows.phi[:, :6], (fr0.jac[rows.body_a] @ dv))
    np.testing.assert_allclose(analytic, fd, rtol=1e-5, atol=1e-7)


def test_object_style_rows_match_finite_differences_of_the_retraction():
    rng = np.random.default_rng(1)
    rot, pos = so3_exp(rng.normal(size=3)), rng.normal(size=3)
    goal_rot, goal_pos = so3_exp(rng.normal(size=3)), rng.normal(size=3)
    cfg = StyleConfig()
    rows = object_style_rows(pos, rot, goal_pos, goal_rot, NUM_LINKS, cfg)
    dxi, h = rng.normal(size=6), 1e-6

    def value(s):
        rows = object_style_rows(pos + s * dxi[:3], so3_exp(s * dxi[3:]) @ rot, goal_pos, goal_rot, NUM_LINKS, cfg)
        return rows.value

    fd = (value(h) - value(-h)) / (2 * h)
    np.testing.assert_allclose(rows.phi[:, :6] @ dxi, fd, rtol=1e-5, atol=1e-7)
    assert set(rows.weight) == {cfg.object_pos_weight, cfg.object_rot_weight}
