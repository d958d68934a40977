"""The rsl-rl VecEnv adapter over the Gymnasium vector envs OTR-G1-Track-v0 and OTR-G1-BoxTrack-v0.

The env already speaks torch on the device; the adapter only renames:

- observations: the env's {"policy": (N, 154), "critic": (N, 286)} dict -> a TensorDict;
- ``step`` -> (obs, reward, dones = terminated | truncated, extras) with ``extras["time_outs"]``
  = truncated (rsl-rl bootstraps those) and ``extras["log"]`` = the env's per-term reward
  means, termination rates and tracking errors, plus metrics for TensorBoard:
  ``metric/mpjpe_mm`` (root-relative MPJPE of the step, envs.mdp.metrics) and, once per rollout,
  ``metric/success_rate`` = successes / (successes + terminations) over the rollout, with the
  env's ``info["success"]``: for the tracking task an episode that ended by time-out or clip
  end, for the box task a clip run to its last frame (the episode may go on with a new start);
  ``metric/non_finite_resets`` (worlds reset because their physics diverged, in the rollout);
  per clip ``clip/<label>/{success_rate, mpjpe_mm, episode_length_s, start_probability}``
  (``agents.metrics.ClipRolloutStats``). In a torch.distributed run these rollout figures are
  summed over the ranks, so rank 0's TensorBoard shows the whole batch;
- ``episode_length_buf`` reads and writes the env's own buffer (rsl-rl randomises it);
- ``state_dict``/``load_state_dict``: the adaptive start sampler's failure statistics.

It also polls the stop conditions (Ctrl-C, time budget) at the start of each rollout, the only
point where a checkpoint is exactly resumable (see agents.stopping); in a distributed run the
ranks agree (any rank's reason stops all of them at the same iteration, since each iteration's
gradient all-reduce needs every rank).
"""

from __future__ import annotations

import sys

import gymnasium
import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict

import otr_gym  # noqa: F401  (registers the environments)
from agents.library import clip_labels
from agents.metrics import M_TO_MM, ClipRolloutStats, reduce_sum
from agents.stopping import StopConditions, TrainingStopped
from envs.config import TrackEnvCfg, load_env_config
from envs.mdp.metrics import mpjpe_root_relative
from envs.task import NON_FINITE, masked_mean


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
        # rollout sums: episodes ended, succeeded, worlds reset for non-finite physics
        self._counts = torch.zeros(3, dtype=torch.float64, device=self.device)
        self.clip_labels = clip_labels(list(self.vec.motion.names))
        self.clip_stats = ClipRolloutStats(self.clip_labels, self.vec.step_dt, self.device)
        self._synced_failure_rate = self.vec.command.failure_rate.clone()
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
            reason = self._stop_reason()
            if reason is not None:
                raise TrainingStopped(reason, completed=self._steps // self.num_steps_per_env)
        obs, reward, terminated, truncated, info = self.env.step(actions)
        self._steps += 1
        state = self.vec.tracking_state  # after physics, before any reset: the frame just tracked
        log = dict(info["log"])
        bad = info["terminations"][NON_FINITE]
        valid = ~bad
        mpjpe = mpjpe_root_relative(state)
        log["metric/mpjpe_mm"] = masked_mean(mpjpe, valid) * M_TO_MM
        dones = terminated | truncated
        success = info["success"]
        self._counts += torch.stack([(success | terminated).sum(), success.sum(), bad.sum()]).double()
        segment = info["segment"]
        self.clip_stats.add_step(segment["clip"], mpjpe, valid, segment["ended"], terminated, segment["frames"])
        if self._steps % self.num_steps_per_env == 0:
            log.update(self._rollout_log())
        self._obs = self._wrap(obs)
        extras = {"time_outs": truncated, "log": log}
        return self._obs, reward, dones, extras

    def _rollout_log(self) -> dict:
        """The once-per-rollout figures (summed over ranks) and a fresh start of their sums."""
        ended, succeeded, non_finite = reduce_sum(self._counts.clone()).tolist()
        self._counts.zero_()
        self._merge_sampler_statistics()
        log = {"metric/non_finite_resets": non_finite}
        if ended > 0:
            log["metric/success_rate"] = succeeded / ended
        log.update(self.clip_stats.flush(self.vec.command.clip_probabilities()))
        return log

    def _merge_sampler_statistics(self) -> None:
        """Distributed run: make every rank's adaptive sampler the one a single process with all
        ranks' envs would have. The failure EMA is linear, so after K steps from a common f₀,
        f = Σ_r f_r − (R − 1)(1 − α)^K f₀ exactly (each rank decayed f₀ once and added its own
        failures). Called at the end of every rollout (K = steps per env)."""
        if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
            return
        command = self.vec.command
        rate = command.failure_rate
        world = torch.distributed.get_world_size()
        decay = (1.0 - command.cfg.adaptive_alpha) ** self.num_steps_per_env
        total = reduce_sum(rate.clone())
        rate.copy_(total - (world - 1) * decay * self._synced_failure_rate)
        self._synced_failure_rate = rate.clone()

    def _stop_reason(self) -> str | None:
        reason = self.stop.reason()
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            flag = torch.tensor([0.0 if reason is None else 1.0], device=self.device)
            torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX)
            if flag.item() > 0 and reason is None:
                reason = "stopped by another rank"
        return reason

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
        self._synced_failure_rate = rate.clone()

    # ------------------------------------------------------------ helpers
    def _wrap(self, obs: dict) -> TensorDict:
        return TensorDict(dict(obs), batch_size=[self.num_envs], device=self.device)


def make_vec_env(task: str, reference, num_envs: int, device: str, env: TrackEnvCfg | dict | None = None,
                 evaluation: bool = False, seed: int = 0):
    """The Gymnasium vector env ``task`` on MuJoCo-Warp (``device`` "cuda[:K]" or "cpu") of
    ``reference`` (a reference source or ``envs.clips.PreparedClips``). ``env``: the task's
    config, loaded already (``otr train`` reads it once), or overrides laid over the task's YAML
    (configs/env/track.yaml or box.yaml)."""
    cfg = env if isinstance(env, TrackEnvCfg) else load_env_config(task, overrides=env or None)
    return gymnasium.make_vec(task, num_envs=num_envs, vectorization_mode="vector_entry_point", device=device,
                              reference=reference, cfg=cfg, evaluation=evaluation, seed=seed)
