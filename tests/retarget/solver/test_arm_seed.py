"""Arm seeds (retarget.solver.arm_seed): style-only arm IK on both Euler branches, within limits."""

import numpy as np
from scipy.spatial.transform import Rotation

from otr_gym import robot
from retarget.solver.arm_seed import (
    SeedConfig,
    _euler_branches,
    arm_chains,
    arm_rotations,
    best_arm,
    seed_arms,
)


def _tracked_targets(chain, base, waist, arm):
    return arm_rotations(chain, base, np.concatenate([waist, arm])[None])[0][[5, 6, 9]]


def test_both_euler_branches_reproduce_the_rotation_for_shoulder_and_wrist_orders():
    for axes in ((1, 0, 2), (0, 1, 2)):
        for m in Rotation.random(20, random_state=2).as_matrix():
            for a, b, c in _euler_branches(m, axes):
                r = {0: "x", 1: "y", 2: "z"}
                back = Rotation.from_euler("".join(r[k].upper() for k in axes), [a, b, c]).as_matrix()
                assert np.abs(back - m).max() < 1e-9


def test_best_arm_recovers_any_reachable_arm_pose_within_the_joint_limits():
    rng = np.random.default_rng(0)
    for chain in arm_chains():
        for _ in range(30):
            arm = rng.uniform(chain.lower, chain.upper)
            waist, base = (rng.uniform(-0.3, 0.3, 3),
                           Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix())
            found, cost = best_arm(chain, base, waist, _tracked_targets(chain, base, waist, arm))
            assert cost < 1e-8
            assert np.all(found >= chain.lower - 1e-12) and np.all(found <= chain.upper + 1e-12)


def test_seed_moves_a_flipped_shoulder_back_towards_its_branch_within_the_velocity_limit():
    """A shoulder pinned at its roll/pitch/yaw limits (the AMASS walk defect) with the human arm
    hanging down: the seed moves it towards the arm-down pose by at most the velocity reach."""
    left, _ = arm_chains()
    q = np.concatenate([[0.0, 0.0, 0.8, 0.0, 0.0, 0.0, 1.0], robot.DEFAULT_JOINT_POS])
    targets = np.tile(np.eye(3), (14, 1, 1))
    down = np.array([-0.7, 0.4, -0.5, 1.2, 0.0, 0.0, 0.0])
    targets[left.slots] = _tracked_targets(left, np.eye(3), np.zeros(3), down)
    stuck = q.copy()
    stuck[7 + left.joints[3:]] = [2.67, 2.25, 2.62, 0.8, 0.0, 0.0, 0.0]
    fps, cfg = 50.0, SeedConfig()
    seeded = seed_arms(stuck, stuck, targets, fps, cfg)
    step = seeded[7 + left.joints[3:]] - stuck[7 + left.joints[3:]]
    assert np.all(np.abs(step) <= cfg.velocity_fraction * left.velocity / fps + 1e-12)
    assert np.sign(step[0]) < 0 and np.abs(step[:3]).max() > 0.5  # pitch leaves its +2.67 limit
    cold = seed_arms(stuck, None, targets, fps, cfg)  # no previous frame: straight to the pose
    assert np.abs(cold[7 + left.joints[3:]] - down).max() < 1e-3
