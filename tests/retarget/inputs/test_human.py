"""The human body (mannequin-x parts), the part <-> G1 tables, T-poses and alignment offsets."""

from __future__ import annotations

import numpy as np
import pytest
from mannequin import Mannequin
from scipy.spatial import cKDTree

from otr_gym import robot
from otr_gym.robot_geometry import posed_vertices as g1_posed_vertices
from otr_gym.robot_geometry import visual_meshes
from otr_gym.rotations import quat_apply, quat_error_angle, quat_from_rotvec, quat_mul, quat_to_matrix, quat_to_rotvec
from retarget.inputs.human import (
    G1_LINK_PARTS,
    PART_NAMES,
    PART_PARENTS,
    SMPLX_REST_QUAT_W,
    STYLE_LINKS,
    HumanModel,
    alignment_offsets,
    fit_shape,
    forward_kinematics,
    g1_tpose_body_poses,
    g1_tpose_qpos,
    human_tpose,
    part_index,
    shape_basis,
)


def _random_pose(rng, frames: int):
    return (rng.normal(scale=0.8, size=(frames, 3)), rng.normal(scale=0.5, size=(frames, 3)),
            rng.normal(scale=0.4, size=(frames, 21, 3)))


def _style_targets(part_quat_w: np.ndarray) -> dict[str, np.ndarray]:
    offsets = alignment_offsets()
    return {link: quat_mul(part_quat_w[..., part_index([part])[0], :], offsets[link])
            for link, part in STYLE_LINKS.items()}


@pytest.fixture(scope="module")
def model() -> HumanModel:
    return HumanModel()


def test_parts_are_the_22_smplx_body_joints_of_mannequin_x():
    figure = Mannequin("convex", lod=0)
    assert PART_NAMES == figure.joint_names[:22]
    assert PART_PARENTS == figure.parents[:22]


def test_surface_splits_all_80_hulls_and_merges_fingers_into_the_wrists(model):
    surface = model.surface
    counts = np.array([len(v) for v in surface.vertices])
    assert counts.sum() == Mannequin("convex", lod=0).num_vertices == 5466
    assert counts.min() > 50
    wrist_hull_only = 72  # the L_Wrist hull alone; the 15 finger hulls add ~530 vertices
    assert counts[PART_NAMES.index("L_Wrist")] > 7 * wrist_hull_only
    for v, f in zip(surface.vertices, surface.faces, strict=True):
        assert f.min() == 0 and f.max() == len(v) - 1  # every vertex used, none out of range


def test_posed_surface_equals_mannequin_x_vertices_for_random_poses(model):
    rng = np.random.default_rng(3)
    orient, transl, body = _random_pose(rng, 4)
    pos, quat = model.pose(orient, transl, body)
    ours = model.posed_vertices(pos, quat)
    figure = Mannequin("convex", lod=0, shape=model.shape.astype(np.float32))
    pose = figure.rest_pose(batch_dims=(4,), dtype=np.float64)
    pose.update(global_rotation=orient, global_translation=transl, body_pose=body)
    reference = figure.vertices(pose)
    for frame in range(4):
        gap, _ = cKDTree(reference[frame]).query(ours[frame])
        back, _ = cKDTree(ours[frame]).query(reference[frame])
        assert max(gap.max(), back.max()) < 1e-9


def test_global_rotation_turns_the_body_about_the_smplx_origin(model):
    """mannequin-x / body-models semantics: pelvis = R_g J0 + transl."""
    orient = np.array([[0.0, 0.0, np.pi / 2]])
    pos, _ = model.pose(orient, np.zeros((1, 3)), np.zeros((1, 21, 3)))
    expected = quat_apply(quat_from_rotvec(orient[0]), model.rest_joints[0])
    np.testing.assert_allclose(pos[0, 0], expected, atol=1e-6)


def test_forward_kinematics_from_world_orientations_reproduces_pose(model):
    pos, quat = model.pose(*_random_pose(np.random.default_rng(4), 6))
    np.testing.assert_allclose(model.forward_kinematics(quat, pos[:, 0]), pos, atol=1e-6)


def test_shape_basis_is_the_affine_map_of_mannequin_x_skeleton():
    beta = np.random.default_rng(5).normal(size=10)
    figure = Mannequin("convex", lod=0)
    zeros = np.zeros
    reference = figure.forward_skeleton(zeros((21, 3)), zeros((3, 3)), zeros((30, 3)), shape=beta)[:22, :3, 3]
    np.testing.assert_allclose(shape_basis().joints(beta), reference, atol=1e-5)


def test_fit_shape_recovers_a_known_shape_and_translation_exactly_without_ridge():
    rng = np.random.default_rng(6)
    truth = HumanModel(rng.normal(scale=0.8, size=10))
    pos, quat = truth.pose(*_random_pose(rng, 30))
    fit = fit_shape(pos, quat, ridge_m2=0.0)
    np.testing.assert_allclose(fit.shape, truth.shape, atol=1e-3)
    np.testing.assert_allclose(fit.pelvis_pos_w, pos[:, 0], atol=1e-5)
    assert fit.joint_error_m.max() < 1e-5


def test_fit_shape_with_default_ridge_stays_within_a_millimetre():
    rng = np.random.default_rng(7)
    truth = HumanModel(rng.normal(scale=0.8, size=10))
    pos, quat = truth.pose(*_random_pose(rng, 30))
    assert fit_shape(pos, quat).joint_error_m.mean() < 1e-3


def test_fit_shape_rejects_wrong_shapes_and_nan():
    with pytest.raises(ValueError, match=r"\(T, 22, 3\)"):
        fit_shape(np.zeros((5, 21, 3)), np.zeros((5, 21, 4)))
    joints = np.zeros((2, 22, 3))
    joints[1, 3, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        fit_shape(joints, np.tile([1.0, 0, 0, 0], (2, 22, 1)))


def test_human_model_rejects_bad_shape_and_pose_arrays():
    with pytest.raises(ValueError, match=r"\(10,\)"):
        HumanModel(np.zeros(16))
    with pytest.raises(ValueError, match="NaN"):
        HumanModel(np.full(10, np.nan))
    with pytest.raises(ValueError, match="body_pose_aa"):
        HumanModel().pose(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 23, 3)))


def test_mean_shape_stature_is_about_1p72_m_and_grows_with_the_first_coefficient(model):
    assert 1.70 < model.stature_m < 1.75
    assert HumanModel(np.eye(10)[0] * 2.0).stature_m > model.stature_m + 0.05


def test_human_tpose_stands_on_the_ground_facing_plus_x(model):
    pos, quat = human_tpose(model)
    vertices = model.posed_vertices(pos[None], quat[None])[0]
    assert vertices[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(pos[0, :2], 0.0, atol=1e-12)
    assert pos[PART_NAMES.index("L_Wrist"), 1] > 0.6 > -0.6 > pos[PART_NAMES.index("R_Wrist"), 1]
    toes, ankle = pos[PART_NAMES.index("L_Foot")], pos[PART_NAMES.index("L_Ankle")]
    assert toes[0] - ankle[0] > 0.08  # the feet point forward (+x)
    head, pelvis = pos[PART_NAMES.index("Head")], pos[0]
    assert head[2] - pelvis[2] > 0.5


def test_g1_tpose_has_straight_horizontal_arms_and_soles_on_the_ground():
    qpos = g1_tpose_qpos()
    assert qpos.shape == (36,)
    np.testing.assert_allclose(qpos[3:7], [1.0, 0.0, 0.0, 0.0])
    pos, quat = g1_tpose_body_poses()
    index = {n: i for i, n in enumerate(robot.BODY_NAMES)}
    for side, sign in (("left", 1.0), ("right", -1.0)):
        chain = pos[[index[f"{side}_shoulder_yaw_link"], index[f"{side}_elbow_link"], index[f"{side}_wrist_yaw_link"]]]
        assert np.ptp(chain[:, 2]) < 0.01  # horizontal
        assert np.all(sign * np.diff(chain[:, 1]) > 0.07)  # reaching sideways
        assert np.abs(chain[:, 0]).max() < 0.02
    meshes = visual_meshes()
    lowest = min(g1_posed_vertices(meshes[b], pos[i], quat[i])[:, 2].min()
                 for i, b in enumerate(robot.BODY_NAMES) if b in meshes)
    assert lowest == pytest.approx(0.0, abs=1e-9)


def test_style_targets_at_the_tpose_equal_the_g1_tpose_orientations(model):
    _, human_quat = human_tpose(model)
    _, g1_quat = g1_tpose_body_poses()
    for link, target in _style_targets(human_quat).items():
        assert quat_error_angle(target, g1_quat[robot.BODY_NAMES.index(link)]) < 1e-6, link


def test_style_targets_turn_with_the_human(model):
    _, human_quat = human_tpose(model)
    _, g1_quat = g1_tpose_body_poses()
    yaw = quat_from_rotvec(np.array([0.0, 0.0, 1.1]))
    turned = quat_mul(np.broadcast_to(yaw, human_quat.shape), human_quat)
    for link, target in _style_targets(turned).items():
        expected = quat_mul(yaw, g1_quat[robot.BODY_NAMES.index(link)])
        assert quat_error_angle(target, expected) < 1e-6, link


def test_standing_human_with_arms_down_gives_upright_g1_trunk_and_flat_feet(model):
    body = np.zeros((1, 21, 3))
    body[0, PART_NAMES.index("L_Shoulder") - 1] = [0.0, 0.0, -1.2]  # arms down
    body[0, PART_NAMES.index("R_Shoulder") - 1] = [0.0, 0.0, 1.2]
    # AMASS-like: a z-up world, subject facing +x, then turned by 0.7 rad of yaw
    root = quat_mul(quat_from_rotvec(np.array([0.0, 0.0, 0.7])), SMPLX_REST_QUAT_W)
    _, quat = model.pose(quat_to_rotvec(root)[None], np.zeros((1, 3)), body)
    targets = _style_targets(quat[0])
    for link in ("pelvis", "torso_link", "left_ankle_roll_link", "right_ankle_roll_link",
                 "left_knee_link", "right_knee_link"):
        z_axis = quat_to_matrix(targets[link])[:, 2]
        assert np.degrees(np.arccos(z_axis[2])) < 10.0, link
    heading = quat_to_matrix(targets["pelvis"])[:, 0]
    assert np.degrees(np.arccos(heading @ [np.cos(0.7), np.sin(0.7), 0.0])) < 5.0


def test_g1_link_table_covers_every_g1_body_with_a_visual_mesh_and_every_part():
    assert set(G1_LINK_PARTS) == set(visual_meshes())
    used = {part for parts in G1_LINK_PARTS.values() for part in parts}
    assert used == set(PART_NAMES)
    assert set(STYLE_LINKS) <= set(robot.BODY_NAMES)
    assert set(STYLE_LINKS.values()) <= set(PART_NAMES)
    assert set(alignment_offsets()) == set(STYLE_LINKS)


def test_demonstration_surface_poses_like_the_model(model):
    pos, quat = model.pose(*_random_pose(np.random.default_rng(8), 3))
    np.testing.assert_allclose(model.surface.posed_vertices(pos, quat), model.posed_vertices(pos, quat))
    lowest = model.surface.lowest_z(pos, quat)
    np.testing.assert_allclose(lowest, model.posed_vertices(pos, quat)[..., 2].min(axis=-1), atol=1e-12)


def test_forward_kinematics_is_batched_over_leading_axes(model):
    pos, quat = model.pose(*_random_pose(np.random.default_rng(9), 6))
    batched = forward_kinematics(quat.reshape(2, 3, 22, 4), pos[:, 0].reshape(2, 3, 3), model.rest_joints)
    np.testing.assert_allclose(batched.reshape(6, 22, 3), pos, atol=1e-6)
