"""The subject's surface per body part (part frames), as a demonstration carries it."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from otr_gym.rotations import quat_to_matrix


@dataclass
class HumanSurface:
    """The subject's surface split per part, each piece in its part frame (m)."""

    part_names: tuple[str, ...]
    vertices: list[np.ndarray]  # per part (V_k, 3), part frame
    faces: list[np.ndarray]  # per part (F_k, 3), indices into vertices[k]

    @property
    def vertex_part(self) -> np.ndarray:
        """Part index of every vertex of the concatenated surface (V,)."""
        return np.repeat(np.arange(len(self.vertices)), [len(v) for v in self.vertices])

    def posed_vertices(self, part_pos_w: np.ndarray, part_quat_w: np.ndarray) -> np.ndarray:
        """World vertices (…, V, 3) for part poses (…, P, 3) m / (…, P, 4) wxyz, parts in order."""
        rot = quat_to_matrix(np.asarray(part_quat_w, np.float64))
        pos = np.asarray(part_pos_w, np.float64)
        # one batched product per part (22 of them), never a loop over frames or vertices
        return np.concatenate([v @ np.swapaxes(rot[..., k, :, :], -1, -2) + pos[..., k, None, :]
                               for k, v in enumerate(self.vertices)], axis=-2)

    def centre_of_mass(self, part_pos_w: np.ndarray, part_quat_w: np.ndarray) -> np.ndarray:
        """World centre of mass (…, 3) m for part poses (…, P, 3) / (…, P, 4), parts in order.

        Each part is its surface's convex hull at uniform density: a part mesh cut from the body
        is open where it meets its neighbours, so its own volume is undefined, and the hulls'
        overlap at the joints is a few per cent of the mass. The hulls are computed once."""
        centre, volume = self.part_hull_mass
        rot = quat_to_matrix(np.asarray(part_quat_w, np.float64))
        world = np.einsum("...kij,kj->...ki", rot, centre) + np.asarray(part_pos_w, np.float64)
        return np.einsum("...ki,k->...i", world, volume / volume.sum())

    @cached_property
    def part_hull_mass(self) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3) hull centroids (part frames, m) and (P,) hull volumes (m³) of the parts."""
        import trimesh

        hulls = [trimesh.convex.convex_hull(v) for v in self.vertices]
        return np.array([h.center_mass for h in hulls]), np.array([h.volume for h in hulls])

    def lowest_z(self, part_pos_w: np.ndarray, part_quat_w: np.ndarray) -> np.ndarray:
        """Height (…,) m of the lowest surface point for part poses (…, P, 3) / (…, P, 4)."""
        rot_z = quat_to_matrix(np.asarray(part_quat_w, np.float64))[..., 2, :]  # third rows (…, P, 3)
        pos_z = np.asarray(part_pos_w, np.float64)[..., 2]
        return np.min(np.stack([(rot_z[..., k, :] @ v.T).min(axis=-1) + pos_z[..., k]
                                for k, v in enumerate(self.vertices)], axis=-1), axis=-1)
