"""Peers' G1 references (Holosoma, ../shared/data/references/holosoma) drive the env unchanged."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.mdp.motion import MotionLibrary
from envs.tracking import TrackEnv, make_task
from otr_gym import robot
from otr_gym.reference import Reference

FILES = ("sub3_largebox_003_mj_w_obj.npz", "motion_crawl_slope.npz")


@pytest.fixture(scope="module")
def holosoma(shared_data):
    return shared_data / "references" / "holosoma"


@pytest.mark.parametrize("name", FILES)
def test_holosoma_file_loads_with_its_tracked_bodies_selected_by_name(holosoma, name):
    raw = Reference.load(holosoma / name)
    lib = MotionLibrary.load(holosoma / name, robot.TRACKED_BODIES)
    assert lib.clip_length.item() == raw.num_frames  # already 50 fps
    index = raw.body_index(robot.TRACKED_BODIES)  # their files hold 51–52 bodies incl. 'world'
    assert np.allclose(lib.body_pos_w.numpy(), raw.body_pos_w[:, index], atol=1e-6)
    # their stored poses agree with our G1's forward kinematics of their joint angles to ~1 cm
    fk = Reference.from_qpos(raw.qpos(), raw.fps)
    err = np.linalg.norm(fk.body_pos_w[:, fk.body_index(robot.TRACKED_BODIES)] - raw.body_pos_w[:, index], axis=-1)
    assert err.max() < 0.015 and err.mean() < 0.004


def test_holosoma_angular_velocities_are_recomputed_from_the_poses(holosoma):
    """Their body_ang_vel_w is R·ω rather than ω; the library differentiates the quaternions."""
    raw = Reference.load(holosoma / FILES[0])
    lib = MotionLibrary.load(holosoma / FILES[0], robot.TRACKED_BODIES)
    fd = raw.with_recomputed_velocities()
    index = raw.body_index(robot.TRACKED_BODIES)
    assert np.allclose(lib.body_ang_vel_w.numpy(), fd.body_ang_vel_w[:, index], atol=1e-4)
    assert np.abs(raw.body_ang_vel_w[:, index] - fd.body_ang_vel_w[:, index]).max() > 1.0


def test_a_folder_of_holosoma_files_is_a_two_clip_library_for_the_env(holosoma):
    task = make_task(holosoma, 2, "mujoco", "cpu", evaluation=True)
    assert task.motion.num_clips == 2 and task.command.clip.tolist() == [0, 1]
    for _ in range(3):
        obs, reward, terminated, truncated, _ = task.step(torch.zeros(2, 29))
        assert torch.isfinite(obs["critic"]).all() and torch.isfinite(reward).all()
    assert task.command.frame.tolist() == [4, 4]


def test_box_clip_runs_in_the_single_env(holosoma):
    env = TrackEnv(holosoma / FILES[0], evaluation=True)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    _, reward, _, _, _ = env.step(np.zeros(29, np.float32))
    assert reward > 0.05  # the robot starts on the reference: the tracking terms pay
