"""Per-frame boolean flags (contact, stance, proximity windows, flights): short breaks closed,
runs of True as frame ranges."""

from __future__ import annotations

import numpy as np


def close_short_gaps(flags: np.ndarray, max_gap: int, closable: np.ndarray | None = None) -> np.ndarray:
    """``flags`` (T, …), time first, with every run of False of at most ``max_gap`` frames
    between two True frames of the same series set True (a copy); with ``closable`` (same
    shape), only runs whose every frame is closable. A leading or trailing run stays."""
    out = np.array(flags, dtype=bool, copy=True)
    if max_gap < 1:
        return out
    series = out.reshape(len(out), -1)  # a view: writes land in ``out``
    allowed = None if closable is None else np.asarray(closable, bool).reshape(len(out), -1)
    for f in range(series.shape[1]):
        on = np.flatnonzero(series[:, f])
        for a, b in zip(on[:-1], on[1:]):
            if 1 < b - a <= max_gap + 1 and (allowed is None or allowed[a + 1:b, f].all()):
                series[a + 1:b, f] = True
    return out


def true_intervals(flags, gap: int = 0) -> list[tuple[int, int]]:
    """[(start, stop)] half-open frame ranges of the runs of True in the 1-D ``flags``, in order;
    runs separated by at most ``gap`` False frames are one (``close_short_gaps``)."""
    flags = np.asarray(flags, dtype=bool)
    closed = close_short_gaps(flags, gap) if flags.size else flags
    edges = np.diff(np.concatenate([[0], closed.astype(np.int8), [0]]))
    return [(int(a), int(b)) for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True)]
