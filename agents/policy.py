"""Rebuild a trained actor from a checkpoint without building the environment.

The run folder records the training config and the environment's observation dimensions, so
the rsl-rl actor (normaliser + MLP + Gaussian head) can be reconstructed and its weights
loaded on any device; evaluation, export and play all start here.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from rsl_rl.models import MLPModel
from tensordict import TensorDict

from agents import runs
from agents.config import TrainCfg, train_config_from_dict


@dataclass
class TrainedPolicy:
    actor: MLPModel  # eval mode; actor(obs TensorDict) -> deterministic mean action
    train_cfg: TrainCfg
    env_spec: dict
    run_config: dict
    checkpoint: runs.Checkpoint

    @property
    def obs_group(self) -> str:
        """The single observation group the actor reads (e.g. "policy")."""
        groups = self.train_cfg.obs_groups["actor"]
        if len(groups) != 1:
            raise ValueError(f"actor reads {groups}; export and play need exactly one observation group")
        return groups[0]

    @torch.no_grad()
    def act(self, obs: TensorDict) -> torch.Tensor:
        return self.actor(obs)


def build_actor(train_cfg: TrainCfg, obs_dims: dict[str, int], num_actions: int) -> MLPModel:
    """An untrained actor with the config's architecture for observation groups of ``obs_dims``."""
    dummy = TensorDict({k: torch.zeros(1, d) for k, d in obs_dims.items()}, batch_size=[1])
    actor_cfg = dict(train_cfg.to_rsl_rl()["actor"])
    actor_cfg.pop("class_name")
    groups = {k: list(v) for k, v in train_cfg.obs_groups.items()}
    missing = [g for g in groups["actor"] if g not in obs_dims]
    if missing:
        raise ValueError(f"actor observation groups {missing} are not among the environment's {sorted(obs_dims)}")
    return MLPModel(dummy, groups, "actor", num_actions, **actor_cfg)


def load_policy(run_or_checkpoint, device: str | torch.device = "cpu") -> TrainedPolicy:
    """The actor of a checkpoint file, or of the latest checkpoint of a run folder."""
    ckpt = run_or_checkpoint if isinstance(run_or_checkpoint, runs.Checkpoint) else \
        runs.resolve_checkpoint(run_or_checkpoint)
    run_config = runs.run_config(ckpt.run_dir)
    env_spec = runs.read_env_spec(ckpt.run_dir)
    if "train" not in run_config:
        raise runs.RunError(f"{ckpt.run_dir / runs.CONFIG_FILE}: no 'train' section")
    train_cfg = train_config_from_dict(run_config["train"])
    actor = build_actor(train_cfg, env_spec["observation_dims"], env_spec["num_actions"])
    state = runs.load_checkpoint(ckpt)
    try:
        actor.load_state_dict(state["actor_state_dict"])
    except (RuntimeError, KeyError, TypeError) as exc:
        raise runs.RunError(f"{ckpt.path}: not a readable checkpoint of this run ({exc})") from exc
    actor.to(device).eval()
    return TrainedPolicy(actor, train_cfg, env_spec, run_config, ckpt)

