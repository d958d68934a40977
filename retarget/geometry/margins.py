"""How far an interpolated distance grid may overstate the true distance, cell by cell.

A trilinear distance grid is exact on flat faces but overestimates the distance near edges,
corners and thin features (a scanned box's handle holes: up to ~4 mm on a 1 cm grid). A
non-penetration row written with the grid's distance would then let the exact surface be
crossed. :func:`interpolation_margin` measures, once per mesh, the largest excess
``grid − exact`` over a 4×4×4 lattice inside every cell near the surface (exact distances from
``retarget.inputs.meshes.signed_distance``); constraint rows subtract it (``ErrorMargin.at``), cost
rows do not. Results are cached on disk next to the grids.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from retarget.geometry.cache import cached_arrays, default_cache_dir
from retarget.geometry.voxel_grid import VoxelGrid
from retarget.inputs.meshes import TriMesh, signed_distance

#: Sample lattice per cell axis: 4³ points measure the largest excess within ~0.1 mm on the
#: OMOMO box (3³ left 0.4 mm unseen).
_LATTICE = 4


@dataclass(frozen=True)
class ErrorMargin:
    """Per-cell upper bound (m) of grid − exact distance; zero away from the surface."""

    origin: np.ndarray  # (3,) of the grid, channel frame
    resolution: float
    cells: tuple[int, int, int]
    values: np.ndarray  # (cx·cy·cz,)

    def at(self, x: np.ndarray) -> np.ndarray:
        """Margin (N,) at points (N, 3) in the channel frame (0 outside the grid)."""
        out = np.empty(len(x))
        _margin_at(np.ascontiguousarray(x, np.float64), self.origin, float(self.resolution),
                   np.array(self.cells, np.intp), self.values, out)
        return out


@numba.njit(cache=True)
def _margin_at(x, origin, resolution, cells, values, out):
    """out[i] ← the value of the cell holding x[i] (cells (cx, cy, cz), C order), 0 outside."""
    cy, cz = cells[1], cells[2]
    for i in range(x.shape[0]):
        u0 = int(np.floor((x[i, 0] - origin[0]) / resolution))
        u1 = int(np.floor((x[i, 1] - origin[1]) / resolution))
        u2 = int(np.floor((x[i, 2] - origin[2]) / resolution))
        if 0 <= u0 < cells[0] and 0 <= u1 < cy and 0 <= u2 < cz:
            out[i] = values[u0 * (cy * cz) + u1 * cz + u2]
        else:
            out[i] = 0.0


def interpolation_margin(grid: VoxelGrid, mesh: TriMesh, reach_m: float, chunk: int = 200_000) -> ErrorMargin:
    """Measure the excess of ``grid`` over the exact signed distance of ``mesh`` in every cell
    with a corner closer than ``reach_m`` to the surface, on either side (cells wholly deeper
    inside get none: 36 % of the OMOMO large box's, whose margin changed no reference)."""
    nx, ny, nz = grid.shape
    d = grid.values[:, 0].reshape(nx, ny, nz)
    corners = [d[i:nx - 1 + i, j:ny - 1 + j, k:nz - 1 + k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    cells = (nx - 1, ny - 1, nz - 1)
    # deeper inside than reach_m, a point's row is violated by more than the reach whatever the margin
    near = np.argwhere((np.minimum.reduce(corners) < reach_m) & (np.maximum.reduce(corners) > -reach_m))
    ticks = (np.arange(_LATTICE) + 0.5) / _LATTICE
    lattice = np.array([(a, b, c) for a in ticks for b in ticks for c in ticks])
    corner = np.array([(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)])
    # a lattice point lies on the side of any corner farther from the surface than from the point
    # (the ball around that corner holds no surface): its winding number is not needed
    to_corner = grid.resolution * np.linalg.norm(lattice[:, None] - corner[None], axis=2)  # (L, 8)
    excess = np.zeros(len(near))
    for start in range(0, len(near), max(1, chunk // len(lattice))):
        block = near[start:start + max(1, chunk // len(lattice))]
        pts = (grid.origin + grid.resolution * (block[:, None, :] + lattice[None])).reshape(-1, 3)
        phi_c = d[tuple((block[:, None, :] + corner[None]).transpose(2, 0, 1))]  # (B, 8)
        clearance = np.abs(phi_c)[:, None, :] - to_corner[None]  # (B, L, 8)
        best = np.argmax(clearance, axis=2)
        known = np.take_along_axis(clearance, best[..., None], axis=2)[..., 0] > 0.0
        side = np.where(known, np.sign(np.take_along_axis(phi_c[:, None, :], best[..., None], axis=2)[..., 0]), 0.0)
        exact, _, _ = signed_distance(mesh, pts, side.ravel())
        interp, _, _ = grid.interpolate(pts)
        excess[start:start + len(block)] = np.maximum(0.0, (interp[:, 0] - exact).reshape(len(block), -1).max(axis=1))
    values = np.zeros(cells)
    values[tuple(near.T)] = excess
    return ErrorMargin(grid.origin, grid.resolution, cells, values.ravel())


def cached_margin(grid: VoxelGrid, mesh: TriMesh, reach_m: float, cache_dir: Path | None = None) -> ErrorMargin:
    """:func:`interpolation_margin`, cached by mesh content, grid geometry and reach."""
    key = f"{mesh.content_hash}-{grid.resolution}-{tuple(grid.shape)}-{grid.origin.tolist()}-{reach_m}-both-sides"
    name = hashlib.sha256(key.encode()).hexdigest()
    path = (default_cache_dir() if cache_dir is None else Path(cache_dir)) / "margins" / f"{name}.npz"
    cells = tuple(s - 1 for s in grid.shape)

    def build() -> dict[str, np.ndarray]:
        return {"values": interpolation_margin(grid, mesh, reach_m).values}

    def check(a: dict[str, np.ndarray]) -> None:
        if a["values"].shape != (int(np.prod(cells)),) or not np.isfinite(a["values"]).all():
            raise ValueError("margin array does not match the grid")

    a = cached_arrays(path, key, build, check)
    return ErrorMargin(grid.origin, grid.resolution, cells, np.asarray(a["values"], np.float64))
