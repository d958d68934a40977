"""PPO configuration: the YAML carries docs/environment.md §7, and rsl-rl-lib 5.x accepts the dict as is."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from rsl_rl.algorithms import PPO
from rsl_rl.modules import EmpiricalNormalization
from tensordict import TensorDict

from agents.config import DEFAULT_CONFIG, AlgorithmCfg, TrainCfg, load_train_config


def test_yaml_defaults_equal_the_dataclass_defaults():
    assert DEFAULT_CONFIG.is_file()
    assert load_train_config() == TrainCfg()


def test_defaults_are_rl_spec_section_7():
    cfg = load_train_config()
    a = cfg.algorithm
    assert (cfg.num_envs, cfg.num_steps_per_env, cfg.max_iterations) == (4096, 24, 30000)
    assert (a.num_learning_epochs, a.num_mini_batches, a.clip_param, a.value_loss_coef) == (5, 4, 0.2, 1.0)
    assert a.use_clipped_value_loss and a.schedule == "adaptive"
    assert (a.entropy_coef, a.gamma, a.lam, a.learning_rate, a.desired_kl, a.max_grad_norm) == \
        (0.005, 0.99, 0.95, 1e-3, 0.01, 1.0)
    for net in (cfg.actor, cfg.critic):
        assert net.hidden_dims == (512, 256, 128) and net.activation == "elu" and net.obs_normalization
    assert cfg.actor.init_std == 1.0


def test_rsl_rl_builds_ppo_with_the_spec_numbers_from_the_dict():
    cfg = TrainCfg(num_envs=8)
    train_cfg = cfg.to_rsl_rl()
    train_cfg["multi_gpu"] = None
    obs = TensorDict({"policy": torch.zeros(8, 154), "critic": torch.zeros(8, 286)}, batch_size=[8])
    env = SimpleNamespace(num_envs=8, num_actions=29)
    alg = PPO.construct_algorithm(obs, env, train_cfg, "cpu")
    assert (alg.clip_param, alg.entropy_coef, alg.gamma, alg.lam, alg.desired_kl) == (0.2, 0.005, 0.99, 0.95, 0.01)
    assert alg.num_learning_epochs == 5 and alg.num_mini_batches == 4 and alg.use_clipped_value_loss
    assert alg.actor.obs_dim == 154 and alg.critic.obs_dim == 286
    assert isinstance(alg.actor.obs_normalizer, EmpiricalNormalization)
    assert isinstance(alg.critic.obs_normalizer, EmpiricalNormalization)
    linear_widths = [m.out_features for m in alg.actor.mlp if isinstance(m, torch.nn.Linear)]
    assert linear_widths == [512, 256, 128, 29]
    assert torch.allclose(alg.actor.distribution.std_param, torch.ones(29))
    assert alg.storage.num_transitions_per_env == 24


def test_faster_numerics_reach_rsl_rl_and_unsupported_compile_modes_are_refused():
    cfg = TrainCfg(num_envs=8, torch_compile_mode="default", algorithm=AlgorithmCfg(use_mixed_precision=True))
    train_cfg = cfg.to_rsl_rl()
    assert train_cfg["torch_compile_mode"] == "default"
    train_cfg["multi_gpu"] = None
    obs = TensorDict({"policy": torch.zeros(8, 154), "critic": torch.zeros(8, 286)}, batch_size=[8])
    alg = PPO.construct_algorithm(obs, SimpleNamespace(num_envs=8, num_actions=29), train_cfg, "cpu")
    assert alg.use_mixed_precision
    assert alg.actor is not alg._raw_actor and alg.critic is not alg._raw_critic  # wrapped by torch.compile
    assert TrainCfg().to_rsl_rl()["torch_compile_mode"] is None and not TrainCfg().algorithm.use_mixed_precision
    with pytest.raises(ValueError, match="'reduce-overhead'"):
        TrainCfg(torch_compile_mode="reduce-overhead")  # CUDA graphs: rsl-rl refuses them too


def test_unknown_config_key_is_named():
    with pytest.raises(ValueError, match="algoritm"):
        load_train_config(overrides={"algoritm": {"gamma": 0.9}})
    with pytest.raises(ValueError, match="gama"):
        load_train_config(overrides={"algorithm": {"gama": 0.9}})


def test_missing_config_file_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.yaml"):
        load_train_config(tmp_path / "nope.yaml")


def test_non_positive_sizes_are_refused():
    with pytest.raises(ValueError, match="num_envs"):
        TrainCfg(num_envs=0)
