"""The ground under a reference (retarget.checks.ground) and the feasibility check standing on it:
a ramp and a platform measured against their planes, a robot on a platform that hovers
without its terrain, and a friction cone that follows the ramp's normal."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from otr_gym import cli, robot
from otr_gym.reference import Reference
from retarget.checks.feasibility import FeasibilityCfg, check_feasibility
from retarget.checks.ground import Ground
from retarget.inputs.meshes import InvalidMeshError

SLOPE = np.radians(12.6)


def _save(mesh: trimesh.Trimesh, path) -> str:
    mesh.export(path)
    return str(path)


def _ramp_and_platform(tmp_path) -> str:
    """A slab rising along +y at 12.6° from y = 0 (z = 0) to y = 2, and a platform beyond it
    (top at the ramp's end height), as in Holosoma's crawl."""
    top = 2.0 * np.tan(SLOPE)
    ramp = trimesh.creation.box(extents=(2.0, 2.0 / np.cos(SLOPE), 0.1))
    ramp.apply_translation((0.0, 0.0, -0.05))  # its top face through the origin before tilting
    ramp.apply_transform(trimesh.transformations.rotation_matrix(SLOPE, (1, 0, 0)))
    ramp.apply_translation((0.0, 1.0, top / 2))
    platform = trimesh.creation.box(extents=(2.0, 2.0, top))
    platform.apply_translation((0.0, 3.0, top / 2))
    return _save(trimesh.util.concatenate([ramp, platform]), tmp_path / "terrain.obj")


def test_heights_and_normals_over_a_ramp_a_platform_and_the_floor(tmp_path):
    g = Ground.from_mesh(_ramp_and_platform(tmp_path))
    top = 2.0 * np.tan(SLOPE)
    ramp_normal = np.array([0.0, -np.sin(SLOPE), np.cos(SLOPE)])
    points = np.array([
        [0.0, 1.0, 0.5],            # over the ramp: its surface at z = tan(12.6°)
        [0.3, 3.0, top + 0.1],      # over the platform
        [0.3, 3.0, top - 0.03],     # pressed 3 cm into the platform: still on it
        [0.3, 3.0, 0.1],            # far below its top (inside it): the floor's
        [5.0, 0.0, 0.2],            # beside the terrain: the floor's
    ])
    height, normal = g.under(points)
    assert height[0] == pytest.approx((0.5 - np.tan(SLOPE)) * np.cos(SLOPE), abs=1e-6)  # obj keeps ~8 digits
    np.testing.assert_allclose(normal[0], ramp_normal, atol=1e-6)
    np.testing.assert_allclose(height[1:], [0.1, -0.03, 0.1, 0.2], atol=1e-6)
    np.testing.assert_allclose(normal[1:], np.tile([0.0, 0.0, 1.0], (4, 1)), atol=1e-9)
    assert g.under(points.reshape(5, 1, 3))[0].shape == (5, 1)
    assert "terrain terrain.obj" in g.describe() and Ground.floor().describe() == "floor z = 0"


def test_bad_terrain_files_are_named(tmp_path, capsys):
    with pytest.raises(InvalidMeshError, match="missing.obj"):
        Ground.from_mesh(tmp_path / "missing.obj")
    # two vertical sheets: faces only, none to stand on
    wall = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1], [0, 0, 0], [0, 1, 0], [0, 1, 1], [0, 0, 1]],
                           [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], process=False)
    with pytest.raises(ValueError, match="wall.obj: terrain mesh has no upward-facing triangle"):
        Ground.from_mesh(_save(wall, tmp_path / "wall.obj"))
    clip = Reference.from_qpos(np.tile(robot.default_qpos(), (10, 1)), 50.0).save(tmp_path / "clip.npz")
    assert cli.main(["verify", str(clip), "--terrain", str(tmp_path / "missing.obj")]) == 2
    assert cli.main(["verify", str(tmp_path / "no_such_clip.npz")]) == 2
    err = capsys.readouterr().err
    assert "missing.obj: mesh file not found" in err and "no_such_clip.npz" in err


def test_a_robot_on_a_platform_stands_on_it_only_with_its_terrain(tmp_path):
    platform = trimesh.creation.box(extents=(2.0, 2.0, 0.4))
    platform.apply_translation((0.0, 0.0, 0.2))
    ground = Ground.from_mesh(_save(platform, tmp_path / "platform.obj"))
    qpos = np.tile(robot.default_qpos(), (20, 1))
    qpos[:, 2] += 0.4
    ref = Reference.from_qpos(qpos, 50.0)
    bare = check_feasibility(ref)
    assert bare.flight.all() and np.allclose(bare.unsupported_fraction, 1.0)
    r = check_feasibility(ref, ground=ground)
    assert not r.flight.any() and r.stance.all()
    assert r.unsupported_fraction.max() < 1e-6
    np.testing.assert_allclose(r.foot_force_w[:, :, 2].sum(axis=1), r.weight_n, rtol=1e-6)
    assert r.summary()["ground"] == ground.describe()


def _tilted_on_a_ramp(tmp_path, angle: float) -> tuple[Reference, Ground]:
    """The standing robot turned about y by ``angle`` with its soles on a ramp of that slope,
    both lifted 0.5 m so that the ramp stays above the floor."""
    turn = Rotation.from_euler("y", angle)
    qpos = np.tile(robot.default_qpos(), (20, 1))
    qpos[:, :3] = turn.apply(qpos[:, :3]) + (0.0, 0.0, 0.5)
    quat = (turn * Rotation.from_quat(qpos[:, [4, 5, 6, 3]])).as_quat()  # xyzw
    qpos[:, 3:7] = quat[:, [3, 0, 1, 2]]
    ramp = trimesh.creation.box(extents=(1.5, 1.5, 0.1))
    ramp.apply_translation((0.0, 0.0, -0.05))  # top face through the soles' plane z = 0
    transform = np.eye(4)
    transform[:3, :3] = turn.as_matrix()
    transform[:3, 3] = (0.0, 0.0, 0.5)
    ramp.apply_transform(transform)
    return Reference.from_qpos(qpos, 50.0), Ground.from_mesh(_save(ramp, tmp_path / f"ramp{angle:.2f}.obj"))


def _check(ref: Reference, ground: Ground):
    # moments weighed next to nothing: the tilted robot's weight line leaves its soles, and the
    # test reads the cone alone
    return check_feasibility(ref, FeasibilityCfg(moment_length_m=1e4), ground)


def test_the_friction_cone_follows_the_ramp_normal(tmp_path):
    # μ = 0.7: a ramp holds a standing robot up to atan(0.7) = 35°; beyond it the weight leaves
    # the cone by sin(θ − 35°) of itself
    mu = 0.7
    gentle = _check(*_tilted_on_a_ramp(tmp_path, np.radians(20.0)))
    assert gentle.stance.all() and not gentle.flight.any()
    assert gentle.unsupported_fraction.max() < 1e-3
    steep = _check(*_tilted_on_a_ramp(tmp_path, np.radians(45.0)))
    assert steep.stance.all()
    expected = np.sin(np.radians(45.0) - np.arctan(mu))
    assert steep.unsupported_fraction.mean() == pytest.approx(expected, rel=0.01)


def test_otr_verify_stands_a_clip_on_its_terrain(tmp_path, capsys):
    from otr_gym.cli import main as otr

    platform = trimesh.creation.box(extents=(2.0, 2.0, 0.4))
    platform.apply_translation((0.0, 0.0, 0.2))
    mesh = _save(platform, tmp_path / "platform.obj")
    qpos = np.tile(robot.default_qpos(), (20, 1))
    qpos[:, 2] += 0.4
    clip = Reference.from_qpos(qpos, 50.0).save(tmp_path / "on_platform.npz")
    assert otr(["verify", str(clip)]) == 0
    assert "1 phase(s), 0.40 s in total" in capsys.readouterr().out  # a hover above the floor
    assert otr(["verify", str(clip), "--terrain", mesh]) == 0
    out = capsys.readouterr().out
    assert "terrain platform.obj" in out and "0 phase(s)" in out and "no frame reaches a limit" in out
