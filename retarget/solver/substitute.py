"""Object substitution and resizing (paper Sec. III-E, contribution C3): one demonstration, new objects.

``substitute(demo, ShapeSpec("ball"))`` returns the demonstration with its manipulated object
replaced by a substitute (a library shape, a user mesh, or the object itself resized,
``retarget.inputs.shapes``). The substitute rides the demonstrated track (its mesh is expressed in the
demonstrated object's frame) and, like the original, is a decision variable of the solver.

What changes in the problem (``retarget.solver.problem.build_problem`` reads :class:`SubstituteObject`):

* **Correspondences.** Entropic OT (eq. m-sinkhorn, ε_ot = 0.1, ``retarget.solver.transport``)
  between the two surface clouds, each in the object frame, centred and normalised to unit RMS
  radius, uniform marginals; each point takes the argmax of the plan (eq. m-ot).
* **Witnesses.** A demonstrated triple (d̂, ŵ, n̂) of any probe against the captured object is
  measured on the captured surface, then ŵ is carried onto the substitute surface by
  :class:`SurfaceMap` and n̂ is turned with the surface normal (the minimal rotation taking the
  captured normal at ŵ to the substitute's at the mapped point). d̂ is kept in metres: the
  normalisation serves only to find correspondences, targets keep their metric meaning.
* **Object probes.** Each probe of the substitute takes the demonstrated triples (against the
  ground, the table, other objects) of its corresponding point on the captured surface.

:class:`SurfaceMap` (our choice; the paper maps witnesses without saying how points between
samples are treated): the argmax assignment defines a displacement at every sample of the
source cloud; a point moves by the Gaussian blend of its nearest samples' displacements, then
is projected onto the target mesh (exact closest point, so every mapped witness lies on the
substitute's surface). With ``debias`` (default) the displacement is measured from the
source's own self-transport image instead of from the sample itself: entropic OT of a cloud
onto itself is not the identity (ε blurs the plan), and subtracting that self-image makes an
identical substitute map exactly onto itself. Measured on the OMOMO large box, 12.8k surface
points off the plan's 2000 samples, error to the known answer (median / p95 / max, mm;
``benchmarks/substitution_map.py``): identical substitute 1.6 / 10.0 / 23 plain, 0 debiased;
×1.6 resize 4.7 / 17.3 / 37 plain, 3.6 / 8.6 / 16 debiased; ×0.7 2.2 / 7.1 / 17 plain,
1.8 / 4.2 / 7.7 debiased.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import igl
import numpy as np
from scipy.spatial import cKDTree

from otr_gym.rotations import quat_apply, quat_from_rotvec
from retarget.geometry.channels import GeometryConfig, SDFChannel, sample_surface
from retarget.inputs.demonstration import Demonstration, DemoObject, InvalidDemonstrationError
from retarget.inputs.meshes import TriMesh, as_trimesh
from retarget.inputs.shapes import ShapeSpec, substitute_mesh
from retarget.solver.transport import TransportConfig, correspondence


@dataclass(frozen=True)
class SubstitutionConfig:
    """Object↔object transport settings (Sec. III-E; our choices where marked)."""

    #: ε_ot of eq. m-sinkhorn, the value of the human↔robot plans (the paper reuses that formulation).
    epsilon: float = 0.1
    #: Our choice: points sampled on each surface for the plan (equal counts keep the argmax
    #: assignment close to a bijection; 2000 is a 1.3 cm spacing on the large box).
    samples: int = 2000
    #: Our choice: subtract each cloud's self-transport image (module docstring).
    debias: bool = True
    #: Our choice: samples whose displacements are blended at a mapped point.
    neighbours: int = 8
    seed: int = 0


@dataclass(eq=False)
class SubstituteObject(DemoObject):
    """A demonstration object whose mesh replaces the captured one: ``vertices``/``faces`` are the
    substitute (in the captured object's frame), ``pos_w``/``quat_w`` the captured track, and
    ``demonstrated_mesh`` the mesh that was captured (the demonstrated triples are measured on it)."""

    demonstrated_mesh: TriMesh | None = None
    shape: str = ""  # library name, 'original' or a mesh file
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    config: SubstitutionConfig = field(default_factory=SubstitutionConfig)


class SurfaceMap:
    """Points of one surface onto another by blended OT displacements (module docstring).

    Both surfaces are in the same frame (the captured object's). Immutable; the AABB tree of the
    target mesh is built on first use (it cannot be pickled).
    """

    def __init__(self, source_points: np.ndarray, displacement: np.ndarray, target: TriMesh, neighbours: int,
                 spacing_m: float) -> None:
        self.source_points = source_points
        self.displacement = displacement
        self.target = target
        self.neighbours = int(min(neighbours, len(source_points)))
        self.spacing_m = float(spacing_m)
        self._tree = cKDTree(source_points)
        self._aabb = None

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_aabb": None}

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Images (N, 3) on the target surface of points (N, 3) on (or near) the source surface."""
        x = np.ascontiguousarray(x, np.float64).reshape(-1, 3)
        if len(x) == 0:
            return np.zeros((0, 3))
        dist, idx = self._tree.query(x, k=self.neighbours)
        dist, idx = dist.reshape(len(x), -1), idx.reshape(len(x), -1)
        sq = dist**2
        a = np.exp(-0.5 * (sq - sq.min(axis=1, keepdims=True)) / self.spacing_m**2)
        a /= a.sum(axis=1, keepdims=True)
        moved = x + np.einsum("nk,nkj->nj", a, self.displacement[idx])
        return self.project(moved)

    def project(self, x: np.ndarray) -> np.ndarray:
        """Exact closest points (N, 3) of the target mesh."""
        if self._aabb is None:
            self._aabb = igl.AABB()
            self._aabb.init(self.target.vertices, self.target.faces)
        return self._aabb.squared_distance(self.target.vertices, self.target.faces, np.ascontiguousarray(x))[2]


def surface_maps(demonstrated: TriMesh, substitute: TriMesh, cfg: SubstitutionConfig = SubstitutionConfig(),
                 cache_dir: Path | None = None) -> tuple[SurfaceMap, SurfaceMap]:
    """(captured → substitute, substitute → captured) maps from one OT correspondence per
    direction (cached on disk with the other OT assignments)."""
    if cfg.samples < 4:
        raise ValueError(f"substitution needs at least 4 samples per surface, got {cfg.samples}")
    clouds = [sample_surface(m, cfg.samples / m.area_m2, cfg.seed).points for m in (demonstrated, substitute)]
    tcfg = TransportConfig(epsilon=cfg.epsilon)
    label = f"{demonstrated.name} <-> {substitute.name}"

    def image(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
        # for every point of src, the point of dst that receives most of its mass
        return dst[correspondence(dst, src, tcfg, cache_dir=cache_dir, name=label)]

    def surface_map(src: np.ndarray, src_mesh: TriMesh, dst: np.ndarray, dst_mesh: TriMesh) -> SurfaceMap:
        origin = image(src, src) if cfg.debias else src
        spacing = np.sqrt(src_mesh.area_m2 / len(src))
        return SurfaceMap(src, image(src, dst) - origin, dst_mesh, cfg.neighbours, spacing)

    return (surface_map(clouds[0], demonstrated, clouds[1], substitute),
            surface_map(clouds[1], substitute, clouds[0], demonstrated))


def _unit_normals(channel: SDFChannel, w: np.ndarray) -> np.ndarray:
    """Outward unit normals (N, 3) at surface points: the normalised gradient of the channel's
    distance grid (smooth across faces, signed by the winding number, so scans work too)."""
    _, grad, _ = channel.distance(w)
    norm = np.linalg.norm(grad, axis=1, keepdims=True)
    return np.divide(grad, norm, out=np.zeros_like(grad), where=norm > 1e-9)


def _minimal_rotation_apply(a: np.ndarray, b: np.ndarray, v: np.ndarray) -> np.ndarray:
    """v (N, 3) turned by the smallest rotation taking unit a to unit b (rows); where a or b
    is unknown (zero) or they are opposite, v is returned as b's direction × sign(a·v)."""
    axis = np.cross(a, b)
    s = np.linalg.norm(axis, axis=1, keepdims=True)
    c = np.einsum("ij,ij->i", a, b)[:, None]
    angle = np.arctan2(s, c)
    rotvec = np.divide(axis, s, out=np.zeros_like(axis), where=s > 1e-12) * angle
    out = quat_apply(quat_from_rotvec(rotvec), v)
    bad = (np.linalg.norm(a, axis=1) < 0.5) | (np.linalg.norm(b, axis=1) < 0.5) | (c[:, 0] < -0.999)
    if bad.any():
        sign = np.where(np.einsum("ij,ij->i", a[bad], v[bad]) < 0, -1.0, 1.0)[:, None]
        out[bad] = sign * b[bad]
    return out


class Substitution:
    """The captured object of a substituted channel and the maps between the two surfaces."""

    def __init__(self, demonstrated: SDFChannel, substitute: SDFChannel, to_substitute: SurfaceMap,
                 to_demonstrated: SurfaceMap) -> None:
        self.demonstrated = demonstrated
        self.substitute = substitute
        self.to_substitute = to_substitute
        self.to_demonstrated = to_demonstrated

    def demonstrated_points(self, points: np.ndarray) -> np.ndarray:
        """The captured-surface point (N, 3) of each substitute surface point (object probes)."""
        return self.to_demonstrated(points)

    def demonstrated_triples(self, x_c: np.ndarray, band: float) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                          np.ndarray]:
        """Demonstrated triples of points x_c (N, 3, object frame) as seen on the substitute:
        (index of the points within ``band`` of the captured surface, d̂ (m, measured on the
        captured surface), ŵ on the substitute surface, n̂ turned with the surface normal)."""
        lo, hi = self.demonstrated.mesh.bounds
        near = np.flatnonzero(np.all((x_c > lo - band) & (x_c < hi + band), axis=1))
        if len(near) == 0:
            return near, np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))
        q = self.demonstrated.query(x_c[near], exact_witness=True)
        keep = q.d < band
        near = near[keep]
        d, n_demo = q.d[keep], q.n[keep]
        # the grid's witness, up to ~1 mm off the captured surface, put on it: an identical
        # substitute then gets ŵ and n̂ back unchanged
        w_demo = self.to_demonstrated.project(q.w[keep])
        w = self.to_substitute(w_demo)
        n = _minimal_rotation_apply(_unit_normals(self.demonstrated, w_demo), _unit_normals(self.substitute, w), n_demo)
        return near, d, w, n


def substitution_for(obj: DemoObject, channel: SDFChannel, geometry: GeometryConfig,
                     cache_dir: Path | None) -> Substitution | None:
    """The :class:`Substitution` of a demonstration object whose channel is ``channel``; None
    unless ``obj`` is a :class:`SubstituteObject`."""
    if not isinstance(obj, SubstituteObject) or obj.demonstrated_mesh is None:
        return None
    demonstrated = SDFChannel.from_mesh(obj.demonstrated_mesh, geometry, cache_dir, name=f"{obj.name} (captured)")
    to_sub, to_demo = surface_maps(demonstrated.mesh, channel.mesh, obj.config, cache_dir)
    return Substitution(demonstrated, channel, to_sub, to_demo)


def manipulated_object(demo: Demonstration, name: str | None = None) -> DemoObject:
    """The object ``name``, or the demonstration's only manipulated (non-static) object."""
    if name is not None:
        return demo.object(name)
    moving = [o for o in demo.objects if not o.static]
    if len(moving) != 1:
        raise InvalidDemonstrationError(
            f"{demo.name}: name the object to substitute: it manipulates {[o.name for o in moving] or 'no object'}")
    return moving[0]


def substitute(demo: Demonstration, spec: ShapeSpec | TriMesh, object_name: str | None = None,
               cfg: SubstitutionConfig = SubstitutionConfig()) -> Demonstration:
    """``demo`` with one object (default: its only manipulated one) replaced by a substitute.

    ``spec`` is a :class:`~retarget.inputs.shapes.ShapeSpec` (library shape, user mesh file, or the
    object itself resized) or a mesh already in the captured object's frame. The human motion
    and the object track are unchanged; ``source["substitution"]`` records what was swapped.
    """
    obj = manipulated_object(demo, object_name)
    captured = obj.demonstrated_mesh if isinstance(obj, SubstituteObject) and obj.demonstrated_mesh is not None \
        else as_trimesh(obj.vertices, obj.faces, obj.mesh_path or f"object '{obj.name}' of {demo.name}")
    if isinstance(spec, ShapeSpec):
        mesh = substitute_mesh(spec, captured, obj.quat_w)
        shape, scale = spec.shape, spec.scale
    else:
        mesh, shape, scale = as_trimesh(spec.vertices, spec.faces, spec.name), spec.name, (1.0, 1.0, 1.0)
    swapped = SubstituteObject(obj.name, mesh.vertices, mesh.faces, obj.pos_w, obj.quat_w,
                               mesh_path=shape if Path(shape).suffix else None, static=obj.static,
                               demonstrated_mesh=captured, shape=shape, scale=tuple(scale), config=cfg)
    objects = [swapped if o is obj else o for o in demo.objects]
    record = {"object": obj.name, "shape": shape, "scale": list(scale), "captured_mesh": captured.name}
    return replace(demo, objects=objects, source={**demo.source, "substitution": record})


def free_objects(demo: Demonstration, names: list[str] | tuple[str, ...]) -> Demonstration:
    """``demo`` with the named static objects (furniture) made free: the solver then moves them
    too (their demonstrated contacts with the ground and other objects hold them in place)."""
    known = {o.name for o in demo.objects}
    missing = [n for n in names if n not in known]
    if missing:
        raise KeyError(f"{demo.name}: no object {missing} (objects: {sorted(known)})")
    return replace(demo, objects=[replace(o, static=False) if o.name in names else o for o in demo.objects])
