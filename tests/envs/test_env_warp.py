"""The MuJoCo-Warp backend and the vector env, run on warp's "cpu" device (as CI does).

The first warp test of a fresh machine compiles MuJoCo-Warp's kernels (45–90 s on 2 cores,
cached in ~/.cache/warp afterwards); the fixtures are module-scoped so that happens once.
"""

from __future__ import annotations

import gymnasium
import mujoco
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode

import otr_gym  # noqa: F401  (registers the environments)
from envs.backends import build_sim_model
from envs.backends.mujoco_backend import MuJoCoBackend
from envs.backends.warp_backend import WarpBackend
from envs.config import TrackEnvCfg
from envs.tracking import make_task
from otr_gym import robot

wp = pytest.importorskip("warp")

NUM_ENVS = 3


@pytest.fixture(scope="module")
def backend_pair(walking_reference):
    """The same evaluation task (no randomisation, no noise) on CPU MuJoCo and on MuJoCo-Warp."""
    cpu = make_task(walking_reference, NUM_ENVS, "mujoco", "cpu", evaluation=True)
    gpu_code = make_task(walking_reference, NUM_ENVS, "warp", "cpu", evaluation=True)
    return cpu, gpu_code


@pytest.fixture(scope="module")
def vec_env(walking_reference):
    envs = gymnasium.make_vec("OTR-G1-Track-v0", num_envs=4, vectorization_mode="vector_entry_point",
                              device="cpu", reference=walking_reference, seed=2)
    yield envs
    envs.close()


def test_both_backends_give_the_same_observations_and_rewards_from_the_same_state(backend_pair):
    """One policy step from an identical state with identical actions, 40 times over a walking
    clip. Measured: rewards agree to 1e-7, every observation term to 2e-5 except the joint
    velocities, which differ by up to 3e-4 rad/s (float32 MuJoCo-Warp vs float64 MuJoCo
    contact solves, 10 Newton iterations)."""
    cpu, warp_task = backend_pair
    cpu.reset(seed=0)
    warp_task.reset(seed=0)
    everyone = torch.ones(NUM_ENVS, dtype=torch.bool)
    layout = cpu.obs_layout["critic"]
    gen = torch.Generator().manual_seed(0)
    worst_term: dict[str, float] = {}
    worst_reward = 0.0
    for _ in range(40):
        qpos, qvel = cpu.backend.qpos.clone(), cpu.backend.qvel.clone()
        cpu.backend.reset(everyone, qpos, qvel)
        warp_task.backend.reset(everyone, qpos, qvel)
        actions = 0.5 * torch.randn(NUM_ENVS, 29, generator=gen)
        obs_a, rew_a, term_a, _, _ = cpu.step(actions)
        obs_b, rew_b, term_b, _, _ = warp_task.step(actions)
        assert torch.equal(term_a, term_b)
        worst_reward = max(worst_reward, (rew_a - rew_b).abs().max().item())
        start = 0
        for name, dim in layout:
            diff = (obs_a["critic"][:, start:start + dim] - obs_b["critic"][:, start:start + dim]).abs().max().item()
            worst_term[name] = max(worst_term.get(name, 0.0), diff)
            start += dim
    assert worst_reward <= 1e-4
    assert max(v for k, v in worst_term.items() if k != "joint_vel") <= 1e-4, worst_term
    assert worst_term["joint_vel"] <= 1e-3, worst_term


def test_zero_action_standing_falls_at_the_same_step_on_both_backends(backend_pair, standing_reference):
    steps = []
    for kind in ("mujoco", "warp"):
        task = make_task(standing_reference, 1, kind, "cpu", evaluation=True)
        terminated, n = torch.zeros(1, dtype=torch.bool), 0
        while not terminated.any() and n < 100:
            _, _, terminated, _, _ = task.step(torch.zeros(1, 29))
            n += 1
        steps.append(n)
    assert steps[0] == steps[1] and 60 <= steps[0] <= 75, steps


def test_make_vec_gives_a_batched_torch_env_with_same_step_autoreset(vec_env):
    assert vec_env.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    assert vec_env.num_envs == 4 and vec_env.device == torch.device("cpu")
    assert vec_env.num_actions == 29 and vec_env.obs_dims == {"policy": 154, "critic": 286}
    assert vec_env.max_episode_length == 500
    assert vec_env.single_observation_space["policy"].shape == (154,)
    assert vec_env.observation_space["critic"].shape == (4, 286)
    assert vec_env.action_space.shape == (4, 29)
    obs, _ = vec_env.reset(seed=0)
    assert obs["policy"].shape == (4, 154) and obs["policy"].dtype == torch.float32
    obs, reward, terminated, truncated, info = vec_env.step(torch.zeros(4, 29))
    assert reward.shape == (4,) and terminated.dtype == torch.bool and truncated.dtype == torch.bool
    assert set(info) >= {"time_outs", "success", "terminations", "log", "final_obs", "_final_obs"}
    assert all(v.ndim == 0 for v in info["log"].values())
    assert {"reward/body_pos", "termination/anchor_height", "metric/body_pos_error_m"} <= set(info["log"])


def test_an_env_that_falls_is_reset_in_the_same_step_and_its_last_observation_kept(vec_env):
    vec_env.reset(seed=1)
    task = vec_env.unwrapped.task
    qvel = task.backend.qvel.clone()
    qvel[2, 1] = 4.0  # knock env 2 over
    task.backend.write_qvel(qvel)
    for _ in range(40):
        before = vec_env.episode_length_buf.clone()
        obs, _, terminated, truncated, info = vec_env.step(torch.zeros(4, 29))
        done = terminated | truncated
        assert torch.equal(info["_final_obs"], done)
        assert torch.equal(vec_env.episode_length_buf, torch.where(done, 0, before + 1))
        if terminated[2]:
            break
    assert terminated[2]
    assert not torch.equal(info["final_obs"]["critic"][2], obs["critic"][2])
    # the new episode starts on its start frame (plus the reset noise of the training config)
    start_qpos = task.motion.qpos(task.command.start_rows)[2]
    assert (task.backend.qpos[2, :3] - start_qpos[:3]).abs().max() <= 0.05 + 1e-6
    assert torch.equal(task.command.frame[2], task.command.start_frame[2] + 1)


def test_reset_mask_resets_only_the_chosen_envs(vec_env):
    vec_env.reset(seed=0)
    for _ in range(3):
        vec_env.step(torch.zeros(4, 29))
    vec_env.reset(options={"reset_mask": np.array([True, False, True, False])})
    assert vec_env.episode_length_buf.tolist() == [0, 3, 0, 3]


def test_state_tensors_are_zero_copy_views_of_the_warp_arrays(vec_env):
    backend = vec_env.unwrapped.task.backend
    data = backend.warp_data
    assert backend.qpos.data_ptr() == data.qpos.ptr
    assert backend.body_pos_w.data_ptr() == data.xpos.ptr
    qpos = data.qpos.numpy()
    qpos[1, 0] = 123.0
    data.qpos.assign(qpos)
    assert backend.qpos[1, 0].item() == 123.0


def test_randomised_friction_and_com_are_per_world(vec_env):
    backend = vec_env.unwrapped.task.backend
    friction = wp.to_torch(backend.warp_model.geom_friction)
    foot = backend.model.geom("left_foot1_collision").id
    ground = backend.model.geom("ground/ground").id
    assert friction.shape[0] == 4 and len(set(friction[:, foot, 0].tolist())) == 4
    assert torch.equal(friction[:, foot, 0], friction[:, ground, 0])  # one draw shared by feet and ground
    assert friction[:, foot, 0].min() >= 0.3 and friction[:, foot, 0].max() <= 1.2
    ipos = wp.to_torch(backend.warp_model.body_ipos)[:, backend.model.body("torso_link").id]
    offset = (ipos - torch.as_tensor(backend.model.body_ipos[backend.model.body("torso_link").id], dtype=torch.float32))
    assert torch.all(offset.abs() <= torch.tensor([0.025, 0.05, 0.05]) + 1e-6) and offset.abs().max() > 0


def test_graph_captured_and_eager_physics_are_identical(standing_reference):
    model = build_sim_model(TrackEnvCfg().sim.contact_bodies)
    bodies = TrackEnvCfg().sim.contact_bodies
    captured = WarpBackend(model, 2, "cpu", contact_bodies=bodies, graph_capture=True)
    eager = WarpBackend(model, 2, "cpu", contact_bodies=bodies, graph_capture=False)
    ctrl = torch.as_tensor(robot.DEFAULT_JOINT_POS, dtype=torch.float32).repeat(2, 1)
    ctrl[1, 15] += 0.5
    for _ in range(10):
        captured.step(ctrl)
        eager.step(ctrl)
    assert torch.equal(captured.qpos, eager.qpos) and torch.equal(captured.qvel, eager.qvel)
    assert torch.equal(captured.body_pos_w, eager.body_pos_w)
    assert torch.equal(captured.contact_force_n, eager.contact_force_n)
    feet = [bodies.index("left_ankle_roll_link"), bodies.index("right_ankle_roll_link")]
    # standing: the feet carry the robot's weight (~33 kg), nothing else touches
    weight = float(model.body_subtreemass[model.body("pelvis").id]) * 9.81
    assert captured.contact_force_n[:, feet].sum(-1).min() > 0.5 * weight
    others = [i for i in range(len(bodies)) if i not in feet]
    assert captured.contact_force_n[:, others].max() == 0.0


def test_joint_torques_are_the_last_substeps_pd_forces_clamped_to_the_effort_limits():
    """Both backends report, after a step, the torques of the step's last physics substep:
    kp·(q* − q) − kd·q̇ at the state that substep started from, clamped to ±effort (checked
    against MuJoCo run by hand from the same state). Targets up to 3 rad off the default pose drive
    some joints past their effort limit."""
    model = build_sim_model(TrackEnvCfg().sim.contact_bodies)
    bodies = TrackEnvCfg().sim.contact_bodies
    cpu = MuJoCoBackend(model, 2, contact_bodies=bodies)
    warp_backend = WarpBackend(model, 2, "cpu", contact_bodies=bodies)
    gen = torch.Generator().manual_seed(1)
    ctrl = (torch.as_tensor(robot.DEFAULT_JOINT_POS, dtype=torch.float32)
            + 3.0 * (2 * torch.rand(2, 29, generator=gen) - 1))
    for backend in (cpu, warp_backend):
        backend.step(ctrl)
    by_hand = np.zeros((2, 29))
    for w in range(2):
        d = mujoco.MjData(model)
        mujoco.mj_resetDataKeyframe(model, d, 0)
        d.ctrl[:] = ctrl[w].double().numpy()
        for _ in range(cpu.decimation - 1):
            mujoco.mj_step(model, d)
        q, qd = d.qpos[7:], d.qvel[6:]
        by_hand[w] = np.clip(robot.KP * (d.ctrl - q) - robot.KD * qd, -robot.EFFORT_LIMIT, robot.EFFORT_LIMIT)
    np.testing.assert_allclose(cpu.joint_torque_nm.numpy(), by_hand, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(warp_backend.joint_torque_nm.numpy(), by_hand, rtol=1e-3, atol=2e-2)
    saturated = np.isclose(np.abs(by_hand), robot.EFFORT_LIMIT)
    assert saturated.any() and not saturated.all()
    assert np.all(np.abs(warp_backend.joint_torque_nm.numpy()) <= robot.EFFORT_LIMIT + 1e-3)


def test_warp_reset_recomputes_body_poses_for_the_new_state(backend_pair):
    _, warp_task = backend_pair
    warp_task.reset(seed=3)
    frames = warp_task.command.start_rows
    ids = warp_task.backend.body_ids(robot.TRACKED_BODIES)
    assert torch.allclose(warp_task.backend.qpos, warp_task.motion.qpos(frames), atol=1e-6)
    assert torch.allclose(warp_task.backend.body_pos_w[:, ids], warp_task.motion.body_pos_w[frames], atol=1e-3)
    assert warp_task.backend.contact_force_n.abs().max() == 0.0


def test_a_missing_device_fails_with_a_message_listing_the_available_ones(standing_reference):
    with pytest.raises(RuntimeError, match=r"warp device 'cuda:99' is not available.*available: \[.*'cpu'"):
        gymnasium.make_vec("OTR-G1-Track-v0", num_envs=2, vectorization_mode="vector_entry_point", device="cuda:99",
                           reference=standing_reference)
    with pytest.raises(ValueError, match="mujoco backend runs on the CPU only"):
        make_task(standing_reference, 2, "mujoco", "cuda")


_START_A_BACKEND = """
import torch
from envs.backends import build_sim_model
from envs.backends.warp_backend import WarpBackend
from envs.config import TrackEnvCfg
from otr_gym import robot

bodies = TrackEnvCfg().sim.contact_bodies
backend = WarpBackend(build_sim_model(bodies), 2, "cpu", contact_bodies=bodies)
backend.step(torch.as_tensor(robot.DEFAULT_JOINT_POS, dtype=torch.float32).repeat(2, 1))
"""


@pytest.mark.slow
def test_starting_the_warp_backend_prints_no_module_lines_unless_asked():
    """Fresh processes (Warp prints a module's line at its first load in a process, compiled or
    cached): none by default, Warp's own lines with OTR_WARP_VERBOSE=1. 35 s on 2 cores with a warm
    kernel cache, 2 min with a cold one."""
    import os
    import subprocess
    import sys

    from conftest import REPO_ROOT

    def start(env: dict) -> str:
        run = subprocess.run([sys.executable, "-c", _START_A_BACKEND], capture_output=True, text=True, env=env,
                             cwd=REPO_ROOT, timeout=900)
        assert run.returncode == 0, run.stderr[-2000:]
        return run.stdout + run.stderr

    quiet = start({k: v for k, v in os.environ.items() if k != "OTR_WARP_VERBOSE"})
    assert "Module " not in quiet, quiet[:2000]
    verbose = start({**os.environ, "OTR_WARP_VERBOSE": "1"})
    assert verbose.count("Module ") >= 10  # the lines the default removes
