"""Evaluation bookkeeping: per-env episode sums, then per-clip and overall summaries.

The per-frame metric is the env's ``envs.mdp.metrics.mpjpe_root_relative`` (paper Sec. IV-E):
MPJPE = mean_b ‖(p_b − p_root) − (p̂_b − p̂_root)‖ over the 14 tracked bodies, root = pelvis,
world frame without rotation alignment (heading drift is charged, as in the paper).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

M_TO_MM = 1000.0


@dataclass
class EpisodeAccumulator:
    """Per-env sums over one evaluation episode: MPJPE over the frames an env was alive,
    and whether its episode ended by a tracking termination."""

    num_envs: int
    device: torch.device | str = "cpu"
    mpjpe_sum_m: torch.Tensor = field(init=False)
    frames: torch.Tensor = field(init=False)
    terminated: torch.Tensor = field(init=False)
    finished: torch.Tensor = field(init=False)

    def __post_init__(self) -> None:
        self.mpjpe_sum_m = torch.zeros(self.num_envs, dtype=torch.float64, device=self.device)
        self.frames = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        self.terminated = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        self.finished = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)

    def add_frame(self, mpjpe_m: torch.Tensor) -> None:
        """MPJPE (N,) of the current frame; envs whose episode already ended are ignored."""
        alive = ~self.finished
        self.mpjpe_sum_m += torch.where(alive, mpjpe_m.to(torch.float64), 0.0)
        self.frames += alive.long()

    def end_step(self, terminated: torch.Tensor, truncated: torch.Tensor) -> None:
        """Record the episode ends of this step (only the first end of each env counts)."""
        alive = ~self.finished
        self.terminated |= alive & terminated.bool()
        self.finished |= alive & (terminated.bool() | truncated.bool())

    @property
    def all_finished(self) -> bool:
        return bool(self.finished.all())

    def per_env(self) -> dict[str, np.ndarray]:
        """success (clip completed without termination), mean MPJPE (mm), frames evaluated."""
        frames = self.frames.cpu().numpy()
        mpjpe = self.mpjpe_sum_m.cpu().numpy() / np.maximum(frames, 1) * M_TO_MM
        success = (self.finished & ~self.terminated).cpu().numpy()
        return {"success": success, "mpjpe_mm": mpjpe, "frames": frames}


def summarize(per_env: dict[str, np.ndarray], clip_ids: np.ndarray, clip_names: list[str]) -> dict:
    """Aggregate per-env results per clip and overall.

    Overall MPJPE is frame-weighted (every evaluated frame counts once), so a policy that falls
    early is not rewarded with a small average over a few frames *and* it shows in success.
    """
    clips = []
    for c, name in enumerate(clip_names):
        sel = clip_ids == c
        if not sel.any():
            continue
        frames = per_env["frames"][sel]
        clips.append({
            "clip": name,
            "envs": int(sel.sum()),
            "success_rate": float(per_env["success"][sel].mean()),
            "mpjpe_mm": float((per_env["mpjpe_mm"][sel] * frames).sum() / max(frames.sum(), 1)),
            "frames": int(frames.sum()),
        })
    frames = per_env["frames"]
    return {
        "success_rate": float(per_env["success"].mean()),
        "mpjpe_mm": float((per_env["mpjpe_mm"] * frames).sum() / max(frames.sum(), 1)),
        "frames": int(frames.sum()),
        "envs": int(frames.size),
        "clips": clips,
    }
