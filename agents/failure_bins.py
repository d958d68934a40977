"""``otr failure-map RUN_OR_CHECKPOINT [--reference REF] [--clip-floor B] [--png P] [--json J]``:
where in each clip a training run's episodes fail, and where its starts go.

The adaptive start sampler (``envs.mdp.commands``) keeps, per (clip, time bin), an exponential
moving average of the terminations that happened there: failures per step, counted over all
envs (α = 0.001 by default: about the last 1000 steps, the last ~40 iterations of 24 steps). Every checkpoint
stores it (``agents.runner``), so the failure map of a run needs no simulation: this reads it
and lays it out over the clips of the run's library, each bin with the frames and seconds it
covers (the sampler's own bin rule, ``envs.mdp.commands.local_bins``). Beside each bin's
failures it gives the share of all starts the sampler draws there from them
(``envs.mdp.commands.start_probabilities``, the run's config): a bin that holds most failures
but few starts is one the library does not practise. ``--clip-floor`` recomputes the starts
under another ``command.library_clip_floor``, from the same failures (before the policy, and
so the failures, would respond).

This is the training distribution's view: episodes start where the sampler sends them, with the
training's randomisation and reset noise. ``otr evaluate`` measures the deterministic episode
from frame 0; ``otr trace`` follows one such episode frame by frame.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from agents import runs
from agents.config import train_config_from_dict
from agents.library import clip_labels, load_library
from envs.config import CommandCfg, load_env_config
from envs.mdp.commands import bin_clips, local_bins, start_bin_counts, start_probabilities
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
    start: np.ndarray  # (n,) share of all the library's starts that each bin draws from these rates

    @property
    def start_share(self) -> float:
        return float(self.start.sum())

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
                f"(frames {self.first_frame[b]}–{self.last_frame[b]}) {100 * share:.0f} %, "
                f"{100 * self.start[b]:.1f} % of starts")


def clip_failures(failure_rate: np.ndarray, clip_frames: list[int], labels: list[str],
                  command: CommandCfg) -> list[ClipFailures]:
    """Split the sampler's flat ``failure_rate`` (B,) into the clips of ``clip_frames`` (their
    lengths at ``command.fps``), with the bins the sampler used, and the share of the starts each
    bin draws under ``command``'s rule (``envs.mdp.commands.start_probabilities``). Raises
    ``ValueError`` when the bin count does not match (the checkpoint came from another library
    or another bin duration)."""
    rate = np.asarray(failure_rate, dtype=np.float64).ravel()
    lengths = torch.as_tensor(clip_frames, dtype=torch.long)
    fps, bin_duration_s = command.fps, command.bin_duration_s
    counts = start_bin_counts(lengths, fps * bin_duration_s)
    if int(counts.sum()) != rate.size:
        raise ValueError(f"the checkpoint's sampler has {rate.size} bins; clips of {clip_frames} frames at "
                         f"{fps:g} fps with {bin_duration_s:g} s bins have {int(counts.sum())}: not this run's library")
    start = start_probabilities(torch.from_numpy(rate), counts, bin_clips(counts), command).numpy()
    out, offset = [], 0
    for label, length, n in zip(labels, lengths.tolist(), counts.tolist(), strict=True):
        local = local_bins(torch.arange(length), torch.tensor(n), torch.tensor(length)).numpy()  # non-decreasing
        first = np.searchsorted(local, np.arange(n), side="left")
        last = np.searchsorted(local, np.arange(n), side="right") - 1
        out.append(ClipFailures(label, int(length), float(fps), first, last, rate[offset:offset + n].copy(),
                                start[offset:offset + n].copy()))
        offset += n
    return out


def load_clip_failures(run_or_checkpoint: str | Path, reference=None,
                       clip_floor: float | None = None) -> tuple[runs.Checkpoint, list[ClipFailures], CommandCfg]:
    """The failure map of a checkpoint (a run folder: its latest), over the clips of
    ``reference`` (default: the run's own library, loaded as training loaded it), with the
    starts each bin draws from those failures under the run's command config, or with
    ``clip_floor`` in place of its ``library_clip_floor`` (what another floor would do with the
    same failures, before the policy reacts). Returns the command config used."""
    ckpt = runs.resolve_checkpoint(run_or_checkpoint)
    state = (runs.load_checkpoint(ckpt).get("infos") or {}).get("training_state", {}).get("env", {})
    if "failure_rate" not in state:
        raise runs.RunError(f"{ckpt.path}: the checkpoint holds no sampler statistics "
                            "(training_state.env.failure_rate)")
    config = runs.run_config(ckpt.run_dir)
    train_cfg = train_config_from_dict(config["train"])
    command = load_env_config(train_cfg.task, overrides=train_cfg.env or None).command
    if clip_floor is not None:
        if not 0.0 <= clip_floor <= 1.0:
            raise ValueError(f"--clip-floor must lie in [0, 1], got {clip_floor}")
        command = replace(command, library_clip_floor=clip_floor)
    library = load_library(reference or config["reference"], train_cfg.task, train_cfg.env)
    sources = [r.source for r in library.references]
    clips = clip_failures(state["failure_rate"].numpy(), [r.num_frames for r in library.references],
                          clip_labels(sources), command)
    return ckpt, clips, command


def format_failures(clips: list[ClipFailures], worst: int = 3) -> str:
    """A table: each clip's failures per step, its share of the run's and of the starts, and its
    worst bins (their share of the clip's failures and of all starts)."""
    total = sum(c.total for c in clips)
    width = max(len(c.clip) for c in clips)
    lines = [f"{'clip':<{width}}  failures/step  share   starts  "
             "worst bins (time, frames, share of the clip's failures, of all starts)"]
    for c in clips:
        share = c.total / total if total > 0 else 0.0
        where = "; ".join(c.describe_bin(b) for b in c.worst(worst)) or "–"
        lines.append(f"{c.clip:<{width}}  {c.total:13.4f}  {100 * share:4.0f} %  {100 * c.start_share:5.1f} %  {where}")
    return "\n".join(lines)


def plot_failures(clips: list[ClipFailures], out_png: str | Path, title: str = "") -> Path:
    """One panel per clip: failures per step (all envs) over the clip's time bins (bars) and
    the share of all starts each bin draws (line, right axis), one scale each for all panels."""
    from agents.plots import panel_grid
    from otr_gym.io import save_figure

    fig, axes = panel_grid(len(clips))
    top = max((float(c.rate.max()) for c in clips), default=0.0) or 1.0
    top_start = max((float(c.start.max()) for c in clips), default=0.0) or 1.0
    for ax, c in zip(axes, clips):
        start = c.first_frame / c.fps
        width = (c.last_frame + 1 - c.first_frame) / c.fps
        ax.bar(start, c.rate, width=width, align="edge", color="tab:red", edgecolor="white", lw=0.5)
        ax.set_xlim(0, c.frames / c.fps)
        ax.set_ylim(0, 1.05 * top)  # one scale: panels compare across clips
        ax.set_title(f"{c.clip} ({c.total:.3g} / step, {100 * c.start_share:.1f} % of starts)", fontsize=9)
        ax.set_xlabel("clip time (s)")
        ax.grid(alpha=0.3)
        twin = ax.twinx()
        edges = np.append(start, c.frames / c.fps)
        twin.stairs(100 * c.start, edges, color="black", lw=1.2)
        twin.set_ylim(0, 105 * top_start)
        twin.tick_params(labelsize=7)
    axes[0].set_ylabel("failures per step (all envs), bars")
    legend = "bars: failures per step (the sampler's moving average); line: % of all starts (right axis)"
    fig.suptitle(f"{title}\n{legend}" if title else legend, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, out_png)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """``otr failure-map``'s arguments."""
    parser.add_argument("run", help="run folder (its latest checkpoint) or model_<it>.pt")
    parser.add_argument("--reference", nargs="+", help="the library's clips (default: the run's reference)")
    parser.add_argument("--worst", type=int, default=3, help="number of bins listed per clip (default: %(default)s)")
    parser.add_argument("--clip-floor", type=float,
                        help="the starts under this command.library_clip_floor (β in [0, 1]: the fraction of clip "
                        "draws spread evenly over the clips) from the same failures (default: the run's)")
    parser.add_argument("--png", help="write the per-clip bars here (PNG)")
    parser.add_argument("--json", help="write the bins here (JSON)")


def main(args: argparse.Namespace) -> int:
    """Print the failure map of ``args.run``; a run, checkpoint or clip that cannot be used: a
    message naming it, exit code 2."""
    try:
        ckpt, clips, command = load_clip_failures(args.run, args.reference, args.clip_floor)
    except (runs.RunError, InvalidReferenceError, ValueError, OSError) as exc:
        print(f"otr failure-map: {exc}", file=sys.stderr)
        return 2
    floor = (f"library_clip_floor {command.library_clip_floor:g}"
             + (" (--clip-floor)" if args.clip_floor is not None else ""))
    print(f"{ckpt.path} (iteration {ckpt.iteration}): failures per step (all envs) by clip time; starts under {floor}")
    print(format_failures(clips, args.worst))
    if args.png:
        print(f"wrote {plot_failures(clips, args.png, f'{ckpt.run_dir.name}, iteration {ckpt.iteration}, {floor}')}")
    if args.json:
        data = {"checkpoint": str(ckpt.path), "iteration": ckpt.iteration,
                "library_clip_floor": command.library_clip_floor,
                "clips": [{"clip": c.clip, "frames": c.frames, "fps": c.fps, "failures_per_step": c.total,
                           "start_share": c.start_share,
                           "bins": [{"first_frame": int(f), "last_frame": int(last), "failures_per_step": float(r),
                                     "start_share": float(p)}
                                    for f, last, r, p in zip(c.first_frame, c.last_frame, c.rate, c.start)]}
                          for c in clips]}
        print(f"wrote {runs.write_json(args.json, data)}")
    return 0
