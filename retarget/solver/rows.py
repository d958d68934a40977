"""Residual and constraint rows of the QP at one iterate (the linearisation, eq. m-qp).

Every row is a pair of 6-vectors φ on the two bodies it involves (``retarget.solver.residuals.Rows``).
Cost rows: interaction residuals of robot probes and object probes against every channel
(eq. m-energy), the contact-state rows and the style rows (eq. m-esty-o). Constraint rows:
non-penetration of probes and of hull and vertex guards against every channel (here); object
guard points against the links' own distance grids (``retarget.solver.object_rows``); capsule and
visual-mesh self-collision (``retarget.solver.self_rows``, eq. m-qp-col).

Hot-path economy: links are culled per channel by bounding spheres before any probe is posed,
probes are posed with one matrix product per link, and the constraint rows that seed a QP are
the extreme points of the rows closer than a margin (``retarget.solver.seed_rows``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np

from otr_gym import robot
from retarget.geometry.centre_of_mass import com_residual
from retarget.geometry.channels import ProximityQuery, SDFChannel
from retarget.geometry.jit import kernel_pose
from retarget.geometry.kinematics import NUM_LINKS, LinkFrames
from retarget.geometry.voxel_grid import _cell_inside, _trilinear_phi
from retarget.solver.iterate import SectionTimer, SolverState, channel_pose, frames_at
from retarget.solver.object_rows import object_guard_rows, object_surface_rows
from retarget.solver.probes import ProbeSet, _posed_point
from retarget.solver.problem import ChannelTrack, Problem
from retarget.solver.residuals import (
    FIXED,
    PairSet,
    Rows,
    Triples,
    _to_channel_point,
    _to_world_direction,
    _twist_row,
    far_field,
    interaction_rows,
    signed_distance_rows,
    to_channel_frame,
    twist_factors,
)
from retarget.solver.seed_rows import initial_constraints
from retarget.solver.self_rows import self_collision_rows, self_mesh_rows
from retarget.solver.stance import stance_rows
from retarget.solver.style import pose_rows
from retarget.solver.targets import FrameTargets, near_channel


@dataclass(frozen=True)
class Linearisation:
    cost: Rows
    constraints: Rows  # every surface pair in the band, then the close capsule pairs
    surface_channel: np.ndarray  # (S,) channel code of the surface rows (``initial_constraints``)
    margin: float  # m: surface rows closer than this may seed the first QP
    frames: LinkFrames
    active_pairs: int
    min_distance: float
    min_self_distance: float
    counts: np.ndarray  # (L + O,) active probes per link and object at this iterate (N_ℓ)
    contact: ContactSelection  # the contact-state rows in use
    #: com(q) − c*_t (3,) m and its Jacobian (3, nv) when the frame has a COM target
    #: (``retarget.solver.flight``), else None
    com: tuple[np.ndarray, np.ndarray] | None = None
    #: contact-state rows in their demonstrated state (no cost here) and the side each keeps
    #: (+1: r ≥ 0, −1: r ≤ 0): ``qp.qp_step`` prices the ones a step would cross
    hinge: Rows | None = None
    hinge_side: np.ndarray | None = None

    @cached_property
    def initial(self) -> np.ndarray:
        """Indices of ``constraints`` put in the first QP: the surface rows chosen by
        :func:`initial_constraints`, then every capsule row. Computed on first use: a trial
        iterate that the trust-region test rejects never needs it."""
        k = len(self.surface_channel)
        c = self.constraints
        surface = Rows(c.value[:k], c.weight[:k], c.phi[:k], c.body_a[:k], c.body_b[:k])
        return np.concatenate([initial_constraints(surface, self.surface_channel, self.margin),
                               np.arange(k, len(c))])


def candidate_links(problem: Problem, track: ChannelTrack, centre_w: np.ndarray, rot_c: np.ndarray,
                     pos_c: np.ndarray) -> np.ndarray:
    """(L,) links whose bounding sphere comes within the band of the channel's bounds."""
    if track.is_ground:
        gap = centre_w[:, 2]
    else:
        c = to_channel_frame(centre_w, rot_c, pos_c)
        gap = np.linalg.norm(np.maximum(0.0, np.maximum(track.lower - c, c - track.upper)), axis=1)
    return gap - problem.link_radius < problem.band_m


def rows_take(rows: Rows, index: np.ndarray) -> Rows:
    return Rows(rows.value.take(index), rows.weight.take(index), rows.phi.take(index, axis=0),
                rows.body_a.take(index), rows.body_b.take(index))


def _distance_block(track: ChannelTrack, rot_c: np.ndarray, pos_c: np.ndarray, x_w: np.ndarray, x_c: np.ndarray,
                    body: np.ndarray, origin: np.ndarray, d: np.ndarray, grad_c: np.ndarray,
                    clearance: np.ndarray | float = 0.0) -> Rows:
    """Non-penetration rows of points against a channel: the grid distance minus the grid's
    measured error bound there (``retarget.geometry.margins``), so that the exact surface is respected,
    minus ``clearance`` (m): for robot points, how far Unitree's original surface may lie
    beyond the shipped mesh (``Problem.surface_margin``)."""
    value = d - track.margin.at(x_c) if track.margin is not None else d
    return signed_distance_rows(value - clearance, grad_c, x_w, origin, body, track.body, rot_c, pos_c)


@dataclass
class _ConstraintRows:
    """Constraint rows collected per block, each with its channel code (``initial_constraints``)."""

    rows: list[Rows]
    channel: list[np.ndarray]

    def add(self, rows: Rows, channel: int) -> None:
        self.rows.append(rows)
        self.channel.append(np.full(len(rows), channel))


@dataclass(frozen=True)
class _RobotPairs:
    """Active robot probe–channel pairs of one channel at the iterate."""

    channel: int
    rot_c: np.ndarray
    pos_c: np.ndarray
    probes: np.ndarray  # (k,) indices into ``Problem.robot``
    x_w: np.ndarray  # (k, 3)
    x_c: np.ndarray  # (k, 3)
    query: ProximityQuery
    desired: Triples  # the demonstrated triples of ``probes``


def _robot_channel(problem: Problem, state: SolverState, targets: FrameTargets, fr: LinkFrames,
                   centre_w: np.ndarray, c: int, con: _ConstraintRows) -> tuple[_RobotPairs | None, np.ndarray]:
    """Robot probes against channel c: the active pairs (cost), their non-penetration rows and
    those of the hull/vertex guards that can come within the margin. Returns the pairs and each
    link's smallest probe distance (the band where not queried)."""
    band, margin, check = problem.band_m, problem.solver.constraint_margin_m, problem.solver.check_margin_m
    track = problem.channels[c]
    rot_c, pos_c = channel_pose(state, track, targets.t)
    near_links = candidate_links(problem, track, centre_w, rot_c, pos_c)
    # area probes: near links, and links with a probe in contact range in the demonstration
    links = np.flatnonzero(near_links | targets.robot_links[c])
    # distance of every area probe, or a lower bound (the band) where not queried
    probe_d = np.full(len(problem.robot), band)
    pairs = None
    probes = _probes_near(problem.robot, links, fr, track, rot_c, pos_c, band, targets.robot_active[c])
    if probes is not None:
        sel, x_w, x_c = probes
        q = track.channel.query(x_c, normals=False)
        probe_d[sel] = q.d
        active = np.flatnonzero(q.in_band | targets.robot_active[c][sel])
        # Beyond the grid's band a pair active in the demonstration reads d = band with no
        # gradient: the distance to its demonstrated witness pulls it in instead (``far_field``),
        # for the interaction and the contact-state rows alike. Without it the G1's pelvis and
        # right knee stayed 19–22 cm from the chair the person leans on (a hold row with a zero
        # Jacobian never moves them).
        x_a = x_c.take(active, axis=0)
        desired = targets.robot[c].take(sel[active])
        pairs = _RobotPairs(c, rot_c, pos_c, sel[active], x_w.take(active, axis=0), x_a,
                            far_field(q, active, x_a, desired, track.is_ground), desired)
        # Against the ground the hull vertices (guards) imply every area probe: skip those.
        if not track.is_ground:
            ib = np.flatnonzero(q.in_band & (q.d < check))
            body = problem.robot.body[sel[ib]]
            con.add(_distance_block(track, rot_c, pos_c, x_w.take(ib, axis=0), x_c.take(ib, axis=0), body,
                                    fr.pos.take(body, axis=0), q.d[ib], q.grad_d.take(ib, axis=0),
                                    problem.surface_margin.take(body)), c)
    link_min = np.minimum.reduceat(probe_d, problem.robot.offsets[:-1])
    # Guard points: the distance field is 1-Lipschitz, so a guard is at least as far as its
    # nearest area probe (its anchor) minus their separation; only guards whose bound is
    # within the margin can be close enough to matter, the rest are provably clear. A link
    # whose closest probe, less its farthest anchor separation, is beyond the margin has
    # no such guard: its guards are not even looked at.
    guards, anchor, anchor_d, reach = ((problem.guards, problem.guard_anchor, problem.guard_anchor_d,
                                        problem.guard_reach) if track.is_ground
                                       else (problem.vertex_guards, problem.vertex_anchor, problem.vertex_anchor_d,
                                             problem.vertex_reach))
    gi = _guards_within(guards.offsets, np.flatnonzero(near_links & (link_min - reach < margin)), anchor, anchor_d,
                        probe_d, margin)
    if len(gi):
        con.add(_guard_rows(problem, fr, track, rot_c, pos_c, guards, gi, check), c)
    return pairs, link_min


def _probes_near(probes: ProbeSet, links: np.ndarray, fr: LinkFrames, track: ChannelTrack, rot_c: np.ndarray,
                 pos_c: np.ndarray, reach: float,
                 demo_active: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The probes of ``links`` (sorted) within the channel's bounds grown by ``reach``, or active
    in the demonstration (``demo_active`` (P,)): their indices, world and channel-frame positions,
    in order, by one numba pass with the arithmetic of ``ProbeSet.posed_bodies``,
    ``to_channel_frame`` and ``near_channel``. None when the links carry no probe."""
    n = int(np.sum(probes.offsets[links + 1] - probes.offsets[links]))
    if n == 0:
        return None
    index, x_w, x_c = np.empty(n, np.intp), np.empty((n, 3)), np.empty((n, 3))
    k = _probes_near_into(probes.points, probes.offsets, np.asarray(links, np.intp), fr.rot, fr.pos,
                          kernel_pose(rot_c), kernel_pose(pos_c), track.is_ground,
                          np.asarray(track.lower - reach, np.float64), np.asarray(track.upper + reach, np.float64),
                          float(reach), demo_active, index, x_w, x_c)
    return index[:k], x_w[:k], x_c[:k]


@numba.njit(cache=True)
def _probes_near_into(points, offsets, links, rot, pos, rot_c, pos_c, ground, lower, upper, reach, demo_active,
                      out_index, out_w, out_c):
    k = 0
    for link in links:
        for p in range(offsets[link], offsets[link + 1]):
            w0, w1, w2 = _posed_point(points, p, link, rot, pos)
            x0, x1, x2 = _to_channel_point(w0, w1, w2, rot_c, pos_c)
            near = (x2 < reach if ground else (lower[0] < x0 < upper[0] and lower[1] < x1 < upper[1]
                                               and lower[2] < x2 < upper[2]))
            if near or demo_active[p]:
                out_index[k] = p
                out_w[k, 0], out_w[k, 1], out_w[k, 2] = w0, w1, w2
                out_c[k, 0], out_c[k, 1], out_c[k, 2] = x0, x1, x2
                k += 1
    return k


def _guard_rows(problem: Problem, fr: LinkFrames, track: ChannelTrack, rot_c: np.ndarray, pos_c: np.ndarray,
                guards: ProbeSet, index: np.ndarray, check: float) -> Rows:
    """Non-penetration rows (``_distance_block``, clearance ``Problem.surface_margin``) of the
    robot guard points ``index`` closer than ``check`` to the channel: one numba pass that poses
    each point, reads the channel's distance and writes the row, for the ground and for grid
    channels; the same bits as the array form (kept for other channels)."""
    channel = track.channel
    if not (track.is_ground or isinstance(channel, SDFChannel)):
        gb = guards.body[index]
        g_w = guards.posed_index(index, fr.rot, fr.pos)
        g_c = to_channel_frame(g_w, rot_c, pos_c)
        d, grad, in_band = channel.distance(g_c)
        ib = np.flatnonzero(in_band & (d < check))
        body = gb[ib]
        return _distance_block(track, rot_c, pos_c, g_w.take(ib, axis=0), g_c.take(ib, axis=0), body,
                               fr.pos.take(body, axis=0), d[ib], grad.take(ib, axis=0),
                               problem.surface_margin.take(body))
    n = len(index)
    value, phi, body, x_w, grad_c = (np.empty(n), np.empty((n, 12)), np.empty(n, np.intp), np.empty((n, 3)),
                                     np.empty((n, 3)))
    if track.is_ground:
        grid, band = None, float(channel.band_m)
        phi_nodes, origin, inv, upper, strides = np.zeros(1), np.zeros(3), 0.0, np.zeros(3), np.zeros(3, np.intp)
    else:
        grid, band = channel.grid, float(channel.band_m)
        phi_nodes, origin, inv, upper, strides = (grid._phi, grid.origin, 1.0 / grid.resolution, grid._upper,
                                                  grid._strides)
    margin = track.margin
    m_origin, m_res, m_cells, m_values = ((margin.origin, float(margin.resolution), np.array(margin.cells, np.intp),
                                           margin.values) if margin is not None
                                          else (np.zeros(3), 1.0, np.zeros(3, np.intp), np.zeros(1)))
    moving = track.body != FIXED
    k = _guard_rows_into(guards.points, guards.body, np.asarray(index, np.intp), fr.rot, fr.pos,
                         kernel_pose(rot_c), kernel_pose(pos_c), grid is None, phi_nodes, origin,
                         inv, upper, strides, band, float(check), margin is not None,
                         m_origin, m_res, m_cells, m_values, problem.surface_margin, moving,
                         value, phi, body, x_w, grad_c)
    if k == 1:  # numpy turns a single row with another BLAS kernel (matrix-vector): as it does
        phi[:1] = twist_factors(grad_c[:1] @ rot_c.T, x_w[:1], fr.pos[body[:1]], pos_c if moving else None)
    return Rows(value[:k], np.ones(k), phi[:k], body[:k], np.full(k, track.body, dtype=np.intp))


@numba.njit(cache=True)
def _guard_rows_into(points, point_body, index, rot, pos, rot_c, pos_c, ground, phi_nodes, origin, inv, upper, strides,
                     band, check, with_margin, m_origin, m_res, m_cells, m_values, surface_margin, moving,
                     out_value, out_phi, out_body, out_x, out_grad):
    """Rows of ``_guard_rows`` (returns their count): per point, the arithmetic of
    ``ProbeSet.posed_index``, ``to_channel_frame``, ``SDFChannel.distance`` (or the ground's z),
    ``ErrorMargin.at``, ``signed_distance_rows``."""
    k = np.int64(0)  # not a literal 0: the callees it is passed to would compile twice
    for m in range(index.shape[0]):
        p = index[m]
        b = point_body[p]
        w0 = rot[b, 0, 0] * points[p, 0] + rot[b, 0, 1] * points[p, 1] + rot[b, 0, 2] * points[p, 2] + pos[b, 0]
        w1 = rot[b, 1, 0] * points[p, 0] + rot[b, 1, 1] * points[p, 1] + rot[b, 1, 2] * points[p, 2] + pos[b, 1]
        w2 = rot[b, 2, 0] * points[p, 0] + rot[b, 2, 1] * points[p, 1] + rot[b, 2, 2] * points[p, 2] + pos[b, 2]
        x0, x1, x2 = _to_channel_point(w0, w1, w2, rot_c, pos_c)
        if ground:
            d, g0, g1, g2 = x2, 0.0, 0.0, 1.0
            if not (d < band and d < check):
                continue
        else:
            u0, u1, u2 = (x0 - origin[0]) * inv, (x1 - origin[1]) * inv, (x2 - origin[2]) * inv
            if not (0.0 <= u0 <= upper[0] and 0.0 <= u1 <= upper[1] and 0.0 <= u2 <= upper[2]):
                continue
            ix, fx = _cell_inside(u0, upper[0])
            iy, fy = _cell_inside(u1, upper[1])
            iz, fz = _cell_inside(u2, upper[2])
            d, g0, g1, g2 = _trilinear_phi(phi_nodes, ix * strides[0] + iy * strides[1] + iz * strides[2], strides[0],
                                           strides[1], fx, fy, fz)
            if not (d < band and d < check):
                continue
            g0, g1, g2 = g0 * inv, g1 * inv, g2 * inv
        value = d
        if with_margin:
            c0 = int(np.floor((x0 - m_origin[0]) / m_res))
            c1 = int(np.floor((x1 - m_origin[1]) / m_res))
            c2 = int(np.floor((x2 - m_origin[2]) / m_res))
            cy, cz = m_cells[1], m_cells[2]
            if 0 <= c0 < m_cells[0] and 0 <= c1 < cy and 0 <= c2 < cz:
                value = d - m_values[c0 * (cy * cz) + c1 * cz + c2]
            else:
                value = d - 0.0
        out_value[k] = value - surface_margin[b]
        out_body[k] = b
        out_x[k, 0], out_x[k, 1], out_x[k, 2] = w0, w1, w2
        out_grad[k, 0], out_grad[k, 1], out_grad[k, 2] = g0, g1, g2
        a0, a1, a2 = _to_world_direction(g0, g1, g2, rot_c)
        if moving:
            _twist_row(a0, a1, a2, w0, w1, w2, pos[b, 0], pos[b, 1], pos[b, 2], pos_c[0], pos_c[1], pos_c[2],
                       out_phi, k)
        else:
            _twist_row(a0, a1, a2, w0, w1, w2, pos[b, 0], pos[b, 1], pos[b, 2], 0.0, 0.0, 0.0, out_phi, k)
            for j in range(6, 12):
                out_phi[k, j] = 0.0
        k += 1
    return k


def _guards_within(offsets: np.ndarray, links: np.ndarray, anchor: np.ndarray, anchor_d: np.ndarray,
                   probe_d: np.ndarray, margin: float) -> np.ndarray:
    """(k,) the guard points of ``links`` (sorted) whose anchor's distance less their separation
    is below ``margin`` (guard ranges ``offsets``), in order: one pass, no gathered arrays."""
    out = np.empty(int(np.sum(offsets[links + 1] - offsets[links])), np.intp)
    return out[:_guards_within_into(offsets, links, anchor, anchor_d, probe_d, float(margin), out)]


@numba.njit(cache=True)
def _guards_within_into(offsets, links, anchor, anchor_d, probe_d, margin, out):
    k = 0
    for link in links:
        for g in range(offsets[link], offsets[link + 1]):
            if probe_d[anchor[g]] - anchor_d[g] < margin:
                out[k] = g
                k += 1
    return k


def _robot_cost(problem: Problem, fr: LinkFrames, pairs: list[_RobotPairs],
                counts: np.ndarray | None) -> tuple[list[Rows], int, np.ndarray]:
    """Interaction rows of the robot probes (eq. m-energy), f_ℓ/N_ℓ with N_ℓ the distinct active
    probes of link ℓ over all channels (or ``counts``). Returns rows, pair count, N_ℓ as counted."""
    active_any = np.zeros(len(problem.robot), dtype=bool)
    for p in pairs:
        active_any[p.probes] = True
    link_counts = np.bincount(problem.robot.body[active_any], minlength=NUM_LINKS)
    n_active = link_counts if counts is None else counts[:NUM_LINKS]
    norm_link = problem.interaction.link_weight / np.maximum(n_active, 1)
    cost = []
    for p in pairs:
        track = problem.channels[p.channel]
        body = problem.robot.body[p.probes]
        ps = PairSet(p.x_w, p.x_c, fr.pos.take(body, axis=0), body, track.body, p.rot_c, p.pos_c, p.query,
                     p.desired, norm_link[body])
        cost.append(interaction_rows(ps, track.channel, problem.interaction.robot_weights, problem.interaction))
    return cost, sum(len(p.probes) for p in pairs), link_counts


@dataclass(frozen=True)
class ContactSelection:
    """The contact-state probes of a frame, chosen at its first iterate (like N_ℓ, so that E
    changes smoothly within the frame): per (channel, unit) the unit's closest probe then, its
    target gap (m), whether it is to touch (else to stay clear) and the row's weight."""

    channel: np.ndarray  # (k,)
    probe: np.ndarray  # (k,) index into Problem.robot
    target: np.ndarray  # (k,) m
    touching: np.ndarray  # (k,) bool
    weight: np.ndarray  # (k,)


def _select_contact_rows(problem: Problem, targets: FrameTargets, pairs: list[_RobotPairs]) -> ContactSelection:
    """Per channel and contact unit (``Problem.contact_units``: links that share human parts,
    the evaluation's units), the unit's closest active probe where the unit is not in its
    demonstrated contact state (``InteractionConfig.hold_weight``): a unit whose parts touch is
    to come in to (d̂_u)₊, one whose parts stay off out to min(d̂_u, c̄). Per unit, not per
    link: the G1's small ankle-pitch housing shares the person's ankle with the foot link and
    cannot reach the floor whenever the person's ankle does."""
    cfg = problem.interaction
    unit_of = problem.contact_units
    out = []
    for p in pairs:
        if len(p.probes) == 0:
            continue
        # per unit (links sharing human parts) the demonstrated gap of its parts' surface; links
        # of no unit keep the smallest d̂ of their own probes
        hat = np.full(unit_of.max() + 1, np.inf)
        np.minimum.at(hat, unit_of, targets.robot_link_d[p.channel])
        gap = targets.unit_d[p.channel]
        hat[:len(gap)] = gap
        unit = unit_of[problem.robot.body[p.probes]]
        order = np.lexsort((p.query.d, unit))  # per unit, closest first
        first = order[np.concatenate([[True], unit[order][1:] != unit[order][:-1]])]
        lk = unit[first]
        touching = np.maximum(hat[lk], 0.0) < cfg.hold_m
        target = np.where(touching, np.maximum(hat[lk], 0.0), np.minimum(hat[lk], cfg.clearance_m))
        clearance = cfg.ground_clearance_weight if problem.channels[p.channel].is_ground else cfg.clearance_weight
        out.append((np.full(len(first), p.channel), p.probes[first], target, touching,
                    np.where(touching, cfg.hold_weight, clearance)))
    if not out:
        return ContactSelection(*(np.zeros(0, t) for t in (np.intp, np.intp, float, bool, float)))
    return ContactSelection(*(np.concatenate(parts) for parts in zip(*out)))


def _contact_state_rows(problem: Problem, fr: LinkFrames, pairs: list[_RobotPairs],
                        selection: ContactSelection) -> tuple[list[Rows], Rows, np.ndarray]:
    """Rows r = d − target of the selected probes (those still in the band) whose unit is out of
    its demonstrated state at this iterate: too far where it is to touch, too close where it is
    to stay clear. With ``solver.price_contact_state``, also the selected probes in their state
    (the hinge candidates, with the side they keep: +1 for r ≥ 0, a unit to stay clear; −1 for
    r ≤ 0, a unit to touch): each costs nothing here, and ``qp.qp_step`` adds it to the QP's cost
    where a step would cross it."""
    out, keep, side = [], [], []
    for p in pairs:
        mine = np.flatnonzero(selection.channel == p.channel)
        if len(mine) == 0 or len(p.probes) == 0:
            continue
        at = np.minimum(np.searchsorted(p.probes, selection.probe[mine]), len(p.probes) - 1)
        found = p.probes[at] == selection.probe[mine]  # p.probes is sorted
        k, mine = at[found], mine[found]
        # a row where the unit is not in its demonstrated state at this iterate
        d = p.query.d[k]
        wrong = np.where(selection.touching[mine], d > selection.target[mine], d < selection.target[mine])
        # (each set's rows built apart: a batch's arithmetic depends on its length in the last
        # bits, and the solve carries such bits into centimetres over a clip)
        if wrong.any():
            out.append(_state_rows(problem, fr, p, selection, k[wrong], mine[wrong]))
        if problem.solver.price_contact_state and not wrong.all():
            keep.append(_state_rows(problem, fr, p, selection, k[~wrong], mine[~wrong]))
            side.append(np.where(selection.touching[mine[~wrong]], -1.0, 1.0))
    return out, Rows.concat(keep), (np.concatenate(side) if side else np.zeros(0))


def _state_rows(problem: Problem, fr: LinkFrames, p: _RobotPairs, selection: ContactSelection, k: np.ndarray,
                mine: np.ndarray) -> Rows:
    """The contact-state rows d − target of the pair set's probes ``k`` (selection entries ``mine``)."""
    link = problem.robot.body[p.probes[k]]
    track = problem.channels[p.channel]
    rows = signed_distance_rows(p.query.d[k] - selection.target[mine], p.query.grad_d[k], p.x_w[k],
                                fr.pos.take(link, axis=0), link, track.body, p.rot_c, p.pos_c)
    # a far-field pull (beyond the band) moves the robot's part in, never the object out to
    # it: dragged by the pelvis the person leans on, the free chair drifted 5.6 cm off its path
    far = ~p.query.in_band[k]
    phi = rows.phi.copy()
    phi[far, 6:] = 0.0
    return Rows(rows.value, selection.weight[mine], phi, rows.body_a, np.where(far, FIXED, rows.body_b))


def _object_rows(problem: Problem, state: SolverState, targets: FrameTargets, i: int, count: int | None,
                 con: _ConstraintRows) -> tuple[list[Rows], int, int]:
    """Free object i's probes against every other channel: interaction rows (object weights),
    non-penetration rows of its probes and of its hull guards. Returns rows, pair count and
    its active probe count."""
    band, check = problem.band_m, problem.solver.check_margin_m
    obj = problem.objects[i]
    body = NUM_LINKS + i
    o_w = obj.probes @ state.obj_rot[i].T + state.obj_pos[i]
    own = problem.channels[obj.channel]
    pairs = []
    for c, track in enumerate(problem.channels):
        if c == obj.channel:
            continue
        rot_c, pos_c = channel_pose(state, track, targets.t)
        o_c = to_channel_frame(o_w, rot_c, pos_c)
        demo_active = targets.objects_active[i][c]
        sel = np.flatnonzero(near_channel(track, o_c, band) | demo_active)
        if len(sel) == 0:
            continue
        q = track.channel.query(o_c.take(sel, axis=0), normals=False)
        active = np.flatnonzero(q.in_band | demo_active[sel])
        a = sel[active]
        a_c = o_c.take(a, axis=0)
        pairs.append((c, track, rot_c, pos_c, a, a_c,
                      far_field(q, active, a_c, targets.objects[i][c].take(a), track.is_ground)))
        ib = np.flatnonzero(q.in_band & (q.d < check))
        pts = sel[ib]
        con.add(_distance_block(track, rot_c, pos_c, o_w.take(pts, axis=0), o_c.take(pts, axis=0),
                                np.full(len(ib), body), np.broadcast_to(state.obj_pos[i], (len(ib), 3)),
                                q.d[ib], q.grad_d.take(ib, axis=0)), c)
        # the object's own hull guards against the ground, furniture and other objects
        g_w = own.guards @ state.obj_rot[i].T + state.obj_pos[i]
        g_c = to_channel_frame(g_w, rot_c, pos_c)
        gs = np.flatnonzero(near_channel(track, g_c, check))
        if len(gs):
            d, grad, in_band = track.channel.distance(g_c[gs])
            gb = np.flatnonzero(in_band & (d < check))
            con.add(_distance_block(track, rot_c, pos_c, g_w[gs[gb]], g_c[gs[gb]], np.full(len(gb), body),
                                    np.broadcast_to(state.obj_pos[i], (len(gb), 3)), d[gb], grad[gb]), c)
    active_any = np.zeros(len(obj.probes), dtype=bool)
    for pair in pairs:
        active_any[pair[4]] = True
    n_counted = int(active_any.sum())
    weight = problem.interaction.link_weight / max(n_counted if count is None else count, 1)
    cost, total = [], 0
    for c, track, rot_c, pos_c, sel, sel_c, q in pairs:
        ps = PairSet(o_w[sel], sel_c,
                     np.broadcast_to(state.obj_pos[i], (len(sel), 3)), np.full(len(sel), body), track.body,
                     rot_c, pos_c, q, targets.objects[i][c].take(sel), np.full(len(sel), weight))
        cost.append(interaction_rows(ps, track.channel, problem.interaction.object_weights, problem.interaction))
        total += len(sel)
    return cost, total, n_counted


def linearise(problem: Problem, state: SolverState, targets: FrameTargets, timings: dict[str, float],
              counts: np.ndarray | None = None, contact: ContactSelection | None = None) -> Linearisation:
    """All rows of the QP at the current iterate.

    ``counts`` (L + O,) fixes N_ℓ, the active probe count of each link and object, instead of
    counting at this iterate: ``solve_frame`` counts once per frame, so that E stays a smooth
    function of the iterate within the frame (a count that jumps by one as a probe crosses d̄
    rescales the whole link's term, and the trust-region test would read that as model error).
    ``contact`` fixes the contact-state rows the same way (chosen here when None).
    """
    tm = SectionTimer(timings)
    margin, check = problem.solver.constraint_margin_m, problem.solver.check_margin_m
    fr = frames_at(problem, state, state.q)
    centre_w = np.einsum("lij,lj->li", fr.rot, problem.link_center) + fr.pos
    tm.lap("kinematics")

    con = _ConstraintRows([], [])
    robot_pairs, link_min = [], np.full((len(problem.channels), NUM_LINKS), np.inf)
    for c in range(len(problem.channels)):
        pairs, link_min[c] = _robot_channel(problem, state, targets, fr, centre_w, c, con)
        if pairs is not None:
            robot_pairs.append(pairs)
    tm.lap("robot_channels")

    cost, total_pairs, link_counts = _robot_cost(problem, fr, robot_pairs, counts)
    if contact is None:
        contact = _select_contact_rows(problem, targets, robot_pairs)
    wrong, hinge, hinge_side = _contact_state_rows(problem, fr, robot_pairs, contact)
    cost += wrong
    tm.lap("robot_rows")

    object_counts = []
    for i in range(len(problem.objects)):
        rows, pairs, n = _object_rows(problem, state, targets, i,
                                      None if counts is None else int(counts[NUM_LINKS + i]), con)
        cost += rows
        total_pairs += pairs
        object_counts.append(n)
    tm.lap("object_rows")

    for c, track in enumerate(problem.channels):
        if track.is_ground or len(track.guards) == 0:
            continue
        rot_c, pos_c = channel_pose(state, track, targets.t)
        # a link can hold an object's edge only where its own surface, hence an area probe
        # within the link's sampling gap, comes close to the object
        links = np.flatnonzero(link_min[c] < problem.sampling_gap + margin)
        links = links[problem.link_grids.has_grid[links]]
        con.add(object_guard_rows(problem, fr, centre_w, links, track, rot_c, pos_c, check), len(problem.channels) + c)
        # out to the constraint margin only: out to the check margin the carry linearised 424
        # surface rows per call (+16 ms per frame); a step that pushes a face in is restored
        con.add(object_surface_rows(problem, fr, centre_w, links, track, rot_c, pos_c, margin),
                len(problem.channels) + c)
    tm.lap("object_guards")

    min_dist = min((float(r.value.min()) for r in con.rows if len(r)), default=np.inf)
    # self-collision of the meshes: grouped like surface rows, per other link (channel code);
    # candidates out to the check margin like every other pair: a full trust-region step moves
    # a foot by more than the 2 cm constraint margin, and on Bandai's walk one ankle went 40 mm
    # into the other knee unseen, after which no QP of the clip was solvable (cluster rows for
    # the 2-5 cm band instead were measured: 2.6 ms faster per walk frame, but 24 failed QPs
    # in Bandai's first 60 frames)
    self_rows = self_mesh_rows(problem, fr, centre_w, check)
    con.rows.append(self_rows)
    con.channel.append(2 * len(problem.channels) + self_rows.body_b)
    tm.lap("self_meshes")

    surface_channel = np.concatenate(con.channel).astype(np.intp) if con.channel else np.zeros(0, np.intp)
    tm.lap("constraint_selection")

    capsules = self_collision_rows(problem, fr, margin)
    min_self = min(float(capsules.value.min()) if len(capsules) else np.inf,
                   float(self_rows.value.min()) if len(self_rows) else np.inf)
    # the surface rows, then the capsule rows and the base-step rows (always in the QP, like the
    # capsule rows; not counted as self-collision), concatenated once
    constraints = Rows.concat([*con.rows, capsules, base_step_rows(problem, state, targets.t, fr)])
    tm.lap("self_collision")

    cost.append(stance_rows(targets.stance, fr, problem.stance_cfg.weight))
    # E_sty,r and E_sty,o in one batch: the tracked links, then the free objects
    links = problem.style.links
    pos_weight, rot_weight = problem.style_weights_at(targets.t)
    cost.append(pose_rows(np.concatenate([fr.pos[links], state.obj_pos]),
                          np.concatenate([fr.rot[links], state.obj_rot]),
                          targets.style_pos, targets.style_rot, problem.style_bodies, pos_weight, rot_weight))
    com = None
    if targets.com is not None:
        if state.com_data is None:
            state.com_data = problem.kin.new_data()
        com = com_residual(problem.kin.model, state.com_data, state.q, targets.com)
    tm.lap("style_rows")
    return Linearisation(Rows.concat(cost), constraints, surface_channel, margin, fr,
                         total_pairs, min_dist, min_self,
                         np.concatenate([link_counts, np.asarray(object_counts, np.intp)]), contact, com,
                         hinge, hinge_side)


#: The root link (pelvis): its origin is the floating base's.
ROOT_LINK = robot.BODY_NAMES.index(robot.ROOT_BODY)


def base_step_rows(problem: Problem, state: SolverState, t: int, fr: LinkFrames) -> Rows:
    """Constraint rows b ∓ (p − p̂) ≥ 0 per world axis (``SolverConfig.base_step_m``): the base
    origin p within b of p̂ = the previous frame's base moved by the pelvis style target's
    displacement (the person's pelvis, its height scaled to the G1's). None on the first frame."""
    if state.prev is None or t == 0:
        return Rows.empty()
    b = problem.solver.base_step_m
    pelvis = ROOT_LINK
    # the pelvis style target's displacement: the person's, its height scaled to the G1's
    slot = int(np.flatnonzero(problem.style.links == pelvis)[0])
    target = state.prev[0][:3] + problem.style.pos_w[t, slot] - problem.style.pos_w[t - 1, slot]
    dev = fr.pos[pelvis] - target
    phi = np.zeros((6, 12))
    phi[:3, :3] = -np.eye(3)
    phi[3:, :3] = np.eye(3)
    return Rows(np.concatenate([b - dev, b + dev]), np.ones(6), phi, np.full(6, pelvis, np.intp),
                np.full(6, FIXED, np.intp))


