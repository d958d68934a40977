"""The per-frame solver's collision rows for the trajectory pass (``retarget.solver.trajectory``):
one frame's ground, object and self-collision rows at a G1 configuration, as rows of the tangent
correction δ (base twist in the pelvis frame, then joints), the objects held where the clip has them.

The rows are the SQP's own (``retarget.solver.rows``, ``object_rows``, ``self_rows``): the G1's
hull guards against the ground, its mesh-vertex guards against every object's distance grid, the
objects' guard and surface points in the links' grids, the links' meshes in each other's grids
and the capsule pairs, each ``value + φ_A·ν_A + φ_B·ν_B ≥ 0`` (m) with the bodies' world-aligned
twists ν = J δ; an object's own twist is zero here (the pass does not move objects). Candidates
reach out to the solver's check margin (5 cm) like the SQP's; which of them seed a window's QP
is ``initial_constraints``'s choice, the others are checked against each solution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from otr_gym.rotations import quat_to_matrix
from retarget.geometry.kinematics import NUM_LINKS
from retarget.solver.object_rows import object_guard_rows, object_surface_rows
from retarget.solver.problem import ChannelTrack, Problem
from retarget.solver.qp import constraint_matrix
from retarget.solver.residuals import FIXED, Rows
from retarget.solver.rows import _guard_rows, candidate_links
from retarget.solver.seed_rows import initial_constraints
from retarget.solver.self_rows import self_collision_rows, self_mesh_rows


@dataclass(frozen=True)
class FrameRows:
    """One frame's collision rows: value + C δ ≥ 0, and which of them seed the QP."""

    value: np.ndarray  # (k,) m at the linearisation point
    jac: np.ndarray  # (k, nv) rate of each row per unit of the frame's tangent correction
    seed: np.ndarray  # (k,) bool: rows put in the first QP (the rest are checked after it)

    def __len__(self) -> int:
        return len(self.value)


@dataclass(frozen=True)
class Scene:
    """What the collision rows read: the clip's problem (probes, grids, channels) and each free
    object's pose per frame as the reference has it (held by the pass)."""

    problem: Problem
    obj_pos: np.ndarray  # (T, O, 3) world, m
    obj_rot: np.ndarray  # (T, O, 3, 3)

    @staticmethod
    def of(problem: Problem, reference) -> Scene:
        """The scene of ``reference`` solved from ``problem``: its object tracks by name."""
        tracks = {o.name: o for o in reference.objects}
        T, n = reference.num_frames, len(problem.objects)
        pos, rot = np.zeros((T, n, 3)), np.tile(np.eye(3), (T, n, 1, 1))
        for i, o in enumerate(problem.objects):
            pos[:, i] = tracks[o.name].pos_w
            rot[:, i] = quat_to_matrix(tracks[o.name].quat_w)
        return Scene(problem, pos, rot)

    def channel_pose(self, track: ChannelTrack, t: int) -> tuple[np.ndarray, np.ndarray]:
        if track.body == FIXED:
            return track.rot_w[t], track.pos_w[t]
        i = track.body - NUM_LINKS
        return self.obj_rot[t, i], self.obj_pos[t, i]

    def rows(self, data, q: np.ndarray, t: int) -> FrameRows:
        """Frame t's collision rows at Pinocchio configuration q (``data``: the caller's scratch)."""
        problem = self.problem
        margin, check = problem.solver.constraint_margin_m, problem.solver.check_margin_m
        fr = problem.kin.frames(data, q)
        centre_w = np.einsum("lij,lj->li", fr.rot, problem.link_center) + fr.pos
        parts: list[Rows] = []
        codes: list[np.ndarray] = []

        def add(rows: Rows, code: int | np.ndarray) -> None:
            parts.append(rows)
            codes.append(np.broadcast_to(code, len(rows)))

        n_channels = len(problem.channels)
        for c, track in enumerate(problem.channels):
            rot_c, pos_c = self.channel_pose(track, t)
            links = np.flatnonzero(candidate_links(problem, track, centre_w, rot_c, pos_c))
            if len(links) == 0:
                continue
            # the hull guards imply the area probes against the ground, the mesh vertices against objects
            guards = problem.guards if track.is_ground else problem.vertex_guards
            index = np.concatenate([np.arange(guards.offsets[k], guards.offsets[k + 1]) for k in links])
            add(_guard_rows(problem, fr, track, rot_c, pos_c, guards, index, check), c)
            if not track.is_ground and len(track.guards):
                gl = links[problem.link_grids.has_grid[links]]
                add(object_guard_rows(problem, fr, centre_w, gl, track, rot_c, pos_c, check), n_channels + c)
                add(object_surface_rows(problem, fr, centre_w, gl, track, rot_c, pos_c, margin), n_channels + c)
        mesh = self_mesh_rows(problem, fr, centre_w, check)
        add(mesh, 2 * n_channels + mesh.body_b)
        surface = Rows.concat(parts)
        code = np.concatenate(codes).astype(np.intp) if codes else np.zeros(0, np.intp)
        seed = np.zeros(len(surface), bool)
        seed[initial_constraints(surface, code, margin)] = True
        capsules = self_collision_rows(problem, fr, margin)
        rows = Rows.concat([surface, capsules])
        seed = np.concatenate([seed, np.ones(len(capsules), bool)])
        # bodies' Jacobians: the links', zero for the held objects and FIXED (the last)
        jac = np.zeros((NUM_LINKS + len(problem.objects) + 1, 6, problem.kin.nv))
        jac[:NUM_LINKS] = fr.jac
        return FrameRows(rows.value, constraint_matrix(rows, jac) if len(rows) else np.zeros((0, problem.kin.nv)),
                         seed)
