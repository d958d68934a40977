"""Two-hand holds of the demonstration: the frames in which the person carries an object off its
support with both hands, and the object style weights of those frames (``StyleConfig.hold_*``).

Everywhere else the free object's rotation is held to the demonstration by λ_o,rot only (1 per
rad², ``StyleConfig.object_rot_weight``): the robot's probes decide it, so the object is free
to follow the smaller robot (the chair the G1's shorter arms hold). In a two-hand hold that
freedom is a lottery: on OMOMO ``sub3_largebox_003`` the probe seed alone turned the reference's
box by up to 45° about the squeeze axis (docs/results/box.md, "No lottery"), and a box that
turns between two palms is one the simulated hands cannot carry. The hold frames are found on
the demonstration alone (the person's hands and the object), so they do not depend on the probe
seed, and get ``hold_rot_weight`` (and ``hold_pos_weight``) instead, blended in and out with a
smoothstep over ``hold_ramp_s``. Only box-like objects get them (``hold_boxes_only``): the shape
the grasp pass squeezes; a chair held to its demonstrated turn drifts from the person's grip,
which the G1's shorter arms cannot make (docs/results/box.md, "No lottery").
"""

from __future__ import annotations

import numpy as np

from retarget.solver.style import StyleConfig
from retarget.solver.targets import surface_distances

#: The human parts whose surface is each hand (``retarget.inputs.human.G1_LINK_PARTS`` of
#: ``robot.HANDS``: SMPL's wrist part carries the hand).
HAND_PARTS = ("L_Wrist", "R_Wrist")


def hold_frames(hand_gap_m: np.ndarray, object_z_m: np.ndarray, cfg: StyleConfig) -> np.ndarray:
    """(T,) bool: both hands within ``hold_reach_m`` of the object (``hand_gap_m`` (T, 2): each
    hand surface's smallest distance to it, m) while the object is lifted more than
    ``hold_lift_m`` above its lowest height over the clip (``object_z_m`` (T,), m)."""
    near = (hand_gap_m <= cfg.hold_reach_m).all(axis=1)
    lifted = object_z_m > object_z_m.min() + cfg.hold_lift_m
    return near & lifted


def hold_blend(held: np.ndarray, ramp_frames: int) -> np.ndarray:
    """(T,) in [0, 1]: 1 on held frames, a smoothstep down to 0 over ``ramp_frames`` either side."""
    T = held.size
    out = np.zeros(T)
    frames = np.flatnonzero(held)
    if frames.size == 0:
        return out
    ramp = max(int(ramp_frames), 1)
    gap = np.abs(np.arange(T)[:, None] - frames[None, :]).min(axis=1)  # frames to the nearest hold frame
    x = np.clip(1.0 - gap / ramp, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def object_style_weights(blend: np.ndarray, cfg: StyleConfig) -> np.ndarray:
    """(T, O, 2) (λ_o,pos, λ_o,rot) per frame and free object from their hold blends (T, O):
    the base weights outside holds, ``hold_pos_weight``/``hold_rot_weight`` in them (a hold
    weight below the base one keeps the base)."""
    base = np.array([cfg.object_pos_weight, cfg.object_rot_weight])
    held = np.maximum(base, [cfg.hold_pos_weight, cfg.hold_rot_weight])
    return base + blend[..., None] * (held - base)


def is_box_like(mesh) -> bool:
    """Whether an object mesh (``TriMesh``: vertices, faces) is one the box environment collides
    as a box and the grasp pass squeezes (``otr_gym.object_box``)."""
    from otr_gym.object_box import BoxFitCfg, fit_box

    return bool(fit_box(np.asarray(mesh.vertices), np.asarray(mesh.faces)).is_box(BoxFitCfg()))


def hand_gaps(demo, part_pos_w: np.ndarray, part_rot_w: np.ndarray, scale: float, track, band: float) -> np.ndarray:
    """(T, 2) m: per frame, the smallest distance of each hand's surface (``HAND_PARTS``, the
    demonstration's mesh × ``scale``) to the object of ``track`` (a ``ChannelTrack``; its captured
    surface where it is substituted), capped at ``band`` (m)."""
    names = list(demo.surface.part_names)
    out = np.empty((part_pos_w.shape[0], len(HAND_PARTS)))
    for k, part in enumerate(HAND_PARTS):
        i = names.index(part)
        v = scale * np.asarray(demo.surface.vertices[i], np.float64)
        x_w = np.einsum("tij,vj->tvi", part_rot_w[:, i], v) + part_pos_w[:, i, None]  # (T, V, 3)
        x_c = np.einsum("tji,tvj->tvi", track.rot_w, x_w - track.pos_w[:, None]).reshape(-1, 3)  # object frame
        d = np.full(len(x_c), band)
        near, d_near = surface_distances(track, x_c, band)
        d[near] = np.minimum(d_near, band)
        out[:, k] = d.reshape(part_pos_w.shape[0], -1).min(axis=1)
    return out
