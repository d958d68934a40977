"""Two-hand holds (retarget.solver.holds): found on the demonstration alone, they give the free
object its hold style weights while the person carries it, and the base weights elsewhere."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from retarget.solver.holds import hold_blend, hold_frames, is_box_like, object_style_weights
from retarget.solver.problem import build_problem, object_hold_weights, resample_demonstration
from retarget.solver.style import StyleConfig

from clips import clip

HOLD = StyleConfig(hold_rot_weight=100.0)


def test_a_hold_needs_both_hands_near_and_the_object_lifted():
    gaps = np.array([[0.01, 0.01], [0.01, 0.20], [0.01, 0.01], [0.01, 0.01]])
    z = np.array([0.15, 0.50, 0.16, 0.50])
    np.testing.assert_array_equal(hold_frames(gaps, z, HOLD), [False, False, False, True])


def test_hold_blend_is_one_on_holds_and_ramps_to_zero_over_the_ramp():
    held = np.zeros(20, bool)
    held[10:12] = True
    blend = hold_blend(held, 4)
    assert (blend[10:12] == 1.0).all() and blend[:6].max() == 0.0 and blend[16:].max() == 0.0
    assert np.all(np.diff(blend[6:11]) > 0) and np.all(np.diff(blend[11:16]) < 0)


def test_a_hold_weight_below_the_base_weight_keeps_the_base():
    w = object_style_weights(np.array([[0.0], [1.0]]), StyleConfig(hold_pos_weight=10.0, hold_rot_weight=50.0))
    np.testing.assert_allclose(w[:, 0], [[300.0, 1.0], [300.0, 50.0]])


def test_hold_weights_go_to_box_like_objects_only():
    import trimesh

    assert is_box_like(trimesh.creation.box(extents=[0.3, 0.4, 0.5]))
    chair = trimesh.util.concatenate([trimesh.creation.box(extents=[0.45, 0.45, 0.05]),  # a seat on legs
                                      *[trimesh.creation.box(extents=[0.04, 0.04, 0.45],
                                                             transform=trimesh.transformations.translation_matrix(
                                                                 [0.2 * sx, 0.2 * sy, -0.25]))
                                        for sx in (-1, 1) for sy in (-1, 1)]])
    assert not is_box_like(chair)


@pytest.fixture(scope="module")
def carry():
    """The synthetic box carry from the box at rest before both hands take it to its lift to 1 m."""
    return resample_demonstration(clip("box_carry", 150, 230), 50.0)


@pytest.fixture(scope="module")
def problem(carry):
    return build_problem(carry, style=HOLD)


def test_box_carry_holds_the_box_rotation_only_while_both_hands_lift_it(problem):
    box = problem.channels[problem.objects[0].channel]
    rot = problem.object_style_w[:, 0, 1]
    lifted = box.pos_w[:, 2] > box.pos_w[:, 2].min() + HOLD.hold_lift_m
    assert (rot[lifted] == 100.0).all()
    ramp = int(round(HOLD.hold_ramp_s * problem.fps))
    resting = np.arange(len(rot)) < np.flatnonzero(lifted)[0] - ramp
    assert resting.any() and (rot[resting] == HOLD.object_rot_weight).all()
    assert (problem.object_style_w[:, 0, 0] == HOLD.object_pos_weight).all()
    # the style rows of a frame read them: the links' weights unchanged, the box's its frame's
    t = int(np.flatnonzero(lifted)[0])
    pos_w, rot_w = problem.style_weights_at(t)
    np.testing.assert_array_equal(rot_w[:-1], problem.style_weights[1][:-1])
    assert rot_w[-1] == 100.0 and pos_w[-1] == HOLD.object_pos_weight


def test_hold_weights_do_not_depend_on_the_probe_seed(carry, problem):
    other = build_problem(carry, style=HOLD, seed=3)
    assert not np.array_equal(other.robot.points, problem.robot.points)
    np.testing.assert_array_equal(other.object_style_w, problem.object_style_w)


def test_base_hold_weights_give_every_frame_the_base_weights(carry, problem):
    base = replace(problem, style_cfg=StyleConfig(), object_style_w=None)
    assert object_hold_weights(carry, base, 1.0, 0.15) is None
    np.testing.assert_array_equal(base.style_weights_at(10)[1], base.style_weights[1])
