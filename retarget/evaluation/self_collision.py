"""Self-penetration of the robot's visual meshes (the paper's *self*, Sec. IV-A).

What is computed: for every ordered pair (a, b) of links that are not kinematic neighbours,
every vertex of link a's visual mesh is tested against link b's visual mesh; its penetration
depth is its unsigned distance to b's surface when it lies inside b (negative signed
distance), else 0. The depth of frame t is the largest such depth over all pairs and vertices
(0 when nothing overlaps). *self* of a sequence is the 95th percentile over its frames of
that per-frame depth, so a single glancing frame does not dominate but a sustained overlap
does.

The G1 visual meshes are not watertight, so "inside" is the fast winding number of
``retarget.inputs.meshes.signed_distance``. Pairs are pruned exactly: link bounding spheres that do
not overlap cannot penetrate, and a vertex outside b's bounding box cannot be inside b.

Neighbours are excluded because their meshes overlap at the joints by design (the shells
interpenetrate around the joint axis): pairs at most ``exclude_hops`` apart in the kinematic
tree are skipped (2 by default: parent–child, grandparent–grandchild and siblings, since the
G1's small intermediate links — ankle pitch, waist roll, hip roll — sit inside their
neighbours' shells).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from otr_gym.rotations import quat_to_matrix
from retarget.geometry.kinematics import link_pairs_beyond
from retarget.inputs.meshes import TriMesh, as_trimesh, signed_distance


@dataclass(frozen=True)
class SelfPenetration:
    """Per-frame deepest self-penetration (m) and the ordered link pair that holds it."""

    depth_m: np.ndarray  # (T,) ≥ 0
    pair: np.ndarray  # (T, 2) link indices (a inside b), −1 where depth is 0

    def percentile_m(self, q: float) -> float:
        return float(np.percentile(self.depth_m, q))


def _spheres(meshes: list[TriMesh]) -> tuple[np.ndarray, np.ndarray]:
    lo = np.stack([m.bounds[0] for m in meshes])
    hi = np.stack([m.bounds[1] for m in meshes])
    centre = 0.5 * (lo + hi)
    radius = np.array([np.linalg.norm(m.vertices - c, axis=1).max() for m, c in zip(meshes, centre)])
    return centre, radius


def self_penetration(meshes: list[TriMesh], pos_w: np.ndarray, quat_w: np.ndarray,
                     pairs: np.ndarray) -> SelfPenetration:
    """Deepest penetration per frame among link ``pairs``.

    meshes: L link surfaces, each in its body frame (m). pos_w (T, L, 3), quat_w (T, L, 4) wxyz:
    body poses (world). pairs (P, 2): unordered link pairs to test (both orders are tested).
    """
    T = pos_w.shape[0]
    rot = quat_to_matrix(quat_w)  # (T, L, 3, 3)
    centre_b, radius = _spheres(meshes)
    centre_w = np.einsum("tlij,lj->tli", rot, centre_b) + pos_w
    box_lo = np.stack([m.bounds[0] for m in meshes])
    box_hi = np.stack([m.bounds[1] for m in meshes])
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    ordered = np.concatenate([pairs, pairs[:, ::-1]])
    a_all, b_all = ordered[:, 0], ordered[:, 1]
    # a's bounding sphere in b's frame against b's bounding box: all pairs and frames at once
    c_in_b = np.einsum("tpji,tpj->tpi", rot[:, b_all], centre_w[:, a_all] - pos_w[:, b_all])
    gap = np.linalg.norm(np.maximum(np.maximum(box_lo[b_all] - c_in_b, c_in_b - box_hi[b_all]), 0.0), axis=-1)
    near = gap < radius[a_all]  # (T, 2P)
    depth = np.zeros(T)
    pair_of = np.full((T, 2), -1, dtype=np.int64)
    for k in np.nonzero(near.any(axis=0))[0]:
        a, b = a_all[k], b_all[k]
        frames = np.nonzero(near[:, k])[0]
        # vertices of a in b's body frame: R_bᵀ (R_a v + p_a − p_b)
        rel_rot = np.matmul(rot[frames, b].transpose(0, 2, 1), rot[frames, a])
        rel_pos = np.einsum("tji,tj->ti", rot[frames, b], pos_w[frames, a] - pos_w[frames, b])
        pts = np.matmul(meshes[a].vertices, rel_rot.transpose(0, 2, 1)) + rel_pos[:, None, :]
        inside_box = np.all((pts > box_lo[b]) & (pts < box_hi[b]), axis=-1)
        t_idx, v_idx = np.nonzero(inside_box)
        if t_idx.size == 0:
            continue
        sd, _, _ = signed_distance(meshes[b], pts[t_idx, v_idx])
        per_frame = np.zeros(frames.size)
        np.maximum.at(per_frame, t_idx, np.maximum(-sd, 0.0))
        deeper = per_frame > depth[frames]
        depth[frames[deeper]] = per_frame[deeper]
        pair_of[frames[deeper]] = (a, b)
    return SelfPenetration(depth, pair_of)


@dataclass(frozen=True)
class RobotSelfModel:
    """The G1 links with a visual mesh, their surfaces (body frame) and the pairs to test."""

    links: tuple[str, ...]
    meshes: tuple[TriMesh, ...]
    pairs: np.ndarray  # (P, 2) indices into links


@lru_cache(maxsize=4)
def g1_self_model(exclude_hops: int = 2) -> RobotSelfModel:
    """Visual meshes of the G1 and its non-neighbouring link pairs (see module docstring)."""
    from otr_gym import robot
    from otr_gym.robot_geometry import visual_meshes
    from otr_gym.scene import robot_model

    vis = visual_meshes()
    links = tuple(b for b in robot.BODY_NAMES if b in vis)
    model = robot_model(visual=False)
    ids = [model.body(n).id for n in links]
    id_to_link = {bid: i for i, bid in enumerate(ids)}
    parents = np.array([id_to_link.get(int(model.body_parentid[bid]), -1) for bid in ids])
    meshes = tuple(as_trimesh(vis[n].vertices, vis[n].faces, f"G1 visual mesh '{n}'") for n in links)
    return RobotSelfModel(links, meshes, link_pairs_beyond(parents, exclude_hops))
