"""Terrain of references recorded on uneven ground (``envs.terrain``): the mesh becomes fixed
collision geometry that bodies rest on (MuJoCo and MuJoCo-Warp agree), a library places a
terrain clip at its own origin without changing what the policy observes, and bad input is
refused naming the file.

The core tests build their own terrain with trimesh: a floor slab (top z = 0), a ramp slab
tilted by 12.6° (Holosoma's slope) and a platform; Holosoma's own slope is checked only where
../shared/data is present.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
import trimesh
import yaml

from agents import train
from agents.deploy.messages import JointCommand
from agents.deploy.safety import STARTUP_KD, STARTUP_KP
from agents.deploy.sim_robot import SimRobot, SimRobotCfg, initial_pose, sim_terrain
from agents.library import load_library, with_terrain
from agents.procedural import WalkSpec, walking_reference
from envs.backends import MuJoCoBackend
from envs.collision import BoxShape, collision_shapes
from envs.config import TRACK_TASK, TerrainCfg, load_track_config
from envs.mdp.metrics import mpjpe_root_relative
from envs.terrain import clip_matches, load_terrain, place_terrain, shape_corners
from envs.tracking import TrackEnv, make_task
from otr_gym.reference import InvalidReferenceError, Reference
from otr_gym.rotations import quat_to_matrix
from otr_gym.scene import SceneSpec, build_scene

SLOPE_RAD = math.radians(12.6)
RAMP_THICKNESS_M = 0.1
RAMP_CENTRE_Z_M = 0.2
PLATFORM_TOP_M = 0.05
CUBE_HALF_M = 0.05


def ramp_height(y: np.ndarray) -> np.ndarray:
    """Height (m) of the test ramp's top face above (x, y): it rises along +y by SLOPE_RAD."""
    return RAMP_CENTRE_Z_M + RAMP_THICKNESS_M / (2 * math.cos(SLOPE_RAD)) + y * math.tan(SLOPE_RAD)


def _tilt_x(angle: float) -> np.ndarray:
    return trimesh.transformations.rotation_matrix(angle, [1.0, 0.0, 0.0])


def _box(extents, centre, transform=None) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=extents, transform=transform)
    box.apply_translation(centre)
    return box


@pytest.fixture(scope="module")
def slope_mesh(tmp_path_factory) -> Path:
    """Floor slab (top z = 0, 6 m wide), a 1.6 × 3 × 0.1 m ramp tilted by 12.6° about x whose
    low end dips below the floor, and a 0.4 m platform beyond its top: one .obj, as Holosoma's."""
    floor = _box((6.0, 6.0, 0.05), (0.0, 0.0, -0.025))
    ramp = _box((1.6, 3.0, RAMP_THICKNESS_M), (0.0, 0.0, RAMP_CENTRE_Z_M), _tilt_x(SLOPE_RAD))
    platform = _box((1.6, 1.5, 0.4), (0.0, 2.2, 0.2))
    path = tmp_path_factory.mktemp("terrain") / "slope.obj"
    trimesh.util.concatenate([floor, ramp, platform]).export(path)
    return path


@pytest.fixture(scope="module")
def platform_clips(tmp_path_factory) -> tuple[Path, Path, Path]:
    """(flat walk, the same walk raised onto a 5 cm platform, the platform's mesh): a library of
    a flat clip and a terrain clip whose robot stands on its terrain."""
    folder = tmp_path_factory.mktemp("platform")
    walk = walking_reference(WalkSpec(steps=4))
    flat = walk.save(folder / "flat_walk.npz")
    raised = walk.translated([0.0, 0.0, PLATFORM_TOP_M]).save(folder / "platform_walk.npz")
    mesh = folder / "platform.obj"
    _box((4.0, 2.0, 0.15), (0.5, 0.0, PLATFORM_TOP_M - 0.075)).export(mesh)
    return flat, raised, mesh


def _terrain_cfg(meshes: dict, **kw) -> dict:
    return {"terrain": {"meshes": {k: str(v) for k, v in meshes.items()}, **kw}}


# ------------------------------------------------------------------ collision geometry
def test_a_tilted_box_mesh_becomes_a_box_with_its_orientation():
    """The ramp slab alone: one box primitive whose 8 corners are the mesh's (to 1e-6 m), so its
    top face keeps the 12.6° slope."""
    ramp = _box((1.6, 3.0, RAMP_THICKNESS_M), (0.0, 0.0, RAMP_CENTRE_Z_M), _tilt_x(SLOPE_RAD))
    shapes, method = collision_shapes(ramp.vertices, ramp.faces, "ramp")
    assert method == "box" and len(shapes) == 1
    box = shapes[0]
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
    corners = (signs * box.half_extents) @ quat_to_matrix(box.quat_wxyz).T + box.pos
    gaps = np.linalg.norm(corners[:, None] - ramp.vertices[None], axis=-1).min(axis=1)
    assert gaps.max() < 1e-6
    assert sorted(2 * box.half_extents) == pytest.approx([RAMP_THICKNESS_M, 1.6, 3.0], abs=1e-6)


def test_terrain_keeps_the_ramp_and_platform_and_drops_the_floor_slab(slope_mesh):
    terrain = load_terrain(str(slope_mesh), ("clip",), np.zeros(3), TerrainCfg())
    assert terrain.method == "boxes" and terrain.dropped == 1 and len(terrain.shapes) == 2
    ramp = _box((1.6, 3.0, RAMP_THICKNESS_M), (0.0, 0.0, RAMP_CENTRE_Z_M), _tilt_x(SLOPE_RAD))
    tops = sorted(shape_corners(s)[:, 2].max() for s in terrain.shapes)
    assert tops == pytest.approx(sorted([0.4, ramp.vertices[:, 2].max()]), abs=1e-6)


# ------------------------------------------------------------------ bodies rest on the terrain
def _drop_model(slope_mesh: Path) -> mujoco.MjModel:
    """Floor + the slope terrain + a free 10 cm cube 2 cm above the ramp at y = 0.3, tilted with it."""
    spec = build_scene(SceneSpec(robot=False, ground=True, visual=False)).spec
    _, scene = place_terrain([_stub_reference("slope_clip")], TerrainCfg(), {"slope_clip": str(slope_mesh)})
    scene.add_to(spec)
    y = 0.3
    centre = [0.0, y, float(ramp_height(np.float64(y))) + CUBE_HALF_M / math.cos(SLOPE_RAD) + 0.02]
    half = SLOPE_RAD / 2
    cube = spec.worldbody.add_body(name="cube", pos=centre, quat=[math.cos(half), math.sin(half), 0.0, 0.0])
    cube.add_freejoint()
    cube.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[CUBE_HALF_M] * 3, mass=1.0)
    return spec.compile()


def _stub_reference(name: str) -> Reference:
    ref = walking_reference(WalkSpec(steps=2))
    ref.source = f"/clips/{name}.npz"
    return ref


def _settled_cube(backend) -> tuple[np.ndarray, np.ndarray]:
    """(corners (8, 3) m, world) of the cube after 1 s of physics from rest."""
    for _ in range(50):  # 50 × 4 × 5 ms
        backend.step(torch.zeros(1, 0, device=backend.device))
    cube = backend.body_ids(["cube"])[0]
    pos = backend.body_pos_w[0, cube].double().cpu().numpy()
    quat = backend.body_quat_w[0, cube].double().cpu().numpy()
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
    return (signs * CUBE_HALF_M) @ quat_to_matrix(quat).T + pos, quat


def _assert_rests_on_the_ramp(corners: np.ndarray, quat: np.ndarray) -> None:
    """The cube's four lowest corners on the ramp plane (within 3 mm, measured along the
    normal), its faces parallel to the ramp (within 0.5°), and still on the ramp (y ≈ 0.3)."""
    normal = np.array([0.0, -math.sin(SLOPE_RAD), math.cos(SLOPE_RAD)])
    heights = (corners[:, 2] - ramp_height(corners[:, 1])) * math.cos(SLOPE_RAD)  # distance along the normal
    lowest = np.sort(heights)[:4]
    assert np.abs(lowest).max() < 3e-3, heights
    up = quat_to_matrix(quat)[:, 2]
    assert math.degrees(math.acos(min(1.0, abs(float(up @ normal))))) < 0.5
    assert corners[:, 1].mean() == pytest.approx(0.3, abs=0.02)


def test_a_cube_dropped_above_the_ramp_rests_on_its_surface_on_mujoco(slope_mesh):
    model = _drop_model(slope_mesh)
    _assert_rests_on_the_ramp(*_settled_cube(MuJoCoBackend(model, 1, decimation=4)))


def test_mujoco_warp_agrees_on_where_the_cube_rests(slope_mesh):
    pytest.importorskip("warp")
    from envs.backends.warp_backend import WarpBackend

    model = _drop_model(slope_mesh)
    cpu, _ = _settled_cube(MuJoCoBackend(model, 1, decimation=4))
    warp_corners, warp_quat = _settled_cube(WarpBackend(model, 1, device="cpu", decimation=4, nconmax=16, njmax=64))
    _assert_rests_on_the_ramp(warp_corners, warp_quat)
    assert np.abs(warp_corners - cpu).max() < 2e-3


# ------------------------------------------------------------------ libraries: one origin per terrain
@pytest.fixture(scope="module")
def library_and_alone(platform_clips):
    """The platform clip in a two-clip library (env 1 plays it) and alone, evaluation mode."""
    flat, raised, mesh = platform_clips
    cfg = load_track_config(overrides=_terrain_cfg({"platform_walk": mesh}))
    library = make_task([flat, raised], 2, "mujoco", "cpu", cfg, evaluation=True)
    alone = make_task(raised, 1, "mujoco", "cpu", cfg, evaluation=True)
    return library, alone


def test_a_terrain_clip_is_shifted_to_its_origin_and_the_flat_clip_is_not(library_and_alone):
    library, alone = library_and_alone
    assert library.terrain.clip_origin_w.tolist() == [[0.0, 0.0, 0.0], [50.0, 0.0, 0.0]]
    assert alone.terrain.clip_origin_w.tolist() == [[0.0, 0.0, 0.0]]
    motion, raised_at_0 = library.motion, alone.motion.body_pos_w
    for clip, expected in ((0, raised_at_0 - torch.tensor([0.0, 0.0, PLATFORM_TOP_M])),
                           (1, raised_at_0 + torch.tensor([50.0, 0.0, 0.0]))):
        rows = torch.arange(int(motion.clip_length[clip])) + motion.clip_start[clip]
        assert torch.allclose(motion.body_pos_w[rows], expected, atol=1e-5)
        assert torch.allclose(motion.root_pos_w[rows], expected[:, 0], atol=1e-5)  # the pelvis is body 0
    model = library.backend.model
    assert model.body("terrain/0").pos.tolist() == [50.0, 0.0, 0.0]
    assert alone.backend.model.body("terrain/0").pos.tolist() == [0.0, 0.0, 0.0]


def test_observations_and_mpjpe_are_the_same_at_the_origin_and_50_m_away(library_and_alone):
    """Env 1 of the library (platform clip at x = 50 m) and the clip alone (x = 0), from the
    same start, stepped with the same actions for 1 s: equal observations, rewards, MPJPE and
    terminations. The robot stands on the platform 50 m away: its lowest ankle stays within
    1 cm of the reference's lowest (on the floor it would sink to 3 cm, 5 cm lower)."""
    library, alone = library_and_alone
    obs_lib, obs_one = library.reset(seed=0), alone.reset(seed=0)
    ankles = library.backend.body_ids(["left_ankle_roll_link", "right_ankle_roll_link"])
    gen = torch.Generator().manual_seed(0)
    worst, lowest_ankle = 0.0, math.inf
    for step in range(51):
        if step:
            actions = 0.3 * torch.randn(1, 29, generator=gen)
            obs_lib, rew_lib, term_lib, _, _ = library.step(torch.cat([torch.zeros(1, 29), actions]))
            obs_one, rew_one, term_one, _, _ = alone.step(actions)
            assert rew_lib[1].item() == pytest.approx(rew_one[0].item(), abs=1e-5)
            assert bool(term_lib[1]) == bool(term_one[0]) is False
            lowest_ankle = min(lowest_ankle, library.backend.body_pos_w[1, ankles, 2].min().item())
        for group in ("policy", "critic"):
            worst = max(worst, (obs_lib[group][1] - obs_one[group][0]).abs().max().item())
        mpjpe_lib = mpjpe_root_relative(library.tracking_state)[1].item()
        assert mpjpe_lib == pytest.approx(mpjpe_root_relative(alone.tracking_state)[0].item(), abs=1e-5)
    assert worst < 1e-4
    assert library.backend.body_pos_w[1, ankles, 0].mean().item() == pytest.approx(50.0, abs=1.0)
    tracked = list(library.cfg.command.tracked_bodies)
    ref_ankles = [tracked.index("left_ankle_roll_link"), tracked.index("right_ankle_roll_link")]
    ref_lowest = library.motion.body_pos_w[library.motion.clip_start[1]:, ref_ankles, 2].min().item()
    assert abs(lowest_ankle - ref_lowest) < 0.01


def test_the_terrain_geoms_take_the_floors_friction_draw(platform_clips):
    flat, raised, mesh = platform_clips
    cfg = load_track_config(overrides=_terrain_cfg({"platform_walk": mesh}))
    task = make_task([flat, raised], 3, "mujoco", "cpu", cfg, seed=1)
    backend = task.backend
    ground, terrain = backend.model.geom("ground/ground").id, backend.model.geom("terrain/0/geom0").id
    draws = [m.geom_friction[ground, 0] for m in backend._models]
    assert [m.geom_friction[terrain, 0] for m in backend._models] == draws
    assert len(set(draws)) == 3 and all(0.3 <= d <= 1.2 for d in draws)


def test_a_single_terrain_clip_keeps_its_place_and_clips_sharing_a_mesh_share_an_origin(platform_clips):
    flat, raised, mesh = platform_clips
    refs = [Reference.load(raised), Reference.load(flat)]
    _, alone = place_terrain(refs[:1], TerrainCfg(), {"platform_walk": str(mesh)})
    assert alone.clip_origin_w.tolist() == [[0.0, 0.0, 0.0]]
    _, both = place_terrain(refs, TerrainCfg(), {"platform_walk": str(mesh), "flat_walk": str(mesh)})
    assert len(both.terrains) == 1 and both.clip_origin_w.tolist() == [[0.0, 0.0, 0.0]] * 2


def test_a_clip_list_line_gives_its_clips_a_terrain(platform_clips, tmp_path):
    flat, raised, mesh = platform_clips
    listing = tmp_path / "clips.txt"
    listing.write_text(f"{flat}\n{raised}  terrain={mesh.name}   # on the platform\n")
    (tmp_path / mesh.name).write_bytes(mesh.read_bytes())  # relative to the list
    task = make_task(listing, 2, "mujoco", "cpu", evaluation=True)
    assert task.terrain.clip_origin_w[:, 0].tolist() == [0.0, 50.0]
    assert task.terrain.terrains[0].mesh == str(tmp_path / mesh.name)


def test_the_run_config_records_clip_list_terrain_with_absolute_paths(platform_clips, tmp_path):
    """``with_terrain``: what train stores in config.yaml (all of it) and evaluation or play of
    part of the library use (the entries of those clips)."""
    flat, raised, mesh = platform_clips
    listing = tmp_path / "clips.txt"
    listing.write_text(f"{flat}\n{raised} terrain={mesh}\n")
    library = load_library(listing, TRACK_TASK, report=False)
    overrides = with_terrain({"sim": {"decimation": 4}}, library)
    assert overrides == {"sim": {"decimation": 4}, "terrain": {"meshes": {str(raised): str(mesh)}}}
    assert with_terrain(overrides, library, [str(raised)]) == overrides
    assert with_terrain(overrides, library, [str(flat)])["terrain"]["meshes"] == {}  # playing the flat clip alone


def test_a_run_records_its_terrain_with_absolute_paths(platform_clips, tmp_path, monkeypatch):
    """``otr train`` stores the terrain (a relative --set path made absolute) in the run record
    that resume, evaluation and play read back."""
    flat, raised, mesh = platform_clips
    monkeypatch.chdir(mesh.parent)
    parser = argparse.ArgumentParser()
    train.configure_parser(parser)
    args = parser.parse_args(["--reference", str(flat), str(raised), "--set",
                              f"env.terrain.meshes.platform_walk={mesh.name}"])
    setup = train._setup(args)
    assert setup.record["train"]["env"]["terrain"]["meshes"] == {"platform_walk": str(mesh)}
    assert load_track_config(overrides=setup.cfg.env).terrain.meshes == {"platform_walk": str(mesh)}


def test_play_renders_the_terrain_and_the_sim_robot_stands_on_it(platform_clips, tmp_path):
    """The single env of ``otr play`` draws the terrain (its renderer's model has the platform),
    and ``otr sim-robot --terrain RUN`` simulates the run's terrain of the clip: a robot held in
    the default pose for 0.5 s stands 5 cm (the platform) higher than on the floor."""
    flat, raised, mesh = platform_clips
    overrides = _terrain_cfg({"platform_walk": mesh})
    env = TrackEnv(raised, render_mode="rgb_array", cfg=load_track_config(overrides=overrides), evaluation=True)
    renderer = env._make_renderer()
    assert renderer.model.body("terrain/0").pos.tolist() == [0.0, 0.0, 0.0]
    assert sorted(renderer.model.geom("terrain/0/geom0").size) == pytest.approx([0.075, 1.0, 2.0])
    renderer.close()
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(yaml.safe_dump({"train": {"task": TRACK_TASK, "env": overrides}}))
    heights = []
    for terrain in (None, sim_terrain(str(run), str(raised)), sim_terrain(str(mesh), str(raised))):
        start = initial_pose(str(flat)) + np.r_[0.0, 0.0, 0.0 if terrain is None else PLATFORM_TOP_M, np.zeros(33)]
        sim = SimRobot(SimRobotCfg(), start, terrain)
        for _ in range(250):
            sim.step(JointCommand(q=start[7:], dq=np.zeros(29), kp=STARTUP_KP, kd=STARTUP_KD, tau=np.zeros(29)))
        heights.append(sim.data.qpos[2])
    assert heights[1] - heights[0] == pytest.approx(PLATFORM_TOP_M, abs=0.005)
    assert heights[2] == pytest.approx(heights[1], abs=1e-9)


def test_terrain_keys_name_clips_by_stem_path_tail_or_path():
    source = "/data/holosoma/motion_crawl_slope.npz"
    for key in ("motion_crawl_slope", "holosoma/motion_crawl_slope", "holosoma/motion_crawl_slope.npz", source):
        assert clip_matches(key, source), key
    for key in ("crawl_slope", "other/motion_crawl_slope", "/data/motion_crawl_slope.npz"):
        assert not clip_matches(key, source), key


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize("content, problem", [
    (None, "not found"),
    (b"not a mesh at all\n", "has no faces"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "has no faces"),
    (b"v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n", "NaN"),
])
def test_a_bad_terrain_file_is_refused_naming_it_and_the_problem(tmp_path, content, problem):
    mesh = tmp_path / "terrain.obj"
    if content is not None:
        mesh.write_bytes(content)
    with pytest.raises(InvalidReferenceError, match=rf"{mesh}: terrain of /clips/crawl.npz.*{problem}"):
        place_terrain([_stub_reference("crawl")], TerrainCfg(), {"crawl": str(mesh)})


def test_an_unreadable_terrain_file_is_refused_naming_it(tmp_path):
    mesh = tmp_path / "terrain.xyz"
    mesh.write_text("1 2\n")
    with pytest.raises(InvalidReferenceError, match=rf"{mesh}: terrain of .* cannot be read"):
        place_terrain([_stub_reference("crawl")], TerrainCfg(), {"crawl": str(mesh)})


def test_a_terrain_for_a_clip_not_in_the_run_is_refused_naming_key_and_mesh(platform_clips):
    flat, _, mesh = platform_clips
    cfg = load_track_config(overrides=_terrain_cfg({"crawl_slope": mesh}))
    with pytest.raises(InvalidReferenceError, match=rf"'crawl_slope' names no clip of this run \(clips: flat_walk\); "
                                                    rf"its mesh {mesh} is not used"):
        make_task(flat, 1, "mujoco", "cpu", cfg)


def test_a_key_naming_two_clips_or_a_clip_given_two_meshes_is_refused(platform_clips, slope_mesh):
    _, _, mesh = platform_clips
    refs = [_stub_reference("a/walk"), _stub_reference("b/walk")]
    with pytest.raises(InvalidReferenceError, match="'walk' names 2 clips"):
        place_terrain(refs, TerrainCfg(), {"walk": str(mesh)})
    with pytest.raises(InvalidReferenceError, match="/clips/a/walk.npz: two terrain meshes"):
        place_terrain(refs, TerrainCfg(), {"a/walk": str(mesh), "/clips/a/walk.npz": str(slope_mesh)})


def test_a_clip_that_could_reach_another_origins_terrain_is_refused(platform_clips):
    flat, raised, mesh = platform_clips
    refs = [Reference.load(flat), Reference.load(raised)]
    with pytest.raises(InvalidReferenceError, match=rf"flat_walk.npz: its reference .* reaches the terrain {mesh} "
                                                    r"placed at x = 3 m.*raise terrain.library_spacing_m \(now 3 m\)"):
        place_terrain(refs, TerrainCfg(library_spacing_m=3.0), {"platform_walk": str(mesh)})


def test_an_unknown_clip_list_option_is_refused_naming_list_and_line(platform_clips, tmp_path):
    flat, _, _ = platform_clips
    listing = tmp_path / "clips.txt"
    listing.write_text(f"# clips\n{flat} terrian=x.obj\n")
    with pytest.raises(InvalidReferenceError, match=rf"{listing}, line 2: unknown option 'terrian'"):
        make_task(listing, 1, "mujoco", "cpu")


# ------------------------------------------------------------------ Holosoma's slope (real data)
def test_holosomas_slope_is_a_tilted_ramp_and_a_platform_under_its_crawl(shared_data):
    """terrain_slope.obj: the floor slab dropped; a ramp box tilted by 12.6° and a 0.41 m
    platform kept. The crawl's soles follow them: over every frame the lowest sole point lies
    between 5 mm below and 7 cm above the simulated surface under it (measured: −4 mm to
    6.6 cm, the feet lifting while the knees carry the crawl), and within 5 mm of the platform
    at the end; above the flat floor alone it would be up to 45 cm."""
    folder = shared_data / "references" / "holosoma"
    terrain = load_terrain(str(folder / "terrain_slope.obj"), ("crawl",), np.zeros(3), TerrainCfg())
    assert terrain.dropped == 1 and len(terrain.shapes) == 2 and all(isinstance(s, BoxShape) for s in terrain.shapes)
    normals = [quat_to_matrix(s.quat_wxyz)[:, int(np.argmin(s.half_extents))] for s in terrain.shapes]
    tilts = sorted(math.degrees(math.acos(min(1.0, abs(n[2])))) for n in normals)
    assert tilts == pytest.approx([0.0, 12.6], abs=0.1)

    cfg = load_track_config(overrides=_terrain_cfg({"motion_crawl_slope": folder / "terrain_slope.obj"}))
    task = make_task(folder / "motion_crawl_slope.npz", 1, "mujoco", "cpu", cfg, evaluation=True)
    assert task.terrain.clip_origin_w.tolist() == [[0.0, 0.0, 0.0]]
    spec = build_scene(SceneSpec(robot=False, ground=True, visual=False)).spec
    task.terrain.add_to(spec)
    ground = spec.compile()
    ground_data = mujoco.MjData(ground)
    mujoco.mj_forward(ground, ground_data)

    def surface_z(xy: np.ndarray) -> float:
        hit = np.zeros(1, np.int32)
        return 5.0 - mujoco.mj_ray(ground, ground_data, np.array([*xy, 5.0]), np.array([0.0, 0.0, -1.0]), None, 1, -1,
                                   hit)

    model, data = task.backend.model, mujoco.MjData(task.backend.model)
    soles = [i for i in range(model.ngeom) if "foot" in model.geom(i).name]  # horizontal capsules
    clearance, above_floor = [], []
    for row in range(int(task.motion.clip_length[0])):
        data.qpos[:] = task.motion.qpos(torch.tensor(row)).double().numpy()
        mujoco.mj_kinematics(model, data)
        bottoms = [(data.geom_xpos[i], data.geom_xpos[i, 2] - model.geom_size[i, 0]) for i in soles]
        clearance.append(min(z - surface_z(p[:2]) for p, z in bottoms))
        above_floor.append(min(z for _, z in bottoms))
    clearance = np.array(clearance)
    assert -0.005 < clearance.min() and clearance.max() < 0.07
    assert np.abs(clearance[-10:]).max() < 0.005
    assert max(above_floor) > 0.4
