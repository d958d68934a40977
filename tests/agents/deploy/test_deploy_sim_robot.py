"""The sim robot's physics and message content, without the transport."""

from __future__ import annotations

import numpy as np
import pytest

from agents.deploy import crc
from agents.deploy.messages import JointCommand, robot_state
from agents.deploy.safety import STARTUP_KD, STARTUP_KP
from agents.deploy.sim_robot import SimRobot, SimRobotCfg, pd_torque, quat_to_rpy
from otr_gym import robot
from otr_gym.rotations import quat_from_euler_xyz


def hold(q=None) -> JointCommand:
    return JointCommand(q=robot.DEFAULT_JOINT_POS.copy() if q is None else q, dq=np.zeros(29), kp=STARTUP_KP,
                        kd=STARTUP_KD, tau=np.zeros(29))


def test_the_motor_law_is_pd_plus_feedforward_clipped_to_effort():
    cmd = JointCommand(q=np.full(29, 1.0), dq=np.full(29, 0.5), kp=np.full(29, 10.0), kd=np.full(29, 2.0),
                       tau=np.full(29, 0.25))
    tau = pd_torque(cmd, np.full(29, 0.9), np.zeros(29))
    np.testing.assert_allclose(tau, 0.25 + 10 * 0.1 + 2 * 0.5)
    big = pd_torque(JointCommand(cmd.q * 100, cmd.dq, cmd.kp, cmd.kd, cmd.tau), np.zeros(29), np.zeros(29))
    np.testing.assert_allclose(big, robot.EFFORT_LIMIT)


def test_lowstate_carries_joints_imu_wxyz_body_gyro_and_specific_force():
    sim = SimRobot(SimRobotCfg(yaw_rad=0.3))
    for _ in range(250):  # 0.5 s standing under the start-up gains
        sim.step(hold())
    msg = sim.low_state()
    assert crc.crc_ok(msg) and msg.tick == 500
    s = robot_state(msg)
    d = sim.data
    np.testing.assert_allclose(s.joint_pos, d.qpos[7:36], atol=1e-6)
    np.testing.assert_allclose(s.quat_wxyz, d.qpos[3:7], atol=1e-6)
    np.testing.assert_allclose(s.gyro_b, d.qvel[3:6], atol=1e-5)  # free-joint angular velocity is body frame
    assert abs(s.accel_b[2] - 9.81) < 0.5  # at rest the accelerometer reads +g along the pelvis z
    rpy = np.array(msg.imu_state.rpy)
    assert abs(rpy[2] - 0.3) < 0.02
    np.testing.assert_allclose(quat_to_rpy(quat_from_euler_xyz(0.1, -0.2, 0.3)), [0.1, -0.2, 0.3], atol=1e-9)


def test_startup_gains_hold_the_default_pose_and_zero_torque_falls():
    held, limp = SimRobot(SimRobotCfg()), SimRobot(SimRobotCfg())
    for _ in range(1000):  # 2 s
        held.step(hold())
        limp.step(None)
    assert held.pelvis_height() > 0.7 and held.torso_tilt() < 0.1
    assert limp.pelvis_height() < 0.5


def test_the_gantry_holds_a_limp_robot_then_lowers_it():
    sim = SimRobot(SimRobotCfg(gantry=True))
    for _ in range(1000):  # 2 s hanging, no torque, no command yet: it keeps hanging
        sim.step(None)
    assert sim.pelvis_height() > 0.6
    sim.release_gantry_in(0.5)
    for _ in range(200):
        sim.step(None)
    assert sim.pelvis_height() > 0.6
    for _ in range(1000):  # lowered over 1 s, then let go with no torque: it sinks
        sim.step(None)
    assert sim.pelvis_height() < 0.5


def test_the_reference_objects_are_simulated_as_the_box_environment_builds_them(box_reference):
    """The generated box clip: a 20 cm box on the floor 0.6 m ahead (it ends on a table)."""
    from agents.deploy.sim_robot import initial_pose, object_summary, sim_objects
    from envs.box import make_box_task
    from otr_gym.reference import Reference

    scene, condim, goals = sim_objects(str(box_reference))
    sim = SimRobot(SimRobotCfg(), initial_pose(str(box_reference)), None, scene, condim)
    assert [o.name for o in sim.moving] == ["box"]
    (table,) = [o for o in scene.objects if o.static]
    assert table.name == "table" and sim.model.body(table.body).jntnum[0] == 0  # fixed
    sim.object_goals = goals
    ref = Reference.load(box_reference)
    np.testing.assert_allclose(sim.object_poses()[0, :3], ref.objects[0].pos_w[0], atol=1e-9)
    # the same collision geometry, mass and friction as the environment's model
    env = make_box_task(str(box_reference), 1, "mujoco", "cpu", evaluation=True).backend.model
    box = scene.moving[0].body
    for m in (sim.model, env):
        assert m.body(box).geomnum[0] == env.body(box).geomnum[0]
    np.testing.assert_allclose(sim.model.body(box).mass, env.body(box).mass)
    g_sim, g_env = sim.model.body(box).geomadr[0], env.body(box).geomadr[0]
    np.testing.assert_allclose(sim.model.geom_size[g_sim], env.geom_size[g_env])
    np.testing.assert_allclose(sim.model.geom_friction[g_sim], env.geom_friction[g_env])
    trace = []
    for k in range(500):  # 1 s holding the default pose: the box rests on the floor
        sim.step(hold())
        if k % 10 == 0:
            trace.append(sim.object_poses())
    assert abs(sim.object_poses()[0, 2] - ref.objects[0].pos_w[0, 2]) < 0.003
    np.testing.assert_allclose(goals["box"][:3], ref.objects[0].pos_w[-1])
    summary = object_summary(sim, np.array(trace))["box"]
    end = np.linalg.norm(ref.objects[0].pos_w[-1] - sim.object_poses()[0, :3])
    assert summary["end_error_m"] == pytest.approx(end) and end > 0.5  # on the floor, not on the table
    assert summary["mass_kg"] == scene.moving[0].mass_kg


def test_sim_robot_refuses_a_malformed_object_mesh_option(box_reference):
    from agents.deploy.sim_robot import sim_objects

    with pytest.raises(ValueError, match="NAME=FILE"):
        sim_objects(str(box_reference), ["box"])


def test_name_value_options_parse_one_way_with_errors_naming_flag_and_item():
    from agents.deploy.mocap import name_map
    from agents.deploy.options import name_values, positive_float

    assert name_values(["box=2.5", "lid = 0.5"], "--object-mass", "NAME=KG", "box=2.5", positive_float) == \
        {"box": 2.5, "lid": 0.5}
    assert name_values(None, "--object-mass", "NAME=KG", "box=2.5") == {}
    assert name_map(["largebox=box_1"]) == {"largebox": "box_1"}  # --mocap-name goes through the same parser
    for items, match in ((["box"], r"--object-mass 'box': expected NAME=KG \(e.g. box=2.5\)"),
                         (["=2"], "expected NAME=KG"), (["box="], "expected NAME=KG"),
                         (["box=-1"], r"--object-mass 'box=-1': -1 must be a finite number > 0"),
                         (["box=0"], "must be a finite number > 0"), (["box=nan"], "must be a finite number > 0"),
                         (["box=heavy"], "'heavy' is not a number"),
                         (["box=1", "box=2"], "'box' is given twice")):
        with pytest.raises(ValueError, match=match):
            name_values(items, "--object-mass", "NAME=KG", "box=2.5", positive_float)


def test_object_options_set_mass_and_friction_and_refuse_unknown_objects(box_reference):
    from agents.deploy.sim_robot import initial_pose, object_properties, sim_objects

    scene, condim, _ = sim_objects(str(box_reference))
    assert object_properties(scene) == {}  # nominal: nothing to change
    props = object_properties(scene, {"box": 2.5}, {"box": 0.6})
    assert props["box"].mass_kg == 2.5 and props["box"].friction == 0.6 and props["box"].inertia_scale == 1.0
    nominal = SimRobot(SimRobotCfg(), initial_pose(str(box_reference)), None, scene, condim)
    sim = SimRobot(SimRobotCfg(), initial_pose(str(box_reference)), None, scene, condim, props)
    body = sim.model.body("object/box").id
    assert sim.model.body_mass[body] == 2.5
    # uniform density: the inertia scales with the mass
    np.testing.assert_allclose(sim.model.body_inertia[body], nominal.model.body_inertia[body] * 2.5 / 1.0)
    geoms = sim.model.geom_bodyid == body
    np.testing.assert_allclose(sim.model.geom_friction[geoms, 0], 0.6)
    np.testing.assert_allclose(sim.model.geom_friction[~geoms], nominal.model.geom_friction[~geoms])
    with pytest.raises(ValueError, match=r"--object-mass: lid is not a moving object of the reference "
                                         r"\(moving: box; static, not changed: table\)"):
        object_properties(scene, {"lid": 1.0})
    with pytest.raises(ValueError, match="--object-friction: table is not a moving object"):
        object_properties(scene, frictions={"table": 0.5})
    with pytest.raises(ValueError, match="--object-draw: the reference has no moving objects"):
        object_properties(None, draw_seed=0)
    # --env-set: the box config the policy was trained with, as its run's --set env.KEY=VALUE
    from agents.deploy.sim_robot import sim_box_config

    heavier, _, _ = sim_objects(str(box_reference), cfg=sim_box_config(None, ["objects.mass_kg=2"]))
    assert heavier.moving[0].mass_kg == 2.0
    with pytest.raises(ValueError, match=r"--env-set objects.nope=1: .*unknown keys \['nope'\]"):
        sim_box_config(None, ["objects.nope=1"])


def test_object_draws_are_the_training_envs_randomisation(box_reference):
    """``--object-draw SEED`` gives the box the mass, inertia and friction the box env's
    randomisation (``randomize_objects``, configs/env/box.yaml's ranges) gives one env from the
    same generator, and the draws over many seeds fill those ranges."""
    import torch

    from agents.deploy.sim_robot import initial_pose, object_properties, sim_objects
    from envs.box import make_box_task
    from envs.config import load_box_config
    from envs.mdp.randomization import randomize_objects

    ranges = load_box_config().objects.randomization
    scene, condim, _ = sim_objects(str(box_reference))
    task = make_box_task(str(box_reference), 1, "mujoco", "cpu", evaluation=True)
    env = task.backend.world_model(0)
    body = env.body("object/box").id
    for seed in (0, 3):
        drawn = randomize_objects(task.backend, ["object/box"], [scene.moving[0].mass_kg], ranges,
                                  torch.Generator().manual_seed(seed))["object/box"][0].tolist()
        props = object_properties(scene, draw_seed=seed)["box"]
        assert (props.friction, props.mass_kg, props.inertia_scale) == tuple(drawn) and props.source == "drawn"
        sim = SimRobot(SimRobotCfg(), initial_pose(str(box_reference)), None, scene, condim, {"box": props})
        assert sim.model.body("object/box").id == body
        np.testing.assert_allclose(sim.model.body_mass[body], env.body_mass[body], rtol=1e-12)
        # the env scales the inertia in float32 (scale · mass / nominal), the sim robot in float64
        np.testing.assert_allclose(sim.model.body_inertia[body], env.body_inertia[body], rtol=1e-6)
        geoms = np.flatnonzero(env.geom_bodyid == body)
        np.testing.assert_allclose(sim.model.geom_friction[geoms], env.geom_friction[geoms], rtol=1e-12)
    # an explicit mass wins over the draw, the drawn friction and inertia scale stay
    over = object_properties(scene, {"box": 4.0}, draw_seed=3)["box"]
    assert over.mass_kg == 4.0 and over.friction == props.friction and over.source == "drawn, mass set"
    draws = np.array([[p.friction, p.mass_kg, p.inertia_scale] for seed in range(200)
                      for p in [object_properties(scene, draw_seed=seed, randomization=ranges)["box"]]])
    nominal = scene.moving[0].mass_kg
    for column, (lo, hi) in enumerate((ranges.friction_range, np.add(ranges.mass_add_kg, nominal),
                                       ranges.inertia_scale)):
        assert lo <= draws[:, column].min() < lo + 0.05 * (hi - lo)
        assert hi - 0.05 * (hi - lo) < draws[:, column].max() <= hi
    assert len({tuple(r) for r in draws}) == 200


def test_the_default_start_pose_stands_where_the_reference_starts(walking_reference):
    """``--start-pose default``: the default pose at the first frame's x, y and heading."""
    from agents.deploy.sim_robot import initial_pose
    from otr_gym.reference import Reference
    from otr_gym.rotations import quat_yaw

    ref = Reference.load(walking_reference)
    q = initial_pose(str(walking_reference), default_pose=True)
    np.testing.assert_array_equal(q[7:], robot.DEFAULT_JOINT_POS)
    np.testing.assert_array_equal(q[:3], [*ref.root_pos_w[0, :2], robot.default_qpos()[2]])
    np.testing.assert_allclose(q[3:7], quat_yaw(ref.root_quat_w[0]), atol=1e-12)
    np.testing.assert_array_equal(initial_pose(str(walking_reference))[7:], ref.dof_pos[0])
