"""The tracking MDP's parts on their own: config, reference library, start sampling, and the
reward / termination / observation functions on hand-made states (no simulator)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
import yaml

from agents.config import load_train_config
from envs.config import DEFAULT_CONFIG, CommandCfg, TrackEnvCfg, load_track_config
from envs.mdp import observations, rewards, terminations
from envs.mdp.commands import MotionCommand
from envs.mdp.metrics import (
    anchor_horizontal_error_m,
    anchor_offset_heading_m,
    mpjpe_root_relative,
    mpjpe_root_relative_heading_aligned,
)
from envs.mdp.motion import MotionLibrary
from envs.mdp.state import TrackingState, aligned_targets
from otr_gym import robot
from otr_gym.reference import InvalidReferenceError, Reference
from otr_gym.rotations import quat_from_euler_xyz, quat_mul

from conftest import benchmark_sets

TRACKED = robot.TRACKED_BODIES
ANCHOR = TRACKED.index(robot.ANCHOR_BODY)


# ------------------------------------------------------------------ config


def test_track_yaml_lists_exactly_the_dataclass_defaults():
    assert load_track_config(DEFAULT_CONFIG) == TrackEnvCfg()


def test_config_rejects_unknown_keys_naming_them(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"sim": {"decimaton": 4}}))
    with pytest.raises(ValueError, match="decimaton"):
        load_track_config(path)


def test_config_overrides_replace_nested_values_and_keep_types():
    cfg = load_track_config(overrides={"rewards": {"body_pos": {"weight": 2}}, "sim": {"episode_length_s": 5}})
    assert cfg.rewards["body_pos"].weight == 2.0 and isinstance(cfg.rewards["body_pos"].weight, float)
    assert cfg.rewards["body_pos"].params == {"sigma": 0.3}
    assert cfg.sim.episode_length_s == 5.0


def test_evaluation_config_turns_off_randomisation_noise_and_starts_at_frame_zero():
    cfg = TrackEnvCfg().for_evaluation()
    assert not cfg.randomization.enabled and not cfg.observations.noise_enabled
    assert not cfg.command.reset_noise_enabled
    assert cfg.command.start == "zero" and cfg.command.on_clip_end == "truncate"


# ------------------------------------------------------------------ reference library


def _clip(frames: int, fps: float = 50.0, x_speed: float = 0.0) -> Reference:
    q = np.tile(robot.default_qpos(), (frames, 1))
    q[:, 0] = x_speed * np.arange(frames) / fps
    return Reference.from_qpos(q, fps)


def test_library_resamples_to_50fps_and_keeps_the_14_tracked_bodies_by_name():
    lib = MotionLibrary.load(_clip(31, fps=30.0, x_speed=0.6), TRACKED)  # 1.0 s at 30 fps
    assert lib.fps == 50.0 and lib.clip_length.tolist() == [51]
    assert lib.body_pos_w.shape == (51, 14, 3) and lib.body_quat_w.shape == (51, 14, 4)
    # finite-difference velocities of the resampled poses: 0.6 m/s forward for every body
    assert torch.allclose(lib.body_lin_vel_w[..., 0], torch.full((51, 14), 0.6), atol=1e-4)
    assert torch.allclose(lib.root_lin_vel_w[:, 0], torch.full((51,), 0.6), atol=1e-4)


def test_library_from_a_folder_concatenates_the_clips_in_name_order(tmp_path):
    _clip(60).save(tmp_path / "a.npz")
    _clip(80, x_speed=0.5).save(tmp_path / "b.npz")
    lib = MotionLibrary.load(tmp_path, TRACKED)
    assert [n.rsplit("/", 1)[-1] for n in lib.names] == ["a.npz", "b.npz"]
    assert lib.clip_start.tolist() == [0, 60] and lib.clip_length.tolist() == [60, 80]
    assert lib.root_pos_w[60 + 50, 0].item() == pytest.approx(0.5, abs=1e-6)  # clip b, 1 s in


def test_reference_with_a_wrong_joint_set_fails_naming_the_file(tmp_path):
    arrays = _clip(60).to_arrays()
    arrays["joint_names"] = np.array([n.replace("left_elbow", "left_knuckle") for n in robot.JOINT_NAMES])
    path = tmp_path / "wrong_joints.npz"
    np.savez(path, **arrays)
    with pytest.raises(InvalidReferenceError, match=r"wrong_joints\.npz.*left_knuckle"):
        MotionLibrary.load(path, TRACKED)


def test_reference_with_nan_fails_naming_the_file_and_the_array(tmp_path):
    arrays = _clip(60).to_arrays()
    arrays["body_pos_w"][10, 3, 1] = np.nan
    path = tmp_path / "nan.npz"
    np.savez(path, **arrays)
    with pytest.raises(InvalidReferenceError, match=r"nan\.npz.*body_pos_w.*NaN"):
        MotionLibrary.load(path, TRACKED)


def test_too_short_reference_fails_naming_the_file_and_its_length(tmp_path):
    path = _clip(10).save(tmp_path / "short.npz")
    with pytest.raises(InvalidReferenceError, match=r"short\.npz.*too short.*10 frames"):
        MotionLibrary.load(path, TRACKED, min_clip_frames=25)


def test_missing_reference_file_fails_naming_the_path(tmp_path):
    with pytest.raises(InvalidReferenceError, match="nowhere.npz"):
        MotionLibrary.load(tmp_path / "nowhere.npz", TRACKED)


def test_reference_without_a_tracked_body_fails_naming_the_body(tmp_path):
    ref = _clip(60)
    keep = [i for i, n in enumerate(ref.body_names) if n != "left_elbow_link"]
    arrays = ref.to_arrays()
    for key in ("body_pos_w", "body_quat_w", "body_lin_vel_w", "body_ang_vel_w"):
        arrays[key] = arrays[key][:, keep]
    arrays["body_names"] = arrays["body_names"][keep]
    path = tmp_path / "no_elbow.npz"
    np.savez(path, **arrays)
    with pytest.raises(InvalidReferenceError, match=r"no_elbow\.npz.*left_elbow_link"):
        MotionLibrary.load(path, TRACKED)


# ------------------------------------------------------------------ start sampling


def _command(lengths, num_envs=4096, **cfg) -> MotionCommand:
    lib = MotionLibrary.load([_clip(n) for n in lengths], TRACKED)
    return MotionCommand(lib, num_envs, replace(CommandCfg(), **cfg), torch.Generator().manual_seed(0))


def test_bins_are_one_second_long_plus_one():
    cmd = _command([250, 120])
    assert cmd.bin_count.tolist() == [6, 3]  # ⌊T/50⌋ + 1


def test_without_failures_starts_are_uniform_over_the_clip():
    cmd = _command([250])
    cmd.resample(torch.ones(4096, dtype=torch.bool))
    counts = torch.bincount(cmd.start_frame * 6 // 248, minlength=6).float()
    assert counts.min() > 0.8 * 4096 / 6 and counts.max() < 1.2 * 4096 / 6
    assert cmd.start_frame.max() <= 248 and torch.equal(cmd.frame, cmd.start_frame + 1)


def test_failures_concentrate_starts_on_the_failing_bin():
    cmd = _command([250], adaptive_floor="absolute", adaptive_uniform_ratio=0.1)  # §2's rule
    cmd.frame[:] = 130  # 130 · 6 / 250 → bin 3
    for _ in range(200):
        cmd.record_failures(torch.ones(4096, dtype=torch.bool))
        cmd.update_failure_rate()
    p = cmd.sampling_probabilities()
    assert p.argmax().item() == 3 and p[3] > 0.9
    cmd.resample(torch.ones(4096, dtype=torch.bool))
    in_bin3 = ((cmd.start_frame * 6 // 248) == 3).float().mean()
    assert in_bin3 > 0.85


@pytest.mark.parametrize("floor", ["absolute", "relative"])
def test_a_bin_that_stops_failing_keeps_its_starts_only_under_the_relative_floor(floor):
    """40 failures a step in bin 3 of a 6-bin clip (8192 envs of a box run fail about that
    often). §2's absolute floor 0.5/6 then leaves bin 0 a share of 0.5/6 / (40 + 0.5) = 0.2 %;
    relative, each bin without failures keeps 0.5/(6·1.5) = 5.6 % of the starts."""
    cmd = _command([250], num_envs=8192, adaptive_floor=floor, adaptive_uniform_ratio=0.5)
    cmd.frame[:] = 130  # bin 3
    failing = torch.arange(8192) < 40
    for _ in range(5000):  # the EMA (α 0.001) reaches 39.7 per step
        cmd.record_failures(failing)
        cmd.update_failure_rate()
    f = 40.0 * (1.0 - 0.999**5000)
    p = cmd.sampling_probabilities()
    quiet = 0.5 / 6 * (f if floor == "relative" else 1.0)
    expected = torch.full((6,), quiet)
    expected[3] += f
    torch.testing.assert_close(p, expected / expected.sum(), rtol=1e-4, atol=0)
    if floor == "relative":
        assert p[0].item() == pytest.approx(0.5 / (6 * 1.5), rel=1e-3)
    else:
        assert p[0].item() < 0.0025
    cmd.resample(torch.ones(8192, dtype=torch.bool))
    share = ((cmd.start_frame * 6 // 248) == 0).float().mean().item()
    assert abs(share - p[0].item()) < 4 * (p[0].item() * (1 - p[0].item()) / 8192) ** 0.5


def test_the_relative_floor_is_the_absolute_one_while_failures_are_rare():
    a, r = _command([250], adaptive_floor="absolute"), _command([250], adaptive_floor="relative")
    for cmd in (a, r):
        cmd.frame[:] = 130
        for _ in range(300):
            cmd.record_failures(torch.arange(4096) < 2)  # Σf = 2·(1 − 0.999³⁰⁰) = 0.52 < 1
            cmd.update_failure_rate()
    torch.testing.assert_close(a.sampling_probabilities(), r.sampling_probabilities())


def test_an_unknown_floor_mode_is_refused():
    with pytest.raises(ValueError, match="adaptive_floor"):
        _command([250], adaptive_floor="proportional")


def test_each_clip_gets_the_same_start_mass_when_nothing_failed():
    cmd = _command([250, 60])
    cmd.resample(torch.ones(4096, dtype=torch.bool))
    share = (cmd.clip == 1).float().mean().item()
    assert share == pytest.approx(0.5, abs=0.04)


def test_zero_start_puts_every_env_on_frame_zero_of_clip_index_mod_clips():
    cmd = _command([100, 60], num_envs=5, start="zero")
    cmd.resample(torch.ones(5, dtype=torch.bool))
    assert cmd.clip.tolist() == [0, 1, 0, 1, 0] and cmd.start_frame.tolist() == [0] * 5


def test_resample_changes_only_masked_envs():
    cmd = _command([250], num_envs=8)
    before = cmd.start_frame.clone()
    mask = torch.tensor([True, False] * 4)
    for _ in range(3):
        cmd.resample(mask)
    assert torch.equal(cmd.start_frame[~mask], before[~mask])


def test_advance_flags_envs_past_the_clip_end():
    cmd = _command([60], num_envs=2, start="zero")
    cmd.resample(torch.ones(2, dtype=torch.bool))
    cmd.frame[1] = 59
    ended = cmd.advance()
    assert ended.tolist() == [False, True] and cmd.frame.tolist() == [2, 59]


def test_start_state_without_noise_is_the_reference_qpos_and_body_frame_angular_velocity():
    q = np.tile(robot.default_qpos(), (100, 1))
    yaw = np.linspace(0.0, 1.0, 100)  # 0.5 rad/s about z, rotated root
    q[:, 3:7] = quat_mul(quat_from_euler_xyz(np.zeros(100), np.full(100, 0.3), yaw), np.array([1.0, 0, 0, 0]))
    lib = MotionLibrary.load(Reference.from_qpos(q, 50.0), TRACKED)
    cmd = MotionCommand(lib, 1, CommandCfg(), torch.Generator().manual_seed(0))
    cmd.start_frame[:] = 40
    qpos, qvel = cmd.start_state(noise=False)
    assert torch.allclose(qpos[0].double(), torch.as_tensor(q[40]), atol=1e-6)
    world_ang = np.array([0.0, 0.0, 50.0 / 99.0])  # finite differences of the yaw ramp
    from otr_gym.rotations import quat_apply_inverse

    assert np.allclose(qvel[0, 3:6].numpy(), quat_apply_inverse(q[40, 3:7], world_ang), atol=1e-4)


def test_reset_noise_stays_within_the_spec_widths_and_soft_limits():
    cmd = _command([100], num_envs=2000)
    cmd.resample(torch.ones(2000, dtype=torch.bool))
    clean_q, clean_v = cmd.start_state(noise=False)
    noisy_q, noisy_v = cmd.start_state(noise=True)
    dpos = (noisy_q[:, :3] - clean_q[:, :3]).abs().amax(0)
    width = torch.tensor([0.05, 0.05, 0.01])
    assert torch.all(dpos <= width + 1e-6) and torch.all(dpos > 0.8 * width)  # 2000 draws reach the edges
    dlin = (noisy_v[:, :3] - clean_v[:, :3]).abs().amax(0)
    assert torch.all(dlin <= torch.tensor([0.5, 0.5, 0.2]) + 1e-6)
    lower, upper = robot.soft_joint_limits(0.9)
    assert torch.all(noisy_q[:, 7:] >= torch.as_tensor(lower, dtype=torch.float32) - 1e-6)
    assert torch.all(noisy_q[:, 7:] <= torch.as_tensor(upper, dtype=torch.float32) + 1e-6)
    assert (noisy_q[:, 7:] - clean_q[:, 7:]).abs().max() <= 0.1 + 1e-6


# ------------------------------------------------------------------ terms on hand-made states


def _state(offset_m: float = 0.0, yaw_rad: float = 0.0, n: int = 3) -> TrackingState:
    """A state whose robot is the reference moved by ``offset_m`` along x and turned by ``yaw_rad``."""
    lib = MotionLibrary.load(_clip(60), TRACKED)
    ref_pos, ref_quat = lib.body_pos_w[:n], lib.body_quat_w[:n]
    turn = quat_from_euler_xyz(torch.zeros(n), torch.zeros(n), torch.full((n,), yaw_rad))[:, None]
    from otr_gym.rotations import quat_apply

    pos = quat_apply(turn.expand_as(ref_quat), ref_pos) + torch.tensor([offset_m, 0.0, 0.0])
    quat = quat_mul(turn.expand_as(ref_quat), ref_quat)
    al_pos, al_quat = aligned_targets(pos[:, ANCHOR], quat[:, ANCHOR], ref_pos, ref_quat, ANCHOR)
    zeros3 = torch.zeros(n, 14, 3)
    joints = lib.joint_pos[:n]
    return TrackingState(
        body_names=TRACKED, anchor=ANCHOR, end_effectors=torch.tensor([5, 6, 12, 13]),
        contact_body_names=("pelvis", "left_ankle_roll_link", "left_knee_link", "right_wrist_yaw_link"),
        joint_pos=joints, joint_vel=torch.zeros(n, 29), root_quat_w=quat[:, 0],
        root_lin_vel_b=torch.zeros(n, 3), root_ang_vel_b=torch.zeros(n, 3),
        body_pos_w=pos, body_quat_w=quat, body_lin_vel_w=zeros3, body_ang_vel_w=zeros3,
        contact_force_n=torch.tensor([[0.5, 300.0, 2.0, 50.0]]).repeat(n, 1),
        ref_joint_pos=joints, ref_joint_vel=torch.zeros(n, 29), ref_body_pos_w=ref_pos, ref_body_quat_w=ref_quat,
        ref_body_lin_vel_w=zeros3, ref_body_ang_vel_w=zeros3,
        ref_body_pos_aligned_w=al_pos, ref_body_quat_aligned_w=al_quat,
        action=torch.ones(n, 29), last_action=torch.zeros(n, 29),
        default_joint_pos=torch.as_tensor(robot.DEFAULT_JOINT_POS, dtype=torch.float32).repeat(n, 1),
    )


def test_alignment_moves_targets_onto_the_robot_anchor_xy_and_yaw():
    s = _state(offset_m=0.7, yaw_rad=0.5)
    assert torch.allclose(s.ref_body_pos_aligned_w, s.body_pos_w, atol=1e-5)
    assert torch.allclose(rewards.body_position_error_exp(s, sigma=0.3), torch.ones(3), atol=1e-6)
    assert torch.allclose(rewards.body_orientation_error_exp(s, sigma=0.4), torch.ones(3), atol=1e-5)


def test_anchor_rewards_use_the_unaligned_reference():
    s = _state(offset_m=0.3)
    assert torch.allclose(rewards.anchor_position_error_exp(s, sigma=0.3), torch.full((3,), math.exp(-1.0)), atol=1e-5)
    s = _state(yaw_rad=0.4)
    expected = torch.full((3,), math.exp(-1.0))
    assert torch.allclose(rewards.anchor_orientation_error_exp(s, sigma=0.4), expected, atol=1e-5)


def test_the_precise_tracking_recipe_adds_a_steeper_position_term_to_section_4s():
    # benchmarks/precise_tracking.sets, the recipe that brought the AMASS jog to 35 mm: 10 PPO
    # epochs, KL target 0.02, and body positions rewarded a second time at σ 0.1 m beside §4's 0.3
    train = load_train_config(overrides=benchmark_sets("precise_tracking.sets"))
    assert (train.algorithm.num_learning_epochs, train.algorithm.desired_kl) == (10, 0.02)
    cfg = load_track_config(overrides=train.env)
    assert set(cfg.rewards) == set(TrackEnvCfg().rewards) | {"body_pos_fine"}
    s = _state()
    off = replace(s, body_pos_w=s.body_pos_w + torch.tensor([0.0, 0.05, 0.0]))  # every body 5 cm to the left

    def value(name):
        term = cfg.rewards[name]
        return term.weight * getattr(rewards, term.fn)(off, **term.params)

    assert torch.allclose(value("body_pos"), torch.full((3,), math.exp(-0.05**2 / 0.3**2)), atol=1e-5)
    assert torch.allclose(value("body_pos_fine"), torch.full((3,), math.exp(-0.05**2 / 0.1**2)), atol=1e-5)
    # at 5 cm the fine term has lost 8x what §4's has: the gradient left where §4's is flat
    assert (1 - value("body_pos_fine")[0]) / (1 - value("body_pos")[0]) > 8


def test_action_rate_joint_limits_and_undesired_contacts():
    s = _state()
    assert torch.equal(rewards.action_rate_l2(s), torch.full((3,), 29.0))
    lower, upper = robot.soft_joint_limits(0.9)
    beyond = s.joint_pos.clone()
    beyond[:, 3] = float(upper[3]) + 0.2  # left knee 0.2 rad past its soft limit
    assert torch.allclose(rewards.joint_pos_limits(replace(s, joint_pos=beyond), 0.9), torch.full((3,), 0.2), atol=1e-5)
    # forces 0.5, 300 (foot, excused), 2.0 (knee), 50 (hand, excused) → one undesired contact
    assert torch.equal(rewards.undesired_contacts(s, 1.0, ["ankle_roll", "wrist_yaw"]), torch.ones(3))


def test_terminations_fire_only_beyond_their_thresholds():
    s = _state()
    for fn, kw in ((terminations.anchor_height_error, {"threshold_m": 0.25}),
                   (terminations.anchor_gravity_error, {"threshold": 0.8}),
                   (terminations.end_effector_height_error, {"threshold_m": 0.25})):
        assert not fn(s, **kw).any()
    low = replace(s, body_pos_w=s.body_pos_w - torch.tensor([0.0, 0.0, 0.3]))
    assert terminations.anchor_height_error(low, 0.25).all()
    assert terminations.end_effector_height_error(low, 0.25).all()
    assert not terminations.anchor_height_error(_state(offset_m=0.6), 0.25).any()  # a lag is not a height error
    for offset, fires in ((0.0, False), (0.4, False), (0.6, True), (-0.6, True)):
        assert terminations.anchor_horizontal_error(_state(offset_m=offset), 0.5).tolist() == [fires] * 3
    # the reference torso is upright, so a roll r changes projected-gravity z by 1 − cos r:
    # 0.64 at 1.2 rad (kept), 0.93 at 1.5 rad (terminated)
    for roll, fires in ((1.2, False), (1.5, True)):
        tilt = quat_from_euler_xyz(torch.full((3,), roll), torch.zeros(3), torch.zeros(3))[:, None]
        tilted = replace(s, body_quat_w=quat_mul(tilt.expand_as(s.body_quat_w), s.body_quat_w))
        assert terminations.anchor_gravity_error(tilted, 0.8).tolist() == [fires] * 3


def test_observation_terms_have_the_spec_dimensions_and_are_zero_when_tracking_perfectly():
    s = _state()
    dims = {name: getattr(observations, name)(s).shape[-1] for name in
            ("command", "anchor_pos_b", "anchor_ori_b", "body_pos_b", "body_ori_b", "base_lin_vel_b",
             "base_ang_vel_b", "joint_pos_rel", "joint_vel", "last_action")}
    assert dims == {"command": 58, "anchor_pos_b": 3, "anchor_ori_b": 6, "body_pos_b": 42, "body_ori_b": 84,
                    "base_lin_vel_b": 3, "base_ang_vel_b": 3, "joint_pos_rel": 29, "joint_vel": 29, "last_action": 29}
    assert torch.allclose(observations.anchor_pos_b(s), torch.zeros(3, 3), atol=1e-6)
    identity_6d = torch.tensor([1.0, 0.0, 0.0, 1.0, 0.0, 0.0])
    assert torch.allclose(observations.anchor_ori_b(s), identity_6d.expand(3, 6), atol=1e-6)


def test_mpjpe_is_root_relative():
    assert torch.allclose(mpjpe_root_relative(_state(offset_m=0.5)), torch.zeros(3), atol=1e-6)
    s = _state()
    bent = s.body_pos_w.clone()
    bent[:, TRACKED.index("left_wrist_yaw_link")] += torch.tensor([0.0, 0.0, 0.14])
    assert torch.allclose(mpjpe_root_relative(replace(s, body_pos_w=bent)), torch.full((3,), 0.01), atol=1e-6)


def test_anchor_offset_is_split_along_the_reference_heading_and_ignores_height():
    s = _state(n=3)
    q = s.ref_anchor_quat_w
    # yaw (wxyz)
    heading = torch.atan2(2 * (q[:, 0] * q[:, 3] + q[:, 1] * q[:, 2]), 1 - 2 * (q[:, 2] ** 2 + q[:, 3] ** 2))
    forward = torch.stack([torch.cos(heading), torch.sin(heading), torch.zeros(3)], -1)
    left = torch.stack([-torch.sin(heading), torch.cos(heading), torch.zeros(3)], -1)
    # the robot 20 cm behind its reference, 5 cm to its left and 30 cm higher
    moved = s.body_pos_w + (-0.2 * forward + 0.05 * left + torch.tensor([0.0, 0.0, 0.3]))[:, None]
    shifted = replace(s, body_pos_w=moved)
    offset = anchor_offset_heading_m(shifted)
    assert torch.allclose(offset, torch.tensor([-0.2, 0.05]).expand(3, 2), atol=1e-5)
    assert torch.allclose(offset.norm(dim=-1), anchor_horizontal_error_m(shifted), atol=1e-6)
    assert torch.allclose(anchor_offset_heading_m(s), torch.zeros(3, 2), atol=1e-6)


def test_mpjpe_charges_heading_drift_and_its_heading_aligned_diagnostic_does_not():
    turned = _state(offset_m=0.5, yaw_rad=0.3)
    assert (mpjpe_root_relative(turned) > 0.03).all()
    assert torch.allclose(mpjpe_root_relative_heading_aligned(turned), torch.zeros(3), atol=1e-5)
    s = _state()
    bent = s.body_pos_w.clone()
    bent[:, TRACKED.index("left_wrist_yaw_link")] += torch.tensor([0.0, 0.0, 0.14])
    posture = mpjpe_root_relative_heading_aligned(replace(s, body_pos_w=bent))
    assert torch.allclose(posture, torch.full((3,), 0.01), atol=1e-6)
