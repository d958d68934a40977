"""Settings of the evaluation protocol (paper Sec. IV-A); defaults are the paper's numbers."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class EvalConfig:
    """What the protocol compares and with which tolerances.

    ``scale``: ``None`` recovers the reference's world scale (see ``retarget.evaluation.scale``);
    a number forces it (the demonstration is then mapped into that world before comparing).
    """

    #: ε_eval (m): a sample (t, u, c) is an interaction when (d)₊ < ε_eval (Sec. IV-A, sets H, R).
    eps_eval_m: float = 0.02
    #: World of the demonstrated samples (d̂, ŵ). "native": the demonstration as captured, so
    #: every method, whatever its world, is compared with the same set H (its witnesses on
    #: the ground mapped by the scale; object witnesses live in the object frame, which
    #: scaling does not change). "reference": the demonstration first mapped into the
    #: reference's world (human and object trajectories × sc, objects not resized).
    contacts_world: str = "native"
    scale: float | None = None
    #: Largest accepted |duration(reference) − duration(demonstration)| (s). OmniRetarget's
    #: 50 fps output of a 30 fps clip ends 0.02 s early; a whole second off is another clip.
    duration_tolerance_s: float = 0.1
    #: Percentile over frames of the per-frame deepest self-penetration (paper: 95th).
    self_percentile: float = 95.0
    #: Demonstrated horizontal excursion (m, RMS about the mean) below which a least-squares
    #: scale fit is ill-conditioned; the fit then falls back to robot height / stature.
    scale_min_excursion_m: float = 0.05
    #: A fitted scale this close (relative) to a known convention (1, robot height / stature)
    #: is taken to be that convention, so sc = 1 is reported as 1 and not 0.993.
    scale_snap_rel: float = 0.02

    def __post_init__(self) -> None:
        if self.contacts_world not in ("native", "reference"):
            raise ValueError(f"contacts_world must be 'native' or 'reference', got {self.contacts_world!r}")
        if not self.eps_eval_m > 0:
            raise ValueError(f"eps_eval_m must be > 0, got {self.eps_eval_m}")
        if self.scale is not None and not (math.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"scale must be a positive number, got {self.scale}")
