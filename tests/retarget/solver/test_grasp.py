"""The grasp pass (retarget.solver.grasp) on synthetic holds: a G1 with its arms forward and a box
on or between its hands, lifted 3 cm over the first frames."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
import trimesh

from otr_gym import robot
from otr_gym.reference import ObjectTrack, Reference
from retarget.checks.feasibility import check_feasibility
from retarget.solver import grasp
from retarget.solver.grasp import GraspCfg, box_signed_distance, grasp_boxes

FPS = 50.0
FRAMES = 40
HALF = np.array([0.12, 0.12, 0.12])


def _arms_forward() -> np.ndarray:
    """(36,) the default stance with both arms reaching forward (palms 0.415 m ahead, 1.01 m up,
    0.242 m apart)."""
    q = robot.default_qpos().copy()
    for side in ("left", "right"):
        q[7 + robot.JOINT_NAMES.index(f"{side}_shoulder_pitch_joint")] = -0.9
        q[7 + robot.JOINT_NAMES.index(f"{side}_elbow_joint")] = 0.6
    return q


def _held(centre: np.ndarray) -> Reference:
    """The arms-forward robot, still, and a 24-cm cube centred at ``centre`` lifted 3 cm over the
    first 10 frames."""
    mesh = trimesh.creation.box(extents=2 * HALF)
    pos = np.tile(centre, (FRAMES, 1)).astype(float)
    pos[:, 2] += 0.03 * np.clip(np.arange(FRAMES) / 10.0, 0.0, 1.0) - 0.03
    zeros = np.zeros((FRAMES, 3))
    box = ObjectTrack("box", pos, np.tile([1.0, 0, 0, 0], (FRAMES, 1)), zeros, zeros,
                      np.asarray(mesh.vertices), np.asarray(mesh.faces))
    return Reference.from_qpos(np.tile(_arms_forward(), (FRAMES, 1)), FPS, objects=[box])


def _geom_depths(ref: Reference, box_centre_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T,) deepest hand geom and (T,) deepest other kept-out geom inside the box (m, ≥ 0)."""
    mdl = grasp._model()
    data = mdl.pin_model.createData()
    q = robot.qpos_mujoco_to_pinocchio(ref.qpos())
    hands, others = np.zeros(len(q)), np.zeros(len(q))
    for t in range(len(q)):
        pin.framesForwardKinematics(mdl.pin_model, data, q[t])
        pos = np.array([data.oMf[f].translation for f, _, _ in mdl.points])
        d, _ = box_signed_distance(pos - box_centre_w[t], HALF)
        d -= np.array([r for _, r, _ in mdl.points])
        is_hand = np.array([k >= 0 for _, _, k in mdl.points])
        hands[t], others[t] = max(0.0, -d[is_hand].min()), max(0.0, -d[~is_hand].min())
    return hands, others


def _palms(ref: Reference) -> np.ndarray:
    """(T, 2, 3) the palms' inner surface centres (world)."""
    mdl = grasp._model()
    data = mdl.pin_model.createData()
    q = robot.qpos_mujoco_to_pinocchio(ref.qpos())
    out = np.empty((len(q), 2, 3))
    for t in range(len(q)):
        pin.framesForwardKinematics(mdl.pin_model, data, q[t])
        out[t] = [data.oMf[f].translation for f in mdl.palm_frames]
    return out


def test_signed_distance_to_a_box_and_its_gradient():
    half = np.array([0.1, 0.2, 0.3])
    x = np.array([[0.0, 0.0, 0.0], [0.15, 0.0, 0.0], [0.15, 0.25, 0.0], [0.05, -0.19, 0.1]])
    d, grad = box_signed_distance(x, half)
    np.testing.assert_allclose(d, [-0.1, 0.05, np.hypot(0.05, 0.05), -0.01], atol=1e-12)
    np.testing.assert_allclose(grad[3], [0.0, -1.0, 0.0])  # inside: the nearest face's normal
    h = 1e-7
    for i in (1, 2, 3):
        fd = [(box_signed_distance(x[i] + h * e, half)[0][0] - d[i]) / h for e in np.eye(3)]
        np.testing.assert_allclose(grad[i], fd, atol=1e-5)


@pytest.fixture(scope="module")
def from_below():
    """A box resting on the palms (bottom face 1 cm above them), the hands under its bottom edges."""
    ref = _held(np.array([0.40, 0.0, 1.014 + HALF[2] + 0.01]))
    return ref, *grasp_boxes(ref, GraspCfg())


def test_a_box_held_from_below_is_regripped_from_its_sides(from_below):
    ref, out, report = from_below
    assert len(report.holds) == 1 and report.holds[0]["axis"] == 1  # squeezed across y, the hands' separation
    centre = out.objects[0].pos_w
    held = slice(10, FRAMES - 1)  # the box off its start height, past the blend-in
    rel = _palms(out)[held] - centre[held, None]
    before = _palms(ref)[held] - centre[held, None]
    assert (before[:, :, 2] < -HALF[2]).all()  # the person's grip: under the bottom face
    # after: each palm at its own side face (left +y, right −y), outside it by less than the
    # curled fingers' reach, at mid height
    assert (rel[:, 0, 1] > HALF[1]).all() and (rel[:, 1, 1] < -HALF[1]).all()
    assert (np.abs(np.abs(rel[:, :, 1]) - HALF[1]) < 0.05).all()
    # antipodal: the squeeze axis (between the palms) passes near the centre and is the faces' normal
    limit = GraspCfg().centre_fraction * HALF
    mid = rel.mean(axis=1)
    # (within 2 cm of the grip point: the forearms' distances to the box, kept as they were, pull too)
    assert (np.abs(mid[:, [0, 2]]) <= limit[[0, 2]] + 0.02).all()
    axis = rel[:, 0] - rel[:, 1]
    cos = axis[:, 1] / np.linalg.norm(axis, axis=1)
    assert (cos > np.cos(np.arctan(0.8))).all()  # inside a friction cone of μ 0.8 at both faces
    hands, others = _geom_depths(out, centre)
    assert hands[held].max() <= GraspCfg().squeeze_m + 1e-3  # the squeeze, no deeper
    assert hands[held].min() >= GraspCfg().squeeze_m - 2e-3
    assert others[held].max() == 0.0
    assert out.metadata["grasp"]["squeeze_m"] == GraspCfg().squeeze_m


def test_the_regripped_box_is_carried_within_the_torque_limits(from_below):
    _, out, _ = from_below
    report = check_feasibility(out)  # a 3-kg box (ObjectMass's default) on the hands once lifted
    assert report.object_load_w[15:, :, 2].sum(axis=1) == pytest.approx(-3.0 * 9.81, rel=0.05)
    assert report.torque_ratio.max() <= 1.0


def test_a_torso_that_would_enter_the_box_is_kept_out():
    # the box's back face 1.6 cm inside the torso's collision capsule
    ref = _held(np.array([0.08 + HALF[0], 0.0, 1.0]))
    centre = ref.objects[0].pos_w
    _, others_before = _geom_depths(ref, centre)
    assert others_before.max() > 0.012
    out, report = grasp_boxes(ref, GraspCfg())
    assert len(report.holds) == 1
    _, others = _geom_depths(out, centre)
    assert others[10:].max() < 1e-3
    assert report.holds[0]["other_depth_m"] < 1e-3


def test_no_hold_leaves_the_reference_as_it_is():
    ref = _held(np.array([0.40, 0.0, 1.014 + HALF[2] + 0.01]))
    far = ref.objects[0]
    far.pos_w = far.pos_w + np.array([2.0, 0.0, 0.0])  # out of the hands' reach
    out, report = grasp_boxes(ref, GraspCfg())
    assert out is ref and report.holds == [] and "no two-hand hold" in report.line()


def test_a_grip_the_g1_can_make_already_is_kept():
    # a box between the palms, its side faces 5 mm inside the nearest point of each hand's
    # collision geoms, centred on the grip: the per-frame hands already squeeze it
    ref = _held(np.array([0.0, 0.0, 0.0]))
    mdl = grasp._model()
    data = mdl.pin_model.createData()
    pin.framesForwardKinematics(mdl.pin_model, data, robot.qpos_mujoco_to_pinocchio(ref.qpos()[:1])[0])
    left = min(data.oMf[f].translation[1] - r for f, r, k in mdl.points if k == 0)
    palms = np.array([data.oMf[f].translation for f in mdl.palm_frames])
    half = np.array([0.1, left + 0.005, 0.1])
    mesh = trimesh.creation.box(extents=2 * half)
    box = ref.objects[0]
    box.mesh_vertices, box.mesh_faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    box.pos_w = box.pos_w + np.array([palms[0, 0], 0.0, palms[0, 2] + 0.03])
    out, report = grasp_boxes(ref, GraspCfg())
    assert [h["kept"] for h in report.holds] == [True] and "kept" in report.line()
    assert out is ref


def test_a_finger_weight_turns_the_fingers_down_the_faces():
    """``finger_weight``: the hands' finger axes (link x) go to ``finger_b`` (here straight down),
    whatever the per-frame solution's turn of the hand about the face normal; off, they keep it."""
    ref = _held(np.array([0.40, 0.0, 1.014 + HALF[2] + 0.01]))
    held = slice(12, FRAMES - 1)

    def fingers(out: Reference) -> np.ndarray:
        mdl = grasp._model()
        data = mdl.pin_model.createData()
        q = robot.qpos_mujoco_to_pinocchio(out.qpos())
        axes = []
        for t in range(held.start, held.stop):
            pin.framesForwardKinematics(mdl.pin_model, data, q[t])
            axes.append([data.oMf[f].rotation[:, 0] for f in mdl.palm_frames])
        return np.array(axes)

    off, _ = grasp_boxes(ref, GraspCfg())
    on, _ = grasp_boxes(ref, GraspCfg(finger_weight=100.0))
    down_off, down_on = -fingers(off)[..., 2], -fingers(on)[..., 2]
    assert down_on.min() > 0.9  # within ~25° of straight down on every held frame
    assert down_on.mean() > down_off.mean() + 0.1


def test_a_kept_out_capsule_across_a_box_edge_is_seen_inside_between_its_ends():
    # each kept-out capsule against a 1-cm thin box whose face passes half a radius from the
    # capsule's middle: both end balls are outside it, so only the balls between them see the overlap
    capsules: dict[tuple[str, float], list[np.ndarray]] = {}
    for body, geom, x, radius in grasp._kept_points():
        if body in grasp.KEPT_OUT_LINKS and radius > 0:
            capsules.setdefault((geom, radius), []).append(x)
    tested = []
    for (geom, radius), xs in capsules.items():
        if len(xs) < 2:
            continue  # a sphere
        a, b = xs[0], xs[1]  # the ends come first (collision_points' order)
        half = np.array([0.005, 0.1, 0.1])  # box axes: along the capsule, across it, the third
        if np.linalg.norm(b - a) / 2 - half[0] < 0.9 * radius:
            continue  # too short for its ends to miss the box (the torso's)
        axis = (b - a) / np.linalg.norm(b - a)
        side = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
        side /= np.linalg.norm(side)
        rot = np.stack([axis, side, np.cross(axis, side)], axis=1)
        centre = (a + b) / 2 + side * (0.5 * radius + half[1])
        depth = radius - box_signed_distance((np.array(xs) - centre) @ rot, half)[0]
        assert depth[:2].max() < 0.0, f"{geom}: its ends already overlap the test box"
        assert depth.max() >= 0.4 * radius, f"{geom}: the balls miss the overlap at its middle"
        tested.append(geom)
    assert {"left_shoulder_yaw_collision", "right_elbow_yaw_collision"} <= set(tested)


def _other_gaps(ref: Reference, box_centre_w: np.ndarray) -> np.ndarray:
    """(T, P) each kept-out collision point's ball distance outside the box (m; hands left out)."""
    mdl = grasp._model()
    data = mdl.pin_model.createData()
    q = robot.qpos_mujoco_to_pinocchio(ref.qpos())
    others = mdl.hand < 0
    out = np.empty((len(q), int(others.sum())))
    for t in range(len(q)):
        pin.framesForwardKinematics(mdl.pin_model, data, q[t])
        pos = np.array([data.oMf[f].translation for f, _, _ in mdl.points])
        out[t] = (box_signed_distance(pos - box_centre_w[t], HALF)[0] - mdl.radius)[others]
    return out


def test_a_far_clearance_keeps_links_as_far_off_the_box_as_the_per_frame_solution_did():
    """``far_clearance_m``: a torso, shoulder or elbow the per-frame solution keeps off the box
    stays off it by that distance up to ``far_clearance_m`` (the contact evaluation's threshold:
    a shoulder the regrip brings within 2 cm of the box reads as a contact the person never made)."""
    ref = _held(np.array([0.30, 0.0, 1.014 + HALF[2] + 0.01]))
    centre = ref.objects[0].pos_w
    held = slice(12, FRAMES - 1)
    before = _other_gaps(ref, centre)[held]
    wanted = np.minimum(0.025, before)
    assert (before > 0.02).any()  # some links start farther than the plain 5-mm clearance keeps them
    far, _ = grasp_boxes(ref, GraspCfg(finger_weight=100.0, far_clearance_m=0.025))
    assert (_other_gaps(far, centre)[held] >= wanted - 1e-3).all()


def test_far_clearance_is_the_per_frame_gap_between_clearance_m_and_far_clearance_m():
    mdl = grasp._model()
    data = mdl.pin_model.createData()
    q = robot.qpos_mujoco_to_pinocchio(_arms_forward()[None])[0]
    pin.framesForwardKinematics(mdl.pin_model, data, q)
    centre, rot = np.array([0.35, 0.0, 1.0]), np.eye(3)
    box = grasp.BoxShape(half_extents=HALF, pos=np.zeros(3), quat_wxyz=np.array([1.0, 0, 0, 0]))
    pos = np.array([data.oMf[f].translation for f, _, _ in mdl.points])
    gap = box_signed_distance(pos - centre, HALF)[0] - mdl.radius
    clear = grasp._clearances(data, centre, rot, box, GraspCfg(far_clearance_m=0.025))
    np.testing.assert_allclose(clear, np.clip(gap, 0.005, 0.025))
    np.testing.assert_allclose(grasp._clearances(data, centre, rot, box, GraspCfg()), 0.005)
