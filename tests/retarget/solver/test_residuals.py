"""Interaction residuals: kernels as in the paper, and analytic Jacobians equal to finite differences."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from otr_gym import robot
from otr_gym.rotations import so3_exp
from retarget.geometry.channels import GeometryConfig, GroundChannel, SDFChannel
from retarget.geometry.kinematics import NUM_LINKS, RobotKinematics
from retarget.inputs.meshes import as_trimesh
from retarget.solver.probes import robot_probes
from retarget.solver.residuals import (
    FIXED,
    InteractionConfig,
    PairSet,
    Rows,
    Triples,
    beta,
    beta_and_slope,
    beta_bar,
    distance_rows,
    interaction_rows,
    to_channel_frame,
    witness_vector,
)

CFG = InteractionConfig()
HAND = robot.BODY_NAMES.index("right_wrist_yaw_link")
OBJECT = NUM_LINKS  # body index of the one free object


def test_kernels_follow_the_paper_definitions():
    sigma, cap = 0.13, 5.0
    d_hat = np.array([0.0, 0.065, 0.2, -0.01, 0.0])
    d = np.array([0.1, 0.2, 0.3, 0.05, -0.5])
    np.testing.assert_allclose(beta_bar(d_hat, sigma), [1.0, 0.25, 0.0, 1.0, 1.0])
    # β uses the smaller of (d̂)₊ and d; penetration raises it above 1, capped at β_max
    np.testing.assert_allclose(beta(d_hat, d, sigma, cap), [1.0, 0.25, 0.0, 1.0, min((1 + 0.5 / 0.13) ** 2, 5.0)])
    assert beta(np.array([0.0]), np.array([-0.5]), sigma, cap)[0] == 5.0


def test_beta_slope_matches_finite_differences():
    d_hat = np.array([0.05, 0.05, 0.0, 0.2, 0.05])
    d = np.array([0.02, 0.08, -0.01, 0.05, 0.2])
    _, slope = beta_and_slope(d_hat, d, 0.13, 5.0)
    h = 1e-7
    fd = (beta(d_hat, d + h, 0.13, 5.0) - beta(d_hat, d - h, 0.13, 5.0)) / (2 * h)
    np.testing.assert_allclose(slope, fd, atol=1e-6)


@pytest.fixture(scope="module")
def box_channel(tmp_path_factory) -> SDFChannel:
    box = trimesh.creation.box((0.3, 0.2, 0.25))
    mesh = as_trimesh(box.vertices, box.faces, "test box")
    return SDFChannel.from_mesh(mesh, GeometryConfig(), cache_dir=tmp_path_factory.mktemp("cache"))


@pytest.fixture(scope="module")
def scene():
    """A bent-arm G1 configuration and a box pose 4 cm beside the right hand."""
    kin = RobotKinematics()
    rng = np.random.default_rng(3)
    q = np.concatenate([[0.1, -0.2, 0.78], [0, 0, 0.0998, 0.995], robot.DEFAULT_JOINT_POS])
    q[3:7] /= np.linalg.norm(q[3:7])
    q[7:] += rng.normal(0.0, 0.1, robot.NUM_JOINTS)
    q[7:] = np.clip(q[7:], robot.JOINT_LOWER, robot.JOINT_UPPER)
    fr = kin.frames(kin.new_data(), q)
    box_rot = so3_exp(np.array([0.2, -0.1, 0.4]))
    box_pos = fr.pos[HAND] + np.array([0.0, -0.04 - 0.1, 0.0])
    return kin, q, box_rot, box_pos


def _hand_rows(kin, q, box_rot, box_pos, channel, kind: str, idx=None, desired=None):
    """Rows of the right-hand probes near the box at (q, box pose); ``idx`` and ``desired``
    freeze the pair set between evaluations."""
    probes = robot_probes()
    fr = kin.frames(kin.new_data(), q)
    sel = np.flatnonzero(probes.body == HAND)
    x_w = probes.points[sel] @ fr.rot[HAND].T + fr.pos[HAND]
    x_c = to_channel_frame(x_w, box_rot, box_pos)
    q_box = channel.query(x_c)
    if idx is None:
        idx = np.flatnonzero(q_box.in_band & (q_box.d > 0.002))
        rng = np.random.default_rng(0)
        # demonstrated triples near the current ones, so that every residual kind is active
        w_hat = q_box.w[idx] + rng.normal(0.0, 0.01, (len(idx), 3))
        desired = Triples(np.clip(q_box.d[idx] + rng.normal(0.0, 0.01, len(idx)), -0.005, None), w_hat,
                          -q_box.n[idx])
    from retarget.geometry.channels import ProximityQuery

    take = ProximityQuery(*(getattr(q_box, f)[idx] for f in ("d", "w", "n", "grad_d", "dw_dx", "in_band")))
    pairs = PairSet(x_w[idx], x_c[idx], np.broadcast_to(fr.pos[HAND], (len(idx), 3)), np.full(len(idx), HAND),
                    OBJECT, box_rot, box_pos, take, desired, np.full(len(idx), 1.0 / len(idx)))
    rows = interaction_rows(pairs, channel, CFG.robot_weights, CFG) if kind == "cost" else distance_rows(pairs)
    return rows, fr, idx, desired


def _predicted(rows: Rows, fr, delta_v: np.ndarray, delta_xi: np.ndarray) -> np.ndarray:
    twist = {HAND: fr.jac[HAND] @ delta_v, OBJECT: delta_xi, FIXED: np.zeros(6)}
    ta = np.array([twist[int(b)] for b in rows.body_a])
    tb = np.array([twist[int(b)] for b in rows.body_b])
    return np.einsum("kc,kc->k", rows.phi[:, :6], ta) + np.einsum("kc,kc->k", rows.phi[:, 6:], tb)


@pytest.mark.parametrize("kind", ["cost", "constraint"])
def test_robot_probe_rows_match_finite_differences_in_robot_and_object_variables(scene, box_channel, kind):
    kin, q, box_rot, box_pos = scene
    rows, fr, idx, desired = _hand_rows(kin, q, box_rot, box_pos, box_channel, kind)
    assert len(idx) >= 10
    if kind == "cost":
        assert len(rows) > 4 * len(idx)  # r^d, r^x (3 rows each) and some r^n rows
    rng = np.random.default_rng(1)
    dv, dxi = rng.normal(size=kin.nv), rng.normal(size=6)
    h = 1e-6

    def rows_at(s):
        qs = kin.integrate(q, s * dv)
        rot = so3_exp(s * dxi[3:]) @ box_rot
        return _hand_rows(kin, qs, rot, box_pos + s * dxi[:3], box_channel, kind, idx, desired)[0]

    plus, minus = rows_at(h), rows_at(-h)
    assert len(plus) == len(minus) == len(rows)  # same residual set (no r^n sign change)
    fd = (plus.value - minus.value) / (2 * h)
    analytic = _predicted(rows, fr, dv, dxi)
    scale = np.maximum(np.abs(fd), 1e-3)
    assert np.median(np.abs(analytic - fd) / scale) < 1e-4
    assert np.mean(np.abs(analytic - fd) / scale < 1e-3) > 0.97  # a few rows may straddle a grid cell face


def test_object_probe_rows_against_the_ground_match_finite_differences():
    ground = GroundChannel()
    rng = np.random.default_rng(2)
    pts_o = rng.uniform(-0.2, 0.2, (50, 3))
    rot, pos = so3_exp(np.array([0.3, 0.1, -0.2])), np.array([0.4, 0.1, 0.25])
    desired = Triples(rng.uniform(0.0, 0.05, 50), rng.normal(size=(50, 3)) * [0.3, 0.3, 0.0],
                      np.tile([0, 0, 1.0], (50, 1)))

    def rows_at(r, p):
        x_w = pts_o @ r.T + p
        pairs = PairSet(x_w, x_w, np.broadcast_to(p, x_w.shape), np.full(50, OBJECT), FIXED, np.eye(3), np.zeros(3),
                        ground.query(x_w), desired, np.full(50, 0.02))
        return interaction_rows(pairs, ground, CFG.object_weights, CFG)

    rows = rows_at(rot, pos)
    dxi, h = rng.normal(size=6), 1e-6
    plus = rows_at(so3_exp(h * dxi[3:]) @ rot, pos + h * dxi[:3])
    minus = rows_at(so3_exp(-h * dxi[3:]) @ rot, pos - h * dxi[:3])
    assert len(plus) == len(minus) == len(rows)
    fd = (plus.value - minus.value) / (2 * h)
    analytic = np.einsum("kc,c->k", rows.phi[:, :6], dxi)
    np.testing.assert_allclose(analytic, fd, rtol=1e-5, atol=1e-7)


def test_witness_vector_has_the_geodesic_length_and_its_jacobian(box_channel):
    rng = np.random.default_rng(4)
    w = box_channel.surface.points[rng.choice(len(box_channel.surface.points), 20)]
    w_hat = box_channel.surface.points[rng.choice(len(box_channel.surface.points), 20)]
    vec, jac = witness_vector(box_channel, w, w_hat, np.broadcast_to(np.eye(3), (20, 3, 3)))
    rho, _ = box_channel.geodesic(w, w_hat)
    np.testing.assert_allclose(np.linalg.norm(vec, axis=1), rho, rtol=1e-9)
    # along the chord its derivative is ∂ρ/∂w (the scalar residual's gradient)
    _, drho = box_channel.geodesic(w, w_hat)
    u = (w - w_hat) / np.linalg.norm(w - w_hat, axis=1, keepdims=True)
    np.testing.assert_allclose(np.einsum("ki,kij->kj", u, jac), drho, atol=1e-9)


def test_tangential_rows_vanish_where_the_demonstration_is_out_of_contact_range():
    ground = GroundChannel()
    x = np.array([[0.0, 0.0, 0.03], [0.1, 0.0, 0.03]])
    far = Triples(np.array([0.2, 0.14]), np.zeros((2, 3)), np.tile([0, 0, 1.0], (2, 1)))  # d̂ ≥ σ: β̄ = 0
    pairs = PairSet(x, x, np.zeros((2, 3)), np.zeros(2, int), FIXED, np.eye(3), np.zeros(3), ground.query(x), far,
                    np.ones(2))
    rows = interaction_rows(pairs, ground, CFG.robot_weights, CFG)
    assert len(rows) == 2  # r^d only
    np.testing.assert_allclose(rows.value, beta(far.d, x[:, 2], 0.13, 5.0) * (x[:, 2] - far.d))
