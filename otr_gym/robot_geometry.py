"""G1 geometry read from the compiled MJCF: visual meshes and collision primitives per body.

Everything is expressed in the **body frame** of the link that carries it (m), so posing a
link is ``R_body @ v + p_body`` with the body pose from MuJoCo or Pinocchio forward
kinematics. MuJoCo recentres meshes at compile time and folds the offset into the geom pose;
reading the compiled model keeps both consistent.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import mujoco
import numpy as np

from otr_gym import robot
from otr_gym.rotations import quat_to_matrix
from otr_gym.scene import robot_model

VISUAL_GROUP = 2
COLLISION_GROUP = 3


@dataclass(frozen=True)
class LinkMesh:
    """A link's visual surface in its body frame (all visual geoms of the body merged)."""

    body: str
    vertices: np.ndarray  # (V, 3) m, body frame
    faces: np.ndarray  # (F, 3) int
    mesh_names: tuple[str, ...] = ()  # the MJCF meshes merged into it

    @property
    def area_m2(self) -> float:
        tri = self.vertices[self.faces]
        return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())


@dataclass(frozen=True)
class Capsule:
    """A collision capsule (or sphere when half_length = 0) in its body frame."""

    body: str
    name: str
    p0: np.ndarray  # (3,) segment end, body frame
    p1: np.ndarray  # (3,)
    radius: float


@lru_cache(maxsize=1)
def _model() -> mujoco.MjModel:
    return robot_model(visual=True)


@lru_cache(maxsize=1)
def visual_meshes() -> dict[str, LinkMesh]:
    """Body name -> merged visual mesh in the body frame, for every G1 body with one."""
    m = _model()
    parts: dict[str, tuple[list, list, int]] = {}
    names: dict[str, list[str]] = {}
    for g in range(m.ngeom):
        if int(m.geom_type[g]) != int(mujoco.mjtGeom.mjGEOM_MESH) or m.geom_group[g] != VISUAL_GROUP:
            continue
        body = m.body(m.geom_bodyid[g]).name
        mid = m.geom_dataid[g]
        v0, nv = m.mesh_vertadr[mid], m.mesh_vertnum[mid]
        f0, nf = m.mesh_faceadr[mid], m.mesh_facenum[mid]
        verts = m.mesh_vert[v0:v0 + nv] @ quat_to_matrix(m.geom_quat[g]).T + m.geom_pos[g]
        faces = m.mesh_face[f0:f0 + nf]
        vs, fs, n = parts.get(body, ([], [], 0))
        vs.append(verts)
        fs.append(faces + n)
        parts[body] = (vs, fs, n + nv)
        names.setdefault(body, []).append(m.mesh(mid).name)
    return {b: LinkMesh(b, np.concatenate(vs).astype(np.float64), np.concatenate(fs).astype(np.int64), tuple(names[b]))
            for b, (vs, fs, _) in parts.items()}


@lru_cache(maxsize=1)
def surface_margin_m() -> np.ndarray:
    """(L,) m per G1 body (BODY_NAMES order): how far Unitree's original surface can lie from
    the shipped visual mesh (the largest error of its meshes, ``otr_gym.true_surface``), 0 for
    bodies without a mesh. Adding it to a clearance makes a check conservative for the true
    surface."""
    from otr_gym.true_surface import surface_error_m

    error = surface_error_m()
    meshes = visual_meshes()
    return np.array([max((error[n] for n in meshes[b].mesh_names), default=0.0) if b in meshes else 0.0
                     for b in robot.BODY_NAMES])


@lru_cache(maxsize=1)
def collision_capsules() -> tuple[Capsule, ...]:
    """Capsules and spheres of the collision geoms (group 3), foot capsules included."""
    m = _model()
    out = []
    for g in range(m.ngeom):
        if m.geom_group[g] != COLLISION_GROUP:
            continue
        kind = int(m.geom_type[g])
        if kind not in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_SPHERE)):
            continue
        half = m.geom_size[g, 1] if kind == int(mujoco.mjtGeom.mjGEOM_CAPSULE) else 0.0
        axis = quat_to_matrix(m.geom_quat[g])[:, 2]
        c = m.geom_pos[g]
        out.append(Capsule(m.body(m.geom_bodyid[g]).name, m.geom(g).name, c - half * axis, c + half * axis,
                           float(m.geom_size[g, 0])))
    return tuple(out)


@dataclass(frozen=True)
class CollisionPoint:
    """A point of a collision geom, body frame, with the radius of the geom's surface around it."""

    body: str
    geom: str
    point: np.ndarray  # (3,) m, body frame
    radius: float  # m (0 for a box corner)


@lru_cache(maxsize=1)
def collision_points() -> tuple[CollisionPoint, ...]:
    """The robot's geometry as the simulation collides it (collision geoms with a non-zero
    contype or conaffinity), reduced to points whose balls reach as low as the geom does over any
    plane: a capsule's two end-sphere centres, a sphere's centre (with the radius), a box's eight
    corners (radius 0). So the geom's depth below a plane or an upward face is the deepest of
    ``radius − height`` over its points. The coarse hand capsules the retargeter uses for
    self-collision (contype 0) are not among them: the simulation's hands are the three boxes."""
    m = _model()
    capsule, sphere, box = (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_SPHERE),
                            int(mujoco.mjtGeom.mjGEOM_BOX))
    out = []
    for g in range(m.ngeom):
        if m.geom_group[g] != COLLISION_GROUP or not (m.geom_contype[g] or m.geom_conaffinity[g]):
            continue
        kind, size, body, name = int(m.geom_type[g]), m.geom_size[g], m.body(m.geom_bodyid[g]).name, m.geom(g).name
        rot, centre = quat_to_matrix(m.geom_quat[g]), m.geom_pos[g]
        if kind == capsule:
            points, radius = [centre - size[1] * rot[:, 2], centre + size[1] * rot[:, 2]], float(size[0])
        elif kind == sphere:
            points, radius = [centre], float(size[0])
        elif kind == box:
            signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
            points, radius = list(centre + (signs * size[:3]) @ rot.T), 0.0
        else:
            raise ValueError(f"{robot.G1_MJCF}: collision geom '{name}' of type {kind} has no point reduction")
        out += [CollisionPoint(body, name, np.asarray(p, np.float64), radius) for p in points]
    return tuple(out)


def posed_vertices(mesh: LinkMesh, pos_w: np.ndarray, quat_w: np.ndarray) -> np.ndarray:
    """World vertices (…, V, 3) of a link mesh for body poses (…, 3) / (…, 4) wxyz."""
    rot = quat_to_matrix(np.asarray(quat_w, np.float64))
    return np.einsum("...ij,vj->...vi", rot, mesh.vertices) + np.asarray(pos_w)[..., None, :]
