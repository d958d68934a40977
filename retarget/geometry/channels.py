"""Proximity channels: probe clouds, SDF/witness voxel grids, the ground, surface geodesics.

A *channel* is an entity a probe can be near: an object, a robot link, the ground. Every
query takes probe positions already expressed in the **channel frame** (the object's mesh
frame; the world for the ground) and returns the proximity triple of the paper (Sec. III-A,
eq. m-triple) with the derivatives the SQP needs:

* Φ (signed distance, m, negative inside) and W (witness = closest surface point) are
  sampled once on a 1 cm voxel grid covering the band d̄ = 15 cm around the surface, then
  interpolated trilinearly; ∂Φ/∂x and ∂W/∂x are the exact derivatives of that interpolant.
  Node values are those of :func:`retarget.inputs.meshes.signed_distance` (exact distance, sign from
  the fast winding number), so scanned meshes with holes keep correct signs; they are built
  for a fraction of its per-node cost by ``retarget.geometry.distance_grid``. Where a cell
  straddles the medial axis (inside an object near an edge, outside in a fold) a blend of
  witnesses lies off the surface; those witnesses are re-projected (see ``SDFChannel.query``).
* ρ(w; ŵ), the geodesic distance between two surface points, is precomputed between all pairs
  of a surface sample cloud with the heat method on point clouds (potpourri3d) and stored as
  the ratio geodesic/chord; for arbitrary witnesses ρ = |w − ŵ| · γ(w, ŵ), γ interpolated from
  the nearest samples. The ratio is ≥ 1 and slowly varying, so ρ → 0 exactly as w → ŵ and
  its gradient keeps the chord direction where the surface is flat.
* The ground is analytic: d = z, w = (x, y, 0).

Grids and geodesic tables are immutable and cached on disk keyed by the mesh content and
the configuration; a cache file that fails validation is rebuilt, never trusted.
"""

from __future__ import annotations

import hashlib
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import igl
import numba
import numpy as np
import potpourri3d as pp3d
from llvmlite import ir as llvm_ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from otr_gym.io import load_npz, save_npz
from retarget.geometry.distance_grid import grid_signed_distance, node_positions
from retarget.geometry.jit import helper, inlined
from retarget.inputs.meshes import InvalidMeshError, TriMesh, load_mesh, object_mesh

#: Bumped whenever the content or layout of cached grids changes.
_GRID_FORMAT = 2
#: Offset (m) along the SDF gradient mixed into witness→probe before normalising, so that n is the
#: outward normal (times sign d) at contact, where x − w is a few µm of interpolation noise.
_NORMAL_BLEND_M = 1e-3
#: Probes closer than this to the surface count as on it: n is the outward normal there.
_ON_SURFACE_M = 1e-6
#: ‖∂W/∂x‖²_F above which a cell's blended witness is distrusted: a closest-point map gives 2 on a
#: face, less at convex edges and corners, more only in concave regions (where blends drift).
_MEDIAL_JACOBIAN_SQ = 2.2
#: Trilinear corner order: bit 2 = x, bit 1 = y, bit 0 = z (so z-pairs are adjacent).
_CORNERS = np.array([[(k >> 2) & 1, (k >> 1) & 1, k & 1] for k in range(8)], dtype=np.intp)


@dataclass(frozen=True)
class GeometryConfig:
    """Proximity geometry settings (paper Sec. III-A; docs/method.md "Proximity triple")."""

    grid_resolution_m: float = 0.01  # 1 cm isotropic voxels (Sec. III-A)
    band_m: float = 0.15  # d̄: grid covers 15 cm beyond the surface; a pair is active when d < d̄
    human_density_per_m2: float = 2000.0  # probe densities (Sec. III-A)
    robot_density_per_m2: float = 2000.0
    object_density_per_m2: float = 1000.0
    # Our choices for the geodesic table (the paper only says "precomputed on the channel cloud"):
    geodesic_min_samples: int = 200  # small links still get a usable all-pairs table
    geodesic_max_samples: int = 2000  # K heat solves and a K×K table: ~3 s and 16 MB at K = 2000
    geodesic_neighbours: int = 4  # samples blended per witness


# --------------------------------------------------------------------------- probe sampling


@dataclass(frozen=True)
class SurfaceSamples:
    """Points on a surface (mesh frame, m), the unit normal of their face, and that face's index.

    Normals follow the face winding (outward for a consistently oriented closed mesh).
    """

    points: np.ndarray  # (N, 3)
    normals: np.ndarray  # (N, 3)
    face: np.ndarray  # (N,) int

    def __len__(self) -> int:
        return len(self.points)


def sample_surface(mesh: TriMesh, density_per_m2: float, seed: int = 0) -> SurfaceSamples:
    """Area-uniform random samples, round(area · density) of them (at least 1); same seed, same cloud."""
    if not density_per_m2 > 0:
        raise ValueError(f"{mesh.name}: density must be > 0 points/m², got {density_per_m2}")
    return _sample_count(mesh, max(1, round(mesh.area_m2 * density_per_m2)), seed)


def _sample_count(mesh: TriMesh, count: int, seed: int) -> SurfaceSamples:
    tri = mesh.vertices[mesh.faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    rng = np.random.default_rng(seed)
    face = rng.choice(len(area2), size=count, p=area2 / area2.sum())
    # Uniform barycentrics by the square-root fold (Osada et al. 2002).
    r1 = np.sqrt(rng.random(count))
    r2 = rng.random(count)
    t = tri[face]
    points = (1 - r1)[:, None] * t[:, 0] + (r1 * (1 - r2))[:, None] * t[:, 1] + (r1 * r2)[:, None] * t[:, 2]
    normals = cross[face] / area2[face, None]
    return SurfaceSamples(points, normals, face.astype(np.int64))


# --------------------------------------------------------------------------- query result


@dataclass(frozen=True)
class ProximityQuery:
    """Proximity triple of N probes w.r.t. one channel, all in the channel frame.

    d (N,) signed distance (m, negative inside, clamped to band_m out of band);
    w (N, 3) witness (closest surface point); n (N, 3) unit vector witness→probe, equal to
    sign(d)·outward normal as d → 0 and the outward normal within 1 µm of the surface (None
    when the query was asked for no normals); grad_d (N, 3) ∂d/∂x, the exact gradient of the trilinear
    interpolant; dw_dx (N, 3, 3) ∂w/∂x, the exact Jacobian of the interpolated witness
    (I − n nᵀ on faces, smaller at convex edges and corners), or I − n nᵀ of the face where a
    witness was re-projected; in_band (N,) bool: inside the grid and d < band_m. Out of band,
    d = band_m and both gradients are zero.
    """

    d: np.ndarray
    w: np.ndarray
    n: np.ndarray | None
    grad_d: np.ndarray
    dw_dx: np.ndarray
    in_band: np.ndarray

    def __len__(self) -> int:
        return len(self.d)


class Channel(Protocol):
    """What the residuals need from a channel; every array in the channel frame."""

    name: str
    is_ground: bool

    def query(self, x_c: np.ndarray, exact_witness: bool = False, normals: bool = True) -> ProximityQuery: ...

    def distance(self, x_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    def geodesic(self, w: np.ndarray, w_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def geodesic_ratio(self, w: np.ndarray, w_hat: np.ndarray,
                       hat_weights: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]: ...

    def geodesic_weights(self, w_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None: ...


def _check_points(name: str, x: np.ndarray, what: str = "probes") -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"{name}: {what} must be (N, 3), got {x.shape}")
    return x


# --------------------------------------------------------------------------- voxel grid


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
        return self.origin + self.resolution * idx, np.take(self.values, idx @ self._strides, axis=0)

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


def _medial_cells(x: np.ndarray, d: np.ndarray, corner_pos: np.ndarray,
                  corner_val: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which probes' cells straddle the medial axis, and a planar witness for them.

    x (M, 3) probes at interpolated distance d (M,), their cell corners (8, M, 3) and values
    (8, M, 4). A corner k on the probe's side of the surface sees it at W_k along the unit
    m_k = (p_k − W_k)/|Φ_k|. Views of one face, or around a convex feature, never converge;
    a view that converges with the cell's mean view (m_k − m̄ opposes W_k − W̄) and differs from
    it by more than ~10° sees another face across the medial axis (inside near an edge,
    outside in a fold), where a blend of witnesses lies off the surface. Returns that mask
    (M,), and for the masked probes the projection of x on the nearest corner tangent plane
    (S, 3) with its unit normal (S, 3): exact on planar faces, hence for probes inside box-like
    objects (NaN where no corner qualifies).
    """
    phi, wk = corner_val[..., 0], corner_val[..., 1:]
    # Corners on the surface have no view direction; corners across it see another medial axis.
    valid = (np.abs(phi) > 1e-6) & ((phi < 0.0) == (d < 0.0)[None])
    mk = (corner_pos - wk) / np.where(valid, np.abs(phi), 1.0)[..., None]
    weight = valid / np.maximum(valid.sum(axis=0), 1)[None]
    dm = mk - np.einsum("km,kmj->mj", weight, mk)[None]
    dwk = wk - np.einsum("km,kmj->mj", weight, wk)[None]
    dm_sq = np.einsum("kmj,kmj->km", dm, dm)
    converge = np.einsum("kmj,kmj->km", dm, dwk) < -0.25 * np.sqrt(dm_sq * np.einsum("kmj,kmj->km", dwk, dwk))
    straddle = np.any(converge & (dm_sq > 0.03) & valid, axis=0)
    rows = np.flatnonzero(straddle)
    m_s, w_s, v_s = mk[:, rows], wk[:, rows], valid[:, rows]
    height = np.einsum("kmj,kmj->km", x[rows][None] - w_s, m_s)  # signed distance of x to each corner plane
    best = np.argmin(np.where(v_s, np.abs(height), np.inf), axis=0)
    cols = np.arange(len(rows))
    normal = np.where(v_s[best, cols][:, None], m_s[best, cols], np.nan)
    return straddle, x[rows] - height[best, cols][:, None] * normal, normal


# --------------------------------------------------------------------------- geodesics


class SurfaceGeodesics:
    """Geodesic distance between arbitrary points of one surface (mesh frame, m).

    Precomputed: heat-method distances (potpourri3d point-cloud solver) between all pairs of
    ``points``, stored as ``ratio`` = geodesic / chord clipped to ≥ 1 (geodesics are never
    shorter than chords; the heat method underestimates at a few sample spacings). Online:
    ρ(w, ŵ) = |w − ŵ| · Σ_ij α_i(w) α_j(ŵ) ratio_ij with Gaussian weights α (bandwidth = mean
    sample spacing) over k samples near each point. The k samples are those nearest to the
    closest node of ``grid`` (a table made once), which spares a k-d tree search per call.
    """

    def __init__(self, points: np.ndarray, ratio: np.ndarray, spacing_m: float, grid: VoxelGrid,
                 neighbour_table: np.ndarray) -> None:
        self.points = points
        self.ratio = ratio
        self.spacing_m = float(spacing_m)
        self.grid = grid
        self.neighbour_table = neighbour_table

    @staticmethod
    def heat_ratio(points: np.ndarray) -> np.ndarray:
        """All-pairs geodesic/chord ratio (K, K) float32 by the heat method on the point cloud."""
        solver = pp3d.PointCloudHeatSolver(points)
        dist = np.stack([solver.compute_distance(i) for i in range(len(points))])
        dist = 0.5 * (dist + dist.T)  # the heat method is not exactly symmetric
        chord = cdist(points, points)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(chord > 0, dist / chord, 1.0)
        return np.maximum(ratio, 1.0).astype(np.float32)

    @staticmethod
    def make_neighbour_table(points: np.ndarray, grid: VoxelGrid, neighbours: int) -> np.ndarray:
        """(nodes, k) int32: the k samples nearest to every grid node."""
        k = int(min(neighbours, len(points)))
        _, idx = cKDTree(points).query(grid.node_positions, k=k)
        return idx.reshape(-1, k).astype(np.int32)

    def weights(self, x: np.ndarray, derivative: bool = False) -> tuple[np.ndarray, ...]:
        """Neighbour indices (N, k) and normalised weights (N, k) of points x (N, 3), and with
        ``derivative`` ∂weights/∂x (N, k, 3)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        table, grid = self.neighbour_table, self.grid
        idx = np.empty((len(x), table.shape[1]), table.dtype)
        a = np.empty(idx.shape)
        da = np.empty(idx.shape + (3,)) if derivative else np.empty((0, 0, 3))
        _neighbours(x, table, grid.origin, 1.0 / grid.resolution, grid._upper, grid._strides, idx)
        _blend_weights(x, idx, self.points, 1.0 / self.spacing_m**2, a, da)
        return (idx, a, da) if derivative else (idx, a)

    def chord_ratio(self, w: np.ndarray, w_hat: np.ndarray,
                    hat_weights: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """γ(w, ŵ) = ρ/|w − ŵ| (N,), the blended geodesic/chord ratio, and ∂γ/∂w (N, 3):
        γ = Σ_ij α_i(w) β_j(ŵ) ratio_ij over the neighbour samples of w and ŵ.

        ``hat_weights``: :meth:`weights` of ŵ when already known (they depend on ŵ alone)."""
        i, a, da = self.weights(w, derivative=True)
        j, b = self.weights(w_hat) if hat_weights is None else hat_weights
        gamma, dgamma = np.empty(len(a)), np.empty((len(a), 3))
        _blend_ratio(self.ratio, i, a, da, j, b, gamma, dgamma)
        return gamma, dgamma

    def distance(self, w: np.ndarray, w_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ρ(w; ŵ) (N,) in m and ∂ρ/∂w (N, 3); w, ŵ on the surface (mesh frame)."""
        gamma, dgamma = self.chord_ratio(w, w_hat)
        chord = w - w_hat
        e = np.sqrt(np.einsum("nj,nj->n", chord, chord))
        unit = np.divide(chord, e[:, None], out=np.zeros_like(chord), where=e[:, None] > 0)
        return e * gamma, gamma[:, None] * unit + e[:, None] * dgamma


@numba.njit(cache=True)
def _neighbours(x, table, origin, inv_resolution, upper, strides, out):
    """out[n] ← the neighbour-table row of the grid node nearest to x[n] (grid frame; see
    ``_nearest_row``); the rows of ``PREFETCH_AHEAD`` points on are prefetched (the table is
    scattered over 8 MB)."""
    for n in range(x.shape[0]):
        if n + PREFETCH_AHEAD < x.shape[0]:
            _prefetch(table, (_nearest_row(x, n + PREFETCH_AHEAD, origin, inv_resolution, upper, strides), 0))
        row = _nearest_row(x, n, origin, inv_resolution, upper, strides)
        for j in range(table.shape[1]):  # element-wise: a row assignment compiles numba's shape-error formatting
            out[n, j] = table[row, j]


@inlined
def _nearest_row(x, n, origin, inv_resolution, upper, strides):
    """The row of the grid node nearest to x[n] (its index per axis rounded half to even and
    clipped to the grid, then the strides)."""
    row = 0
    for c in range(3):
        row += int(min(max(np.rint((x[n, c] - origin[c]) * inv_resolution), 0.0), upper[c])) * strides[c]
    return row


@numba.njit(cache=True)
def _blend_weights(x, idx, points, inv_h2, a, da):
    """Gaussian weights a (N, k) of the samples ``points[idx]`` around each x (N, 3), bandwidth
    h (inv_h2 = 1/h²), normalised to sum 1; when ``da`` has N rows, ∂a/∂x = a (s − s̄)/h²."""
    k = idx.shape[1]
    diff = np.empty((k, 3))
    sq = np.empty(k)
    for n in range(x.shape[0]):
        low = np.inf
        for i in range(k):
            for c in range(3):
                diff[i, c] = points[idx[n, i], c] - x[n, c]  # s_i − x
            sq[i] = diff[i, 0] * diff[i, 0] + diff[i, 1] * diff[i, 1] + diff[i, 2] * diff[i, 2]
            low = min(low, sq[i])
        total = 0.0
        for i in range(k):
            a[n, i] = np.exp(-0.5 * inv_h2 * (sq[i] - low))
            total += a[n, i]
        for i in range(k):
            a[n, i] /= total
        if da.shape[0]:
            for c in range(3):
                mean = 0.0
                for i in range(k):
                    mean += a[n, i] * diff[i, c]
                for i in range(k):
                    da[n, i, c] = (diff[i, c] - mean) * (a[n, i] * inv_h2)


@numba.njit(cache=True)
def _blend_ratio(ratio, i_idx, a, da, j_idx, b, gamma, dgamma):
    """γ = Σ_i a_i row_i and ∂γ/∂w = Σ_i ∂a_i row_i with row_i = Σ_j b_j ratio[i, j]. The
    table (K × K, 16 MB at K = 2000) is read at scattered entries: those of the witness
    ``PREFETCH_AHEAD`` further on are prefetched meanwhile."""
    for n in range(a.shape[0]):
        if n + PREFETCH_AHEAD < a.shape[0]:
            for i in range(a.shape[1]):
                for j in range(b.shape[1]):
                    _prefetch(ratio, (i_idx[n + PREFETCH_AHEAD, i], j_idx[n + PREFETCH_AHEAD, j]))
        g = 0.0
        d0 = d1 = d2 = 0.0
        for i in range(a.shape[1]):
            row = 0.0
            for j in range(b.shape[1]):
                row += np.float64(ratio[i_idx[n, i], j_idx[n, j]]) * b[n, j]
            g += a[n, i] * row
            d0 += da[n, i, 0] * row
            d1 += da[n, i, 1] * row
            d2 += da[n, i, 2] * row
        gamma[n] = g
        dgamma[n, 0], dgamma[n, 1], dgamma[n, 2] = d0, d1, d2


# --------------------------------------------------------------------------- disk cache


def default_cache_dir() -> Path:
    """$OTR_CACHE_DIR, else ~/.cache/otr-gym."""
    return Path(os.environ.get("OTR_CACHE_DIR", Path.home() / ".cache" / "otr-gym"))


def cached_arrays(path: Path, key: str, build: Callable[[], dict[str, np.ndarray]],
                  check: Callable[[dict[str, np.ndarray]], None]) -> dict[str, np.ndarray]:
    """Load ``path`` if it holds ``key`` and passes ``check``; otherwise build, save, return.

    A file that cannot be read, holds another key, or fails ``check`` (which raises) is
    rebuilt with a warning naming it.
    """
    if path.is_file():
        try:
            arrays = load_npz(path)
            if str(arrays.pop("cache_key", "")) != key:
                raise ValueError("cache key mismatch")
            check(arrays)
            return arrays
        except Exception as exc:  # noqa: BLE001 - any unreadable or invalid file is rebuilt, never trusted
            warnings.warn(f"{path}: invalid cache file ({type(exc).__name__}: {exc}); rebuilding", stacklevel=3)
    arrays = build()
    save_npz(path, {**arrays, "cache_key": np.array(key)}, compressed=False)
    return arrays


def _hash_key(*parts: object) -> str:
    return hashlib.sha256("|".join(str(p) for p in parts).encode()).hexdigest()


# --------------------------------------------------------------------------- channels


class SDFChannel:
    """A rigid mesh as a proximity channel (object or robot link), everything in its mesh frame.

    Immutable after construction: ``mesh``, ``surface`` (its probe cloud at the channel's
    density), ``grid`` (Φ, W), ``geodesics``.
    """

    is_ground = False

    def __init__(self, name: str, mesh: TriMesh, surface: SurfaceSamples, grid: VoxelGrid,
                 geodesics: SurfaceGeodesics, band_m: float) -> None:
        self.name = name
        self.mesh = mesh
        self.surface = surface
        self.grid = grid
        self.geodesics = geodesics
        self.band_m = float(band_m)
        self._aabb = None

    @classmethod
    def from_mesh(cls, mesh: TriMesh, cfg: GeometryConfig = GeometryConfig(), cache_dir: Path | None = None,
                  density_per_m2: float | None = None, seed: int = 0, name: str | None = None) -> SDFChannel:
        """Build (or load from the cache) the channel of ``mesh``.

        ``density_per_m2`` of the surface cloud defaults to the object density (use
        ``cfg.robot_density_per_m2`` for robot links). Raises InvalidMeshError naming the mesh
        when it has invalid arrays; a surface that encloses no volume becomes a shell
        (``retarget.inputs.meshes.object_mesh``, with a warning).
        """
        mesh = object_mesh(mesh.vertices, mesh.faces, getattr(mesh, "name", "<mesh>"))
        density = cfg.object_density_per_m2 if density_per_m2 is None else float(density_per_m2)
        surface = sample_surface(mesh, density, seed)
        n_geo = int(np.clip(len(surface), cfg.geodesic_min_samples, cfg.geodesic_max_samples))
        geo_samples = surface if n_geo == len(surface) else _sample_count(mesh, n_geo, seed + 1)
        key = _hash_key(_GRID_FORMAT, mesh.content_hash, cfg.grid_resolution_m, cfg.band_m, density, seed,
                        n_geo)
        path = (default_cache_dir() if cache_dir is None else Path(cache_dir)) / "sdf" / f"{key}.npz"

        def build() -> dict[str, np.ndarray]:
            grid = build_sdf_grid(mesh, cfg.grid_resolution_m, cfg.band_m)
            return {"origin": grid.origin, "resolution": np.array(grid.resolution), "shape": np.array(grid.shape),
                    "values": grid.values, "geodesic_ratio": SurfaceGeodesics.heat_ratio(geo_samples.points),
                    "geodesic_neighbours": SurfaceGeodesics.make_neighbour_table(geo_samples.points, grid,
                                                                                 cfg.geodesic_neighbours)}

        def check(a: dict[str, np.ndarray]) -> None:
            shape = tuple(int(s) for s in a["shape"])
            if len(shape) != 3 or a["values"].shape != (int(np.prod(shape)), 4) or a["origin"].shape != (3,):
                raise ValueError(f"grid arrays have inconsistent shapes {a['values'].shape} vs {shape}")
            if a["geodesic_ratio"].shape != (n_geo, n_geo):
                raise ValueError(f"geodesic table is {a['geodesic_ratio'].shape}, expected {(n_geo, n_geo)}")
            table = a["geodesic_neighbours"]
            if table.shape[0] != len(a["values"]) or table.min() < 0 or table.max() >= n_geo:
                raise ValueError(f"geodesic neighbour table {table.shape} does not match the grid")
            if not (np.isfinite(a["values"]).all() and np.isfinite(a["geodesic_ratio"]).all()):
                raise ValueError("non-finite values")

        a = cached_arrays(path, key, build, check)
        grid = VoxelGrid(np.asarray(a["origin"], np.float64), float(a["resolution"]),
                         tuple(int(s) for s in a["shape"]), np.ascontiguousarray(a["values"], np.float64))
        spacing = float(np.sqrt(mesh.area_m2 / n_geo))
        geodesics = SurfaceGeodesics(geo_samples.points, a["geodesic_ratio"], spacing, grid,
                                     a["geodesic_neighbours"])
        return cls(name or mesh.name, mesh, surface, grid, geodesics, cfg.band_m)

    def query(self, x_c: np.ndarray, exact_witness: bool = False, normals: bool = True) -> ProximityQuery:
        """Proximity of probes ``x_c`` (N, 3) given in the channel frame (m).

        Witnesses are the trilinear blend of the grid's, except in cells that straddle the
        medial axis (see :func:`_medial_cells`), where a blend lies off the surface:
        penetrating probes there take the planar witness (exact on flat faces). With
        ``exact_witness`` (once-per-frame work such as the demonstration's targets), every
        such cell, and every cell stretched like a concave fold, gets the exact closest point
        of the mesh instead (AABB tree, ~25 µs per probe). Without ``normals`` the result's
        ``n`` is None (the solver's residuals use the demonstrated n̂ only).
        """
        x = _check_points(self.name, x_c)
        val, jac, inside = self.grid.interpolate(x)
        d, in_band = _into_band(val[:, 0], jac.reshape(len(x), jac.shape[1] * 3), inside, self.band_m)
        w = val[:, 1:]
        dw_dx = jac[:, 1:]
        # Only penetrating probes and blends that stretch more than a closest-point map does on
        # a face (‖∂w/∂x‖²_F = 2; less at convex edges and corners) can straddle the medial axis.
        # The hot path checks penetrating probes only: outside, only folds (concave regions)
        # stretch, and their blends stay within ~2 mm of the surface for 99 % of probes near it.
        if exact_witness:
            stretched = np.einsum("nij,nij->n", dw_dx, dw_dx) > _MEDIAL_JACOBIAN_SQ
            suspect = np.flatnonzero(in_band & (stretched | (val[:, 0] < 0.0)))
        else:
            suspect = np.flatnonzero(in_band & (val[:, 0] < 0.0))
        if len(suspect):
            straddle, w_plane, n_plane = _medial_cells(x[suspect], val[suspect, 0], *self.grid.corners(x[suspect]))
            if exact_witness:
                fix = suspect[straddle | stretched[suspect]]
                w[fix] = self._closest_points(x[fix])
                normal = x[fix] - w[fix]
                normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
            else:
                keep = np.isfinite(n_plane[:, 0])
                fix, normal = suspect[straddle][keep], n_plane[keep]
                w[fix] = w_plane[keep]
            # The tangent projection of a face (exact there; at an edge or vertex the true ∂w/∂x is smaller).
            dw_dx[fix] = np.eye(3) - normal[:, :, None] * normal[:, None, :]
        grad = jac[:, 0]
        n = self._normals(x, d, w, grad) if normals else None
        return ProximityQuery(d=d, w=w, n=n, grad_d=grad, dw_dx=dw_dx, in_band=in_band)

    @staticmethod
    def _normals(x: np.ndarray, d: np.ndarray, w: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """Unit witness→probe directions (N, 3); the outward normal (× sign d) at contact."""
        sign = np.where(d < -_ON_SURFACE_M, -1.0, 1.0)[:, None]
        g_norm = np.linalg.norm(grad, axis=1, keepdims=True)
        outward = sign * (x - w) + _NORMAL_BLEND_M * np.divide(grad, g_norm, out=np.zeros_like(grad),
                                                                where=g_norm > 0)
        o_norm = np.linalg.norm(outward, axis=1, keepdims=True)
        return sign * np.divide(outward, o_norm, out=np.zeros_like(outward), where=o_norm > 0)

    def distance(self, x_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(d, ∂d/∂x, in_band) of :meth:`query` alone, for points that need no witness
        (non-penetration constraints): (N,), (N, 3), (N,) bool, channel frame."""
        x = _check_points(self.name, x_c)
        val, grad, inside = self.grid.interpolate_distance(x)
        d, in_band = _into_band(val, grad, inside, self.band_m)
        return d, grad, in_band

    def _closest_points(self, x: np.ndarray) -> np.ndarray:
        """Exact closest surface points (M, 3); the AABB tree is built on first use (it cannot be pickled)."""
        if len(x) == 0:
            return np.zeros((0, 3))
        if self._aabb is None:
            self._aabb = igl.AABB()
            self._aabb.init(self.mesh.vertices, self.mesh.faces)
        return self._aabb.squared_distance(self.mesh.vertices, self.mesh.faces, np.ascontiguousarray(x))[2]

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_aabb": None}

    def geodesic(self, w: np.ndarray, w_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Geodesic distance ρ (N,) between witnesses w and ŵ (N, 3) on this surface, and ∂ρ/∂w (N, 3)."""
        return self.geodesics.distance(_check_points(self.name, w, "witnesses"),
                                       _check_points(self.name, w_hat, "witnesses"))

    def geodesic_ratio(self, w: np.ndarray, w_hat: np.ndarray,
                       hat_weights: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """γ = ρ/|w − ŵ| (N,) and ∂γ/∂w (N, 3) for witnesses (N, 3); ``hat_weights`` from
        :meth:`geodesic_weights` of ŵ spares their recomputation."""
        return self.geodesics.chord_ratio(w, w_hat, hat_weights)

    def geodesic_weights(self, w_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The geodesic table's neighbours (N, k) and blending weights (N, k) of witnesses ŵ."""
        return self.geodesics.weights(w_hat)


def _into_band(val: np.ndarray, jac: np.ndarray, inside: np.ndarray, band: float) -> tuple[np.ndarray, np.ndarray]:
    """Interpolated distances ``val`` (N,) as a query answers them: d = val inside the grid and
    below the band, else the band (N,), and that mask (N,); the rows of their Jacobian ``jac``
    (N, ·) are zeroed in place outside it (multiplied by 0.0, as by the mask)."""
    d, in_band = np.empty(len(val)), np.empty(len(val), dtype=bool)
    _into_band_kernel(np.ascontiguousarray(val), jac, inside, float(band), d, in_band)
    return d, in_band


@numba.njit(cache=True)
def _into_band_kernel(val, jac, inside, band, d, in_band):
    for i in range(val.shape[0]):
        in_band[i] = inside[i] and val[i] < band
        d[i] = val[i] if in_band[i] else band
        scale = 1.0 if in_band[i] else 0.0
        for j in range(jac.shape[1]):
            jac[i, j] *= scale


class GroundChannel:
    """The flat ground z = 0 (world frame), exact everywhere; in_band marks z < band_m."""

    is_ground = True

    def __init__(self, name: str = "ground", band_m: float = GeometryConfig.band_m) -> None:
        self.name = name
        self.band_m = float(band_m)

    def query(self, x_c: np.ndarray, exact_witness: bool = False, normals: bool = True) -> ProximityQuery:
        """Exact triple of probes ``x_c`` (N, 3) in the world frame (``exact_witness`` has no
        effect; without ``normals``, ``n`` is None)."""
        x = _check_points(self.name, x_c)
        k = len(x)
        d, w, grad, dw_dx = np.empty(k), np.empty((k, 3)), np.empty((k, 3)), np.empty((k, 3, 3))
        n, in_band = np.empty((k if normals else 0, 3)), np.empty(k, dtype=bool)
        _ground_query(x, self.band_m, d, w, n, grad, dw_dx, in_band)
        return ProximityQuery(d=d, w=w, n=n if normals else None, grad_d=grad, dw_dx=dw_dx, in_band=in_band)

    def distance(self, x_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(d = z, ∂d/∂x = e_z, d < band) of points (N, 3) in the world frame."""
        x = _check_points(self.name, x_c)
        grad = np.zeros((len(x), 3))
        grad[:, 2] = 1.0
        return x[:, 2].copy(), grad, x[:, 2] < self.band_m

    def geodesic(self, w: np.ndarray, w_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Planar distance between witnesses (N,) and its gradient w.r.t. w (N, 3)."""
        diff = _check_points(self.name, w, "witnesses") - _check_points(self.name, w_hat, "witnesses")
        diff[:, 2] = 0.0
        rho = np.linalg.norm(diff, axis=1)
        return rho, np.divide(diff, rho[:, None], out=np.zeros_like(diff), where=rho[:, None] > 0)

    def geodesic_ratio(self, w: np.ndarray, w_hat: np.ndarray,
                       hat_weights: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """γ = 1, ∂γ/∂w = 0: on the plane the geodesic is the chord (witnesses at z = 0)."""
        return np.ones(len(w)), np.zeros((len(w), 3))

    def geodesic_weights(self, w_hat: np.ndarray) -> None:
        """None: the plane needs no geodesic table."""
        return None


@numba.njit(cache=True)
def _ground_query(x, band, d, w, n, grad, dw_dx, in_band):
    """``GroundChannel.query`` point by point: d = z, w = (x, y, 0), n = ±e_z (when ``n`` has
    rows), ∂d/∂x = e_z, ∂w/∂x = diag(1, 1, 0), in band below ``band``."""
    for i in range(x.shape[0]):
        d[i] = x[i, 2]
        w[i, 0], w[i, 1], w[i, 2] = x[i, 0], x[i, 1], 0.0
        if n.shape[0]:
            n[i, 0], n[i, 1], n[i, 2] = 0.0, 0.0, -1.0 if d[i] < 0.0 else 1.0
        grad[i, 0], grad[i, 1], grad[i, 2] = 0.0, 0.0, 1.0
        for a in range(3):
            for b in range(3):
                dw_dx[i, a, b] = 1.0 if a == b and a < 2 else 0.0
        in_band[i] = d[i] < band


def load_channel(path: str | Path, cfg: GeometryConfig = GeometryConfig(), cache_dir: Path | None = None,
                 **kw) -> SDFChannel:
    """Channel of a mesh file; a missing or unreadable file raises InvalidMeshError naming it."""
    return SDFChannel.from_mesh(load_mesh(path), cfg, cache_dir, **kw)


__all__ = ["Channel", "GeometryConfig", "GridStack", "GroundChannel", "InvalidMeshError", "ProximityQuery",
           "SDFChannel", "SurfaceGeodesics", "SurfaceSamples", "VoxelGrid", "build_sdf_grid", "cached_arrays",
           "default_cache_dir", "load_channel", "sample_surface"]
