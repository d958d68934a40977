"""Contact annotations of a solved frame: per link and channel, the smallest signed distance
and its witness (the reference's ``contact_distance`` / ``contact_witness_c``)."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from retarget.geometry.jit import kernel_pose
from retarget.geometry.kinematics import NUM_LINKS, LinkFrames
from retarget.geometry.voxel_grid import PREFETCH_AHEAD, _cell_axis, _prefetch_phi_cell, _trilinear_phi
from retarget.solver.iterate import SolverState, channel_pose, frames_at
from retarget.solver.probes import _posed_point
from retarget.solver.problem import ChannelTrack, Problem
from retarget.solver.residuals import _to_channel_point
from retarget.solver.rows import candidate_links


@dataclass(frozen=True)
class FrameContacts:
    """Per-link distance to every channel at the solution (ContactAnnotations rows)."""

    distance: np.ndarray  # (L, C) m, clamped to d̄ when far
    witness_c: np.ndarray  # (L, C, 3) channel frame


def frame_contacts(problem: Problem, state: SolverState, t: int) -> FrameContacts:
    """Per link and channel: the smallest signed distance over its probes and hull guard points
    (links whose bounding sphere stays beyond d̄ keep the clamped value d̄)."""
    fr = frames_at(problem, state, state.q)
    band = problem.band_m
    centre_w = np.einsum("lij,lj->li", fr.rot, problem.link_center) + fr.pos
    C = len(problem.channels)
    dist = np.full((NUM_LINKS, C), band)
    wit = np.zeros((NUM_LINKS, C, 3))
    for c, track in enumerate(problem.channels):
        rot_c, pos_c = channel_pose(state, track, t)
        links = np.flatnonzero(candidate_links(problem, track, centre_w, rot_c, pos_c))
        # distances alone find each link's closest point; only those need a witness
        owner, x_c = closest_of_links(problem, fr, track, links, rot_c, pos_c)
        if len(owner) == 0:
            continue
        q = track.channel.query(x_c, normals=False)
        dist[owner, c] = np.minimum(q.d, band)
        wit[owner, c] = q.w
    return FrameContacts(dist, wit)



def closest_of_links(problem: Problem, fr: LinkFrames, track: ChannelTrack, links: np.ndarray, rot_c: np.ndarray,
                     pos_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The links of ``links`` (sorted) with a probe or hull guard point near the channel (within
    its bounds grown by d̄), and each one's closest such point (channel frame): the first of its
    smallest distance min(d, d̄), its probes before its guards. One numba pass with the
    arithmetic of ``ProbeSet.posed_bodies``, ``to_channel_frame``, ``near_channel`` and the
    channel's ``distance``; the grid cells are prefetched."""
    robot, guards, band = problem.robot, problem.guards, float(problem.band_m)
    links = np.asarray(links, np.intp)
    n = int(np.sum(robot.offsets[links + 1] - robot.offsets[links] + guards.offsets[links + 1] - guards.offsets[links]))
    ground = track.is_ground
    grid = None if ground else track.channel.grid
    phi, origin, inv, upper, strides = ((np.zeros(1), np.zeros(3), 0.0, np.zeros(3), np.zeros(3, np.intp)) if ground
                                        else (grid._phi, grid.origin, 1.0 / grid.resolution, grid._upper,
                                              grid._strides))
    owner, x_c, buffer = np.empty(NUM_LINKS, np.intp), np.empty((NUM_LINKS, 3)), np.empty((n, 3))
    k = _closest_of_links(robot.points, robot.offsets, guards.points, guards.offsets, links, fr.rot, fr.pos,
                          kernel_pose(rot_c), kernel_pose(pos_c), ground,
                          np.asarray(track.lower - band, np.float64), np.asarray(track.upper + band, np.float64),
                          band, phi, origin, inv, upper, strides, buffer, np.empty(n, np.intp), owner, x_c)
    return owner[:k], x_c[:k]


@numba.njit(cache=True)
def _closest_of_links(points, offsets, guards, guard_offsets, links, rot, pos, rot_c, pos_c, ground, lower, upper_c,
                      band, phi, origin, inv, upper, strides, buffer, buffer_owner, out_owner, out_x):
    """``closest_of_links``: the near points of every link posed into ``buffer`` first, then read
    in the grid (``PREFETCH_AHEAD`` prefetched) keeping each link's first smallest distance."""
    m = 0
    for link in links:
        for source, off in ((points, offsets), (guards, guard_offsets)):
            for p in range(off[link], off[link + 1]):
                w0, w1, w2 = _posed_point(source, p, link, rot, pos)
                x0, x1, x2 = _to_channel_point(w0, w1, w2, rot_c, pos_c)
                near = (x2 < band if ground else (lower[0] < x0 < upper_c[0] and lower[1] < x1 < upper_c[1]
                                                  and lower[2] < x2 < upper_c[2]))
                if near:
                    buffer[m, 0], buffer[m, 1], buffer[m, 2], buffer_owner[m] = x0, x1, x2, link
                    m += 1
    k = -1
    best = np.inf
    for i in range(m):
        if ground:
            d = min(buffer[i, 2], band)
        else:
            if i + PREFETCH_AHEAD < m:
                j = i + PREFETCH_AHEAD
                ix, _, _ = _cell_axis(buffer[j, 0], origin[0], inv, upper[0])
                iy, _, _ = _cell_axis(buffer[j, 1], origin[1], inv, upper[1])
                iz, _, _ = _cell_axis(buffer[j, 2], origin[2], inv, upper[2])
                _prefetch_phi_cell(phi, ix * strides[0] + iy * strides[1] + iz * strides[2], strides[0], strides[1])
            ix, fx, ok_x = _cell_axis(buffer[i, 0], origin[0], inv, upper[0])
            iy, fy, ok_y = _cell_axis(buffer[i, 1], origin[1], inv, upper[1])
            iz, fz, ok_z = _cell_axis(buffer[i, 2], origin[2], inv, upper[2])
            d, _, _, _ = _trilinear_phi(phi, ix * strides[0] + iy * strides[1] + iz * strides[2], strides[0],
                                        strides[1], fx, fy, fz)
            d = min(d if ok_x and ok_y and ok_z and d < band else band, band)
        if k < 0 or buffer_owner[i] != out_owner[k]:  # the first near point of the next link
            k += 1
            out_owner[k], best = buffer_owner[i], d
            out_x[k, 0], out_x[k, 1], out_x[k, 2] = buffer[i, 0], buffer[i, 1], buffer[i, 2]
        elif d < best:
            best = d
            out_x[k, 0], out_x[k, 1], out_x[k, 2] = buffer[i, 0], buffer[i, 1], buffer[i, 2]
    return k + 1
