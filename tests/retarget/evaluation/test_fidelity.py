"""Retarget fidelity on generated clips: hands that hold, feet that stay planted, open meshes,
and the AMASS SMPL-H pelvis (issue: retarget fidelity on real captures)."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

from otr_gym import robot
from otr_gym.robot_geometry import visual_meshes
from retarget.clip import retarget_demonstration
from retarget.config import RetargetConfig

from clips import clip


@pytest.fixture(scope="module")
def carry():
    """Frames of the synthetic box carry from the lift to the set-down (box held throughout
    most of it), retargeted natively at 30 fps."""
    demo = clip("box_carry", 150, 260)
    ref = retarget_demonstration(demo, RetargetConfig(fps=None))
    return demo, ref


def test_hands_touch_the_carried_box_in_95_percent_of_the_demonstrated_contact_frames(carry):
    from retarget.checks.verify import check_reference
    from retarget.solver.problem import resample_demonstration

    demo, ref = carry
    checks = check_reference(ref, resample_demonstration(demo, ref.fps))
    assert checks.hand_contact_frames >= 100  # both hands, most of the 110 frames
    assert checks.hand_hold >= 0.95
    assert checks.object_penetration_mesh_m <= 1e-3


def _stance_slides(ref, stance: np.ndarray) -> list[float]:
    """Per stance interval of each foot: how far (m) its least-moving sole vertex travels
    horizontally from the interval's first frame to its last."""
    meshes = visual_meshes()
    out = []
    for f, foot in enumerate(robot.FEET):
        i = ref.body_index([foot])[0]
        from otr_gym.robot_geometry import posed_vertices

        v = posed_vertices(meshes[foot], ref.body_pos_w[:, i], ref.body_quat_w[:, i])  # (T, V, 3)
        on = np.concatenate([[False], stance[:, f], [False]])
        starts, stops = np.flatnonzero(on[1:] & ~on[:-1]), np.flatnonzero(~on[1:] & on[:-1])
        for a, b in zip(starts, stops):
            if b - a < 3:
                continue
            travel = np.linalg.norm(v[b - 1, :, :2] - v[a, :, :2], axis=1)
            out.append(float(travel.min()))
    return out


def test_a_synthetic_walk_keeps_each_stance_foot_within_5_mm(tmp_path):
    from retarget.solver.problem import build_problem, resample_demonstration

    demo = clip("walk", 0, 90)
    ref = retarget_demonstration(demo, RetargetConfig(fps=None))
    stance = build_problem(resample_demonstration(demo, ref.fps)).stance
    assert stance.any(axis=0).all()  # both feet stand at some point
    slides = _stance_slides(ref, stance)
    assert len(slides) >= 3
    assert max(slides) < 0.005, slides
    # and on the floor: the lowest sole point within 1.5 mm of z = 0 while standing
    for f, foot in enumerate(robot.FEET):
        i = ref.body_index([foot])[0]
        from otr_gym.robot_geometry import posed_vertices

        low = posed_vertices(visual_meshes()[foot], ref.body_pos_w[:, i], ref.body_quat_w[:, i])[..., 2].min(axis=1)
        assert np.all(np.abs(low[stance[:, f]]) < 1.5e-3)


def _open_box(size=(0.3, 0.25, 0.2)) -> tuple[np.ndarray, np.ndarray]:
    """A box without its top face (five faces, ten triangles), centred at the origin."""
    import trimesh

    box = trimesh.creation.box(extents=size)
    top = box.face_normals[:, 2] > 0.99
    return np.asarray(box.vertices), np.asarray(box.faces[~top])


def test_a_stance_break_shorter_than_min_lift_is_closed_and_a_step_is_kept():
    """At 50 fps with ``min_lift_s`` 0.07, a still foot whose lowest point flickers over the
    contact height for 3 frames (60 ms) between two stances stands through them; 4 frames (80 ms)
    stay a break, as do a break at the clip's start and a 3-frame break of a foot that slides
    (faster than ``flicker_speed_m_s``). 0, the default, keeps every break."""
    from otr_gym.flags import close_short_gaps
    from retarget.solver.stance import StanceConfig, demonstrated_stance

    T = 30
    low = np.full((T, 2), 0.005)
    foot_speed = np.full((T, 2), 0.1)
    low[0:2, 0] = low[10:13, 0] = 0.025  # left, still: a break at the start, then 3 frames
    low[20:24, 1] = 0.025  # right, still: 4 frames
    low[5:8, 1] = 0.025  # right: 3 frames, sliding at 0.6 m/s
    foot_speed[5:8, 1] = 0.6
    pelvis = np.full(T, 0.5)
    stance, sweep = demonstrated_stance(low, foot_speed, pelvis, StanceConfig(min_lift_s=0.07), fps=50.0)
    assert stance[2:, 0].all() and not stance[:2, 0].any()
    assert not stance[20:24, 1].any() and stance[8:20, 1].all() and stance[24:, 1].all()
    assert not stance[5:8, 1].any() and not sweep.any()
    default, _ = demonstrated_stance(low, foot_speed, pelvis, StanceConfig(), fps=50.0)
    assert not default[10:13, 0].any()
    flags = np.array([[1, 0, 1, 0, 0, 1, 0, 0, 0, 1]], bool).T
    assert close_short_gaps(flags, 2)[:, 0].tolist() == [True] * 6 + [False] * 3 + [True]
    np.testing.assert_array_equal(close_short_gaps(flags, 0), flags)
    closable = np.ones_like(flags)
    closable[3] = False
    assert close_short_gaps(flags, 2, closable)[:, 0].tolist() == [True, True, True, False, False, True,
                                                                  False, False, False, True]


def test_a_foot_near_the_floor_stands_unless_it_sweeps_past_the_body():
    """Stance needs the foot within 2 cm of the floor and no faster than the pelvis (or 1 m/s);
    a foot skimming the floor faster than that sweeps: held on the floor, free horizontally."""
    from retarget.solver.stance import StanceConfig, demonstrated_stance, stance_targets

    low = np.array([[0.005, 0.005], [0.010, 0.030], [0.015, 0.001], [0.0, 0.0]])  # (T, F) m
    foot_speed = np.array([[0.05, 0.10], [2.50, 0.20], [1.30, 1.30], [0.90, 0.90]])  # m/s
    pelvis_speed = np.array([1.2, 1.2, 1.2, 0.2])  # m/s
    stance, sweep = demonstrated_stance(low, foot_speed, pelvis_speed, StanceConfig())
    assert stance.tolist() == [[True, True], [False, False], [False, False], [True, True]]
    assert sweep.tolist() == [[False, False], [True, False], [True, True], [False, False]]
    assert not (stance & sweep).any()

    sole = np.array([[0.1, 0.02, -0.03], [-0.05, 0.02, -0.03], [0.1, -0.02, -0.03]])
    cfg = StanceConfig(touch_m=0.002, ramp_frames=1)
    t = stance_targets(stance, 1, np.array([7, 13]), (sole, sole), np.array([0.002, 0.002]), None, cfg,
                       sweep=sweep)
    assert np.all(t.link == 7) and len(t.link) == 3  # only the sweeping foot has rows at t = 1
    assert np.isnan(t.target_w[:, :2]).all() and np.allclose(t.target_w[:, 2], 0.002)  # z held, xy free
    # with a clearance the sweeping sole is held that high above the floor; standing soles are not
    cleared = StanceConfig(touch_m=0.002, ramp_frames=1, sweep_clearance_m=0.01)
    lifted = stance_targets(stance, 1, np.array([7, 13]), (sole, sole), np.array([0.002, 0.002]), None, cleared,
                            sweep=sweep)
    assert np.all(lifted.link == 7) and np.allclose(lifted.target_w[:, 2], 0.012)
    standing = stance_targets(stance, 0, np.array([7, 13]), (sole, sole), np.array([0.002, 0.002]), None, cleared,
                              sweep=sweep)
    assert len(standing.link) == 6 and np.allclose(standing.target_w[:, 2], 0.002)


def test_a_planted_sole_point_keeps_its_anchor_unless_it_slipped_too_far():
    """A held point's target is where it was held (its anchor), not the previous solution's
    position, so sub-millimetre slips do not add up frame after frame; a point dragged farther
    than ``anchor_slip_m`` is held where it went."""
    from retarget.geometry.kinematics import LinkFrames
    from retarget.solver.stance import StanceConfig, stance_targets

    sole = np.array([[0.1, 0.02, -0.03], [-0.05, 0.02, -0.03]])
    stance = np.ones((3, 1), dtype=bool)
    feet, floor = np.array([0]), np.array([0.0])

    def frames_at(x: float) -> LinkFrames:  # the foot link 3 cm up, its sole on the floor, at x
        return LinkFrames(pos=np.array([[x, 0.0, 0.03]]), rot=np.eye(3)[None], jac=None)

    cfg = StanceConfig(touch_m=0.002, ramp_frames=1, anchor_slip_m=0.002)
    first = stance_targets(stance, 1, feet, (sole,), floor, frames_at(0.0), cfg)
    assert np.allclose(first.target_w[:, :2], sole[:, :2])  # held where the solution was
    assert np.allclose(first.anchors[0], sole[:, :2])
    kept = stance_targets(stance, 2, feet, (sole,), floor, frames_at(0.001), cfg, before=first)
    assert np.allclose(kept.target_w[:, :2], sole[:, :2])  # 1 mm slip: back to the anchor
    dragged = stance_targets(stance, 2, feet, (sole,), floor, frames_at(0.005), cfg, before=first)
    assert np.allclose(dragged.target_w[:, :2], sole[:, :2] + [0.005, 0.0])  # 5 mm: re-anchored
    assert np.allclose(dragged.anchors[0], sole[:, :2] + [0.005, 0.0])


def test_a_foot_rolling_onto_its_toes_is_held_by_its_front_edge_only():
    """While the person's ankle-to-toe line pitches toes-down beyond ``roll_tilt_rad`` from its
    flat stance pitch, only the G1 sole's front edge is held (its anchors kept): a held point
    behind the edge would keep the rigid sole flat."""
    from retarget.geometry.kinematics import LinkFrames
    from retarget.solver.stance import FootTurns, StanceConfig, demonstrated_roll, stance_targets

    # one foot standing for 4 frames, pitched 0°, 1°, 2° then 40° toes-down from flat (its toe
    # joint 1 cm below the ankle when flat); a second foot whose stance frames are all at 40°
    # never rolls: each foot's flat pitch is its median over its own stance frames
    pitch = np.radians([[0.0, 40.0], [1.0, 40.0], [2.0, 10.0], [40.0, 40.0]]) + np.arctan2(0.01, 0.15)
    ankle = np.zeros((4, 2, 3))
    toe = np.stack([0.15 * np.ones_like(pitch), np.zeros_like(pitch), -0.15 * np.tan(pitch)], axis=-1)
    stance = np.array([[True, True], [True, True], [True, False], [True, True]])
    rolling = demonstrated_roll(ankle, toe, stance, np.radians(3.0))
    assert rolling[:, 0].tolist() == [False, False, False, True]
    assert not rolling[:, 1].any()

    sole = np.array([[0.12, 0.03, -0.03], [0.118, -0.03, -0.03], [0.05, 0.0, -0.03], [-0.05, 0.0, -0.03]])
    feet, floor = np.array([0]), np.array([0.0])
    flat = LinkFrames(pos=np.array([[0.2, 0.1, 0.03]]), rot=np.eye(3)[None], jac=None)
    cfg = StanceConfig(touch_m=0.002, ramp_frames=1, roll_edge_m=0.005)
    turns = FootTurns(np.zeros((4, 1)), np.zeros((4, 1, 2)), rolling[:, :1])
    held = stance_targets(stance[:, :1], 2, feet, (sole,), floor, flat, cfg, turns)
    assert len(held.link) == 4  # not rolling yet: the whole sole
    edge = stance_targets(stance[:, :1], 3, feet, (sole,), floor, flat, cfg, turns, before=held)
    assert np.allclose(edge.points, sole[:2])  # the two points within 5 mm of the tip
    assert np.allclose(edge.target_w[:, :2], sole[:2, :2] + [0.2, 0.1]) and np.allclose(edge.target_w[:, 2], 0.0)
    assert np.allclose(edge.anchors[0][:2], sole[:2, :2] + [0.2, 0.1]) and np.isnan(edge.anchors[0][2:]).all()
    # without roll-offs (turns None) the same frame holds the whole sole
    assert len(stance_targets(stance[:, :1], 3, feet, (sole,), floor, flat, cfg).link) == 4


def test_an_open_five_faced_box_is_retargeted_as_a_shell_with_a_warning():
    from retarget.inputs.meshes import SHELL_THICKNESS_M

    demo = clip("box_carry", 150, 166)
    v, f = _open_box()
    assert len(f) == 10
    box = demo.objects[0]
    demo = replace(demo, objects=[replace(box, vertices=v, faces=f)] + list(demo.objects[1:]))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ref = retarget_demonstration(demo, RetargetConfig(fps=None))
    assert any("box" in str(w.message) and "treated as a shell 10 mm thick" in str(w.message) for w in caught)
    assert ref.num_frames == demo.num_frames
    assert np.isfinite(ref.joint_pos).all()
    # the open box is solid for the solver: no probe deeper than ε_col into its 10 mm shell
    c = list(ref.contacts.channel_names).index(box.name)
    assert ref.contacts.distance[:, :, c].min() >= -3e-4 - 1e-6
    assert SHELL_THICKNESS_M == 0.01


def test_an_amass_smplh_pelvis_sits_at_trans_plus_the_smpl_template_pelvis(tmp_path):
    """AMASS SMPL-H ``trans`` places SMPL's pelvis joint (−0.22 m in the model's y), not SMPL-X's
    (−0.35 m): with identity poses and mean shape the pelvis is at trans + J₀ (x, y; z is grounded)."""
    from retarget.inputs.readers import SMPL_TEMPLATE_PELVIS, load_demonstration

    frames = 4
    trans = np.array([[0.5, -0.2, 0.9]] * frames) + np.arange(frames)[:, None] * np.array([0.01, 0.0, 0.0])
    path = tmp_path / "smplh_still.npz"
    np.savez(path, poses=np.zeros((frames, 156)), trans=trans, betas=np.zeros(16), gender="neutral",
             mocap_framerate=120.0)
    demo = load_demonstration(path)
    pelvis = demo.part_pos_w[:, 0]
    np.testing.assert_allclose(pelvis[:, :2], (trans + SMPL_TEMPLATE_PELVIS)[:, :2], atol=1e-9)
