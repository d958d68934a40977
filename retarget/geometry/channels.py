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
the configuration; a cache file that fails validation is rebuilt, never trusted. The grids are
``retarget.geometry.voxel_grid``, the geodesic tables ``retarget.geometry.geodesics``, the disk
cache ``retarget.geometry.cache``; this module holds the channels that combine them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import igl
import numba
import numpy as np

from retarget.geometry.cache import cached_arrays, default_cache_dir, hash_key
from retarget.geometry.geodesics import SurfaceGeodesics
from retarget.geometry.voxel_grid import VoxelGrid, build_sdf_grid
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


@dataclass(frozen=True)
class GeometryConfig:
    """Proximity geometry settings (paper Sec. III-A; docs/method.md "Proximity triple")."""

    grid_resolution_m: float = 0.01  # 1 cm isotropic voxels (Sec. III-A)
    band_m: float = 0.15  # d̄: grid covers 15 cm beyond the surface; a pair is active when d < d̄
    human_density_per_m2: float = 2000.0  # probe densities (Sec. III-A)
    robot_density_per_m2: float = 2000.0
    object_density_per_m2: float = 1000.0
    #: Ours: the human and robot probes as an even cover (``sample_surface``'s ``even``: farthest-point
    #: thinning of a 8× denser random sample) rather than i.i.d. area-uniform draws; the probe seed
    #: then only picks which of several near-equal covers is used (docs/results/box.md, "No lottery").
    even_probes: bool = False
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


#: ``sample_surface(even=True)``: candidates drawn per kept sample before the farthest-point thinning.
EVEN_OVERSAMPLING = 8


def sample_surface(mesh: TriMesh, density_per_m2: float, seed: int = 0, even: bool = False) -> SurfaceSamples:
    """Area-uniform random samples, round(area · density) of them (at least 1); same seed, same cloud.

    ``even``: an even cover instead: ``EVEN_OVERSAMPLING`` × as many area-uniform draws, thinned by
    farthest-point sampling (from the first draw) to the count. Two seeds give two covers of the
    same spacing (blue noise) instead of two i.i.d. clouds with their clumps and holes; the
    samples come in farthest-point order, so any prefix is itself an even, sparser cover."""
    if not density_per_m2 > 0:
        raise ValueError(f"{mesh.name}: density must be > 0 points/m², got {density_per_m2}")
    count = max(1, round(mesh.area_m2 * density_per_m2))
    if not even:
        return _sample_count(mesh, count, seed)
    dense = _sample_count(mesh, EVEN_OVERSAMPLING * count, seed)
    keep = farthest_point_order(dense.points, count)
    return SurfaceSamples(dense.points[keep], dense.normals[keep], dense.face[keep])


def farthest_point_order(points: np.ndarray, count: int) -> np.ndarray:
    """Indices of ``count`` of ``points`` (N, 3): farthest-point sampling from the first point
    (each next point the one farthest from those chosen; Euclidean)."""
    count = min(count, len(points))
    chosen = np.empty(count, np.int64)
    chosen[0] = 0
    dist = np.sum((points - points[0]) ** 2, axis=1)
    for k in range(1, count):
        chosen[k] = i = int(np.argmax(dist))
        np.minimum(dist, np.sum((points - points[i]) ** 2, axis=1), out=dist)
    return chosen


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


# --------------------------------------------------------------------------- geodesics


# --------------------------------------------------------------------------- disk cache


# --------------------------------------------------------------------------- channels


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
        key = hash_key(_GRID_FORMAT, mesh.content_hash, cfg.grid_resolution_m, cfg.band_m, density, seed,
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


__all__ = ["Channel", "GeometryConfig", "GroundChannel", "InvalidMeshError", "ProximityQuery", "SDFChannel",
           "SurfaceSamples", "load_channel", "sample_surface"]
