"""Contact annotations of a solved frame: per link and channel, the smallest signed distance
and its witness (the reference's ``contact_distance`` / ``contact_witness_c``)."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from retarget.iterate import SolverState, channel_pose, frames_at
from retarget.kinematics import NUM_LINKS
from retarget.problem import Problem
from retarget.residuals import to_channel_frame
from retarget.rows import candidate_links
from retarget.targets import near_channel


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
        pidx, p_w = problem.robot.posed_bodies(links, fr.rot, fr.pos)
        gidx, g_w = problem.guards.posed_bodies(links, fr.rot, fr.pos)
        link = np.concatenate([problem.robot.body[pidx], problem.guards.body[gidx]])
        x_c = to_channel_frame(np.concatenate([p_w, g_w]), rot_c, pos_c)
        idx = np.flatnonzero(near_channel(track, x_c, band))
        if len(idx) == 0:
            continue
        # distances alone find each link's closest point; only those need a witness
        d = np.minimum(track.channel.distance(np.take(x_c, idx, axis=0))[0], band)
        owner = link[idx]
        first = closest_per_owner(d, owner, NUM_LINKS)
        q = track.channel.query(np.take(x_c, idx[first], axis=0), normals=False)
        dist[owner[first], c] = np.minimum(q.d, band)
        wit[owner[first], c] = q.w
    return FrameContacts(dist, wit)



def closest_per_owner(d: np.ndarray, owner: np.ndarray, n_owners: int) -> np.ndarray:
    """Per owner present, in ascending owner order, the index of its smallest ``d`` (the first
    of equal ones): the first entry per owner of ``np.lexsort((d, owner))``, without the sort."""
    best = np.full(n_owners, -1, np.intp)
    _closest_per_owner(np.asarray(d, np.float64), np.asarray(owner, np.intp), best)
    return best[best >= 0]


@numba.njit(cache=True)
def _closest_per_owner(d, owner, best):
    for i in range(d.shape[0]):
        o = owner[i]
        if best[o] < 0 or d[i] < d[best[o]]:
            best[o] = i
