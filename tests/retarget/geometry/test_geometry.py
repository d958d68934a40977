"""retarget.geometry.channels: probe sampling, SDF/witness grids, ground channel, geodesics, caching."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from retarget.geometry.channels import GeometryConfig, GroundChannel, SDFChannel, load_channel, sample_surface
from retarget.inputs.meshes import InvalidMeshError, TriMesh, as_trimesh, load_mesh, signed_distance, winding_number

HALF = np.array([0.20, 0.15, 0.10])  # box half extents (m)
RADIUS = 0.15  # sphere radius (m)


def box_sdf(x: np.ndarray) -> np.ndarray:
    """Analytic signed distance of the box [-HALF, HALF]."""
    q = np.abs(x) - HALF
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("otr-cache")


@pytest.fixture(scope="module")
def box_mesh() -> TriMesh:
    b = trimesh.creation.box(extents=2 * HALF)
    return as_trimesh(b.vertices, b.faces, "test box")


@pytest.fixture(scope="module")
def box(box_mesh, cache) -> SDFChannel:
    return SDFChannel.from_mesh(box_mesh, cache_dir=cache)


@pytest.fixture(scope="module")
def sphere(cache) -> SDFChannel:
    s = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)
    return SDFChannel.from_mesh(as_trimesh(s.vertices, s.faces, "test sphere"), cache_dir=cache)


def band_points(lo, hi, n, seed=0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(lo, hi, size=(n, 3))


# ------------------------------------------------------------------ probe sampling


def test_sampling_is_deterministic_by_seed_and_counts_area_times_density(box_mesh):
    a = sample_surface(box_mesh, 2000.0, seed=3)
    b = sample_surface(box_mesh, 2000.0, seed=3)
    c = sample_surface(box_mesh, 2000.0, seed=4)
    assert len(a) == round(box_mesh.area_m2 * 2000.0) == 1040  # 2(0.4·0.3 + 0.4·0.2 + 0.3·0.2) m² = 0.52 m²
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.face, b.face)
    assert not np.allclose(a.points, c.points)


def test_samples_lie_on_the_surface_with_unit_face_normals(box_mesh):
    s = sample_surface(box_mesh, 2000.0)
    d, _, _ = signed_distance(box_mesh, s.points)
    assert np.abs(d).max() < 1e-12
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1.0, atol=1e-12)
    # the box's normals are the outward axis directions of the face each sample lies on
    outward = np.sign(s.points) * (np.abs(np.abs(s.points) - HALF) < 1e-9)
    np.testing.assert_allclose(s.normals, outward, atol=1e-12)


def test_sampling_is_area_uniform_over_faces_of_different_size(box_mesh):
    s = sample_surface(box_mesh, 20000.0)  # 10 400 points
    axis = np.argmax(np.abs(s.points) / HALF, axis=1)  # which pair of faces each point lies on
    observed = np.bincount(axis, minlength=3) / len(s)
    areas = np.array([HALF[1] * HALF[2], HALF[0] * HALF[2], HALF[0] * HALF[1]])
    expected = areas / areas.sum()
    # binomial standard deviation at this count is ~0.5 %; allow 4 sigma
    np.testing.assert_allclose(observed, expected, atol=0.02)


# ------------------------------------------------------------------ SDF and witness grids


def test_box_sdf_matches_analytic_distance_within_a_few_mm(box):
    lo, hi = -HALF - box.band_m, HALF + box.band_m
    x = band_points(lo, hi, 100_000)
    q = box.query(x)
    exact = box_sdf(x)
    err = np.abs(q.d - exact)[q.in_band]
    assert q.in_band.mean() > 0.8
    assert np.percentile(err, 99) < 1e-3
    assert err.max() < 6e-3  # trilinear across the kinks of the distance at edges / the medial axis
    # over (or just under) one face, two voxels from its edges, the distance is affine: exact
    margin = HALF - np.abs(x)
    one_face = (np.sum(margin < 0.005, axis=1) == 1) & (np.sort(margin, axis=1)[:, 1] > 0.02)
    assert one_face[q.in_band].sum() > 10_000
    assert np.abs(q.d - exact)[q.in_band & one_face].max() < 1e-9


def test_sphere_sdf_matches_exact_mesh_distance_within_1mm(sphere):
    x = band_points(-RADIUS - 0.15, RADIUS + 0.15, 50_000, seed=1)
    q = sphere.query(x)
    exact, _, _ = signed_distance(sphere.mesh, x)
    err = np.abs(q.d - exact)[q.in_band & (exact > -0.1)]  # the centre is a kink of the distance
    assert np.percentile(err, 99) < 5e-4
    assert err.max() < 1.5e-3


def test_largebox_scan_sign_matches_winding_number_at_1cm_and_beyond(shared_data, tmp_path):
    mesh = load_mesh(shared_data / "objects" / "largebox.obj")
    assert not trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).is_watertight
    ch = SDFChannel.from_mesh(mesh, cache_dir=tmp_path)
    x = band_points(mesh.bounds[0] - 0.15, mesh.bounds[1] + 0.15, 50_000, seed=2)
    q = ch.query(x)
    exact, _, _ = signed_distance(mesh, x)
    inside = np.abs(winding_number(mesh, x)) > 0.5
    far = q.in_band & (np.abs(exact) >= 0.01)
    assert far.sum() > 20_000 and (~inside[far]).any() and inside[far].any()
    assert np.array_equal(q.d[far] < 0, inside[far])  # 100 % sign agreement
    err = np.abs(q.d - exact)[q.in_band]
    assert np.percentile(err, 99) < 2e-3
    assert err.max() < 6e-3
    # exact witnesses for once-per-frame work: on the scanned surface to about a millimetre
    qe = ch.query(x[q.in_band][:5000], exact_witness=True)
    dw, _, _ = signed_distance(mesh, qe.w)
    assert np.percentile(np.abs(dw), 99) < 1.5e-3
    assert np.abs(dw).max() < 5e-3


def test_witnesses_lie_on_the_box_and_d_is_signed_probe_to_witness_distance(box):
    x = band_points(-HALF - box.band_m, HALF + box.band_m, 50_000, seed=3)
    q = box.query(x)
    ib = q.in_band
    on_surface, _, _ = signed_distance(box.mesh, q.w[ib])
    assert np.percentile(np.abs(on_surface), 99) < 1e-9
    assert np.abs(on_surface).max() < 3e-3  # cells that cross the surface next to an edge
    offset = np.linalg.norm(x[ib] - q.w[ib], axis=1)
    assert np.percentile(np.abs(np.abs(q.d[ib]) - offset), 99) < 1e-3
    assert np.abs(np.abs(q.d[ib]) - offset).max() < 6e-3


def test_probe_inside_near_an_edge_gets_the_nearest_face_as_witness(box):
    # 2 cm below the top face, 4 cm inside the +x face: the blend of the cell would mix both faces
    x = np.array([[HALF[0] - 0.04 + 1e-3 * k, 0.0123, HALF[2] - 0.02] for k in range(10)])
    q = box.query(x)
    np.testing.assert_allclose(q.w[:, 2], HALF[2], atol=1e-9)
    np.testing.assert_allclose(q.w[:, :2], x[:, :2], atol=1e-9)
    np.testing.assert_allclose(q.n, np.tile([0.0, 0.0, -1.0], (10, 1)), atol=1e-6)  # witness -> probe: inward
    np.testing.assert_allclose(q.dw_dx, np.tile(np.diag([1.0, 1.0, 0.0]), (10, 1, 1)), atol=1e-9)


def test_distance_gradient_and_witness_jacobian_match_finite_differences(box, sphere):
    for ch, lo, hi in ((box, -HALF - 0.12, HALF + 0.12), (sphere, -RADIUS - 0.12, RADIUS + 0.12)):
        x = band_points(lo, hi, 4000, seed=4)
        frac = (x - ch.grid.origin) / ch.grid.resolution % 1.0
        x = x[np.all((frac > 0.05) & (frac < 0.95), axis=1)]  # the interpolant is smooth inside a cell
        q = ch.query(x)
        x, q = x[q.in_band], ch.query(x[q.in_band])
        # only blended witnesses are differentiable everywhere; re-projected ones are checked above
        blended = np.einsum("nij,nij->n", q.dw_dx, q.dw_dx) < 2.2
        h = 1e-6
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            plus, minus = ch.query(x + e), ch.query(x - e)
            np.testing.assert_allclose((plus.d - minus.d) / (2 * h), q.grad_d[:, k], atol=1e-6)
            fd_w = (plus.w - minus.w) / (2 * h)
            np.testing.assert_allclose(fd_w[blended], q.dw_dx[blended, :, k], atol=1e-5)


def test_gradient_is_the_outward_face_normal_and_n_points_witness_to_probe(box):
    x = np.array([[0.0, 0.0, HALF[2] + 0.05], [0.05, -HALF[1] - 0.003, 0.0], [0.0, 0.0, HALF[2] - 0.004],
                  [0.07, 0.02, HALF[2]]])
    q = box.query(x)
    np.testing.assert_allclose(q.d, [0.05, 0.003, -0.004, 0.0], atol=1e-9)
    np.testing.assert_allclose(q.grad_d, [[0, 0, 1], [0, -1, 0], [0, 0, 1], [0, 0, 1]], atol=1e-9)
    np.testing.assert_allclose(q.n, [[0, 0, 1], [0, -1, 0], [0, 0, -1], [0, 0, 1]], atol=1e-9)


def test_probes_beyond_the_band_are_clamped_with_zero_gradients(box):
    x = np.array([[0.0, 0.0, HALF[2] + 0.149], [0.0, 0.0, HALF[2] + 0.151], [2.0, 0.0, 0.0],
                  [HALF[0] + 0.14, HALF[1] + 0.14, HALF[2] + 0.14]])  # the last: in the grid, 24 cm away
    q = box.query(x)
    np.testing.assert_array_equal(q.in_band, [True, False, False, False])
    np.testing.assert_allclose(q.d, [0.149, 0.15, 0.15, 0.15], atol=1e-9)
    assert np.all(q.grad_d[1:] == 0.0) and np.all(q.dw_dx[1:] == 0.0)
    assert np.isfinite(q.w).all() and np.isfinite(q.n).all()


def test_query_rejects_points_that_are_not_n_by_3(box):
    with pytest.raises(ValueError, match="test box: probes must be"):
        box.query(np.zeros((4, 2)))


# ------------------------------------------------------------------ ground


def test_ground_channel_is_the_plane_z_0_with_its_analytic_derivatives():
    g = GroundChannel(band_m=0.15)
    x = np.array([[0.3, -1.0, 0.02], [1.0, 2.0, -0.01], [0.0, 0.0, 0.4]])
    q = g.query(x)
    np.testing.assert_allclose(q.d, [0.02, -0.01, 0.4])
    np.testing.assert_allclose(q.w, [[0.3, -1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(q.n, [[0, 0, 1], [0, 0, -1], [0, 0, 1]])
    np.testing.assert_allclose(q.grad_d, np.tile([0.0, 0.0, 1.0], (3, 1)))
    np.testing.assert_allclose(q.dw_dx, np.tile(np.diag([1.0, 1.0, 0.0]), (3, 1, 1)))
    np.testing.assert_array_equal(q.in_band, [True, True, False])
    assert g.is_ground and g.name == "ground"
    rho, grad = g.geodesic(np.array([[3.0, 4.0, 0.0], [1.0, 1.0, 0.0]]), np.zeros((2, 3)) + [0, 0, 0.0])
    np.testing.assert_allclose(rho, [5.0, np.sqrt(2.0)])
    np.testing.assert_allclose(grad, [[0.6, 0.8, 0.0], [np.sqrt(0.5), np.sqrt(0.5), 0.0]])


# ------------------------------------------------------------------ geodesics


def sphere_points(n, seed):
    p = np.random.default_rng(seed).normal(size=(n, 3))
    return RADIUS * p / np.linalg.norm(p, axis=1, keepdims=True)


def great_circle(a, b):
    return RADIUS * np.arccos(np.clip(np.einsum("ij,ij->i", a, b) / RADIUS**2, -1.0, 1.0))


def test_geodesic_on_a_sphere_matches_great_circle_distance(sphere):
    a, b = sphere_points(4000, 5), sphere_points(4000, 6)
    rho, _ = sphere.geodesic(a, b)
    rel = np.abs(rho - great_circle(a, b)) / great_circle(a, b)
    assert np.median(rel) < 0.04  # heat method on a ~500-point cloud
    assert np.percentile(rel, 95) < 0.07
    assert rel.max() < 0.12
    # short arcs (0–10 cm, median 3 cm): the chord dominates, errors of a few tenths of a mm
    c = a + np.random.default_rng(7).normal(scale=0.02, size=a.shape)
    c *= RADIUS / np.linalg.norm(c, axis=1, keepdims=True)
    rho, _ = sphere.geodesic(a, c)
    rel = np.abs(rho - great_circle(a, c)) / great_circle(a, c)
    assert np.percentile(rel, 99) < 0.015
    assert rel.max() < 0.03
    assert np.abs(rho - great_circle(a, c)).max() < 1.5e-3
    rho, grad = sphere.geodesic(a, a)
    assert np.all(rho == 0.0) and np.all(grad == 0.0)


def test_geodesic_gradient_points_away_from_the_target_along_the_surface(sphere):
    a = sphere_points(2000, 8)
    b = a + np.random.default_rng(9).normal(scale=0.05, size=a.shape)
    b *= RADIUS / np.linalg.norm(b, axis=1, keepdims=True)
    _, grad = sphere.geodesic(a, b)
    cos_ab = np.einsum("ij,ij->i", a, b) / RADIUS**2
    true = -(b - cos_ab[:, None] * a) / np.sqrt(1.0 - cos_ab**2)[:, None] / RADIUS  # unit tangent away from b
    tangential = grad - np.einsum("ij,ij->i", grad, a)[:, None] * a / RADIUS**2
    cos = np.einsum("ij,ij->i", tangential, true) / np.linalg.norm(tangential, axis=1)
    assert np.percentile(cos, 5) > 0.99
    assert np.abs(np.median(np.linalg.norm(tangential, axis=1)) - 1.0) < 0.05


def test_geodesic_gradient_matches_finite_differences(sphere):
    a, b = sphere_points(1000, 10), sphere_points(1000, 11)
    _, grad = sphere.geodesic(a, b)
    h = 1e-7
    fd = np.stack([(sphere.geodesic(a + h * e, b)[0] - sphere.geodesic(a - h * e, b)[0]) / (2 * h)
                   for e in np.eye(3)], axis=1)
    # the neighbour set of a witness switches at grid-node boundaries: a few pairs straddle one
    ok = np.all(np.abs(fd - grad) < 1e-5 * np.maximum(1.0, np.abs(grad)), axis=1)
    assert ok.mean() > 0.98


# ------------------------------------------------------------------ cache and bad input


def test_cache_hit_returns_identical_arrays_and_a_changed_mesh_misses(box_mesh, tmp_path):
    first = SDFChannel.from_mesh(box_mesh, cache_dir=tmp_path)
    files = sorted((tmp_path / "sdf").glob("*.npz"))
    assert len(files) == 1
    second = SDFChannel.from_mesh(TriMesh(box_mesh.vertices.copy(), box_mesh.faces.copy(), "renamed"),
                                  cache_dir=tmp_path)
    assert sorted((tmp_path / "sdf").glob("*.npz")) == files
    np.testing.assert_array_equal(first.grid.values, second.grid.values)
    np.testing.assert_array_equal(first.geodesics.ratio, second.geodesics.ratio)
    np.testing.assert_array_equal(first.surface.points, second.surface.points)
    moved = TriMesh(box_mesh.vertices * [1.0, 1.0, 1.1], box_mesh.faces, "taller box")
    third = SDFChannel.from_mesh(moved, cache_dir=tmp_path)
    assert len(list((tmp_path / "sdf").glob("*.npz"))) == 2
    assert third.query(np.array([[0.0, 0.0, 0.2]])).d[0] == pytest.approx(0.09, abs=1e-9)
    assert not list((tmp_path / "sdf").glob("*.tmp"))  # atomic writes leave no temporary file


def test_a_corrupt_cache_file_is_rebuilt_not_trusted(box_mesh, tmp_path):
    good = SDFChannel.from_mesh(box_mesh, cache_dir=tmp_path)
    (path,) = (tmp_path / "sdf").glob("*.npz")
    path.write_bytes(path.read_bytes()[:1000])  # truncated
    with pytest.warns(UserWarning, match="invalid cache file"):
        rebuilt = SDFChannel.from_mesh(box_mesh, cache_dir=tmp_path)
    np.testing.assert_array_equal(rebuilt.grid.values, good.grid.values)
    with np.load(path) as z:  # the file was replaced by a valid one
        values = z["values"]
        values[0, 0] = np.nan
        tampered = {k: z[k] for k in z.files}
    tampered["values"] = values
    np.savez(path, **tampered)
    with pytest.warns(UserWarning, match="non-finite"):
        again = SDFChannel.from_mesh(box_mesh, cache_dir=tmp_path)
    np.testing.assert_array_equal(again.grid.values, good.grid.values)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        SDFChannel.from_mesh(box_mesh, cache_dir=tmp_path)  # and is trusted again once valid


def test_bad_meshes_raise_invalid_mesh_error_naming_the_mesh(box_mesh, tmp_path):
    nan = box_mesh.vertices.copy()
    nan[3, 1] = np.nan
    with pytest.raises(InvalidMeshError, match="crate.*NaN"):
        SDFChannel.from_mesh(TriMesh(nan, box_mesh.faces, "crate"), cache_dir=tmp_path)
    with pytest.raises(InvalidMeshError, match="missing.obj.*not found"):
        load_channel(tmp_path / "missing.obj", cache_dir=tmp_path)
    with pytest.raises(InvalidMeshError, match="empty: faces must be"):
        SDFChannel.from_mesh(TriMesh(box_mesh.vertices, np.zeros((0, 3), np.int64), "empty"), cache_dir=tmp_path)
    assert not (tmp_path / "sdf").exists()  # nothing was cached for them


def test_a_surface_without_inside_is_a_shell_of_documented_thickness(tmp_path):
    """An open L-shaped sheet (a floor and a wall, 4 triangles) has no inside: it becomes a
    shell, distance = unsigned distance − half of SHELL_THICKNESS_M, with a warning naming it."""
    from retarget.inputs.meshes import SHELL_THICKNESS_M

    v = np.array([[0, 0, 0], [0.4, 0, 0], [0.4, 0.3, 0], [0, 0.3, 0], [0, 0.3, 0.3], [0.4, 0.3, 0.3]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [3, 2, 5], [3, 5, 4]])
    with pytest.warns(UserWarning, match="tablecloth: .*(encloses no volume|ambiguous).*shell 10 mm"):
        ch = SDFChannel.from_mesh(as_trimesh(v, f, "tablecloth"), cache_dir=tmp_path)
    assert ch.mesh.shell_m == SHELL_THICKNESS_M
    pts = np.array([[0.2, 0.1, 0.05], [0.2, 0.1, -0.02], [0.2, 0.25, 0.1], [0.2, 0.1, 0.0]])
    half = 0.5 * SHELL_THICKNESS_M
    exact, closest, _ = signed_distance(ch.mesh, pts)
    np.testing.assert_allclose(exact, [0.05 - half, 0.02 - half, 0.05 - half, -half], atol=1e-9)
    np.testing.assert_allclose(closest[:2, 2], 0.0, atol=1e-9)  # witnesses on the sheet's mid-surface
    # the 1 cm grid agrees away from the sheet (at the sheet its kink is smoothed, see margins)
    np.testing.assert_allclose(ch.query(pts[:3]).d, exact[:3], atol=1e-3)


def test_config_defaults_are_the_papers_numbers():
    cfg = GeometryConfig()
    assert (cfg.grid_resolution_m, cfg.band_m) == (0.01, 0.15)
    assert (cfg.human_density_per_m2, cfg.robot_density_per_m2, cfg.object_density_per_m2) == (2000, 2000, 1000)


def test_even_sampling_is_a_cover_without_clumps(box_mesh):
    """``even``: as many points, on the surface, deterministic by seed, and no two closer than a
    good share of the cover's spacing (i.i.d. draws put some pairs nearly on top of each other)."""
    from scipy.spatial import cKDTree

    a = sample_surface(box_mesh, 2000.0, seed=3, even=True)
    b = sample_surface(box_mesh, 2000.0, seed=3, even=True)
    c = sample_surface(box_mesh, 2000.0, seed=4, even=True)
    r = sample_surface(box_mesh, 2000.0, seed=3)
    assert len(a) == len(r) == 1040
    np.testing.assert_array_equal(a.points, b.points)
    assert not np.allclose(a.points, c.points)
    d, _, _ = signed_distance(box_mesh, a.points)
    assert np.abs(d).max() < 1e-12
    spacing = np.sqrt(box_mesh.area_m2 / len(a))  # ~2.2 cm
    nearest = lambda p: cKDTree(p).query(p, k=2)[0][:, 1]  # noqa: E731
    assert nearest(a.points).min() > 0.5 * spacing
    assert nearest(r.points).min() < 0.1 * spacing
