"""Signed-distance (and witness) values on regular voxel grids: trilinear interpolation, batched over
query points in compiled kernels with cache prefetching, a stack of grids queried together, the
exact grid of a mesh (``retarget.geometry.distance_grid``). Grid frame = the mesh's frame,
metres."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from llvmlite import ir as llvm_ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from retarget.geometry.distance_grid import grid_signed_distance, node_positions
from retarget.geometry.jit import helper, inlined
from retarget.inputs.meshes import TriMesh

#: Trilinear corner order: bit 2 = x, bit 1 = y, bit 0 = z (so z-pairs are adjacent).
_CORNERS = np.array([[(k >> 2) & 1, (k >> 1) & 1, k & 1] for k in range(8)], dtype=np.intp)


@dataclass(frozen=True)
class VoxelGrid:
    """Samples of (Φ, Wx, Wy, Wz) at the nodes of a regular grid, channel frame.

    Node (i, j, k) sits at origin + resolution · (i, j, k); ``values`` is (nx·ny·nz, 4) in
    C order so a node's row is i·ny·nz + j·nz + k.
    """

    origin: np.ndarray  # (3,) m
    resolution: float  # m
    shape: tuple[int, int, int]
    values: np.ndarray  # (nx*ny*nz, 4)

    def __post_init__(self) -> None:
        _, ny, nz = self.shape
        strides = np.array([ny * nz, nz, 1], dtype=np.intp)
        object.__setattr__(self, "_strides", strides)
        object.__setattr__(self, "_upper", np.array(self.shape, np.float64) - 1.0)
        object.__setattr__(self, "_phi", np.ascontiguousarray(self.values[:, 0]))

    @property
    def node_positions(self) -> np.ndarray:
        """(nx·ny·nz, 3) node positions in row order (m)."""
        return node_positions(self.origin, self.resolution, self.shape)

    def _cells(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Lower-corner node index (N, 3) of each point's cell, position in the cell (N, 3) in
        [0, 1], inside-grid mask (N,). Outside points use the cell of their projection."""
        u = (x - self.origin) * (1.0 / self.resolution)
        inside = np.all((u >= 0.0) & (u <= self._upper), axis=1)
        i0 = np.clip(np.floor(u), 0.0, self._upper - 1.0)
        return i0.astype(np.intp), np.clip(u - i0, 0.0, 1.0), inside

    def corners(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (8, N, 3) and values (8, N, 4) of the corners of each point's cell."""
        i0, _, _ = self._cells(x)
        idx = i0[None] + _CORNERS[:, None]
        return self.origin + self.resolution * idx, self.values.take(idx @ self._strides, axis=0)

    def interpolate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Trilinear values (N, 4), their Jacobian (N, 4, 3) and an inside-grid mask (N,).

        Points outside the grid are evaluated at their projection onto the grid box with a
        zero Jacobian (the caller marks them out of band).
        """
        return _interpolate(x, self.values, self.origin, 1.0 / self.resolution, self._upper, self._strides)

    def interpolate_distance(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Φ alone: :meth:`interpolate`'s first column (N,), its gradient (N, 3) and the
        inside mask, for a quarter of the memory traffic (constraint points need no witness)."""
        val, jac, inside = _interpolate(x, self._phi[:, None], self.origin, 1.0 / self.resolution, self._upper,
                                        self._strides)
        return val[:, 0], jac[:, 0], inside


def _interpolate(x: np.ndarray, values: np.ndarray, origin: np.ndarray, inv_resolution: float, upper: np.ndarray,
                 strides: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Trilinear interpolation of one grid's node ``values`` (M, C) at points x (N, 3) (grid
    frame): values (N, C), their Jacobian (N, C, 3) (zero outside the grid) and inside (N,)."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    n, ch = len(x), values.shape[1]
    val, jac, inside = np.empty((n, ch)), np.empty((n, ch, 3)), np.empty(n, dtype=np.bool_)
    _trilinear_kernel(x, np.zeros(n, np.intp), values, origin[None], np.array([inv_resolution]), upper[None],
                      strides[None], np.zeros(1, np.intp), val, jac, inside)
    return val, jac, inside


#: Points ahead whose grid cells a kernel asks the cache for while it interpolates the current
#: one: grid lookups are scattered over tens of MB, and waiting for each cell in turn took most
#: of their time (the loads of several points ahead overlap instead).
PREFETCH_AHEAD = 8


@intrinsic
def _prefetch(typingctx, ary, index):
    """Ask the cache for the element ``ary[index]`` (``index`` a tuple, one int per axis) without
    waiting for it (LLVM's prefetch: read, keep in all cache levels); changes no value."""
    sig = types.void(ary, index)

    def codegen(context, builder, signature, args):
        aryty, idxty = signature.args
        array = context.make_array(aryty)(context, builder, args[0])
        idx = [context.cast(builder, v, t, types.intp)
               for v, t in zip(cgutils.unpack_tuple(builder, args[1], len(idxty)), idxty)]
        ptr = cgutils.get_item_pointer(context, builder, aryty, array, idx, wraparound=False)
        i32 = llvm_ir.IntType(32)
        fn = cgutils.get_or_insert_function(builder.module, llvm_ir.FunctionType(llvm_ir.VoidType(),
                                                                                 [ptr.type, i32, i32, i32]),
                                            "llvm.prefetch.p0")
        builder.call(fn, [ptr, i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


@inlined
def _prefetch_cell(values, r, sx, sy):
    """Prefetch the 8 corner rows of the cell whose lower node is row r of ``values`` (M, C):
    four pairs of adjacent rows (z neighbours), each pair's first and last element."""
    last = values.shape[1] - 1
    for o in (0, sy, sx, sx + sy):
        _prefetch(values, (r + o, 0))
        _prefetch(values, (r + o + 1, last))


@inlined
def _prefetch_phi_cell(phi, r, sx, sy):
    """``_prefetch_cell`` of a flat Φ table (M,)."""
    for o in (0, sy, sx, sx + sy):
        _prefetch(phi, (r + o,))
        _prefetch(phi, (r + o + 1,))


@numba.njit(cache=True)
def _trilinear_kernel(x, grid, values, origin, inv_resolution, upper, strides, offset, val, jac, inside):
    """Trilinear interpolant of node values (M, C) at points x (N, 3), point i in the frame of
    grid g = grid[i] (origin[g], 1/resolution, upper[g] = shape − 1, node strides[g], first row
    offset[g] in ``values``); writes val (N, C), jac (N, C, 3) (∂/∂x, zero outside the grid)
    and inside (N,). Points outside use the cell of their projection onto the grid box.

    Per channel, successive lerps along z, y, x; each level's difference is the partial along
    that axis (corner rows: z pairs adjacent, then y, then x). The cell of the point
    ``PREFETCH_AHEAD`` further on is prefetched meanwhile.
    """
    n = x.shape[0]
    for i in range(n):
        if i + PREFETCH_AHEAD < n:
            r, _, _, _, _ = _cell_row(x, i + PREFETCH_AHEAD, grid, origin, inv_resolution, upper, strides, offset)
            g = grid[i + PREFETCH_AHEAD]
            _prefetch_cell(values, r, strides[g, 0], strides[g, 1])
        g = grid[i]
        r, fx, fy, fz, ok = _cell_row(x, i, grid, origin, inv_resolution, upper, strides, offset)
        inside[i] = ok
        scale = inv_resolution[g] * ok
        sx, sy = strides[g, 0], strides[g, 1]
        for k in range(values.shape[1]):
            v, gx, gy, gz = _trilinear_phi(values[:, k], r, sx, sy, fx, fy, fz)
            val[i, k] = v
            jac[i, k, 0] = gx * scale
            jac[i, k, 1] = gy * scale
            jac[i, k, 2] = gz * scale


@inlined
def _cell_row(x, i, grid, origin, inv_resolution, upper, strides, offset):
    """Point i's cell in its grid grid[i] (arguments as ``_trilinear_kernel``): see ``_cell_of``."""
    return _cell_of(x[i, 0], x[i, 1], x[i, 2], grid[i], origin, inv_resolution, upper, strides, offset)


@inlined
def _cell_of(x0, x1, x2, g, origin, inv_resolution, upper, strides, offset):
    """The cell of point x in grid g (tables as ``_trilinear_kernel``'s): the row of its lower
    node, the position in the cell (fx, fy, fz) in [0, 1], and whether x lies within the grid
    (outside, the cell of its projection)."""
    ix, fx, ok_x = _cell_axis(x0, origin[g, 0], inv_resolution[g], upper[g, 0])
    iy, fy, ok_y = _cell_axis(x1, origin[g, 1], inv_resolution[g], upper[g, 1])
    iz, fz, ok_z = _cell_axis(x2, origin[g, 2], inv_resolution[g], upper[g, 2])
    return offset[g] + ix * strides[g, 0] + iy * strides[g, 1] + iz * strides[g, 2], fx, fy, fz, ok_x and ok_y and ok_z


@helper
def _cell_axis(x, origin, inv_resolution, upper):
    """Along one axis: the cell's lower node index, the position in the cell in [0, 1], and
    whether x lies within the grid (outside, the cell of the projection)."""
    u = (x - origin) * inv_resolution
    c, f = _cell_inside(u, upper)
    return c, f, u >= 0.0 and u <= upper


@inlined
def _cell_inside(u, upper):
    """Along one axis, for a grid coordinate u: the cell's lower node index and the position in
    the cell in [0, 1] (a u outside [0, upper] gets the cell of its projection)."""
    c = min(max(np.floor(u), 0.0), upper - 1.0)
    return int(c), min(max(u - c, 0.0), 1.0)


@inlined
def _trilinear_phi(phi, r, sx, sy, fx, fy, fz):
    """One channel of :func:`_trilinear_kernel` at the cell whose lower node is row r (node
    strides sx, sy, 1) and position (fx, fy, fz) in it: the value and its partials along x, y,
    z per cell width (the same arithmetic; unused partials are optimised away when inlined)."""
    c000, c001 = phi[r], phi[r + 1]
    c010, c011 = phi[r + sy], phi[r + sy + 1]
    c100, c101 = phi[r + sx], phi[r + sx + 1]
    c110, c111 = phi[r + sx + sy], phi[r + sx + sy + 1]
    dz00, dz01, dz10, dz11 = c001 - c000, c011 - c010, c101 - c100, c111 - c110
    cz00, cz01 = c000 + fz * dz00, c010 + fz * dz01
    cz10, cz11 = c100 + fz * dz10, c110 + fz * dz11
    dy0, dy1 = cz01 - cz00, cz11 - cz10
    cyz0, cyz1 = cz00 + fy * dy0, cz10 + fy * dy1
    dyz0, dyz1 = dz00 + fy * (dz01 - dz00), dz10 + fy * (dz11 - dz10)
    dx = cyz1 - cyz0
    return cyz0 + fx * dx, dx, dy0 + fx * (dy1 - dy0), dyz0 + fx * (dyz1 - dyz0)


class GridStack:
    """The Φ columns of several voxel grids (each in its own frame) in one flat table, so that
    points spread over many grids (guard points against every nearby robot link) take one
    trilinear query. Grids may be missing (None): such entries must not be queried.
    """

    def __init__(self, grids: list[VoxelGrid | None]) -> None:
        present = [g for g in grids if g is not None]
        self.has_grid = np.array([g is not None for g in grids])
        zero3 = np.zeros(3)
        self.origin = np.array([zero3 if g is None else g.origin for g in grids])
        self.inv_resolution = np.array([0.0 if g is None else 1.0 / g.resolution for g in grids])
        self.upper = np.array([zero3 + 1.0 if g is None else g._upper for g in grids])
        self.strides = np.array([np.zeros(3, np.intp) if g is None else g._strides for g in grids])
        sizes = np.array([0 if g is None else len(g.values) for g in grids])
        self.offset = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.intp)
        self.phi = (np.concatenate([g._phi for g in present]) if present else np.zeros(0))[:, None]
        #: (G, 3) centre of each grid's box (grid frame) and (G,) its half diagonal (inf when missing)
        self.box_centre = self.origin + 0.5 * self.upper * np.array([0.0 if g is None else g.resolution
                                                                      for g in grids])[:, None]
        self.box_radius = np.array([np.inf if g is None else 0.5 * g.resolution * np.linalg.norm(g._upper)
                                    for g in grids])

    def distance(self, x: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Φ (N,), its gradient (N, 3) and the inside mask (N,) of points x (N, 3), each in the
        frame of its grid ``grid`` (N,); as :meth:`VoxelGrid.interpolate_distance` per grid."""
        n = len(x)
        val, jac, inside = np.empty((n, 1)), np.empty((n, 1, 3)), np.empty(n, dtype=np.bool_)
        _trilinear_kernel(np.ascontiguousarray(x, dtype=np.float64), np.asarray(grid, np.intp), self.phi,
                          self.origin, self.inv_resolution, self.upper, self.strides, self.offset, val, jac, inside)
        return val[:, 0], jac[:, 0], inside


def build_sdf_grid(mesh: TriMesh, resolution_m: float, band_m: float, far_m: float | None = None) -> VoxelGrid:
    """Exact Φ and W at every node of the box bounds ± (band + 1.5 voxels) (mesh frame).

    The margin of a voxel puts every point closer than ``band_m`` to the surface inside a grid
    cell, so the band is fully covered; the extra half voxel keeps nodes off the faces of
    primitives whose sizes are whole centimetres (a node on the surface has no normal).
    With ``far_m``, nodes provably farther outside hold a lower bound of Φ instead
    (``retarget.geometry.distance_grid``): for grids read only closer than ``far_m`` − √3·resolution.
    """
    pad = band_m + 1.5 * resolution_m
    lo = mesh.bounds[0] - pad
    shape = tuple(int(s) for s in np.ceil((mesh.bounds[1] + pad - lo) / resolution_m).astype(int) + 1)
    return VoxelGrid(lo, float(resolution_m), shape, grid_signed_distance(mesh, lo, float(resolution_m), shape, far_m))


