"""Interaction agreement between a demonstration and a retarget (paper Sec. IV-A).

Samples (t, u, c) pair frame t, body unit u and channel c. With ε = ε_eval:
H = {(d̂)₊ < ε} (demonstrated), R = {(d)₊ < ε} (retargeted); penetrations count as
interactions. P = |H∩R|/|R|, R = |H∩R|/|H|, J = |H∩R|/|H∪R| as sample ratios; over H,
dd = mean |d − (d̂)₊| (gap error) and dw = mean ‖w − ŵ‖ (placement error, witnesses in the
channel frame). A ratio with an empty denominator is NaN (e.g. precision when the robot
touches nothing): it is undefined, not 0 or 1, and the dataset median skips it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


def interaction_set(d: np.ndarray, eps_m: float) -> np.ndarray:
    """Boolean mask of samples in interaction: (d)₊ < ε (d signed, m)."""
    return np.maximum(d, 0.0) < eps_m


@dataclass(frozen=True)
class ContactScores:
    """Agreement of H and R over a set of samples; distances in m, ratios in [0, 1]."""

    n_h: int
    n_r: int
    n_both: int
    precision: float
    recall: float
    jaccard: float
    dd_m: float
    dw_m: float

    def as_dict(self) -> dict:
        return asdict(self)


def _ratio(num: int, den: int) -> float:
    return num / den if den else float("nan")


def contact_scores(d_hat: np.ndarray, w_hat: np.ndarray, d: np.ndarray, w: np.ndarray,
                   eps_m: float) -> ContactScores:
    """Scores of samples of any shape S: d_hat, d (S) signed distances (m); w_hat, w (S, 3)
    witnesses in the channel frame (m)."""
    h = interaction_set(d_hat, eps_m)
    r = interaction_set(d, eps_m)
    n_h, n_r, n_both, n_any = int(h.sum()), int(r.sum()), int((h & r).sum()), int((h | r).sum())
    if n_h:
        dd = float(np.mean(np.abs(d[h] - np.maximum(d_hat[h], 0.0))))
        dw = float(np.mean(np.linalg.norm(w[h] - w_hat[h], axis=-1)))
    else:
        dd = dw = float("nan")
    return ContactScores(n_h, n_r, n_both, _ratio(n_both, n_r), _ratio(n_both, n_h), _ratio(n_both, n_any), dd, dw)
