"""Procedural demonstrations obey contact: planted, non-sliding supports; no floating, no sinking;
hands on the box sides while it is held; the box rests on the floor or the table otherwise."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from otr_gym.rotations import (
    quat_apply,
    quat_apply_inverse,
    quat_canonical,
    quat_conj,
    quat_error_angle,
    quat_from_rotvec,
    quat_from_vector_pairs,
    quat_mul,
    quat_to_matrix,
)
from retarget.inputs.demonstration import Demonstration
from retarget.inputs.human import PART_NAMES
from retarget.inputs.synthetic import KINDS, generate

CM = 0.01


@pytest.fixture(scope="module")
def clips() -> dict[str, tuple[Demonstration, float]]:
    out = {}
    for kind in KINDS:
        start = time.perf_counter()
        demo = generate(kind, seed=0)
        out[kind] = (demo, time.perf_counter() - start)
    return out


def _support_heights(demo: Demonstration, parts) -> np.ndarray:
    """Lowest point (T,) of the rigid group of ``parts``."""
    idx = [PART_NAMES.index(p) for p in parts]
    return np.min([(quat_to_matrix(demo.part_quat_w[:, k])[:, 2, :] @ demo.surface.vertices[k].T).min(axis=1)
                   + demo.part_pos_w[:, k, 2] for k in idx], axis=0)


def _stance_slide_speed(demo: Demonstration, part: str, stance: np.ndarray) -> float:
    """Fastest vertex speed (m/s) of ``part`` between consecutive stance frames."""
    k = PART_NAMES.index(part)
    rot = quat_to_matrix(demo.part_quat_w[:, k])
    verts = np.einsum("tij,vj->tvi", rot, demo.surface.vertices[k]) + demo.part_pos_w[:, k, None]
    both = stance[1:] & stance[:-1]
    speed = np.linalg.norm(np.diff(verts, axis=0), axis=-1).max(axis=-1) * demo.fps
    return float(speed[both].max())


def _box_signed_distance(points: np.ndarray, centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    q = np.abs(points - centre) - half
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


def test_every_kind_generates_a_valid_clip_in_under_10_s(clips):
    for kind, (demo, seconds) in clips.items():
        assert seconds < 10.0, kind
        demo.validate()
        assert demo.num_frames > 100 and demo.fps == 30.0
        assert demo.source == {"format": "synthetic", "kind": kind, "seed": 0}


def test_generation_is_deterministic_in_the_seed():
    a, b, c = generate("walk", seed=3), generate("walk", seed=3), generate("walk", seed=4)
    np.testing.assert_array_equal(a.part_pos_w, b.part_pos_w)
    np.testing.assert_array_equal(a.shape, b.shape)
    assert not np.array_equal(a.shape, c.shape)


def test_frame_rate_changes_sampling_not_motion():
    fast, slow = generate("walk", seed=1, fps=60.0), generate("walk", seed=1, fps=30.0)
    assert abs(fast.duration_s - slow.duration_s) < 1.0 / 30.0
    common = min(slow.num_frames, len(fast.part_pos_w[::2]))
    # the pelvis smoothing is sampled at each rate: 0.9 mm apart at most
    np.testing.assert_allclose(fast.part_pos_w[::2][:common], slow.part_pos_w[:common], atol=2e-3)


def test_body_never_floats_nor_sinks_by_more_than_1cm(clips):
    for kind, (demo, _) in clips.items():
        lowest = demo.surface.lowest_z(demo.part_pos_w, demo.part_quat_w)
        assert np.all(np.abs(lowest) < CM), kind


def test_walking_feet_are_flat_on_the_ground_and_do_not_slide_in_stance(clips):
    for kind in ("walk", "box_carry"):
        demo = clips[kind][0]
        for side in ("L", "R"):
            stance = demo.annotations[f"stance_{side}_Ankle"]
            assert 0.5 < stance.mean() < 1.0
            foot = _support_heights(demo, (f"{side}_Ankle", f"{side}_Foot"))
            assert np.all(np.abs(foot[stance]) < CM), (kind, side)
            assert _stance_slide_speed(demo, f"{side}_Ankle", stance) < CM, (kind, side)
            sole_normal = quat_to_matrix(demo.part_quat_w[stance, PART_NAMES.index(f"{side}_Ankle")])[:, :, 1]
            assert np.all(sole_normal[:, 2] > np.cos(np.radians(2.0)))  # flat: the foot's up axis is vertical


def test_walk_takes_steps_forward(clips):
    demo = clips["walk"][0]
    assert demo.part_pos_w[-1, 0, 0] - demo.part_pos_w[0, 0, 0] > 1.2
    swings = sum(int(np.sum(np.diff(demo.annotations[f"stance_{s}_Ankle"].astype(int)) == -1)) for s in "LR")
    assert swings >= 4


def test_crawl_rests_on_hands_and_knees_which_stay_put(clips):
    demo = clips["crawl"][0]
    for limb in ("L_Knee", "R_Knee", "L_Wrist", "R_Wrist"):
        stance = demo.annotations[f"stance_{limb}"]
        assert 0.7 < stance.mean() < 0.9
        assert np.all(np.abs(_support_heights(demo, (limb,))[stance]) < CM), limb
        assert _stance_slide_speed(demo, limb, stance) < CM, limb
    assert demo.part_pos_w[:, 0, 2].max() < 0.7  # on all fours
    for foot in ("L_Ankle", "R_Ankle"):
        assert _support_heights(demo, (foot,)).min() > -CM
    assert demo.part_pos_w[-1, 0, 0] - demo.part_pos_w[0, 0, 0] > 0.4


def test_box_carry_hands_touch_opposite_box_sides_while_held(clips):
    demo = clips["box_carry"][0]
    box = demo.object("box")
    half = 0.5 * np.ptp(box.vertices, axis=0)
    np.testing.assert_allclose(2 * half, [0.35, 0.40, 0.30])
    held = demo.annotations["box_held"]
    assert held.sum() > 100
    vertices = demo.human_vertices_w(held)
    part = demo.surface.vertex_part
    for side, sign in (("L", 1.0), ("R", -1.0)):
        k = PART_NAMES.index(f"{side}_Wrist")
        distance = _box_signed_distance(vertices[:, part == k], box.pos_w[held][:, None], half).min(axis=1)
        assert np.all((distance >= 0.0) & (distance < CM)), side
        lateral = demo.part_pos_w[held, k, 1] - box.pos_w[held, 1]
        assert np.all(sign * lateral > half[1]), side  # the left hand on the +y side, the right on −y


def test_box_moves_rigidly_with_the_hands(clips):
    demo = clips["box_carry"][0]
    box = demo.object("box")
    held = demo.annotations["box_held"]
    assert np.ptp(box.pos_w[held, 2]) > 0.5  # it is lifted and set down
    for side in ("L", "R"):
        k = PART_NAMES.index(f"{side}_Wrist")
        in_box = quat_apply_inverse(box.quat_w[held], demo.part_pos_w[held, k] - box.pos_w[held])
        assert np.ptp(in_box, axis=0).max() < 1e-9
        relative = quat_mul(quat_conj(box.quat_w[held]), demo.part_quat_w[held, k])
        assert quat_error_angle(relative, relative[:1]).max() < 1e-9


def test_box_rests_on_the_floor_then_on_the_table(clips):
    demo = clips["box_carry"][0]
    box, table = demo.object("box"), demo.object("table")
    held = demo.annotations["box_held"]
    first, last = np.flatnonzero(held)[[0, -1]]
    bottom = box.posed_vertices()[:, :, 2].min(axis=1)
    np.testing.assert_allclose(bottom[:first], 0.0, atol=1e-9)
    np.testing.assert_allclose(bottom[last + 1:], 0.75, atol=1e-9)
    assert np.ptp(box.pos_w[:first], axis=0).max() < 1e-12 and np.ptp(box.pos_w[last + 1:], axis=0).max() < 1e-12
    assert table.static and np.ptp(table.pos_w, axis=0).max() == 0.0
    table_top = table.posed_vertices([0])[0]
    assert table_top[:, 2].max() == pytest.approx(0.75)
    footprint = box.posed_vertices([-1])[0]
    assert table_top[:, 0].min() < footprint[:, 0].min() and footprint[:, 0].max() < table_top[:, 0].max()


def test_box_carry_body_keeps_out_of_the_box_and_the_table(clips):
    demo = clips["box_carry"][0]
    box, table = demo.object("box"), demo.object("table")
    half = 0.5 * np.ptp(box.vertices, axis=0)
    vertices = demo.human_vertices_w()
    part = demo.surface.vertex_part
    hands = np.isin(part, [PART_NAMES.index("L_Wrist"), PART_NAMES.index("R_Wrist")])
    to_box = _box_signed_distance(vertices, box.pos_w[:, None], half)
    assert to_box[:, ~hands].min() > 0.0
    assert to_box[:, hands].min() > -CM  # reaching and letting go: at most a brush
    top_centre = table.pos_w[:, None] + np.array([0.0, 0.0, 0.73])
    assert _box_signed_distance(vertices, top_centre, np.array([0.4, 0.3, 0.02])).min() > 0.0


def test_unknown_kind_and_bad_rate_are_rejected():
    with pytest.raises(ValueError, match="unknown synthetic demonstration 'dance'"):
        generate("dance")
    with pytest.raises(ValueError, match="fps must be positive"):
        generate("walk", fps=0.0)


def test_quat_from_vector_pairs_recovers_the_rotation_that_maps_the_pairs():
    """The TRIAD helper the posing relies on (otr_gym.rotations), for NumPy and torch."""
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, 50, 3))
    truth = quat_from_rotvec(rng.normal(size=(50, 3)))
    found = quat_from_vector_pairs(a, 3.0 * b + a, quat_apply(truth, a), quat_apply(truth, b))
    np.testing.assert_allclose(quat_canonical(found), quat_canonical(truth), atol=1e-12)
    as_torch = quat_from_vector_pairs(*(torch.tensor(x) for x in (a, b, quat_apply(truth, a), quat_apply(truth, b))))
    np.testing.assert_allclose(quat_canonical(as_torch).numpy(), quat_canonical(truth), atol=1e-12)
