"""Motion capture as a deployment input: the IDL, the tracker's velocities and faults, the box
task's motion-capture actor rebuilt from captured poses, and the controller's safety rules."""

from __future__ import annotations

import re
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.deploy.controller import Controller, ControllerCfg, CycleInput
from agents.deploy.messages import RobotState
from agents.deploy.mocap import (
    BASE_BODY,
    MocapFault,
    MocapFrame,
    MocapFrame_,
    MocapTracker,
    MocapTrackerCfg,
    RigidBodyPose_,
    mocap_frame,
    mocap_message,
    name_map,
)
from agents.deploy.observation import MOCAP, BaseEstimate, ObjectEstimate, ObservationBuilder, PolicySpec
from agents.deploy.reference_policy import training_metadata
from agents.deploy.safety import SafetyCfg, Stage
from otr_gym import robot
from otr_gym.rotations import quat_from_rotvec, quat_mul

IDL = Path(__file__).resolve().parents[3] / "agents" / "deploy" / "idl" / "otr_mocap.idl"
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def frame(seq: int, t_s: float, bodies: dict[str, tuple]) -> MocapFrame:
    names = tuple(bodies)
    return MocapFrame(int(round(t_s * 1e9)), seq, names,
                      np.array([np.asarray(bodies[n][0], float) for n in names]).reshape(-1, 3),
                      np.array([np.asarray(bodies[n][1], float) for n in names]).reshape(-1, 4))


# ------------------------------------------------------------------ the message
def test_the_idl_file_declares_the_python_types_fields_in_order():
    text = IDL.read_text()
    for cls in (RigidBodyPose_, MocapFrame_):
        name = cls.__name__
        body = re.search(rf"struct {name} \{{(.*?)\}};", text, re.S).group(1)
        declared = re.findall(r"\s(\w+)(?:\[\d+\])?;", re.sub(r"//.*", "", body))
        assert declared == [f.name for f in fields(cls)], name
        assert f"@final\n      struct {name}" in text
    assert "string<32> name" in text and "sequence<RigidBodyPose_, 32> bodies" in text


def test_a_frame_survives_the_wire_and_bad_frames_are_refused_before_sending():
    f = frame(7, 1.5, {"pelvis": ([0.1, -0.2, 0.8], [0.9, 0.1, 0.0, 0.0]), "largebox": ([1, 2, 3], IDENTITY)})
    back = mocap_frame(MocapFrame_.deserialize(mocap_message(f).serialize()))
    assert back.names == f.names and back.seq == 7 and back.stamp_ns == f.stamp_ns
    np.testing.assert_array_equal(back.pos_w, f.pos_w)
    np.testing.assert_array_equal(back.quat_wxyz, f.quat_wxyz)
    with pytest.raises(ValueError, match="at most 32 bytes"):
        mocap_message(frame(0, 0.0, {"x" * 40: ([0, 0, 0], IDENTITY)}))
    assert name_map(["largebox=box_1"]) == {"largebox": "box_1"}
    with pytest.raises(ValueError, match="--mocap-name 'largebox': expected POLICY=STREAM"):
        name_map(["largebox"])


# ------------------------------------------------------------------ the tracker
def test_velocities_are_the_slope_over_the_window_of_captured_frames():
    """A body moving at 0.5 m/s and turning at 1 rad/s about z, captured at 100 Hz with 1 mm of
    noise and read every 20 ms: the velocities within 0.05 m/s and 0.05 rad/s (one frame's finite
    difference would be off by ~0.1 m/s with this noise)."""
    rng = np.random.default_rng(0)
    tracker = MocapTracker(MocapTrackerCfg(bodies=(BASE_BODY,), required=(BASE_BODY,)))
    v, w = np.array([0.5, -0.1, 0.0]), np.array([0.0, 0.0, 1.0])
    diffs = []
    for k in range(100):
        t = 0.01 * k
        pos = v * t + rng.normal(0.0, 0.001, 3)
        tracker.update(frame(k, t, {BASE_BODY: (pos, quat_from_rotvec(w * t))}) if k % 2 == 0 else None)
        if k > 20 and k % 2 == 0:
            diffs.append(np.linalg.norm(np.diff([h[1][0] for h in list(tracker.history)[-2:]], axis=0)) / 0.02)
            m = tracker.motion()
            assert np.linalg.norm(m.lin_vel_w[0] - v) < 0.05 and np.linalg.norm(m.ang_vel_w[0] - w) < 0.05
    assert np.std(diffs) > 0.05  # the noise a one-frame difference would pass on


def test_the_tracker_names_a_stale_stream_a_nan_pose_and_a_body_it_does_not_carry():
    cfg = MocapTrackerCfg(bodies=(BASE_BODY, "largebox", "chair"), required=(BASE_BODY, "largebox"),
                          names={"largebox": "box_1"}, stale_cycles=3)
    tracker = MocapTracker(cfg)
    assert tracker.current_fault()[0] == MocapFault.STALE  # nothing yet
    good = {"pelvis": ([0, 0, 0.8], IDENTITY), "box_1": ([1, 0, 0.1], IDENTITY)}
    tracker.update(frame(1, 0.0, good))
    assert tracker.current_fault() is None  # "chair" is followed but not read by the policy: NaN there
    assert np.isnan(tracker.motion().pos_w[2]).all() and np.isfinite(tracker.motion().pos_w[:2]).all()
    for _ in range(2):
        tracker.update(frame(1, 0.0, good))  # the same frame again is no new frame
    assert tracker.current_fault() is None
    tracker.update(None)
    assert tracker.current_fault() == (MocapFault.STALE, "no new mocap frame for 3 cycles")
    tracker.update(frame(2, 0.02, {**good, "box_1": ([np.nan, 0, 0.1], IDENTITY)}))
    assert tracker.current_fault() == (MocapFault.NAN, "the mocap pose of largebox is not finite (or not a unit "
                                                       "quaternion) in frame 2")
    tracker.update(frame(3, 0.04, {"pelvis": ([0, 0, 0.8], IDENTITY), "box": ([1, 0, 0.1], IDENTITY)}))
    kind, message = tracker.current_fault()
    assert kind == MocapFault.MISSING_BODY
    assert "carries ['pelvis', 'box'], not largebox (as 'box_1')" in message and "--mocap-name" in message


# ------------------------------------------------------------------ the observation
def test_the_mocap_box_actor_equals_the_training_envs_from_captured_poses(box_reference):
    """OTR-G1-BoxTrack-v0's ``mocap`` actor (the robot's world position and velocity, the box's
    and the table's pose relative to it): rebuilt from the LowState plus what motion capture
    measures (the pelvis pose and velocity, the box pose), it equals the env's observation."""
    from envs.box import make_box_task

    env = {"observations": {"actor": "mocap"}}
    meta = training_metadata(box_reference, "OTR-G1-BoxTrack-v0", env)
    names = [t["name"] for t in meta["observation_layout"]]
    assert {"anchor_pos_b", "base_lin_vel_b", "object_pos_b", "static_object_pos_b"} <= set(names)
    from envs.config import load_box_config

    task = make_box_task(box_reference, 1, "mujoco", "cpu", cfg=load_box_config(None, env), evaluation=True)
    task.reset()
    builder = ObservationBuilder(PolicySpec.from_metadata(meta, "meta"), box_reference, frozenset({MOCAP}))
    box = task.backend.model.body(f"object/{builder.objects.names[0]}").jntadr[0]
    qadr, vadr = task.backend.model.jnt_qposadr[box], task.backend.model.jnt_dofadr[box]
    rng = np.random.default_rng(0)
    for step in range(40):
        obs = task.step(torch.as_tensor(rng.normal(0, 0.02, (1, 29)), dtype=torch.float32))[0] if step else \
            task.observations(task.state)
        qpos, qvel = task.backend.qpos[0].numpy().astype(float), task.backend.qvel[0].numpy().astype(float)
        lowstate = RobotState(joint_pos=qpos[7:36], joint_vel=qvel[6:35], quat_wxyz=qpos[3:7], gyro_b=qvel[3:6],
                              accel_b=np.zeros(3), tick_ms=0, mode_machine=5, remote_keys=0)
        base = BaseEstimate(qpos[:3], qvel[:3], qpos[3:7])  # the free joint's linear velocity is in the world
        objects = ObjectEstimate(qpos[None, qadr:qadr + 3], qpos[None, qadr + 3:qadr + 7],
                                 qvel[None, vadr:vadr + 3], qvel[None, vadr + 3:vadr + 6])
        frame_ = int(task.command.frame[0])
        s = builder.tracking_state(lowstate, frame_, task.action[0].numpy(), base, objects)
        np.testing.assert_allclose(builder.observation(s), obs["policy"][0].numpy(), atol=5e-5,
                                   err_msg=f"step {step}, frame {frame_}")


# ------------------------------------------------------------------ the controller
@pytest.fixture(scope="module")
def mocap_spec(box_reference):
    return PolicySpec.from_metadata(training_metadata(box_reference, "OTR-G1-BoxTrack-v0",
                                                      {"observations": {"actor": "mocap"}}), "mocap.onnx")


def standing(q=None) -> RobotState:
    return RobotState(joint_pos=robot.DEFAULT_JOINT_POS.copy() if q is None else q, joint_vel=np.zeros(29),
                      quat_wxyz=IDENTITY.copy(), gyro_b=np.zeros(3), accel_b=np.array([0, 0, 9.81]), tick_ms=0,
                      mode_machine=5, remote_keys=0)


def controller(spec, reference, names=None):
    builder = ObservationBuilder(spec, reference, frozenset({MOCAP}))
    cfg = ControllerCfg(SafetyCfg(ramp_s=0.04, blend_s=0.0, end_hold_s=0.0), auto_start=True,
                        mocap_names={} if names is None else names)
    return Controller(spec, builder, lambda obs: np.zeros(29, np.float32), cfg)


def scene(seq: int, t: float, shift=(0.0, 0.0), **replace) -> MocapFrame:
    """The robot 0.7 m above (x, y) = shift and the box 0.6 m ahead of it, as the capture sees them."""
    dx, dy = shift
    bodies = {"pelvis": ([dx, dy, 0.75], IDENTITY), "box": ([dx + 0.6, dy, 0.1], IDENTITY)}
    bodies.update(replace)
    return frame(seq, t, bodies)


@pytest.mark.parametrize("fault", ["stale", "nan", "unknown"])
def test_a_stream_that_cannot_feed_the_policy_damps_the_robot_with_a_message(mocap_spec, box_reference, fault):
    c = controller(mocap_spec, box_reference)
    outs = [c.step(CycleInput(0.02 * k, standing(), mocap=scene(k, 0.02 * k))) for k in range(6)]
    assert outs[-1].stage == Stage.TRACK and outs[-1].action is not None
    assert np.isfinite(outs[-1].observation).all()
    for k in range(6, 12):
        if fault == "stale":
            m = None
        elif fault == "nan":
            m = scene(k, 0.02 * k, box=([np.nan, 0.0, 0.1], IDENTITY))
        else:
            m = frame(k, 0.02 * k, {"pelvis": ([0, 0, 0.75], IDENTITY), "crate": ([0.6, 0, 0.1], IDENTITY)})
        out = c.step(CycleInput(0.02 * k, standing(), mocap=m))
        if out.stage == Stage.DAMP:
            break
    assert out.stage == Stage.DAMP and out.command.kp.max() == 0.0
    reason = {"stale": MocapFault.STALE, "nan": MocapFault.NAN, "unknown": MocapFault.MISSING_BODY}[fault]
    assert c.stages.damp_reason == reason
    assert k == (8 if fault == "stale" else 6)  # stale: the 3rd cycle without a frame
    expected = {"stale": "no new mocap frame for 3 cycles", "nan": "the mocap pose of box is not finite",
                "unknown": "carries ['pelvis', 'crate'], not box that the policy needs"}[fault]
    assert expected in c.fault_detail


def test_without_a_frame_tracking_never_starts_and_a_mapped_name_feeds_the_policy(mocap_spec, box_reference):
    c = controller(mocap_spec, box_reference)
    for k in range(4):
        out = c.step(CycleInput(0.02 * k, standing()))
    assert out.stage == Stage.DAMP and c.stages.damp_reason == MocapFault.STALE
    assert c.fault_detail == "no mocap frame has arrived"
    c = controller(mocap_spec, box_reference, names={"box": "box_1"})
    for k in range(6):
        m = frame(k, 0.02 * k, {"pelvis": ([2.0, 1.0, 0.75], IDENTITY), "box_1": ([2.6, 1.0, 0.1], IDENTITY)})
        out = c.step(CycleInput(0.02 * k, standing(), mocap=m))
    assert out.stage == Stage.TRACK
    # the clip is shifted onto the robot standing at (2, 1): its box (reference 0.6 m ahead) is met
    np.testing.assert_allclose(c.builder.offset_w[:2], [2.0, 1.0], atol=0.05)
    assert out.object_error_m is not None and out.object_error_m[0] < 0.05


def test_a_turned_capture_world_turns_the_clip_with_it(mocap_spec, box_reference):
    """The capture's heading is its own: 90° about z, the robot at (0, 0) facing +y, the box
    0.6 m ahead of it at (0, 0.6): the reference's box (0.6 m ahead in its frame) lands on it."""
    turn = quat_from_rotvec(np.array([0.0, 0.0, np.pi / 2]))
    c = controller(mocap_spec, box_reference)
    state = standing()
    state = RobotState(**{**state.__dict__, "quat_wxyz": turn})
    for k in range(6):
        m = frame(k, 0.02 * k, {"pelvis": ([0.0, 0.0, 0.75], turn), "box": ([0.0, 0.6, 0.1], quat_mul(turn, IDENTITY))})
        out = c.step(CycleInput(0.02 * k, state, mocap=m))
    assert out.stage == Stage.TRACK and out.object_error_m[0] < 0.05


def test_a_nan_capture_is_kept_in_the_log_and_replays_to_the_same_fault(mocap_spec, box_reference, tmp_path):
    """Nothing is lost from the log: the frame with the NaN pose is recorded as captured (NaN
    there, the body present), the damping and its message are saved, and the recorded inputs
    drive a fresh controller into the same fault on the same cycle."""
    from agents.deploy.log import CycleLog, DeployLog

    c = controller(mocap_spec, box_reference)
    log = CycleLog(mocap_spec.observation_dim, {"period_ns": 20_000_000}, c.mocap)
    for k in range(9):
        m = scene(k, 0.02 * k, box=([np.nan, 0.0, 0.1], IDENTITY)) if k == 7 else scene(k, 0.02 * k)
        inp = CycleInput(0.02 * k, standing(), mocap=m)
        log.append(inp, c.step(inp), k, k, k)
    assert c.stage == Stage.DAMP
    saved = DeployLog.load(log.save(tmp_path / "run", c.stages.transitions, c.fault_detail))
    a = saved.arrays
    assert a["mocap_fresh"].all() and a["mocap_present"].all()
    assert np.isnan(a["mocap_pos"][7, 1, 0]) and np.isfinite(a["mocap_pos"][6]).all()
    assert a["stage"][7] == Stage.DAMP and a["stage"][6] == Stage.TRACK
    assert "the mocap pose of box is not finite" in saved.meta["fault_detail"]
    assert saved.transitions()[-1][1:] == ("TRACK", "DAMP", MocapFault.NAN)
    again = controller(mocap_spec, box_reference)
    stages = [again.step(inp).stage for inp in saved.inputs()]
    np.testing.assert_array_equal(stages, a["stage"])
