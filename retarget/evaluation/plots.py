"""PNG figures of an evaluation (matplotlib, Agg backend), drawn from the JSON records.

- ``plot_contact_timeline``: per channel (ground, each object) one panel; rows = body units
  that interact at least once, time on x; a cell is coloured by who interacts there:
  demonstration only (H \\ R, missed), retarget only (R \\ H, spurious), both (H ∩ R).
- ``plot_metric_distributions``: one panel per table metric, its per-sequence values over
  the evaluated set (box plot and points), so a dataset's spread shows next to its median.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from otr_gym.io import save_figure
from retarget.evaluation.sequence import TABLE_COLUMNS

#: Colours of a timeline cell: nothing, H only, R only, both.
TIMELINE_COLOURS = ("#ffffff", "#e8871e", "#3a7dc9", "#3fa34d")
TIMELINE_LABELS = ("", "demonstration only (missed)", "retarget only (spurious)", "both")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _mask(intervals, frames: int) -> np.ndarray:
    m = np.zeros(frames, bool)
    for start, stop in intervals:
        m[start:stop] = True
    return m


def _short(name: str, limit: int = 22) -> str:
    return name if len(name) <= limit else name[: limit - 1] + "…"


def plot_contact_timeline(record: dict, path: str | Path) -> Path:
    """Contact timeline of one sequence record (``SequenceResult.as_dict``) to ``path`` (PNG)."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    plt = _pyplot()
    frames, fps = record["frames"], record["fps"] or 1.0
    channels = record["channels"]
    timeline = record["timeline"]
    heights = [max(1, len(timeline.get(c, {}))) for c in channels]
    fig, axes = plt.subplots(len(channels), 1, figsize=(11, 1.2 + 0.28 * sum(heights) + 0.6 * len(channels)),
                             gridspec_kw={"height_ratios": heights}, squeeze=False)
    cmap = ListedColormap(TIMELINE_COLOURS)
    for ax, channel in zip(axes[:, 0], channels):
        rows = timeline.get(channel, {})
        names = list(rows)
        grid = np.zeros((max(1, len(names)), frames), np.int8)
        for i, n in enumerate(names):
            grid[i] = _mask(rows[n]["H"], frames) + 2 * _mask(rows[n]["R"], frames)
        ax.imshow(grid, aspect="auto", interpolation="nearest", cmap=cmap, vmin=0, vmax=3,
                  extent=(0.0, frames / fps, len(grid) - 0.5, -0.5))
        ax.set_yticks(range(len(names)), [_short(n) for n in names], fontsize=7)
        # this channel's own sample ratios (the record's object metrics pool every object)
        h, r = (grid & 1).astype(bool), (grid & 2).astype(bool)
        both = np.count_nonzero(h & r)
        ratios = (("R", both, np.count_nonzero(h)), ("P", both, np.count_nonzero(r)),
                  ("J", both, np.count_nonzero(h | r)))
        scores = ", ".join(f"{k} {100 * num / den:.0f}%" for k, num, den in ratios if den)
        ax.set_title(f"{channel}" + (f" — {scores}" if scores else " — no interaction"), fontsize=9, loc="left")
        ax.set_xlim(0.0, frames / fps)
    axes[-1, 0].set_xlabel("time (s)")
    fig.legend(handles=[Patch(color=c, label=lbl) for c, lbl in zip(TIMELINE_COLOURS[1:], TIMELINE_LABELS[1:])],
               loc="upper right", ncol=3, fontsize=8, frameon=False)
    fig.suptitle(f"{record['name']} vs {Path(record['demonstration']).name} (sc {record['metrics']['sc']:.2f})",
                 fontsize=10, x=0.01, ha="left")
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    return save_figure(fig, path)


def plot_metric_distributions(records: list[dict], path: str | Path) -> Path:
    """Per-sequence values of every table metric over ``records`` to ``path`` (PNG)."""
    plt = _pyplot()
    cols = 5
    rows = math.ceil(len(TABLE_COLUMNS) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(2.4 * cols, 2.3 * rows), squeeze=False)
    rng = np.random.default_rng(0)  # horizontal jitter of the points, fixed for reproducible figures
    for ax, (key, header, unit, factor, _) in zip(axes.ravel(), TABLE_COLUMNS):
        vals = np.array([np.nan if r["metrics"].get(key) is None else r["metrics"][key] * factor for r in records])
        vals = vals[np.isfinite(vals)]
        group = "object " if key.startswith("object") else "ground " if key.startswith("ground") else ""
        ax.set_title(f"{group}{header}" + (f" ({unit})" if unit else ""), fontsize=9)
        if vals.size == 0:
            ax.set_xticks([])
            ax.text(0.5, 0.5, "undefined", ha="center", va="center", transform=ax.transAxes, fontsize=8)
            continue
        ax.boxplot(vals, widths=0.5)
        ax.plot(1 + rng.uniform(-0.12, 0.12, vals.size), vals, "o", ms=3, alpha=0.6, color="#3a7dc9")
        ax.set_xticks([])
        ax.ticklabel_format(axis="y", useOffset=False, style="plain")
    for ax in axes.ravel()[len(TABLE_COLUMNS):]:
        ax.axis("off")
    fig.suptitle(f"metric distributions over {len(records)} sequence(s)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)
