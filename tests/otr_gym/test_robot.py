"""The G1 model and its specification: one MJCF, loaded by MuJoCo and Pinocchio alike."""

from __future__ import annotations

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from otr_gym import robot
from otr_gym.robot_geometry import collision_capsules, visual_meshes
from otr_gym.rotations import matrix_to_quat, quat_error_angle, quat_from_rotvec
from otr_gym.scene import ObjectSpec, SceneSpec, TableSpec, build_scene, robot_model


@pytest.fixture(scope="module")
def mj_model():
    return robot_model(visual=True)


def random_qpos(rng: np.random.Generator, n: int) -> np.ndarray:
    q = np.empty((n, 36))
    q[:, :3] = rng.uniform(-1, 1, (n, 3))
    q[:, 3:7] = quat_from_rotvec(rng.normal(size=(n, 3)))
    q[:, 7:] = rng.uniform(robot.JOINT_LOWER, robot.JOINT_UPPER, (n, 29))
    return q


def test_mujoco_and_pinocchio_give_the_same_body_poses_for_random_configurations(mj_model):
    pmodel = robot.load_pinocchio_model()
    pdata = pmodel.createData()
    mdata = mujoco.MjData(mj_model)
    rng = np.random.default_rng(0)
    worst_pos, worst_rot = 0.0, 0.0
    for q in random_qpos(rng, 50):
        mdata.qpos[:] = q
        mujoco.mj_kinematics(mj_model, mdata)
        pin.framesForwardKinematics(pmodel, pdata, robot.qpos_mujoco_to_pinocchio(q))
        for name in robot.BODY_NAMES:
            oMf = pdata.oMf[pmodel.getFrameId(name, pin.BODY)]
            b = mj_model.body(name).id
            worst_pos = max(worst_pos, np.abs(oMf.translation - mdata.xpos[b]).max())
            worst_rot = max(worst_rot, quat_error_angle(matrix_to_quat(oMf.rotation), mdata.xquat[b]))
    assert worst_pos <= 1e-6
    assert worst_rot <= 1e-6


def test_joint_and_body_order_of_the_mjcf_is_the_spec_order(mj_model):
    joints = [mj_model.joint(i).name for i in range(1, mj_model.njnt)]
    bodies = [mj_model.body(i).name for i in range(1, mj_model.nbody)]
    assert tuple(joints) == robot.JOINT_NAMES
    assert tuple(bodies) == robot.BODY_NAMES
    assert [mj_model.actuator(i).trnid[0] for i in range(mj_model.nu)] == list(range(1, 30))


def test_gains_follow_the_reflected_inertia_derivation_of_the_rl_spec():
    # docs/environment.md §1 table: kp, kd, armature, action scale for hip_pitch, knee, ankle, shoulder, wrist_pitch
    expected = {
        "left_hip_pitch_joint": (40.179, 2.558, 0.010178, 0.5475),
        "left_knee_joint": (99.098, 6.309, 0.025102, 0.3507),
        "left_ankle_pitch_joint": (28.501, 1.814, 0.007219, 0.4386),
        "waist_roll_joint": (28.501, 1.814, 0.007219, 0.4386),
        "left_shoulder_pitch_joint": (14.251, 0.907, 0.003610, 0.4386),
        "right_wrist_pitch_joint": (16.778, 1.068, 0.00425, 0.0745),
    }
    for name, (kp, kd, arm, scale) in expected.items():
        i = robot.JOINT_NAMES.index(name)
        assert robot.KP[i] == pytest.approx(kp, abs=1e-3)
        assert robot.KD[i] == pytest.approx(kd, abs=1e-3)
        assert robot.ARMATURE[i] == pytest.approx(arm, abs=1e-6)
        assert robot.ACTION_SCALE[i] == pytest.approx(scale, abs=1e-4)


def test_mjcf_actuators_apply_the_spec_pd_law(mj_model):
    for i in range(len(robot.JOINT_NAMES)):
        assert mj_model.actuator_gainprm[i, 0] == pytest.approx(robot.KP[i], rel=1e-6)
        assert mj_model.actuator_biasprm[i, 1] == pytest.approx(-robot.KP[i], rel=1e-6)
        assert mj_model.actuator_biasprm[i, 2] == pytest.approx(-robot.KD[i], rel=1e-6)
        assert mj_model.actuator_forcerange[i, 1] == pytest.approx(robot.EFFORT_LIMIT[i])
        assert mj_model.dof_armature[6 + i] == pytest.approx(robot.ARMATURE[i], rel=1e-6)
        assert tuple(mj_model.jnt_range[1 + i]) == pytest.approx((robot.JOINT_LOWER[i], robot.JOINT_UPPER[i]))
    assert mj_model.opt.timestep == 0.005


def test_default_keyframe_is_the_knees_bent_pose_with_feet_on_the_ground():
    model = build_scene(SceneSpec()).model
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    assert np.allclose(data.qpos, robot.default_qpos())
    foot_geoms = [g for g in range(model.ngeom) if "foot" in model.geom(g).name]
    sole = min(data.geom_xpos[g, 2] - model.geom_size[g, 0] for g in foot_geoms)
    assert abs(sole) < 0.02  # soles within 2 cm of the ground in the default pose


def test_assets_stay_within_10_mb_and_keep_the_unitree_licence():
    g1 = robot.G1_MJCF.parent
    total = sum(p.stat().st_size for p in robot.ASSETS_DIR.rglob("*") if p.is_file())
    assert total <= 10_000_000  # error-bounded meshes (tools/build_g1_assets.py): 8.4 MB
    assert "BSD 3-Clause" in (g1 / "LICENSE").read_text()


def test_every_link_has_a_visual_mesh_and_collision_capsules_cover_limbs():
    meshes = visual_meshes()
    assert set(meshes) == set(robot.BODY_NAMES)
    assert 1.5 < sum(m.area_m2 for m in meshes.values()) < 3.0  # whole G1 surface, m²
    bodies = {c.body for c in collision_capsules()}
    for limb in ("left_knee_link", "right_elbow_link", "left_wrist_yaw_link", "torso_link", "pelvis"):
        assert limb in bodies


def test_scene_composes_robot_ground_table_and_objects_with_robot_qpos_first():
    scene = build_scene(SceneSpec(table=TableSpec(pos=(1.2, 0.0, 0.75)),
                                  objects=(ObjectSpec("box", box_half_extents=(0.2, 0.17, 0.15), pos=(0.6, 0, 0.15)),)))
    m = scene.model
    assert m.nq == 36 + 7 and m.nu == 29
    data = mujoco.MjData(m)
    mujoco.mj_forward(m, data)
    top = m.geom("table/table_top").id
    assert data.geom_xpos[top, 2] + m.geom_size[top, 2] == pytest.approx(0.75)
    assert m.body("box").id > m.body("torso_link").id


def test_unknown_joint_and_body_names_are_named_in_the_error():
    with pytest.raises(KeyError, match="left_pinky_joint"):
        robot.joint_indices(["left_knee_joint", "left_pinky_joint"])
    with pytest.raises(KeyError, match="head_link"):
        robot.body_indices(["head_link"])
