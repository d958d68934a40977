"""Dynamic feasibility of references (retarget.checks.feasibility) on generated G1 motions whose
answers are known: a standing robot, a hover, a ballistic flight, an elbow faster than its
motor, a sliding stance, a teleport, a robot sunk into the floor, a hand on the floor, and
torques checked against MuJoCo's inverse dynamics."""

from __future__ import annotations

import json

import mujoco
import numpy as np
import pytest

from otr_gym import cli, robot
from otr_gym.reference import Reference
from otr_gym.rotations import quat_from_euler_xyz
from retarget.checks.feasibility import (
    GRAVITY,
    FeasibilityCfg,
    check_feasibility,
    format_report,
)

from conftest import lowest_collision_reach

FPS = 50.0
ELBOW = robot.JOINT_NAMES.index("left_elbow_joint")


def _clip(frames: int = 50) -> np.ndarray:
    """(frames, 36) qpos of the default standing pose, feet flat on the floor."""
    return np.tile(robot.default_qpos(), (frames, 1))


def _ref(qpos: np.ndarray) -> Reference:
    return Reference.from_qpos(qpos, FPS)


@pytest.fixture(scope="module")
def standing():
    return check_feasibility(_ref(_clip()))


def test_standing_still_is_feasible_and_the_feet_carry_the_weight(standing):
    r = standing
    # the floor carries the whole weight, shared by the feet; nothing is left to the pelvis
    np.testing.assert_allclose(r.foot_force_w[:, :, 2].sum(axis=1), r.weight_n, rtol=1e-6)
    np.testing.assert_allclose(r.foot_force_w[:, 0, 2], r.foot_force_w[:, 1, 2], rtol=0.02)
    assert r.unsupported_fraction.max() < 1e-6
    assert r.weight_n == pytest.approx(33.34 * GRAVITY, rel=1e-3)  # the G1 MJCF's mass
    assert r.stance.all() and not r.flight.any()
    assert np.nanmax(r.slide_speed_mps) < 1e-9
    assert r.torque_ratio.max() < 0.25 and r.joint_speed_ratio.max() < 1e-9
    assert r.intervals == [] and r.hardest() == []
    assert r.penetration_m.max() < 1e-3  # the soles on the floor, not in it
    assert format_report(r).endswith("no frame reaches a limit")
    assert r.flagged_share() == 0.0 and r.verdict() == "verdict: feasible (no frame of 50 reaches a limit)"


def test_a_hover_is_a_flight_with_the_whole_weight_unsupported():
    qpos = _clip(40)
    qpos[:, 2] += 0.5
    r = check_feasibility(_ref(qpos))
    assert r.flight_phases() == [(0, 39)]
    assert r.summary()["flight"]["durations_s"] == [pytest.approx(40 / FPS)]
    assert r.summary()["flight"]["unsupported_mean_fraction"] == [pytest.approx(1.0)]
    assert "not ballistic in the air" in format_report(r) and "100% of weight" in format_report(r)
    # at rest in the air: the base wrench is exactly the weight, and no foot can supply it
    np.testing.assert_allclose(r.unsupported_fraction, 1.0, rtol=1e-9)
    assert r.foot_force_w.max() == 0.0
    assert all("unsupported" in h.reasons and "flight" in h.reasons for h in r.hardest())


def test_a_ballistic_flight_needs_no_support():
    t = np.arange(30) / FPS
    qpos = _clip(30)
    qpos[:, 2] += 0.5 + 2.5 * t - 0.5 * GRAVITY * t**2  # thrown up at 2.5 m/s, 0.3 m up or more throughout
    qpos[:, 0] += 1.5 * t
    r = check_feasibility(_ref(qpos))
    assert r.flight.all()
    # free fall of a rigid pose: the centre of mass accelerates at g, no external force needed
    assert r.unsupported_fraction.max() < 0.01
    assert r.summary()["flight"]["unsupported_mean_fraction"][0] < 0.01
    assert r.torque_ratio.max() < 0.01
    # flight is no limit in itself: a thrown body is feasible, its frames in the air named
    assert r.intervals == [] and r.flagged_share() == 0.0
    assert r.verdict() == "verdict: feasible (no frame of 30 reaches a limit; 30 frames in the air)"


def test_an_elbow_faster_than_its_motor_is_named_with_its_speed_ratio():
    qpos = _clip()
    # 40 rad/s for three frames (0.8 rad per 1/50 s), the 5020's limit is 37 rad/s
    start = robot.JOINT_LOWER[ELBOW] + 0.05
    ramp = start + 0.8 * np.clip(np.arange(50) - 20, 0, 3)
    qpos[:, 7 + ELBOW] = ramp
    r = check_feasibility(_ref(qpos))
    summary = r.summary()["joint_speed"]
    assert summary["joint"] == "left_elbow_joint"
    assert summary["peak_ratio"] == pytest.approx(40.0 / robot.VELOCITY_LIMIT[ELBOW], rel=1e-9)
    over = np.flatnonzero(r.joint_speed_ratio[:, ELBOW] >= 1.0)
    assert over.tolist() == [21, 22]  # central differences: the two frames inside the ramp
    assert "left_elbow" in r.reasons(21)["joint speed"] and "left_elbow" in r.reasons(22)["joint speed"]
    # the ramp's corners (0 → 40 rad/s in one frame) also throw the hand off its path
    hard = r.hardest()
    assert 20 <= hard[0].frame <= 23 and hard[0].reasons["limb jump"].startswith("left hand ")


def test_a_stance_foot_that_slides_is_measured_and_flagged():
    qpos = _clip()
    qpos[:, 0] += 0.1 * np.arange(50) / FPS  # the standing robot glides at 10 cm/s
    r = check_feasibility(_ref(qpos))
    np.testing.assert_allclose(r.slide_speed_mps, 0.1, rtol=1e-9)
    assert r.summary()["stance_sliding"]["frames_over"] == 50
    assert "sliding" in r.hardest()[0].reasons


def test_a_teleport_shows_as_a_pelvis_jump_on_both_sides():
    qpos = _clip()
    qpos[25:, 1] += 0.10  # 10 cm sideways in one frame
    r = check_feasibility(_ref(qpos))
    np.testing.assert_allclose(r.root_jump_m[[24, 25]], 0.05, rtol=1e-9)
    assert np.delete(r.root_jump_m, [24, 25]).max() < 1e-12
    hard = r.hardest()
    assert hard[0].frame in (24, 25) and hard[0].start <= 24 and hard[0].stop >= 25
    assert "jump" in hard[0].reasons


def test_a_foot_that_snaps_for_one_frame_is_a_limb_jump_not_a_pelvis_jump():
    """The left knee bent 0.6 rad for frame 25 only: the pelvis stays, the left foot leaves the
    line of its neighbours by its whole excursion there and by half of it on either side."""
    qpos = _clip()
    qpos[25, 7 + robot.JOINT_NAMES.index("left_knee_joint")] += 0.6
    r = check_feasibility(_ref(qpos))
    foot = r.limb_jump_m[:, 0]
    ref = _ref(qpos)
    i = ref.body_index(["left_ankle_roll_link"])[0]
    excursion = np.linalg.norm(ref.body_pos_w[25, i] - ref.body_pos_w[24, i])
    assert excursion > 0.1  # a real snap: ~16 cm
    assert foot[25] == pytest.approx(excursion, rel=1e-6)
    np.testing.assert_allclose(foot[[24, 26]], excursion / 2, rtol=1e-6)
    assert np.delete(foot, [24, 25, 26]).max() < 1e-9 and r.limb_jump_m[:, 1:].max() < 1e-9
    assert r.root_jump_m.max() < 1e-12
    assert r.reasons(25)["limb jump"].startswith("left foot ") and "jump" not in r.reasons(25)
    assert r.hardest()[0].frame in (24, 25, 26)  # the foot also slides there (it stays near the floor)
    summary = r.summary()["limb_jump"]
    assert summary["limb"] == "left foot" and summary["frames_over"] == 3
    # the verdict counts every limit reached, the most-reached first
    over = r.frames_over()
    assert over["limb jump"] == 3 and over["jump"] == 0
    assert r.flagged_share() == pytest.approx((r.severity() >= 1).sum() / 50)
    counts = r.verdict().split("over a limit: ")[1].split(", ")
    assert "limb jump 3" in counts and [int(c.rsplit(" ", 1)[1]) for c in counts] == sorted(
        (n for n in over.values() if n), reverse=True)
    assert "limb jumps (feet, hands)" in format_report(r)


def test_a_robot_sunk_into_the_floor_is_flagged_by_its_soles_depth():
    """Sunk 5 and 8 cm (the standing soles sit 3 mm above the floor): the depths differ by the
    3 cm, the soles are what is deepest, and every frame is flagged."""
    depth = {}
    for sink in (0.05, 0.08):
        qpos = _clip(20)
        qpos[:, 2] -= sink
        depth[sink] = r = check_feasibility(_ref(qpos))
        assert set(r.penetration_link) <= set(robot.FEET)
        assert r.summary()["penetration"]["frames_over"] == 20
    np.testing.assert_allclose(depth[0.08].penetration_m - depth[0.05].penetration_m, 0.03, atol=1e-9)
    r = depth[0.05]
    assert 0.045 < r.penetration_m[0] <= 0.05
    cm = f"{100 * r.penetration_m[10]:.1f} cm"
    assert r.reasons(10)["penetration"].endswith(f"{cm} into the ground")
    assert f"collision geometry in the ground deepest {cm}" in format_report(r)


def test_a_robot_lying_face_down_in_the_floor_names_its_deepest_link():
    """Pitched 120° forward and lowered until MuJoCo puts its lowest collision geometry 4 cm below
    z = 0: the check finds the same depth at the same link (a capsule's lowest point, not a sole)."""
    pose = robot.default_qpos()
    pose[3:7] = quat_from_euler_xyz(0.0, np.deg2rad(120.0), 0.0)
    lowest, body = lowest_collision_reach(pose)
    pose[2] -= lowest + 0.04
    assert body == "torso_link"  # 8 cm lower than any other link's geometry in this pose
    r = check_feasibility(_ref(np.tile(pose, (10, 1))))
    np.testing.assert_allclose(r.penetration_m, 0.04, atol=2e-3)
    assert set(r.penetration_link) == {body}


def test_a_hand_carries_weight_on_its_boxes_not_on_the_retargeters_capsule():
    """Pitched face down, the left arm reaching for the floor with the palm turned to it: the
    hand's boxes (what the simulation collides) reach 1.9 cm lower than the retargeter's coarse
    hand capsule (contype 0) and lower than every other link. With the boxes 1 cm above the floor
    the hand is on the ground and pushes (the capsule is then 2.9 cm up, beyond the 2-cm contact
    height: it alone would not count); raised to 2.5 cm, nothing touches."""
    from otr_gym.robot_geometry import collision_capsules

    pose = robot.default_qpos()
    pose[3:7] = quat_from_euler_xyz(0.0, np.deg2rad(90.0), 0.0)
    for joint, angle in (("left_shoulder_pitch", -1.2), ("left_elbow", 0.6), ("left_wrist_roll", 1.5),
                         ("left_wrist_pitch", -1.0)):
        pose[7 + robot.JOINT_NAMES.index(f"{joint}_joint")] = angle
    lowest, body = lowest_collision_reach(pose)
    assert body == "left_wrist_yaw_link"
    model = mujoco.MjModel.from_xml_path(str(robot.G1_MJCF))
    data = mujoco.MjData(model)
    (capsule,) = [c for c in collision_capsules() if c.name == "left_hand_collision"]
    for height, on_ground in ((0.01, True), (0.025, False)):
        qpos = pose.copy()
        qpos[2] += height - lowest
        data.qpos[:] = qpos
        mujoco.mj_kinematics(model, data)
        b = model.body(capsule.body).id
        capsule_low = min((data.xpos[b] + data.xmat[b].reshape(3, 3) @ p)[2] for p in (capsule.p0, capsule.p1))
        assert capsule_low - capsule.radius > FeasibilityCfg().contact_height_m
        r = check_feasibility(_ref(np.tile(qpos, (10, 1))))
        if on_ground:
            assert r.other_support.all()
            assert (r.other_force_w[:, 2] > 0.05 * r.weight_n).all()
        else:
            assert not r.other_support.any() and not r.other_force_w.any()


def test_torques_match_mujoco_inverse_dynamics_of_the_same_motion():
    """Hovering (no contact) with every joint on a parabola: central differences are exact,
    so the joint torques must equal MuJoCo's ``mj_inverse`` (armature included) and the
    unsupported force the norm of its free-joint force."""
    frames = 40
    tau = np.arange(frames) / (frames - 1) - 0.5  # normalised time in [-0.5, 0.5]
    qpos = _clip(frames)
    qpos[:, 2] += 0.6
    mid = 0.5 * (robot.JOINT_LOWER + robot.JOINT_UPPER)
    half = 0.45 * (robot.JOINT_UPPER - robot.JOINT_LOWER)
    rng = np.random.default_rng(0)
    c1, c2 = rng.uniform(-0.9, 0.9, (2, robot.NUM_JOINTS))  # |c1|/2 + |c2|/4 < 1: inside the limits
    qpos[:, 7:] = mid + half * (c1 * tau[:, None] + c2 * tau[:, None] ** 2)
    r = check_feasibility(_ref(qpos), FeasibilityCfg(lowpass_hz=None))
    assert np.abs(r.torque_nm).max() > 5.0  # not a trivially small comparison

    model = mujoco.MjModel.from_xml_path(str(robot.G1_MJCF))
    model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT  # random poses may touch themselves
    data = mujoco.MjData(model)
    for f in (5, 20, 34):
        data.qpos[:] = qpos[f]
        data.qvel[:] = 0.0
        data.qvel[6:] = (qpos[f + 1, 7:] - qpos[f - 1, 7:]) * FPS / 2
        data.qacc[:] = 0.0
        data.qacc[6:] = (qpos[f + 1, 7:] - 2 * qpos[f, 7:] + qpos[f - 1, 7:]) * FPS**2
        mujoco.mj_inverse(model, data)
        assert not data.qfrc_constraint.any()
        np.testing.assert_allclose(r.torque_nm[f], data.qfrc_inverse[6:], atol=1e-6)
        assert r.unsupported_force_n[f] == pytest.approx(np.linalg.norm(data.qfrc_inverse[:3]), rel=1e-6)


def test_verify_prints_the_section_and_writes_picture_and_summary(tmp_path, capsys):
    qpos = _clip()
    qpos[25:, 1] += 0.10
    path = _ref(qpos).save(tmp_path / "teleport.npz")
    png, js = tmp_path / "feasibility.png", tmp_path / "feasibility.json"
    assert cli.main(["verify", str(path), "--feasibility-png", str(png), "--feasibility-json", str(js)]) == 0
    out = capsys.readouterr().out
    assert "dynamic feasibility at 50 fps" in out and "hardest frames" in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = json.loads(js.read_text())
    # the verdict ends the output; the teleport's two frames are over the pelvis-jump limit (its
    # low-passed acceleration also leaves the base unsupported around them)
    assert out.rstrip().splitlines()[-1] == summary["verdict"]
    assert summary["verdict"].startswith(f"verdict: {summary['flagged_frames']} of 50 frames")
    assert "jump 2" in summary["verdict"].split(": ", 2)[2].split(", ")
    assert summary["flagged_frames"] > 0 and summary["flagged_share"] == pytest.approx(summary["flagged_frames"] / 50)
    assert summary["frames_over"]["jump"] == 2
    assert summary["jump"]["peak_m"] == pytest.approx(0.05)
    assert summary["hardest"][0]["frame"] in (24, 25)
    assert summary["penetration"]["peak_m"] < 1e-3 and summary["penetration"]["frames_over"] == 0


def _held_box(mass_kg: float):
    """A standing robot that holds a box between its hands from frame 20 on (the box rests 0.5 m
    lower, away from the hands, before): the check with the box at ``mass_kg``."""
    from otr_gym.reference import ObjectTrack
    from retarget.geometry.dynamics import ObjectMass, hand_points

    qpos = _clip()
    hands = hand_points(robot.qpos_mujoco_to_pinocchio(qpos))  # (T, 2, 3)
    centre = hands.mean(axis=1)
    pos = centre.copy()
    pos[:20, 2] -= 0.5
    verts = np.concatenate([hands[0] - centre[0], [[0.0, 0.0, -0.1]]])
    zeros = np.zeros_like(pos)
    box = ObjectTrack("box", pos, np.tile([1.0, 0, 0, 0], (50, 1)), zeros, zeros, verts, np.array([[0, 1, 2]]))
    ref = Reference.from_qpos(qpos, FPS, objects=[box])
    return check_feasibility(ref, FeasibilityCfg(object_mass=ObjectMass(mass_kg)))


def test_a_carried_box_weighs_on_the_hands_and_the_feet_carry_it():
    held, light = _held_box(3.0), _held_box(0.0)
    # held, at rest (frames after the lift; the 6 Hz filter's ringing fades): each hand carries half its weight
    np.testing.assert_allclose(held.object_load_w[35:45], np.tile([[0, 0, -1.5 * GRAVITY]] * 2, (10, 1, 1)),
                               rtol=0.01, atol=1e-9)
    assert not held.object_load_w[:15].any()  # on the floor, away from the hands: no load
    np.testing.assert_allclose(held.foot_force_w[35:45, :, 2].sum(axis=1), held.weight_n + 3.0 * GRAVITY, rtol=0.01)
    shoulder = robot.JOINT_NAMES.index("left_shoulder_pitch_joint")
    assert np.abs(held.torque_nm[40, shoulder]) > np.abs(light.torque_nm[40, shoulder]) + 0.5
    assert not light.object_load_w.any()


def test_verify_refuses_a_negative_object_mass(tmp_path, capsys):
    path = _ref(_clip(10)).save(tmp_path / "stand.npz")
    assert cli.main(["verify", str(path), "--object-mass-kg", "-1"]) == 2
    assert "--object-mass-kg -1" in capsys.readouterr().err


def test_the_lowpass_is_scipys_butterworth_filtfilt_bit_for_bit():
    """``lowpass`` computes ``filtfilt(*butter(2, wn), x, axis=0)`` without importing
    scipy.signal (its import is ~1 s of a retarget run's start): the same bits, for any cut-off
    and the array shapes the callers pass (twists (T, nv), positions (T, 3), (T, k, 3))."""
    from scipy.signal import butter, filtfilt

    from retarget.geometry.dynamics import butter2, lowpass

    rng = np.random.default_rng(0)
    for wn in np.concatenate([rng.uniform(0.01, 0.99, 500), [0.1, 0.2, 0.4, 0.5]]):
        b, a = butter(2, wn)
        b2, a2 = butter2(wn)
        assert np.array_equal(b, b2) and np.array_equal(a, a2), wn
    for trial in range(60):
        fps, cutoff = float(rng.choice([30.0, 50.0, 60.0, 120.0])), float(rng.uniform(1.0, 14.0))
        shape = [(int(rng.integers(16, 400)),), (int(rng.integers(16, 400)), 35), (int(rng.integers(16, 60)), 4, 3)]
        x = rng.normal(size=shape[trial % 3]) * 10.0 ** rng.uniform(-3, 2)
        expected = filtfilt(*butter(2, cutoff / (0.5 * fps)), x, axis=0)
        assert np.array_equal(lowpass(x, cutoff, fps), expected), (trial, x.shape)
    short, long = rng.normal(size=(15, 3)), rng.normal(size=(40, 3))
    assert lowpass(short, 5.0, 50.0) is short and lowpass(long, None, 50.0) is long  # too short, off
