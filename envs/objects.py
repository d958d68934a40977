"""The reference's objects as simulated bodies (OTR-G1-BoxTrack-v0).

``scene_objects(refs, cfg)`` decides, once per clip library, what each object of the
references becomes:

- *moving* objects (the box): a free body whose collision geometry comes from the reference's
  embedded mesh (``envs.collision``: a fitted box when box-like, else boxes or a convex
  decomposition), or from ``cfg.overrides[name]`` (mesh file or box); mass and friction from
  the config; inertia from the collision geometry at uniform density;
- *static* objects (the table): whose pose never changes in any clip: a fixed body at that pose.

Every geom of an object has MuJoCo priority 1 so its friction coefficient, not the max with
the robot's, governs its contacts (``ObjectsCfg.friction``). Names in the compiled model:
body ``object/<name>``, free joint ``object/<name>/joint``, geoms ``object/<name>/geom<k>``;
moving objects' free joints follow the robot's in ``qpos`` (7 each) and ``qvel`` (6 each), in
``SceneObjects.moving`` order.

Errors name the reference file and the object: a reference without objects, an object
without a mesh (and no override), a mesh that cannot be decomposed, clips that disagree on
their objects.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
import torch

from envs.collision import BoxShape, CollisionShape, CollisionShapeError, collision_shapes, load_mesh
from envs.config import ObjectsCfg
from otr_gym.reference import InvalidReferenceError, Reference
from otr_gym.rotations import quat_apply_inverse, quat_error_angle

BODY_PREFIX = "object/"
OBJECT_RGBA = (0.8, 0.55, 0.3, 1.0)
STATIC_RGBA = (0.55, 0.4, 0.25, 1.0)
GROUND_GEOM = "ground/ground"


@dataclass(frozen=True)
class SceneObject:
    name: str
    static: bool
    shapes: tuple[CollisionShape, ...]
    method: str  # "box", "boxes", "convex decomposition" or "override box"
    mass_kg: float
    friction: float
    pos_w: np.ndarray  # (3,) fixed pose (static) or the first clip's first frame (moving)
    quat_w: np.ndarray  # (4,) wxyz
    visual_vertices: np.ndarray | None = None  # the mesh as given, for rendering
    visual_faces: np.ndarray | None = None
    #: (3,) m the box was narrowed by per axis to fit the reference's grasps
    #: (``envs.mdp.objects.fit_boxes_to_grasps``), None when untouched
    grasp_shrink_m: np.ndarray | None = None

    @property
    def body(self) -> str:
        return BODY_PREFIX + self.name


@dataclass(frozen=True)
class SceneObjects:
    objects: tuple[SceneObject, ...]
    source: str  # the first clip's file, for messages

    @property
    def moving(self) -> tuple[SceneObject, ...]:
        return tuple(o for o in self.objects if not o.static)

    @property
    def static(self) -> tuple[SceneObject, ...]:
        return tuple(o for o in self.objects if o.static)

    def add_to(self, spec: mujoco.MjSpec, visual: bool, condim: int = 3) -> None:
        """Add every object to ``spec``. With ``visual`` the given mesh is added for display
        (non-colliding) and the collision geoms are put in the hidden group 3."""
        for obj in self.objects:
            _add_object(spec, obj, visual, condim)


def _add_object(spec: mujoco.MjSpec, obj: SceneObject, visual: bool, condim: int) -> None:
    body = spec.worldbody.add_body(name=obj.body, pos=obj.pos_w.tolist(), quat=obj.quat_w.tolist())
    if not obj.static:
        body.add_freejoint(name=f"{obj.body}/joint")
    rgba = list(STATIC_RGBA if obj.static else OBJECT_RGBA)
    show_mesh = visual and obj.visual_vertices is not None and obj.method != "box"
    common = {"friction": [obj.friction, 0.005, 0.0001], "priority": 1, "condim": condim,
              "rgba": [*rgba[:3], 0.0] if show_mesh else rgba, "group": 3 if show_mesh else 0}
    volumes = [_volume(s) for s in obj.shapes]
    density = 0.0 if obj.static else obj.mass_kg / sum(volumes)
    for k, shape in enumerate(obj.shapes):
        name = f"{obj.body}/geom{k}"
        if isinstance(shape, BoxShape):
            body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=shape.half_extents.tolist(),
                          pos=shape.pos.tolist(), quat=shape.quat_wxyz.tolist(), density=density, **common)
        else:
            spec.add_mesh(name=f"{name}/hull", uservert=shape.vertices.ravel().tolist(),
                          userface=np.asarray(shape.faces, np.int32).ravel().tolist())
            body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"{name}/hull", density=density,
                          **common)
    if show_mesh:
        spec.add_mesh(name=f"{obj.body}/visual", uservert=np.asarray(obj.visual_vertices, np.float64).ravel().tolist(),
                      userface=np.asarray(obj.visual_faces, np.int32).ravel().tolist())
        body.add_geom(name=f"{obj.body}/visual", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"{obj.body}/visual",
                      contype=0, conaffinity=0, density=0.0, group=1, rgba=rgba)


def _volume(shape: CollisionShape) -> float:
    if isinstance(shape, BoxShape):
        return float(np.prod(2.0 * shape.half_extents))
    import trimesh

    return float(trimesh.Trimesh(shape.vertices, shape.faces, process=False).convex_hull.volume)


def scene_objects(refs: Sequence[Reference], cfg: ObjectsCfg) -> SceneObjects:
    """The objects of a clip library (see the module docstring). All clips must carry the
    same object names with the same meshes; static objects must have the same pose in all."""
    if not refs:
        raise InvalidReferenceError("no reference clips given")
    first = refs[0]
    for ref in refs:
        if not ref.objects:
            raise InvalidReferenceError(
                f"{ref.source}: OTR-G1-BoxTrack-v0 needs a reference with objects (object_pos_w or objects_*), "
                "this one has none (track it with OTR-G1-Track-v0)")
        names = [o.name for o in ref.objects]
        if names != [o.name for o in first.objects]:
            raise InvalidReferenceError(f"{ref.source}: objects {names} differ from {first.source}'s "
                                        f"{[o.name for o in first.objects]} (one object set per clip library)")
    unknown = sorted(set(cfg.overrides) - {o.name for o in first.objects})
    if unknown:
        raise ValueError(f"objects.overrides names {unknown}, which are not objects of {first.source} "
                         f"({[o.name for o in first.objects]})")
    out = []
    for i in range(len(first.objects)):
        static = all(is_static(ref.objects[i], cfg) for ref in refs)
        for ref in refs[1:]:
            _check_same_object(first, ref, i, static)
        out.append(_scene_object(first, i, static, cfg))
    if not any(not o.static for o in out):
        raise InvalidReferenceError(f"{first.source}: every object ({[o.name for o in out]}) is static: "
                                    "nothing for OTR-G1-BoxTrack-v0 to track")
    return SceneObjects(tuple(out), first.source)


def is_static(track, cfg: ObjectsCfg) -> bool:
    """Whether an object track stays within the static tolerances over its clip (a fixed body)."""
    moved = np.linalg.norm(track.pos_w - track.pos_w[0], axis=-1).max()
    turned = quat_error_angle(track.quat_w, np.broadcast_to(track.quat_w[0], track.quat_w.shape)).max()
    return bool(moved <= cfg.static_tolerance_m and turned <= cfg.static_tolerance_rad)


def _check_same_object(first: Reference, ref: Reference, i: int, static: bool) -> None:
    a, b = first.objects[i], ref.objects[i]
    if (a.mesh_vertices is None) != (b.mesh_vertices is None) or (
            a.mesh_vertices is not None and (a.mesh_vertices.shape != b.mesh_vertices.shape
                                             or np.abs(a.mesh_vertices - b.mesh_vertices).max() > 1e-4)):
        raise InvalidReferenceError(f"{ref.source}: object '{b.name}' has another mesh than in {first.source} "
                                    "(one object set per clip library)")
    if static:
        moved = np.linalg.norm(b.pos_w[0] - a.pos_w[0])
        turned = float(quat_error_angle(b.quat_w[0], a.quat_w[0]))
        if moved > 1e-3 or turned > 1e-3:
            raise InvalidReferenceError(f"{ref.source}: static object '{b.name}' stands elsewhere than in "
                                        f"{first.source} ({moved:.3f} m, {turned:.3f} rad): a fixed body has one pose")


def _scene_object(ref: Reference, i: int, static: bool, cfg: ObjectsCfg) -> SceneObject:
    track = ref.objects[i]
    what = f"{ref.source}: object '{track.name}'"
    override = cfg.overrides.get(track.name)
    vertices, faces = track.mesh_vertices, track.mesh_faces
    if override is not None and override.mesh is not None:
        try:
            vertices, faces = load_mesh(override.mesh, f"mesh of {what}")
        except CollisionShapeError as exc:
            raise InvalidReferenceError(str(exc)) from exc
    if override is not None and override.box_half_extents is not None:
        half = np.asarray(override.box_half_extents, np.float64)
        if half.shape != (3,) or not np.all(half > 0):
            raise ValueError(f"objects.overrides.{track.name}.box_half_extents must be 3 positive numbers, "
                             f"got {override.box_half_extents}")
        shapes, method = [BoxShape(half, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))], "override box"
    else:
        if vertices is None or faces is None:
            raise InvalidReferenceError(
                f"{what} has no mesh (the file embeds none): give one with the env config "
                f"objects.overrides.{track.name}.mesh (`otr train --set env.objects.overrides.{track.name}.mesh=MESH`) "
                f"or objects.overrides.{track.name}.box_half_extents")
        try:
            shapes, method = collision_shapes(vertices, faces, what, cfg.collision)
        except CollisionShapeError as exc:
            raise InvalidReferenceError(str(exc)) from exc
    mass = override.mass_kg if override is not None and override.mass_kg is not None else cfg.mass_kg
    friction = override.friction if override is not None and override.friction is not None else cfg.friction
    if not mass > 0:
        raise ValueError(f"{what}: mass must be > 0 kg, got {mass}")
    return SceneObject(name=track.name, static=static, shapes=tuple(shapes), method=method, mass_kg=float(mass),
                       friction=float(friction), pos_w=np.asarray(track.pos_w[0], np.float64),
                       quat_w=np.asarray(track.quat_w[0], np.float64),
                       visual_vertices=None if vertices is None else np.asarray(vertices, np.float64),
                       visual_faces=None if faces is None else np.asarray(faces, np.int64))


def object_qpos(pos_w: torch.Tensor, quat_w: torch.Tensor) -> torch.Tensor:
    """(…, M·7) free-joint qpos of M objects from (…, M, 3) positions and (…, M, 4) wxyz."""
    return torch.cat([pos_w, quat_w], dim=-1).flatten(-2)


def object_qvel(quat_w: torch.Tensor, lin_vel_w: torch.Tensor, ang_vel_w: torch.Tensor) -> torch.Tensor:
    """(…, M·6) free-joint qvel: linear velocity (world), angular velocity in the object frame."""
    return torch.cat([lin_vel_w, quat_apply_inverse(quat_w, ang_vel_w)], dim=-1).flatten(-2)
