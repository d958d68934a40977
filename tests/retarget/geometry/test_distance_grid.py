"""Grids of exact signed distance built for a fraction of the per-node cost (retarget.geometry.distance_grid)."""

import numpy as np
import pytest
import trimesh

from retarget.geometry.distance_grid import grid_signed_distance, node_positions
from retarget.geometry.margins import interpolation_margin
from retarget.geometry.voxel_grid import build_sdf_grid
from retarget.inputs.meshes import as_trimesh, signed_distance


def _l_block() -> trimesh.Trimesh:
    """A concave solid, an L-shaped prism 8 cm thick, so that the grid has a fold outside and
    edges inside."""
    outline = np.array([(0.0, 0.0), (0.20, 0.0), (0.20, 0.16), (0.14, 0.16), (0.14, 0.06), (0.0, 0.06)])
    n = len(outline)
    vertices = np.concatenate([np.column_stack([outline, np.full(n, z)]) for z in (-0.04, 0.04)])
    cap = [(0, 1, 4), (1, 3, 4), (1, 2, 3), (0, 4, 5)]  # the L split into triangles
    faces = [tuple(reversed(f)) for f in cap] + [tuple(i + n for i in f) for f in cap]
    for i in range(n):
        j = (i + 1) % n
        faces += [(i, j, j + n), (i, j + n, i + n)]
    mesh = trimesh.Trimesh(vertices, np.array(faces), process=True)
    trimesh.repair.fix_normals(mesh)
    assert mesh.is_watertight and mesh.volume > 0
    # subdivided, so that closest points fall on many faces, edges and vertices
    return mesh.subdivide().subdivide()


def _holed_sphere(cap_z: float) -> trimesh.Trimesh:
    """A sphere of radius 8 cm with the faces above ``cap_z`` removed: the winding number fades
    across the hole instead of jumping, so sides cannot spread near it."""
    s = trimesh.creation.icosphere(subdivisions=4, radius=0.08)
    keep = s.triangles_center[:, 2] < cap_z
    return trimesh.Trimesh(s.vertices, s.faces[keep], process=False)


def _grid(mesh, resolution, pad):
    lo = mesh.bounds[0] - pad
    shape = tuple(int(s) for s in np.ceil((mesh.bounds[1] + pad - lo) / resolution).astype(int) + 1)
    return lo, shape


@pytest.mark.parametrize("make", [_l_block, lambda: _holed_sphere(0.06), lambda: _holed_sphere(0.078)],
                         ids=["concave-solid", "sphere-with-a-wide-hole", "sphere-with-a-small-hole"])
def test_every_node_equals_the_per_node_signed_distance(make):
    t = make()
    mesh = as_trimesh(t.vertices, t.faces, "test")
    lo, shape = _grid(mesh, 0.01, 0.05)
    d, closest, _ = signed_distance(mesh, node_positions(lo, 0.01, shape))
    values = grid_signed_distance(mesh, lo, 0.01, shape)
    assert (d < 0).sum() > 100  # both sides are present
    np.testing.assert_array_equal(values[:, 0], d)
    np.testing.assert_array_equal(values[:, 1:], closest)


def test_far_nodes_hold_a_lower_bound_and_every_cell_read_closer_than_the_reach_is_exact():
    t = _l_block()
    mesh = as_trimesh(t.vertices, t.faces, "test")
    h, reach = 0.005, 0.03
    far_m = reach + np.sqrt(3.0) * h
    lo, shape = _grid(mesh, h, reach + 1.5 * h)
    d, closest, _ = signed_distance(mesh, node_positions(lo, h, shape))
    values = grid_signed_distance(mesh, lo, h, shape, far_m=far_m)
    assert np.mean(values[:, 0] != d) > 0.2  # the point of it: a share of the nodes is never measured
    beyond = d > far_m
    assert np.all(values[beyond, 0] > far_m)
    assert np.all(values[beyond, 0] <= d[beyond] + 1e-12)  # a lower bound: never farther than the truth
    np.testing.assert_array_equal(values[~beyond, 0], d[~beyond])
    np.testing.assert_array_equal(values[~beyond, 1:], closest[~beyond])
    # points closer than the reach interpolate from exact nodes only: the same as the exact grid
    full = build_sdf_grid(mesh, h, reach)
    fast = build_sdf_grid(mesh, h, reach, far_m=far_m)
    x = np.random.default_rng(1).uniform(mesh.bounds[0] - reach, mesh.bounds[1] + reach, (20000, 3))
    near = full.interpolate_distance(x)[0] < reach
    assert near.sum() > 1000
    np.testing.assert_array_equal(fast.interpolate_distance(x[near])[0], full.interpolate_distance(x[near])[0])


def test_the_margin_taking_sides_from_cell_corners_equals_the_winding_number_everywhere():
    t = _l_block()
    mesh = as_trimesh(t.vertices, t.faces, "test")
    grid = build_sdf_grid(mesh, 0.01, 0.05)
    margin = interpolation_margin(grid, mesh, 0.02)
    # the same measure with every lattice point's side from its own winding number
    nx, ny, nz = grid.shape
    d = grid.values[:, 0].reshape(grid.shape)
    corners = [d[i:nx - 1 + i, j:ny - 1 + j, k:nz - 1 + k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    cell = np.argwhere((np.minimum.reduce(corners) < 0.02) & (np.maximum.reduce(corners) > -0.02))
    ticks = (np.arange(4) + 0.5) / 4
    lattice = np.array([(a, b, c) for a in ticks for b in ticks for c in ticks])
    pts = (grid.origin + grid.resolution * (cell[:, None] + lattice[None])).reshape(-1, 3)
    exact, _, _ = signed_distance(mesh, pts)
    excess = np.maximum(0.0, (grid.interpolate(pts)[0][:, 0] - exact).reshape(len(cell), -1).max(axis=1))
    expected = np.zeros(margin.cells)
    expected[tuple(cell.T)] = excess
    assert expected.max() > 1e-3  # the L's edges and fold overstate the distance somewhere
    np.testing.assert_array_equal(margin.values, expected.ravel())
