"""Contacts between objects and their surroundings: a box on the table, a box on the floor.

The robot's contacts are scored per (body unit, channel); an object's own contacts with the
scene are scored here the same way, with the manipulated object as the "unit": for every
manipulated object a and every other object b (and the ground), samples (t, a, b) carry the
demonstrated signed distance of a's closest mesh vertex to b (captured meshes at the captured
poses) and the retargeted one (the reference's meshes, a substitute's when it carries one, at
the reference's poses). H, R, P, R, J and dd follow ``contact`` with the same ε_eval. dw is
kept for completeness; with a substitute the two witnesses lie on different surfaces.

Vertices are posed in chunks of frames (a 13.5k-vertex scan over 300 frames would hold
~100 MB of posed vertices at once).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from retarget.evaluation.channels import ObjectChannel
from retarget.evaluation.contact import ContactScores, contact_scores, interaction_set
from retarget.evaluation.proximity import BoundedMesh, ground_proximity, mesh_proximity
from retarget.evaluation.units import Piece, PosedUnit

#: Frames posed at once.
CHUNK_FRAMES = 64


@dataclass(frozen=True)
class PairSamples:
    """Demonstrated and retargeted distances (T,) m and witnesses (T, 3) (b's frame) of object
    ``a`` to ``b`` ('ground' or another object)."""

    a: str
    b: str
    d_hat_m: np.ndarray
    w_hat: np.ndarray
    d_m: np.ndarray
    w: np.ndarray

    @property
    def name(self) -> str:
        return f"{self.a}|{self.b}"

    def scores(self, eps_m: float) -> ContactScores:
        return contact_scores(self.d_hat_m, self.w_hat, self.d_m, self.w, eps_m)


def _unit(mesh_vertices: np.ndarray, pos_w: np.ndarray, quat_w: np.ndarray) -> PosedUnit:
    return PosedUnit.from_poses([Piece.of(mesh_vertices)], pos_w[:, None], quat_w[:, None])


def _ground(unit: PosedUnit, T: int) -> tuple[np.ndarray, np.ndarray]:
    d, w = np.empty(T), np.empty((T, 3))
    for s in range(0, T, CHUNK_FRAMES):
        ch = slice(s, min(s + CHUNK_FRAMES, T))
        d[ch], w[ch] = ground_proximity(unit.frames(ch))
    return d, w


def object_pair_samples(channels: list[ObjectChannel], eps_m: float) -> list[PairSamples]:
    """Samples of every tracked manipulated object against the ground and every other object."""
    out = []
    bounded: dict[int, BoundedMesh] = {}

    def bound(mesh) -> BoundedMesh:
        if id(mesh) not in bounded:
            bounded[id(mesh)] = BoundedMesh.from_mesh(mesh)
        return bounded[id(mesh)]

    for a in channels:
        if not a.tracked or a.static:
            continue
        T = len(a.demo_pos_w)
        demo_u = _unit(a.demo_mesh.vertices, a.demo_pos_w, a.demo_quat_w)
        ref_u = _unit(a.ref_mesh.vertices, a.ref_pos_w, a.ref_quat_w)
        out.append(PairSamples(a.name, "ground", *_ground(demo_u, T), *_ground(ref_u, T)))
        for b in channels:
            if b is a:
                continue
            d_hat, w_hat, d, w = np.empty(T), np.empty((T, 3)), np.empty(T), np.empty((T, 3))
            for s in range(0, T, CHUNK_FRAMES):
                ch = slice(s, min(s + CHUNK_FRAMES, T))
                d_hat[ch], w_hat[ch] = (x[:, 0] for x in mesh_proximity(
                    bound(b.demo_mesh), [demo_u.frames(ch).in_frame(b.demo_pos_w[ch], b.demo_quat_w[ch])], eps_m))
                # exact wherever the demonstration is in contact (dd), else only below ε
                need = np.where(interaction_set(d_hat[ch], eps_m), np.inf, eps_m)[:, None]
                d[ch], w[ch] = (x[:, 0] for x in mesh_proximity(
                    bound(b.ref_mesh), [ref_u.frames(ch).in_frame(b.ref_pos_w[ch], b.ref_quat_w[ch])], need))
            out.append(PairSamples(a.name, b.name, d_hat, w_hat, d, w))
    return out


def pooled_scores(samples: list[PairSamples], eps_m: float) -> ContactScores:
    """Scores over the pooled samples of several pairs (NaN ratios when there are none)."""
    if not samples:
        return contact_scores(np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), eps_m)
    return contact_scores(np.concatenate([s.d_hat_m for s in samples]), np.concatenate([s.w_hat for s in samples]),
                          np.concatenate([s.d_m for s in samples]), np.concatenate([s.w for s in samples]), eps_m)
