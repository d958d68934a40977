"""The ballistic second pass (``retarget.solver.flight``): the COM target of a flight is a throw, the
supports are the fixed channels, the COM term's Jacobian is the solver's, and a hovering hop
comes out thrown."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pinocchio as pin
import pytest

from otr_gym import robot
from retarget.checks.feasibility import check_feasibility
from retarget.clip import retarget_demonstration
from retarget.config import RetargetConfig
from retarget.geometry.centre_of_mass import com_path, com_residual
from retarget.solver.balance import BalanceConfig
from retarget.solver.flight import GRAVITY_M_S2, FlightConfig, ballistic_com, supported_frames

from clips import clip

FPS = 50.0


def _hover(T: int = 80, first: int = 30, last: int = 49) -> tuple[np.ndarray, np.ndarray]:
    """A COM walking forward at 1 m/s that hovers 10 cm up over frames first..last."""
    t = np.arange(T) / FPS
    com = np.column_stack([t, 0.02 * np.sin(3 * t), np.full(T, 0.66)])
    flight = np.zeros(T, bool)
    flight[first:last + 1] = True
    com[flight, 2] += 0.10
    return com, flight


def _acceleration(x: np.ndarray) -> np.ndarray:
    return (x[:-2] - 2 * x[1:-1] + x[2:]) * FPS * FPS  # frame t at index t − 1


def test_a_hover_becomes_a_throw_between_the_same_supports():
    com, flight = _hover()
    c = ballistic_com(com, flight, FPS)
    air = _acceleration(c)[np.flatnonzero(flight) - 1]
    # within 0.1 m/s² (the fit trades the throw at 1e4 against the stance terms)
    np.testing.assert_allclose(air, np.broadcast_to(GRAVITY_M_S2, air.shape), atol=0.1)
    # the stance frames leading in push off; far from the flight the path is left as it was
    np.testing.assert_allclose(c[:10], com[:10], atol=1e-3)
    np.testing.assert_allclose(c[-10:], com[-10:], atol=1e-3)
    assert _acceleration(c)[28, 2] > 20.0  # the take-off frame (29) pushes up at over 2 g
    # the walk's own accelerations (a sine sideways) are kept where nothing flies
    np.testing.assert_allclose(_acceleration(c)[:15, 1], _acceleration(com)[:15, 1], atol=1e-3)


def test_without_a_flight_the_target_is_the_path_and_bad_input_is_named():
    com, _ = _hover()
    no_flight = np.zeros(len(com), bool)
    no_flight[0] = True  # a first frame in the air has no second difference to throw
    np.testing.assert_array_equal(ballistic_com(com, no_flight, FPS), com)
    with pytest.raises(ValueError, match=r"com must be a finite \(T, 3\) array"):
        ballistic_com(np.full((10, 3), np.nan), np.zeros(10, bool), FPS)
    with pytest.raises(ValueError, match=r"flight must be \(T,\) = \(80,\)"):
        ballistic_com(com, np.zeros(79, bool), FPS)
    one_support = np.ones(len(com), bool)
    one_support[5] = False
    with pytest.raises(ValueError, match="needs two supported frames, got 1 of 80"):
        ballistic_com(com, one_support, FPS)


def test_only_the_fixed_channels_carry_the_robot():
    contacts = np.full((4, 3, 3), 0.15)  # (T, links, channels): ground, a held box, a table
    contacts[1, 0, 0] = 0.01  # a foot on the ground
    contacts[2, 2, 1] = 0.0  # a hand on the held box only
    contacts[3, 1, 2] = 0.019  # a knee on the table
    np.testing.assert_array_equal(supported_frames(contacts, [0, 2], 0.02), [False, True, False, True])
    with pytest.raises(ValueError, match=r"\(T, L, C\)"):
        supported_frames(contacts[0], [0], 0.02)


def test_the_com_jacobian_is_the_derivative_along_the_solver_retraction():
    model = robot.load_pinocchio_model()
    rng = np.random.default_rng(3)
    q = pin.neutral(model)
    q[7:] = rng.uniform(robot.JOINT_LOWER, robot.JOINT_UPPER) * 0.5
    q[3:7] = pin.Quaternion(pin.rpy.rpyToMatrix(0.2, -0.1, 0.7)).coeffs()
    target = np.array([0.1, -0.2, 0.5])
    r, jac = com_residual(model, model.createData(), q, target)
    np.testing.assert_allclose(r, pin.centerOfMass(model, model.createData(), q) - target, atol=1e-12)
    eps = 1e-6
    numeric = np.column_stack([(com_path(model, pin.integrate(model, q, eps * e)[None])[0]
                                - com_path(model, pin.integrate(model, q, -eps * e)[None])[0]) / (2 * eps)
                               for e in np.eye(model.nv)])
    np.testing.assert_allclose(jac, numeric, atol=1e-7)


def _hovering_hop(height: float = 0.15):
    """Frames 30–59 of the synthetic walk (30 fps) whose whole body floats ``height`` up over 0.4 s."""
    demo = clip("walk", 30, 60)
    t = np.arange(demo.num_frames) / demo.fps
    rise = np.clip((t - 0.3) / 0.1, 0, 1) - np.clip((t - 0.7) / 0.1, 0, 1)
    lift = height * (0.5 - 0.5 * np.cos(np.pi * rise))
    return replace(demo, name="hop", part_pos_w=demo.part_pos_w + np.array([0.0, 0.0, 1.0]) * lift[:, None, None])


@pytest.fixture(scope="module")
def hop_references():
    """{flight enabled: (reference, frames reported to ``progress``)} of the hovering hop."""
    demo = _hovering_hop()
    out = {}
    for on in (False, True):
        solved = []
        cfg = RetargetConfig(flight=FlightConfig(enabled=on), balance=BalanceConfig(enabled=False))  # flight alone
        out[on] = retarget_demonstration(demo, cfg, solved.append), solved
    return out


def test_a_hovering_hop_is_thrown_by_the_second_pass(hop_references):
    (hover, one), (thrown, two) = hop_references[False], hop_references[True]
    assert one == list(range(hover.num_frames)) and two == one + one  # progress covers both passes
    assert hover.metadata["passes"] == {"passes": 1}
    assert thrown.metadata["passes"]["passes"] == 2 and thrown.metadata["passes"]["flight_frames"] >= 15
    model = robot.load_pinocchio_model()
    first = check_feasibility(hover)
    (a, b), = first.flight_phases()
    inner = np.arange(a + 2, b - 1)  # the flight without its take-off and landing frames
    az = {on: _acceleration(com_path(model, robot.qpos_mujoco_to_pinocchio(r.qpos()))[:, 2])[inner - 1]
          for on, (r, _) in hop_references.items()}
    assert abs(np.median(az[False])) < 2.0  # the first pass hovers like the person
    # the second throws (its own first and last flight frames may still be braking)
    assert np.median(az[True]) == pytest.approx(-9.81, abs=0.1) and np.abs(az[True] + 9.81).max() < 1.5
    second = check_feasibility(thrown)
    hovering = first.summary()["flight"]["unsupported_mean_fraction"][0]
    assert hovering > 0.7
    assert max(second.summary()["flight"]["unsupported_mean_fraction"]) < 0.6 * hovering  # measured 0.90 → 0.47
    # nothing below the floor, every QP solved
    assert thrown.metadata["solver"]["min_distance_m"] >= -3e-4
    assert thrown.metadata["solver"]["qp_failures"] == 0
