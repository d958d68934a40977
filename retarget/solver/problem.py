"""The OTRetarget problem of one demonstration: its data types (:class:`SolverConfig`,
:class:`ChannelTrack`, :class:`FreeObject`, the immutable :class:`Problem`) and how they are
built from a :class:`~retarget.inputs.readers.Demonstration` (probes, channels, OT correspondences,
style targets), once per clip.

Modes (docs/method.md "Modes"):

* ``native`` (default): robot and scene at the captured metric scale; every manipulated object
  is a decision variable, static furniture stays a fixed channel.
* ``scaled``: the human (trajectories and surface) and the object trajectories are multiplied
  by sc = G1 height / stature (objects keep their size; object heights scale about the first
  frame's, ``retarget.inputs.readers.scaled_object_positions``) and every object is fixed (the paper's
  ablation and OmniRetarget's convention).
* ``robot-only``: the ground is the only channel; objects are ignored.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from otr_gym import robot
from otr_gym.robot_geometry import surface_margin_m, visual_meshes
from otr_gym.rotations import quat_slerp, quat_to_matrix
from retarget.evaluation.feet import least_moving_speed
from retarget.geometry.channels import Channel, GeometryConfig, GroundChannel, SDFChannel
from retarget.geometry.kinematics import NUM_LINKS, RobotKinematics, link_pairs_beyond
from retarget.geometry.margins import ErrorMargin, cached_margin
from retarget.geometry.voxel_grid import GridStack
from retarget.inputs.demonstration import Demonstration, DemoObject, InvalidDemonstrationError, scaled_object_positions
from retarget.inputs.human_surface import HumanSurface
from retarget.inputs.meshes import as_trimesh, object_mesh
from retarget.solver.probes import (
    PointClusters,
    ProbeSet,
    SurfaceGuards,
    hull_guard_points,
    human_probes,
    object_surface_guards,
    robot_guard_points,
    robot_probes,
    robot_self_points,
    robot_vertex_guards,
)
from retarget.solver.residuals import FIXED, InteractionConfig
from retarget.solver.stance import (
    FootTurns,
    StanceConfig,
    demonstrated_roll,
    demonstrated_stance,
    demonstrated_turns,
    sole_points,
)
from retarget.solver.style import StyleConfig, StyleTargets, pelvis_height_ratio, robot_style_targets
from retarget.solver.substitute import Substitution, substitution_for

MODES = ("native", "scaled", "robot-only")


def link_clearance(clearance_m: dict[str, float]) -> np.ndarray:
    """(L,) m per G1 body of ``SolverConfig.link_clearance_m``; an unknown link or a negative or
    non-finite clearance raises naming it."""
    out = np.zeros(len(robot.BODY_NAMES))
    for link, value in clearance_m.items():
        if link not in robot.BODY_NAMES:
            raise ValueError(f"solver.link_clearance_m: unknown G1 link '{link}' (links: robot.BODY_NAMES)")
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"solver.link_clearance_m: '{link}' must be a finite clearance >= 0 m, got {value}")
        out[robot.BODY_NAMES.index(link)] = float(value)
    return out


@dataclass(frozen=True)
class SolverConfig:
    """SQP budget, trust region and constraint settings (eq. m-qp; docs/method.md "Solver")."""

    #: Iterations on the cold-started first frame (Sec. III-D: 50) and on warm-started frames
    #: (ours: 3; the paper's 6). Measured on the five shared clips (``benchmarks/fidelity.py``,
    #: 2026-11-25): a frame's fourth to sixth trial steps gain a median 2-4e-4 of its merit on
    #: the box carry, and stopping after three left every figure as good or better (chair
    #: object R 81 → 88 %, dd 10.5 → 7.8 mm; walk–jog–turn ground penetration 3.6 → 0.3 mm)
    #: at 0.7-0.8× the time; two steps let the box carry's feet sink 7.9 mm.
    first_frame_iterations: int = 50
    iterations: int = 3
    #: Stop when ‖δ‖∞ falls below this (Sec. III-D).
    step_tolerance: float = 1e-4
    #: Per-DoF trust region: 5 cm on translations, 0.10 rad on rotations and joints (eq. m-qp-tr).
    trust_linear_m: float = 0.05
    trust_angular_rad: float = 0.10
    #: ε_col: non-penetration d + gᵀδ ≥ −ε_col (eq. m-qp-col).
    penetration_tolerance_m: float = 3e-4
    #: Ours: extra clearance (m) per G1 link (``robot.BODY_NAMES``), added to its surface margin
    #: in every non-penetration row (ground, objects, the robot's own links). The box task
    #: collides the G1's collision capsules, which stand out of the visual meshes that the
    #: solve keeps off the object: on the OMOMO large box our torso and right shoulder capsules
    #: sit 17 and 13 mm inside the simulated box through the lift. Empty by default: on that
    #: clip the kinematic playback varies as much with the probe seed as with this (docs/results/box.md,
    #: ``benchmarks/reference_seeds.py``).
    link_clearance_m: dict[str, float] = field(default_factory=dict)
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
    #: Ours: per frame, the robot's base (pelvis origin, world) may move by the demonstrated
    #: pelvis displacement ± this (m; 8 mm at 50 fps = 0.4 m/s of velocity deviation). Without it
    #: a base that lags while a foot is planted jumps back when the foot lifts (AMASS jog: 9.4 cm
    #: off its path in one frame, 56 frames over 1 cm); with 2 cm: 3.0 cm, 34 frames; with 8 mm:
    #: 1.4 cm, 10 frames, at the same ground contact quality (``retarget.checks.feasibility``).
    base_step_m: float = 0.008
    #: Our choice: an object closer than this to a robot link is "held" and the warm start of
    #: the next frame moves it rigidly with the robot (``warm_start``).
    hold_distance_m: float = 0.01
    #: Ours: the warm start also moves each foot that is not planted (in stance at t − 1 and t)
    #: by the person's displacement of that foot, on its leg's joints
    #: (``retarget.solver.leg_seed.carry_swing_feet``). Left where the rigid warm start puts it,
    #: a swing foot falls behind the frame's optimum by the 3-step budget's shortfall every frame
    #: and catches up in one frame when a stance or roll-off flag changes (Bandai's shared walk:
    #: its 16.7 cm limb jump). Off: on 12 Bandai clips it halves the median limb-jump peak
    #: (24.1 -> 10.9 cm), but the solve takes 8-20 % more CPU time a frame (Bandai walks, box
    #: carry), the box's object J falls 89.6 -> 89.3 % and the jog's ground J 99.6 -> 98.9 %
    #: (docs/results/feasibility.md, *Why a swing foot jumps*).
    carry_swing_feet: bool = False
    #: Ours: before the trust-region test judges a trial step, the held sole points are put back
    #: on their targets on their legs' joints (``retarget.solver.leg_seed.replant_trial``), a
    #: second-order correction of the refusals that a pitched held foot's toe causes. Off: on Bandai
    #: walks it moved the standing shin into the swinging foot (docs/results/feasibility.md).
    replant_trial: bool = False
    #: Ours: a contact-state row in its state (a foot the person keeps off the floor, clear of
    #: it) that a step would carry across is priced in that step's QP (``qp.qp_step``). Off, the
    #: model did not know the cost it would meet and the trust-region test refused the step:
    #: on Bandai's walk 177 of 222 refusals, 38 of 241 frames that took no step at all, a
    #: staircase in the joints (docs/results/feasibility.md, *Refused steps*). Off by default
    #: (on in ``configs/retarget/executable.yaml``): the references change and a synthetic
    #: box-placing clip cut mid-carry then keeps the hands on the box on 78 % of its frames,
    #: under its test's 90 % (the seed-0 reference of 53a180a: 95 %).
    price_contact_state: bool = False
    #: Ours: a trial step whose deepest pair lies this much deeper than the iterate's (or than
    #: ε_col) is refused whatever its merit (m): the L1 penalty prices a centimetre inside a
    #: surface at 1, less than a COM target can gain (the wooden chair: 18 mm into a slat; 2 mm
    #: also refused steps the chair needed without one: it drifted 29 cm). inf: off (the default;
    #: 0.003 in ``configs/retarget/executable.yaml``, whose COM target needs it).
    step_penetration_m: float = float("inf")
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
    #: Object substitution (retarget.solver.substitute): the captured object whose surface the
    #: demonstrated triples are measured on, and the map of its witnesses onto ``channel``.
    substitution: Substitution | None = None
    #: The surface's own points against the links (faces pressed into a link's hollows).
    surface_guards: SurfaceGuards | None = None

    @property
    def is_ground(self) -> bool:
        return bool(self.channel.is_ground)


@dataclass(frozen=True)
class FreeObject:
    """A manipulated object: a decision variable, a channel for the robot, and a probe carrier."""

    name: str
    channel: int  # index of its ChannelTrack
    probes: np.ndarray  # (P_o, 3) object frame
    #: (P_o, 3) object frame: each probe's demonstrated point, on the captured surface when the
    #: object is a substitute (retarget.solver.substitute); None: the probes themselves.
    demo_probes: np.ndarray | None = None

    @property
    def demonstrated_probes(self) -> np.ndarray:
        return self.probes if self.demo_probes is None else self.demo_probes


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
    #: (L,) m: how far Unitree's original surface may lie beyond each link's shipped mesh
    #: (``otr_gym.robot_geometry.surface_margin_m``); non-penetration rows keep it as clearance.
    surface_margin: np.ndarray
    #: Planted feet (``retarget.solver.stance``): G1 foot links (F,), their flat-sole points (link
    #: frame), the person's stance and sweep flags per frame (T, F) and the settings.
    feet: np.ndarray
    soles: tuple[np.ndarray, ...]
    stance: np.ndarray
    sweep: np.ndarray
    turns: FootTurns
    stance_cfg: StanceConfig
    #: (P, 2) links whose visual meshes must not overlap (more than two joints apart)
    self_pairs: np.ndarray
    self_points: ProbeSet  # visual-mesh vertices thinned for self-collision (``robot_self_points``)
    self_clusters: PointClusters  # their clusters
    #: (L,) contact unit of each link: links sharing human parts (``retarget.evaluation.units``),
    #: links without a part their own unit
    contact_units: np.ndarray
    #: The human surface of the contact units (their parts' mesh vertices, part frames, × scale)
    #: and the unit of each vertex: a unit's demonstrated gap is its whole surface's, as the
    #: evaluation measures it, not only the OT sources' (``targets.unit_gaps``).
    unit_surface: ProbeSet
    unit_of_vertex: np.ndarray
    #: (T, 3) m, world: the centre-of-mass path of a second pass (``retarget.solver.balance``,
    #: ``retarget.solver.flight``), held by Σ_k w_k (com(q) − c*_t)_k² with ``com_weight`` w
    #: (per m²; one weight, or one per world axis x, y, z); None in the first pass.
    com_target: np.ndarray | None = None
    com_weight: float | tuple[float, float, float] = 0.0
    #: With a rate r > 0, ``com_target`` is the person's COM and the target of frame t is
    #: c*_t + o_t, the offset o following the G1's own (o ← o + r (com_t − c*_t − o) after each
    #: frame, o from frame 0's solution, which has no COM term): the G1 keeps its own posture's
    #: offset from the person's COM but moves it as the person does (``retarget.solver.balance``).
    com_offset_rate: float = 0.0
    #: (T, O, 2): (λ_o,pos, λ_o,rot) of every free object per frame (``retarget.solver.holds``:
    #: the hold weights in the person's two-hand holds); None: ``style_cfg``'s on every frame.
    object_style_w: np.ndarray | None = None

    @cached_property
    def num_surface_units(self) -> int:
        """Contact units that have human surface (the first of ``contact_units``' numbering)."""
        return int(self.unit_of_vertex.max()) + 1

    @property
    def num_frames(self) -> int:
        return int(self.part_pos_w.shape[0])

    @cached_property
    def com_weights(self) -> np.ndarray:
        """(3,) per m²: ``com_weight`` per world axis."""
        return np.broadcast_to(np.asarray(self.com_weight, np.float64), (3,)).copy()

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
        """(λ_pos, λ_rot) of every style body (eq. m-esty-o), the objects' outside holds."""
        cfg, n_links, n_obj = self.style_cfg, len(self.style.links), len(self.objects)
        return (np.r_[np.full(n_links, cfg.pos_weight), np.full(n_obj, cfg.object_pos_weight)],
                np.r_[np.full(n_links, cfg.rot_weight), np.full(n_obj, cfg.object_rot_weight)])

    def style_weights_at(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """(λ_pos, λ_rot) of every style body at frame t: the objects' hold weights in a hold."""
        pos, rot = self.style_weights
        if self.object_style_w is None or not self.objects:
            return pos, rot
        n_links = len(self.style.links)
        w = self.object_style_w[t]
        return np.r_[pos[:n_links], w[:, 0]], np.r_[rot[:n_links], w[:, 1]]

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



@lru_cache(maxsize=1)
def kinematics() -> RobotKinematics:
    """The process-wide G1 model (immutable)."""
    return RobotKinematics()


def resample_demonstration(demo: Demonstration, fps: float) -> Demonstration:
    """The demonstration at ``fps`` (linear positions, slerp orientations, nearest-frame
    annotations); same duration."""
    if abs(fps - demo.fps) < 1e-9:
        return demo
    if not fps > 0:
        raise ValueError(f"{demo.name}: fps must be > 0, got {fps}")
    t_src = np.arange(demo.num_frames) / demo.fps
    n = int(np.floor(t_src[-1] * fps + 1e-9)) + 1
    u = np.arange(n) / fps * demo.fps
    i0 = np.clip(np.floor(u).astype(int), 0, demo.num_frames - 1)
    i1 = np.minimum(i0 + 1, demo.num_frames - 1)
    a = np.clip(u - i0, 0.0, 1.0)

    def lerp(x):
        w = a.reshape((-1,) + (1,) * (x.ndim - 1))
        return (1 - w) * x[i0] + w * x[i1]

    def slerp(q):
        return quat_slerp(q[i0], q[i1], np.broadcast_to(a.reshape((-1,) + (1,) * (q.ndim - 2)), q[i0].shape[:-1]))

    objects = [replace(o, pos_w=lerp(o.pos_w), quat_w=slerp(o.quat_w)) for o in demo.objects]
    nearest = np.rint(u).astype(int).clip(0, demo.num_frames - 1)
    annotations = {k: np.asarray(v)[nearest] for k, v in demo.annotations.items()}
    return replace(demo, fps=float(fps), part_pos_w=lerp(demo.part_pos_w), part_quat_w=slerp(demo.part_quat_w),
                   objects=objects, annotations=annotations)


def mode_scale(demo: Demonstration, mode: str) -> float:
    """sc = G1 height / stature in the scaled mode, 1 otherwise."""
    if mode not in MODES:
        raise ValueError(f"unknown retarget mode '{mode}' (choose from {MODES})")
    if mode != "scaled":
        return 1.0
    if not demo.stature_m > 0:
        raise InvalidDemonstrationError(f"{demo.name}: stature must be > 0 m for the scaled mode, got {demo.stature_m}")
    return robot.HEIGHT_M / demo.stature_m


def correspondences(robot_set: ProbeSet, human: ProbeSet, demo: Demonstration, scale: float,
                    cache_dir: Path | None, links_together: str = "none") -> np.ndarray:
    """src(p) (P_robot,): index into ``human`` of every robot probe's demonstrated point (OT);
    ``links_together`` names a ``retarget.inputs.human.LINK_GROUPINGS`` entry."""
    from retarget.inputs.human import link_grouping
    from retarget.solver.transport import robot_human_correspondences

    return robot_human_correspondences(robot_set, human, demo, scale=scale, cache_dir=cache_dir,
                                       together=link_grouping(links_together))


def _object_channel(obj: DemoObject, geometry: GeometryConfig, cache_dir: Path | None) -> SDFChannel:
    source = obj.mesh_path or obj.name
    mesh = object_mesh(obj.vertices, obj.faces, f"object '{obj.name}' ({source})")
    return SDFChannel.from_mesh(mesh, geometry, cache_dir, name=obj.name)


def build_problem(demo: Demonstration, mode: str = "native", *, geometry: GeometryConfig = GeometryConfig(),
                  interaction: InteractionConfig = InteractionConfig(), style: StyleConfig = StyleConfig(),
                  solver: SolverConfig = SolverConfig(), guard_spacing_m: float = 0.008,
                  max_probes_per_link: int | None = None, seed: int = 0, cache_dir: Path | None = None,
                  stance: StanceConfig = StanceConfig(), links_together: str = "none") -> Problem:
    """Probes, channels, correspondences and style targets of ``demo`` (at its own fps)."""
    scale = mode_scale(demo, mode)
    kin = kinematics()
    T = demo.num_frames
    part_pos = demo.part_pos_w * scale
    part_rot = quat_to_matrix(demo.part_quat_w)
    human = human_probes(demo.surface, geometry.human_density_per_m2, seed, scale, geometry.even_probes)
    robot_set = robot_probes(geometry.robot_density_per_m2, seed, max_probes_per_link, geometry.even_probes)
    src = correspondences(robot_set, human, demo, scale, cache_dir, links_together)
    demo_points = ProbeSet(human.body_names, human.points[src], human.body[src])

    eye = np.broadcast_to(np.eye(3), (T, 3, 3))
    inf = np.full(3, np.inf)
    channels = [ChannelTrack("ground", GroundChannel("ground", geometry.band_m), FIXED, np.zeros((T, 3)), eye,
                             -inf, inf, np.zeros((0, 3)), None)]
    objects: list[FreeObject] = []
    if mode != "robot-only":
        for obj in demo.objects:
            ch = _object_channel(obj, geometry, cache_dir)
            swap = substitution_for(obj, ch, geometry, cache_dir)
            free = mode == "native" and not obj.static
            body = NUM_LINKS + len(objects) if free else FIXED
            lower, upper = ch.mesh.bounds
            channels.append(ChannelTrack(obj.name, ch, body, scaled_object_positions(obj.pos_w, scale),
                                         quat_to_matrix(obj.quat_w),
                                         lower, upper, hull_guard_points(ch.mesh.vertices, guard_spacing_m,
                                                                         along_edges=True),
                                         cached_margin(ch.grid, ch.mesh, MARGIN_REACH_M, cache_dir), swap,
                                         object_surface_guards(ch.mesh)))
            if free:
                objects.append(FreeObject(obj.name, len(channels) - 1, ch.surface.points,
                                          None if swap is None else swap.demonstrated_points(ch.surface.points)))

    targets = robot_style_targets(part_pos, demo.part_quat_w, kin, pelvis_height_ratio(demo.stature_m * scale))
    guards = robot_guard_points(guard_spacing_m)
    feet = robot.body_indices(list(robot.FEET))
    soles = tuple(sole_points(guards.points[guards.body == f], stance.sole_band_m) for f in feet)
    in_stance, sweep, turns = demonstrated_feet(demo, part_pos, part_rot, scale, soles, stance)
    vertex_guards = robot_vertex_guards()
    both = ProbeSet(robot_set.body_names, np.concatenate([robot_set.points, guards.points]),
                    np.concatenate([robot_set.body, guards.body]))
    centre, radius = both.bounding_spheres()
    (ga, gd), (va, vd) = guard_anchors(robot_set, guards), guard_anchors(robot_set, vertex_guards)
    gap = np.zeros(NUM_LINKS)
    np.maximum.at(gap, vertex_guards.body, vd)
    anchors = {"guard_anchor": ga, "guard_anchor_d": gd, "vertex_anchor": va, "vertex_anchor_d": vd,
               "sampling_gap": gap}
    problem = Problem(fps=demo.fps, kin=kin, robot=robot_set, guards=guards, vertex_guards=vertex_guards,
                      link_center=centre, link_radius=radius, **anchors,
                      link_grids=robot_link_grids(solver.check_margin_m, cache_dir),
                      demo_points=demo_points, part_pos_w=part_pos, part_rot_w=part_rot, channels=tuple(channels),
                      objects=tuple(objects), style=targets, q_init=np.zeros(kin.nq), interaction=interaction,
                      style_cfg=style, solver=solver, band_m=geometry.band_m,
                      surface_margin=surface_margin_m() + link_clearance(solver.link_clearance_m),
                      feet=np.asarray(feet, np.intp), soles=soles, stance=in_stance, sweep=sweep, turns=turns,
                      stance_cfg=stance, self_pairs=link_pairs_beyond(kin.parents, 2),
                      self_points=robot_self_points()[0], self_clusters=robot_self_points()[1],
                      contact_units=contact_units(), **unit_surface(demo.surface, scale))
    return replace(problem, q_init=initial_configuration(problem),
                   object_style_w=object_hold_weights(demo, problem, scale, geometry.band_m))


def object_hold_weights(demo: Demonstration, problem: Problem, scale: float, band_m: float) -> np.ndarray | None:
    """(T, O, 2) per-frame (λ_o,pos, λ_o,rot) of the free objects (``retarget.solver.holds``);
    None when there is no free object or the hold weights are no stronger than the base ones."""
    from retarget.solver.holds import hand_gaps, hold_blend, hold_frames, is_box_like, object_style_weights

    cfg = problem.style_cfg
    if not problem.objects or (cfg.hold_pos_weight <= cfg.object_pos_weight
                               and cfg.hold_rot_weight <= cfg.object_rot_weight):
        return None
    ramp = int(round(cfg.hold_ramp_s * problem.fps))
    blend = np.zeros((problem.num_frames, len(problem.objects)))
    for i, o in enumerate(problem.objects):
        track = problem.channels[o.channel]
        if cfg.hold_boxes_only and not is_box_like(track.channel.mesh):
            continue
        gaps = hand_gaps(demo, problem.part_pos_w, problem.part_rot_w, scale, track, band_m)
        blend[:, i] = hold_blend(hold_frames(gaps, track.pos_w[:, 2], cfg), ramp)
    return object_style_weights(blend, cfg)


def unit_surface(surface: HumanSurface, scale: float) -> dict[str, np.ndarray | ProbeSet]:
    """``Problem.unit_surface`` and ``unit_of_vertex``: the mesh vertices of every human part
    that a contact unit stands for (part frames, × ``scale``); parts of no unit (fingers) are left out."""
    from retarget.evaluation.units import default_units

    unit_of_part = {part: u for u, unit in enumerate(default_units()) for part in unit.parts}
    parts = [k for k, name in enumerate(surface.part_names) if name in unit_of_part]
    points = np.concatenate([np.asarray(surface.vertices[k], np.float64) * scale for k in parts])
    body = np.repeat(np.asarray(parts, np.intp), [len(surface.vertices[k]) for k in parts])
    units = np.repeat(np.asarray([unit_of_part[surface.part_names[k]] for k in parts], np.intp),
                      [len(surface.vertices[k]) for k in parts])
    return {"unit_surface": ProbeSet(tuple(surface.part_names), points, body), "unit_of_vertex": units}


@lru_cache(maxsize=1)
def contact_units() -> np.ndarray:
    """(L,) the evaluation unit of each G1 link (``retarget.evaluation.units.default_units``)."""
    from retarget.evaluation.units import default_units

    out = np.full(NUM_LINKS, -1, np.intp)
    for u, unit in enumerate(default_units()):
        out[robot.body_indices(list(unit.links))] = u
    free = np.flatnonzero(out < 0)
    out[free] = out.max() + 1 + np.arange(len(free))
    return out


def demonstrated_feet(demo: Demonstration, part_pos_w: np.ndarray, part_rot_w: np.ndarray, scale: float,
                      soles: tuple[np.ndarray, ...], cfg: StanceConfig) -> tuple[np.ndarray, np.ndarray, FootTurns]:
    """The person's stance and sweep flags (T, F; ``demonstrated_stance``), stance turns
    mapped onto the G1 soles and roll-offs (``demonstrated_roll``), from the foot units (the
    human parts of each G1 foot link, ``retarget.inputs.human.G1_LINK_PARTS``: ankle, then toes),
    surface × ``scale`` (``retarget.solver.stance``)."""
    from retarget.inputs.human import G1_LINK_PARTS

    names = list(demo.surface.part_names)
    parts = [[names.index(p) for p in G1_LINK_PARTS[foot]] for foot in robot.FEET]
    vertices = [np.concatenate([np.einsum("tij,vj->tvi", part_rot_w[:, k], scale * np.asarray(demo.surface.vertices[k]))
                                + part_pos_w[:, k, None] for k in ks], axis=1) for ks in parts]
    stance, sweep = demonstrated_stance(np.stack([v[..., 2].min(axis=1) for v in vertices], axis=1),
                                        np.stack([least_moving_speed(v, demo.fps) for v in vertices], axis=1),
                                        least_moving_speed(part_pos_w[:, :1], demo.fps), cfg, demo.fps)
    boxes = np.stack([[s[:, :2].min(axis=0), s[:, :2].max(axis=0)] for s in soles])
    ankles, toes = part_pos_w[:, [ks[0] for ks in parts]], part_pos_w[:, [ks[1] for ks in parts]]
    turns = demonstrated_turns(ankles, part_rot_w[:, [ks[0] for ks in parts]], toes, vertices, stance, boxes,
                               cfg.pivot_min_rad)
    rolling = demonstrated_roll(ankles, toes, stance, cfg.roll_tilt_rad)
    return stance, sweep, replace(turns, rolling=rolling)


#: Cells of an object grid within this distance of the surface get a measured error margin.
MARGIN_REACH_M = 0.02

#: Resolution of the robot links' distance grids (m): 5 mm keeps the trilinear error on the
#: arms' 3.5 cm radius below 0.1 mm (h²/8R), where a 1 cm grid would err by 0.4 mm.
LINK_GRID_RESOLUTION_M = 0.005


@lru_cache(maxsize=2)
def robot_link_grids(reach_m: float, cache_dir: Path | None = None) -> GridStack:
    """The signed distance grids of the G1 links' visual meshes (link frames) out to
    ``reach_m`` (exact there; beyond, a lower bound: ``build_sdf_grid``'s ``far_m``), stacked in
    BODY_NAMES order (links without a mesh have none); each grid is
    cached on disk like the object grids, one file per link mesh (its content hash in the name:
    scoring on Unitree's original meshes, ``otr_gym.true_surface``, must not evict the shipped
    meshes' grids, and the other way round)."""
    from retarget.geometry.cache import cached_arrays, default_cache_dir
    from retarget.geometry.voxel_grid import VoxelGrid, build_sdf_grid

    meshes = visual_meshes()
    root = (default_cache_dir() if cache_dir is None else Path(cache_dir)) / "robot_links"
    # read only closer than reach_m: nodes whose every cell lies beyond it are bounded, not measured
    far_m = reach_m + np.sqrt(3.0) * LINK_GRID_RESOLUTION_M
    grids = []
    for name in robot.BODY_NAMES:
        if name not in meshes:
            grids.append(None)
            continue
        mesh = as_trimesh(meshes[name].vertices, meshes[name].faces, f"G1 link {name}")
        key = f"{mesh.content_hash}-{LINK_GRID_RESOLUTION_M}-{reach_m}-bounded-beyond-{far_m}"

        def build(mesh=mesh) -> dict[str, np.ndarray]:
            g = build_sdf_grid(mesh, LINK_GRID_RESOLUTION_M, reach_m, far_m)
            return {"origin": g.origin, "shape": np.array(g.shape), "values": g.values}

        def check(a: dict[str, np.ndarray]) -> None:
            if a["values"].shape != (int(np.prod(a["shape"])), 4) or not np.isfinite(a["values"]).all():
                raise ValueError("inconsistent grid arrays")

        a = cached_arrays(root / f"{name}-{mesh.content_hash[:16]}.npz", key, build, check)
        grids.append(VoxelGrid(np.asarray(a["origin"], np.float64), LINK_GRID_RESOLUTION_M,
                               tuple(int(v) for v in a["shape"]), np.ascontiguousarray(a["values"], np.float64)))
    return GridStack(grids)


def guard_anchors(probes: ProbeSet, guards: ProbeSet) -> tuple[np.ndarray, np.ndarray]:
    """For every guard point, the nearest area probe of the same link (index into ``probes``)
    and their distance (m), in the link frame."""
    anchor = np.zeros(len(guards), np.intp)
    dist = np.zeros(len(guards))
    for k in range(len(probes.body_names)):
        p_idx, g_idx = np.flatnonzero(probes.body == k), np.flatnonzero(guards.body == k)
        if len(g_idx):
            if len(p_idx) == 0:
                raise RuntimeError(f"link {probes.body_names[k]} has guard points but no area probe")
            dist[g_idx], nearest = cKDTree(probes.points[p_idx]).query(guards.points[g_idx])
            anchor[g_idx] = p_idx[nearest]
    return anchor, dist


def initial_configuration(problem: Problem) -> np.ndarray:
    """Cold start: pelvis at the demonstrated pelvis with its desired orientation, default
    joints, lowered or raised so that the lowest robot point touches the ground."""
    from otr_gym.rotations import matrix_to_quat, wxyz_to_xyzw

    links = list(problem.style.links)
    pelvis = links.index(robot.body_indices([robot.ROOT_BODY])[0])
    q = np.concatenate([problem.part_pos_w[0, 0], wxyz_to_xyzw(matrix_to_quat(problem.style.rot_w[0, pelvis])),
                        robot.DEFAULT_JOINT_POS])
    fr = problem.kin.frames(problem.kin.new_data(), q)
    lowest = min(problem.robot.posed(fr.rot, fr.pos)[:, 2].min(), problem.guards.posed(fr.rot, fr.pos)[:, 2].min())
    q[2] -= lowest
    return q
