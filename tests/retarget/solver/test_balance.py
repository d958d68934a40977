"""The balance pass (``retarget.solver.balance``): the COM target is the first solution's COM
without its jitter, it composes with the ballistic pass, and a retargeted walk comes out with a
steadier centre of mass and no more unsupported frames."""

from __future__ import annotations

import numpy as np
import pytest

from otr_gym import robot
from retarget.checks.feasibility import check_feasibility
from retarget.clip import retarget_demonstration
from retarget.config import RetargetConfig
from retarget.geometry.centre_of_mass import com_path
from retarget.solver.balance import BalanceConfig, balance_target

from clips import clip

FPS = 50.0


def _second_difference(x: np.ndarray) -> np.ndarray:
    return (x[:-2] - 2 * x[1:-1] + x[2:]) * FPS * FPS


def test_the_target_keeps_the_motion_and_drops_the_jitter():
    t = np.arange(200) / FPS
    smooth = np.column_stack([0.8 * t, 0.05 * np.sin(2 * np.pi * 0.9 * t), 0.66 + 0.01 * np.sin(2 * np.pi * 1.8 * t)])
    jitter = 0.003 * (-1.0) ** np.arange(200)[:, None] * np.array([1.0, 0.5, 0.2])  # 3 mm frame to frame
    target = balance_target(smooth + jitter, FPS, BalanceConfig())
    inner = slice(10, -10)  # the filter's ends are padded
    assert np.abs(target - smooth)[inner].max() < 1e-3  # the walk's 0.9 and 1.8 Hz pass
    raw = np.linalg.norm(_second_difference(smooth + jitter)[inner], axis=1)
    kept = np.linalg.norm(_second_difference(target)[inner], axis=1)
    assert np.median(raw) > 30.0 and np.median(kept) < 2.0  # ±3 mm alternating: 4·3 mm·fps² = 30 m/s²


@pytest.mark.parametrize("bad", [np.zeros((10, 2)), np.full((10, 3), np.nan)])
def test_a_bad_com_path_is_refused(bad):
    with pytest.raises(ValueError, match="com must be a finite"):
        balance_target(bad, FPS, BalanceConfig())


def test_a_cutoff_at_or_above_nyquist_changes_nothing():
    com = np.random.default_rng(0).normal(size=(30, 3))
    assert np.array_equal(balance_target(com, FPS, BalanceConfig(cutoff_hz=25.0)), com)
    with pytest.raises(ValueError, match="cutoff_hz"):
        balance_target(com, FPS, BalanceConfig(cutoff_hz=0.0))


@pytest.fixture(scope="module")
def walk_references():
    """{balance enabled: reference} of the synthetic walk, frames 0-89 at 30 fps (3 s)."""
    demo = clip("walk", 0, 90)
    return {on: retarget_demonstration(demo, RetargetConfig(balance=BalanceConfig(enabled=on))) for on in (False, True)}


def test_a_walk_comes_out_steadier_and_no_less_supported(walk_references):
    model = robot.load_pinocchio_model()
    acc, report = {}, {}
    for on, ref in walk_references.items():
        com = com_path(model, robot.qpos_mujoco_to_pinocchio(ref.qpos()))
        acc[on] = np.median(np.linalg.norm(_second_difference(com)[:, :2], axis=1))
        report[on] = check_feasibility(ref)
    assert walk_references[True].metadata["passes"]["passes"] == 2
    assert walk_references[True].metadata["passes"]["balance"] is True
    assert walk_references[False].metadata["passes"] == {"passes": 1}
    assert acc[True] < 0.75 * acc[False]  # measured 2.95 → 1.90 m/s² (median, raw 50 fps)
    over = {on: r.frames_over()["unsupported"] for on, r in report.items()}
    assert over[True] <= over[False]  # measured 31 → 20 of 90 frames
    # the pass moves the body over the feet, not into the floor
    assert walk_references[True].metadata["solver"]["min_distance_m"] >= -3e-4


def test_pass_two_moves_the_body_over_the_feet():
    """The second problem: the COM target is smoothed horizontally and held there only, every
    style target but the legs' moves by the correction, the legs' stay where the person put them."""
    from retarget.clip import problem_from_config
    from retarget.solver.balance import LEG_LINKS, balance_problem
    from retarget.solver.flight import FlightConfig
    from retarget.solver.problem import resample_demonstration
    from retarget.solver.sqp import solve_sequence

    cfg = RetargetConfig(balance=BalanceConfig(enabled=True))
    problem = problem_from_config(resample_demonstration(clip("walk", 0, 45), FPS), cfg)
    first = solve_sequence(problem)
    second, stats = balance_problem(problem, first, cfg.balance, FlightConfig())
    com = com_path(problem.kin.model, robot.qpos_mujoco_to_pinocchio(first.qpos))
    shift = second.com_target - com
    assert np.abs(shift[:, 2]).max() == 0.0 and second.com_weights.tolist() == [1e4, 1e4, 0.0]
    assert stats["com_shift_max_m"] == pytest.approx(np.linalg.norm(shift, axis=1).max())
    legs = np.isin(problem.style.links, LEG_LINKS)
    assert legs.any() and (~legs).any()
    moved = second.style.pos_w - problem.style.pos_w
    assert np.array_equal(moved[:, legs], np.zeros_like(moved[:, legs]))
    np.testing.assert_allclose(moved[:, ~legs], np.broadcast_to(shift[:, None, :], moved[:, ~legs].shape), atol=1e-12)
    assert balance_problem(problem, first, BalanceConfig(enabled=False), FlightConfig()) is None


def test_the_person_com_weighs_each_part_by_its_volume():
    """Two parts, a 0.2 m cube and a 0.1 m cube (8:1 in volume), posed apart and turned: the
    COM lies 1/9 of the way from the big one's centre to the small one's."""
    import trimesh

    from otr_gym.rotations import matrix_to_quat, so3_exp
    from retarget.inputs.human_surface import HumanSurface

    big, small = trimesh.creation.box((0.2, 0.2, 0.2)), trimesh.creation.box((0.1, 0.1, 0.1))
    offset = np.array([0.05, 0.0, 0.0])  # the small part's mesh sits off its frame's origin
    surface = HumanSurface(("a", "b"), [big.vertices, small.vertices + offset], [big.faces, small.faces])
    rot = so3_exp(np.array([0.0, 0.0, np.pi / 2]))  # part b turned 90° about z: its offset points along y
    pos = np.array([[[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]]])
    quat = np.stack([matrix_to_quat(np.eye(3)), matrix_to_quat(rot)])[None]
    com = surface.centre_of_mass(pos, quat)
    centre_b = pos[0, 1] + rot @ offset
    np.testing.assert_allclose(com[0], (8 * pos[0, 0] + centre_b) / 9, atol=1e-12)
    assert com.shape == (1, 3)


def test_the_first_solve_holds_the_person_com_where_asked():
    """``problem_from_config`` gives the first solve the person's COM (low-passed, × the mode's
    scale) as a horizontal target with its weight and offset rate; weight 0 gives none."""
    from retarget.clip import problem_from_config
    from retarget.solver.problem import mode_scale, resample_demonstration

    demo = resample_demonstration(clip("walk", 0, 45), FPS)
    person = demo.surface.centre_of_mass(demo.part_pos_w, demo.part_quat_w)
    cfg = RetargetConfig(balance=BalanceConfig(person_com_weight=1e4))  # configs/retarget/executable.yaml's
    problem = problem_from_config(demo, cfg)
    assert problem.com_weights.tolist() == [cfg.balance.person_com_weight] * 2 + [0.0]
    assert problem.com_offset_rate == cfg.balance.person_offset_rate > 0
    np.testing.assert_allclose(problem.com_target, balance_target(person, FPS, cfg.balance))
    scaled = problem_from_config(demo, RetargetConfig(mode="scaled", balance=cfg.balance))
    np.testing.assert_allclose(scaled.com_target, balance_target(person * mode_scale(demo, "scaled"), FPS,
                                                                 cfg.balance))
    off = problem_from_config(demo, RetargetConfig())  # the default: off
    assert off.com_target is None and off.com_weights.tolist() == [0.0, 0.0, 0.0]
    with pytest.raises(ValueError, match="person_com_weight"):
        problem_from_config(demo, RetargetConfig(balance=BalanceConfig(person_com_weight=-1.0)))
