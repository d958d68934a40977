"""``python -m agents.failure_bins RUN_OR_CHECKPOINT [--reference REF] [--png P] [--json J]``:
where in each clip a training run's episodes fail.

The adaptive start sampler (``envs.mdp.commands``) keeps, per (clip, time bin), an exponential
moving average of the terminations that happened there: failures per step, counted over all
envs (α = 0.001 by default: about the last 1000 steps, the last ~40 iterations of 24 steps). Every checkpoint
stores it (``agents.runner``), so the failure map of a run needs no simulation: this reads it
and lays it out over the clips of the run's library, each bin with the frames and seconds it
covers (the sampler's own bin rule, ``envs.mdp.commands.local_bins``).

This is the training distribution's view: episodes start where the sampler sends them, with the
training's randomisation and reset noise. ``otr evaluate`` measures the deterministic episode
from frame 0; ``agents.episode_trace`` follows one such episode frame by frame.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from agents import runs
from agents.config import train_config_from_dict
from agents.library import clip_labels, load_library
from envs.config import load_env_config
from envs.mdp.commands import local_bins, start_bin_counts
from otr_gym.reference import InvalidReferenceError


@dataclass(frozen=True)
class ClipFailures:
    """One clip's failure-rate bins."""

    clip: str  # label (agents.library.clip_labels)
    frames: int  # clip length at the policy rate
    fps: float  # policy rate (frames per second)
    first_frame: np.ndarray  # (n,) int: first frame of each bin
    last_frame: np.ndarray  # (n,) int: last frame of each bin (inclusive)
    rate: np.ndarray  # (n,) failures per step over all envs (the sampler's moving average)

    @property
    def total(self) -> float:
        return float(self.rate.sum())

    def worst(self, k: int = 3) -> list[int]:
        """Indices of the (up to) ``k`` bins with the highest rate, those with failures only."""
        order = np.argsort(-self.rate, kind="stable")[:k]
        return [int(b) for b in order if self.rate[b] > 0]

    def describe_bin(self, b: int) -> str:
        share = self.rate[b] / self.total if self.total > 0 else 0.0
        return (f"{self.first_frame[b] / self.fps:.1f}–{(self.last_frame[b] + 1) / self.fps:.1f} s "
                f"(frames {self.first_frame[b]}–{self.last_frame[b]}) {100 * share:.0f} %")


def clip_failures(failure_rate: np.ndarray, clip_frames: list[int], labels: list[str], fps: float,
                  bin_duration_s: float) -> list[ClipFailures]:
    """Split the sampler's flat ``failure_rate`` (B,) into the clips of ``clip_frames`` (their
    lengths at ``fps``), with the bins the sampler used. Raises ``ValueError`` when the bin count
    does not match (the checkpoint came from another library or another bin duration)."""
    rate = np.asarray(failure_rate, dtype=np.float64).ravel()
    lengths = torch.as_tensor(clip_frames, dtype=torch.long)
    counts = start_bin_counts(lengths, fps * bin_duration_s)
    if int(counts.sum()) != rate.size:
        raise ValueError(f"the checkpoint's sampler has {rate.size} bins; clips of {clip_frames} frames at "
                         f"{fps:g} fps with {bin_duration_s:g} s bins have {int(counts.sum())}: not this run's library")
    out, offset = [], 0
    for label, length, n in zip(labels, lengths.tolist(), counts.tolist(), strict=True):
        local = local_bins(torch.arange(length), torch.tensor(n), torch.tensor(length)).numpy()  # non-decreasing
        first = np.searchsorted(local, np.arange(n), side="left")
        last = np.searchsorted(local, np.arange(n), side="right") - 1
        out.append(ClipFailures(label, int(length), float(fps), first, last, rate[offset:offset + n].copy()))
        offset += n
    return out


def load_clip_failures(run_or_checkpoint: str | Path, reference=None) -> tuple[runs.Checkpoint, list[ClipFailures]]:
    """The failure map of a checkpoint (a run folder: its latest), over the clips of
    ``reference`` (default: the run's own library, loaded as training loaded it)."""
    ckpt = runs.resolve_checkpoint(run_or_checkpoint)
    state = (runs.load_checkpoint(ckpt).get("infos") or {}).get("training_state", {}).get("env", {})
    if "failure_rate" not in state:
        raise runs.RunError(f"{ckpt.path}: the checkpoint holds no sampler statistics (training_state.env.failure_rate)")
    config = runs.run_config(ckpt.run_dir)
    train_cfg = train_config_from_dict(config["train"])
    command = load_env_config(train_cfg.task, overrides=train_cfg.env or None).command
    library = load_library(reference or config["reference"], train_cfg.task, train_cfg.env)
    sources = [r.source for r in library.references]
    clips = clip_failures(state["failure_rate"].numpy(), [r.num_frames for r in library.references],
                          clip_labels(sources), command.fps, command.bin_duration_s)
    return ckpt, clips


def format_failures(clips: list[ClipFailures], worst: int = 3) -> str:
    """A table: each clip's failures per step, its share of the run's, and its worst bins."""
    total = sum(c.total for c in clips)
    width = max(len(c.clip) for c in clips)
    lines = [f"{'clip':<{width}}  failures/step  share  worst bins (time, frames, share of the clip's failures)"]
    for c in clips:
        share = c.total / total if total > 0 else 0.0
        where = "; ".join(c.describe_bin(b) for b in c.worst(worst)) or "–"
        lines.append(f"{c.clip:<{width}}  {c.total:13.4f}  {100 * share:4.0f} %  {where}")
    return "\n".join(lines)


def plot_failures(clips: list[ClipFailures], out_png: str | Path, title: str = "") -> Path:
    """One panel per clip: failures per step (all envs) over the clip's time bins, one scale for all."""
    from agents.plots import panel_grid
    from otr_gym.io import save_figure

    fig, axes = panel_grid(len(clips))
    top = max((float(c.rate.max()) for c in clips), default=0.0) or 1.0
    for ax, c in zip(axes, clips):
        start = c.first_frame / c.fps
        width = (c.last_frame + 1 - c.first_frame) / c.fps
        ax.bar(start, c.rate, width=width, align="edge", color="tab:red", edgecolor="white", lw=0.5)
        ax.set_xlim(0, c.frames / c.fps)
        ax.set_ylim(0, 1.05 * top)  # one scale: panels compare across clips
        ax.set_title(f"{c.clip} ({c.total:.3g} / step)", fontsize=9)
        ax.set_xlabel("clip time (s)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("failures per step (all envs)")
    fig.suptitle(title or "where episodes fail (the sampler's moving average)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, out_png)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m agents.failure_bins", description=__doc__.split("\n\n")[1])
    parser.add_argument("run", help="run folder (its latest checkpoint) or model_<it>.pt")
    parser.add_argument("--reference", nargs="+", help="the library's clips (default: the run's reference)")
    parser.add_argument("--worst", type=int, default=3, help="bins listed per clip (default: 3)")
    parser.add_argument("--png", help="write the per-clip bars here")
    parser.add_argument("--json", help="write the bins here")
    args = parser.parse_args(argv)
    try:
        ckpt, clips = load_clip_failures(args.run, args.reference)
    except (runs.RunError, InvalidReferenceError, ValueError, OSError) as exc:
        print(f"agents.failure_bins: {exc}", file=sys.stderr)
        return 2
    print(f"{ckpt.path} (iteration {ckpt.iteration}): failures per step (all envs) by clip time")
    print(format_failures(clips, args.worst))
    if args.png:
        print(f"wrote {plot_failures(clips, args.png, f'{ckpt.run_dir.name}, iteration {ckpt.iteration}')}")
    if args.json:
        data = {"checkpoint": str(ckpt.path), "iteration": ckpt.iteration,
                "clips": [{"clip": c.clip, "frames": c.frames, "fps": c.fps, "failures_per_step": c.total,
                           "bins": [{"first_frame": int(f), "last_frame": int(l), "failures_per_step": float(r)}
                                    for f, l, r in zip(c.first_frame, c.last_frame, c.rate)]} for c in clips]}
        print(f"wrote {runs.write_json(args.json, data)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
