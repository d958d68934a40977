"""Geodesic distances on a mesh surface (heat method, potpourri3d) between its samples, and the
blends that read them at any point near the surface: the geodesic-to-chord ratio behind the
interaction residuals' weights (docs/method.md "Interaction residuals and cost")."""

from __future__ import annotations

import numba
import numpy as np
import potpourri3d as pp3d
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from retarget.geometry.jit import inlined
from retarget.geometry.voxel_grid import PREFETCH_AHEAD, VoxelGrid, _prefetch


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
