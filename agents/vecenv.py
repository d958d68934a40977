"""The rsl-rl VecEnv adapter over the Gymnasium vector envs OTR-G1-Track-v0 and OTR-G1-BoxTrack-v0.

The env already speaks torch on the device; the adapter only renames:

- observations: the env's {"policy": (N, 154), "critic": (N, 286)} dict -> a TensorDict;
- ``step`` -> (obs, reward, dones = terminated | truncated, extras) with ``extras["time_outs"]``
  = truncated (rsl-rl bootstraps those) and ``extras["log"]`` = the env's per-term reward
  means, termination rates and tracking errors, plus two metrics for TensorBoard:
  ``metric/mpjpe_mm`` (root-relative MPJPE of the step, envs.mdp.metrics) and, once per rollout,
  ``metric/success_rate`` = successes / (successes + terminations) over the rollout, with the
  env's ``info["success"]``: for the tracking task an episode that ended by time-out or clip
  end, for the box task a clip run to its last frame (the episode may go on with a new start);
- ``episode_length_buf`` reads and writes the env's own buffer (rsl-rl randomises it);
- ``state_dict``/``load_state_dict``: the adaptive start sampler's failure statistics.

It also polls the stop conditions (Ctrl-C, time budget) at the start of each rollout, the only
point where a checkpoint is exactly resumable (see agents.stopping).
"""

from __future__ import annotations

import sys

import gymnasium
import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict

import otr_gym  # noqa: F401  (registers the environments)
from agents.metrics import M_TO_MM
from agents.stopping import StopConditions, TrainingStopped
from envs.config import load_env_config
from envs.mdp.metrics import mpjpe_root_relative


class RslRlVecEnv(VecEnv):
    def __init__(self, env, num_steps_per_env: int, seed: int | None = None, stop: StopConditions | None = None):
        self.env = env
        self.vec = env.unwrapped  # envs.tracking.TrackVecEnv: its trainer interface
        self.num_envs = self.vec.num_envs
        self.num_actions = self.vec.num_actions
        self.max_episode_length = self.vec.max_episode_length
        self.device = self.vec.device
        self.cfg = self.vec.task.cfg
        self.num_steps_per_env = int(num_steps_per_env)
        self.stop = stop
        self._steps = 0
        self._ended = torch.zeros((), device=self.device)
        self._succeeded = torch.zeros((), device=self.device)
        obs, _ = env.reset(seed=seed)
        self._obs = self._wrap(obs)

    # ------------------------------------------------------------ rsl-rl VecEnv
    @property
    def episode_length_buf(self) -> torch.Tensor:
        return self.vec.episode_length_buf

    @episode_length_buf.setter
    def episode_length_buf(self, value: torch.Tensor) -> None:
        self.vec.episode_length_buf = value

    def get_observations(self) -> TensorDict:
        return self._obs

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        if self._steps % self.num_steps_per_env == 0 and self.stop is not None:
            reason = self.stop.reason()
            if reason is not None:
                raise TrainingStopped(reason, completed=self._steps // self.num_steps_per_env)
        obs, reward, terminated, truncated, info = self.env.step(actions)
        self._steps += 1
        state = self.vec.tracking_state  # after physics, before any reset: the frame just tracked
        log = dict(info["log"])
        log["metric/mpjpe_mm"] = mpjpe_root_relative(state).mean() * M_TO_MM
        dones = terminated | truncated
        success = info["success"]
        self._ended += (success | terminated).sum()
        self._succeeded += success.sum()
        if self._steps % self.num_steps_per_env == 0:
            ended = self._ended.item()
            if ended > 0:
                log["metric/success_rate"] = self._succeeded / ended
            self._ended.zero_()
            self._succeeded.zero_()
        self._obs = self._wrap(obs)
        extras = {"time_outs": truncated, "log": log}
        return self._obs, reward, dones, extras

    # ------------------------------------------------------------ checkpointed env state
    def state_dict(self) -> dict:
        return {"failure_rate": self.vec.command.failure_rate.detach().cpu().clone()}

    def load_state_dict(self, state: dict) -> None:
        """Restore the sampler's failure statistics when the clip set has the same bins."""
        rate = self.vec.command.failure_rate
        saved = state.get("failure_rate")
        if saved is None:
            return
        if saved.shape != rate.shape:
            print(f"note: the checkpoint's sampler has {saved.numel()} bins, this reference {rate.numel()}: "
                  "start sampling statistics begin afresh", file=sys.stderr)
            return
        rate.copy_(saved.to(rate.device))

    # ------------------------------------------------------------ helpers
    def _wrap(self, obs: dict) -> TensorDict:
        return TensorDict(dict(obs), batch_size=[self.num_envs], device=self.device)


def make_vec_env(task: str, reference, num_envs: int, device: str, env_overrides: dict | None = None,
                 evaluation: bool = False, seed: int = 0):
    """The Gymnasium vector env ``task`` on MuJoCo-Warp (``device`` "cuda[:K]" or "cpu"),
    with ``env_overrides`` applied on top of the task's YAML (configs/env/track.yaml or box.yaml)."""
    cfg = load_env_config(task, overrides=env_overrides or None)
    return gymnasium.make_vec(task, num_envs=num_envs, vectorization_mode="vector_entry_point", device=device,
                              reference=reference, cfg=cfg, evaluation=evaluation, seed=seed)
