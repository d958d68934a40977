"""The ground under a reference: the floor plane z = 0, and a terrain mesh on it if the clip
was recorded on one (Holosoma's crawl: a ramp tilted by 12.6° up to a 0.41 m platform).

``Ground.under(points)`` gives, for points in the clip's world frame (z up, metres), their
distance above the ground along its normal and that normal: the ground under a point is the
highest surface beneath it, among the floor and the terrain's upward-facing triangles (normal
z ≥ ``min_normal_z``) whose footprint (xy) holds the point. "Beneath" allows the point to sink
``sink_tolerance_m`` into a surface (a sole pressed 2 cm into a platform stands on the platform,
not on the floor under it); a point deeper than that belongs to a lower surface. Walls and
overhangs carry nothing here: the feasibility check asks where a foot, a knee or a hand can push
against gravity, which is an upward face.

The same file the simulation collides with (``envs.terrain``, ``--set env.terrain.meshes.…``)
is the one to give, so the check and the simulation stand the robot on the same ground.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from retarget.inputs.meshes import load_mesh

#: Points per batch of the point × triangle footprint test (bounds the (N, F) temporaries).
_CHUNK = 65536


@dataclass(frozen=True)
class Ground:
    """The floor z = 0 plus the upward triangles of a terrain mesh (none: the floor alone)."""

    triangles: np.ndarray  # (F, 3, 3) m, world: upward-facing terrain triangles
    normals: np.ndarray  # (F, 3) their unit normals (z > 0)
    source: str | None = None  # the terrain file, None for the bare floor
    sink_tolerance_m: float = 0.05
    min_normal_z: float = 0.2  # steeper faces (over ~78°) are walls: they carry nothing

    @classmethod
    def floor(cls) -> Ground:
        return cls(np.zeros((0, 3, 3)), np.zeros((0, 3)))

    @classmethod
    def from_mesh(cls, path: str | Path, min_normal_z: float = 0.2) -> Ground:
        """The floor plus the terrain in ``path`` (any trimesh-readable file, metres, the clip's
        world frame). A missing or unreadable file raises ``InvalidMeshError`` naming it; a mesh
        without an upward face raises ``ValueError``."""
        mesh = load_mesh(path)
        tri = mesh.vertices[mesh.faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(normal, axis=1)
        keep = length > 1e-12
        normal[keep] /= length[keep, None]
        up = keep & (normal[:, 2] >= min_normal_z)
        if not up.any():
            raise ValueError(f"{path}: terrain mesh has no upward-facing triangle (normal z >= {min_normal_z}) "
                             "to stand on")
        return cls(tri[up], normal[up], str(path), min_normal_z=min_normal_z)

    def describe(self) -> str:
        if self.source is None:
            return "floor z = 0"
        return f"floor z = 0 and terrain {Path(self.source).name} ({len(self.triangles)} upward faces)"

    def under(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(height (...,) m along the ground's normal, normal (..., 3)) of ``points`` (..., 3)."""
        p = np.asarray(points, np.float64)
        flat = p.reshape(-1, 3)
        height = flat[:, 2].copy()  # the floor: z above z = 0, normal +z
        normal = np.zeros_like(flat)
        normal[:, 2] = 1.0
        if len(self.triangles):
            for start in range(0, len(flat), _CHUNK):
                self._terrain(flat[start:start + _CHUNK], height[start:start + _CHUNK], normal[start:start + _CHUNK])
        return height.reshape(p.shape[:-1]), normal.reshape(p.shape)

    def _terrain(self, p: np.ndarray, height: np.ndarray, normal: np.ndarray) -> None:
        """Where a terrain face lies under ``p`` (N, 3) above the floor, replace the floor's
        ``height`` and ``normal`` (in place) by the highest such face's."""
        a, b, c = self.triangles[:, 0], self.triangles[:, 1], self.triangles[:, 2]
        # barycentric coordinates of the points' xy in each face's xy footprint
        e0, e1 = (b - a)[:, :2], (c - a)[:, :2]
        det = e0[:, 0] * e1[:, 1] - e0[:, 1] * e1[:, 0]  # (F,): twice the footprint's area, > 0 facing up
        d = p[:, None, :2] - a[None, :, :2]  # (N, F, 2)
        u = (d[..., 0] * e1[:, 1] - d[..., 1] * e1[:, 0]) / det
        v = (e0[:, 0] * d[..., 1] - e0[:, 1] * d[..., 0]) / det
        inside = (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9)
        surface_z = a[:, 2] + u * (b - a)[:, 2] + v * (c - a)[:, 2]  # (N, F): the face's z at the point's xy
        beneath = inside & (surface_z <= p[:, 2:3] + self.sink_tolerance_m)
        candidate = np.where(beneath, surface_z, -np.inf)
        face = candidate.argmax(axis=1)
        best_z = candidate[np.arange(len(p)), face]
        higher = best_z > 0.0  # above the floor (terrain below z = 0 is under the floor plane)
        if not higher.any():
            return
        n = self.normals[face[higher]]
        height[higher] = (p[higher, 2] - best_z[higher]) * n[:, 2]  # vertical gap -> distance along n
        normal[higher] = n


def load_clip_on_ground(reference: str | Path, terrain: str | Path | None = None):
    """(the ``Reference`` in ``reference``, the ``Ground`` it was recorded on: the floor, plus the
    mesh in ``terrain`` if given), for the commands that take a clip and its terrain. A missing or
    unreadable file raises a ``ValueError`` naming it (``InvalidReferenceError``,
    ``InvalidMeshError``)."""
    from otr_gym.reference import Reference

    ground = Ground.from_mesh(terrain) if terrain else Ground.floor()
    return Reference.load(reference), ground
