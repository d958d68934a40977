"""The runner's observation is the training env's, rebuilt from the ONNX metadata and what a
LowState carries (joints, IMU), not from the simulator."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest
import torch

from agents.deploy.messages import RobotState
from agents.deploy.observation import ESTIMATOR, MOCAP, ObservationBuilder, PolicySpec, PolicySpecError
from agents.deploy.reference_policy import training_metadata, write_reference_policy
from envs.tracking import make_task
from otr_gym import robot


@pytest.fixture(scope="module")
def meta(walking_reference):
    return training_metadata(walking_reference)


def test_observation_equals_the_training_envs_from_the_lowstate_alone(walking_reference, meta):
    task = make_task(walking_reference, 1, "mujoco", "cpu", evaluation=True)
    task.reset()
    builder = ObservationBuilder(PolicySpec.from_metadata(meta, "meta"), walking_reference)
    rng = np.random.default_rng(0)
    obs = None
    for step in range(12):
        if step:
            obs = task.step(torch.as_tensor(rng.normal(0, 0.3, (1, 29)), dtype=torch.float32))[0]
        else:
            obs = task.observations(task.state)
        qpos, qvel = task.backend.qpos[0].numpy(), task.backend.qvel[0].numpy()
        lowstate = RobotState(joint_pos=qpos[7:], joint_vel=qvel[6:], quat_wxyz=qpos[3:7], gyro_b=qvel[3:6],
                              accel_b=np.zeros(3), tick_ms=0, mode_machine=5, remote_keys=0)
        frame = int(task.command.frame[0])
        s = builder.tracking_state(lowstate, frame, task.action[0].numpy())
        np.testing.assert_allclose(builder.observation(s), obs["policy"][0].numpy(), atol=2e-5,
                                   err_msg=f"step {step}, frame {frame}")
    assert frame == 12  # the env's target frame = the runner's (start 0 + 1 + steps)


def test_terms_the_robot_cannot_measure_are_refused_by_name_with_the_flag_that_feeds_them(meta, walking_reference):
    layout = [*meta["observation_layout"], {"name": "anchor_pos_b", "dim": 3, "start": 154}]
    spec = PolicySpec.from_metadata(dict(meta, observation_layout=layout), "p.onnx")
    with pytest.raises(PolicySpecError, match="anchor_pos_b need the robot's world position.*--mocap TOPIC"):
        ObservationBuilder(spec, walking_reference)
    ObservationBuilder(spec, walking_reference, frozenset({MOCAP}))  # a source: accepted
    forces = [*meta["observation_layout"], {"name": "object_contact_forces", "dim": 6, "start": 154}]
    with pytest.raises(PolicySpecError, match="object_contact_forces.*no deployment measures"):
        PolicySpec.from_metadata(dict(meta, observation_layout=forces), "p.onnx")


def test_metadata_with_another_joint_order_or_missing_fields_is_refused(meta):
    with pytest.raises(PolicySpecError, match="joint order"):
        PolicySpec.from_metadata(dict(meta, joint_names=list(reversed(meta["joint_names"]))), "p.onnx")
    without = {k: v for k, v in meta.items() if k != "joint_stiffness"}
    with pytest.raises(PolicySpecError, match="p.onnx: metadata lacks \\['joint_stiffness'\\]"):
        PolicySpec.from_metadata(without, "p.onnx")
    with pytest.raises(PolicySpecError, match="default_joint_pos"):
        PolicySpec.from_metadata(dict(meta, default_joint_pos=[0.0] * 28), "p.onnx")


def test_a_missing_policy_file_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.onnx"):
        PolicySpec.from_onnx(tmp_path / "nope.onnx")


def test_reference_policy_outputs_the_reference_joint_targets(tmp_path, walking_reference):
    path = write_reference_policy(tmp_path / "ref.onnx", walking_reference)
    spec = PolicySpec.from_onnx(path)
    np.testing.assert_array_equal(spec.kp[:6], [350, 200, 200, 300, 300, 150])  # start-up gains, documented
    builder = ObservationBuilder(spec, walking_reference)
    stand = RobotState(robot.DEFAULT_JOINT_POS.copy(), np.zeros(29), np.array([1.0, 0, 0, 0]), np.zeros(3),
                       np.zeros(3), 0, 5, 0)
    obs = builder.observation(builder.tracking_state(stand, 40, np.zeros(29)))
    action = ort.InferenceSession(str(path)).run(["actions"], {"obs": obs[None]})[0][0]
    q_ref = builder.motion.joint_pos[40].numpy()
    np.testing.assert_allclose(spec.default_joint_pos + spec.action_scale * action, q_ref, atol=1e-5)


def test_the_perception_free_box_actor_is_rebuilt_from_the_lowstate_and_the_reference(box_reference):
    """OTR-G1-BoxTrack-v0's default actor: the robot's own sensors, the reference's object
    command and contact schedule; the runner's observation equals the training env's."""
    from envs.box import make_box_task

    meta = training_metadata(box_reference, "OTR-G1-BoxTrack-v0")
    names = [t["name"] for t in meta["observation_layout"]]
    assert names[-2:] == ["object_command", "contact_schedule"] and "object_pos_b" not in names
    task = make_box_task(box_reference, 1, "mujoco", "cpu", evaluation=True)
    task.reset()
    builder = ObservationBuilder(PolicySpec.from_metadata(meta, "meta"), box_reference)
    rng = np.random.default_rng(0)
    gates = []
    for step in range(60):  # the box on the floor, then lifted off it (its reference leaves the floor)
        obs = task.step(torch.as_tensor(rng.normal(0, 0.02, (1, 29)), dtype=torch.float32))[0] if step else \
            task.observations(task.state)
        qpos, qvel = task.backend.qpos[0].numpy(), task.backend.qvel[0].numpy()
        lowstate = RobotState(joint_pos=qpos[7:36], joint_vel=qvel[6:35], quat_wxyz=qpos[3:7], gyro_b=qvel[3:6],
                              accel_b=np.zeros(3), tick_ms=0, mode_machine=5, remote_keys=0)
        frame = int(task.command.frame[0])
        s = builder.tracking_state(lowstate, frame, task.action[0].numpy())
        np.testing.assert_allclose(builder.observation(s), obs["policy"][0].numpy(), atol=2e-5,
                                   err_msg=f"step {step}, frame {frame}")
        gates.append(float(s.objects.support_gate.max()))
    assert max(gates) == 1.0 and min(gates) == 0.0  # compared with the floor window open and closed
    # the hand windows come later in the clip (frames 60-99) than a robot standing still keeps the
    # box within the object termination: the runner's gates are the env's on every frame
    torch.testing.assert_close(builder.objects.hand_gate, task.objects.hand_gate)
    assert builder.objects.hand_gate.max() == 1.0


def test_a_box_actor_that_observes_the_object_pose_is_refused_without_motion_capture(box_reference):
    meta = training_metadata(box_reference, "OTR-G1-BoxTrack-v0", {"observations": {"actor": "mocap"}})
    spec = PolicySpec.from_metadata(meta, "box.onnx")
    with pytest.raises(PolicySpecError, match="anchor_pos_b, base_lin_vel_b, object_pos_b, object_ori_b, "
                                              "static_object_pos_b, static_object_ori_b need .*object's pose.*"
                                              "--mocap TOPIC"):
        ObservationBuilder(spec, box_reference)
    with pytest.raises(PolicySpecError, match="object_pos_b, object_ori_b need the object's pose.*run with --mocap"):
        ObservationBuilder(spec, box_reference, frozenset({ESTIMATOR}))  # the robot's pose only


def test_the_reference_policy_takes_the_box_tasks_actors(tmp_path, box_reference, capsys):
    from otr_gym import cli

    out = tmp_path / "box.onnx"
    assert cli.main(["reference-policy", str(out), "--reference", str(box_reference), "--task",
                     "OTR-G1-BoxTrack-v0", "--box-actor", "mocap"]) == 0
    spec = PolicySpec.from_onnx(out)
    expected = training_metadata(box_reference, "OTR-G1-BoxTrack-v0", {"observations": {"actor": "mocap"}})
    assert [n for n, _ in spec.observation_layout] == [t["name"] for t in expected["observation_layout"]]
    assert "object_pos_b" in spec.needs() and spec.kp[0] == 350  # start-up gains: open loop needs them
    capsys.readouterr()
    assert cli.main(["reference-policy", str(tmp_path / "x.onnx"), "--box-actor", "mocap"]) == 2
    assert "--box-actor needs --task OTR-G1-BoxTrack-v0" in capsys.readouterr().err


def test_the_clip_turned_block_by_block_equals_the_clip_turned_at_once(box_reference):
    """``ObservationBuilder.align`` turns the reference a block of frames at a time, when first
    read (turning a whole clip took 12-20 ms of the cycle tracking starts on): every frame of
    every body and object array equals the whole clip turned and shifted at once, bit for bit."""
    from otr_gym.rotations import quat_apply, quat_mul, quat_yaw

    builder = ObservationBuilder(PolicySpec.from_metadata(training_metadata(box_reference, "OTR-G1-BoxTrack-v0"),
                                                          "meta"), box_reference)
    q = np.array([0.9, 0.1, -0.2, 0.37])
    delta, offset = quat_yaw(q / np.linalg.norm(q)), np.array([0.3, -1.2, 0.0])
    builder.align(delta, offset)
    d, off = torch.as_tensor(delta, dtype=torch.float32), torch.as_tensor(offset, dtype=torch.float32)
    m, o = builder.motion, builder.objects
    for aligned, source, kind in ((builder.ref_body_pos_w, m.body_pos_w, "pos"),
                                  (builder.ref_body_lin_vel_w, m.body_lin_vel_w, "vec"),
                                  (builder.ref_body_ang_vel_w, m.body_ang_vel_w, "vec"),
                                  (builder.ref_body_quat_w, m.body_quat_w, "quat"),
                                  (builder.ref_object_pos_w, o.pos_w, "pos"),
                                  (builder.ref_object_lin_vel_w, o.lin_vel_w, "vec"),
                                  (builder.ref_object_ang_vel_w, o.ang_vel_w, "vec"),
                                  (builder.ref_object_quat_w, o.quat_w, "quat")):
        whole = (quat_mul(d.expand_as(source), source) if kind == "quat" else
                 quat_apply(d.expand(*source.shape[:-1], 4), source) + (off if kind == "pos" else 0.0))
        assert len(aligned) == len(whole) > aligned.BLOCK
        assert torch.equal(aligned[len(whole) - 1], whole[-1]) and torch.equal(aligned[-1], whole[-1])
        assert torch.equal(aligned[7, -1], whole[7, -1])
        assert torch.equal(aligned.full(), whole)
    with pytest.raises(IndexError):
        builder.ref_body_pos_w[len(m.body_pos_w)]
