"""Exact unit–channel proximity: each body unit's closest vertex to the ground or a mesh.

A unit (``units.PosedUnit``) is a set of rigid surface pieces moving over T frames. Its
distance to a channel at frame t is the signed distance of its closest vertex (negative =
penetration), and its witness is that vertex's closest point on the channel surface, in the
**channel frame** (world for the ground, object frame for objects).

Mesh distances are exact (``retarget.inputs.meshes.signed_distance``: AABB point–triangle queries,
winding-number sign robust to holes). Querying every vertex of every frame would cost
~10 µs × 30k vertices × T, so vertices that provably cannot be the closest one are skipped,
without approximation. The signed distance to the mesh's oriented bounding box is a lower
bound of the signed distance to the mesh (``BoundedMesh``). A unit's vertex with the smallest
bound is queried first; only
vertices whose bound could beat that distance are queried next. Before any vertex is posed,
whole pieces are bounded the same way through their bounding spheres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from retarget.evaluation.units import PosedUnit
from retarget.inputs.meshes import TriMesh, signed_distance


def ground_proximity(unit: PosedUnit) -> tuple[np.ndarray, np.ndarray]:
    """Distance of a unit (world poses) to the ground plane z = 0.

    Returns d (T,) = its lowest vertex height (m) and witness (T, 3) = that vertex projected
    onto the plane (world).
    """
    T = unit.num_frames
    low_z = np.empty((T, len(unit.pieces)))
    low_v = np.empty((T, len(unit.pieces)), dtype=np.int64)
    for k, p in enumerate(unit.pieces):
        z = unit.rot[:, k, 2, :] @ p.vertices.T + unit.pos[:, k, 2, None]  # (T, V_k): third row only
        low_v[:, k] = np.argmin(z, axis=1)
        low_z[:, k] = np.take_along_axis(z, low_v[:, k, None], axis=1)[:, 0]
    k_best = np.argmin(low_z, axis=1)
    witness = np.zeros((T, 3))
    for k, p in enumerate(unit.pieces):
        t = np.nonzero(k_best == k)[0]
        v = p.vertices[low_v[t, k]]
        witness[t, :2] = (np.einsum("tij,tj->ti", unit.rot[t, k], v) + unit.pos[t, k])[:, :2]
    return low_z[np.arange(T), k_best], witness


@dataclass(frozen=True)
class BoundedMesh:
    """A channel surface (its own frame, m) and its oriented bounding box (OBB).

    The OBB's signed distance is a lower bound of the mesh's everywhere: outside the box it
    is the distance to the box, which contains the mesh; inside, a point inside the mesh is no
    deeper than its distance to the box boundary. It is 1-Lipschitz, so a sphere of radius r
    around c is no closer than bound(c) − r.
    """

    mesh: TriMesh
    box_rot: np.ndarray  # (3, 3) rows: box axes in the mesh frame
    box_centre: np.ndarray  # (3,) in the box frame
    box_half: np.ndarray  # (3,) half extents

    @classmethod
    def from_mesh(cls, mesh: TriMesh) -> BoundedMesh:
        import trimesh

        to_box = trimesh.bounds.oriented_bounds(mesh.vertices)[0]
        rot = to_box[:3, :3]
        local = mesh.vertices @ rot.T
        lo, hi = local.min(axis=0), local.max(axis=0)
        return cls(mesh, rot, 0.5 * (lo + hi), 0.5 * (hi - lo))

    def lower_bound(self, points: np.ndarray) -> np.ndarray:
        """(…,) lower bound of the signed distance of points (…, 3) in the mesh frame (m)."""
        q = np.abs(points @ self.box_rot.T - self.box_centre) - self.box_half
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
        return np.where(outside > 0.0, outside, q.max(axis=-1))


#: Vertices queried per open sample in successive rounds (None: all that remain). Each round
#: is one libigl call (~0.1 s set-up on a 27k-face scan); later rounds see only the vertices
#: whose bound still beats the best distance found.
_ROUND_SIZES = (1, 32, None)


def mesh_proximity(target: BoundedMesh, units_c: list[PosedUnit],
                   exact_below: np.ndarray | float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Distance of several units to one mesh, exact wherever it is below ``exact_below``.

    target: the channel surface in its own frame. units_c: the units, posed in the channel
    frame (``PosedUnit.in_frame``). exact_below: (T, U) or scalar (m); a sample
    whose distance is at least this value only needs to be known as such, so it may be
    returned as a value ≥ exact_below (a bound, with a NaN witness when no vertex was queried)
    instead of its exact distance. The protocol needs exact distances below ε_eval (membership
    of H and R) and everywhere on H for the robot (dd, dw).

    Returns d (T, U) signed distance of each unit's closest vertex (m, negative inside) and
    witness (T, U, 3), its closest point on the mesh (channel frame).
    """
    T, U = units_c[0].num_frames, len(units_c)
    limit = np.broadcast_to(np.asarray(exact_below, np.float64), (T, U))
    d = np.empty((T, U))  # a lower bound until a vertex is queried, then the best exact distance
    w = np.full((T, U, 3), np.nan)
    rows = []  # per unit: frames, posed vertices, their bounds (ascending) and the vertex order
    for u, unit in enumerate(units_c):
        # whole pieces: the bound at their sphere centres minus their radii
        d[:, u] = np.min(target.lower_bound(unit.centres()) - unit.radii(), axis=1)
        t_open = np.nonzero(d[:, u] < limit[:, u])[0]
        pts = unit.vertices(t_open)
        b = target.lower_bound(pts)  # (n, V_u)
        d[t_open, u] = b.min(axis=1)
        need = d[t_open, u] < limit[t_open, u]
        order = np.argsort(b[need], axis=1)
        rows.append((t_open[need], pts[need], np.take_along_axis(b[need], order, axis=1), order))
    best = np.full((T, U), np.inf)
    # rounds of queries in ascending bound order; a vertex is queried only while its bound
    # could still beat the best distance found (or bring the unit under its limit)
    start = 0
    for count in _ROUND_SIZES:
        block = slice(start, None if count is None else start + count)
        keys, pts = [], []
        for u, (t, p, b_sorted, order) in enumerate(rows):
            cand = b_sorted[:, block] < np.minimum(best[t, u], limit[t, u])[:, None]
            i_idx, j_idx = np.nonzero(cand)
            keys.append(t[i_idx] * U + u)
            pts.append(p[i_idx, order[:, block][i_idx, j_idx]])
        keys = np.concatenate(keys)
        if keys.size == 0:
            break
        dc, wc, _ = signed_distance(target.mesh, np.concatenate(pts))
        first = np.lexsort((dc, keys))
        uniq, at = np.unique(keys[first], return_index=True)
        pick = first[at]
        t_b, u_b = np.divmod(uniq, U)
        better = dc[pick] < best[t_b, u_b]
        best[t_b[better], u_b[better]] = dc[pick[better]]
        w[t_b[better], u_b[better]] = wc[pick[better]]
        if count is None:
            break
        start += count
    queried = np.isfinite(best)
    d[queried] = best[queried]
    return d, w
