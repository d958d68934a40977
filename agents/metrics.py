"""Evaluation bookkeeping: per-env episode sums, then per-clip and overall summaries.

The per-frame metric is the env's ``envs.mdp.metrics.mpjpe_root_relative`` (paper Sec. IV-E)
(and for the box task its object errors, ``ObjectEpisodeMetrics``):
MPJPE = mean_b ‖(p_b − p_root) − (p̂_b − p̂_root)‖ over the 14 tracked bodies, root = pelvis,
world frame without rotation alignment (heading drift is charged, as in the paper).
Beside it, as a diagnostic only, ``mpjpe_heading_aligned_mm``: the same with the reference turned
by the anchors' yaw difference (``mpjpe_root_relative_heading_aligned``), i.e. posture without
heading drift; the gap between the two is what heading drift costs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from envs.mdp.metrics import object_orientation_error_rad, object_position_error_m

M_TO_MM = 1000.0


@dataclass
class EpisodeAccumulator:
    """Per-env sums over one evaluation episode: MPJPE over the frames an env was alive,
    whether its episode ended by a tracking termination, and which terminations fired on that
    step (``ended_by``: termination name -> (N,) bool; several may fire at once)."""

    num_envs: int
    device: torch.device | str = "cpu"
    mpjpe_sum_m: torch.Tensor = field(init=False)
    aligned_sum_m: torch.Tensor = field(init=False)
    frames: torch.Tensor = field(init=False)
    terminated: torch.Tensor = field(init=False)
    finished: torch.Tensor = field(init=False)
    ended_by: dict[str, torch.Tensor] = field(init=False)

    def __post_init__(self) -> None:
        self.mpjpe_sum_m = torch.zeros(self.num_envs, dtype=torch.float64, device=self.device)
        self.aligned_sum_m = torch.zeros(self.num_envs, dtype=torch.float64, device=self.device)
        self.frames = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        self.terminated = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        self.finished = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        self.ended_by = {}

    def add_frame(self, mpjpe_m: torch.Tensor, valid: torch.Tensor | None = None,
                  heading_aligned_m: torch.Tensor | None = None) -> None:
        """MPJPE (N,) of the current frame (and its heading-aligned diagnostic, if given); envs
        whose episode already ended, and frames of ``valid`` False (a world whose physics
        diverged), are ignored."""
        alive = ~self.finished if valid is None else ~self.finished & valid
        self.mpjpe_sum_m += torch.where(alive, mpjpe_m.to(torch.float64), 0.0)
        if heading_aligned_m is not None:
            self.aligned_sum_m += torch.where(alive, heading_aligned_m.to(torch.float64), 0.0)
        self.frames += alive.long()

    def end_step(self, terminated: torch.Tensor, truncated: torch.Tensor,
                 fired: dict[str, torch.Tensor] | None = None) -> None:
        """Record the episode ends of this step (only the first end of each env counts);
        ``fired``: the env's terminations of this step by name (``info["terminations"]``)."""
        alive = ~self.finished
        for name, flag in (fired or {}).items():
            ended = self.ended_by.setdefault(name, torch.zeros_like(self.finished))
            ended |= alive & flag.bool()
        self.terminated |= alive & terminated.bool()
        self.finished |= alive & (terminated.bool() | truncated.bool())

    @property
    def all_finished(self) -> bool:
        return bool(self.finished.all())

    def per_env(self) -> dict[str, np.ndarray]:
        """success (clip completed without termination), mean MPJPE (mm) and its heading-aligned
        diagnostic (mm; 0 if never given), frames evaluated, and per termination name whether it
        ended the env's episode (``ended_by``)."""
        frames = self.frames.cpu().numpy()
        mpjpe = self.mpjpe_sum_m.cpu().numpy() / np.maximum(frames, 1) * M_TO_MM
        aligned = self.aligned_sum_m.cpu().numpy() / np.maximum(frames, 1) * M_TO_MM
        success = (self.finished & ~self.terminated).cpu().numpy()
        ended_by = {name: flag.cpu().numpy() for name, flag in self.ended_by.items()}
        return {"success": success, "mpjpe_mm": mpjpe, "mpjpe_heading_aligned_mm": aligned, "frames": frames,
                "ended_by": ended_by}


def summarize(per_env: dict[str, np.ndarray], clip_ids: np.ndarray, clip_names: list[str],
              objects: ObjectEpisodeMetrics | None = None, clip_frames: list[int] | None = None) -> dict:
    """Aggregate per-env results per clip and overall (with ``objects``, their metrics too;
    with ``clip_frames``, each clip's length in frames as ``clip_frames``: an episode that
    tracks the whole clip lives ``clip_frames`` − 1 frames, its first target being frame 1).

    Overall MPJPE is frame-weighted (every evaluated frame counts once), so a policy that falls
    early is not rewarded with a small average over a few frames *and* it shows in success.
    """
    def weighted(key: str, sel) -> dict:  # frame-weighted mean of a per-env figure, if present
        if key not in per_env:
            return {}
        frames = per_env["frames"][sel]
        return {key: float((per_env[key][sel] * frames).sum() / max(frames.sum(), 1))}

    def ended_by(sel) -> dict:  # how many envs each termination ended (those that fired at all)
        counts = {name: int(flag[sel].sum()) for name, flag in per_env.get("ended_by", {}).items()}
        return {"ended_by": {name: n for name, n in counts.items() if n}}

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
            **weighted("mpjpe_heading_aligned_mm", sel),
            "frames": int(frames.sum()),
            **ended_by(sel),
            **(objects.summary(sel) if objects is not None else {}),
            **({"clip_frames": int(clip_frames[c])} if clip_frames is not None else {}),
        })
    frames = per_env["frames"]
    return {
        "success_rate": float(per_env["success"].mean()),
        "mpjpe_mm": float((per_env["mpjpe_mm"] * frames).sum() / max(frames.sum(), 1)),
        **weighted("mpjpe_heading_aligned_mm", slice(None)),
        "frames": int(frames.sum()),
        "envs": int(frames.size),
        **ended_by(slice(None)),
        **(objects.summary() if objects is not None else {}),
        "clips": clips,
    }


class ClipRolloutStats:
    """Per-clip training statistics over one rollout, kept on the device (no host sync per step).

    A *segment* is the stretch of one clip an env tracks from a (re)start until a termination,
    the clip's end or a time-out (the env's ``info["segment"]``). Per clip c:

    - ``success_rate``: of the segments on c that ended in the rollout, the fraction that did
      not end by a termination (clip end or time-out);
    - ``mpjpe_mm``: root-relative MPJPE over every env-step spent on c (finite worlds only);
    - ``episode_length_s``: mean length of those segments (s);
    - ``start_probability``: the adaptive sampler's total start probability of c's bins.

    ``flush`` returns them as TensorBoard tags ``clip/<label>/<name>`` and clears the sums; in a
    distributed run the sums are all-reduced first, so every rank logs the global values.
    """

    _FIELDS = ("steps", "mpjpe_sum_m", "ended", "failed", "segment_frames")

    def __init__(self, labels: list[str], step_dt: float, device: torch.device | str):
        self.labels = list(labels)
        self.step_dt = float(step_dt)
        self.sums = torch.zeros(len(self._FIELDS), len(labels), dtype=torch.float64, device=device)

    def add_step(self, clip: torch.Tensor, mpjpe_m: torch.Tensor, valid: torch.Tensor, ended: torch.Tensor,
                 failed: torch.Tensor, segment_frames: torch.Tensor) -> None:
        """One env step: (N,) clip of each env, its MPJPE (m), finite flag, segment end, failure
        (a termination) and the segment's frames so far."""
        ended = ended.bool()
        values = torch.stack([valid.double(), torch.where(valid, mpjpe_m.double(), 0.0), ended.double(),
                              (ended & failed.bool()).double(), torch.where(ended, segment_frames.double(), 0.0)])
        self.sums.index_add_(1, clip.long(), values)

    def flush(self, start_probability: torch.Tensor | None = None) -> dict[str, float]:
        """Tags of the rollout (clips without data are left out) and reset. ``start_probability``
        (C,) is logged as given (the sampler is identical on every rank)."""
        sums = reduce_sum(self.sums.clone())
        steps, mpjpe, ended, failed, frames = sums.cpu().numpy()
        out: dict[str, float] = {}
        for c, label in enumerate(self.labels):
            tag = f"clip/{label}/"
            if steps[c] > 0:
                out[tag + "mpjpe_mm"] = float(mpjpe[c] / steps[c] * M_TO_MM)
            if ended[c] > 0:
                out[tag + "success_rate"] = float(1.0 - failed[c] / ended[c])
                out[tag + "episode_length_s"] = float(frames[c] / ended[c] * self.step_dt)
        if start_probability is not None:
            for label, p in zip(self.labels, start_probability.tolist(), strict=True):
                out[f"clip/{label}/start_probability"] = float(p)
        self.sums.zero_()
        return out


def reduce_sum(x: torch.Tensor) -> torch.Tensor:
    """``x`` summed over the ranks of a torch.distributed run (unchanged in a single process)."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.all_reduce(x, op=torch.distributed.ReduceOp.SUM)
    return x


CONTACT_FORCE_N = 1.0  # an object "touches" a support when their contact force exceeds this


class ObjectEpisodeMetrics:
    """Per-frame object errors of an evaluation (OTR-G1-BoxTrack-v0), kept for every env and
    step so that means and percentiles can be taken over any set of envs:

    - object position error (cm; mean over the moving objects) and orientation error (deg),
      every frame an env is alive;
    - per support (ground, table): frames inside an object–support window, and of those the
      frames where an object touches it (contact force > 1 N);
    - at the last frame of an episode that succeeded: the position error, and whether the
      object touches each support whose window is open there (e.g. the box on the table).
    """

    def __init__(self, num_envs: int, support_names: tuple[str, ...], device: torch.device | str = "cpu"):
        self.support_names = tuple(support_names)
        self._pos, self._ori, self._alive, self._inside, self._touch = [], [], [], [], []
        self.final_pos_cm = torch.full((num_envs,), float("nan"), dtype=torch.float64, device=device)
        self.final_touch = torch.full((num_envs, len(support_names)), float("nan"), dtype=torch.float64, device=device)

    def add_frame(self, s, alive: torch.Tensor) -> None:
        o = s.objects
        self._pos.append(object_position_error_m(s).mean(-1) * 100.0)
        self._ori.append(torch.rad2deg(object_orientation_error_rad(s)).mean(-1))
        self._alive.append(alive.clone())
        inside = (o.support_gate > 0).any(dim=1)  # (N, S): any object's window with that support
        touch = ((o.support_force_n > CONTACT_FORCE_N) & (o.support_gate > 0)).any(dim=1)
        self._inside.append(inside)
        self._touch.append(touch)

    def end_step(self, s, succeeded_now: torch.Tensor) -> None:
        """Record the last frame of envs whose episode succeeded in this step."""
        o = s.objects
        rows = succeeded_now.bool()
        self.final_pos_cm = torch.where(rows, object_position_error_m(s).mean(-1).double() * 100.0, self.final_pos_cm)
        window = (o.support_gate > 0).any(dim=1)
        touch = (o.support_force_n > CONTACT_FORCE_N).any(dim=1).double()
        value = torch.where(window, touch, torch.full_like(touch, float("nan")))
        self.final_touch = torch.where(rows[:, None], value, self.final_touch)

    def summary(self, envs: np.ndarray | None = None) -> dict:
        """Object metrics over the envs selected by ``envs`` ((N,) bool; all when None)."""
        alive = torch.stack(self._alive).cpu().numpy()  # (steps, N)
        sel = np.ones(alive.shape[1], bool) if envs is None else np.asarray(envs, bool)
        mask = alive[:, sel]
        pos = torch.stack(self._pos).cpu().numpy()[:, sel][mask]
        ori = torch.stack(self._ori).cpu().numpy()[:, sel][mask]
        inside = torch.stack(self._inside).cpu().numpy()[:, sel] & mask[..., None]
        touch = torch.stack(self._touch).cpu().numpy()[:, sel] & mask[..., None]
        final = self.final_pos_cm.cpu().numpy()[sel]
        final_touch = self.final_touch.cpu().numpy()[sel]
        out = {
            "object_pos_error_cm": float(pos.mean()) if pos.size else None,
            "object_pos_error_p95_cm": float(np.percentile(pos, 95)) if pos.size else None,
            "object_ori_error_deg": float(ori.mean()) if ori.size else None,
            "object_final_pos_error_cm": float(np.nanmean(final)) if np.isfinite(final).any() else None,
            "support_contact": {},
        }
        for k, name in enumerate(self.support_names):
            frames = int(inside[..., k].sum())
            ends = final_touch[:, k][np.isfinite(final_touch[:, k])]
            out["support_contact"][name] = {
                "window_frames": frames,
                "contact_rate": float(touch[..., k].sum() / frames) if frames else None,
                "contact_at_clip_end": float(ends.mean()) if ends.size else None,
            }
        return out
