"""Self-collision rows of the G1 (eq. m-qp-col): capsule pairs closer than a margin, and the
visual-mesh points of one link inside another's distance grid (clustered, deepest point per
cluster)."""

from __future__ import annotations

import numba
import numpy as np

from retarget.geometry.jit import inlined
from retarget.geometry.kinematics import LinkFrames
from retarget.geometry.voxel_grid import PREFETCH_AHEAD, _cell_inside, _prefetch_phi_cell, _trilinear_phi
from retarget.solver.probes import _in_frame, _pose_in_frame, _posed_point
from retarget.solver.problem import Problem
from retarget.solver.residuals import Rows, _twist_row


def self_mesh_rows(problem: Problem, fr: LinkFrames, centre_w: np.ndarray, reach: float) -> Rows:
    """Self-collision of the links' visual meshes: every vertex of link a against the distance
    grid of link b (its frame), for the pairs of ``Problem.self_pairs`` whose bounding spheres
    come within ``reach``, both ways; rows d − (m_a + m_b) ≥ 0 with both links moving, where m
    is each link's surface margin (so that Unitree's original shells do not overlap either).
    Vertices are tested by clusters first (``retarget.solver.probes.PointClusters``): only clusters
    whose centre, less their radius, is within ``reach`` of b are posed vertex by vertex.

    The capsules (``self_collision_rows``) keep limbs apart coarsely; these rows are what the
    evaluation measures (vertices of one mesh inside another)."""
    pairs = problem.self_pairs
    gap = (np.linalg.norm(centre_w[pairs[:, 0]] - centre_w[pairs[:, 1]], axis=1)
           - problem.link_radius[pairs[:, 0]] - problem.link_radius[pairs[:, 1]])
    close = pairs[gap < reach]
    if len(close) == 0:
        return Rows.empty()
    ordered = np.ascontiguousarray(np.concatenate([close, close[:, ::-1]]), np.intp)
    clusters, grids, vg = problem.self_clusters, problem.link_grids, problem.self_points
    grid = (grids.phi.ravel(), grids.origin, grids.inv_resolution, grids.upper, grids.strides, grids.offset)
    # first the clusters within reach, then their vertices: a cluster or vertex outside b's grid is
    # dropped before its cell is read, and the outputs are sized by the vertices that can matter
    first = clusters.body_offsets[ordered[:, 0]]
    bound = int(np.sum(clusters.body_offsets[ordered[:, 0] + 1] - first))
    pair, cluster = np.empty(bound, np.intp), np.empty(bound, np.intp)
    n = _self_mesh_clusters(ordered, clusters.centre, clusters.radius, clusters.body_offsets, fr.rot, fr.pos,
                            float(reach), *grid, grids.box_centre, grids.box_radius, pair, cluster)
    pair, cluster = pair[:n], cluster[:n]
    bound = int(np.sum(clusters.offsets[cluster + 1] - clusters.offsets[cluster]))
    link_a, link_b = np.empty(bound, np.intp), np.empty(bound, np.intp)
    value, phi = np.empty(bound), np.empty((bound, 12))
    k = _self_mesh_points(ordered, pair, cluster, clusters.offsets, vg.points, fr.rot, fr.pos, float(reach), *grid,
                          problem.surface_margin, link_a, link_b, value, phi)
    return Rows(value[:k], np.ones(k), phi[:k], link_a[:k], link_b[:k])


@numba.njit(cache=True)
def _self_mesh_clusters(ordered, centre, radius, body_offsets, rot, pos, reach, phi, origin, inv_resolution, upper,
                        strides, offset, box_centre, box_radius, out_pair, out_cluster):
    """The clusters of ``self_mesh_rows`` whose vertices are to be tested: per ordered pair
    (a, b) (index p), each cluster c of a whose centre lies in b's grid with Φ − radius < reach,
    as (p, c) in that order; returns their count. Each link's cluster centres are posed in the
    world once; a centre farther from b's grid box centre than its half diagonal (``box_centre``,
    ``box_radius``, grid frame), plus a micrometre for rounding, lies outside b's grid: it is
    dropped without being posed into b's frame."""
    world = np.empty((centre.shape[0], 3))
    posed = np.zeros(body_offsets.shape[0] - 1, np.bool_)
    k = 0
    for p in range(ordered.shape[0]):
        a, b = ordered[p, 0], ordered[p, 1]
        if not posed[a]:
            for c in range(body_offsets[a], body_offsets[a + 1]):
                world[c, 0], world[c, 1], world[c, 2] = _posed_point(centre, c, a, rot, pos)
            posed[a] = True
        g0, g1, g2 = _posed_point(box_centre, b, b, rot, pos)
        reach_sq = (box_radius[b] + 1e-6) ** 2
        inv = inv_resolution[b]
        o0, o1, o2 = origin[b, 0], origin[b, 1], origin[b, 2]
        up0, up1, up2 = upper[b, 0], upper[b, 1], upper[b, 2]
        sx, sy, sz = strides[b, 0], strides[b, 1], strides[b, 2]
        for c in range(body_offsets[a], body_offsets[a + 1]):
            e0, e1, e2 = world[c, 0] - g0, world[c, 1] - g1, world[c, 2] - g2
            if e0 * e0 + e1 * e1 + e2 * e2 > reach_sq:
                continue
            x0, x1, x2 = _in_frame(world[c, 0], world[c, 1], world[c, 2], b, rot, pos)
            inside, val, _, _, _ = _phi_at(x0, x1, x2, phi, offset[b], o0, o1, o2, inv, up0, up1, up2, sx, sy, sz)
            if inside and val - radius[c] < reach:
                out_pair[k], out_cluster[k] = p, c
                k += 1
    return k


@numba.njit(cache=True)
def _self_mesh_points(ordered, pair, cluster, offsets, points, rot, pos, reach, phi, origin, inv_resolution, upper,
                      strides, offset, surface_margin, out_a, out_b, out_value, out_phi):
    """The rows of ``self_mesh_rows``: for each (pair p = (a, b), cluster c of a) of
    ``_self_mesh_clusters``, each vertex x of c in b's grid with Φ < reach, as the row
    Φ − m_a − m_b with the factors φ of ``twist_factors`` for the world gradient R_b ∇Φ; returns
    the count. Point by point the arithmetic of ``posed_in_frames``, ``GridStack.distance`` and
    ``twist_factors``, without their intermediate arrays. R_b ∇Φ is summed as numpy's einsum
    sums it on our builds ((x + z) + y), so that references did not move by a bit."""
    k = np.int64(0)  # not a literal 0: the callees it is passed to would compile twice
    for q in range(pair.shape[0]):
        a, b = ordered[pair[q], 0], ordered[pair[q], 1]
        inv = inv_resolution[b]
        o0, o1, o2 = origin[b, 0], origin[b, 1], origin[b, 2]
        up0, up1, up2 = upper[b, 0], upper[b, 1], upper[b, 2]
        sx, sy, sz = strides[b, 0], strides[b, 1], strides[b, 2]
        c = cluster[q]
        end = offsets[c + 1]
        for v in range(offsets[c], end):
            if v + PREFETCH_AHEAD < end:
                _prefetch_point_cell(points, v + PREFETCH_AHEAD, a, b, rot, pos, phi, offset[b], o0, o1, o2, inv,
                                     up0, up1, up2, sx, sy, sz)
            inside, val, g0, g1, g2, w0, w1, w2 = _phi_in_grid(points, v, a, b, rot, pos, phi, offset[b], o0, o1,
                                                               o2, inv, up0, up1, up2, sx, sy, sz)
            if not (inside and val < reach):
                continue
            g0, g1, g2 = g0 * inv, g1 * inv, g2 * inv
            a0 = (rot[b, 0, 0] * g0 + rot[b, 0, 2] * g2) + rot[b, 0, 1] * g1
            a1 = (rot[b, 1, 0] * g0 + rot[b, 1, 2] * g2) + rot[b, 1, 1] * g1
            a2 = (rot[b, 2, 0] * g0 + rot[b, 2, 2] * g2) + rot[b, 2, 1] * g1
            out_a[k], out_b[k] = a, b
            out_value[k] = val - surface_margin[a] - surface_margin[b]
            _twist_row(a0, a1, a2, w0, w1, w2, pos[a, 0], pos[a, 1], pos[a, 2], pos[b, 0], pos[b, 1], pos[b, 2],
                       out_phi, k)
            k += 1
    return k


@inlined
def _phi_in_grid(points, v, a, b, rot, pos, phi, row0, o0, o1, o2, inv, up0, up1, up2, sx, sy, sz):
    """Point v of body a posed into body b's grid (origin o, 1/resolution inv, upper bounds up,
    strides s, first row row0): whether it lies inside, then Φ and its partials per cell width
    (unread when outside) and its world position."""
    w0, w1, w2, x0, x1, x2 = _pose_in_frame(points, v, a, b, rot, pos)
    inside, val, g0, g1, g2 = _phi_at(x0, x1, x2, phi, row0, o0, o1, o2, inv, up0, up1, up2, sx, sy, sz)
    return inside, val, g0, g1, g2, w0, w1, w2


@inlined
def _phi_at(x0, x1, x2, phi, row0, o0, o1, o2, inv, up0, up1, up2, sx, sy, sz):
    """A point x in a grid's frame (grid as ``_phi_in_grid``): whether it lies inside, then Φ and
    its partials per cell width (unread when outside)."""
    u0, u1, u2 = (x0 - o0) * inv, (x1 - o1) * inv, (x2 - o2) * inv
    if not (0.0 <= u0 <= up0 and 0.0 <= u1 <= up1 and 0.0 <= u2 <= up2):
        return False, 0.0, 0.0, 0.0, 0.0
    ix, fx = _cell_inside(u0, up0)
    iy, fy = _cell_inside(u1, up1)
    iz, fz = _cell_inside(u2, up2)
    val, g0, g1, g2 = _trilinear_phi(phi, row0 + ix * sx + iy * sy + iz * sz, sx, sy, fx, fy, fz)
    return True, val, g0, g1, g2


@inlined
def _prefetch_point_cell(points, v, a, b, rot, pos, phi, row0, o0, o1, o2, inv, up0, up1, up2, sx, sy, sz):
    """Prefetch the cell of b's grid that ``_phi_in_grid`` will read for point v (same arguments)."""
    _, _, _, x0, x1, x2 = _pose_in_frame(points, v, a, b, rot, pos)
    u0, u1, u2 = (x0 - o0) * inv, (x1 - o1) * inv, (x2 - o2) * inv
    if 0.0 <= u0 <= up0 and 0.0 <= u1 <= up1 and 0.0 <= u2 <= up2:
        ix, _ = _cell_inside(u0, up0)
        iy, _ = _cell_inside(u1, up1)
        iz, _ = _cell_inside(u2, up2)
        _prefetch_phi_cell(phi, row0 + ix * sx + iy * sy + iz * sz, sx, sy)


def self_collision_rows(problem: Problem, fr: LinkFrames, margin: float) -> Rows:
    """Capsule pairs closer than ``margin``: d + n·(ẋ_a − ẋ_b) rows (n from b to a)."""
    sc = problem.kin.self_collision.distances(fr, within=margin)
    close = np.flatnonzero(sc.dist < margin)
    phi = np.empty((len(close), 12))
    _capsule_rows(sc.point_a, sc.point_b, sc.normal, sc.link_a, sc.link_b, fr.pos, close, phi)
    return Rows(sc.dist[close], np.ones(len(close)), phi, sc.link_a[close], sc.link_b[close])


@numba.njit(cache=True)
def _capsule_rows(point_a, point_b, normal, link_a, link_b, pos, close, out):
    """φ of the capsule pairs ``close``: the distance's rate is n·(ẋ_a − ẋ_b) at the surface
    points (the radii lie along n), φ = (n, (p_a − o_a) × n, −n, −((p_b − o_b) × n)): the
    second cross product negated after it is computed, as the array form had it."""
    for r in range(close.shape[0]):
        k = close[r]
        n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
        a, b = link_a[k], link_b[k]
        u0, u1, u2 = point_a[k, 0] - pos[a, 0], point_a[k, 1] - pos[a, 1], point_a[k, 2] - pos[a, 2]
        v0, v1, v2 = point_b[k, 0] - pos[b, 0], point_b[k, 1] - pos[b, 1], point_b[k, 2] - pos[b, 2]
        out[r, 0], out[r, 1], out[r, 2] = n0, n1, n2
        out[r, 3], out[r, 4], out[r, 5] = u1 * n2 - u2 * n1, u2 * n0 - u0 * n2, u0 * n1 - u1 * n0
        out[r, 6], out[r, 7], out[r, 8] = -n0, -n1, -n2
        out[r, 9], out[r, 10], out[r, 11] = -(v1 * n2 - v2 * n1), -(v2 * n0 - v0 * n2), -(v0 * n1 - v1 * n0)
