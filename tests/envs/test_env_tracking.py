"""OTR-G1-Track-v0 on CPU MuJoCo: the Gymnasium single env and the MDP's episode behaviour."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch

import otr_gym  # noqa: F401  (registers the environments)
from envs.config import RewardTermCfg, TrackEnvCfg
from envs.tracking import TrackEnv, make_task
from otr_gym import robot
from otr_gym.reference import InvalidReferenceError, Reference

from conftest import env_checker_messages


@pytest.fixture(scope="module")
def eval_task(standing_reference):
    """Two standing envs, no randomisation or noise, episodes of the clip (4 s)."""
    return make_task(standing_reference, 2, "mujoco", "cpu", evaluation=True)


def test_make_returns_a_single_env_with_the_spec_spaces(standing_reference):
    env = gymnasium.make("OTR-G1-Track-v0", reference=standing_reference)
    assert env.observation_space["policy"].shape == (154,)
    assert env.observation_space["critic"].shape == (286,)
    assert env.action_space.shape == (29,)
    obs, info = env.reset(seed=3)
    assert env.observation_space.contains(obs)
    assert info["frame"] == info["start_frame"] + 1 and info["clip"] == 0 and info["episode_length"] == 0
    env.close()


def test_gymnasium_env_checker_passes(standing_reference):
    env = gymnasium.make("OTR-G1-Track-v0", reference=standing_reference, render_mode="rgb_array", width=160,
                         height=120)
    # the only complaint allowed is the unnormalised action range (raw actions, scaled inside)
    messages = env_checker_messages(env)
    assert all("normalized space" in m for m in messages), messages
    env.close()


def test_rendered_frame_shows_the_robot_and_its_reference_ghost(standing_reference):
    env = TrackEnv(standing_reference, render_mode="rgb_array", evaluation=True, width=160, height=120)
    env.reset(seed=0)
    try:
        frame = env.render()
    except RuntimeError as exc:
        pytest.skip(f"no offscreen OpenGL on this machine: {exc}")
    assert frame.shape == (120, 160, 3) and frame.dtype == np.uint8
    renderer, qpos = env._renderer, env.task.backend.qpos[0].double().numpy()
    # the camera follows the pelvis position, not its heading: turning the robot around
    # changes only the pixels the robot covers
    turned = qpos.copy()
    turned[3:7] = [0.0, 0.0, 0.0, 1.0]
    robot_only = renderer.render(qpos)
    robot_pixels = np.abs(robot_only.astype(int) - renderer.render(turned).astype(int)).sum(-1) > 30
    assert 0.005 < robot_pixels.mean() < 0.3
    # a ghost beside the robot: a translucent, blue-tinted figure over the floor
    ghost = qpos + np.r_[0.0, 0.6, 0.0, np.zeros(33)]
    with_ghost = renderer.render(qpos, ghost_qpos=ghost).astype(int)
    changed = np.abs(with_ghost - robot_only.astype(int)).sum(-1) > 30
    assert changed.mean() > 0.02
    tint = (with_ghost - robot_only.astype(int))[changed]
    assert tint[:, 2].mean() > tint[:, 0].mean()
    env.close()


def test_reset_puts_the_robot_on_the_sampled_reference_frame(walking_reference):
    cfg = TrackEnvCfg()
    cfg.command.reset_noise_enabled = False
    task = make_task(walking_reference, 3, "mujoco", "cpu", cfg=cfg, seed=5)
    task.reset(seed=11)
    cmd = task.command
    assert len(set(cmd.start_frame.tolist())) > 1  # adaptive sampling: different frames
    expected = task.motion.qpos(cmd.start_rows)
    assert torch.allclose(task.backend.qpos, expected, atol=1e-6)
    # the body poses were recomputed for the new qpos: they match the reference's bodies (to
    # 1 mm: resampling 30 → 50 fps interpolates body positions, not the kinematics)
    ids = task.backend.body_ids(robot.TRACKED_BODIES)
    assert torch.allclose(task.backend.body_pos_w[:, ids], task.motion.body_pos_w[cmd.start_rows], atol=1e-3)
    assert torch.equal(cmd.frame, cmd.start_frame + 1)


def test_zero_action_on_a_standing_reference_holds_1_2_s_then_falls(eval_task):
    """The open-loop default-pose PD cannot hold the G1 up: it sags and topples after ~1.3 s
    (measured: first termination at step 64, the end-effector height term)."""
    eval_task.reset()
    steps, rewards = 0, []
    while True:
        _, reward, terminated, truncated, extras = eval_task.step(torch.zeros(2, 29))
        steps += 1
        rewards.append(reward)
        if terminated.any() or steps == 100:
            break
    # on the reference, the six tracking terms pay almost their maximum Σw·dt = 5 · 0.02
    assert rewards[0].min() > 0.9 * 0.1
    assert 60 <= steps <= 75, steps
    assert terminated.all() and not truncated.any()
    assert any(v.all() for v in extras["terminations"].values())


def test_a_push_over_terminates_the_pushed_env_only(eval_task):
    eval_task.reset()
    qvel = eval_task.backend.qvel.clone()
    qvel[0, 1] = 3.0  # 3 m/s sideways on env 0
    eval_task.backend.write_qvel(qvel)
    fired_at = None
    for k in range(40):
        _, _, terminated, _, extras = eval_task.step(torch.zeros(2, 29))
        if terminated[0]:
            fired_at = k
            break
        assert not terminated[1]
    assert fired_at is not None and fired_at < 40
    assert not terminated[1]
    assert extras["terminations"]["anchor_height"][0] or extras["terminations"]["anchor_ori"][0] \
        or extras["terminations"]["ee_height"][0]


def test_failure_is_counted_in_the_adaptive_bins(standing_reference):
    task = make_task(standing_reference, 2, "mujoco", "cpu", seed=0)
    before = task.command.failure_rate.sum().item()
    qvel = task.backend.qvel.clone()
    qvel[:, 1] = 4.0
    task.backend.write_qvel(qvel)
    terminated = torch.zeros(2, dtype=torch.bool)
    while not terminated.any():
        _, _, terminated, _, _ = task.step(torch.zeros(2, 29))
    after = task.command.failure_rate.sum().item()
    assert after == pytest.approx(before * 0.999 + 0.001 * terminated.sum().item(), rel=1e-5)


def test_clip_end_restarts_the_robot_without_ending_the_episode(walking_reference):
    cfg = TrackEnvCfg()
    cfg.command.reset_noise_enabled = False
    cfg.randomization.enabled = False  # no pushes: the robot must survive a few steps
    task = make_task(walking_reference, 1, "mujoco", "cpu", cfg=cfg)
    last = int(task.command.clip_length[0]) - 1
    task.command.start_frame[:] = last - 3
    task.command.frame[:] = last - 2
    task._restart(torch.zeros(1, dtype=torch.bool))
    for _ in range(3):
        _, _, terminated, truncated, _ = task.step(torch.zeros(1, 29))
        assert not terminated.any() and not truncated.any()
    assert task.episode_length_buf.item() == 3  # the episode went on ...
    assert task.command.frame.item() == task.command.start_frame.item() + 1  # ... from a new start
    assert torch.allclose(task.backend.qpos, task.motion.qpos(task.command.start_rows), atol=1e-6)


def test_evaluation_episode_starts_at_frame_zero_and_ends_with_the_clip(tmp_path):
    # a 1 s standing clip: shorter than the ~1.3 s the zero-action robot stays up
    path = Reference.from_qpos(np.tile(robot.default_qpos(), (51, 1)), 50.0).save(tmp_path / "one_second.npz")
    env = TrackEnv(path, evaluation=True)
    _, info = env.reset(seed=0)
    assert info["start_frame"] == 0 and info["frame"] == 1
    assert np.allclose(env.task.backend.qpos[0].numpy(), robot.default_qpos(), atol=1e-6)
    steps, terminated, truncated = 0, False, False
    while not (terminated or truncated):
        _, _, terminated, truncated, info = env.step(np.zeros(29, np.float32))
        steps += 1
    assert truncated and not terminated and info["success"]
    assert steps == 50  # frames 1 … 50 were the targets


def test_policy_metadata_carries_what_onnx_export_needs(standing_reference):
    env = TrackEnv(standing_reference)
    meta = env.policy_metadata()
    assert meta["joint_names"] == list(robot.JOINT_NAMES)
    assert np.allclose(meta["joint_stiffness"], robot.KP) and np.allclose(meta["joint_damping"], robot.KD)
    assert np.allclose(meta["action_scale"], robot.ACTION_SCALE)
    assert np.allclose(meta["default_joint_pos"], robot.DEFAULT_JOINT_POS)
    assert sum(meta["observation_dims"]["policy"]) == 154 and sum(meta["observation_dims"]["critic"]) == 286
    assert meta["observation_names"]["policy"][0] == "command" and meta["fps"] == 50.0
    assert meta["policy_dt"] == pytest.approx(0.02) and meta["anchor_body_name"] == "torso_link"


def test_bad_reference_fails_at_construction_naming_the_file(tmp_path):
    bad = tmp_path / "broken.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(InvalidReferenceError, match="broken.npz"):
        gymnasium.make("OTR-G1-Track-v0", reference=bad)


def test_a_reward_is_a_function_plus_a_config_line_and_unknown_names_fail(standing_reference):
    cfg = TrackEnvCfg()
    cfg.rewards = {"only_anchor": RewardTermCfg("anchor_position_error_exp", 2.0, {"sigma": 0.3})}
    task = make_task(standing_reference, 1, "mujoco", "cpu", cfg=cfg)
    _, reward, _, _, extras = task.step(torch.zeros(1, 29))
    assert set(k for k in extras["log"] if k.startswith("reward/")) == {"reward/only_anchor"}
    assert reward.item() == pytest.approx(extras["log"]["reward/only_anchor"].item())
    assert 0.0 < reward.item() <= 2.0 * 0.02
    cfg.rewards = {"typo": RewardTermCfg("anchor_position_eror_exp", 1.0)}
    with pytest.raises(ValueError, match="anchor_position_eror_exp"):
        make_task(standing_reference, 1, "mujoco", "cpu", cfg=cfg)
