"""rsl-rl's OnPolicyRunner with crash-safe, exactly resumable checkpoints.

PPO and the learning loop are rsl-rl-lib's, untouched. Only the multi-GPU set-up and
checkpoint I/O are extended:

- ``_configure_multi_gpu`` takes the process group ``agents.distributed`` already created
  (rsl-rl would create an NCCL group itself and insist on ``cuda:LOCAL_RANK``; here the CPU
  with gloo works too, which is how the distributed path is tested) and fills in exactly the
  fields rsl-rl's PPO and logger read (``cfg["multi_gpu"]``, ranks, world size);
- ``save`` writes on rank 0 only, atomically (rsl-rl calls ``torch.save`` on the final name, so a
  kill during a save leaves a truncated ``model_<it>.pt``) and stores, besides rsl-rl's actor/critic
  (normalisers included)/optimizer/iteration, the logger's totals, the torch RNG states and the
  environment's adaptive-sampling failure statistics;
- ``load`` restores all of it and continues at the *next* iteration: rsl-rl saves
  ``iter = it`` after iteration ``it`` and restarts its loop at ``iter``, which would repeat
  that iteration's number in the TensorBoard curves. In a distributed run every rank loads the
  same checkpoint but keeps its own torch RNG (seeded ``seed + rank``): restoring rank 0's
  would give every rank the same action noise.
"""

from __future__ import annotations

import os

import torch
from rsl_rl.runners import OnPolicyRunner

from agents import runs


class TrackingRunner(OnPolicyRunner):
    """OnPolicyRunner over ``agents.vecenv.RslRlVecEnv`` (for its sampler state)."""

    def training_state(self) -> dict:
        state = {
            "logger": {"tot_timesteps": self.logger.tot_timesteps, "tot_time": self.logger.tot_time},
            "torch_rng": torch.get_rng_state(),
            "env": self.env.state_dict(),
        }
        if torch.cuda.is_available():
            state["cuda_rng"] = torch.cuda.get_rng_state_all()
        return state

    def _configure_multi_gpu(self) -> None:
        if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
            super()._configure_multi_gpu()
            return
        self.gpu_world_size = torch.distributed.get_world_size()
        self.gpu_global_rank = torch.distributed.get_rank()
        self.gpu_local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        self.is_distributed = self.gpu_world_size > 1
        self.cfg["multi_gpu"] = {"global_rank": self.gpu_global_rank, "local_rank": self.gpu_local_rank,
                                 "world_size": self.gpu_world_size} if self.is_distributed else None

    def save(self, path: str, infos: dict | None = None) -> None:
        if self.gpu_global_rank != 0:
            return
        saved = self.alg.save()
        saved["iter"] = self.current_learning_iteration
        saved["infos"] = {**(infos or {}), "training_state": self.training_state()}
        runs.atomic_write(path, lambda f: torch.save(saved, f))
        self.logger.save_model(path, self.current_learning_iteration)

    def load(self, path: str, load_cfg: dict | None = None, strict: bool = True,
             map_location: str | None = None) -> dict:
        infos = super().load(path, load_cfg, strict, map_location) or {}
        state = infos.get("training_state")
        if state is not None:
            self.logger.tot_timesteps = state["logger"]["tot_timesteps"]
            self.logger.tot_time = state["logger"]["tot_time"]
            if not self.is_distributed:
                torch.set_rng_state(state["torch_rng"].cpu())
                if "cuda_rng" in state and torch.cuda.is_available():
                    torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda_rng"]])
            self.env.load_state_dict(state["env"])
        if load_cfg is None or load_cfg.get("iteration"):
            self.current_learning_iteration += 1
        return infos
