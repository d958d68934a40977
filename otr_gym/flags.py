"""Per-frame boolean flags (contact, stance, proximity windows): short breaks closed."""

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
