"""Typed PPO training configuration (docs/environment.md §7) and its rsl-rl-lib 5.x dictionary.

``configs/agents/ppo_track.yaml`` lists the same values as the dataclass defaults below; it is
read by ``load_train_config`` and the resolved configuration is written into every run folder,
so a run can be resumed, evaluated and exported without the original YAML.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from otr_gym.config import from_dict, load_yaml_mapping, merge

DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "agents" / "ppo_track.yaml"


@dataclass
class ActorCfg:
    hidden_dims: tuple[int, ...] = (512, 256, 128)  # §7
    activation: str = "elu"  # §7
    obs_normalization: bool = True  # §7: empirical observation normalisation
    init_std: float = 1.0  # §7: initial action std (scalar parameterisation)


@dataclass
class CriticCfg:
    hidden_dims: tuple[int, ...] = (512, 256, 128)  # §7
    activation: str = "elu"  # §7
    obs_normalization: bool = True  # §7


@dataclass
class AlgorithmCfg:
    """Keyword arguments of ``rsl_rl.algorithms.PPO`` (all §7)."""

    num_learning_epochs: int = 5
    num_mini_batches: int = 4
    clip_param: float = 0.2
    use_clipped_value_loss: bool = True
    value_loss_coef: float = 1.0
    entropy_coef: float = 0.005
    gamma: float = 0.99
    lam: float = 0.95
    learning_rate: float = 1.0e-3
    #: rsl-rl's adaptive rule is exactly §7's: ÷1.5 above 2·KL*, ×1.5 below KL*/2, lr in [1e-5, 1e-2].
    schedule: str = "adaptive"
    desired_kl: float = 0.01
    max_grad_norm: float = 1.0
    optimizer: str = "adam"
    #: rsl-rl's bfloat16 autocast of the update's forward passes and losses (ours; off: every
    #: run in README learned in float32; ``benchmarks/ppo_update_speed.py`` measures the update).
    use_mixed_precision: bool = False


#: ``TrainCfg.torch_compile_mode`` values rsl-rl-lib 5.x accepts.
COMPILE_MODES = (None, "default", "max-autotune-no-cudagraphs")


def _obs_groups() -> dict[str, list[str]]:
    # §3: the actor reads the 154-dim "policy" group, the critic the privileged 286-dim "critic" group
    return {"actor": ["policy"], "critic": ["critic"]}


@dataclass
class TrainCfg:
    task: str = "OTR-G1-Track-v0"
    num_envs: int = 4096  # §7
    num_steps_per_env: int = 24  # §7
    max_iterations: int = 30000  # §7
    save_interval: int = 500  # §7 (MJ)
    seed: int = 42
    #: §7 HS: start with random episode lengths so that time-outs do not all fall on one step.
    init_at_random_ep_len: bool = True
    obs_groups: dict[str, list[str]] = field(default_factory=_obs_groups)
    actor: ActorCfg = field(default_factory=ActorCfg)
    critic: CriticCfg = field(default_factory=CriticCfg)
    algorithm: AlgorithmCfg = field(default_factory=AlgorithmCfg)
    #: Float32 matrix products on TF32 tensor cores (CUDA, ``torch.backends.cuda.matmul``): the
    #: networks' layers in the rollout and the update. The MDP's maths is element-wise, so the
    #: environment is unaffected. Ours; off: every run in README learned in full float32.
    tf32_matmul: bool = False
    #: ``torch.compile`` mode of actor and critic (rsl-rl's ``torch_compile_mode``): None (eager,
    #: every run in README), "default" or "max-autotune-no-cudagraphs" (rsl-rl refuses the CUDA-graph
    #: modes: its algorithms call the models several times per graph).
    torch_compile_mode: str | None = None
    #: Overrides of the environment config (configs/env/track.yaml layout).
    env: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("num_envs", "num_steps_per_env", "max_iterations", "save_interval"):
            if getattr(self, name) < 1:
                raise ValueError(f"training config: {name} must be >= 1, got {getattr(self, name)}")
        if self.torch_compile_mode not in COMPILE_MODES:
            raise ValueError(f"training config: torch_compile_mode {self.torch_compile_mode!r} is not one of "
                             f"{', '.join(map(repr, COMPILE_MODES))}")

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (YAML-safe: tuples become lists)."""
        return _plain(dataclasses.asdict(self))

    def to_rsl_rl(self) -> dict[str, Any]:
        """The ``train_cfg`` dictionary of ``rsl_rl.runners.OnPolicyRunner`` (rsl-rl-lib 5.x)."""
        actor = dataclasses.asdict(self.actor)
        init_std = actor.pop("init_std")
        return {
            "num_steps_per_env": self.num_steps_per_env,
            "save_interval": self.save_interval,
            "obs_groups": {k: list(v) for k, v in self.obs_groups.items()},
            "check_for_nan": True,
            "logger": "tensorboard",
            "algorithm": {"class_name": "PPO", **dataclasses.asdict(self.algorithm)},
            "actor": {"class_name": "MLPModel", **_plain(actor),
                      "distribution_cfg": {"class_name": "GaussianDistribution", "init_std": init_std,
                                           "std_type": "scalar"}},
            "critic": {"class_name": "MLPModel", **_plain(dataclasses.asdict(self.critic))},
            "torch_compile_mode": self.torch_compile_mode,
        }


def load_train_config(path: str | Path | None = None, overrides: dict | None = None) -> TrainCfg:
    """Read a YAML file (default ``configs/agents/ppo_track.yaml``, dataclass defaults if that
    file is absent) and apply ``overrides`` (same nested layout) on top; unknown keys raise."""
    data = merge(load_yaml_mapping(path, DEFAULT_CONFIG, "training"), overrides)
    return train_config_from_dict(data)


def train_config_from_dict(data: dict) -> TrainCfg:
    """A TrainCfg from a nested mapping (e.g. the ``train`` section of a run's config.yaml)."""
    return from_dict(TrainCfg, data, "train")


def _plain(value):
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value
