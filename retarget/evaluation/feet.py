"""Foot contact quality of a retarget: *skate* and *clear* (paper Sec. IV-A).

Stance is taken from the **demonstration**: frame t is a stance frame of a foot when the
demonstrated foot unit is in ground interaction ((d̂)₊ < ε_eval, i.e. the sample is in H).
Every method is then judged on the same frames, and a robot foot hovering above the floor
while the human stands shows up as positive clearance (the paper's GMR row has clear 30.9 mm,
above ε_eval, which a robot-side stance definition could not produce).

- skate: at each stance frame, the horizontal speed of the foot mesh's least-moving vertex
  (central differences of its world position at the reference rate); median over the stance
  frames of both feet, cm/s. The least-moving vertex makes heel or toe pivots count as
  no sliding, as they should.
- clear: the robot foot unit's ground distance (its lowest vertex height, negative when
  below the floor) at the stance frames; median over both feet, mm.
"""

from __future__ import annotations

import numpy as np


def least_moving_speed(vertices_w: np.ndarray, fps: float) -> np.ndarray:
    """Horizontal speed (m/s) of the slowest vertex per frame; vertices_w (T, V, 3) world
    (zero for a single frame)."""
    if len(vertices_w) < 2:
        return np.zeros(len(vertices_w))
    vel_xy = np.gradient(vertices_w[..., :2], 1.0 / fps, axis=0)
    return np.linalg.norm(vel_xy, axis=-1).min(axis=1)


def skate_and_clear(feet_vertices_w: list[np.ndarray], stance: np.ndarray, fps: float) -> tuple[float, float]:
    """(skate m/s, clear m) of the robot feet.

    feet_vertices_w: per foot, its mesh vertices (T, V, 3) world (m); stance (T, F) boolean
    stance frames from the demonstration. NaN when no foot is ever in stance.
    """
    speeds, heights = [], []
    for f, verts in enumerate(feet_vertices_w):
        on = stance[:, f]
        speeds.append(least_moving_speed(verts, fps)[on])
        heights.append(verts[on, :, 2].min(axis=1) if on.any() else np.empty(0))
    speeds, heights = np.concatenate(speeds), np.concatenate(heights)
    if speeds.size == 0:
        return float("nan"), float("nan")
    return float(np.median(speeds)), float(np.median(heights))
