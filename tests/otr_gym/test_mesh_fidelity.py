"""The shipped G1 meshes against Unitree's originals (the mjlab 1.6.0 wheel, fetched once with pip).

Skips with a reason when the wheel can neither be found in the cache nor downloaded.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from otr_gym import robot
from otr_gym.robot_geometry import surface_margin_m, visual_meshes
from otr_gym.true_surface import (
    MESH_ERROR_JSON,
    TrueSurfaceUnavailable,
    mesh_error,
    original_mesh_dir,
)

MESH_DIR = robot.G1_MJCF.parent / "meshes"


@pytest.fixture(scope="module")
def originals():
    try:
        return original_mesh_dir()
    except TrueSurfaceUnavailable as exc:
        pytest.skip(f"Unitree's original G1 meshes are unavailable: {exc}")


@pytest.fixture(scope="module")
def measured(originals):
    table = {}
    for shipped in sorted(MESH_DIR.glob("*.stl")):
        original = originals / shipped.name
        assert original.is_file(), f"{shipped.name} has no original in the mjlab wheel"
        table[shipped.stem] = mesh_error(trimesh.load(original, process=True), trimesh.load(shipped, process=True))
    return table


def test_every_shipped_mesh_is_within_1mm_p99_and_2mm_max_of_the_original_outer_surface(measured):
    assert len(measured) == 35
    worst_p99 = max(e.p99_mm for e in measured.values())
    worst_max = max(e.max_mm for e in measured.values())
    assert worst_p99 <= 1.0, {k: e.p99_mm for k, e in measured.items() if e.p99_mm > 1.0}
    assert worst_max <= 2.0, {k: e.max_mm for k, e in measured.items() if e.max_mm > 2.0}


def test_convex_hulls_keep_their_volume_within_2_percent_and_no_piece_falls_apart(measured):
    for name, e in measured.items():
        assert abs(e.hull_volume_change_pct) <= 2.0, (name, e.hull_volume_change_pct)
        assert e.components[1] <= e.components[0], (name, e.components)
    # the hands were the worst offenders of the old 1500-triangle meshes (4 pieces, hull -19 %)
    assert measured["left_rubber_hand"].components == (1, 1)


def test_the_recorded_error_table_bounds_the_measured_error(measured):
    """The margin that keeps the solver conservative must not understate the real error."""
    recorded = json.loads(MESH_ERROR_JSON.read_text())["links"]
    assert set(recorded) == set(measured)
    for name, e in measured.items():
        assert recorded[name]["surface_error_mm"] >= 0.95 * e.max_mm, name


def test_link_margins_take_the_worst_mesh_of_each_body():
    margin = dict(zip(robot.BODY_NAMES, surface_margin_m()))
    recorded = {k: v["surface_error_mm"] * 1e-3 for k, v in json.loads(MESH_ERROR_JSON.read_text())["links"].items()}
    meshes = visual_meshes()
    assert set(meshes["torso_link"].mesh_names) >= {"torso_link", "head_link"}
    assert margin["torso_link"] == pytest.approx(max(recorded[n] for n in meshes["torso_link"].mesh_names))
    assert margin["left_wrist_yaw_link"] >= recorded["left_rubber_hand"]
    assert np.all((surface_margin_m() > 0) & (surface_margin_m() < 1e-3))
