"""Demonstrated quantities of one frame (paper Sec. III-B): the desired proximity triples of
every robot probe, read through its OT source point src(p) on the human, and of every free
object's probes, plus the frame's style targets. Computed once per frame, before its SQP
iterations, and read by every iterate."""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np

from retarget.geometry.kinematics import NUM_LINKS
from retarget.solver.problem import ChannelTrack, Problem
from retarget.solver.residuals import Triples, to_channel_frame
from retarget.solver.stance import StanceTargets


@dataclass(frozen=True)
class FrameTargets:
    """Demonstrated quantities of frame t, computed once before its SQP iterations."""

    t: int
    robot: tuple[Triples, ...]  # per channel, for every robot probe (d̂ = d̄ when far)
    robot_active: tuple[np.ndarray, ...]  # per channel (P,) bool: d̂ < d̄
    robot_links: tuple[np.ndarray, ...]  # per channel (L,) bool: links with an active probe
    robot_link_d: tuple[np.ndarray, ...]  # per channel (L,) m: each link's smallest d̂ (d̄ when far)
    unit_d: tuple[np.ndarray, ...]  # per channel (U,) m: each contact unit's demonstrated gap (d̄ when far)
    objects: tuple[tuple[Triples | None, ...], ...]  # per free object, per channel (None: own channel)
    objects_active: tuple[tuple[np.ndarray | None, ...], ...]
    obj_pos: np.ndarray  # (O, 3) demonstrated object poses
    obj_rot: np.ndarray  # (O, 3, 3)
    style_pos: np.ndarray  # (S + O, 3) style targets of ``Problem.style_bodies``
    style_rot: np.ndarray  # (S + O, 3, 3)
    #: planted-foot targets; they depend on the previous frame's solution, so the solver sets them
    stance: StanceTargets = field(default_factory=StanceTargets.empty)
    com: np.ndarray | None = None  # (3,) m, world: the COM target of a ballistic pass (``retarget.solver.flight``)


def near_channel(track: ChannelTrack, x_c: np.ndarray, reach: float) -> np.ndarray:
    """Points (channel frame) inside the channel's bounds grown by ``reach``."""
    if track.is_ground:
        return x_c[:, 2] < reach
    out = np.empty(len(x_c), dtype=bool)
    _inside_box(np.ascontiguousarray(x_c, np.float64), np.asarray(track.lower - reach, np.float64),
                np.asarray(track.upper + reach, np.float64), out)
    return out


@numba.njit(cache=True)
def _inside_box(x, lower, upper, out):
    """out[i] ← lower < x[i] < upper on every axis (strict, as the array form)."""
    for i in range(x.shape[0]):
        out[i] = (lower[0] < x[i, 0] < upper[0]) and (lower[1] < x[i, 1] < upper[1]) and (lower[2] < x[i, 2] < upper[2])


def _far_triples(n: int, band: float) -> Triples:
    return Triples(np.full(n, band), np.zeros((n, 3)), np.zeros((n, 3)))


def _demo_triples(track: ChannelTrack, x_w: np.ndarray, rot: np.ndarray, pos: np.ndarray,
                  band: float) -> tuple[Triples, np.ndarray]:
    """Triples of demonstrated points against a channel; only points near it are queried."""
    x_c = to_channel_frame(x_w, rot, pos)
    out = _far_triples(len(x_w), band)
    if track.substitution is not None:
        # measured on the captured surface, ŵ carried onto the substitute (retarget.solver.substitute)
        near, d, w, n = track.substitution.demonstrated_triples(x_c, band)
    else:
        near = np.flatnonzero(near_channel(track, x_c, band))
        if len(near):
            # once per frame: the exact witness where the grid's blend is unreliable (geometry doc)
            q = track.channel.query(x_c[near], exact_witness=True)
            d, w, n = q.d, q.w, q.n
    if len(near):
        out.d[near], out.w[near], out.n[near] = d, w, n
        # ŵ's place in the geodesic table, for the r^x rows of every iterate of the frame
        hat = track.channel.geodesic_weights(w)
        if hat is not None:
            geodesic = tuple(np.zeros((len(x_w),) + h.shape[1:], h.dtype) for h in hat)
            for full, part in zip(geodesic, hat):
                full[near] = part
            out = Triples(out.d, out.w, out.n, geodesic)
    return out, out.d < band


def unit_gaps(problem: Problem, track: ChannelTrack, surface_w: np.ndarray, rot: np.ndarray, pos: np.ndarray,
              band: float) -> np.ndarray:
    """(U,) m: per contact unit, the smallest distance of its parts' surface (``surface_w``,
    world) to the channel (d̄ when farther), on the captured object where it is substituted.

    This is the gap the evaluation scores a unit's contact by. The OT sources of a unit's
    probes sample its parts too sparsely for it: on OMOMO's table the person's forearm comes
    within 19 mm of the top where its sources stay at 28 mm, so the forearm was held off as
    "not touching" and object recall lost 66 frames."""
    gap = np.full(problem.num_surface_units, band)
    near, d = surface_distances(track, to_channel_frame(surface_w, rot, pos), band)
    if len(near):
        np.minimum.at(gap, problem.unit_of_vertex[near], d)
    return gap


def surface_distances(track: ChannelTrack, x_c: np.ndarray, band: float) -> tuple[np.ndarray, np.ndarray]:
    """(indices of the points ``x_c`` (N, 3, channel frame) within the channel's bounds grown by
    ``band``, their distances to the channel (m)): the demonstrated surface's distances, so on
    the captured object where it is substituted. Every other point is farther than ``band``."""
    if track.substitution is not None:
        channel = track.substitution.demonstrated
        lo, hi = channel.mesh.bounds
        near = np.flatnonzero(np.all((x_c > lo - band) & (x_c < hi + band), axis=1))
    else:
        channel = track.channel
        near = np.flatnonzero(near_channel(track, x_c, band))
    return near, (channel.distance(x_c[near])[0] if len(near) else np.zeros(0))


def frame_targets(problem: Problem, t: int) -> FrameTargets:
    """Demonstrated triples of robot probes (through src(p)) and object probes at frame t."""
    band = problem.band_m
    human_w = problem.demo_points.posed(problem.part_rot_w[t], problem.part_pos_w[t])
    surface_w = problem.unit_surface.posed(problem.part_rot_w[t], problem.part_pos_w[t])
    robot_t, robot_a, robot_l, robot_ld, unit_d = [], [], [], [], []
    for track in problem.channels:
        tri, active = _demo_triples(track, human_w, track.rot_w[t], track.pos_w[t], band)
        robot_t.append(tri)
        robot_a.append(active)
        robot_l.append(np.bincount(problem.robot.body[active], minlength=NUM_LINKS) > 0)
        link_d = np.full(NUM_LINKS, band)
        np.minimum.at(link_d, problem.robot.body, tri.d)
        robot_ld.append(link_d)
        unit_d.append(unit_gaps(problem, track, surface_w, track.rot_w[t], track.pos_w[t], band))
    obj_t, obj_a = [], []
    for obj in problem.objects:
        own = problem.channels[obj.channel]
        x_w = obj.demonstrated_probes @ own.rot_w[t].T + own.pos_w[t]
        per_t, per_a = [], []
        for c, track in enumerate(problem.channels):
            if c == obj.channel:
                per_t.append(None)
                per_a.append(None)
                continue
            tri, active = _demo_triples(track, x_w, track.rot_w[t], track.pos_w[t], band)
            per_t.append(tri)
            per_a.append(active)
        obj_t.append(tuple(per_t))
        obj_a.append(tuple(per_a))
    obj_pos = np.array([problem.channels[o.channel].pos_w[t] for o in problem.objects]).reshape(-1, 3)
    obj_rot = np.array([problem.channels[o.channel].rot_w[t] for o in problem.objects]).reshape(-1, 3, 3)
    return FrameTargets(t, tuple(robot_t), tuple(robot_a), tuple(robot_l), tuple(robot_ld), tuple(unit_d),
                        tuple(obj_t), tuple(obj_a),
                        obj_pos, obj_rot, np.concatenate([problem.style.pos_w[t], obj_pos]),
                        np.concatenate([problem.style.rot_w[t], obj_rot]),
                        com=None if problem.com_target is None else problem.com_target[t])
