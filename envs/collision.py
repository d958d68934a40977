"""Collision geometry of a reference object from its mesh: one box primitive when the mesh is
box-like, boxes when it is a union of disjoint boxes, otherwise a convex decomposition.

Box primitives are what MuJoCo(-Warp) collides fastest and most robustly (analytic box–box,
box–capsule, box–plane), so a box-like mesh (a carton, a scanned crate) becomes its
minimum-volume oriented bounding box. "Box-like" is judged on the mesh itself, with three
scores that also hold for open, noisy scans (OMOMO's large box is 303 fragments, not watertight):

- ``hull_fill``: volume of the convex hull / volume of the box (a box ≈ 1, a cylinder 0.79,
  a sphere 0.52);
- ``on_box``: fraction of the mesh's surface (area samples) within ``tolerance`` of the
  box's surface (the mesh is no thinner than the box: a table's legs fail here, a hollow
  scan does not);
- ``covered``: fraction of the box's surface within ``tolerance`` of the mesh (the box adds
  no material the mesh lacks: a table's missing underside fails here, a scan's missing
  bottom face alone does not).

``tolerance`` is a fraction of the box's smallest half-extent (for ``covered`` at least twice
the spacing of the mesh samples it is measured against). Measured with the defaults:
OMOMO ``largebox.obj`` (0.919, 0.968, 0.956) → box; an ideal box with no bottom face
(1.0, 1.0, 0.85) → box; a cylinder (0.79, 0.84, 0.69), OMOMO's table (1.0, 0.72, 0.47) and
chair (0.73, 0.50, 0.26) → not box-like.

Otherwise a mesh made of a few disjoint box-like pieces (the demo's table: a top and four
legs) becomes one box per piece; anything else is decomposed into convex hulls by CoACD
(``coacd`` on PyPI; Wei et al., SIGGRAPH 2022), cached on disk by mesh content and settings
(``$OTR_CACHE_DIR``, else ``~/.cache/otr-gym``), since it takes seconds to a minute.

Frames: everything is in the object's own frame (the frame of the reference's object pose;
for a terrain mesh, ``envs.terrain``, the clip's world frame), metres; box orientations are
wxyz quaternions, so a fitted box keeps the mesh's orientation (a tilted ramp stays tilted).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from otr_gym.io import load_npz, save_npz
from otr_gym.object_box import BoxFitCfg, BoxShape, fit_box


class CollisionShapeError(ValueError):
    """An object mesh that cannot be turned into collision geometry; the message names it."""


@dataclass(frozen=True)
class HullShape:
    vertices: np.ndarray  # (V, 3) m, object frame, convex
    faces: np.ndarray  # (F, 3)


CollisionShape = BoxShape | HullShape


@dataclass(frozen=True)
class CollisionCfg(BoxFitCfg):
    """How reference meshes become collision geometry (see the module docstring); the
    box-likeness thresholds are ``BoxFitCfg``'s."""

    max_box_pieces: int = 16  # a union of more disjoint pieces is decomposed instead
    # CoACD (run_coacd arguments): concavity threshold and budget; settings that took 6-15 s
    # on OMOMO's scanned table and chair (30-55 k faces) with 6-16 hulls.
    coacd_threshold: float = 0.08
    coacd_max_hulls: int = 16
    coacd_resolution: int = 1000
    coacd_preprocess_resolution: int = 30
    coacd_mcts_iterations: int = 60
    coacd_mcts_nodes: int = 10


def load_mesh(path: str | Path, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3), faces (F, 3)) of a mesh file (any trimesh-readable format, as stored:
    no unit or frame conversion). ``what`` says whose mesh it is in errors ("mesh of clip.npz:
    object 'box'"); a missing or unreadable file, or one without faces, raises
    ``CollisionShapeError`` naming the file."""
    import trimesh

    file = Path(path).expanduser()
    if not file.is_file():
        raise CollisionShapeError(f"{file}: {what} not found")
    try:
        mesh = trimesh.load(file, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise CollisionShapeError(f"{file}: {what} cannot be read ({type(exc).__name__}: {exc})") from exc
    if not hasattr(mesh, "faces") or len(mesh.faces) == 0:
        raise CollisionShapeError(f"{file}: {what} has no faces (not a mesh file, or an empty one)")
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def collision_shapes(vertices: np.ndarray | None, faces: np.ndarray | None, what: str,
                     cfg: CollisionCfg = CollisionCfg(),
                     cache_dir: Path | None = None) -> tuple[list[CollisionShape], str]:
    """(shapes, method) for a mesh; ``method`` is "box", "boxes" or "convex decomposition".

    ``what`` names the mesh in errors (e.g. "clip.npz: object 'box'"). Raises
    ``CollisionShapeError`` for a missing, empty, non-finite or flat mesh, and when the
    decomposition fails or returns nothing.
    """
    import trimesh

    if vertices is None or faces is None:
        raise CollisionShapeError(f"{what}: no mesh")
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise CollisionShapeError(f"{what}: mesh must have (V, 3) vertices and (F ≥ 1, 3) faces, "
                                  f"got {vertices.shape} and {faces.shape}")
    if not np.isfinite(vertices).all():
        raise CollisionShapeError(f"{what}: mesh vertices contain NaN/inf")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise CollisionShapeError(f"{what}: mesh faces index vertices outside [0, {len(vertices)})")
    spread = np.linalg.svd(vertices - vertices.mean(axis=0), compute_uv=False)
    if len(spread) < 3 or spread[2] <= 1e-6 * max(spread[0], 1e-12):
        raise CollisionShapeError(f"{what}: mesh cannot be decomposed: its vertices lie in a plane or on a line "
                                  "(no volume)")
    mesh = trimesh.Trimesh(vertices, faces.astype(np.int64), process=False)
    try:
        volume = float(mesh.convex_hull.volume)
    except Exception as exc:  # qhull refuses flat / degenerate point sets
        raise CollisionShapeError(f"{what}: mesh cannot be decomposed: its vertices span no volume ({exc})") from exc
    if not volume > 1e-9:
        raise CollisionShapeError(f"{what}: mesh cannot be decomposed: its convex hull has no volume "
                                  f"({volume:.2e} m³; a flat or degenerate mesh)")
    whole = fit_box(vertices, faces, cfg)
    if whole.is_box(cfg):
        return [whole.box], "box"
    pieces = mesh.split(only_watertight=False)
    if 1 < len(pieces) <= cfg.max_box_pieces:
        fits = []
        for piece in pieces:
            if piece.convex_hull.volume <= 1e-9:
                break
            fit = fit_box(piece.vertices, piece.faces, cfg)
            if not fit.is_box(cfg):
                break
            fits.append(fit.box)
        else:
            return fits, "boxes"
    return _decompose(mesh, what, cfg, cache_dir), "convex decomposition"


def _decompose(mesh, what: str, cfg: CollisionCfg, cache_dir: Path | None) -> list[HullShape]:
    settings = {k: v for k, v in dataclasses.asdict(cfg).items() if k.startswith("coacd") or k == "seed"}
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(mesh.vertices, np.float64).tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, np.int64).tobytes())
    digest.update(json.dumps(settings, sort_keys=True).encode())
    folder = Path(cache_dir) if cache_dir is not None else \
        Path(os.environ.get("OTR_CACHE_DIR", Path.home() / ".cache" / "otr-gym"))
    path = folder / "collision" / f"{digest.hexdigest()[:32]}.npz"
    if path.is_file():
        try:
            data = load_npz(path)
            return [HullShape(data[f"v{i}"], data[f"f{i}"]) for i in range(int(data["count"]))]
        except (OSError, ValueError, KeyError):  # NpzError is a ValueError
            pass  # an unreadable cache entry is rebuilt below
    try:
        import coacd
    except ImportError as exc:
        raise CollisionShapeError(f"{what}: the mesh is not box-like and its convex decomposition needs the "
                                  "'coacd' package (pip install coacd)") from exc
    coacd.set_log_level("error")
    try:
        parts = coacd.run_coacd(
            coacd.Mesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32)),
            threshold=cfg.coacd_threshold, max_convex_hull=cfg.coacd_max_hulls, resolution=cfg.coacd_resolution,
            preprocess_resolution=cfg.coacd_preprocess_resolution, mcts_iterations=cfg.coacd_mcts_iterations,
            mcts_nodes=cfg.coacd_mcts_nodes, seed=cfg.seed)
    except Exception as exc:
        raise CollisionShapeError(f"{what}: convex decomposition failed ({type(exc).__name__}: {exc})") from exc
    hulls = [HullShape(np.asarray(v, np.float64), np.asarray(f, np.int32)) for v, f in parts if len(f) >= 4]
    if not hulls:
        raise CollisionShapeError(f"{what}: convex decomposition returned no convex part")
    arrays = {"count": np.array(len(hulls))}
    for i, h in enumerate(hulls):
        arrays[f"v{i}"], arrays[f"f{i}"] = h.vertices, h.faces
    save_npz(path, arrays)
    return hulls
