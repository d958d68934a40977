"""Non-penetration rows of free objects against the robot's links (eq. m-qp-col): the object's
guard points (hull, edges) and the deepest surface point per cluster, each read in the
distance grid of every link whose bounding sphere it reaches."""

from __future__ import annotations

import numba
import numpy as np

from retarget.geometry.jit import helper, inlined, kernel_pose
from retarget.geometry.kinematics import LinkFrames
from retarget.geometry.voxel_grid import PREFETCH_AHEAD, _cell_of, _prefetch_phi_cell, _trilinear_phi
from retarget.solver.probes import _in_frame
from retarget.solver.problem import ChannelTrack, Problem
from retarget.solver.residuals import Rows, _twist_row


def object_guard_rows(problem: Problem, fr: LinkFrames, centre_w: np.ndarray, links: np.ndarray,
                      track: ChannelTrack, rot_c: np.ndarray, pos_c: np.ndarray, reach: float) -> Rows:
    """Distances of an object's guard points (corners, edge points) to every robot link of
    ``links`` (links with a distance grid) closer than ``reach``, from each link's own grid
    (link frame), in one stacked query; ``centre_w`` (L, 3) the links' bounding-sphere centres.

    A box edge pressed into an arm lies between the arm's probes; seen from the arm's distance
    field it is the deepest point. Rows, grouped by link: body A the object (FIXED when
    pinned), body B the link.
    """
    g_w = track.guards @ rot_c.T + pos_c
    pair_link, guard = _spheres_reach(np.ascontiguousarray(centre_w[links]), problem.link_radius[links], g_w, reach)
    if len(guard) == 0:
        return Rows.empty()
    grids = problem.link_grids
    value, phi, link = np.empty(len(guard)), np.empty((len(guard), 12)), np.empty(len(guard), np.intp)
    k = _object_guard_rows_into(links[pair_link], guard, g_w, fr.rot, fr.pos, grids.phi.ravel(), grids.origin,
                                grids.inv_resolution, grids.upper, grids.strides, grids.offset, float(reach),
                                problem.surface_margin, kernel_pose(pos_c), value, phi, link)
    return Rows(value[:k], np.ones(k), phi[:k], np.full(k, track.body), link[:k])


@numba.njit(cache=True)
def _object_guard_rows_into(link, guard, g_w, rot, pos, phi, origin, inv_resolution, upper, strides, offset, reach,
                            surface_margin, pos_c, out_value, out_phi, out_link):
    """The rows of ``object_guard_rows`` (returns their count): guard point guard[q] (world
    ``g_w``) in the frame of link[q], Rᵀ(x − o) summed as numpy's einsum sums it (left to right),
    its distance in the link's grid, and the row where it lies inside closer than ``reach``."""
    k = np.int64(0)  # not a literal 0: the callees it is passed to would compile twice
    for q in range(guard.shape[0]):
        if q + PREFETCH_AHEAD < guard.shape[0]:
            g = guard[q + PREFETCH_AHEAD]
            _prefetch_link_cell(g_w[g, 0], g_w[g, 1], g_w[g, 2], link[q + PREFETCH_AHEAD], rot, pos, phi, origin,
                                inv_resolution, upper, strides, offset)
        b, g = link[q], guard[q]
        val, g0, g1, g2, inside = _link_grid_distance(g_w[g, 0], g_w[g, 1], g_w[g, 2], b, rot, pos, phi, origin,
                                                      inv_resolution, upper, strides, offset)
        if inside and val < reach:
            _object_link_row(val, g0, g1, g2, g_w[g, 0], g_w[g, 1], g_w[g, 2], b, rot, pos, pos_c, surface_margin,
                             out_value, out_phi, out_link, k)
            k += 1
    return k


@inlined
def _link_grid_distance(w0, w1, w2, b, rot, pos, phi, origin, inv_resolution, upper, strides, offset):
    """A world point in link b's frame (``_in_frame``) and ``GridStack.distance`` there: Φ, its
    gradient (zero outside the grid) and whether it lies inside (outside, Φ of the cell of its
    projection, as the array form)."""
    x0, x1, x2 = _in_frame(w0, w1, w2, b, rot, pos)
    r, fx, fy, fz, inside = _cell_of(x0, x1, x2, b, origin, inv_resolution, upper, strides, offset)
    val, g0, g1, g2 = _trilinear_phi(phi, r, strides[b, 0], strides[b, 1], fx, fy, fz)
    scale = inv_resolution[b] * inside
    return val, g0 * scale, g1 * scale, g2 * scale, inside


@helper
def _object_link_row(val, g0, g1, g2, w0, w1, w2, b, rot, pos, pos_c, surface_margin, out_value, out_phi, out_link,
                     k):
    """Row k: Φ − m_b ≥ 0 of an object point (world w) at link b's distance Φ with gradient g
    (link frame): body A the object (origin ``pos_c``), body B the link; R_b g summed as numpy's
    einsum sums three contiguous terms ((x + z) + y)."""
    a0 = (rot[b, 0, 0] * g0 + rot[b, 0, 2] * g2) + rot[b, 0, 1] * g1
    a1 = (rot[b, 1, 0] * g0 + rot[b, 1, 2] * g2) + rot[b, 1, 1] * g1
    a2 = (rot[b, 2, 0] * g0 + rot[b, 2, 2] * g2) + rot[b, 2, 1] * g1
    out_value[k] = val - surface_margin[b]
    out_link[k] = b
    _twist_row(a0, a1, a2, w0, w1, w2, pos_c[0], pos_c[1], pos_c[2], pos[b, 0], pos[b, 1], pos[b, 2], out_phi, k)


def _spheres_reach(centre: np.ndarray, radius: np.ndarray, x: np.ndarray,
                   reach: float) -> tuple[np.ndarray, np.ndarray]:
    """(sphere, point) index pairs, sphere-major as ``np.nonzero``, of the points x (G, 3) whose
    distance to a sphere (centre (l, 3), radius (l,)) is below ``reach``: ‖c − x‖ − r < reach."""
    out_s, out_p = np.empty(len(centre) * len(x), np.intp), np.empty(len(centre) * len(x), np.intp)
    k = _spheres_reach_into(centre, radius, np.ascontiguousarray(x, np.float64), float(reach), out_s, out_p)
    return out_s[:k], out_p[:k]


@numba.njit(cache=True)
def _spheres_reach_into(centre, radius, x, reach, out_s, out_p):
    k = 0
    for s in range(centre.shape[0]):
        for p in range(x.shape[0]):
            d0, d1, d2 = centre[s, 0] - x[p, 0], centre[s, 1] - x[p, 1], centre[s, 2] - x[p, 2]
            if np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) - radius[s] < reach:
                out_s[k], out_p[k] = s, p
                k += 1
    return k


def object_surface_rows(problem: Problem, fr: LinkFrames, centre_w: np.ndarray, links: np.ndarray,
                        track: ChannelTrack, rot_c: np.ndarray, pos_c: np.ndarray, reach: float) -> Rows:
    """The deepest of each cluster of the object's surface points (``ChannelTrack.surface_guards``)
    against every link of ``links`` it comes within ``reach`` of, from the link's distance grid
    (arguments as ``object_guard_rows``).

    Where the object's flat face meets a hollow of a link (a wrist's inner side, a palm) neither
    the link's vertices nor the object's hull guards are the deepest point: a face point is. One
    row per cluster and link, at its deepest point, keeps every point of the cluster out at the
    iterate: one row per 4 cm² of touching face instead of 16. Rows as ``object_guard_rows``.
    """
    sg = track.surface_guards
    if sg is None or len(links) == 0:
        return Rows.empty()
    cl, grids = sg.clusters, problem.link_grids
    pair, pair_cl = sg.clusters_near((centre_w[links] - pos_c) @ rot_c, problem.link_radius[links] + reach)
    if len(pair_cl) == 0:
        return Rows.empty()
    grids = problem.link_grids
    n = len(pair_cl)
    value, phi, link = np.empty(n), np.empty((n, 12)), np.empty(n, np.intp)
    k = _object_surface_rows_into(links[pair], pair_cl, cl.centre, cl.radius, cl.offsets, sg.points,
                                  kernel_pose(rot_c), kernel_pose(pos_c), fr.rot,
                                  fr.pos, grids.phi.ravel(), grids.origin, grids.inv_resolution, grids.upper,
                                  grids.strides, grids.offset, float(reach), problem.surface_margin, value, phi, link)
    return Rows(value[:k], np.ones(k), phi[:k], np.full(k, track.body), link[:k])


@numba.njit(cache=True)
def _object_surface_rows_into(link, cluster, centre, radius, offsets, points, rot_c, pos_c, rot, pos, phi, origin,
                              inv_resolution, upper, strides, offset, reach, surface_margin, out_value, out_phi,
                              out_link):
    """The rows of ``object_surface_rows`` (returns their count): per (link, cluster) pair, the
    cluster's centre in the link's grid with Φ − radius < reach, then its deepest point (the
    first smallest Φ among the points inside the grid) if closer than ``reach``. Points are
    posed as ``posed_in_frames`` poses them (the object a body at (``rot_c``, ``pos_c``))."""
    k = np.int64(0)  # not a literal 0: the callees it is passed to would compile twice
    for q in range(cluster.shape[0]):
        if q + PREFETCH_AHEAD < cluster.shape[0]:
            p0, p1, p2 = _object_point(centre, cluster[q + PREFETCH_AHEAD], rot_c, pos_c)
            _prefetch_link_cell(p0, p1, p2, link[q + PREFETCH_AHEAD], rot, pos, phi, origin, inv_resolution, upper,
                                strides, offset)
        b, c = link[q], cluster[q]
        w0, w1, w2 = _object_point(centre, c, rot_c, pos_c)
        val, _, _, _, inside = _link_grid_distance(w0, w1, w2, b, rot, pos, phi, origin, inv_resolution, upper,
                                                   strides, offset)
        if not (inside and val - radius[c] < reach):
            continue
        best_key = np.inf
        start, end = offsets[c], offsets[c + 1]
        for v in range(start, end):
            if v + PREFETCH_AHEAD < end:
                p0, p1, p2 = _object_point(points, v + PREFETCH_AHEAD, rot_c, pos_c)
                _prefetch_link_cell(p0, p1, p2, b, rot, pos, phi, origin, inv_resolution, upper, strides, offset)
            p0, p1, p2 = _object_point(points, v, rot_c, pos_c)
            d, g0, g1, g2, inside = _link_grid_distance(p0, p1, p2, b, rot, pos, phi, origin, inv_resolution, upper,
                                                        strides, offset)
            key = d if inside else np.inf
            if v == start or key < best_key:
                best_key, best = key, (d, g0, g1, g2, p0, p1, p2)
        d, g0, g1, g2, p0, p1, p2 = best
        if d < reach:
            _object_link_row(d, g0, g1, g2, p0, p1, p2, b, rot, pos, pos_c, surface_margin, out_value, out_phi,
                             out_link, k)
            k += 1
    return k


@inlined
def _object_point(points, i, rot_c, pos_c):
    """Object-frame point i in the world, as ``posed_in_frames`` poses it."""
    return (rot_c[0, 0] * points[i, 0] + rot_c[0, 1] * points[i, 1] + rot_c[0, 2] * points[i, 2] + pos_c[0],
            rot_c[1, 0] * points[i, 0] + rot_c[1, 1] * points[i, 1] + rot_c[1, 2] * points[i, 2] + pos_c[1],
            rot_c[2, 0] * points[i, 0] + rot_c[2, 1] * points[i, 1] + rot_c[2, 2] * points[i, 2] + pos_c[2])


@inlined
def _prefetch_link_cell(w0, w1, w2, b, rot, pos, phi, origin, inv_resolution, upper, strides, offset):
    """Prefetch the cell of link b's grid that ``_link_grid_distance`` will read for world point w."""
    x0, x1, x2 = _in_frame(w0, w1, w2, b, rot, pos)
    r, _, _, _, _ = _cell_of(x0, x1, x2, b, origin, inv_resolution, upper, strides, offset)
    _prefetch_phi_cell(phi, r, strides[b, 0], strides[b, 1])
