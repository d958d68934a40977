"""The trust-region SQP: its kinematics and QP pieces, and what it guarantees on short clips."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pinocchio as pin
import pytest

from otr_gym import robot
from retarget.checks.verify import check_reference
from retarget.clip import retarget_demonstration
from retarget.config import RetargetConfig
from retarget.geometry.kinematics import NUM_LINKS, RobotKinematics, segment_closest_points
from retarget.solver.iterate import new_state
from retarget.solver.problem import SolverConfig, build_problem, resample_demonstration
from retarget.solver.qp import assemble_cost, body_jacobians, model_at, qp_step
from retarget.solver.residuals import FIXED, Rows
from retarget.solver.rows import linearise
from retarget.solver.targets import frame_targets

from clips import clip

EPS_COL = 3e-4


@pytest.fixture(scope="module")
def kin() -> RobotKinematics:
    return RobotKinematics()


def test_link_jacobians_equal_pinocchio_local_world_aligned_frame_jacobians(kin):
    rng = np.random.default_rng(0)
    q = pin.neutral(kin.model)
    q[:3] = rng.normal(size=3)
    q[3:7] = pin.Quaternion(pin.exp3(rng.normal(size=3))).coeffs()
    q[7:] = rng.uniform(robot.JOINT_LOWER, robot.JOINT_UPPER)
    data = kin.new_data()
    fr = kin.frames(data, q)
    for k, name in enumerate(robot.BODY_NAMES):
        fid = kin.model.getFrameId(name, pin.BODY)
        ref = pin.getFrameJacobian(kin.model, data, fid, pin.LOCAL_WORLD_ALIGNED)
        np.testing.assert_allclose(fr.jac[k], ref, atol=1e-12)
        np.testing.assert_allclose(fr.pos[k], data.oMf[fid].translation, atol=1e-12)


def test_segment_closest_points_match_a_dense_search():
    rng = np.random.default_rng(1)
    p0, p1, q0, q1 = (rng.normal(size=(60, 3)) for _ in range(4))
    p1[:10] = p0[:10]  # spheres
    a, b = segment_closest_points(p0, p1, q0, q1)
    s = np.linspace(0.0, 1.0, 201)
    pa = p0[:, None] + s[None, :, None] * (p1 - p0)[:, None]
    pb = q0[:, None] + s[None, :, None] * (q1 - q0)[:, None]
    dense = np.linalg.norm(pa[:, :, None] - pb[:, None], axis=-1).min(axis=(1, 2))
    assert np.all(np.linalg.norm(a - b, axis=1) <= dense + 1e-9)
    assert np.all(np.linalg.norm(a - b, axis=1) >= dense - 1e-2)


def test_merged_cost_assembly_equals_the_dense_gauss_newton_product():
    rng = np.random.default_rng(2)
    n_bodies, n = 4, 17
    jac = np.concatenate([rng.normal(size=(n_bodies, 6, n)), np.zeros((1, 6, n))])
    k = 60
    body_a = np.sort(rng.integers(0, n_bodies, k))
    body_b = np.where(rng.random(k) < 0.5, FIXED, rng.integers(0, n_bodies, k))
    rows = Rows(rng.normal(size=k), rng.random(k), rng.normal(size=(k, 12)), body_a, body_b)
    dense = (np.einsum("kc,kcn->kn", rows.phi[:, :6], jac[body_a])
             + np.einsum("kc,kcn->kn", rows.phi[:, 6:], jac[body_b]))
    H, g = assemble_cost(rows, jac)
    np.testing.assert_allclose(H, dense.T @ (rows.weight[:, None] * dense), atol=1e-9)
    np.testing.assert_allclose(g, dense.T @ (rows.weight * rows.value), atol=1e-9)


def test_qp_step_stays_in_the_trust_region_and_the_joint_limits():
    demo = resample_demonstration(clip("walk", 30, 36), 50.0)
    problem = build_problem(demo, "robot-only")
    state = new_state(problem)
    state.q[7:] = robot.JOINT_UPPER - 0.01  # next to the upper limits
    targets = frame_targets(problem, 0)
    lin = linearise(problem, state, targets, {})
    from retarget.solver.iterate import FrameStats

    delta = qp_step(problem, state, targets, model_at(problem, state, lin, {}), 1.0, FrameStats())
    cfg = problem.solver
    assert np.all(np.abs(delta[:3]) <= cfg.trust_linear_m + 1e-7)
    assert np.all(np.abs(delta[3:]) <= cfg.trust_angular_rad + 1e-7)
    assert np.all(state.q[7:] + delta[6:] <= robot.JOINT_UPPER + 1e-7)
    assert body_jacobians(problem, lin.frames).shape == (NUM_LINKS + 1, 6, problem.num_variables)


@pytest.fixture(scope="module")
def walk_reference():
    demo = resample_demonstration(clip("walk", 20, 50), 50.0)
    return demo, retarget_demonstration(demo, RetargetConfig(mode="robot-only"))


def test_robot_only_walk_keeps_stance_feet_on_the_ground_without_penetration(walk_reference):
    demo, ref = walk_reference
    ground = ref.contacts.channel_names.index("ground")
    feet = ref.body_index(robot.FEET)
    dist = ref.contacts.distance[:, feet, ground]  # (T, 2): lowest probe or hull point of each foot
    assert dist.min() >= -EPS_COL
    # the demonstrated stance phases, resampled with the demonstration to the reference's 50 fps
    t = np.arange(ref.num_frames) / ref.fps
    stance = np.stack([demo.annotations[f"stance_{p}_Ankle"] for p in "LR"], axis=1)
    assert stance.shape == (ref.num_frames, 2)
    assert stance.any(axis=0).all()
    assert np.abs(dist[stance.astype(bool)]).max() < 0.005, "a stance foot leaves the ground by 5 mm or more"
    checks = check_reference(ref, demo)
    assert checks.ground_penetration_mesh_m <= EPS_COL
    assert checks.joint_limit_excess_rad < 1e-6 and checks.joint_speed_ratio <= 1.0 + 1e-6
    assert t[-1] == pytest.approx(demo.duration_s)


def test_the_same_demonstration_gives_the_same_reference():
    """Same input, same output, bit for bit: no randomness anywhere (seeded sampling, cached
    assignments), and ProxQP's portable build (retarget/__init__.py) answers a QP the same way
    wherever its buffers land (the vectorised builds moved the last bit: 8e-16 after a few frames)."""
    demo = resample_demonstration(clip("walk", 40, 46), 50.0)
    a = retarget_demonstration(demo, RetargetConfig(mode="robot-only"))
    b = retarget_demonstration(demo, RetargetConfig(mode="robot-only"))
    assert np.array_equal(a.joint_pos, b.joint_pos)
    assert np.array_equal(a.contacts.distance, b.contacts.distance)
    assert a.metadata["solver"]["iterations_mean"] == b.metadata["solver"]["iterations_mean"]


def test_penetration_never_exceeds_0p3mm_on_a_synthetic_box_lift():
    """The per-frame solve's guarantee. The grasp pass after it squeezes the hands' collision
    boxes 8 mm into the faces on purpose, which on this exact box takes the hands' meshes 7.7 mm
    in (tests/retarget/solver/test_grasp.py checks the collision geoms' depth)."""
    demo = resample_demonstration(clip("box_carry", 130, 175), 50.0)  # reach, grasp, lift
    cfg = RetargetConfig()
    ref = retarget_demonstration(demo, replace(cfg, grasp=replace(cfg.grasp, enabled=False)))
    assert [o.name for o in ref.objects] == ["box", "table"]
    assert ref.contacts.distance.min() >= -EPS_COL  # the solver's own probes, every channel
    checks = check_reference(ref, demo)  # exact distances of the visual-mesh vertices
    assert checks.object_penetration_mesh_m <= EPS_COL
    assert checks.ground_penetration_mesh_m <= EPS_COL
    assert checks.object_min_height_m >= -EPS_COL
    assert checks.hand_contact_frames > 50 and checks.hand_hold >= 0.85


def test_a_qp_with_conflicting_rows_still_satisfies_the_rows_it_can():
    """Elastic mode: when a row cannot be met inside the step boxes, ProxQP fails; the re-solve
    keeps every other row and meets the impossible one as far as the box allows (before, the
    rows were dropped and the step ignored all of them)."""
    from retarget.solver.qp_workspace import QPWorkspace

    ws = QPWorkspace(eps_abs=1e-9)
    H, g = np.eye(2), np.zeros(2)
    C = np.array([[1.0, 0.0], [0.0, 1.0]])
    lower = np.array([0.5, 0.05])  # x0 ≥ 0.5 (beyond the box) and x1 ≥ 0.05 (feasible)
    x = ws.solve(H, g, C, lower, np.array([-0.1, -0.1]), np.array([0.1, 0.1]))
    assert ws.failures == 1
    np.testing.assert_allclose(x, [0.1, 0.05], atol=1e-6)
    ok = ws.solve(H, g, C[1:], lower[1:], np.array([-0.1, -0.1]), np.array([0.1, 0.1]))
    assert ws.failures == 1 and np.allclose(ok, [0.0, 0.05], atol=1e-6)


def test_the_elastic_re_solve_over_a_working_set_of_rows_equals_the_slack_qp_over_all_rows():
    """300 rows, all violated at 0, that cannot all be met inside the step boxes: 280 push one
    way and 20 the other (as where a too-big box fills the hands' reach). The working-set
    re-solve gives the step of the slack QP over every row, through QPs that never take them
    all, and leaves rows violated (a true elastic step)."""
    from retarget.solver.qp_workspace import QPWorkspace

    rng = np.random.default_rng(3)
    n = 8
    A = rng.normal(size=(n, n))
    H, g = A @ A.T + np.eye(n), rng.normal(size=n)
    C = np.vstack([1.0 + 0.3 * rng.normal(size=(280, n)), -1.0 + 0.3 * rng.normal(size=(20, n))])
    lower = np.concatenate([rng.uniform(0.0, 0.2, 280), rng.uniform(0.2, 0.4, 20)])
    box_lo, box_hi = np.full(n, -0.2), np.full(n, 0.2)
    ws = QPWorkspace(eps_abs=1e-9, elastic_batch=16)
    x = ws._solve_elastic_working(H, g, C, lower, box_lo, box_hi)
    assert max(size for size, _ in ws._qps) <= n + 100
    full = QPWorkspace(eps_abs=1e-9)._solve_with_slacks(H, g, C, lower, box_lo, box_hi)
    np.testing.assert_allclose(x, full, atol=1e-8)
    assert (lower - C @ x > 1e-3).sum() > 10


def _elastic_merit(H, g, C, lower, rho, x):
    s = np.maximum(lower - C @ x, 0.0)
    return 0.5 * x @ H @ x + g @ x + rho * s.sum() + 0.5 * rho * s @ s


@pytest.mark.parametrize("rows", [300, 1200])
def test_a_failed_qp_is_re_solved_without_a_slack_qp_whatever_its_rows(rows):
    """The elastic re-solve is one interior-point solve over x alone (``elastic_ipm``), not
    ProxQP's dense slack QP of n + m variables over a growing working set: on Bandai's
    walk_musical_002 a frame of 843 self-collision rows, most violated at the answer, grew that
    set to 687 rows and took 127 s. Here the conflicting rows are many and the answer leaves
    most of them violated: the failed QP is ProxQP's only solve, and the step is the slack QP's
    (same merit to 1e-12, the same x as ProxQP's slack QP over every row where that is small
    enough to solve)."""
    from retarget.solver.qp_workspace import QPWorkspace

    rng = np.random.default_rng(3)
    n = 35
    A = rng.normal(size=(n, n))
    H, g = A @ A.T + np.eye(n), rng.normal(size=n)
    push = rows * 2 // 3
    C = np.vstack([1.0 + 0.3 * rng.normal(size=(push, n)), -1.0 + 0.3 * rng.normal(size=(rows - push, n))])
    lower = np.concatenate([rng.uniform(0.0, 0.2, push), rng.uniform(0.2, 0.4, rows - push)])
    box_lo, box_hi = np.full(n, -0.05), np.full(n, 0.05)
    ws = QPWorkspace(eps_abs=1e-9)
    x = ws.solve(H, g, C, lower, box_lo, box_hi)
    assert (ws.failures, ws.elastic_ipm, ws.solves) == (1, 1, 1)
    assert (lower - C @ x > 1e-3).sum() > rows // 4  # a true elastic step: many rows stay violated
    assert np.all(x >= box_lo - 1e-12) and np.all(x <= box_hi + 1e-12)
    rho = 100.0 * (1.0 + float(np.abs(np.diag(H)).max()))
    if rows <= 300:
        full = QPWorkspace(eps_abs=1e-9)._solve_with_slacks(H, g, C, lower, box_lo, box_hi)
        np.testing.assert_allclose(x, full, atol=1e-7)
        merit, best = _elastic_merit(H, g, C, lower, rho, x), _elastic_merit(H, g, C, lower, rho, full)
        assert merit <= best * (1 + 1e-12)
    # optimality: no feasible coordinate move lowers the merit
    merit = _elastic_merit(H, g, C, lower, rho, x)
    for i in range(n):
        for step in (1e-6, -1e-6):
            y = x.copy()
            y[i] = np.clip(y[i] + step, box_lo[i], box_hi[i])
            assert _elastic_merit(H, g, C, lower, rho, y) >= merit - 1e-9 * abs(merit)


def test_an_elastic_re_solve_whose_rows_all_hold_still_minimises_the_objective():
    """A failed QP is not always a conflict (ProxQP may stop at its iteration cap): where every
    row holds at the origin, the re-solve still takes the step the objective asks for inside the
    boxes (a first version returned the origin, a null step, and a free-table carry lost its box
    contacts: recall 0.47)."""
    from retarget.solver.qp_workspace import QPWorkspace

    H, g = np.eye(2), np.array([-1.0, 0.2])
    C, lower = np.array([[1.0, 0.0], [0.0, 1.0]]), np.array([-5.0, -5.0])
    x = QPWorkspace(eps_abs=1e-9)._solve_elastic(H, g, C, lower, np.full(2, -0.5), np.full(2, 0.5))
    np.testing.assert_allclose(x, [0.5, -0.2], atol=1e-7)


def test_a_board_face_cut_into_a_hand_far_from_its_edges_gives_one_row_per_cluster_at_its_deepest_point():
    """A flat face pressed into a link away from the object's hull guards (corners, edges): only
    the surface guards see it (OMOMO box ×1.3: a face point 23 mm from the nearest guard went
    1.5 mm into a wrist unseen). One row per cluster of surface points that comes within reach of
    the link, at the point the link's distance grid puts deepest: the culling by cluster spheres
    loses none of them."""
    from dataclasses import replace

    import trimesh

    from otr_gym.robot_geometry import visual_meshes
    from retarget.inputs.meshes import TriMesh, as_trimesh, signed_distance
    from retarget.solver.object_rows import object_guard_rows, object_surface_rows
    from retarget.solver.probes import hull_guard_points, object_surface_guards

    problem = build_problem(resample_demonstration(clip("box_carry", 130, 133), 50.0))
    state = new_state(problem)
    fr = problem.kin.frames(state.data, state.q)
    name = "right_wrist_yaw_link"
    hand = robot.BODY_NAMES.index(name)
    link_mesh = visual_meshes()[name]
    low = (link_mesh.vertices @ fr.rot[hand].T + fr.pos[hand])[:, 2].argmin()
    lowest = link_mesh.vertices[low] @ fr.rot[hand].T + fr.pos[hand]
    top = lowest[2] + 0.003  # the board's top face 3 mm above the hand's lowest point
    box = trimesh.creation.box(extents=(1.0, 1.0, 0.02))
    board = TriMesh(np.asarray(box.vertices) + [lowest[0], lowest[1], top - 0.01], np.asarray(box.faces), "board")
    guards = object_surface_guards(board)
    track = replace(problem.channels[1], body=FIXED, surface_guards=guards,
                    guards=hull_guard_points(board.vertices, 0.008, along_edges=True))
    links, reach = np.flatnonzero(problem.link_grids.has_grid), problem.solver.check_margin_m
    centre_w = np.einsum("lij,lj->li", fr.rot, problem.link_center) + fr.pos
    hull_rows = object_guard_rows(problem, fr, centre_w, links, track, np.eye(3), np.zeros(3), reach)
    assert hand not in hull_rows.body_b, "the board's corners and edges are 0.5 m from the hand"

    # the face under the hand every millimetre, measured exactly against the link's mesh: it cuts in
    g = np.arange(-0.06, 0.0605, 0.001)
    face = np.stack(np.meshgrid(lowest[0] + g, lowest[1] + g, [top]), -1).reshape(-1, 3)
    hand_mesh = as_trimesh(link_mesh.vertices, link_mesh.faces, name)
    assert signed_distance(hand_mesh, (face - fr.pos[hand]) @ fr.rot[hand])[0].min() < -0.002

    rows = object_surface_rows(problem, fr, centre_w, links, track, np.eye(3), np.zeros(3), reach)
    at_hand = np.flatnonzero(rows.body_b == hand)
    assert np.all(rows.body_a[at_hand] == FIXED)
    # every guard point against the hand's grid, without any culling
    local = (guards.points - fr.pos[hand]) @ fr.rot[hand]
    d, _, inside = problem.link_grids.distance(local, np.full(len(local), hand))
    d = np.where(inside, d, np.inf)
    cluster = np.repeat(np.arange(len(guards.clusters.radius)), np.diff(guards.clusters.offsets))
    within = np.unique(cluster[d < reach])
    deepest = np.array([d[cluster == k].min() for k in within])
    assert d.min() < 0.0, "the grid sees the face inside the hand"
    assert len(at_hand) == len(within)
    np.testing.assert_allclose(np.sort(rows.value[at_hand] + problem.surface_margin[hand]), np.sort(deepest),
                               atol=1e-12)


def test_a_hand_that_holds_in_the_demonstration_is_pulled_in_from_beyond_the_grid_band():
    """A part in contact in the demonstration whose robot probes all lie beyond the object's
    grid band (15 cm) reads d = band there, with no gradient; its contact-state row must still
    pull it towards the demonstrated witness (the far field), or a smaller robot's knee or pelvis
    stays wherever it started (OMOMO chair: 19–22 cm away for 35 frames)."""
    from retarget.solver.rows import _ConstraintRows, _contact_state_rows, _robot_channel, _select_contact_rows

    problem = build_problem(resample_demonstration(clip("box_carry", 200, 203), 50.0))
    state = new_state(problem)  # the robot at its cold start, the box where the person holds it
    targets = frame_targets(problem, 0)
    c = next(k for k, tr in enumerate(problem.channels) if not tr.channel.is_ground)
    state.obj_pos[0] = state.obj_pos[0] + np.array([0.0, 0.0, 0.6])  # and lifted far above the hands
    fr = problem.kin.frames(state.data, state.q)
    centre_w = np.einsum("lij,lj->li", fr.rot, problem.link_center) + fr.pos
    pairs, _ = _robot_channel(problem, state, targets, fr, centre_w, c, _ConstraintRows([], []))
    assert pairs is not None and not pairs.query.in_band.any()  # every pair is demonstrated, none in the band
    selection = _select_contact_rows(problem, targets, [pairs])
    rows = _contact_state_rows(problem, fr, [pairs], selection)[0][0]  # (rows out of state per pair set, ...)
    names = np.array(robot.BODY_NAMES)[rows.body_a]
    hands = np.char.startswith(names, "left_wrist") | np.char.startswith(names, "right_wrist")
    # both hands held the box in these frames: a row on each (at the hand unit's closest probe)
    assert {n.split("_")[0] for n in names[hands]} == {"left", "right"}
    for k in np.flatnonzero(hands):
        assert rows.value[k] > 0.3  # far: |x − ŵ| less the demonstrated gap
        assert np.linalg.norm(rows.phi[k, :3]) > 0.99  # a unit pull, not the band's zero gradient
        assert rows.body_b[k] == FIXED and not rows.phi[k, 6:].any()  # the hand moves in, the box stays


def test_a_units_demonstrated_gap_is_its_whole_surface_and_decides_whether_it_is_held():
    """The contact-state rows judge a unit by the gap of its parts' whole surface, as the
    evaluation scores it, not by the few OT sources of its probes: on OMOMO's table those
    sources kept the person's forearm at 28 mm where its surface came within 19 mm, and the
    G1's forearm was held off the table (object recall 87 %)."""
    from dataclasses import replace

    from retarget.evaluation.units import default_units
    from retarget.inputs.meshes import as_trimesh, signed_distance
    from retarget.solver.rows import _ConstraintRows, _robot_channel, _select_contact_rows

    problem = build_problem(resample_demonstration(clip("box_carry", 200, 203), 50.0))
    c = next(k for k, tr in enumerate(problem.channels) if not tr.channel.is_ground)
    track = problem.channels[c]
    targets = frame_targets(problem, 1)
    # the gap of every unit's surface, measured exactly on the mesh at the demonstrated pose
    surface_w = problem.unit_surface.posed(problem.part_rot_w[1], problem.part_pos_w[1])
    local = (surface_w - track.pos_w[1]) @ track.rot_w[1]
    mesh = track.channel.mesh
    exact = signed_distance(as_trimesh(mesh.vertices, mesh.faces, "box"), local)[0]
    units = default_units()
    gaps = targets.unit_d[c]
    held = 0
    for u, unit in enumerate(units):
        mine = problem.unit_of_vertex == u
        want = min(exact[mine].min(), problem.band_m) if mine.any() else problem.band_m
        assert gaps[u] == pytest.approx(want, abs=1.5e-3), unit.name  # the grid's interpolation error
        held += want < problem.interaction.hold_m
    assert held >= 2  # both hands hold the box in these frames
    # a unit whose sources are all far but whose surface touches is to be pulled in to its gap
    state = new_state(problem)
    fr = problem.kin.frames(state.data, state.q)
    centre_w = np.einsum("lij,lj->li", fr.rot, problem.link_center) + fr.pos
    pairs, _ = _robot_channel(problem, state, targets, fr, centre_w, c, _ConstraintRows([], []))
    hand = robot.body_indices(["left_wrist_yaw_link"])[0]
    u = problem.contact_units[hand]
    far_sources = [ld.copy() for ld in targets.robot_link_d]
    far_sources[c][problem.contact_units == u] = 0.05
    unit_d = [g.copy() for g in targets.unit_d]
    unit_d[c][u] = 0.004
    sel = _select_contact_rows(problem, replace(targets, robot_link_d=tuple(far_sources), unit_d=tuple(unit_d)),
                               [pairs])
    mine = problem.contact_units[problem.robot.body[sel.probe]] == u
    assert mine.sum() == 1 and sel.touching[mine].all() and sel.target[mine] == pytest.approx(0.004)
    # and one whose surface stays 5 cm off is held out to the clearance, whatever its sources say
    unit_d[c][u] = 0.05
    far_sources[c][problem.contact_units == u] = 0.0
    sel = _select_contact_rows(problem, replace(targets, robot_link_d=tuple(far_sources), unit_d=tuple(unit_d)),
                               [pairs])
    mine = problem.contact_units[problem.robot.body[sel.probe]] == u
    assert not sel.touching[mine].any() and sel.target[mine] == pytest.approx(problem.interaction.clearance_m)


def test_the_extreme_rows_group_sums_repeat_numpys_pairwise_sum_bit_for_bit():
    """``rows._pairwise_sum`` repeats numpy's summation tree (8 accumulators up to 128 terms,
    halves rounded to multiples of 8 beyond) over gathered rows: its sums must equal
    np.add.reduce exactly, across the 128-term boundary and several levels."""
    import numba

    from retarget.solver.seed_rows import _pairwise_sum

    @numba.njit
    def gathered_sum(x, rows, col, lo, n):  # the helper has no Python entry point of its own
        return _pairwise_sum(x, rows, col, lo, n)

    rng = np.random.default_rng(7)
    for n in (1, 7, 8, 9, 127, 128, 129, 136, 255, 256, 1000, 4099):
        x = rng.normal(size=(n + 9, 3)) * 10.0 ** rng.uniform(-4, 4, size=(n + 9, 3))
        rows = rng.permutation(n + 9)[: n + 4].astype(np.intp)
        for col in range(3):
            expected = np.add.reduce(x[rows[3:3 + n], col].copy())
            got = gathered_sum(x, rows, np.int64(col), 3, n)
            assert got == expected, (n, col, got - expected)
    # not merely close: a plain left-to-right sum of the same terms differs somewhere
    x = rng.normal(size=(1000, 1)) * 10.0 ** rng.uniform(-4, 4, size=(1000, 1))
    assert float(np.cumsum(x[:, 0])[-1]) != gathered_sum(x, np.arange(1000), np.int64(0), 0, 1000)


def test_link_clearance_keeps_the_named_links_that_far_from_the_object():
    demo = resample_demonstration(clip("box_carry", 130, 140), 50.0)  # the hands close on the box
    plain = retarget_demonstration(demo, RetargetConfig())
    clearance = 0.02
    hands = {link: clearance for link in robot.HANDS}
    kept = retarget_demonstration(demo, RetargetConfig(solver=SolverConfig(link_clearance_m=hands)))

    def hand_gap(ref) -> float:  # the hand units' smallest distance to the box over the clip
        c = ref.contacts
        units = [i for i, name in enumerate(c.body_names) if name.startswith(tuple(robot.HANDS))]
        return float(c.distance[:, units, c.channel_names.index("box")].min())

    assert hand_gap(plain) < 0.005  # the hands grasp the box
    assert hand_gap(kept) >= clearance - EPS_COL
    with pytest.raises(ValueError, match="unknown G1 link 'palm'"):
        retarget_demonstration(demo, RetargetConfig(solver=SolverConfig(link_clearance_m={"palm": 0.01})))
