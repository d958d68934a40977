"""From a demonstration to the solver's immutable :class:`~retarget.solver.Problem`.

Modes (METHOD.md "Modes"):

* ``native`` (default): robot and scene at the captured metric scale; every manipulated object
  is a decision variable, static furniture stays a fixed channel.
* ``scaled``: the human (trajectories and surface) and the object trajectories are multiplied
  by sc = G1 height / stature (objects keep their size; object heights scale about the first
  frame's, ``retarget.demos.scaled_object_positions``) and every object is fixed (the paper's
  ablation and OmniRetarget's convention).
* ``robot-only``: the ground is the only channel; objects are ignored.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from otr_gym import robot
from otr_gym.robot_geometry import visual_meshes
from otr_gym.rotations import quat_slerp, quat_to_matrix
from retarget.demos import (
    Demonstration,
    DemoObject,
    InvalidDemonstrationError,
    scaled_object_positions,
)
from retarget.geometry import GeometryConfig, GridStack, GroundChannel, SDFChannel
from retarget.kinematics import NUM_LINKS, RobotKinematics
from retarget.margins import cached_margin
from retarget.meshes import as_trimesh
from retarget.probes import (
    ProbeSet,
    hull_guard_points,
    human_probes,
    robot_guard_points,
    robot_probes,
    robot_vertex_guards,
)
from retarget.residuals import FIXED, InteractionConfig
from retarget.solver import ChannelTrack, FreeObject, Problem, SolverConfig
from retarget.style import StyleConfig, pelvis_height_ratio, robot_style_targets

MODES = ("native", "scaled", "robot-only")


@lru_cache(maxsize=1)
def kinematics() -> RobotKinematics:
    """The process-wide G1 model (immutable)."""
    return RobotKinematics()


def resample_demonstration(demo: Demonstration, fps: float) -> Demonstration:
    """The demonstration at ``fps`` (linear positions, slerp orientations, nearest-frame
    annotations); same duration."""
    if abs(fps - demo.fps) < 1e-9:
        return demo
    if not fps > 0:
        raise ValueError(f"{demo.name}: fps must be > 0, got {fps}")
    t_src = np.arange(demo.num_frames) / demo.fps
    n = int(np.floor(t_src[-1] * fps + 1e-9)) + 1
    u = np.arange(n) / fps * demo.fps
    i0 = np.clip(np.floor(u).astype(int), 0, demo.num_frames - 1)
    i1 = np.minimum(i0 + 1, demo.num_frames - 1)
    a = np.clip(u - i0, 0.0, 1.0)

    def lerp(x):
        w = a.reshape((-1,) + (1,) * (x.ndim - 1))
        return (1 - w) * x[i0] + w * x[i1]

    def slerp(q):
        return quat_slerp(q[i0], q[i1], np.broadcast_to(a.reshape((-1,) + (1,) * (q.ndim - 2)), q[i0].shape[:-1]))

    objects = [replace(o, pos_w=lerp(o.pos_w), quat_w=slerp(o.quat_w)) for o in demo.objects]
    nearest = np.rint(u).astype(int).clip(0, demo.num_frames - 1)
    annotations = {k: np.asarray(v)[nearest] for k, v in demo.annotations.items()}
    return replace(demo, fps=float(fps), part_pos_w=lerp(demo.part_pos_w), part_quat_w=slerp(demo.part_quat_w),
                   objects=objects, annotations=annotations)


def mode_scale(demo: Demonstration, mode: str) -> float:
    """sc = G1 height / stature in the scaled mode, 1 otherwise."""
    if mode not in MODES:
        raise ValueError(f"unknown retarget mode '{mode}' (choose from {MODES})")
    if mode != "scaled":
        return 1.0
    if not demo.stature_m > 0:
        raise InvalidDemonstrationError(f"{demo.name}: stature must be > 0 m for the scaled mode, got {demo.stature_m}")
    return robot.HEIGHT_M / demo.stature_m


def correspondences(robot_set: ProbeSet, human: ProbeSet, demo: Demonstration, scale: float,
                    cache_dir: Path | None) -> np.ndarray:
    """src(p) (P_robot,): index into ``human`` of every robot probe's demonstrated point (OT)."""
    from retarget.transport import robot_human_correspondences

    return robot_human_correspondences(robot_set, human, demo, scale=scale, cache_dir=cache_dir)


def _object_channel(obj: DemoObject, geometry: GeometryConfig, cache_dir: Path | None) -> SDFChannel:
    source = obj.mesh_path or obj.name
    mesh = as_trimesh(obj.vertices, obj.faces, f"object '{obj.name}' ({source})")
    return SDFChannel.from_mesh(mesh, geometry, cache_dir, name=obj.name)


def build_problem(demo: Demonstration, mode: str = "native", *, geometry: GeometryConfig = GeometryConfig(),
                  interaction: InteractionConfig = InteractionConfig(), style: StyleConfig = StyleConfig(),
                  solver: SolverConfig = SolverConfig(), guard_spacing_m: float = 0.008,
                  max_probes_per_link: int | None = None, seed: int = 0, cache_dir: Path | None = None) -> Problem:
    """Probes, channels, correspondences and style targets of ``demo`` (at its own fps)."""
    scale = mode_scale(demo, mode)
    kin = kinematics()
    T = demo.num_frames
    part_pos = demo.part_pos_w * scale
    part_rot = quat_to_matrix(demo.part_quat_w)
    human = human_probes(demo.surface, geometry.human_density_per_m2, seed, scale)
    robot_set = robot_probes(geometry.robot_density_per_m2, seed, max_probes_per_link)
    src = correspondences(robot_set, human, demo, scale, cache_dir)
    demo_points = ProbeSet(human.body_names, human.points[src], human.body[src])

    eye = np.broadcast_to(np.eye(3), (T, 3, 3))
    inf = np.full(3, np.inf)
    channels = [ChannelTrack("ground", GroundChannel("ground", geometry.band_m), FIXED, np.zeros((T, 3)), eye,
                             -inf, inf, np.zeros((0, 3)), None)]
    objects: list[FreeObject] = []
    if mode != "robot-only":
        for obj in demo.objects:
            ch = _object_channel(obj, geometry, cache_dir)
            free = mode == "native" and not obj.static
            body = NUM_LINKS + len(objects) if free else FIXED
            lower, upper = ch.mesh.bounds
            channels.append(ChannelTrack(obj.name, ch, body, scaled_object_positions(obj.pos_w, scale),
                                         quat_to_matrix(obj.quat_w),
                                         lower, upper, hull_guard_points(ch.mesh.vertices, guard_spacing_m,
                                                                         along_edges=True),
                                         cached_margin(ch.grid, ch.mesh, MARGIN_REACH_M, cache_dir)))
            if free:
                objects.append(FreeObject(obj.name, len(channels) - 1, ch.surface.points))

    targets = robot_style_targets(part_pos, demo.part_quat_w, kin, pelvis_height_ratio(demo.stature_m * scale))
    guards = robot_guard_points(guard_spacing_m)
    vertex_guards = robot_vertex_guards()
    both = ProbeSet(robot_set.body_names, np.concatenate([robot_set.points, guards.points]),
                    np.concatenate([robot_set.body, guards.body]))
    centre, radius = both.bounding_spheres()
    (ga, gd), (va, vd) = guard_anchors(robot_set, guards), guard_anchors(robot_set, vertex_guards)
    gap = np.zeros(NUM_LINKS)
    np.maximum.at(gap, vertex_guards.body, vd)
    anchors = {"guard_anchor": ga, "guard_anchor_d": gd, "vertex_anchor": va, "vertex_anchor_d": vd,
               "sampling_gap": gap}
    problem = Problem(fps=demo.fps, kin=kin, robot=robot_set, guards=guards, vertex_guards=vertex_guards,
                      link_center=centre, link_radius=radius, **anchors,
                      link_grids=robot_link_grids(solver.check_margin_m, cache_dir) if len(channels) > 1
                      else GridStack([None] * NUM_LINKS),
                      demo_points=demo_points, part_pos_w=part_pos, part_rot_w=part_rot, channels=tuple(channels),
                      objects=tuple(objects), style=targets, q_init=np.zeros(kin.nq), interaction=interaction,
                      style_cfg=style, solver=solver, band_m=geometry.band_m)
    return replace(problem, q_init=initial_configuration(problem))


#: Cells of an object grid within this distance of the surface get a measured error margin.
MARGIN_REACH_M = 0.02

#: Resolution of the robot links' distance grids (m): 5 mm keeps the trilinear error on the
#: arms' 3.5 cm radius below 0.1 mm (h²/8R), where a 1 cm grid would err by 0.4 mm.
LINK_GRID_RESOLUTION_M = 0.005


@lru_cache(maxsize=2)
def robot_link_grids(reach_m: float, cache_dir: Path | None = None) -> GridStack:
    """The signed distance grids of the G1 links' visual meshes (link frames) out to
    ``reach_m``, stacked in BODY_NAMES order (links without a mesh have none); each grid is
    cached on disk like the object grids."""
    from retarget.geometry import (
        VoxelGrid,
        build_sdf_grid,
        cached_arrays,
        default_cache_dir,
    )

    meshes = visual_meshes()
    root = (default_cache_dir() if cache_dir is None else Path(cache_dir)) / "robot_links"
    grids = []
    for name in robot.BODY_NAMES:
        if name not in meshes:
            grids.append(None)
            continue
        mesh = as_trimesh(meshes[name].vertices, meshes[name].faces, f"G1 link {name}")
        key = f"{mesh.content_hash}-{LINK_GRID_RESOLUTION_M}-{reach_m}"

        def build(mesh=mesh) -> dict[str, np.ndarray]:
            g = build_sdf_grid(mesh, LINK_GRID_RESOLUTION_M, reach_m)
            return {"origin": g.origin, "shape": np.array(g.shape), "values": g.values}

        def check(a: dict[str, np.ndarray]) -> None:
            if a["values"].shape != (int(np.prod(a["shape"])), 4) or not np.isfinite(a["values"]).all():
                raise ValueError("inconsistent grid arrays")

        a = cached_arrays(root / f"{name}.npz", key, build, check)
        grids.append(VoxelGrid(np.asarray(a["origin"], np.float64), LINK_GRID_RESOLUTION_M,
                               tuple(int(v) for v in a["shape"]), np.ascontiguousarray(a["values"], np.float64)))
    return GridStack(grids)


def guard_anchors(probes: ProbeSet, guards: ProbeSet) -> tuple[np.ndarray, np.ndarray]:
    """For every guard point, the nearest area probe of the same link (index into ``probes``)
    and their distance (m), in the link frame."""
    anchor = np.zeros(len(guards), np.intp)
    dist = np.zeros(len(guards))
    for k in range(len(probes.body_names)):
        p_idx, g_idx = np.flatnonzero(probes.body == k), np.flatnonzero(guards.body == k)
        if len(g_idx):
            if len(p_idx) == 0:
                raise RuntimeError(f"link {probes.body_names[k]} has guard points but no area probe")
            dist[g_idx], nearest = cKDTree(probes.points[p_idx]).query(guards.points[g_idx])
            anchor[g_idx] = p_idx[nearest]
    return anchor, dist


def initial_configuration(problem: Problem) -> np.ndarray:
    """Cold start: pelvis at the demonstrated pelvis with its desired orientation, default
    joints, lowered or raised so that the lowest robot point touches the ground."""
    from otr_gym.rotations import matrix_to_quat, wxyz_to_xyzw

    links = list(problem.style.links)
    pelvis = links.index(robot.body_indices([robot.ROOT_BODY])[0])
    q = np.concatenate([problem.part_pos_w[0, 0], wxyz_to_xyzw(matrix_to_quat(problem.style.rot_w[0, pelvis])),
                        robot.DEFAULT_JOINT_POS])
    fr = problem.kin.frames(problem.kin.new_data(), q)
    lowest = min(problem.robot.posed(fr.rot, fr.pos)[:, 2].min(), problem.guards.posed(fr.rot, fr.pos)[:, 2].min())
    q[2] -= lowest
    return q
