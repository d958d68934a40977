"""An object's oriented box: the minimum-volume box around its mesh and how box-like the mesh is.

The box environment collides a box-like object as this box (``envs.collision``), and the
retargeter's grasp pass (``retarget.solver.grasp``) places the G1's hands on its faces, so both
take it from here. Frames: the object's own frame (that of the reference's object pose), metres;
box orientations wxyz.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from otr_gym.rotations import matrix_to_quat


@dataclass(frozen=True)
class BoxShape:
    half_extents: np.ndarray  # (3,) m
    pos: np.ndarray  # (3,) m, object frame
    quat_wxyz: np.ndarray  # (4,) object frame


@dataclass(frozen=True)
class BoxFitCfg:
    """When a mesh counts as a box (the three scores of ``envs.collision``'s module doc)."""

    min_hull_fill: float = 0.85
    min_on_box: float = 0.9
    min_covered: float = 0.8
    tolerance: float = 0.15  # × the smallest half-extent
    samples: int = 4000  # surface samples per score
    seed: int = 0


@dataclass(frozen=True)
class BoxFit:
    box: BoxShape
    hull_fill: float
    on_box: float
    covered: float

    def is_box(self, cfg: BoxFitCfg) -> bool:
        return self.hull_fill >= cfg.min_hull_fill and self.on_box >= cfg.min_on_box and self.covered >= cfg.min_covered


def fit_box(vertices: np.ndarray, faces: np.ndarray, cfg: BoxFitCfg = BoxFitCfg()) -> BoxFit:
    """The minimum-volume oriented bounding box of a mesh and its box-likeness scores."""
    import trimesh
    from scipy.spatial import cKDTree

    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    hull = mesh.convex_hull
    obb = hull.bounding_box_oriented
    transform = np.asarray(obb.primitive.transform, np.float64)
    half = 0.5 * np.asarray(obb.primitive.extents, np.float64)
    tol = cfg.tolerance * float(half.min())
    to_box = np.linalg.inv(transform)
    points, _ = trimesh.sample.sample_surface(mesh, cfg.samples, seed=cfg.seed)
    local = trimesh.transform_points(points, to_box)
    gap = np.abs(np.min(half - np.abs(local), axis=1))  # distance to the nearest box face
    box_points, _ = trimesh.sample.sample_surface(trimesh.creation.box(extents=2 * half), cfg.samples, seed=cfg.seed)
    nearest, _ = cKDTree(local).query(box_points)
    # box points are compared with mesh *samples*: allow for their spacing on thin pieces
    spacing = float(np.sqrt(mesh.area / cfg.samples))
    rot = transform[:3, :3]
    if np.linalg.det(rot) < 0:  # keep a right-handed frame (flip one axis; a box is symmetric)
        rot = rot * np.array([1.0, 1.0, -1.0])
    box = BoxShape(half_extents=half, pos=transform[:3, 3].copy(), quat_wxyz=matrix_to_quat(rot))
    return BoxFit(box, float(hull.volume / np.prod(2 * half)), float(np.mean(gap < tol)),
                  float(np.mean(nearest < max(tol, 2.0 * spacing))))
