"""Terrain of references recorded on uneven ground (a slope, a platform), simulated as fixed
collision geometry on both backends (OTR-G1-Track-v0 and OTR-G1-BoxTrack-v0).

A reference may come with a terrain mesh: any trimesh-readable file, metres, in the clip's own
world frame (z up, the floor plane at z = 0), e.g. Holosoma's ``terrain_slope.obj`` beside
``motion_crawl_slope.npz``. ``envs.collision.collision_shapes`` turns it into one box, disjoint
oriented boxes (that slope: a ramp slab tilted by 12.6° and a platform) or a CoACD convex
decomposition. Pieces that lie wholly at or below the floor (their top at most
``TerrainCfg.floor_tolerance_m`` above z = 0, e.g. the file's 14.8 m floor slab) are dropped:
the simulation's floor plane already provides them. The rest become geoms of one fixed body
``terrain/<k>`` per mesh (geoms ``terrain/<k>/geom<j>``), with the floor's friction (and its
per-env draw when randomised). A model with terrain gets MuJoCo-Warp contact and constraint
buffers of at least ``TerrainCfg.nconmax``/``njmax`` per world (``contact_buffers``).

Naming (``TerrainCfg.meshes``, clip -> mesh, or ``terrain=`` on a clip-list line, see
``otr_gym.reference.clip_entries``): a key names a clip by its file stem (its label in logs),
a trailing part of its path ("holosoma/motion_crawl_slope", ".npz" optional) or its path. A key
that names no clip of the run, or several, and a clip given two different meshes raise.

Libraries: all worlds share one model, so every terrain is present in every world. Each mesh
(clips naming the same file share it) gets its own origin ``library_spacing_m`` apart along +x;
clips without terrain stay at the origin 0 (a library whose clips all have terrain starts at 0,
so a single clip keeps its terrain where it is). A clip's reference positions (root, bodies,
objects) are shifted by its origin when the library is built (``Reference.translated``);
orientations and velocities do not change. Observations are anchor-relative and MPJPE
root-relative, so the shift changes neither (tests/test_terrain.py). A clip whose reference
(its bounding box grown by ``reach_margin_m``) comes near the terrain of another origin is
refused: its robot could wander onto it.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from envs.collision import BoxShape, CollisionShape, CollisionShapeError, collision_shapes, load_mesh
from envs.config import SimCfg, TerrainCfg
from envs.objects import GROUND_GEOM
from otr_gym.reference import ClipEntry, InvalidReferenceError, Reference
from otr_gym.rotations import quat_to_matrix

BODY_PREFIX = "terrain/"
RGBA = (0.55, 0.5, 0.42, 1.0)


@dataclass(frozen=True)
class Terrain:
    """One terrain mesh in the simulation."""

    mesh: str  # the file (absolute path)
    clips: tuple[str, ...]  # sources of the clips recorded on it
    shapes: tuple[CollisionShape, ...]  # clip world frame (before the origin shift), above the floor
    method: str  # how the mesh became shapes (envs.collision)
    dropped: int  # pieces at or below the floor, left to the floor plane
    origin_w: np.ndarray  # (3,) m: where the clips' world frame lies in the simulation

    def bounds_w(self) -> np.ndarray:
        """(2, 3) lower and upper corner (m, simulation world) of the shapes; NaN when none."""
        if not self.shapes:
            return np.full((2, 3), np.nan)
        points = np.concatenate([shape_corners(s) for s in self.shapes]) + self.origin_w
        return np.stack([points.min(axis=0), points.max(axis=0)])


@dataclass(frozen=True)
class SceneTerrain:
    """The terrains of a clip library and every clip's origin."""

    terrains: tuple[Terrain, ...]
    clip_origin_w: np.ndarray  # (C, 3) m, library order

    def body(self, k: int) -> str:
        return f"{BODY_PREFIX}{k}"

    def geom_names(self) -> list[str]:
        return [f"{self.body(k)}/geom{j}" for k, t in enumerate(self.terrains) for j in range(len(t.shapes))]

    def add_to(self, spec: mujoco.MjSpec) -> None:
        """Add every terrain to ``spec`` as a fixed body at its origin, with the friction and
        condim of the spec's floor (``ground/ground``) when it has one."""
        floor = next((g for g in spec.geoms if g.name == GROUND_GEOM), None)
        common = {"rgba": list(RGBA)}
        if floor is not None:
            common.update(friction=list(floor.friction), condim=floor.condim)
        for k, terrain in enumerate(self.terrains):
            body = spec.worldbody.add_body(name=self.body(k), pos=terrain.origin_w.tolist())
            for j, shape in enumerate(terrain.shapes):
                name = f"{self.body(k)}/geom{j}"
                if isinstance(shape, BoxShape):
                    body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=shape.half_extents.tolist(),
                                  pos=shape.pos.tolist(), quat=shape.quat_wxyz.tolist(), **common)
                else:
                    spec.add_mesh(name=f"{name}/hull", uservert=shape.vertices.ravel().tolist(),
                                  userface=np.asarray(shape.faces, np.int32).ravel().tolist())
                    body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"{name}/hull", **common)

    def info(self) -> list[dict]:
        """Plain-JSON description (env_spec.json): mesh, clips, origin, collision geometry."""
        return [{"mesh": t.mesh, "clips": list(t.clips), "origin_m": t.origin_w.tolist(), "collision": t.method,
                 "pieces": len(t.shapes), "dropped_at_floor": t.dropped} for t in self.terrains]


def flat(num_clips: int) -> SceneTerrain:
    """No terrain: every clip at the origin."""
    return SceneTerrain((), np.zeros((num_clips, 3)))


def contact_buffers(sim: SimCfg, cfg: TerrainCfg, terrain: SceneTerrain) -> tuple[int, int]:
    """(nconmax, njmax) per world for MuJoCo-Warp: ``sim``'s, raised to ``cfg``'s with terrain."""
    if not terrain.terrains:
        return sim.nconmax, sim.njmax
    return max(sim.nconmax, cfg.nconmax), max(sim.njmax, cfg.njmax)


def clip_matches(key: str, source: str) -> bool:
    """Whether terrain key ``key`` names the clip loaded from ``source`` (see the module docstring)."""
    k, s = Path(key).expanduser(), Path(source).expanduser()
    if k.is_absolute():
        return os.path.abspath(k) == os.path.abspath(s)
    key_parts = k.with_suffix("").parts if k.suffix == ".npz" else k.parts
    clip_parts = s.with_suffix("").parts
    return 0 < len(key_parts) <= len(clip_parts) and clip_parts[-len(key_parts):] == key_parts


def terrain_meshes(meshes: Mapping[str, str], listed: Mapping[str, str] | None = None) -> dict[str, str]:
    """``meshes`` (clip key -> mesh, ``TerrainCfg.meshes``) with ``listed`` (clip path -> mesh:
    the ``terrain=`` options of clip lists, ``listed_terrain``) added, every mesh path absolute.
    A clip given two different meshes raises naming both."""
    out = {key: os.path.abspath(Path(mesh).expanduser()) for key, mesh in meshes.items()}
    for key, mesh in (listed or {}).items():
        if key in out and out[key] != mesh:
            raise InvalidReferenceError(f"{key}: terrain {mesh} (clip list) differs from {out[key]} (terrain.meshes)")
        out[key] = mesh
    return out


def listed_terrain(entries: Iterable[ClipEntry]) -> dict[str, str]:
    """{clip path: absolute mesh path} of the ``terrain=`` options of clip-list entries
    (``otr_gym.reference.clip_entries``: whoever expands the clip lists reads them, once)."""
    return {str(e.path): os.path.abspath(e.terrain) for e in entries if e.terrain is not None}


def meshes_for_clips(meshes: Mapping[str, str], sources: Sequence[str]) -> dict[str, str]:
    """The entries of ``meshes`` that name one of the clips ``sources`` (evaluating or playing
    part of a library)."""
    return {key: mesh for key, mesh in meshes.items() if any(clip_matches(key, s) for s in sources)}


def place_terrain(refs: Sequence[Reference], cfg: TerrainCfg,
                  meshes: Mapping[str, str] | None = None) -> tuple[list[Reference], SceneTerrain]:
    """(``refs`` shifted to their origins, the scene's terrain) for a clip library; ``meshes``
    defaults to ``cfg.meshes`` (see ``terrain_meshes`` for clip lists)."""
    meshes = cfg.meshes if meshes is None else meshes
    sources = [r.source for r in refs]
    mesh_of = _mesh_of_clip(meshes, sources)
    if not mesh_of:
        return list(refs), flat(len(refs))
    if not cfg.library_spacing_m > 0:
        raise ValueError(f"terrain.library_spacing_m must be > 0, got {cfg.library_spacing_m}")
    files = list(dict.fromkeys(mesh_of[i] for i in sorted(mesh_of)))
    first_slot = 0 if len(mesh_of) == len(refs) else 1  # clips without terrain keep the origin
    terrains = []
    for k, file in enumerate(files):
        clips = tuple(sources[i] for i in sorted(mesh_of) if mesh_of[i] == file)
        origin = np.array([(first_slot + k) * cfg.library_spacing_m, 0.0, 0.0])
        terrains.append(load_terrain(file, clips, origin, cfg))
    origins = np.array([terrains[files.index(mesh_of[i])].origin_w if i in mesh_of else np.zeros(3)
                        for i in range(len(refs))])
    placed = [r.translated(o) if o.any() else r for r, o in zip(refs, origins, strict=True)]
    scene = SceneTerrain(tuple(terrains), origins)
    _check_reach(placed, scene, cfg)
    return placed, scene


def _mesh_of_clip(meshes: Mapping[str, str], sources: Sequence[str]) -> dict[int, str]:
    """{clip index: absolute mesh path}; raises for keys that name no clip or several, and for
    a clip given two meshes."""
    out: dict[int, str] = {}
    given_by: dict[int, str] = {}
    for key, mesh in meshes.items():
        hits = [i for i, s in enumerate(sources) if clip_matches(key, s)]
        if not hits:
            names = ", ".join(Path(s).stem for s in sources)
            raise InvalidReferenceError(f"terrain.meshes: '{key}' names no clip of this run (clips: {names}); "
                                        f"its mesh {mesh} is not used")
        if len(hits) > 1:
            raise InvalidReferenceError(f"terrain.meshes: '{key}' names {len(hits)} clips "
                                        f"({', '.join(sources[i] for i in hits)}): give more of the path")
        i, file = hits[0], os.path.abspath(Path(mesh).expanduser())
        if i in out and out[i] != file:
            raise InvalidReferenceError(f"{sources[i]}: two terrain meshes, {out[i]} ('{given_by[i]}') and "
                                        f"{file} ('{key}')")
        out[i], given_by[i] = file, key
    return out


def load_terrain(file: str, clips: tuple[str, ...], origin_w: np.ndarray, cfg: TerrainCfg) -> Terrain:
    """The terrain of ``clips`` from mesh ``file``, placed at ``origin_w`` (3,) (m); errors
    (``InvalidReferenceError``) name the file and the problem."""
    what = f"terrain of {', '.join(clips)}"
    try:
        vertices, faces = load_mesh(file, what)
        shapes, method = collision_shapes(vertices, faces, f"{file}: {what}", cfg.collision)
    except CollisionShapeError as exc:
        raise InvalidReferenceError(str(exc)) from exc
    kept = tuple(s for s in shapes if shape_corners(s)[:, 2].max() > cfg.floor_tolerance_m)
    return Terrain(mesh=file, clips=clips, shapes=kept, method=method, dropped=len(shapes) - len(kept),
                   origin_w=origin_w)


def shape_corners(shape: CollisionShape) -> np.ndarray:
    """(P, 3) points spanning a shape (box corners, hull vertices), in the frame of its pose."""
    if isinstance(shape, BoxShape):
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
        return (signs * shape.half_extents) @ quat_to_matrix(shape.quat_wxyz).T + shape.pos
    return np.asarray(shape.vertices, np.float64)


def _check_reach(refs: Sequence[Reference], scene: SceneTerrain, cfg: TerrainCfg) -> None:
    """Raise when a clip's reference, grown by ``reach_margin_m``, overlaps in x-y the terrain
    of another origin."""
    for terrain in scene.terrains:
        lo, hi = terrain.bounds_w()[:, :2]
        if np.isnan(lo).any():
            continue
        for ref, origin in zip(refs, scene.clip_origin_w, strict=True):
            if np.allclose(origin, terrain.origin_w):
                continue
            xy = ref.body_pos_w[..., :2].reshape(-1, 2)
            near_lo, near_hi = xy.min(axis=0) - cfg.reach_margin_m, xy.max(axis=0) + cfg.reach_margin_m
            if np.all(near_lo < hi) and np.all(lo < near_hi):
                raise InvalidReferenceError(
                    f"{ref.source}: its reference (x {near_lo[0]:.1f}..{near_hi[0]:.1f} m, y {near_lo[1]:.1f}.."
                    f"{near_hi[1]:.1f} m with the {cfg.reach_margin_m:g} m margin) reaches the terrain {terrain.mesh} "
                    f"placed at x = {terrain.origin_w[0]:g} m (x {lo[0]:.1f}..{hi[0]:.1f} m): raise "
                    f"terrain.library_spacing_m (now {cfg.library_spacing_m:g} m)")
