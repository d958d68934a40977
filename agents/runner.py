"""rsl-rl's OnPolicyRunner with crash-safe, exactly resumable checkpoints.

PPO and the learning loop are rsl-rl-lib's, untouched. Only checkpoint I/O is extended:

- ``save`` writes atomically (rsl-rl calls ``torch.save`` on the final name, so a kill during
  a save leaves a truncated ``model_<it>.pt``) and stores, besides rsl-rl's actor/critic
  (normalisers included)/optimizer/iteration, the logger's totals, the torch RNG states and the
  environment's adaptive-sampling failure statistics;
- ``load`` restores all of it and continues at the *next* iteration: rsl-rl saves
  ``iter = it`` after iteration ``it`` and restarts its loop at ``iter``, which would repeat
  that iteration's number in the TensorBoard curves.
"""

from __future__ import annotations

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

    def save(self, path: str, infos: dict | None = None) -> None:
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
            torch.set_rng_state(state["torch_rng"].cpu())
            if "cuda_rng" in state and torch.cuda.is_available():
                torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda_rng"]])
            self.env.load_state_dict(state["env"])
        if load_cfg is None or load_cfg.get("iteration"):
            self.current_learning_iteration += 1
        return infos
