"""World scale of a reference, and the demonstration mapped into that world.

Methods retarget in their own world: native (sc = 1), or, like OmniRetarget and our scaled
ablation, a world where human and object trajectories are multiplied by
sc = robot height / stature (1.32 m / stature) while the object keeps its size. The protocol
compares a reference with the demonstration mapped into the reference's world.

Recovering sc (``recover_scale``): least squares of the reference's trajectories against the
demonstration's at the same times, each coordinate track with its own offset (so a shifted
origin or the height convention below does not bias it): every matched object's position
(3 coordinates) and the pelvis' horizontal position (the robot pelvis is lower than a scaled
human pelvis — leg proportions differ — so its height is left out). sc = Σ⟨r̃, d̃⟩ / Σ⟨d̃, d̃⟩
over the mean-removed tracks r̃ (reference) and d̃ (demonstration); the fit reports its RMS
residual and R². A fit within 2 % of a known convention (1, robot height / stature) takes
that convention's exact value. A demonstration that barely moves horizontally makes the fit
ill-conditioned: the stature ratio is used then, and the report says so.

Mapping (``scale_demonstration``): the human is scaled about the world origin — part positions
and its surface × sc, so the floor stays at z = 0; objects move as OmniRetarget's files show
(verified on sub3_largebox_003: x, y ratio 0.6800 throughout, z = z₀ + sc (z − z₀)): horizontal
position × sc, height about its height at the first frame, so a box resting on the floor stays
on it; object meshes are not resized.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from otr_gym import robot
from retarget.inputs.demonstration import Demonstration, scaled_object_positions


@dataclass(frozen=True)
class ScaleFit:
    """The scale used for one reference and how it was obtained."""

    sc: float
    source: str  # "given", "metadata", "fit", "fit = <convention>", "stature (…)"
    fit_sc: float  # least-squares estimate (NaN when the fit is ill-conditioned)
    fit_rms_m: float  # RMS residual of the fit (m)
    fit_r2: float  # explained fraction of the reference tracks' variance
    excursion_m: float  # RMS of the demonstrated tracks about their means (m)
    stature_sc: float  # robot height / stature

    def as_dict(self) -> dict:
        return asdict(self)


def fit_track_scale(ref_tracks: list[np.ndarray], demo_tracks: list[np.ndarray]) -> tuple[float, float, float, float]:
    """Least-squares sc with ref ≈ sc · demo + offset per coordinate.

    ref_tracks, demo_tracks: matching (T, k) arrays (m). Returns (sc, rms residual m, R²,
    demonstrated RMS excursion m).
    """
    r = np.concatenate([x - x.mean(axis=0) for x in ref_tracks], axis=1)
    d = np.concatenate([x - x.mean(axis=0) for x in demo_tracks], axis=1)
    dd = float(np.sum(d * d))
    excursion = float(np.sqrt(dd / len(d)))
    if dd == 0.0:
        return float("nan"), float("nan"), float("nan"), 0.0
    sc = float(np.sum(r * d) / dd)
    res = r - sc * d
    rr = float(np.sum(r * r))
    r2 = 1.0 - float(np.sum(res * res)) / rr if rr > 0 else float("nan")
    return sc, float(np.sqrt(np.sum(res * res) / len(d))), r2, excursion


def recover_scale(ref_tracks: list[np.ndarray], demo_tracks: list[np.ndarray], stature_m: float,
                  given: float | None = None, metadata_scale: float | None = None,
                  min_excursion_m: float = 0.05, snap_rel: float = 0.02) -> ScaleFit:
    """The scale of a reference's world (see module docstring); ``given`` wins, then the
    reference's own ``metadata_scale`` (our files record it), then the fit."""
    fit_sc, rms, r2, excursion = fit_track_scale(ref_tracks, demo_tracks)
    stature_sc = robot.HEIGHT_M / stature_m
    common = {"fit_sc": fit_sc, "fit_rms_m": rms, "fit_r2": r2, "excursion_m": excursion, "stature_sc": stature_sc}
    if given is not None:
        return ScaleFit(sc=float(given), source="given", **common)
    if metadata_scale is not None:
        return ScaleFit(sc=float(metadata_scale), source="metadata", **common)
    if not excursion >= min_excursion_m:
        return ScaleFit(sc=stature_sc, source=f"stature (motion of {excursion * 100:.1f} cm too small to fit)",
                        **common)
    for name, value in (("native", 1.0), ("robot height / stature", stature_sc)):
        if abs(fit_sc / value - 1.0) <= snap_rel:
            return ScaleFit(sc=value, source=f"fit = {name}", **common)
    return ScaleFit(sc=fit_sc, source="fit", **common)


def scale_demonstration(demo: Demonstration, sc: float) -> Demonstration:
    """The demonstration in a world scaled by ``sc`` (see module docstring)."""
    if sc == 1.0:
        return demo
    surface = replace(demo.surface, vertices=[v * sc for v in demo.surface.vertices])
    objects = []
    for o in demo.objects:
        objects.append(replace(o, pos_w=scaled_object_positions(o.pos_w, sc)))
    return replace(demo, part_pos_w=demo.part_pos_w * sc, surface=surface, stature_m=demo.stature_m * sc,
                   objects=objects)
