"""A world whose physics turns non-finite is reset alone: the termination ``non_finite``, reward
0, finite observations, the other worlds untouched (bit-for-bit the same as a run without the
fault), on MuJoCo-Warp (warp's CPU device) and on CPU MuJoCo (which resets such a world to
qpos0 by itself and only warns; that must not pass unnoticed)."""

from __future__ import annotations

import math
from dataclasses import replace

import gymnasium
import pytest
import torch

import otr_gym  # noqa: F401  (registers the environments)
from agents.vecenv import RslRlVecEnv
from envs.task import NON_FINITE
from envs.tracking import make_task

pytest.importorskip("warp").config.quiet = True

NUM_ENVS = 4
BAD = 1


def _poison(task, kind: str) -> None:
    """NaN into world BAD's root height, the way a diverging solver leaves it."""
    if kind == "warp":
        task.backend.qpos[BAD, 2] = math.nan  # a zero-copy view of the warp state
    else:
        task.backend._datas[BAD].qpos[2] = math.nan  # the MuJoCo data itself


@pytest.mark.parametrize("kind", ["warp", "mujoco"])
def test_a_nan_in_one_world_resets_only_that_world(kind, standing_reference):
    clean = make_task(standing_reference, NUM_ENVS, kind, "cpu", evaluation=True)
    hurt = make_task(standing_reference, NUM_ENVS, kind, "cpu", evaluation=True)
    clean.reset(seed=0)
    hurt.reset(seed=0)
    gen = torch.Generator().manual_seed(0)
    others = [w for w in range(NUM_ENVS) if w != BAD]
    for step in range(8):
        actions = 0.3 * torch.randn(NUM_ENVS, 29, generator=gen)
        if step == 3:
            _poison(hurt, kind)
        _, rew_c, term_c, _, _ = clean.step(actions)
        obs_h, rew_h, term_h, _, info = hurt.step(actions)
        # the other worlds never notice
        assert torch.equal(hurt.backend.qpos[others], clean.backend.qpos[others]), step
        assert torch.equal(rew_h[others], rew_c[others]) and torch.equal(term_h[others], term_c[others])
        assert all(torch.isfinite(o).all() for o in obs_h.values()) and torch.isfinite(rew_h).all()
        if step == 3:
            assert info["terminations"][NON_FINITE].tolist() == [w == BAD for w in range(NUM_ENVS)]
            assert bool(term_h[BAD]) and float(rew_h[BAD]) == 0.0
            assert int(info["log"]["metric/non_finite_worlds"]) == 1
            assert torch.isfinite(info["log"]["metric/body_pos_error_m"])
            # reset onto its start frame (frame 0 in evaluation), episode counters cleared
            start = hurt.motion.qpos(hurt.command.start_rows)[BAD]
            torch.testing.assert_close(hurt.backend.qpos[BAD], start, atol=1e-6, rtol=0)
            assert int(hurt.episode_length_buf[BAD]) == 0 and int(hurt.command.frame[BAD]) == 1
        else:
            assert not info["terminations"][NON_FINITE].any(), step
    assert torch.isfinite(hurt.backend.qpos).all()


def test_an_observation_that_comes_out_non_finite_is_zeroed_and_its_world_reset_next_step(standing_reference):
    task = make_task(standing_reference, NUM_ENVS, "warp", "cpu", evaluation=True)
    task.reset(seed=0)
    zeros = torch.zeros(NUM_ENVS, 29)
    task.step(zeros)
    broken = task.state.action.clone()
    broken[BAD, 0] = math.nan  # as a policy with a broken output would leave its last action (±inf is clipped)
    obs = task._finite_observations(replace(task.state, action=broken))
    assert all(torch.isfinite(o).all() for o in obs.values())
    last_action = task.obs_dims["policy"] - 29  # the policy group's last term
    assert float(obs["policy"][BAD, last_action]) == 0.0
    _, reward, terminated, _, info = task.step(zeros)
    assert info["terminations"][NON_FINITE].tolist() == [w == BAD for w in range(NUM_ENVS)]
    assert bool(terminated[BAD]) and float(reward[BAD]) == 0.0


def test_training_adapter_counts_the_reset_and_keeps_the_batch_finite(standing_reference):
    env = gymnasium.make_vec("OTR-G1-Track-v0", num_envs=NUM_ENVS, vectorization_mode="vector_entry_point",
                             device="cpu", reference=standing_reference, seed=0)
    vec = RslRlVecEnv(env, num_steps_per_env=2, seed=0)
    actions = torch.zeros(NUM_ENVS, 29)
    vec.step(actions)
    _poison(vec.vec.task, "warp")
    obs, reward, dones, extras = vec.step(actions)  # the rollout's last step: its figures are logged
    assert torch.isfinite(reward).all() and all(torch.isfinite(v).all() for v in obs.values())
    assert bool(dones[BAD])
    log = extras["log"]
    assert log["metric/non_finite_resets"] == 1.0
    assert math.isfinite(float(log["metric/mpjpe_mm"])) and float(log["metric/mpjpe_mm"]) < 500.0
    env.close()
