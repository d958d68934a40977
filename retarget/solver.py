"""Trust-region SQP over the G1 configuration and every free object's pose (paper Sec. III-D).

Per frame t the solver minimises E_int + E_sty,r + E_sty,o + ‖q_t ⊖ q_{t−1}‖² subject to joint
limits, joint velocity limits, object displacement boxes, non-penetration of every probe–channel
pair and capsule self-collision (eq. m-program, m-qp). Each SQP iterate linearises everything
(Gauss–Newton Hessian, analytic Jacobians) into a dense QP solved by ProxQP, whose workspace is
reused across iterations and frames (``QPWorkspace``; ProxQP's own warm start from its previous
result is a switch, off because it measured slower). The SQP is warm-started: each frame starts
from the previous solution moved by the demonstrated displacement (``warm_start``).

Decision variables δ = (δv, δξ_1, …, δξ_O): δv ∈ R³⁵ the Pinocchio tangent of the G1 (base
twist in the base frame, then joints), δξ_o = (δτ, δθ) ∈ R⁶ per free object (retraction
τ ← τ + δτ, R ← exp(δθ)R). Every residual/constraint row is a pair of 6-vectors φ on the two
bodies it involves (``retarget.residuals.Rows``); with one (6, n) Jacobian per body the QP is
assembled per run of rows sharing their bodies: H += Jᵀ(Σ w φφᵀ)J, so its cost grows with the
number of (link, channel) pairs, not with the number of probes.

Hot-path economy: links are culled per channel by bounding spheres before any probe is posed,
probes are posed with one matrix product per link, the QP gets only the constraint rows that
can bind (per link and channel, the extreme points of the rows closer than a margin), and
every QP solution is checked against all pairs in the band, adding the violated rows.

The immutable :class:`Problem` (probes, channels, targets) is built by ``retarget.problem``;
the mutable :class:`SolverState` holds the iterate, the previous frame and the QP workspace.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import cached_property

import numba
import numpy as np
import pinocchio as pin
from proxsuite import proxqp
from threadpoolctl import threadpool_limits

from otr_gym import robot
from otr_gym.rotations import so3_exp, so3_log
from retarget.arm_seed import arm_links, seed_arms
from retarget.geometry import Channel, ProximityQuery
from retarget.kinematics import NUM_LINKS, LinkFrames, RobotKinematics
from retarget.margins import ErrorMargin
from retarget.probes import ProbeSet
from retarget.residuals import (
    FIXED,
    InteractionConfig,
    PairSet,
    Rows,
    Triples,
    cross,
    interaction_rows,
    signed_distance_rows,
    to_channel_frame,
    twist_factors,
)
from retarget.style import StyleConfig, StyleTargets, pose_rows


@dataclass(frozen=True)
class SolverConfig:
    """SQP budget, trust region and constraint settings (eq. m-qp; METHOD.md "Solver")."""

    #: Iterations on the cold-started first frame and on warm-started frames (Sec. III-D).
    first_frame_iterations: int = 50
    iterations: int = 6
    #: Stop when ‖δ‖∞ falls below this (Sec. III-D).
    step_tolerance: float = 1e-4
    #: Per-DoF trust region: 5 cm on translations, 0.10 rad on rotations and joints (eq. m-qp-tr).
    trust_linear_m: float = 0.05
    trust_angular_rad: float = 0.10
    #: ε_col: non-penetration d + gᵀδ ≥ −ε_col (eq. m-qp-col).
    penetration_tolerance_m: float = 3e-4
    #: Our choice: pairs closer than this seed the QP's constraint rows; every other pair of the
    #: band is checked against each QP solution and added if its linearisation is violated.
    constraint_margin_m: float = 0.02
    #: Our choice: pairs closer than this are checked against each QP solution (farther ones
    #: would need one step to close more than 5 cm; the end-of-frame pass checks all pairs).
    check_margin_m: float = 0.05
    #: Our choice: if a frame's budget ends with a violation beyond ε_col, up to this many
    #: restoration steps (smallest move the linearised constraints accept) follow, the k-th
    #: within the trust region × ``feasibility_trust_scale``^k.
    feasibility_iterations: int = 10
    feasibility_trust_scale: float = 0.5
    #: Trust-region update (our choice; the paper fixes the boxes): a rejected step shrinks
    #: the per-DoF boxes to this fraction of its own extent, an accepted one that met the model
    #: doubles them back (never above 5 cm / 0.10 rad).
    trust_shrink: float = 0.25
    #: Our choice: a frame also stops when the model predicts less than this relative decrease
    #: of the merit. Measured on the OMOMO box carry: below ~1e-4 of the merit the proximity
    #: terms' non-smoothness (witnesses jumping across box edges) dominates the model's
    #: prediction, and the steps that follow move the robot by millimetres (1e-5 took 5.3
    #: iterations per frame, 1e-4 4.2, with the same quality figures).
    model_tolerance: float = 1e-4
    #: Our choice: a frame also stops when a step predicted to gain less than this fraction of
    #: the merit is rejected: the model is then no better than the merit's non-smoothness,
    #: and the shrunken steps after it gained 1e-4 of the merit (median) on the box carry.
    rejected_model_tolerance: float = 1e-3
    #: L1 penalty (per m of violation beyond ε_col, summed over pairs) in the merit function.
    violation_penalty: float = 100.0
    #: b_env (our choice): per-frame deviation of an object's displacement from the demonstrated
    #: displacement, (m, rad). 2 cm and 0.05 rad per frame at 50 fps (1 m/s, 2.5 rad/s of
    #: velocity change): free enough to re-time a lift, too tight for a resting box to jump.
    object_step_box: tuple[float, float] = (0.02, 0.05)
    #: b_cor (our choice): deviation from the demonstrated pose, (m, rad). The paper's boxes
    #: drift 3–27 cm; 0.35 m / 0.6 rad bounds that with margin.
    object_deviation_box: tuple[float, float] = (0.35, 0.6)
    #: Our choice: an object closer than this to a robot link is "held" and the warm start of
    #: the next frame moves it rigidly with the robot (``warm_start``).
    hold_distance_m: float = 0.01
    #: Weight of ‖q_t ⊖ q_{t−1}‖² (eq. m-program: 1).
    previous_frame_weight: float = 1.0
    #: Levenberg damping on every variable, only for a well-posed QP (no physical meaning).
    damping: float = 1e-6
    #: ProxQP absolute tolerance; steps are converged at 1e-4, so 1e-7 is ample.
    qp_eps_abs: float = 1e-7
    #: Warm-start ProxQP from its previous result (same workspace, updated in place). Off by
    #: default, measured: replaying 424 QPs of the OMOMO box carry, the previous result made
    #: ProxQP slower (3.76 vs 1.04 ms per solve; median 31 vs 16 iterations, worst 680 vs 42):
    #: the constraint rows change between iterates, so the previous duals point the wrong way.
    #: The workspace itself is still reused (update, no re-allocation) when sizes repeat.
    qp_warm_start: bool = False


@dataclass(frozen=True)
class ChannelTrack:
    """A channel of the scene and its pose: fixed (ground, furniture, pinned objects) or free."""

    name: str
    channel: Channel
    body: int  # FIXED or the solver body index of a free object (NUM_LINKS + i)
    pos_w: np.ndarray  # (T, 3) pose when fixed; demonstrated pose when free
    rot_w: np.ndarray  # (T, 3, 3)
    lower: np.ndarray  # (3,) channel-frame bounds of the surface (−inf for the ground)
    upper: np.ndarray  # (3,)
    guards: np.ndarray  # (G, 3) channel frame: hull vertices and edge points (none for the ground)
    margin: ErrorMargin | None  # grid − exact distance bound, subtracted in non-penetration rows

    @property
    def is_ground(self) -> bool:
        return bool(self.channel.is_ground)


@dataclass(frozen=True)
class FreeObject:
    """A manipulated object: a decision variable, a channel for the robot, and a probe carrier."""

    name: str
    channel: int  # index of its ChannelTrack
    probes: np.ndarray  # (P_o, 3) object frame


@dataclass(frozen=True)
class Problem:
    """Everything precomputed for one demonstration (immutable)."""

    fps: float
    kin: RobotKinematics
    robot: ProbeSet  # area samples (cost and constraints), link frames
    guards: ProbeSet  # hull vertices (constraints against the ground), link frames
    vertex_guards: ProbeSet  # mesh vertices + hull vertices (constraints against objects), link frames
    link_center: np.ndarray  # (L, 3) link frame: bounding sphere of probes and guards
    link_radius: np.ndarray  # (L,)
    guard_anchor: np.ndarray  # (G,) nearest area probe (same link) of each hull guard
    guard_anchor_d: np.ndarray  # (G,) m, their separation
    vertex_anchor: np.ndarray  # (V,) the same for the vertex guards
    vertex_anchor_d: np.ndarray  # (V,)
    sampling_gap: np.ndarray  # (L,) m: largest vertex-to-nearest-probe distance of each link
    link_grids: tuple  # per link: VoxelGrid of its signed distance (link frame), or None without a mesh
    demo_points: ProbeSet  # src(p) of each robot probe, on its human part (part frame)
    part_pos_w: np.ndarray  # (T, 22, 3) demonstration part positions (world)
    part_rot_w: np.ndarray  # (T, 22, 3, 3)
    channels: tuple[ChannelTrack, ...]
    objects: tuple[FreeObject, ...]
    style: StyleTargets
    q_init: np.ndarray  # (nq,) Pinocchio configuration for the cold start
    interaction: InteractionConfig
    style_cfg: StyleConfig
    solver: SolverConfig
    band_m: float  # d̄

    @property
    def num_frames(self) -> int:
        return int(self.part_pos_w.shape[0])

    @cached_property
    def trust(self) -> np.ndarray:
        """Full per-DoF trust region (n,): 5 cm on translations, 0.10 rad on rotations (eq. m-qp-tr)."""
        cfg, nv = self.solver, self.kin.nv
        return np.concatenate([np.full(3, cfg.trust_linear_m), np.full(nv - 3, cfg.trust_angular_rad),
                               np.tile(np.r_[np.full(3, cfg.trust_linear_m), np.full(3, cfg.trust_angular_rad)],
                                       len(self.objects))])

    @cached_property
    def style_bodies(self) -> np.ndarray:
        """Bodies with a style cost: the tracked links, then the free objects."""
        return np.concatenate([self.style.links, NUM_LINKS + np.arange(len(self.objects))])

    @cached_property
    def style_weights(self) -> tuple[np.ndarray, np.ndarray]:
        """(λ_pos, λ_rot) of every style body (eq. m-esty-o)."""
        cfg, n_links, n_obj = self.style_cfg, len(self.style.links), len(self.objects)
        return (np.r_[np.full(n_links, cfg.pos_weight), np.full(n_obj, cfg.object_pos_weight)],
                np.r_[np.full(n_links, cfg.rot_weight), np.full(n_obj, cfg.object_rot_weight)])

    @cached_property
    def guard_reach(self) -> np.ndarray:
        """(L,) m: the largest anchor separation among each link's hull guards."""
        return _per_body_max(self.guards.body, self.guard_anchor_d)

    @cached_property
    def vertex_reach(self) -> np.ndarray:
        """(L,) m: the largest anchor separation among each link's vertex guards."""
        return _per_body_max(self.vertex_guards.body, self.vertex_anchor_d)

    @property
    def num_variables(self) -> int:
        return self.kin.nv + 6 * len(self.objects)


def _per_body_max(body: np.ndarray, value: np.ndarray) -> np.ndarray:
    out = np.zeros(NUM_LINKS)
    np.maximum.at(out, body, value)
    return out


# ------------------------------------------------------------------ per-frame targets


@dataclass(frozen=True)
class FrameTargets:
    """Demonstrated quantities of frame t, computed once before its SQP iterations."""

    t: int
    robot: tuple[Triples, ...]  # per channel, for every robot probe (d̂ = d̄ when far)
    robot_active: tuple[np.ndarray, ...]  # per channel (P,) bool: d̂ < d̄
    robot_links: tuple[np.ndarray, ...]  # per channel (L,) bool: links with an active probe
    objects: tuple[tuple[Triples | None, ...], ...]  # per free object, per channel (None: own channel)
    objects_active: tuple[tuple[np.ndarray | None, ...], ...]
    obj_pos: np.ndarray  # (O, 3) demonstrated object poses
    obj_rot: np.ndarray  # (O, 3, 3)
    style_pos: np.ndarray  # (S + O, 3) style targets of ``Problem.style_bodies``
    style_rot: np.ndarray  # (S + O, 3, 3)


def _near(track: ChannelTrack, x_c: np.ndarray, reach: float) -> np.ndarray:
    """Points (channel frame) inside the channel's bounds grown by ``reach``."""
    if track.is_ground:
        return x_c[:, 2] < reach
    return np.all((x_c > track.lower - reach) & (x_c < track.upper + reach), axis=1)


def _far_triples(n: int, band: float) -> Triples:
    return Triples(np.full(n, band), np.zeros((n, 3)), np.zeros((n, 3)))


def _demo_triples(track: ChannelTrack, x_w: np.ndarray, rot: np.ndarray, pos: np.ndarray,
                  band: float) -> tuple[Triples, np.ndarray]:
    """Triples of demonstrated points against a channel; only points near it are queried."""
    x_c = to_channel_frame(x_w, rot, pos)
    near = np.flatnonzero(_near(track, x_c, band))
    out = _far_triples(len(x_w), band)
    if len(near):
        # once per frame: the exact witness where the grid's blend is unreliable (geometry doc)
        q = track.channel.query(x_c[near], exact_witness=True)
        out.d[near], out.w[near], out.n[near] = q.d, q.w, q.n
        # ŵ's place in the geodesic table, for the r^x rows of every iterate of the frame
        hat = track.channel.geodesic_weights(q.w)
        if hat is not None:
            geodesic = tuple(np.zeros((len(x_w),) + h.shape[1:], h.dtype) for h in hat)
            for full, part in zip(geodesic, hat):
                full[near] = part
            out = Triples(out.d, out.w, out.n, geodesic)
    return out, out.d < band


def frame_targets(problem: Problem, t: int) -> FrameTargets:
    """Demonstrated triples of robot probes (through src(p)) and object probes at frame t."""
    band = problem.band_m
    human_w = problem.demo_points.posed(problem.part_rot_w[t], problem.part_pos_w[t])
    robot_t, robot_a, robot_l = [], [], []
    for track in problem.channels:
        tri, active = _demo_triples(track, human_w, track.rot_w[t], track.pos_w[t], band)
        robot_t.append(tri)
        robot_a.append(active)
        robot_l.append(np.bincount(problem.robot.body[active], minlength=NUM_LINKS) > 0)
    obj_t, obj_a = [], []
    for obj in problem.objects:
        own = problem.channels[obj.channel]
        x_w = obj.probes @ own.rot_w[t].T + own.pos_w[t]
        per_t, per_a = [], []
        for c, track in enumerate(problem.channels):
            if c == obj.channel:
                per_t.append(None)
                per_a.append(None)
                continue
            tri, active = _demo_triples(track, x_w, track.rot_w[t], track.pos_w[t], band)
            per_t.append(tri)
            per_a.append(active)
        obj_t.append(tuple(per_t))
        obj_a.append(tuple(per_a))
    obj_pos = np.array([problem.channels[o.channel].pos_w[t] for o in problem.objects]).reshape(-1, 3)
    obj_rot = np.array([problem.channels[o.channel].rot_w[t] for o in problem.objects]).reshape(-1, 3, 3)
    return FrameTargets(t, tuple(robot_t), tuple(robot_a), tuple(robot_l), tuple(obj_t), tuple(obj_a),
                        obj_pos, obj_rot, np.concatenate([problem.style.pos_w[t], obj_pos]),
                        np.concatenate([problem.style.rot_w[t], obj_rot]))


# ------------------------------------------------------------------ state


class QPWorkspace:
    """ProxQP dense problems kept alive per (n, padded n_in): updated, not re-initialised, when
    the sizes repeat, so their buffers (and, with ``warm_start``, their last primal/dual
    solution) carry over between SQP iterations and frames. Constraint rows are padded with inactive rows to a
    multiple of ``pad`` so that sizes repeat.

    If ProxQP does not converge (linearised constraints in conflict within the trust region),
    the step is re-solved asking penetrating rows only not to get worse, then without
    constraint rows, so the SQP always moves; the trust-region test then judges the step.
    """

    def __init__(self, eps_abs: float, warm_start: bool = False, pad: int = 16) -> None:
        self.eps_abs = eps_abs
        self.warm_start = warm_start
        self.pad = pad
        self._qps: dict[tuple[int, int], proxqp.dense.QP] = {}
        self.solves = 0
        self.failures = 0

    def solve(self, H, g, C, lower, box_lo, box_hi) -> np.ndarray:
        x, ok = self._solve(H, g, C, lower, box_lo, box_hi)
        if not ok:
            self.failures += 1
            x, ok = self._solve(H, g, C, np.minimum(lower, 0.0), box_lo, box_hi)
        if not ok:
            x, _ = self._solve(H, g, C[:0], lower[:0], box_lo, box_hi)
        return x

    def _solve(self, H, g, C, lower, box_lo, box_hi) -> tuple[np.ndarray, bool]:
        self.solves += 1
        n, m = H.shape[0], C.shape[0]
        m_pad = max(self.pad, -(-m // self.pad) * self.pad)
        upper = np.full(m_pad, 1e20)
        if m_pad != m:
            C = np.vstack([C, np.zeros((m_pad - m, n))])
            lower = np.concatenate([lower, np.full(m_pad - m, -1e20)])
        key = (n, m_pad)
        qp = self._qps.get(key)
        if qp is None:
            # measured on the box carry: the primal-dual factorisation is 1.5× faster at these sizes
            qp = proxqp.dense.QP(n, 0, m_pad, True, proxqp.dense.HessianType.Dense,
                                 proxqp.dense.DenseBackend.PrimalDualLDLT)
            qp.settings.eps_abs = self.eps_abs
            qp.settings.eps_rel = 0.0
            # Measured on 1076 QPs of the OMOMO box carry: at most 21 outer iterations when solved,
            # and the same solutions (to 2e-15) with these caps as with 1000 × 1500. A QP whose
            # linearised constraints conflict is not detected as infeasible: with the defaults it
            # took up to 40 s to give up (with 30 × 100, ≤ 0.5 s even at 1300 rows); ``solve`` then
            # relaxes the rows as for any failure.
            qp.settings.max_iter = 30
            qp.settings.max_iter_in = 100
            qp.settings.initial_guess = (proxqp.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT if self.warm_start
                                         else proxqp.InitialGuess.NO_INITIAL_GUESS)
            qp.init(H, g, None, None, C, lower, upper, box_lo, box_hi)
            self._qps[key] = qp
        else:
            qp.update(H, g, None, None, C, lower, upper, box_lo, box_hi, update_preconditioner=True)
        qp.solve()
        ok = qp.results.info.status == proxqp.QPSolverOutput.PROXQP_SOLVED
        return qp.results.x.copy(), ok


@dataclass
class SolverState:
    """The mutable part: the iterate, the previous frame's solution and the QP workspace."""

    data: pin.Data
    q: np.ndarray  # (nq,) Pinocchio
    obj_pos: np.ndarray  # (O, 3)
    obj_rot: np.ndarray  # (O, 3, 3)
    qp: QPWorkspace
    prev: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (q, obj_pos, obj_rot) of t − 1
    prev_demo: tuple[np.ndarray, np.ndarray] | None = None  # demonstrated object poses at t − 1


@dataclass
class FrameStats:
    iterations: int = 0  # QP steps tried
    rejected: int = 0  # of which undone by the trust-region test
    qp_rows: list[int] = field(default_factory=list)
    active_pairs: int = 0
    min_distance_m: float = np.inf  # smallest probe/guard distance to any collidable channel
    min_self_distance_m: float = np.inf
    timings: dict[str, float] = field(default_factory=dict)


class _Timer:
    """Accumulates wall time per section into a dict (the benchmark's profile)."""

    def __init__(self, stats: dict[str, float]) -> None:
        self.stats = stats
        self.t = time.perf_counter()

    def lap(self, key: str) -> None:
        now = time.perf_counter()
        self.stats[key] = self.stats.get(key, 0.0) + now - self.t
        self.t = now


# ------------------------------------------------------------------ linearisation


@dataclass(frozen=True)
class Linearisation:
    cost: Rows
    constraints: Rows  # every surface pair in the band, then the close capsule pairs
    surface_channel: np.ndarray  # (S,) channel code of the surface rows (``initial_constraints``)
    margin: float  # m: surface rows closer than this may seed the first QP
    frames: LinkFrames
    active_pairs: int
    min_distance: float
    min_self_distance: float
    counts: np.ndarray  # (L + O,) active probes per link and object at this iterate (N_ℓ)

    @cached_property
    def initial(self) -> np.ndarray:
        """Indices of ``constraints`` put in the first QP: the surface rows chosen by
        :func:`initial_constraints`, then every capsule row. Computed on first use: a trial
        iterate that the trust-region test rejects never needs it."""
        k = len(self.surface_channel)
        c = self.constraints
        surface = Rows(c.value[:k], c.weight[:k], c.phi[:k], c.body_a[:k], c.body_b[:k])
        return np.concatenate([initial_constraints(surface, self.surface_channel, self.margin),
                               np.arange(k, len(c))])


def _channel_pose(state: SolverState, track: ChannelTrack, t: int) -> tuple[np.ndarray, np.ndarray]:
    if track.body == FIXED:
        return track.rot_w[t], track.pos_w[t]
    i = track.body - NUM_LINKS
    return state.obj_rot[i], state.obj_pos[i]


def _candidate_links(problem: Problem, track: ChannelTrack, centre_w: np.ndarray, rot_c: np.ndarray,
                     pos_c: np.ndarray) -> np.ndarray:
    """(L,) links whose bounding sphere comes within the band of the channel's bounds."""
    if track.is_ground:
        gap = centre_w[:, 2]
    else:
        c = to_channel_frame(centre_w, rot_c, pos_c)
        gap = np.linalg.norm(np.maximum(0.0, np.maximum(track.lower - c, c - track.upper)), axis=1)
    return gap - problem.link_radius < problem.band_m


def _take(q: ProximityQuery, index: np.ndarray) -> ProximityQuery:
    """The answers of ``index`` (np.take: several times faster than fancy indexing of rows)."""
    return ProximityQuery(d=np.take(q.d, index), w=np.take(q.w, index, axis=0),
                          n=None if q.n is None else np.take(q.n, index, axis=0),
                          grad_d=np.take(q.grad_d, index, axis=0), dw_dx=np.take(q.dw_dx, index, axis=0),
                          in_band=np.take(q.in_band, index))


def _rows_take(rows: Rows, index: np.ndarray) -> Rows:
    return Rows(np.take(rows.value, index), np.take(rows.weight, index), np.take(rows.phi, index, axis=0),
                np.take(rows.body_a, index), np.take(rows.body_b, index))


#: Rows are grouped by the nearest of these 6 directions to their distance gradient; each group
#: keeps its extreme points under tilts in 8 directions perpendicular to the group's gradient.
_BINS = np.concatenate([np.eye(3), -np.eye(3)])
_ANGLES = np.arange(8) * (np.pi / 4)


def initial_constraints(rows: Rows, channel: np.ndarray, margin: float, tilt_rad: float = 0.2) -> np.ndarray:
    """Rows to put in the first QP: among those closer than ``margin``, per group (body,
    channel, binned gradient a), the rows that are smallest after a small rotation ω of the
    body perpendicular to a (|ω| = ``tilt_rad``, 8 directions, and ω = 0).

    A row reads d_p + a·v + ω·((x_p − o) × a). Over a group a is nearly constant, so the row
    that binds first for a step (v, ω) is the minimiser of d_p + ω·φ_p[3:6]: an extreme point
    of the group (for a plane, a vertex of the convex hull); ω along a does not change it. The
    others are implied to first order; ``qp_step`` checks every candidate row after each QP and
    adds any violated one, so this choice affects speed, never feasibility.
    """
    close = np.flatnonzero(rows.value < margin)
    if len(close) == 0:
        return close
    a = rows.phi[close, :3]
    key = (rows.body_a[close] * 64 + channel[close]) * 32 + np.argmax(a @ _BINS.T, axis=1)
    order = np.argsort(key, kind="stable")
    starts = np.flatnonzero(np.concatenate([[True], np.diff(key[order]) != 0]))
    counts = np.diff(np.concatenate([starts, [len(close)]]))
    mean_a = np.add.reduceat(a[order], starts, axis=0)
    mean_a /= np.maximum(np.linalg.norm(mean_a, axis=1, keepdims=True), 1e-12)
    t1 = cross(mean_a, np.eye(3)[np.argmin(np.abs(mean_a), axis=1)])
    t1 /= np.maximum(np.linalg.norm(t1, axis=1, keepdims=True), 1e-12)
    t2 = cross(mean_a, t1)
    tilts = (np.cos(_ANGLES)[None, :, None] * t1[:, None] + np.sin(_ANGLES)[None, :, None] * t2[:, None])  # (G, 8, 3)
    moment = rows.phi[close[order], 3:6]
    scores = rows.value[close[order], None] + tilt_rad * np.einsum("kj,kdj->kd", moment,
                                                                   np.repeat(tilts, counts, axis=0))
    scores = np.concatenate([rows.value[close[order], None], scores], axis=1)  # (k, 9)
    best = np.minimum.reduceat(scores, starts, axis=0)
    extreme = (scores <= np.repeat(best, counts, axis=0)).any(axis=1)
    return np.sort(close[order[extreme]])


def _distance_block(track: ChannelTrack, rot_c: np.ndarray, pos_c: np.ndarray, x_w: np.ndarray, x_c: np.ndarray,
                    body: np.ndarray, origin: np.ndarray, d: np.ndarray, grad_c: np.ndarray) -> Rows:
    """Non-penetration rows of points against a channel: the grid distance minus the grid's
    measured error bound there (``retarget.margins``), so that the exact surface is respected."""
    value = d - track.margin.at(x_c) if track.margin is not None else d
    return signed_distance_rows(value, grad_c, x_w, origin, body, track.body, rot_c, pos_c)


def linearise(problem: Problem, state: SolverState, targets: FrameTargets, timings: dict[str, float],
              counts: np.ndarray | None = None) -> Linearisation:
    """All rows of the QP at the current iterate.

    ``counts`` (L + O,) fixes N_ℓ, the active probe count of each link and object, instead of
    counting at this iterate: ``solve_frame`` counts once per frame, so that E stays a smooth
    function of the iterate within the frame (a count that jumps by one as a probe crosses d̄
    rescales the whole link's term, and the trust-region test would read that as model error).
    """
    tm = _Timer(timings)
    band, margin = problem.band_m, problem.solver.constraint_margin_m
    check = problem.solver.check_margin_m
    fr = problem.kin.frames(state.data, state.q)
    centre_w = np.einsum("lij,lj->li", fr.rot, problem.link_center) + fr.pos
    tm.lap("kinematics")

    robot_pairs = []
    con_rows: list[Rows] = []
    con_channel: list[np.ndarray] = []
    active_links: list[np.ndarray] = []
    link_min = np.full((len(problem.channels), NUM_LINKS), np.inf)
    for c, track in enumerate(problem.channels):
        rot_c, pos_c = _channel_pose(state, track, targets.t)
        near_links = _candidate_links(problem, track, centre_w, rot_c, pos_c)
        # area probes: near links, and links with a probe in contact range in the demonstration
        links = np.flatnonzero(near_links | targets.robot_links[c])
        idx, x_w = problem.robot.posed_bodies(links, fr.rot, fr.pos)
        # distance of every area probe, or a lower bound (the band) where not queried
        probe_d = np.full(len(problem.robot), band)
        if len(idx):
            x_c = to_channel_frame(x_w, rot_c, pos_c)
            demo_active = targets.robot_active[c][idx]
            sel = np.flatnonzero(_near(track, x_c, band) | demo_active)
            q = track.channel.query(np.take(x_c, sel, axis=0), normals=False)
            probe_d[idx[sel]] = q.d
            active = np.flatnonzero(q.in_band | demo_active[sel])
            a = sel[active]
            robot_pairs.append((c, rot_c, pos_c, idx[a], np.take(x_w, a, axis=0), np.take(x_c, a, axis=0),
                                _take(q, active)))
            active_links.append(idx[a])
            # Against the ground the hull vertices (guards) imply every area probe: skip those.
            if not track.is_ground:
                ib = np.flatnonzero(q.in_band & (q.d < check))
                pts, body = sel[ib], problem.robot.body[idx[sel[ib]]]
                con_rows.append(_distance_block(track, rot_c, pos_c, np.take(x_w, pts, axis=0),
                                                np.take(x_c, pts, axis=0), body, np.take(fr.pos, body, axis=0),
                                                q.d[ib], np.take(q.grad_d, ib, axis=0)))
                con_channel.append(np.full(len(ib), c))
        link_min[c] = np.minimum.reduceat(probe_d, problem.robot.offsets[:-1])
        # Guard points: the distance field is 1-Lipschitz, so a guard is at least as far as its
        # nearest area probe (its anchor) minus their separation; only guards whose bound is
        # within the margin can be close enough to matter, the rest are provably clear. A link
        # whose closest probe, less its farthest anchor separation, is beyond the margin has
        # no such guard: its guards are not even looked at.
        guards, anchor, anchor_d, reach = ((problem.guards, problem.guard_anchor, problem.guard_anchor_d,
                                            problem.guard_reach) if track.is_ground
                                           else (problem.vertex_guards, problem.vertex_anchor, problem.vertex_anchor_d,
                                                 problem.vertex_reach))
        gi = guards.indices_of(np.flatnonzero(near_links & (link_min[c] - reach < margin)))
        gi = gi[probe_d[anchor[gi]] - anchor_d[gi] < margin]
        if len(gi):
            gb = guards.body[gi]
            g_w = guards.posed_index(gi, fr.rot, fr.pos)
            g_c = to_channel_frame(g_w, rot_c, pos_c)
            d, grad, in_band = track.channel.distance(g_c)
            ib = np.flatnonzero(in_band & (d < check))
            body = gb[ib]
            con_rows.append(_distance_block(track, rot_c, pos_c, np.take(g_w, ib, axis=0), np.take(g_c, ib, axis=0),
                                            body, np.take(fr.pos, body, axis=0), d[ib], np.take(grad, ib, axis=0)))
            con_channel.append(np.full(len(ib), c))
    tm.lap("robot_channels")

    cost: list[Rows] = []
    total_pairs = 0
    # f_ℓ/N_ℓ: N_ℓ counts the distinct active probes of link ℓ over all channels
    active_any = np.zeros(len(problem.robot), dtype=bool)
    for probes in active_links:
        active_any[probes] = True
    n_active = link_counts = np.bincount(problem.robot.body[active_any], minlength=NUM_LINKS)
    if counts is not None:
        n_active = counts[:NUM_LINKS]
    norm_link = problem.interaction.link_weight / np.maximum(n_active, 1)
    for c, rot_c, pos_c, idx, x_w, x_c, q in robot_pairs:
        track = problem.channels[c]
        body = problem.robot.body[idx]
        ps = PairSet(x_w, x_c, np.take(fr.pos, body, axis=0), body, track.body, rot_c, pos_c, q,
                     targets.robot[c].take(idx), norm_link[body])
        cost.append(interaction_rows(ps, track.channel, problem.interaction.robot_weights, problem.interaction))
        total_pairs += len(idx)
    tm.lap("robot_rows")

    object_counts: list[int] = []
    for i, obj in enumerate(problem.objects):
        body = NUM_LINKS + i
        o_w = obj.probes @ state.obj_rot[i].T + state.obj_pos[i]
        own = problem.channels[obj.channel]
        pairs = []
        for c, track in enumerate(problem.channels):
            if c == obj.channel:
                continue
            rot_c, pos_c = _channel_pose(state, track, targets.t)
            o_c = to_channel_frame(o_w, rot_c, pos_c)
            demo_active = targets.objects_active[i][c]
            sel = np.flatnonzero(_near(track, o_c, band) | demo_active)
            if len(sel) == 0:
                continue
            q = track.channel.query(np.take(o_c, sel, axis=0), normals=False)
            active = np.flatnonzero(q.in_band | demo_active[sel])
            pairs.append((c, track, rot_c, pos_c, sel[active], _take(q, active)))
            ib = np.flatnonzero(q.in_band & (q.d < check))
            pts = sel[ib]
            con_rows.append(_distance_block(track, rot_c, pos_c, np.take(o_w, pts, axis=0), np.take(o_c, pts, axis=0),
                                            np.full(len(ib), body), np.broadcast_to(state.obj_pos[i], (len(ib), 3)),
                                            q.d[ib], np.take(q.grad_d, ib, axis=0)))
            con_channel.append(np.full(len(ib), c))
            # the object's own hull guards against the ground, furniture and other objects
            g_w = own.guards @ state.obj_rot[i].T + state.obj_pos[i]
            g_c = to_channel_frame(g_w, rot_c, pos_c)
            gs = np.flatnonzero(_near(track, g_c, check))
            if len(gs):
                d, grad, in_band = track.channel.distance(g_c[gs])
                gb = np.flatnonzero(in_band & (d < check))
                con_rows.append(_distance_block(track, rot_c, pos_c, g_w[gs[gb]], g_c[gs[gb]], np.full(len(gb), body),
                                                np.broadcast_to(state.obj_pos[i], (len(gb), 3)), d[gb], grad[gb]))
                con_channel.append(np.full(len(gb), c))
        active_any = np.zeros(len(obj.probes), dtype=bool)
        for pair in pairs:
            active_any[pair[4]] = True
        n_obj_active = int(active_any.sum()) if counts is None else int(counts[NUM_LINKS + i])
        object_counts.append(int(active_any.sum()))
        for c, track, rot_c, pos_c, sel, q in pairs:
            ps = PairSet(o_w[sel], to_channel_frame(o_w[sel], rot_c, pos_c),
                         np.broadcast_to(state.obj_pos[i], (len(sel), 3)), np.full(len(sel), body), track.body,
                         rot_c, pos_c, q, targets.objects[i][c].take(sel),
                         np.full(len(sel), problem.interaction.link_weight / max(n_obj_active, 1)))
            cost.append(interaction_rows(ps, track.channel, problem.interaction.object_weights, problem.interaction))
            total_pairs += len(sel)
    tm.lap("object_rows")

    for c, track in enumerate(problem.channels):
        if track.is_ground or len(track.guards) == 0:
            continue
        rot_c, pos_c = _channel_pose(state, track, targets.t)
        # a link can hold an object's edge only where its own surface, hence an area probe
        # within the link's sampling gap, comes close to the object
        links = np.flatnonzero(link_min[c] < problem.sampling_gap + margin)
        rows = object_guard_rows(problem, fr, links, track, rot_c, pos_c, check)
        con_rows.append(rows)
        con_channel.append(np.full(len(rows), len(problem.channels) + c))
    tm.lap("object_guards")

    surface = Rows.concat(con_rows)
    min_dist = float(surface.value.min()) if len(surface) else np.inf
    surface_channel = np.concatenate(con_channel).astype(np.intp) if con_channel else np.zeros(0, np.intp)
    tm.lap("constraint_selection")

    capsules = self_collision_rows(problem, fr, margin)
    min_self = float(capsules.value.min()) if len(capsules) else np.inf
    tm.lap("self_collision")

    # E_sty,r and E_sty,o in one batch: the tracked links, then the free objects
    links = problem.style.links
    pos_weight, rot_weight = problem.style_weights
    cost.append(pose_rows(np.concatenate([fr.pos[links], state.obj_pos]), np.concatenate([fr.rot[links], state.obj_rot]),
                          targets.style_pos, targets.style_rot, problem.style_bodies, pos_weight, rot_weight))
    tm.lap("style_rows")
    return Linearisation(Rows.concat(cost), Rows.concat([surface, capsules]), surface_channel, margin, fr,
                         total_pairs, min_dist, min_self, np.concatenate([link_counts, np.asarray(object_counts, np.intp)]))


def object_guard_rows(problem: Problem, fr: LinkFrames, links: np.ndarray, track: ChannelTrack,
                      rot_c: np.ndarray, pos_c: np.ndarray, reach: float) -> Rows:
    """Distances of an object's guard points (corners, edge points) to every robot link closer
    than ``reach``, from each link's own distance grid (link frame), in one stacked query.

    A box edge pressed into an arm lies between the arm's probes; seen from the arm's distance
    field it is the deepest point. Rows, grouped by link: body A the object (FIXED when
    pinned), body B the link.
    """
    grids = problem.link_grids
    links = links[grids.has_grid[links]]
    g_w = track.guards @ rot_c.T + pos_c
    centre_w = np.einsum("lij,lj->li", fr.rot[links], problem.link_center[links]) + fr.pos[links]
    gap = np.linalg.norm(centre_w[:, None, :] - g_w[None], axis=2) - problem.link_radius[links, None]  # (l, G)
    pair_link, guard = np.nonzero(gap < reach)
    if len(guard) == 0:
        return Rows.empty()
    link = links[pair_link]
    x = g_w[guard]
    local = np.einsum("kji,kj->ki", fr.rot[link], x - fr.pos[link])  # Rᵀ(x − o)
    d, grad, inside = grids.distance(local, link)
    keep = np.flatnonzero(inside & (d < reach))
    link, x = link[keep], x[keep]
    a_w = np.einsum("kij,kj->ki", fr.rot[link], grad[keep])  # ∇d in the world
    phi = twist_factors(a_w, x, np.broadcast_to(pos_c, x.shape), fr.pos[link])
    return Rows(d[keep], np.ones(len(x)), phi, np.full(len(x), track.body), link)


def self_collision_rows(problem: Problem, fr: LinkFrames, margin: float) -> Rows:
    """Capsule pairs closer than ``margin``: d + n·(ẋ_a − ẋ_b) rows (n from b to a)."""
    sc = problem.kin.self_collision.distances(fr, within=margin)
    close = sc.dist < margin
    la, lb, n = sc.link_a[close], sc.link_b[close], sc.normal[close]
    # the distance's rate is n·(ẋ_a − ẋ_b) at the surface points (the radii lie along n)
    phi = np.concatenate([n, cross(sc.point_a[close] - fr.pos[la], n), -n, -cross(sc.point_b[close] - fr.pos[lb], n)],
                         axis=1)
    return Rows(sc.dist[close], np.ones(len(la)), phi, la, lb)


# ------------------------------------------------------------------ QP assembly


def body_jacobians(problem: Problem, frames: LinkFrames) -> np.ndarray:
    """(L + O + 1, 6, n): link Jacobians, object selectors, and zeros for FIXED (index −1)."""
    n = problem.num_variables
    nv = problem.kin.nv
    jac = np.zeros((NUM_LINKS + len(problem.objects) + 1, 6, n))
    jac[:NUM_LINKS, :, :nv] = frames.jac
    for i in range(len(problem.objects)):
        jac[NUM_LINKS + i, :, nv + 6 * i:nv + 6 * i + 6] = np.eye(6)
    return jac


def _runs(code: np.ndarray) -> np.ndarray:
    return np.flatnonzero(np.concatenate([[True], code[1:] != code[:-1]]))


def assemble_cost(rows: Rows, jac: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Newton H = Σ w JᵀJ and g = Σ w J r, merged per run of rows on the same bodies.

    A run's rows share their bodies, hence their Jacobians: its block is
    [J_A; J_B]ᵀ (Φᵀ W Φ) [J_A; J_B] (J_B = 0 for a fixed channel). The 12×12 Φᵀ W Φ of each
    run is accumulated in one pass over the rows, then all runs go through one batched product
    with their Jacobians: the cost grows with the number of (body, channel) runs, not of probes.
    """
    n = jac.shape[2]
    if len(rows) == 0:
        return np.zeros((n, n)), np.zeros(n)
    starts = _runs(rows.body_a * (jac.shape[0] + 1) + rows.body_b)
    m = np.empty((len(starts), 12, 12))
    v = np.empty((len(starts), 12))
    _run_moments(rows.value, rows.weight, rows.phi, np.append(starts, len(rows)), rows.body_b[starts] == FIXED, m, v)
    j = np.concatenate([np.take(jac, rows.body_a[starts], axis=0), np.take(jac, rows.body_b[starts], axis=0)],
                       axis=1).reshape(-1, n)
    mj = (m @ j.reshape(len(starts), 12, n)).reshape(-1, n)
    return j.T @ mj, j.T @ v.ravel()


@numba.njit(cache=True)
def _run_moments(value, weight, phi, bounds, fixed_b, m, v):
    """Per run r (rows bounds[r]:bounds[r + 1]): m[r] = Σ w φφᵀ (12, 12), v[r] = Σ w r φ (12,).
    Runs against a fixed body B (J_B = 0) only need the upper-left 6×6 block."""
    for r in range(m.shape[0]):
        size = 6 if fixed_b[r] else 12
        m[r] = 0.0
        v[r] = 0.0
        for k in range(bounds[r], bounds[r + 1]):
            w = weight[k]
            for a in range(size):
                wa = w * phi[k, a]
                v[r, a] += wa * value[k]
                for b in range(a, size):
                    m[r, a, b] += wa * phi[k, b]
        for a in range(size):
            for b in range(a):
                m[r, a, b] = m[r, b, a]


def constraint_matrix(rows: Rows, jac: np.ndarray) -> np.ndarray:
    """(k, n) rows φ_Aᵀ J_A + φ_Bᵀ J_B."""
    return (np.einsum("kc,kcn->kn", rows.phi[:, :6], jac[rows.body_a])
            + np.einsum("kc,kcn->kn", rows.phi[:, 6:], jac[rows.body_b]))


def _interval(lo: np.ndarray, hi: np.ndarray, trust: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[lo, hi] ∩ [−trust, trust]; when empty (the iterate violates a bound by more than one
    step), the step that moves furthest towards [lo, hi]."""
    a, b = np.maximum(lo, -trust), np.minimum(hi, trust)
    empty = a > b
    toward = np.clip(np.where(lo > 0, lo, hi), -trust, trust)
    return np.where(empty, toward, a), np.where(empty, toward, b)


def variable_bounds(problem: Problem, state: SolverState, targets: FrameTargets) -> tuple[np.ndarray, np.ndarray]:
    """Per-variable boxes on the step at the iterate, trust region aside: joint limits ∩
    velocity limits ∩ object boxes (eq. m-qp-lim, m-qp-vel, m-qp-box)."""
    cfg = problem.solver
    nv = problem.kin.nv
    lo = np.full(problem.num_variables, -np.inf)
    hi = np.full(problem.num_variables, np.inf)
    qj = state.q[7:]
    lo[6:nv] = problem.kin.joint_lower - qj
    hi[6:nv] = problem.kin.joint_upper - qj
    if state.prev is not None:
        reach = robot.VELOCITY_LIMIT / problem.fps
        qj_prev = state.prev[0][7:]
        lo[6:nv] = np.maximum(lo[6:nv], qj_prev - reach - qj)
        hi[6:nv] = np.minimum(hi[6:nv], qj_prev + reach - qj)
    n_obj = len(problem.objects)
    if n_obj:
        # deviation from the demonstrated pose (b_cor), and from the predicted pose: the last
        # solution moved by the demonstrated displacement (b_env)
        ref_pos, ref_rot, boxes = [targets.obj_pos], [targets.obj_rot], [cfg.object_deviation_box]
        if state.prev is not None and state.prev_demo is not None:
            dp, dr = state.prev_demo
            ref_pos.append(state.prev[1] + targets.obj_pos - dp)
            ref_rot.append(targets.obj_rot @ np.swapaxes(dr, -1, -2) @ state.prev[2])
            boxes.append(cfg.object_step_box)
        k = len(boxes)
        ref_rot = np.concatenate(ref_rot)
        error = np.concatenate([np.tile(state.obj_pos, (k, 1)) - np.concatenate(ref_pos),
                                so3_log(np.tile(state.obj_rot, (k, 1, 1)) @ np.swapaxes(ref_rot, -1, -2))],
                               axis=1).reshape(k, n_obj * 6)
        box = np.array([np.tile(np.repeat(b, 3), n_obj) for b in boxes])  # (k, 6 O)
        lo[nv:] = np.max(-box - error, axis=0)
        hi[nv:] = np.min(box - error, axis=0)
    return lo, hi


def step_bounds(problem: Problem, bounds: tuple[np.ndarray, np.ndarray],
                trust_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Per-variable boxes: trust region × ``trust_scale`` ∩ ``variable_bounds``."""
    return _interval(bounds[0], bounds[1], trust_scale * problem.trust)


# ------------------------------------------------------------------ SQP


@dataclass
class _QPModel:
    """The Gauss–Newton model of one accepted iterate, reused when a trial step is rejected.

    A trial iterate first gets its merit only; ``jac``, ``H``, ``g`` and ``chosen`` are filled
    by :func:`_assemble` once the trust-region test accepts it."""

    lin: Linearisation
    energy: float  # E at the iterate
    penalty: float  # L1 penalty of its violations beyond ε_col
    jac: np.ndarray | None = None
    H: np.ndarray | None = None
    g: np.ndarray | None = None
    chosen: np.ndarray | None = None  # constraint rows in the QP
    bounds: tuple[np.ndarray, np.ndarray] | None = None  # ``variable_bounds`` at the iterate, once asked

    @property
    def merit(self) -> float:
        return self.energy + self.penalty


def _merit(problem: Problem, state: SolverState, lin: Linearisation) -> tuple[float, float]:
    """(E = Σ w r² + ‖q ⊖ q_{t−1}‖², L1 penalty on the violations beyond ε_col)."""
    cfg = problem.solver
    energy = float(np.dot(lin.cost.weight, lin.cost.value ** 2))
    if state.prev is not None:
        e = problem.kin.difference(state.prev[0], state.q)
        energy += cfg.previous_frame_weight * float(e @ e)
    excess = np.maximum(0.0, -cfg.penetration_tolerance_m - lin.constraints.value)
    return energy, cfg.violation_penalty * float(excess.sum())


def _model(problem: Problem, state: SolverState, lin: Linearisation, timings: dict[str, float],
           assemble: bool = True) -> _QPModel:
    """The model at the state's iterate (linearised as ``lin``); without ``assemble``, its merit only."""
    tm = _Timer(timings)
    model = _QPModel(lin, *_merit(problem, state, lin))
    tm.lap("qp_assembly")
    if assemble:
        _assemble(problem, state, model, timings)
    return model


def _assemble(problem: Problem, state: SolverState, model: _QPModel, timings: dict[str, float]) -> None:
    """Fill the model's QP (H, g, Jacobians, first constraint rows); the state must be at its iterate."""
    tm = _Timer(timings)
    cfg, lin = problem.solver, model.lin
    chosen = np.zeros(len(lin.constraints), dtype=bool)
    chosen[lin.initial] = True
    tm.lap("constraint_selection")
    jac = body_jacobians(problem, lin.frames)
    H, g = assemble_cost(lin.cost, jac)
    nv = problem.kin.nv
    if state.prev is not None:
        e = problem.kin.difference(state.prev[0], state.q)  # q ⊖ q_{t−1}
        H[:nv, :nv] += cfg.previous_frame_weight * np.eye(nv)
        g[:nv] += cfg.previous_frame_weight * e
    H[np.diag_indices_from(H)] += cfg.damping
    model.jac, model.H, model.g, model.chosen = jac, H, g, chosen
    tm.lap("qp_assembly")


def qp_step(problem: Problem, state: SolverState, targets: FrameTargets, model: _QPModel, trust_scale: float,
            stats: FrameStats) -> np.ndarray:
    """The QP step of eq. m-qp at the model's iterate, trust region × ``trust_scale``.

    Constraint rows start from ``model.chosen``; after each solve every candidate row is
    predicted through the bodies' twists and the violated ones are added (at most 3 times, and
    not after a QP that ProxQP could not solve).
    """
    cfg = problem.solver
    eps = cfg.penetration_tolerance_m
    tm = _Timer(stats.timings)
    if model.bounds is None:
        model.bounds = variable_bounds(problem, state, targets)
    box_lo, box_hi = step_bounds(problem, model.bounds, trust_scale)
    rows, chosen, jac = model.lin.constraints, model.chosen, model.jac
    for _ in range(4):
        sub = _rows_take(rows, np.flatnonzero(chosen))
        # Rows aim at d ≥ 0 (ε_col is the slack for linearisation error); a penetrating pair
        # asks to get out by at most one step, so the QP stays feasible.
        lower = np.minimum(-sub.value, trust_scale * cfg.trust_linear_m)
        C = constraint_matrix(sub, jac)
        tm.lap("qp_assembly")
        failures = state.qp.failures
        delta = state.qp.solve(model.H, model.g, C, lower, box_lo, box_hi)
        tm.lap("qp_solve")
        if state.qp.failures > failures:
            break  # the rows conflict already: more rows cannot help, the relaxed step stands
        twist = jac @ delta  # (bodies, 6)
        both = np.concatenate([np.take(twist, rows.body_a, axis=0), np.take(twist, rows.body_b, axis=0)], axis=1)
        predicted = rows.value + np.einsum("kc,kc->k", rows.phi, both)
        violated = (predicted < -eps) & ~chosen
        tm.lap("qp_assembly")
        if not violated.any():
            break
        chosen |= violated
    stats.qp_rows.append(int(chosen.sum()))
    return delta


def retract(problem: Problem, state: SolverState, delta: np.ndarray) -> None:
    """q ← q ⊕ δv; τ ← τ + δτ, R ← exp(δθ) R for every free object."""
    nv = problem.kin.nv
    state.q = problem.kin.integrate(state.q, delta[:nv])
    for i in range(len(problem.objects)):
        d = delta[nv + 6 * i:nv + 6 * i + 6]
        state.obj_pos[i] = state.obj_pos[i] + d[:3]
        state.obj_rot[i] = so3_exp(d[3:]) @ state.obj_rot[i]


def solve_frame(problem: Problem, state: SolverState, t: int) -> FrameStats:
    """Trust-region SQP of frame t from the state's current iterate (warm start).

    Each iteration solves the QP, evaluates the merit (E plus an L1 penalty on violations
    beyond ε_col) at the trial point, and accepts the step if the merit decreases by at least
    a tenth of the model's prediction; otherwise the step is undone and the trust region
    shrinks (×``trust_shrink``), after good steps it grows back. The proximity residuals are
    not smooth everywhere (witnesses jump across box edges), so without this test the
    Gauss–Newton steps can wander at the full trust radius instead of converging. The budget
    (50 iterations on the first frame, 6 after) counts trial steps; it ends early when
    ‖δ‖∞ < 1e-4, when the model predicts too small a decrease (``model_tolerance``), or when a
    step predicted to gain little is rejected (``rejected_model_tolerance``). If the accepted
    point still violates ε_col, restoration steps follow (``SolverConfig.feasibility_iterations``).
    """
    stats = FrameStats()
    tm = _Timer(stats.timings)
    targets = frame_targets(problem, t)
    tm.lap("demo_triples")
    cfg = problem.solver
    eps = cfg.penetration_tolerance_m
    budget = cfg.first_frame_iterations if state.prev is None else cfg.iterations
    lin = linearise(problem, state, targets, stats.timings)
    counts = lin.counts
    model = _model(problem, state, lin, stats.timings)
    scale = 1.0
    for _ in range(budget):
        delta = qp_step(problem, state, targets, model, scale, stats)
        stats.iterations += 1
        step = float(np.abs(delta).max())
        # predicted merit decrease: the model's decrease of E, and the violations the QP removes
        predicted = -(2.0 * model.g @ delta + delta @ model.H @ delta) + model.penalty
        if step < cfg.step_tolerance or predicted < cfg.model_tolerance * model.merit:
            break
        saved = (state.q.copy(), state.obj_pos.copy(), state.obj_rot.copy())
        retract(problem, state, delta)
        trial = linearise(problem, state, targets, stats.timings, counts=counts)
        trial_model = _model(problem, state, trial, stats.timings, assemble=False)
        gain = model.merit - trial_model.merit
        if gain > 0.1 * max(predicted, 0.0) and gain > 0.0:
            _assemble(problem, state, trial_model, stats.timings)
            model = trial_model
            if gain > 0.75 * predicted:
                scale = min(1.0, 2.0 * scale)
        else:
            state.q, state.obj_pos, state.obj_rot = saved
            stats.rejected += 1
            if predicted < cfg.rejected_model_tolerance * model.merit:
                break
            # shrink around the rejected step (which may sit well inside the region)
            scale = cfg.trust_shrink * float(np.max(np.abs(delta) / problem.trust))
    lin = model.lin
    # Feasibility restoration: the smallest move that the linearised constraints accept, with a
    # trust region shrinking each time, until every pair is within ε_col (linearisation error
    # is second order in the step, so small steps converge).
    for k in range(cfg.feasibility_iterations):
        if lin.min_distance >= -eps and lin.min_self_distance >= -eps:
            break
        jac = body_jacobians(problem, lin.frames)
        n = problem.num_variables
        chosen = np.zeros(len(lin.constraints), dtype=bool)
        chosen[lin.initial] = True
        chosen |= lin.constraints.value < eps
        restore = _QPModel(lin, 0.0, 0.0, jac, np.eye(n), np.zeros(n), chosen)
        failures = state.qp.failures
        delta = qp_step(problem, state, targets, restore, cfg.feasibility_trust_scale ** k, stats)
        stats.iterations += 1
        retract(problem, state, delta)
        lin = linearise(problem, state, targets, stats.timings, counts=counts)
        if state.qp.failures > failures:
            break  # the linearised constraints conflict (e.g. a pinned object in the hand's way)
    stats.active_pairs = lin.active_pairs
    stats.min_distance_m = lin.min_distance
    stats.min_self_distance_m = lin.min_self_distance
    state.prev = (state.q.copy(), state.obj_pos.copy(), state.obj_rot.copy())
    state.prev_demo = (targets.obj_pos.copy(), targets.obj_rot.copy())
    return stats


@dataclass(frozen=True)
class FrameContacts:
    """Per-link distance to every channel at the solution (ContactAnnotations rows)."""

    distance: np.ndarray  # (L, C) m, clamped to d̄ when far
    witness_c: np.ndarray  # (L, C, 3) channel frame


def frame_contacts(problem: Problem, state: SolverState, t: int) -> FrameContacts:
    """Per link and channel: the smallest signed distance over its probes and hull guard points
    (links whose bounding sphere stays beyond d̄ keep the clamped value d̄)."""
    fr = problem.kin.frames(state.data, state.q)
    band = problem.band_m
    centre_w = np.einsum("lij,lj->li", fr.rot, problem.link_center) + fr.pos
    C = len(problem.channels)
    dist = np.full((NUM_LINKS, C), band)
    wit = np.zeros((NUM_LINKS, C, 3))
    for c, track in enumerate(problem.channels):
        rot_c, pos_c = _channel_pose(state, track, t)
        links = np.flatnonzero(_candidate_links(problem, track, centre_w, rot_c, pos_c))
        pidx, p_w = problem.robot.posed_bodies(links, fr.rot, fr.pos)
        gidx, g_w = problem.guards.posed_bodies(links, fr.rot, fr.pos)
        link = np.concatenate([problem.robot.body[pidx], problem.guards.body[gidx]])
        x_c = to_channel_frame(np.concatenate([p_w, g_w]), rot_c, pos_c)
        idx = np.flatnonzero(_near(track, x_c, band))
        if len(idx) == 0:
            continue
        # distances alone find each link's closest point; only those need a witness
        d = np.minimum(track.channel.distance(np.take(x_c, idx, axis=0))[0], band)
        owner = link[idx]
        order = np.lexsort((d, owner))  # per link, closest first
        first = order[np.concatenate([[True], owner[order][1:] != owner[order][:-1]])]
        q = track.channel.query(np.take(x_c, idx[first], axis=0), normals=False)
        dist[owner[first], c] = np.minimum(q.d, band)
        wit[owner[first], c] = q.w
    return FrameContacts(dist, wit)


@dataclass
class Solution:
    """The solved sequence: MuJoCo-layout qpos, free-object poses, contacts and statistics."""

    qpos: np.ndarray  # (T, 36) [xyz, wxyz, joints]
    obj_pos: np.ndarray  # (T, O, 3)
    obj_rot: np.ndarray  # (T, O, 3, 3)
    contacts: np.ndarray  # (T, L, C)
    witness_c: np.ndarray  # (T, L, C, 3)
    stats: list[FrameStats]
    qp_failures: int


def new_state(problem: Problem) -> SolverState:
    pos = np.array([problem.channels[o.channel].pos_w[0] for o in problem.objects]).reshape(-1, 3)
    rot = np.array([problem.channels[o.channel].rot_w[0] for o in problem.objects]).reshape(-1, 3, 3)
    return SolverState(problem.kin.new_data(), problem.q_init.copy(), pos.copy(), rot.copy(),
                       QPWorkspace(problem.solver.qp_eps_abs, problem.solver.qp_warm_start))


def warm_start(problem: Problem, state: SolverState, t: int, held: np.ndarray) -> None:
    """First iterate of frame t from the solution of t − 1, moved by the demonstration.

    The robot base and every object it holds (``held``, per free object) move together by the
    demonstrated pelvis's planar displacement (xy translation, yaw about the base): a rigid
    motion of the robot with its load keeps the previous solution's contacts and clearances,
    and a planar one keeps the soles on the ground. Objects not held move by their own
    demonstrated displacement.
    """
    pelvis = int(np.flatnonzero(problem.style.links == 0)[0])
    rot_prev, rot_now = problem.style.rot_w[t - 1, pelvis], problem.style.rot_w[t, pelvis]
    yaw = np.arctan2(rot_now[1, 0], rot_now[0, 0]) - np.arctan2(rot_prev[1, 0], rot_prev[0, 0])
    turn = so3_exp(np.array([0.0, 0.0, yaw]))
    shift = problem.part_pos_w[t, 0] - problem.part_pos_w[t - 1, 0]
    shift[2] = 0.0
    base = state.q[:3].copy()
    state.q[:3] = base + shift
    base_rot = pin.Quaternion(state.q[6], *state.q[3:6]).toRotationMatrix()
    state.q[3:7] = pin.Quaternion(turn @ base_rot).coeffs()  # xyzw
    for i, o in enumerate(problem.objects):
        if held[i]:
            state.obj_pos[i] = base + shift + turn @ (state.obj_pos[i] - base)
            state.obj_rot[i] = turn @ state.obj_rot[i]
        else:
            tr = problem.channels[o.channel]
            state.obj_pos[i] += tr.pos_w[t] - tr.pos_w[t - 1]
            state.obj_rot[i] = tr.rot_w[t] @ tr.rot_w[t - 1].T @ state.obj_rot[i]


def solve_sequence(problem: Problem, progress=None) -> Solution:
    """Solve every frame in order, each warm-started from the previous solution.

    BLAS and OpenMP run on one thread meanwhile: the products are small, so threads cost more
    than they save, and the pipeline's workers give the parallelism.
    """
    with threadpool_limits(limits=1):
        return _solve_sequence(problem, progress)


def _solve_sequence(problem: Problem, progress) -> Solution:
    state = new_state(problem)
    T, n_obj = problem.num_frames, len(problem.objects)
    qpos = np.empty((T, 7 + robot.NUM_JOINTS))
    obj_pos, obj_rot = np.empty((T, n_obj, 3)), np.empty((T, n_obj, 3, 3))
    contacts = np.empty((T, NUM_LINKS, len(problem.channels)))
    witness = np.empty((T, NUM_LINKS, len(problem.channels), 3))
    stats = []
    held = np.zeros(n_obj, dtype=bool)
    object_channels = np.array([c for c, tr in enumerate(problem.channels) if not tr.is_ground], dtype=np.intp)
    arm_link_ids = {side: arm_links(side) for side in ("left", "right")}
    arms_free = (True, True)
    for t in range(T):
        if t > 0:
            warm_start(problem, state, t, held)
            # a local SQP cannot leave an arm branch pinned at joint limits (retarget.arm_seed)
            state.q = seed_arms(state.q, state.prev[0], problem.style.rot_w[t], problem.fps, free=arms_free)
        stats.append(solve_frame(problem, state, t))
        fc = frame_contacts(problem, state, t)
        held = np.array([fc.distance[:, o.channel].min() < problem.solver.hold_distance_m for o in problem.objects],
                        dtype=bool)
        arms_free = tuple(bool((fc.distance[arm_link_ids[side]][:, object_channels] >= problem.band_m).all())
                          for side in ("left", "right"))
        qpos[t] = robot.qpos_pinocchio_to_mujoco(state.q)
        obj_pos[t], obj_rot[t] = state.obj_pos, state.obj_rot
        contacts[t], witness[t] = fc.distance, fc.witness_c
        if progress is not None:
            progress(t)
    return Solution(qpos, obj_pos, obj_rot, contacts, witness, stats, state.qp.failures)
