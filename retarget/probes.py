"""Probe clouds of the robot, the demonstrator and objects, and how to pose them.

A :class:`ProbeSet` holds surface points grouped by the body that carries them (contiguous per
body), each in its body frame (G1 link frame, human part frame, object mesh frame). Densities
are the paper's (Sec. III-A): 2000 pts/m² on the robot and the human, 1000 pts/m² on objects.

The robot and the objects also carry *guard points*: the vertices of each body's convex hull
(thinned to a few millimetres; for objects also points along the hull's edges). They enter
only the non-penetration constraints, never the cost: against a plane the lowest point of a
body is always a hull vertex, so guarding the hull keeps every visual-mesh vertex above the
ground, which area samples 2 cm apart cannot promise; and an object's edges and corners, which
indent a robot link between its probes, are checked against the link's own distance field.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numba
import numpy as np
from scipy.spatial import ConvexHull

from otr_gym import robot
from otr_gym.robot_geometry import visual_meshes
from retarget.human_surface import HumanSurface
from retarget.geometry import GeometryConfig, sample_surface
from retarget.meshes import as_trimesh


@dataclass(frozen=True)
class ProbeSet:
    """Points (P, 3) in their body frames; ``body`` (P,) indexes ``body_names``; sorted by body."""

    body_names: tuple[str, ...]
    points: np.ndarray
    body: np.ndarray

    def __len__(self) -> int:
        return len(self.points)

    @property
    def counts(self) -> np.ndarray:
        return np.bincount(self.body, minlength=len(self.body_names))

    @cached_property
    def offsets(self) -> np.ndarray:
        """(B + 1,): probes of body k are rows offsets[k]:offsets[k + 1]."""
        return np.concatenate([[0], np.cumsum(self.counts)])

    def posed(self, rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """World points (…, P, 3) for body rotations (…, B, 3, 3) and origins (…, B, 3)."""
        r = rot[..., self.body, :, :]
        return np.einsum("...pij,pj->...pi", r, self.points) + pos[..., self.body, :]

    def indices_of(self, bodies: np.ndarray) -> np.ndarray:
        """(k,) indices of the points of ``bodies`` (sorted body indices), in order."""
        off = self.offsets
        bodies = np.asarray(bodies, np.intp)
        out = np.empty(int(np.sum(off[bodies + 1] - off[bodies])), np.intp)
        _ranges(off, bodies, out)
        return out

    def posed_index(self, index: np.ndarray, rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """World points (k, 3) of the points ``index`` (k,) for body rotations (B, 3, 3) and
        origins (B, 3): the hot-path form, one pass without gathering rotations per point."""
        out = np.empty((len(index), 3))
        _pose(self.points, self.body, np.asarray(index, np.intp), rot, pos, out)
        return out

    def posed_bodies(self, bodies: np.ndarray, rot: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(indices, world points) of the probes of ``bodies`` (sorted body indices)."""
        index = self.indices_of(bodies)
        return index, self.posed_index(index, rot, pos)

    def bounding_spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """Per body: centre (B, 3) in the body frame and radius (B,) enclosing its probes."""
        centre = np.zeros((len(self.body_names), 3))
        radius = np.zeros(len(self.body_names))
        for k in range(len(self.body_names)):
            pts = self.points[self.body == k]
            if len(pts):
                centre[k] = 0.5 * (pts.min(0) + pts.max(0))
                radius[k] = np.linalg.norm(pts - centre[k], axis=1).max()
        return centre, radius


@numba.njit(cache=True)
def _ranges(offsets, bodies, out):
    """out ← the concatenated ranges offsets[b]:offsets[b + 1] of ``bodies``."""
    m = 0
    for b in bodies:
        for p in range(offsets[b], offsets[b + 1]):
            out[m] = p
            m += 1


@numba.njit(cache=True)
def _pose(points, body, index, rot, pos, out):
    """out[m] ← rot[b] points[p] + pos[b] for p = index[m], b = body[p]."""
    for m in range(index.shape[0]):
        p = index[m]
        b = body[p]
        for r in range(3):
            out[m, r] = rot[b, r, 0] * points[p, 0] + rot[b, r, 1] * points[p, 1] + rot[b, r, 2] * points[p, 2] + pos[b, r]


def _stack(names: tuple[str, ...], clouds: list[np.ndarray]) -> ProbeSet:
    body = np.concatenate([np.full(len(c), k, dtype=np.intp) for k, c in enumerate(clouds)])
    points = np.concatenate(clouds) if clouds else np.zeros((0, 3))
    return ProbeSet(names, np.ascontiguousarray(points, np.float64), body)


@lru_cache(maxsize=4)
def robot_probes(density_per_m2: float = GeometryConfig.robot_density_per_m2, seed: int = 0,
                 max_per_link: int | None = None) -> ProbeSet:
    """Area-uniform samples of every G1 link's visual mesh (link frames), links in BODY_NAMES order.

    Links without a visual mesh carry no probe. The sampling is deterministic (seed per link).
    ``max_per_link`` keeps only the first samples of a larger link: the samples are i.i.d.
    uniform, so that is the same surface at a lower density (the torso's 0.56 m² would
    otherwise carry a quarter of all probes; E_int normalises each link by its active count).
    """
    meshes = visual_meshes()
    clouds = []
    for k, name in enumerate(robot.BODY_NAMES):
        if name not in meshes:
            clouds.append(np.zeros((0, 3)))
            continue
        m = meshes[name]
        points = sample_surface(as_trimesh(m.vertices, m.faces, name), density_per_m2, seed + k).points
        clouds.append(points if max_per_link is None else points[:max_per_link])
    return _stack(robot.BODY_NAMES, clouds)


def hull_guard_points(vertices: np.ndarray, spacing_m: float, along_edges: bool = False) -> np.ndarray:
    """Vertices of the convex hull of ``vertices`` (and, with ``along_edges``, points every
    ``spacing_m`` along the hull's edges), thinned to one per ``spacing_m`` voxel (same frame).

    Hull vertices are where a body first meets a plane; edge points are where a convex body's
    edge first cuts into a curved surface (a box edge pressed into an arm).
    """
    hull = ConvexHull(vertices)
    points = [vertices[hull.vertices]]
    if along_edges:
        # feature edges only: the two facets meeting there turn by more than ~20°
        normal = hull.equations[:, :3]
        edges = []
        for k in range(3):
            sharp = np.einsum("ij,ij->i", normal, normal[hull.neighbors[:, k]]) < np.cos(np.radians(20.0))
            edges.append(np.delete(hull.simplices, k, axis=1)[sharp])
        edges = np.unique(np.sort(np.concatenate(edges), axis=1), axis=0)
        a, b = vertices[edges[:, 0]], vertices[edges[:, 1]]
        count = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / spacing_m).astype(int), 1)
        frac = np.concatenate([np.zeros(0)] + [np.arange(1, c) / c for c in count])  # a smooth hull has none
        seg = np.repeat(np.arange(len(edges)), count - 1)
        points.append(a[seg] + frac[:, None] * (b[seg] - a[seg]))
    points = np.concatenate(points)
    _, first = np.unique(np.floor(points / spacing_m).astype(np.int64), axis=0, return_index=True)
    return points[np.sort(first)]


@lru_cache(maxsize=4)
def robot_guard_points(spacing_m: float = 0.008) -> ProbeSet:
    """Convex-hull vertices of every G1 link's visual mesh, one per ``spacing_m`` voxel (link frames)."""
    meshes = visual_meshes()
    clouds = [hull_guard_points(meshes[name].vertices, spacing_m) if name in meshes else np.zeros((0, 3))
              for name in robot.BODY_NAMES]
    return _stack(robot.BODY_NAMES, clouds)


@lru_cache(maxsize=1)
def robot_vertex_guards() -> ProbeSet:
    """Every distinct visual-mesh vertex of every G1 link (link frames): the points an exact
    check of the meshes looks at, for the channels (objects) whose edges and concave parts
    (handles) reach between hull vertices. Thinning them is not safe: on the OMOMO box a
    4 mm thinning left a torso vertex 1.2 mm deep while its neighbours 3 mm away were clear."""
    meshes = visual_meshes()
    clouds = [np.unique(meshes[name].vertices, axis=0) if name in meshes else np.zeros((0, 3))
              for name in robot.BODY_NAMES]
    return _stack(robot.BODY_NAMES, clouds)


def human_probes(surface: HumanSurface, density_per_m2: float = GeometryConfig.human_density_per_m2,
                 seed: int = 0, scale: float = 1.0) -> ProbeSet:
    """Area-uniform samples of every human part's surface (part frames, × ``scale``)."""
    clouds = []
    for k, (name, v, f) in enumerate(zip(surface.part_names, surface.vertices, surface.faces)):
        mesh = as_trimesh(np.asarray(v) * scale, f, f"human part {name}")
        clouds.append(sample_surface(mesh, density_per_m2, seed + k).points)
    return _stack(tuple(surface.part_names), clouds)
