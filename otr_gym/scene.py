"""Compose MuJoCo scenes at run time: G1 + ground + table + free objects.

The pieces are small MJCF files under ``otr_gym/assets`` (``g1/g1.xml``,
``scenes/ground.xml``, ``scenes/table.xml``) joined with ``mujoco.MjSpec.attach``; objects are
added as free bodies with a mesh (any trimesh-readable file) or a box primitive.
The robot keeps its own names (no prefix), so ``JOINT_NAMES``/``BODY_NAMES`` index the model;
scene pieces are prefixed (``ground/``, ``table/``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from otr_gym.robot import ASSETS_DIR, G1_MJCF

GROUND_XML = ASSETS_DIR / "scenes" / "ground.xml"
TABLE_XML = ASSETS_DIR / "scenes" / "table.xml"


@dataclass(frozen=True)
class ObjectSpec:
    """A free rigid object: ``mesh`` (file path) or ``vertices``/``faces`` arrays (m, object
    frame), or a ``box_half_extents`` primitive."""

    name: str
    mesh: Path | None = None
    vertices: np.ndarray | None = None
    faces: np.ndarray | None = None
    box_half_extents: tuple[float, float, float] | None = None
    mass_kg: float = 2.0
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    rgba: tuple[float, float, float, float] = (0.8, 0.55, 0.3, 1.0)
    friction: float = 0.6


@dataclass(frozen=True)
class TableSpec:
    """Static table; ``pos`` is the centre of the top's upper face (m, world)."""

    pos: tuple[float, float, float] = (1.0, 0.0, 0.75)
    half_extents: tuple[float, float] = (0.4, 0.3)


@dataclass(frozen=True)
class SceneSpec:
    robot: bool = True
    ground: bool = True
    visual: bool = True  # keep the robot's visual meshes (rendering, evaluation); off for fast GPU sims
    table: TableSpec | None = None
    objects: tuple[ObjectSpec, ...] = field(default_factory=tuple)


@dataclass
class Scene:
    spec: mujoco.MjSpec
    model: mujoco.MjModel
    object_names: tuple[str, ...]


def _robot_spec(visual: bool) -> mujoco.MjSpec:
    spec = mujoco.MjSpec.from_file(str(G1_MJCF))
    # $OTR_G1_MESH_DIR swaps the visual meshes for same-named files elsewhere: Unitree's
    # originals, to judge a reference on the true surface (otr_gym.true_surface)
    if os.environ.get("OTR_G1_MESH_DIR"):
        spec.meshdir = os.environ["OTR_G1_MESH_DIR"]
    if not visual:
        for geom in list(spec.geoms):
            if geom.type == mujoco.mjtGeom.mjGEOM_MESH and geom.contype == 0 and geom.conaffinity == 0:
                spec.delete(geom)
        for mesh in list(spec.meshes):
            spec.delete(mesh)
    return spec


def _add_table(spec: mujoco.MjSpec, table: TableSpec) -> None:
    piece = mujoco.MjSpec.from_file(str(TABLE_XML))
    hx, hy = table.half_extents
    height = table.pos[2]
    for geom in piece.geoms:
        if geom.name == "table_top":
            geom.size = [hx, hy, 0.02]
            geom.pos = [0.0, 0.0, height - 0.02]
        else:
            sx, sy = np.sign(geom.pos[0]), np.sign(geom.pos[1])
            geom.size = [0.02, 0.02, 0.5 * (height - 0.04)]
            geom.pos = [sx * (hx - 0.04), sy * (hy - 0.04), 0.5 * (height - 0.04)]
    frame = spec.worldbody.add_frame(pos=[table.pos[0], table.pos[1], 0.0])
    spec.attach(piece, prefix="table/", frame=frame)


def _add_object(spec: mujoco.MjSpec, obj: ObjectSpec) -> None:
    body = spec.worldbody.add_body(name=obj.name, pos=list(obj.pos), quat=list(obj.quat_wxyz))
    body.add_freejoint(name=f"{obj.name}_freejoint")
    geom_kw = dict(rgba=list(obj.rgba), friction=[obj.friction, 0.005, 0.0001], mass=obj.mass_kg)
    if obj.mesh is not None or obj.vertices is not None:
        import trimesh

        if obj.vertices is not None:
            mesh = trimesh.Trimesh(np.asarray(obj.vertices), np.asarray(obj.faces), process=False)
        else:
            assert obj.mesh is not None  # checked above: a mesh file or vertices
            path = Path(obj.mesh)
            if not path.is_file():
                raise FileNotFoundError(f"{path}: object mesh for '{obj.name}' not found")
            mesh = trimesh.load(path, force="mesh", process=False)  # type: ignore[assignment]
        if len(mesh.faces) > 2000:  # MuJoCo collides with the convex hull; keep the visual light
            mesh = mesh.convex_hull
        spec.add_mesh(name=f"{obj.name}_mesh", uservert=np.asarray(mesh.vertices, np.float64).ravel().tolist(),
                      userface=np.asarray(mesh.faces, np.int32).ravel().tolist())
        body.add_geom(name=f"{obj.name}_geom", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"{obj.name}_mesh",
                      **geom_kw)
    elif obj.box_half_extents is not None:
        body.add_geom(name=f"{obj.name}_geom", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(obj.box_half_extents),
                      **geom_kw)
    else:
        raise ValueError(f"object '{obj.name}' needs a mesh or box_half_extents")


def build_scene(scene: SceneSpec) -> Scene:
    """Compile the scene. The G1 spec is the base, so robot names are unprefixed and its qpos
    comes first; the ground is ``ground/ground``, the table ``table/...``, objects keep their names."""
    spec = _robot_spec(scene.visual) if scene.robot else mujoco.MjSpec()
    if scene.ground:
        ground = mujoco.MjSpec.from_file(str(GROUND_XML))
        spec.attach(ground, prefix="ground/", frame=spec.worldbody.add_frame())
        # attach() carries bodies and assets but not <visual>: copy the render settings
        spec.visual.headlight.diffuse = ground.visual.headlight.diffuse
        spec.visual.headlight.ambient = ground.visual.headlight.ambient
        spec.visual.headlight.specular = ground.visual.headlight.specular
        spec.visual.global_.offwidth = ground.visual.global_.offwidth
        spec.visual.global_.offheight = ground.visual.global_.offheight
    if scene.table is not None:
        _add_table(spec, scene.table)
    for obj in scene.objects:
        _add_object(spec, obj)
    model = spec.compile()
    return Scene(spec=spec, model=model, object_names=tuple(o.name for o in scene.objects))


def robot_model(visual: bool = True) -> mujoco.MjModel:
    """The G1 alone as an ``mujoco.MjModel`` (no ground, no objects)."""
    return build_scene(SceneSpec(ground=False, visual=visual)).model
