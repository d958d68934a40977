"""Probe clouds of the robot, the demonstrator and objects, and how to pose them.

A :class:`ProbeSet` holds surface points grouped by the body that carries them (contiguous per
body), each in its body frame (G1 link frame, human part frame, object mesh frame). Densities
are the paper's (Sec. III-A): 2000 pts/m² on the robot and the human, 1000 pts/m² on objects.

The robot and the objects also carry *guard points*: the vertices of each body's convex hull
(thinned to a few millimetres; for objects also points along the hull's edges). They enter
only the non-penetration constraints, never the cost: against a plane the lowest point of a
body is always a hull vertex, so guarding the hull keeps every visual-mesh vertex above the
ground, which area samples 2 cm apart cannot promise; and an object's edges and corners, which
indent a robot link between its probes, are checked against the link's own distance field, as
are an object's surface points (``object_surface_guards``), for faces pressed into a link's hollows.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numba
import numpy as np
from scipy.spatial import ConvexHull

from otr_gym import robot
from otr_gym.robot_geometry import visual_meshes
from retarget.geometry.channels import GeometryConfig, sample_surface
from retarget.geometry.jit import inlined
from retarget.inputs.human_surface import HumanSurface
from retarget.inputs.meshes import TriMesh, as_trimesh


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


@dataclass(frozen=True)
class PointClusters:
    """Runs of consecutive points of a :class:`ProbeSet` (same body, same ``size_m`` voxel):
    their body, centre and radius in the body frame, and their point ranges. A query first
    tests clusters, then poses only the points of the clusters that can matter."""

    body: np.ndarray  # (K,) sorted
    centre: np.ndarray  # (K, 3) body frame (m)
    radius: np.ndarray  # (K,) m
    offsets: np.ndarray  # (K + 1,): cluster k holds points offsets[k]:offsets[k + 1]
    body_offsets: np.ndarray  # (B + 1,): the clusters of body b are body_offsets[b]:body_offsets[b + 1]

    def of_bodies(self, bodies: np.ndarray) -> np.ndarray:
        """(k,) indices of the clusters of ``bodies`` (any order, repeats allowed), concatenated."""
        bodies = np.asarray(bodies, np.intp)
        out = np.empty(int(np.sum(self.body_offsets[bodies + 1] - self.body_offsets[bodies])), np.intp)
        _ranges(self.body_offsets, bodies, out)
        return out

    def points_of(self, clusters: np.ndarray) -> np.ndarray:
        """(k,) indices of the points of ``clusters``, concatenated in that order."""
        clusters = np.asarray(clusters, np.intp)
        out = np.empty(int(np.sum(self.offsets[clusters + 1] - self.offsets[clusters])), np.intp)
        _ranges(self.offsets, clusters, out)
        return out


def _voxel_keys(points: np.ndarray, size_m: float) -> np.ndarray:
    cell = np.floor(points / size_m).astype(np.int64)
    cell -= cell.min(axis=0) if len(cell) else 0
    return (cell[:, 0] * 4096 + cell[:, 1]) * 4096 + cell[:, 2]


def voxel_sorted(probes: ProbeSet, size_m: float) -> ProbeSet:
    """The same points, sorted within each body by ``size_m`` voxel (clusters become runs)."""
    order = np.lexsort((_voxel_keys(probes.points, size_m), probes.body))
    return ProbeSet(probes.body_names, probes.points[order], probes.body[order])


def point_clusters(probes: ProbeSet, size_m: float) -> PointClusters:
    """The voxel runs of a :func:`voxel_sorted` probe set."""
    key = _voxel_keys(probes.points, size_m)
    starts = np.flatnonzero(np.concatenate([[True], (key[1:] != key[:-1]) | (probes.body[1:] != probes.body[:-1])]))
    offsets = np.append(starts, len(probes.points))
    counts = np.diff(offsets)
    centre = np.add.reduceat(probes.points, starts, axis=0) / counts[:, None]
    owner = np.repeat(np.arange(len(starts)), counts)
    radius = np.zeros(len(starts))
    np.maximum.at(radius, owner, np.linalg.norm(probes.points - centre[owner], axis=1))
    body = probes.body[starts]
    body_offsets = np.searchsorted(body, np.arange(len(probes.body_names) + 1))
    return PointClusters(body, centre, radius, offsets, body_offsets)


def posed_in_frames(points: np.ndarray, body: np.ndarray, frame: np.ndarray, rot: np.ndarray,
                    pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World positions (k, 3) of body-frame points (k, 3) on bodies ``body`` (k,), and the same
    points in the frames of bodies ``frame`` (k,): R_fᵀ(R_b p + o_b − o_f). One pass, no gathered
    rotation matrices (the self-collision hot path)."""
    n = len(points)
    out_w, out_f = np.empty((n, 3)), np.empty((n, 3))
    _pose_into(np.ascontiguousarray(points, np.float64), np.asarray(body, np.intp), np.asarray(frame, np.intp),
               rot, pos, out_w, out_f)
    return out_w, out_f


@numba.njit(cache=True)
def _pose_into(points, body, frame, rot, pos, out_w, out_f):
    for k in range(points.shape[0]):
        b, f = body[k], frame[k]
        for r in range(3):
            out_w[k, r] = (rot[b, r, 0] * points[k, 0] + rot[b, r, 1] * points[k, 1] + rot[b, r, 2] * points[k, 2]
                           + pos[b, r])
        d0, d1, d2 = out_w[k, 0] - pos[f, 0], out_w[k, 1] - pos[f, 1], out_w[k, 2] - pos[f, 2]
        for r in range(3):
            out_f[k, r] = rot[f, 0, r] * d0 + rot[f, 1, r] * d1 + rot[f, 2, r] * d2


@inlined
def _pose_in_frame(points, i, body, frame, rot, pos):
    """Point i of ``points`` on ``body``: its world position and its position in the frame of
    ``frame``, as six scalars (the arithmetic of :func:`_pose_into`)."""
    w0, w1, w2 = _posed_point(points, i, body, rot, pos)
    return (w0, w1, w2) + _in_frame(w0, w1, w2, frame, rot, pos)


@inlined
def _posed_point(points, i, body, rot, pos):
    """Point i of ``points`` (frame of ``body``) in the world (the arithmetic of :func:`_pose_into`)."""
    return (rot[body, 0, 0] * points[i, 0] + rot[body, 0, 1] * points[i, 1] + rot[body, 0, 2] * points[i, 2]
            + pos[body, 0],
            rot[body, 1, 0] * points[i, 0] + rot[body, 1, 1] * points[i, 1] + rot[body, 1, 2] * points[i, 2]
            + pos[body, 1],
            rot[body, 2, 0] * points[i, 0] + rot[body, 2, 1] * points[i, 1] + rot[body, 2, 2] * points[i, 2]
            + pos[body, 2])


@inlined
def _in_frame(w0, w1, w2, frame, rot, pos):
    """World point w in the frame of ``frame``, Rᵀ(w − o) summed left to right (the arithmetic of
    :func:`_pose_into`, and of numpy's einsum "kji,kj->ki")."""
    d0, d1, d2 = w0 - pos[frame, 0], w1 - pos[frame, 1], w2 - pos[frame, 2]
    return (rot[frame, 0, 0] * d0 + rot[frame, 1, 0] * d1 + rot[frame, 2, 0] * d2,
            rot[frame, 0, 1] * d0 + rot[frame, 1, 1] * d1 + rot[frame, 2, 1] * d2,
            rot[frame, 0, 2] * d0 + rot[frame, 1, 2] * d1 + rot[frame, 2, 2] * d2)


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
            out[m, r] = (rot[b, r, 0] * points[p, 0] + rot[b, r, 1] * points[p, 1] + rot[b, r, 2] * points[p, 2]
                         + pos[b, r])


def _stack(names: tuple[str, ...], clouds: list[np.ndarray]) -> ProbeSet:
    body = np.concatenate([np.full(len(c), k, dtype=np.intp) for k, c in enumerate(clouds)])
    points = np.concatenate(clouds) if clouds else np.zeros((0, 3))
    return ProbeSet(names, np.ascontiguousarray(points, np.float64), body)


@lru_cache(maxsize=4)
def robot_probes(density_per_m2: float = GeometryConfig.robot_density_per_m2, seed: int = 0,
                 max_per_link: int | None = None, even: bool = False) -> ProbeSet:
    """Area-uniform samples of every G1 link's visual mesh (link frames), links in BODY_NAMES order.

    Links without a visual mesh carry no probe. The sampling is deterministic (seed per link).
    ``max_per_link`` keeps only the first samples of a larger link: the samples are i.i.d.
    uniform, so that is the same surface at a lower density (the torso's 0.56 m² would
    otherwise carry a quarter of all probes; E_int normalises each link by its active count).
    ``even``: each link's cloud an even cover (``sample_surface``; its prefixes are even covers too).
    """
    meshes = visual_meshes()
    clouds = []
    for k, name in enumerate(robot.BODY_NAMES):
        if name not in meshes:
            clouds.append(np.zeros((0, 3)))
            continue
        m = meshes[name]
        points = sample_surface(as_trimesh(m.vertices, m.faces, name), density_per_m2, seed + k, even).points
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


#: Spacing of an object's surface guard points (m): the evaluation's own
#: (``retarget.checks.verify.object_in_robot_depth``). Hull and edge guards miss a flat face pressed
#: into a concave part of a link: on the OMOMO box ×1.3 a face point 23 mm from the nearest
#: guard went 1.5 mm into the right wrist.
OBJECT_SURFACE_GUARD_M = 0.005
#: Voxel of their clusters (m): the solver keeps one row per cluster and link, its deepest point.
OBJECT_GUARD_CLUSTER_M = 0.02


@dataclass(frozen=True)
class SurfaceGuards:
    """An object's surface points (object frame, sorted into clusters) and their clusters."""

    points: np.ndarray  # (S, 3)
    clusters: PointClusters

    @cached_property
    def _centre_sq(self) -> np.ndarray:
        return np.einsum("ki,ki->k", self.clusters.centre, self.clusters.centre)

    def clusters_near(self, centres: np.ndarray, reach: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(sphere, cluster) index pairs of the clusters that come within ``reach`` (n,) of the
        spheres' ``centres`` (n, 3), object frame: the centre gap less the cluster's radius.
        Squared gaps from one matrix product (a few links against thousands of clusters)."""
        sq = (np.einsum("ni,ni->n", centres, centres)[:, None] + self._centre_sq[None]
              - 2.0 * centres @ self.clusters.centre.T)
        return np.nonzero(sq < (reach[:, None] + self.clusters.radius[None]) ** 2)


def object_surface_guards(mesh: TriMesh, spacing_m: float = OBJECT_SURFACE_GUARD_M,
                          cluster_m: float = OBJECT_GUARD_CLUSTER_M, seed: int = 0) -> SurfaceGuards:
    """The mesh's vertices and area samples, thinned to one per ``spacing_m`` voxel (mesh frame),
    in ``cluster_m`` voxel clusters. Samples are drawn twice as dense as the spacing asks so that
    the thinned cloud leaves no cell empty where the surface passes."""
    samples = sample_surface(mesh, 2.0 / spacing_m**2, seed).points
    points = np.concatenate([np.asarray(mesh.vertices, np.float64), samples])
    _, first = np.unique(np.floor(points / spacing_m).astype(np.int64), axis=0, return_index=True)
    cloud = voxel_sorted(ProbeSet(("object",), points[np.sort(first)], np.zeros(len(first), np.intp)), cluster_m)
    return SurfaceGuards(cloud.points, point_clusters(cloud, cluster_m))


def segment_argmin(values: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Index of the smallest value of each consecutive segment of ``counts`` (n,) entries (≥ 1)."""
    out = np.empty(len(counts), np.intp)
    _segment_argmin(np.asarray(values, np.float64), np.asarray(counts, np.intp), out)
    return out


@numba.njit(cache=True)
def _segment_argmin(values, counts, out):
    start = 0
    for s in range(counts.shape[0]):
        best = start
        for k in range(start + 1, start + counts[s]):
            if values[k] < values[best]:
                best = k
        out[s] = best
        start += counts[s]


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


#: Voxel of the vertex clusters (m): a few dozen vertices each, up to a thousand per link.
VERTEX_CLUSTER_M = 0.02


#: Spacing of the self-collision points (m): one visual-mesh vertex per 4 mm voxel. Two robot
#: shells meet at smooth or rounded parts, where a 4 mm gap between points hides less than
#: 0.1 mm of curvature (s²/8R on the arms' 3.5 cm radius).
SELF_POINT_SPACING_M = 0.004


@lru_cache(maxsize=1)
def robot_self_points() -> tuple[ProbeSet, PointClusters]:
    """The G1's self-collision points (visual-mesh vertices thinned to one per
    ``SELF_POINT_SPACING_M`` voxel, link frames), sorted into clusters, and the clusters."""
    guards = robot_vertex_guards()
    clouds = []
    for k in range(len(guards.body_names)):
        pts = guards.points[guards.body == k]
        _, first = np.unique(np.floor(pts / SELF_POINT_SPACING_M).astype(np.int64), axis=0, return_index=True)
        clouds.append(pts[np.sort(first)])
    points = voxel_sorted(_stack(guards.body_names, clouds), VERTEX_CLUSTER_M)
    return points, point_clusters(points, VERTEX_CLUSTER_M)


def human_probes(surface: HumanSurface, density_per_m2: float = GeometryConfig.human_density_per_m2,
                 seed: int = 0, scale: float = 1.0, even: bool = False) -> ProbeSet:
    """Area-uniform samples of every human part's surface (part frames, × ``scale``); ``even``: an
    even cover of each part (``sample_surface``)."""
    clouds = []
    for k, (name, v, f) in enumerate(zip(surface.part_names, surface.vertices, surface.faces)):
        mesh = as_trimesh(np.asarray(v) * scale, f, f"human part {name}")
        clouds.append(sample_surface(mesh, density_per_m2, seed + k, even).points)
    return _stack(tuple(surface.part_names), clouds)
