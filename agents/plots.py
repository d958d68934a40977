"""PNG figures of a run: training curves (from its TensorBoard events) and evaluation results.

Written atomically; matplotlib's Agg backend, so no display is needed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from agents import runs  # noqa: E402
from otr_gym.io import save_figure  # noqa: E402

#: TensorBoard tag -> panel title; rsl-rl's logger writes the first three, the adapter the rest.
TRAINING_PANELS = {
    "Train/mean_reward": "mean episode reward",
    "Train/mean_episode_length": "mean episode length (steps)",
    "Perf/total_fps": "env steps / s",
    "metric/mpjpe_mm": "MPJPE, root-relative (mm)",
    "metric/success_rate": "success rate",
    "metric/object_pos_error_m": "object position error (m)",
    "metric/object_ori_error_rad": "object orientation error (rad)",
    "termination/object_pos": "object termination rate (per step)",
}
#: One more panel overlays every per-term reward (weight · value · dt, mean over envs).
REWARD_PREFIX = "reward/"


def read_scalars(run_dir: str | Path) -> dict[str, tuple[list[int], list[float]]]:
    """tag -> (iterations, values) over all event files of the run. A resumed run re-logs the
    iterations after its last checkpoint; the later value of an iteration wins."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    files = sorted(Path(run_dir).glob("events.out.tfevents.*"), key=lambda p: p.stat().st_mtime)
    if not files:
        raise runs.RunError(f"{run_dir}: no TensorBoard event files")
    merged: dict[str, dict[int, float]] = {}
    for path in files:
        acc = EventAccumulator(str(path), size_guidance={"scalars": 0})
        acc.Reload()
        for tag in acc.Tags()["scalars"]:
            merged.setdefault(tag, {}).update({e.step: e.value for e in acc.Scalars(tag)})
    return {tag: (sorted(v), [v[k] for k in sorted(v)]) for tag, v in merged.items()}


def learning_minutes(scalars: dict[str, tuple[list[int], list[float]]]) -> tuple[list[int], list[float]]:
    """(iterations, cumulative learning time in minutes at the end of each): rsl-rl's
    per-iteration collection plus update time, what ``--max-minutes`` budgets (env build and
    kernel compilation are outside it)."""
    import numpy as np

    if "Perf/collection_time" not in scalars or "Perf/learning_time" not in scalars:
        raise runs.RunError("no Perf/collection_time and Perf/learning_time curves in the run's TensorBoard events")
    its, collection = scalars["Perf/collection_time"]
    learning = dict(zip(*scalars["Perf/learning_time"], strict=True))
    seconds = np.asarray(collection) + np.asarray([learning.get(it, 0.0) for it in its])
    return list(its), (np.cumsum(seconds) / 60.0).tolist()


#: The x axes ``plot_runs`` can draw against.
RUN_AXES = ("minutes", "iteration")


def plot_runs(run_dirs: list[str | Path], out_png: str | Path, labels: list[str] | None = None,
              x: str = "minutes") -> Path:
    """Several runs side by side: one panel per ``TRAINING_PANELS`` curve that any run has, one
    line per run, against learning time (``x="minutes"``), so runs that shared a GPU or ran at
    other speeds compare at equal budgets, or against the PPO iteration (``x="iteration"``),
    which takes the machine's speed out of a comparison of recipes run on different hosts."""
    labels = labels or [Path(r).name for r in run_dirs]
    if len(labels) != len(run_dirs):
        raise ValueError(f"{len(labels)} labels for {len(run_dirs)} runs")
    if x not in RUN_AXES:
        raise ValueError(f"x axis {x!r}: one of {', '.join(RUN_AXES)}")
    curves = []
    for run in run_dirs:
        scalars = read_scalars(run)
        if x == "iteration":
            curves.append((scalars, None))
            continue
        try:
            its, minutes = learning_minutes(scalars)
        except runs.RunError as e:
            raise runs.RunError(f"{run}: {e}") from None
        curves.append((scalars, dict(zip(its, minutes, strict=True))))
    panels = [(tag, title) for tag, title in TRAINING_PANELS.items()
              if tag != "Perf/total_fps" and any(tag in s for s, _ in curves)]
    fig, axes = panel_grid(len(panels))
    for ax, (tag, title) in zip(axes, panels, strict=True):
        for (scalars, minutes), label in zip(curves, labels, strict=True):
            if tag in scalars:
                its, values = scalars[tag]
                xs = its if minutes is None else [minutes.get(it, float("nan")) for it in its]
                ax.plot(xs, values, lw=1.1, label=label)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("learning time (min)" if x == "minutes" else "iteration")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, out_png)


def plot_training(run_dir: str | Path, out_png: str | Path) -> Path:
    scalars = read_scalars(run_dir)
    panels = [(tag, title) for tag, title in TRAINING_PANELS.items() if tag in scalars]
    rewards = sorted(tag for tag in scalars if tag.startswith(REWARD_PREFIX))
    if rewards:
        panels.append((REWARD_PREFIX, "reward terms (weight · value · dt)"))
    fig, axes = panel_grid(len(panels))
    for ax, (tag, title) in zip(axes, panels, strict=True):
        if tag == REWARD_PREFIX:
            for name in rewards:
                ax.plot(*scalars[name], lw=1.0, label=name[len(REWARD_PREFIX):])
            ax.legend(fontsize=6, ncol=2)
        else:
            ax.plot(*scalars[tag], lw=1.2)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
    fig.suptitle(Path(run_dir).name, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, out_png)


#: Per-clip training curves (``agents.metrics.ClipRolloutStats``): tag suffix -> panel title.
CLIP_PANELS = {
    "success_rate": "success rate (segments on the clip)",
    "mpjpe_mm": "MPJPE, root-relative (mm)",
    "episode_length_s": "segment length (s)",
    "start_probability": "start probability (adaptive sampling)",
}


def plot_clip_curves(run_dir: str | Path, out_png: str | Path, smooth: int = 10) -> Path:
    """One panel per ``CLIP_PANELS`` entry, one line per clip (``clip/<label>/…`` tags); lines
    are running means over ``smooth`` iterations (segment statistics of one rollout are noisy)."""
    import numpy as np

    scalars = read_scalars(run_dir)
    labels = sorted({tag.split("/")[1] for tag in scalars if tag.startswith("clip/") and tag.count("/") >= 2})
    if not labels:
        raise runs.RunError(f"{run_dir}: no per-clip curves (clip/<label>/...) in its TensorBoard events")
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), squeeze=False)
    for ax, (name, title) in zip(axes.flat, CLIP_PANELS.items()):
        for label in labels:
            tag = f"clip/{label}/{name}"
            if tag not in scalars:
                continue
            its, values = scalars[tag]
            k = max(1, min(smooth, len(values)))
            mean = np.convolve(values, np.ones(k) / k, mode="valid")
            ax.plot(its[k - 1:], mean, lw=1.1, label=label)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
        if name in ("success_rate", "start_probability"):
            # a fraction: a single clip's start probability is 1 ± float noise, which autoscaling
            # would draw as a band of 1e-7 wiggles
            ax.set_ylim(-0.02, 1.02)
    axes[0, 0].legend(fontsize=7, ncol=2)
    fig.suptitle(f"{Path(run_dir).name}: per clip (running mean over {smooth} iterations)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, out_png)


def tracked_share(clip: dict) -> float:
    """Share of a clip its evaluation episodes tracked (``evaluate`` per-clip result with
    ``clip_frames``): 1 when every episode reached the last frame."""
    return min(1.0, clip["frames"] / (clip["envs"] * max(clip["clip_frames"] - 1, 1)))


def checkpoint_minutes(results: dict) -> list[float] | None:
    """Learning minutes at each evaluated checkpoint (``learning_minutes`` of the run's event
    files), or None when the run folder has no such curves (a checkpoint carried alone)."""
    run_dir = Path(results["checkpoints"][-1]["checkpoint"]).parent
    try:
        its, minutes = learning_minutes(read_scalars(run_dir))
    except (runs.RunError, OSError):
        return None
    at = dict(zip(its, minutes, strict=True))
    found = [at.get(e["iteration"]) for e in results["checkpoints"]]
    return None if None in found else found


def plot_evaluation(results: dict, out_png: str | Path) -> Path:
    """MPJPE and success rate against the checkpoint's learning minutes (the iteration when the
    run's event files are not there); for a library, beside it, the share of each clip its
    episodes tracked, so that the checkpoint from which every clip passes can be read off."""
    evals = results["checkpoints"]
    minutes = checkpoint_minutes(results)
    x = minutes or [e["iteration"] for e in evals]
    xlabel = "learning minutes at the checkpoint" if minutes else "checkpoint iteration"
    clips = [c["clip"] for c in evals[-1]["clips"]]
    library = len(clips) > 1 and all("clip_frames" in c for e in evals for c in e["clips"])
    fig, axes = plt.subplots(1, 2 if library else 1, figsize=(12 if library else 6, 3.6), squeeze=False)
    ax = axes[0][0]
    ax.plot(x, [e["mpjpe_mm"] for e in evals], "o-", color="tab:blue", label="MPJPE (mm)")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("MPJPE, root-relative (mm)", color="tab:blue")
    ax.grid(alpha=0.3)
    twin = ax.twinx()
    twin.plot(x, [100 * e["success_rate"] for e in evals], "s--", color="tab:green", label="success (%)")
    twin.set_ylabel("success (%)", color="tab:green")
    twin.set_ylim(-5, 105)
    ax.set_title(f"{results['run']} on {results['reference']['name']}", fontsize=9)
    if library:
        ax = axes[0][1]
        for name in clips:
            share = [next((100 * tracked_share(c) for c in e["clips"] if c["clip"] == name), float("nan"))
                     for e in evals]
            ax.plot(x, share, "o-", ms=3, label=name)
        ax.set_ylim(-5, 105)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("share of the clip tracked (%)")
        ax.set_title("per clip: 100 % = every episode reached the clip's end", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))  # clear of the lines at 100 %
    fig.tight_layout()
    return save_figure(fig, out_png)


def panel_grid(n: int):
    """A figure of ``n`` panels, three a row; (figure, the n axes in reading order)."""
    cols = min(3, n)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    return fig, list(axes.flat[:n])


def training_summary(run_dir: str | Path) -> dict:
    """Last values of the main curves and the throughput (median over iterations, so the
    first iteration's warm-up does not count)."""
    import statistics

    scalars = read_scalars(run_dir)
    last = {tag: scalars[tag][1][-1] for tag in TRAINING_PANELS if tag in scalars}
    steps, fps = scalars.get("Perf/total_fps", ([], []))
    return {
        "run": Path(run_dir).name,
        "iterations": (steps[-1] + 1) if steps else 0,
        "median_fps": statistics.median(fps) if fps else None,
        "learning_minutes": learning_minutes(scalars)[1][-1] if "Perf/collection_time" in scalars else None,
        "last": last,
    }


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """``otr plot``'s arguments."""
    parser.add_argument("run", nargs="+", help="run folder(s)")
    parser.add_argument("--png", required=True, help="output PNG of the training curves")
    parser.add_argument("--labels", nargs="+", help="with several runs: their legend labels (default: folder names)")
    parser.add_argument("--x", choices=RUN_AXES, default="minutes",
                        help="with several runs: draw against learning time (minutes) or PPO iteration "
                        "(default: %(default)s)")
    parser.add_argument("--json", help="output JSON summary (iterations, median FPS, last values); one run only")
    parser.add_argument("--clips-png", help="output PNG of the per-clip curves (success, MPJPE, segment length, "
                        "start probability); one run only")


def main(args: argparse.Namespace) -> int:
    """``otr plot RUN… --png PNG``: write the figures; a run that cannot be read, options that do not
    fit the runs given, or runs that cannot be compared: a message naming the problem, exit code 2."""
    several = len(args.run) > 1 or args.labels
    if several and (args.json or args.clips_png):
        print("otr plot: --json and --clips-png take one run", file=sys.stderr)
        return 2
    try:
        if several:
            print(f"wrote {plot_runs(args.run, args.png, args.labels, args.x)}")
            return 0
        run = args.run[0]
        print(f"wrote {plot_training(run, args.png)}")
        if args.clips_png:
            print(f"wrote {plot_clip_curves(run, args.clips_png)}")
        if args.json:
            summary = training_summary(run)
            print(f"wrote {runs.write_json(args.json, summary)}: {summary['iterations']} iterations, "
                  f"median {summary['median_fps']} env steps/s")
    except (runs.RunError, ValueError) as exc:
        print(f"otr plot: {exc}", file=sys.stderr)
        return 2
    return 0
