"""OTR-G1-BoxTrack-v0: objects in the simulation, contact windows, object terms, bad input.

The reference is generated (``conftest._box_clip``): the G1 stands still while a 20 cm box
moves through known windows (floor [0, 40), beside the left hand [60, 100), on a static table
[110, 151)); one file carries contact annotations, the other none.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import gymnasium
import mujoco
import numpy as np
import pytest
import torch
import trimesh

import otr_gym  # noqa: F401  (registers the environments)
from envs.box import make_box_task
from envs.collision import collision_shapes
from envs.config import BOX_CONFIG, BoxEnvCfg, TerminationTermCfg, load_box_config
from envs.mdp import rewards as reward_terms
from envs.mdp.motion import prepared_references
from envs.mdp.objects import _Geometry, proximity_gate
from envs.mdp.state import ObjectState
from envs.objects import object_qpos
from otr_gym.reference import InvalidReferenceError, Reference
from otr_gym.rotations import quat_apply, quat_apply_inverse, quat_mul

from conftest import BOX_HALF_M, benchmark_sets, env_checker_messages


def _cfg(**command) -> BoxEnvCfg:
    cfg = BoxEnvCfg()
    for key, value in command.items():
        setattr(cfg.command, key, value)
    return cfg


@pytest.fixture(scope="module")
def eval_task(box_reference):
    return make_box_task(box_reference, 2, "mujoco", "cpu", evaluation=True)


# ------------------------------------------------------------------ configuration and errors
def test_box_yaml_lists_exactly_the_dataclass_defaults():
    assert load_box_config(BOX_CONFIG) == BoxEnvCfg()


def test_the_default_actor_observes_nothing_a_g1_does_not_measure_and_mocap_is_one_name_away():
    from agents.deploy.observation import TERM_SOURCES

    default = [(t.fn, t.noise) for t in BoxEnvCfg().observations.policy]
    assert not [fn for fn, _ in default if fn in TERM_SOURCES]
    assert [fn for fn, _ in default][-2:] == ["object_command", "contact_schedule"]
    # the motion-capture actor, the default before 2026-12-07: §3 MJ's actor with state estimation
    # and the object's pose
    mocap = [(t.fn, t.noise) for t in load_box_config(None, {"observations": {"actor": "mocap"}}).observations.policy]
    assert ("anchor_pos_b", 0.25) in mocap and ("base_lin_vel_b", 0.5) in mocap and ("object_pos_b", 0.02) in mocap
    # benchmarks/box_no_state_estimation.sets, passed as SETS to train_box.sh, is the 154-dim actor
    # (§3 HS) of the box runs before 2026-11-29: the mocap actor less the robot's world position
    older = load_box_config(BOX_CONFIG, benchmark_sets("box_no_state_estimation.sets")["env"])
    assert [(t.fn, t.noise) for t in older.observations.policy] == [
        t for t in mocap if t[0] not in ("anchor_pos_b", "base_lin_vel_b")]
    # the perception-free actor is that one less the object's and the table's pose
    assert default == [(t.fn, t.noise) for t in older.observations.policy
                       if not t.fn.startswith(("object_pos", "object_ori", "static_"))]
    with pytest.raises(ValueError, match="observations.actor 'lidar' is none of"):
        load_box_config(None, {"observations": {"actor": "lidar"}})


def test_a_reference_without_objects_is_refused_naming_the_file(walking_reference):
    with pytest.raises(InvalidReferenceError, match=rf"{walking_reference}: OTR-G1-BoxTrack-v0 needs a reference "
                                                    r"with objects"):
        make_box_task(walking_reference, 1, "mujoco", "cpu")


def test_an_object_without_mesh_is_refused_naming_file_and_object(box_reference_geometry, tmp_path):
    ref = Reference.load(box_reference_geometry)
    ref.objects[0].mesh_vertices = ref.objects[0].mesh_faces = None
    path = ref.save(tmp_path / "meshless.npz")
    with pytest.raises(InvalidReferenceError, match=rf"{path}: object 'box' has no mesh.*overrides\.box\.mesh"):
        make_box_task(path, 1, "mujoco", "cpu")
    # ... and a mesh given in the config makes it usable
    mesh = tmp_path / "box.obj"
    trimesh.creation.box(extents=(2 * BOX_HALF_M,) * 3).export(mesh)
    cfg = load_box_config(overrides={"objects": {"overrides": {"box": {"mesh": str(mesh)}}}})
    task = make_box_task(path, 1, "mujoco", "cpu", cfg=cfg)
    assert task.scene.objects[0].method == "box"


def test_a_mesh_that_cannot_be_decomposed_is_refused_naming_file_and_object(box_reference_geometry, tmp_path):
    ref = Reference.load(box_reference_geometry)
    flat = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    flat.vertices[:, 2] = 0.0  # every vertex in one plane: no volume to decompose
    ref.objects[0].mesh_vertices, ref.objects[0].mesh_faces = np.asarray(flat.vertices), np.asarray(flat.faces)
    path = ref.save(tmp_path / "flat.npz")
    with pytest.raises(InvalidReferenceError, match=rf"{path}: object 'box'.*cannot be decomposed"):
        make_box_task(path, 1, "mujoco", "cpu")


def test_box_like_meshes_become_boxes_and_others_convex_hulls(tmp_path):
    box = trimesh.creation.box(extents=(0.35, 0.4, 0.3))
    shapes, method = collision_shapes(box.vertices, box.faces, "box")
    assert method == "box" and np.allclose(np.sort(2 * shapes[0].half_extents), [0.3, 0.35, 0.4], atol=1e-6)
    open_box = trimesh.Trimesh(box.vertices, box.faces[box.face_normals[:, 2] > -0.5])  # a scan without bottom
    assert collision_shapes(open_box.vertices, open_box.faces, "open box")[1] == "box"
    legs = trimesh.util.concatenate([
        trimesh.creation.box(extents=(0.04, 0.04, 0.7),
                             transform=trimesh.transformations.translation_matrix((x, 0, 0)))
        for x in (0.0, 0.5)])
    shapes, method = collision_shapes(legs.vertices, legs.faces, "legs")
    assert method == "boxes" and len(shapes) == 2
    torus = trimesh.creation.torus(0.2, 0.05, major_sections=24, minor_sections=12)
    shapes, method = collision_shapes(torus.vertices, torus.faces, "torus", cache_dir=tmp_path)
    assert method == "convex decomposition" and len(shapes) >= 4
    hull_points = np.concatenate([s.vertices for s in shapes])
    assert np.abs(np.linalg.norm(hull_points[:, :2], axis=1) - 0.2).max() < 0.06  # hulls hug the ring


# ------------------------------------------------------------------ windows (gates)
def test_proximity_gate_ramps_up_closes_short_gaps_and_cuts_off_at_the_window_end():
    d = np.full(40, 0.3)
    d[10:30] = 0.01
    d[20:22] = 0.3  # a 2-frame gap: closed (min gap 0.1 s = 5 frames)
    gate = proximity_gate(d, 0.05, fps=50.0, ramp_s=0.1, min_gap_s=0.1)
    assert np.all(gate[:10] == 0) and np.all(gate[30:] == 0)
    assert np.allclose(gate[10:15], [0.2, 0.4, 0.6, 0.8, 1.0]) and np.all(gate[15:30] == 1.0)


@pytest.mark.parametrize("source", ["annotations", "geometry"])
def test_every_gate_is_zero_outside_its_window_and_positive_inside(source, box_reference, box_reference_geometry):
    path = box_reference if source == "annotations" else box_reference_geometry
    task = make_box_task(path, 1, "mujoco", "cpu", evaluation=True)
    lib = task.objects
    assert lib.window_source == (source,) and lib.support_names == ("ground", "table")
    hands = lib.hand_gate[:, :, 0].numpy()  # (T, 2)
    supports = lib.support_gate[:, 0].numpy()  # (T, 2)
    frames = np.arange(len(hands))

    def check(gate, inside, outside):
        assert np.all(gate[np.isin(frames, inside)] > 0)
        assert np.all(gate[np.isin(frames, outside)] == 0)

    # annotations: left [60, 100), right [70, 90); geometry: the box glides in beside the left hand
    # only (a frame of approach may fall within 5 cm), never near the right one
    check(hands[:, 0], range(60, 100), [*range(58), *range(101, 151)])
    if source == "annotations":
        check(hands[:, 1], range(70, 90), [*range(70), *range(90, 151)])
    else:
        assert np.all(hands[:, 1] == 0)
    check(supports[:, 0], range(40), range(42, 151))  # ground
    check(supports[:, 1], range(110, 151), range(108))  # table


def test_gated_rewards_pay_one_outside_their_windows_whatever_the_contact():
    s = _object_state(hand_gate=torch.zeros(3, 2, 1), hand_force_n=torch.tensor([0.0, 30.0, 300.0])[:, None, None]
                      .expand(3, 2, 1), hand_offset_m=torch.tensor([0.0, 0.2, 1.0]))
    value = reward_terms.hand_contact_force_setpoint(s, 0.3, 0.05, 10.0, 40.0, 5.0)
    assert torch.allclose(value, torch.ones(3))


def test_force_reward_rises_with_hand_box_force_inside_a_window_then_holds_at_the_set_point():
    forces = torch.tensor([0.0, 2.0, 5.0, 9.0, 10.0, 20.0, 80.0])
    s = _object_state(hand_gate=torch.ones(len(forces), 2, 1), hand_force_n=forces[:, None, None].expand(-1, 2, 1),
                      hand_offset_m=torch.zeros(len(forces)))
    value = reward_terms.hand_contact_force_setpoint(s, 0.3, 0.05, 10.0, 40.0, 5.0)
    assert torch.all(value[1:5] > value[:4])  # rises up to F_th = 10 N
    assert torch.allclose(value[4:], torch.full((3,), 5.0))  # the set-point: gain · 1 at and beyond F_th
    assert value[0] == pytest.approx(5.0 * np.exp(-10.0 / 40.0))
    # and falls as the hand leaves its target on the object (beyond the 5 cm tolerance)
    far = _object_state(hand_gate=torch.ones(3, 2, 1), hand_force_n=torch.full((3, 2, 1), 20.0),
                        hand_offset_m=torch.tensor([0.04, 0.2, 0.5]))
    v = reward_terms.hand_contact_force_setpoint(far, 0.3, 0.05, 10.0, 40.0, 5.0)
    assert v[0] == pytest.approx(5.0) and v[0] > v[1] > v[2]


def test_grip_set_point_is_the_force_that_holds_the_box_by_friction():
    forces = torch.tensor([0.0, 10.0, 20.0, 29.0, 30.0, 45.0])
    s = _object_state(hand_gate=torch.ones(len(forces), 2, 1), hand_force_n=forces[:, None, None].expand(-1, 2, 1),
                      hand_offset_m=torch.zeros(len(forces)), grip_force_n=torch.full((len(forces), 1), 20.0))
    value = reward_terms.hand_grip_force_setpoint(s, 0.3, 0.05, 40.0, 5.0, 10.0, 60.0, 1.5)
    assert torch.all(value[1:5] > value[:4])  # rises up to F_th = 1.5 · 20 N
    assert torch.allclose(value[4:], torch.full((2,), 5.0))


def test_grip_force_is_mass_times_lift_acceleration_over_two_mu_per_env(box_reference):
    task = make_box_task(box_reference, 4, "mujoco", "cpu")  # training: mass and friction drawn per env
    task.reset(seed=0)
    rows = task.command.rows
    need = task.tracking_state.objects.grip_force_n[:, 0]
    a = task.objects.lin_acc_w[rows, 0] - torch.tensor([0.0, 0.0, -9.81])
    m, mu = task._object_mass[:, 0], task._object_friction[:, 0]
    assert torch.allclose(need, m * torch.linalg.norm(a, dim=-1) / (2 * mu))
    assert torch.all((m >= 1.0) & (m <= 3.0)) and torch.all((mu >= 0.8) & (mu <= 1.0)) and m.std() > 0


def _object_state(hand_gate, hand_force_n, hand_offset_m, grip_force_n=None) -> SimpleNamespace:
    """A state with one box at the origin, both hands ``hand_offset_m`` (n,) from their targets."""
    n = hand_gate.shape[0]
    zeros3 = torch.zeros(n, 1, 3)
    ident = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 1, 4)
    target = torch.zeros(n, 2, 1, 3)
    hand = torch.zeros(n, 2, 3)
    hand[:, :, 0] = hand_offset_m[:, None]
    return SimpleNamespace(objects=ObjectState(names=("box",), support_names=(), pos_w=zeros3, quat_w=ident,
                       lin_vel_w=zeros3, ang_vel_w=zeros3, ref_pos_w=zeros3, ref_quat_w=ident, ref_lin_vel_w=zeros3,
                       ref_ang_vel_w=zeros3, hand_pos_w=hand, hand_target_w=target, hand_gate=hand_gate,
                       hand_force_n=hand_force_n, support_gate=torch.zeros(n, 1, 0),
                       support_force_n=torch.zeros(n, 1, 0), static_pos_w=torch.zeros(0, 3),
                       static_quat_w=torch.zeros(0, 4), grip_force_n=grip_force_n))


# ------------------------------------------------------------------ simulation
def test_hand_box_force_is_measured_when_the_box_is_pressed_on_the_hand(box_reference):
    task = make_box_task(box_reference, 1, "mujoco", "cpu", evaluation=True)
    task.reset(seed=0)
    row = task.motion.clip_start[0] + 80  # box 1.95 cm left of the left hand's palm box
    qpos, qvel = task.backend.qpos.clone(), task.backend.qvel.clone()
    qpos[0, 36:39] = task.objects.pos_w[row, 0]
    qpos[0, 37] -= 0.03  # 1 cm into the palm box
    qvel[0, 35:] = 0.0
    task.backend.reset(torch.ones(1, dtype=torch.bool), qpos, qvel)
    task.step(torch.zeros(1, 29))
    pressed = task.tracking_state.objects.hand_force_n[0, :, 0]
    assert pressed[0] > 1.0 and pressed[1] == 0.0  # left hand pushed, right hand free
    qpos[0, 37] += 0.2
    task.backend.reset(torch.ones(1, dtype=torch.bool), qpos, qvel)
    task.step(torch.zeros(1, 29))
    assert torch.all(task.tracking_state.objects.hand_force_n == 0.0)


@pytest.mark.parametrize("backend", ["mujoco", "warp"])
def test_a_hand_s_contact_root_decides_whether_its_wrist_box_presses_for_the_hand(backend, box_reference):
    """The box pressed 1 cm into the left wrist box (on ``left_wrist_pitch_link``), clear of the
    palm and fingers: the hand's force counts it only when the wrist_pitch link roots the hand."""
    if backend == "warp":
        pytest.importorskip("warp").config.quiet = True
    probe = make_box_task(box_reference, 1, "mujoco", "cpu", evaluation=True)
    probe.reset(seed=0)
    m = probe.backend.model
    d = mujoco.MjData(m)
    d.qpos[:] = probe.backend.qpos[0].numpy()
    mujoco.mj_kinematics(m, d)
    wrist = m.geom("left_wrist_collision").id
    box = [g for g in range(m.ngeom) if m.geom_bodyid[g] == m.body("object/box").id]
    robot_geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] not in (0, m.body("object/box").id)
                   and m.geom_contype[g] | m.geom_conaffinity[g]]

    def distance(g: int) -> float:
        return min(mujoco.mj_geomDistance(m, d, g, b, 0.5, np.zeros(6)) for b in box)

    up_out, centre = np.array([0.0, 1.0, 1.0]) / math.sqrt(2.0), d.geom_xpos[wrist].copy()
    lo, hi = 0.0, 0.5  # box centre along up_out from the wrist box: 1 cm into it
    for _ in range(40):
        d.qpos[36:39] = centre + 0.5 * (lo + hi) * up_out
        mujoco.mj_kinematics(m, d)
        lo, hi = (0.5 * (lo + hi), hi) if distance(wrist) < -0.01 else (lo, 0.5 * (lo + hi))
    gaps = {m.geom(g).name: distance(g) for g in robot_geoms}
    assert [name for name, gap in gaps.items() if gap <= 0.0] == ["left_wrist_collision"], gaps
    assert gaps["left_wrist_collision"] == pytest.approx(-0.01, abs=1e-4)
    assert min(gaps[f"left_{g}_collision"] for g in ("palm", "finger", "fingertip")) > 0.02
    forces = {}
    for roots in ((), ("left_wrist_pitch_link", "right_wrist_pitch_link")):
        cfg = BoxEnvCfg()
        cfg.objects.hand_contact_roots = roots
        task = make_box_task(box_reference, 1, backend, "cpu", cfg=cfg, evaluation=True)
        task.reset(seed=0)
        qpos, qvel = task.backend.qpos.clone(), task.backend.qvel.clone()
        qpos[0, 36:43] = torch.as_tensor(np.r_[d.qpos[36:39], 1.0, 0.0, 0.0, 0.0], dtype=qpos.dtype)
        qvel[0, 35:] = 0.0
        task.backend.reset(torch.ones(1, dtype=torch.bool), qpos, qvel)
        task.step(torch.zeros(1, 29))
        forces[roots] = task.tracking_state.objects.hand_force_n[0, :, 0]
        assert task.policy_metadata()["objects"]["hand_contact_roots"] == list(roots or cfg.objects.hand_bodies)
    assert torch.all(forces[()] == 0.0)  # the palm and fingers do not touch it
    wrist_force = forces[("left_wrist_pitch_link", "right_wrist_pitch_link")]
    assert wrist_force[0] > 5.0 and wrist_force[1] == 0.0, wrist_force


def test_a_hand_contact_root_must_hold_its_hand(box_reference):
    cfg = BoxEnvCfg()
    cfg.objects.hand_contact_roots = ("left_wrist_pitch_link",)
    with pytest.raises(ValueError, match=r"one body per hand"):
        make_box_task(box_reference, 1, "mujoco", "cpu", cfg=cfg, evaluation=True)
    cfg.objects.hand_contact_roots = ("right_wrist_pitch_link", "left_wrist_pitch_link")
    with pytest.raises(KeyError, match=r"'right_wrist_pitch_link' is not 'left_wrist_yaw_link' or a body above it"):
        make_box_task(box_reference, 1, "mujoco", "cpu", cfg=cfg, evaluation=True)


def test_objects_start_on_the_reference_pose_with_its_velocity(box_reference):
    task = make_box_task(box_reference, 4, "mujoco", "cpu", cfg=_cfg(reset_noise_enabled=False, start="uniform"),
                         seed=3)
    task.reset(seed=5)
    rows = task.command.start_rows
    assert len(set(rows.tolist())) > 1
    lib = task.objects
    assert torch.allclose(task.backend.qpos[:, 36:43], object_qpos(lib.pos_w[rows], lib.quat_w[rows]), atol=1e-6)
    assert torch.allclose(task.backend.qvel[:, 35:38], lib.lin_vel_w[rows, 0], atol=1e-6)
    table = task.backend.body_ids(["object/table"])[0]
    assert torch.allclose(task.backend.body_pos_w[:, table], torch.tensor([1.3, 0.0, 0.0]), atol=1e-6)


def test_a_held_box_follows_the_robots_reset_noise(box_reference):
    task = make_box_task(box_reference, 64, "mujoco", "cpu", cfg=_cfg(start="uniform"), seed=0)
    task.reset(seed=1)
    rows = task.command.start_rows
    held = (task.objects.hand_gate[rows] > 0).any(dim=1)[:, 0]
    assert held.any() and (~held).any()
    # held: the box keeps its pose in the pelvis frame exactly (it moves with the root noise);
    # loose: it gets its own ±5 cm in x, y and the robot ±5 cm / ±0.2 rad yaw about the root
    ref_local = quat_apply_inverse(task.motion.root_quat_w[rows], task.objects.pos_w[rows, 0] -
                                   task.motion.root_pos_w[rows])
    sim_local = quat_apply_inverse(task.backend.qpos[:, 3:7], task.backend.qpos[:, 36:39] - task.backend.qpos[:, :3])
    error = (sim_local - ref_local).norm(dim=-1)
    assert error[held].max() < 1e-5
    assert error[~held].min() > 1e-3 and error[~held].max() > 0.03


def test_the_object_termination_fires_beyond_25_cm(eval_task):
    task = eval_task
    task.reset(seed=0)
    qpos, qvel = task.backend.qpos.clone(), task.backend.qvel.clone()
    qpos[:, 36] += torch.tensor([0.20, 0.30])  # box 20 cm / 30 cm off (at rest on the floor)
    task.backend.reset(torch.ones(2, dtype=torch.bool), qpos, qvel)
    _, _, terminated, _, extras = task.step(torch.zeros(2, 29))
    assert extras["terminations"]["object_pos"].tolist() == [False, True]
    assert terminated[1] and not extras["success"].any()


def test_the_object_orientation_termination_fires_past_its_angle(box_reference):
    cfg = BoxEnvCfg()
    cfg.terminations["object_ori"] = TerminationTermCfg(fn="object_orientation_error", params={"threshold_rad": 1.0})
    task = make_box_task(box_reference, 3, "mujoco", "cpu", cfg=cfg, evaluation=True)
    task.reset(seed=0)
    qpos, qvel = task.backend.qpos.clone(), task.backend.qvel.clone()
    for i, angle in enumerate((0.0, 0.8, 1.3)):  # box turned about its reference's vertical axis (at rest)
        turn = torch.tensor([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)])
        qpos[i, 39:43] = quat_mul(turn, qpos[i, 39:43])
    task.backend.reset(torch.ones(3, dtype=torch.bool), qpos, qvel)
    _, _, terminated, _, extras = task.step(torch.zeros(3, 29))
    assert extras["terminations"]["object_ori"].tolist() == [False, False, True]
    assert extras["terminations"]["object_pos"].tolist() == [False, False, False]
    assert terminated.tolist() == [False, False, True]


def test_success_is_the_clip_s_last_frame_reached(eval_task):
    task = eval_task
    task.reset(seed=0)
    lib, motion = task.objects, task.motion
    successes = []
    for _ in range(int(motion.clip_length[0])):
        # keep robot and box on the reference, as a perfect policy would
        rows = task.command.rows
        qpos = torch.cat([motion.qpos(rows), object_qpos(lib.pos_w[rows], lib.quat_w[rows])], dim=-1)
        task.backend.reset(torch.ones(2, dtype=torch.bool), qpos, torch.zeros_like(task.backend.qvel))
        _, _, terminated, truncated, extras = task.step(torch.zeros(2, 29))
        assert not terminated.any()
        successes.append(bool(extras["success"][0]))
        if truncated.all():
            break
    assert successes[-1] and not any(successes[:-1]) and len(successes) == int(motion.clip_length[0]) - 1


def test_observations_name_the_object_terms_and_their_sizes(eval_task):
    layout = dict(eval_task.obs_layout["policy"])
    assert layout["object_command"] == 15 and layout["contact_schedule"] == 2 + 2
    assert eval_task.obs_dims["policy"] == 154 + 15 + 4  # the perception-free actor
    critic = dict(eval_task.obs_layout["critic"])
    assert critic["object_pos_b"] == 3 and critic["object_ori_b"] == 6 and critic["static_object_pos_b"] == 3
    meta = eval_task.policy_metadata()
    assert "object_command" in meta["observation_names"]["policy"]
    assert meta["objects"]["moving"] == ["box"] and meta["objects"]["static"] == ["table"]
    # the reference box as seen from the reference torso equals the simulated one at a reset on the reference
    eval_task.reset(seed=0)
    obs = eval_task.observations(eval_task.state)["critic"]
    start = {n: sum(d for _, d in eval_task.obs_layout["critic"][:i]) for i, (n, _) in
             enumerate(eval_task.obs_layout["critic"])}
    sim = obs[:, start["object_pos_b"]:start["object_pos_b"] + 3]
    ref = obs[:, start["object_command"]:start["object_command"] + 3]
    # reset puts the robot on the start frame; the command shows the next (target) frame
    assert torch.allclose(sim, ref, atol=0.02)


def test_gymnasium_env_checker_passes_on_the_single_env(box_reference):
    env = gymnasium.make("OTR-G1-BoxTrack-v0", reference=box_reference)
    messages = env_checker_messages(env)
    assert all("normalized space" in m for m in messages), messages
    env.close()


def test_rendered_frame_shows_the_box_and_its_reference_ghost(box_reference):
    env = gymnasium.make("OTR-G1-BoxTrack-v0", reference=box_reference, render_mode="rgb_array", evaluation=True,
                         width=160, height=120)
    env.reset(seed=0)
    try:
        frame = env.render()
    except RuntimeError as exc:
        pytest.skip(f"no offscreen OpenGL on this machine: {exc}")
    assert frame.shape == (120, 160, 3)
    renderer, task = env.unwrapped._renderer, env.unwrapped.task
    qpos = task.backend.qpos[0].double().numpy()
    no_box = qpos.copy()
    no_box[36:39] = [50.0, 50.0, -5.0]  # the box far away, below the floor
    with_box = renderer.render(qpos).astype(int)
    assert (np.abs(with_box - renderer.render(no_box).astype(int)).sum(-1) > 30).mean() > 0.002
    ghost = qpos.copy()
    ghost[36:39] += [0.0, -0.5, 0.3]  # the reference box beside the simulated one (robot ghost unmoved)
    on_top = renderer.render(qpos, ghost_qpos=qpos).astype(int)
    beside = renderer.render(qpos, ghost_qpos=ghost).astype(int)
    changed = np.abs(beside - on_top).sum(-1) > 30
    assert changed.mean() > 0.002
    env.close()


# ------------------------------------------------------------------ MuJoCo-Warp (warp "cpu" device)
def test_both_backends_put_the_objects_on_the_reference_and_agree_on_their_state(box_reference):
    """Same start (no reset noise), same actions: object poses, velocities and contact forces
    of CPU MuJoCo and MuJoCo-Warp agree; the first MuJoCo-Warp use compiles kernels (~1 min)."""
    pytest.importorskip("warp")
    cfg = _cfg(reset_noise_enabled=False, start="uniform")
    cfg.randomization.enabled = False
    cpu = make_box_task(box_reference, 3, "mujoco", "cpu", cfg=cfg, seed=4)
    gpu_code = make_box_task(box_reference, 3, "warp", "cpu", cfg=cfg, seed=4)
    cpu.reset(seed=7)
    gpu_code.reset(seed=7)
    rows = cpu.command.start_rows
    assert torch.equal(rows, gpu_code.command.start_rows)
    expected = object_qpos(cpu.objects.pos_w[rows], cpu.objects.quat_w[rows])
    for task in (cpu, gpu_code):
        assert torch.allclose(task.backend.qpos[:, 36:43], expected, atol=1e-6)
        ids = task.backend.body_ids(["object/box"])
        assert torch.allclose(task.backend.body_pos_w[:, ids[0]], cpu.objects.pos_w[rows, 0], atol=1e-5)
    gen = torch.Generator().manual_seed(0)
    worst = {"pos": 0.0, "quat": 0.0, "lin_vel": 0.0, "support_force": 0.0}
    everyone = torch.ones(3, dtype=torch.bool)
    for _ in range(15):
        qpos, qvel = cpu.backend.qpos.clone(), cpu.backend.qvel.clone()
        gpu_code.backend.reset(everyone, qpos, qvel)
        cpu.backend.reset(everyone, qpos, qvel)
        actions = 0.3 * torch.randn(3, 29, generator=gen)
        _, _, term_a, _, _ = cpu.step(actions)
        _, _, term_b, _, _ = gpu_code.step(actions)
        a, b = cpu.tracking_state.objects, gpu_code.tracking_state.objects
        assert torch.equal(term_a, term_b)
        worst["pos"] = max(worst["pos"], (a.pos_w - b.pos_w).abs().max().item())
        worst["quat"] = max(worst["quat"], (a.quat_w - b.quat_w).abs().max().item())
        worst["lin_vel"] = max(worst["lin_vel"], (a.lin_vel_w - b.lin_vel_w).abs().max().item())
        worst["support_force"] = max(worst["support_force"], (a.support_force_n - b.support_force_n).abs().max().item())
    assert worst["pos"] < 1e-3 and worst["quat"] < 1e-3 and worst["lin_vel"] < 0.05, worst
    assert worst["support_force"] < 10.0, worst


def test_a_box_the_reference_hand_starts_inside_is_narrowed_on_the_grasped_axis_only(box_reference_geometry, tmp_path):
    ref = Reference.load(box_reference_geometry)
    wide = trimesh.creation.box(extents=(2 * BOX_HALF_M, 2 * BOX_HALF_M + 0.06, 2 * BOX_HALF_M))
    ref.objects[0].mesh_vertices, ref.objects[0].mesh_faces = np.asarray(wide.vertices), np.asarray(wide.faces)
    path = ref.save(tmp_path / "wide.npz")  # beside the left hand, the box now reaches into its capsule
    cfg = load_box_config(overrides={"objects": {"grasp_fit": False}})
    before = make_box_task(path, 1, "mujoco", "cpu", cfg=cfg, evaluation=True)
    task = make_box_task(path, 1, "mujoco", "cpu", evaluation=True)
    box = task.scene.moving[0]
    assert before.scene.moving[0].grasp_shrink_m is None
    assert np.allclose(np.sort(before.scene.moving[0].shapes[0].half_extents), [0.1, 0.1, 0.13])
    lateral = int(np.argmax(before.scene.moving[0].shapes[0].half_extents))  # the 26 cm (y) axis
    assert np.flatnonzero(box.grasp_shrink_m).tolist() == [lateral] and box.grasp_shrink_m[lateral] > 0.005
    assert np.allclose(box.shapes[0].half_extents + box.grasp_shrink_m, before.scene.moving[0].shapes[0].half_extents)
    assert task.policy_metadata()["objects"]["grasp_shrink_m"]["box"] == pytest.approx(box.grasp_shrink_m.tolist())

    def left_hand_gap(t) -> np.ndarray:
        prepared = prepared_references(path, t.cfg.command.tracked_bodies)[0]
        hands, _ = _Geometry(t.backend.model, t.scene, t.cfg.objects).distances(prepared, [0], [1], hands=True)
        return hands[62:98, 0, 0]  # the frames the box rests beside the left hand

    assert left_hand_gap(before).max() < -0.005  # the reference hand starts inside the box
    assert np.quantile(left_hand_gap(task), 0.25) >= -1e-3  # after the fit it starts (at most) touching it


def test_a_reference_made_with_a_designed_squeeze_keeps_it(box_reference_geometry, tmp_path):
    # the retargeter's grasp pass (retarget.solver.grasp) puts the hands that deep on purpose
    # and records it: the fit narrows the box only by what lies beyond it
    ref = Reference.load(box_reference_geometry)
    wide = trimesh.creation.box(extents=(2 * BOX_HALF_M, 2 * BOX_HALF_M + 0.06, 2 * BOX_HALF_M))
    ref.objects[0].mesh_vertices, ref.objects[0].mesh_faces = np.asarray(wide.vertices), np.asarray(wide.faces)
    plain = make_box_task(ref.save(tmp_path / "wide.npz"), 1, "mujoco", "cpu", evaluation=True).scene.moving[0]
    lateral = int(np.flatnonzero(plain.grasp_shrink_m)[0])
    ref.metadata["grasp"] = {"squeeze_m": float(plain.grasp_shrink_m[lateral]) - 0.002}
    meant = make_box_task(ref.save(tmp_path / "squeezed.npz"), 1, "mujoco", "cpu", evaluation=True).scene.moving[0]
    assert meant.grasp_shrink_m[lateral] == pytest.approx(0.002, abs=1e-6)


def test_a_box_held_between_both_hands_at_its_bottom_edges_is_narrowed_between_the_hands_not_in_height(
        box_reference_geometry, tmp_path):
    # OMOMO's lift: both hands at the box's bottom edges. Their points lie nearest to the bottom
    # face, yet the box is squeezed between them (y here); narrowing the height instead would lift
    # the box's bottom off the floor it rests on in the reference (3.2 cm on sub3_largebox_003).
    ref = Reference.load(box_reference_geometry)
    hands = ref.body_index(["left_wrist_yaw_link", "right_wrist_yaw_link"])
    points = ref.body_pos_w[0, hands] + quat_apply(ref.body_quat_w[0, hands], np.array([0.11, 0.0, 0.0]))
    half = np.array([0.1, points[0, 1] + 0.01, 0.12])  # each hand point 1 cm inside a side face (y)
    box = ref.objects[0]
    floor = np.array([0.6, 0.0, half[2]])
    between = np.array([points[:, 0].mean(), 0.0, points[:, 2].mean() + half[2]])  # hands at the bottom face
    keys = [(0, floor), (39, floor), (49, np.array([0.9, 0.0, 1.2])), (60, between), (99, between),
            (104, np.array([0.9, 0.6, 1.2])), (110, box.pos_w[110] + [0.0, 0.0, half[2] - BOX_HALF_M]),
            (150, box.pos_w[150] + [0.0, 0.0, half[2] - BOX_HALF_M])]
    t = np.arange(ref.num_frames)
    box.pos_w = np.stack([np.interp(t, [k for k, _ in keys], [p[i] for _, p in keys]) for i in range(3)], axis=1)
    box.lin_vel_w = np.gradient(box.pos_w, 1.0 / ref.fps, axis=0)
    mesh = trimesh.creation.box(extents=2 * half)
    box.mesh_vertices, box.mesh_faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    path = ref.save(tmp_path / "bottom_grasp.npz")
    assert np.all(np.argmax(np.abs(points - between) / half, axis=-1) == 2)  # the bottom face is the nearest

    cfg = load_box_config(overrides={"objects": {"grasp_fit": False}})
    before = make_box_task(path, 1, "mujoco", "cpu", cfg=cfg, evaluation=True).scene.moving[0].shapes[0]
    task = make_box_task(path, 1, "mujoco", "cpu", evaluation=True)
    fitted = task.scene.moving[0]
    world_axis = np.argmax(np.abs(quat_apply(np.broadcast_to(before.quat_wxyz, (3, 4)), np.eye(3))), axis=-1)
    lateral, vertical = int(np.flatnonzero(world_axis == 1)[0]), int(np.flatnonzero(world_axis == 2)[0])
    assert np.flatnonzero(fitted.grasp_shrink_m).tolist() == [lateral] and fitted.grasp_shrink_m[lateral] > 0.02
    assert fitted.shapes[0].half_extents[vertical] == pytest.approx(half[2], abs=1e-3)
    # ... so the box stays on its reference height on the floor (frame 0: the start frame)
    task.reset()
    for _ in range(10):
        task.step(torch.zeros(1, 29))
    box_state = task.tracking_state.objects
    assert abs(box_state.pos_w[0, 0, 2].item() - box_state.ref_pos_w[0, 0, 2].item()) < 3e-3


def test_kinematic_playback_leaves_an_uncarried_box_where_it_stands(box_reference):
    """The generated clip's box stands on the floor for frames [0, 40), then the reference flies
    it away from every hand (frames 39-49): played back with the robot on the reference, the
    simulated box stays on the floor, exact while the reference agrees, and the playback ends on
    the first frame where the reference is more than the 25 cm termination away."""
    from envs.kinematic_playback import play
    from otr_gym.reference import Reference

    result = play(box_reference)
    ref_box = Reference.load(box_reference).objects[0].pos_w
    start = ref_box[0]
    moved = np.linalg.norm(ref_box - start, axis=-1)
    first_far = int(np.argmax(moved > result.termination_m))
    assert result.termination_m == 0.25
    assert result.ended_at is not None and abs(result.ended_at - first_far) <= 1
    assert result.frames == result.ended_at and result.clip_frames == len(ref_box)
    np.testing.assert_allclose(result.pos_error_cm[:35], 0.0, atol=0.5)
    # once the reference leaves, the error is the reference's own displacement from the standing box
    np.testing.assert_allclose(result.pos_error_cm[-1], 100 * moved[result.ended_at], atol=0.5)
    assert max(result.ori_error_deg[:35]) < 1.0


def test_playback_draws_follow_the_object_randomisation_and_their_seed(box_reference):
    """``draw_seed`` draws the box's friction, mass and inertia from ``objects.randomization``
    (friction [0.8, 1.0], mass 1 kg + [0, 2], inertia × [0.5, 1.5]), the same for the same seed;
    the uncarried box of the generated clip stands where it stands whatever it weighs."""
    from envs.kinematic_playback import play

    nominal = play(box_reference)
    first, again, other = (play(box_reference, draw_seed=k) for k in (3, 3, 4))
    assert nominal.draw is None
    (body, (friction, mass, scale)), = first.draw.items()
    assert 0.8 <= friction <= 1.0 and 1.0 <= mass <= 3.0 and 0.5 <= scale <= 1.5
    assert again.draw == first.draw and other.draw != first.draw
    assert again.pos_error_cm == first.pos_error_cm
    assert first.ended_at == nominal.ended_at
    np.testing.assert_allclose(first.pos_error_cm[:35], nominal.pos_error_cm[:35], atol=0.2)


def test_draws_played_together_equal_draws_played_alone(box_reference):
    """``play_draws`` builds the task once: a nominal run after a draw is nominal again, and every
    run equals the same run played on its own."""
    from envs.kinematic_playback import play, play_draws

    first, drawn, again = play_draws(box_reference, [None, 3, None])
    assert first.draw is None and again.draw is None and drawn.draw == play(box_reference, draw_seed=3).draw
    assert first.pos_error_cm == again.pos_error_cm == play(box_reference).pos_error_cm
    assert drawn.pos_error_cm == play(box_reference, draw_seed=3).pos_error_cm


def test_the_played_back_robot_is_immovable_within_a_physics_step(box_reference):
    """Unactuated, the G1 falls and swings under gravity inside a step, which can switch a deep
    hand-box contact off; the playback's robot must not accelerate, while the box still does."""
    import mujoco

    from envs.kinematic_playback import kinematic_robot

    task = make_box_task(box_reference, 1, "mujoco", "cpu", evaluation=True, autoreset=False)
    model = task.backend.model
    data = mujoco.MjData(model)
    data.qpos[:36] = task.motion.qpos(torch.tensor([0]))[0].double().numpy()
    data.qpos[36:39] = task.objects.pos_w[0, 0].numpy() + np.array([0.0, 0.0, 0.5])  # box dropped from 50 cm
    data.qpos[39:43] = task.objects.quat_w[0, 0].numpy()
    mujoco.mj_forward(model, data)
    assert np.abs(data.qacc[:35]).max() > 5.0  # the free G1 falls (base) and its limbs swing
    kinematic_robot(model, 35)
    mujoco.mj_forward(model, data)
    assert np.abs(data.qacc[:35]).max() < 1e-3  # what remains: 35 kg of G1 under gravity against 10⁶ kg
    np.testing.assert_allclose(data.qacc[37], -9.81, atol=1e-3)  # the falling box: gravity alone


def test_reference_overlaps_name_a_torso_the_reference_puts_inside_its_box(box_reference_geometry, tmp_path):
    """The generated clip keeps every robot collision geom out of its box. Moved 15 cm in front of
    the torso capsule's axis (radius 9 cm; the box's half-width 10 cm) for frames 10-14, the box
    holds the torso 2-4 cm deep (less whatever the grasp fit narrowed on that axis), and only then."""
    from envs.kinematic_playback import play
    from envs.mdp.objects import reference_overlaps

    task = make_box_task(box_reference_geometry, 1, "mujoco", "cpu", evaluation=True)
    model = task.backend.model
    assert reference_overlaps(Reference.load(box_reference_geometry), task.scene, model, task.cfg.objects) == []

    data = mujoco.MjData(model)
    torso = model.geom("torso_collision").id
    shoved = Reference.load(box_reference_geometry)
    for t in range(10, 15):
        data.qpos[:36] = task.motion.qpos(torch.tensor([t]))[0].double().numpy()
        mujoco.mj_kinematics(model, data)
        shoved.objects[0].pos_w[t] = data.geom_xpos[torso] + np.array([0.15, 0.0, 0.0])
        shoved.objects[0].quat_w[t] = [1.0, 0.0, 0.0, 0.0]
    path = shoved.save(tmp_path / "shoved.npz")
    found = {o.geom: o for o in reference_overlaps(Reference.load(path), task.scene, model, task.cfg.objects)}
    assert found["torso_collision"].body == "torso_link" and not found["torso_collision"].hand
    assert found["torso_collision"].frames == 5 and 0.02 < found["torso_collision"].deepest_m < 0.045
    assert all(o.frames <= 5 for o in found.values())
    # the playback reports them (grasp_playback.py prints this line)
    line = play(path).overlap_line()
    assert f"torso_collision {1000 * found['torso_collision'].deepest_m:.1f} mm (5 frames)," in line + ","


def test_held_grasp_tells_a_box_held_at_its_side_from_one_hung_over_the_hand(box_reference_geometry, tmp_path):
    """The generated clip holds its box beside the left hand, centre at the hand point's height,
    in the air (frames 60-99): the hand is at the box's side, about half-way up. Raised to rest on
    top of the hand, the same box is held at its bottom face (-1 half-height), the inverted
    pendulum that tips; turned 90° while held, it reads a 90° tilt."""
    from envs.mdp.objects import held_grasp

    def grasp(ref: Reference):
        path = ref.save(tmp_path / f"{len(list(tmp_path.iterdir()))}.npz")
        task = make_box_task(path, 1, "mujoco", "cpu", evaluation=True)
        return held_grasp(ref, task.scene, task.backend.model, task.cfg.objects), task

    ref = Reference.load(box_reference_geometry)
    beside, task = grasp(ref)
    assert 40 <= beside.frames <= 52  # frames 60-99 plus the approach within the 5 cm window
    assert abs(beside.hand_height) < 0.5 and beside.tilt_deg == pytest.approx(0.0, abs=1e-3)
    assert abs(beside.hand_centre_height) < 0.5  # the hand beside the box: its centre too
    assert beside.centre_height_m == pytest.approx(ref.objects[0].pos_w[60:100, 2].mean(), abs=0.03)

    # the box put on the hand from above (frames 45-104, the approach included): its bottom face
    # 1 cm over the hand's highest point
    model = task.backend.model
    data = mujoco.MjData(model)
    data.qpos[:36] = task.motion.qpos(torch.tensor([60]))[0].double().numpy()
    mujoco.mj_kinematics(model, data)
    left = model.body("left_wrist_yaw_link").id
    tops = []
    for g in range(model.ngeom):
        if model.geom_bodyid[g] == left and model.geom_contype[g] | model.geom_conaffinity[g]:
            rot_z = data.geom_xmat[g].reshape(3, 3)[2]  # world z of the geom's local axes
            centre, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
            tops.append(data.geom_xpos[g][2] + rot_z @ centre + np.abs(rot_z) @ half)
    over = Reference.load(box_reference_geometry)
    box = over.objects[0]
    box.pos_w[45:105] = [*data.xpos[left][:2], max(tops) + 0.01 + BOX_HALF_M]
    box.lin_vel_w = np.gradient(box.pos_w, 1.0 / over.fps, axis=0)
    on_hand, _ = grasp(over)
    assert on_hand.frames >= 55
    assert on_hand.hand_height == pytest.approx(-1.0, abs=0.02)
    # the hand geoms' centre lies under the bottom face, by more than the 1 cm gap
    assert on_hand.hand_centre_height < -1.0 - 0.01 / BOX_HALF_M
    assert on_hand.centre_height_m == pytest.approx(max(tops) + 0.01 + BOX_HALF_M, abs=0.01)

    turned = Reference.load(box_reference_geometry)
    turned.objects[0].quat_w[60:100] = [math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0]  # 90° about x
    side, _ = grasp(turned)
    # a cube turned about an axis is the same shape: the same frames are held, the 40 turned ones at 90°
    assert side.frames == beside.frames
    assert side.tilt_deg == pytest.approx(90.0 * 40 / side.frames, abs=0.5)
