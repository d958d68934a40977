"""Dynamic feasibility of a reference: what a tracking policy on the real G1 will find hard.

``check_feasibility(reference)`` looks at the motion alone (no demonstration), at the tracking
rate (50 fps, docs/environment.md §2: the clip is resampled at load exactly like this), frame by frame:

* **jumps**: how far the pelvis lies off the straight line between its neighbours,
  |p_t − (p_{t−1} + p_{t+1})/2| = |a|·dt²/2 (1 cm at 50 fps is 5 g): a teleport of the
  reference, which no robot follows;
* **limb jumps**: the same for the feet and hands (ankle roll and wrist yaw links), whose
  teleports the pelvis bound does not catch: a foot held flat while the person rolls onto the
  ball snaps to its swing pose in one frame when the stance ends (AMASS jog: 20 cm in 1/120 s);
* **joint speed** |q̇| (central differences) against ``robot.VELOCITY_LIMIT``;
* **joint acceleration** |q̈| against what the joint's motor can give it alone,
  τ_max / M_ii(q): the full effort limit acting on the joint's own inertia (armature included),
  everything else held. A reference above it cannot be followed whatever the rest does;
* **torques** from contact-consistent inverse dynamics (below) against ``robot.EFFORT_LIMIT``;
* **unsupported base wrench**: the part of the floating base's wrench that the feet cannot
  supply from the floor (no foot down, a pull, a push outside the friction cone or the sole);
  as a fraction of the robot's weight. Non-zero in flight unless the flight is ballistic;
* **sliding**: horizontal speed of the least-moving vertex of a foot on the ground (its lowest
  vertex within ``contact_height_m``; ``retarget.evaluation.feet.least_moving_speed``, so
  heel/toe pivots do not count, while a swing foot skimming the floor does: it would drag);
* **flight**: frames with no part of the robot on the floor, grouped into phases with their
  duration (hands, knees or any other link on the floor support a crawl like feet do);
* **penetration**: how deep the robot's collision geometry as the simulation has it
  (``otr_gym.robot_geometry.collision_points``: capsules, spheres, the hands' boxes) lies below
  the ground, and which link. The simulation pushes such a link back out, so a policy cannot
  put it where the reference does: a reference that puts our hands in the ground (Holosoma's
  crawl: 8.9 cm into its ramp and platform) asks for wrist angles the robot can only miss
  (``otr clear-ground`` re-solves the arms out of it).

Inverse dynamics (Pinocchio). v and a are Lie-group finite differences of the configurations
(``pin.difference``: the free-flyer twist in the pelvis frame, exact for a constant twist).
As in inverse-dynamics practice on motion capture (Winter's 6 Hz), the twists are low-passed
first (zero-phase Butterworth, ``lowpass_hz``) for accelerations and torques: differencing twice
turns a retargeter's millimetre frame-to-frame jitter into accelerations of several g that the
PD loop never follows (a 1 mm wobble at 50 fps is 0.5 g). Speeds, jumps (pelvis and limbs) and sliding use the raw
motion. τ_rnea = RNEA(q, v, a) = M a + h includes the armature. The ground can only push: each sole
point (the corners of the G1 foot capsules, ``otr_gym.robot_geometry``; for every other link the
points of its geometry as the simulation collides it, ``collision_points``: the point of each
capsule end sphere or sphere nearest the ground, each corner of the hands' boxes) within
``contact_height_m`` of the ground carries a force in the linearised friction cone (4 edges,
coefficient μ), f = E λ, λ ≥ 0. The contact forces are the non-negative least-squares fit of
the base rows, min ‖W(τ_rnea[:6] − (Jᵀ E λ)[:6])‖² + ε‖λ‖² (W weighs moments by 1/L to make
them forces), so they supply as much of the base wrench as physics allows and never pull.
What they cannot supply is the *unsupported* wrench; the joint torques are
τ = τ_rnea[6:] − (Jᵀ E λ)[6:], i.e. with the unsupported remainder applied at the pelvis (a
"hand of god", flagged separately). This is the standard contact-consistent inverse dynamics
of a floating base; plain RNEA would hold the pelvis instead and hide the stance-leg torques.

The ground is the floor z = 0 (``retarget.checks.ground``), and with ``ground=Ground.from_mesh(FILE)``
(``otr verify --terrain FILE``) also a terrain mesh on it: support points then
stand on the highest upward face beneath them, "within ``contact_height_m``" is measured along
that face's normal and the friction cone is built about it. Without the terrain, a reference
recorded on one (Holosoma's crawl up a slope onto a platform) shows up as flight wherever it
leaves the plane.

Severity of a frame = the largest ratio of a measure to its limit. Flight is not a limit: a
thrown body needs no support, and a flight that is not ballistic shows as unsupported force (the
issue's rule: the base wrench within what the contacts supply, except in demonstrated flight,
where the pelvis follows a ballistic arc); flight phases are reported beside the limits.
``FeasibilityReport.intervals`` are the runs of frames at severity ≥ 1; ``hardest`` picks the
worst frames (one per ``peak_separation_s``) with every measure over its limit there and the
run it belongs to; ``format_report`` prints the summary and that table, ``plot_feasibility``
draws the timeline (PNG).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from otr_gym import robot
from otr_gym.flags import true_intervals
from otr_gym.robot_geometry import posed_vertices, visual_meshes
from otr_gym.rotations import skew
from retarget.checks.ground import Ground
from retarget.evaluation.feet import least_moving_speed
from retarget.geometry.dynamics import (
    GRAVITY,
    ObjectMass,
    carried_object_load,
    cone_edges,
    g1_dynamics,
    hand_points,
    lowpass,
    twist_steps,
    velocity_acceleration,
)

FOOT_NAMES = ("left", "right")
#: The limbs whose jumps are measured: ``robot.FEET`` then ``robot.HANDS``.
LIMB_NAMES = ("left foot", "right foot", "left hand", "right hand")


@dataclass(frozen=True)
class FeasibilityCfg:
    fps: float = 50.0  # analyse at the tracking rate (docs/environment.md §2: references resampled to 50 fps)
    #: A sole point (or, for stance, the foot mesh's lowest vertex) within this distance (m) of
    #: the ground (the floor z = 0, or a terrain face along its normal) is on the ground.
    contact_height_m: float = 0.02
    #: Friction coefficient of the cone (MuJoCo's default 1.0; training randomises foot friction
    #: in [0.3, 1.2], docs/environment.md §6): 0.7 is a floor the policy meets often.
    friction: float = 0.7
    #: Accelerations and torques from twists low-passed at this frequency (Hz; None: raw).
    lowpass_hz: float | None = 6.0
    #: Moments are divided by this length (m) to weigh them like forces in the contact fit.
    moment_length_m: float = 0.5
    #: Weight of ‖λ‖² in the contact fit (N⁻²·N²: picks the smallest forces among equals) for
    #: the feet, and for every other link (hands, knees): 100× more, so the fit leans on a hand
    #: only where the feet cannot carry the motion (a 5 N·m wrist holding body weight is a
    #: finding only if the feet could not have).
    force_regularization: float = 1e-6
    other_link_regularization: float = 1e-4
    #: Flags: stance sliding above this speed (m/s); unsupported base force above this fraction
    #: of the weight (the ratios to the joint limits flag at 1).
    slide_speed_mps: float = 0.05
    unsupported_fraction: float = 0.2
    jump_m: float = 0.01  # pelvis off the line of its neighbours by more (m): 5 g at 50 fps
    #: A foot or hand off the line of its neighbours by more (m): 15 g at 50 fps, beyond a
    #: heel strike's deceleration.
    limb_jump_m: float = 0.03
    #: Collision geometry deeper than this below the ground (m) is flagged: the simulation's
    #: contacts push it out (our references keep the hands within 2 cm of their ground).
    penetration_m: float = 0.03
    #: What a carried object weighs (``retarget.geometry.dynamics.ObjectMass``): its weight and
    #: acceleration load the hands holding it (torques and the base wrench include them).
    object_mass: ObjectMass = ObjectMass()
    merge_gap_frames: int = 2  # flagged frames closer than this join one interval
    peak_separation_s: float = 0.2  # the hardest-frames table keeps one frame per window


@dataclass(frozen=True)
class HardFrame:
    """One of the hardest frames: its severity, the flagged run [start, stop] around it and
    why (measure -> text with the value and the joint or foot)."""

    frame: int
    severity: float
    start: int
    stop: int
    reasons: dict[str, str]


@dataclass
class FeasibilityReport:
    """Per-frame measures (T = frames at ``fps``) and the ranked flagged intervals."""

    source: str
    fps: float
    cfg: FeasibilityCfg
    root_height_m: np.ndarray  # (T,)
    root_jump_m: np.ndarray  # (T,) pelvis off the line of its neighbours
    limb_jump_m: np.ndarray  # (T, 4) feet and hands (LIMB_NAMES) off the lines of their neighbours
    joint_speed_ratio: np.ndarray  # (T, 29) |q̇| / velocity limit
    joint_accel_ratio: np.ndarray  # (T, 29) |q̈| / (τ_max / M_ii)
    torque_nm: np.ndarray  # (T, 29) contact-consistent inverse dynamics
    torque_ratio: np.ndarray  # (T, 29) |τ| / effort limit
    foot_force_w: np.ndarray  # (T, 2, 3) N, world: total floor force on each foot
    other_force_w: np.ndarray  # (T, 3) N, world: floor force on every other link (hands, knees, …)
    other_support: np.ndarray  # (T,) bool: a link other than the feet on the floor
    unsupported_force_n: np.ndarray  # (T,) N: base force the floor cannot supply
    unsupported_moment_nm: np.ndarray  # (T,) N·m
    stance: np.ndarray  # (T, 2) bool: the foot's lowest vertex within contact_height_m
    slide_speed_mps: np.ndarray  # (T, 2) least-moving-vertex speed, NaN when not in stance
    penetration_m: np.ndarray  # (T,) m: how deep the deepest collision point lies below the ground (0: none)
    penetration_link: tuple[str, ...]  # (T,) the link it belongs to ("" where none is below)
    weight_n: float
    object_load_w: np.ndarray  # (T, 2, 3) N, world: carried objects' force on each hand (robot.HANDS)
    ground: str = "floor z = 0"  # what the robot stands on (``Ground.describe``)

    @property
    def num_frames(self) -> int:
        return int(self.root_height_m.shape[0])

    @property
    def time_s(self) -> np.ndarray:
        return np.arange(self.num_frames) / self.fps

    @property
    def flight(self) -> np.ndarray:
        """(T,) bool: nothing on the ground (neither foot nor any other link)."""
        return ~(self.stance.any(axis=1) | self.other_support)

    @property
    def unsupported_fraction(self) -> np.ndarray:
        """(T,) unsupported base force / weight."""
        return self.unsupported_force_n / self.weight_n

    def flight_phases(self) -> list[tuple[int, int]]:
        """[(first, last)] frames of each flight phase."""
        return _runs(self.flight)

    def measures(self) -> dict[str, np.ndarray]:
        """measure -> (T,) ratio to its limit (flight is no limit: see ``flight_frames``)."""
        c = self.cfg
        return {
            "jump": self.root_jump_m / c.jump_m,
            "limb jump": self.limb_jump_m.max(axis=1) / c.limb_jump_m,
            "joint speed": self.joint_speed_ratio.max(axis=1),
            "joint accel": self.joint_accel_ratio.max(axis=1),
            "torque": self.torque_ratio.max(axis=1),
            "unsupported": self.unsupported_fraction / c.unsupported_fraction,
            "sliding": np.nan_to_num(self.slide_speed_mps, nan=0.0).max(axis=1) / c.slide_speed_mps,
            "penetration": self.penetration_m / c.penetration_m,
        }

    def severity(self) -> np.ndarray:
        """(T,) the largest ratio of a measure to its limit."""
        return np.max(np.stack(list(self.measures().values())), axis=0)

    @property
    def intervals(self) -> list[tuple[int, int]]:
        """[(first, last)] runs of frames at severity ≥ 1 (gaps ≤ ``merge_gap_frames`` closed)."""
        return _runs(self.severity() >= 1.0, self.cfg.merge_gap_frames)

    def reasons(self, f: int) -> dict[str, str]:
        """Every measure at or over its limit at frame ``f``, with its value and where."""
        c, t = self.cfg, self.time_s
        why: dict[str, str] = {}
        if self.root_jump_m[f] >= c.jump_m:
            why["jump"] = f"pelvis {100 * self.root_jump_m[f]:.1f} cm off its neighbours' line"
        k = int(np.argmax(self.limb_jump_m[f]))
        if self.limb_jump_m[f, k] >= c.limb_jump_m:
            why["limb jump"] = f"{LIMB_NAMES[k]} {100 * self.limb_jump_m[f, k]:.1f} cm off its neighbours' line"
        for key, ratio, unit in (("joint speed", self.joint_speed_ratio, "velocity limit"),
                                 ("joint accel", self.joint_accel_ratio, "motor-alone limit"),
                                 ("torque", self.torque_ratio, "effort limit")):
            j = int(np.argmax(ratio[f]))
            if ratio[f, j] >= 1.0:
                text = f"{robot.JOINT_NAMES[j].removesuffix('_joint')} {ratio[f, j]:.1f}x {unit}"
                if key == "torque":
                    text += f" ({abs(self.torque_nm[f, j]):.0f} N·m)"
                why[key] = text
        if self.unsupported_fraction[f] >= c.unsupported_fraction:
            why["unsupported"] = f"{100 * self.unsupported_fraction[f]:.0f}% of weight"
        slide = np.nan_to_num(self.slide_speed_mps[f], nan=0.0)
        k = int(np.argmax(slide))
        if slide[k] >= c.slide_speed_mps:
            why["sliding"] = f"{FOOT_NAMES[k]} foot {100 * slide[k]:.0f} cm/s"
        for a, b in self.flight_phases():
            if a <= f <= b:
                why["flight"] = f"{(b - a + 1) / self.fps:.2f} s ({t[a]:.2f}-{t[b]:.2f} s)"
        if self.penetration_m[f] >= c.penetration_m:
            why["penetration"] = f"{self.penetration_link[f]} {100 * self.penetration_m[f]:.1f} cm into the ground"
        return why

    def frames_over(self) -> dict[str, int]:
        """measure -> how many frames reach its limit."""
        return {key: int((ratio >= 1.0).sum()) for key, ratio in self.measures().items()}

    def flagged_share(self) -> float:
        """Fraction of the clip's frames at or over some limit (0 for a feasible reference)."""
        return float((self.severity() >= 1.0).mean()) if self.num_frames else 0.0

    def brief(self) -> dict:
        """What a corpus table needs of this clip: the flagged share, frames over each limit, the
        peaks of the limb and pelvis jumps (m) and of the torque over effort, and the verdict."""
        return {"flagged_share": self.flagged_share(), "frames_over": self.frames_over(),
                "limb_jump_peak_m": float(self.limb_jump_m.max(initial=0.0)),
                "pelvis_jump_peak_m": float(self.root_jump_m.max(initial=0.0)),
                "torque_peak_ratio": float(self.torque_ratio.max(initial=0.0)),
                "flight_frames": int(self.flight.sum()), "verdict": self.verdict()}

    def verdict(self) -> str:
        """One line: "feasible", or how many frames are over which limits (most frames first);
        frames in the air are named beside them (no limit: their support is judged as unsupported force)."""
        flagged = int((self.severity() >= 1.0).sum())
        air = int(self.flight.sum())
        in_air = f"; {air} frames in the air" if air else ""
        if flagged == 0:
            return f"verdict: feasible (no frame of {self.num_frames} reaches a limit{in_air})"
        over = sorted(((n, key) for key, n in self.frames_over().items() if n), reverse=True)
        return (f"verdict: {flagged} of {self.num_frames} frames ({100 * flagged / self.num_frames:.1f} %) over a "
                f"limit: {', '.join(f'{key} {n}' for n, key in over)}{in_air}")

    def hardest(self, count: int = 10) -> list[HardFrame]:
        """The ``count`` worst frames at severity ≥ 1, at most one per ``peak_separation_s``."""
        sev = self.severity()
        runs = self.intervals
        window = max(1, round(self.cfg.peak_separation_s * self.fps))
        taken = np.zeros(self.num_frames, bool)
        out = []
        for f in np.argsort(-sev, kind="stable"):
            if len(out) >= count or sev[f] < 1.0:
                break
            if taken[f]:
                continue
            taken[max(0, f - window + 1):f + window] = True
            start, stop = next((a, b) for a, b in runs if a <= f <= b)
            out.append(HardFrame(int(f), float(sev[f]), start, stop, self.reasons(int(f))))
        return out

    def summary(self) -> dict:
        """Peak of every measure, where it happens, and how many frames reach the limit."""
        t = self.time_s
        out: dict = {"source": self.source, "fps": self.fps, "frames": self.num_frames,
                     "duration_s": (self.num_frames - 1) / self.fps, "ground": self.ground}
        f = int(np.argmax(self.root_jump_m))
        out["jump"] = {"peak_m": float(self.root_jump_m[f]), "time_s": float(t[f]),
                       "frames_over": int((self.root_jump_m >= self.cfg.jump_m).sum())}
        f, k = np.unravel_index(np.argmax(self.limb_jump_m), self.limb_jump_m.shape)
        out["limb_jump"] = {"peak_m": float(self.limb_jump_m[f, k]), "limb": LIMB_NAMES[k], "time_s": float(t[f]),
                            "frames_over": int((self.limb_jump_m.max(axis=1) >= self.cfg.limb_jump_m).sum())}
        for key, ratio, extra in (("joint_speed", self.joint_speed_ratio, None),
                                  ("joint_accel", self.joint_accel_ratio, None),
                                  ("torque", self.torque_ratio, np.abs(self.torque_nm))):
            f, j = np.unravel_index(np.argmax(ratio), ratio.shape)
            out[key] = {"peak_ratio": float(ratio[f, j]), "joint": robot.JOINT_NAMES[j], "time_s": float(t[f]),
                        "frames_over": int((ratio.max(axis=1) >= 1.0).sum())}
            if extra is not None:
                out[key]["peak_nm"] = float(extra[f, j])
        f = int(np.argmax(self.unsupported_fraction))
        out["unsupported"] = {"peak_fraction_of_weight": float(self.unsupported_fraction[f]), "time_s": float(t[f]),
                              "peak_moment_nm": float(self.unsupported_moment_nm.max()),
                              "frames_over": int((self.unsupported_fraction >= self.cfg.unsupported_fraction).sum())}
        slide = self.slide_speed_mps
        on = np.isfinite(slide)
        if on.any():
            f, k = np.unravel_index(np.nanargmax(slide), slide.shape)
            out["stance_sliding"] = {"median_mps": float(np.median(slide[on])), "peak_mps": float(slide[f, k]),
                                     "foot": FOOT_NAMES[k], "time_s": float(t[f]),
                                     "frames_over": int((np.nan_to_num(slide, nan=0.0) >= self.cfg.slide_speed_mps)
                                                        .any(axis=1).sum())}
        else:
            out["stance_sliding"] = {"median_mps": None, "peak_mps": None, "frames_over": 0}
        phases = self.flight_phases()
        # A thrown body needs no support: what a flight phase leaves unsupported is the part of its
        # motion that is not ballistic (a reference that floats through a leap reads near 1).
        out["flight"] = {"phases": len(phases), "durations_s": [(b - a + 1) / self.fps for a, b in phases],
                         "total_s": float(self.flight.sum() / self.fps),
                         "unsupported_mean_fraction": [float(self.unsupported_fraction[a:b + 1].mean())
                                                       for a, b in phases]}
        f = int(np.argmax(self.penetration_m))
        out["penetration"] = {"peak_m": float(self.penetration_m[f]),
                              "link": self.penetration_link[f],
                              "time_s": float(t[f]),
                              "frames_over": int((self.penetration_m >= self.cfg.penetration_m).sum())}
        out["flagged_frames"] = int((self.severity() >= 1.0).sum())
        out["flagged_share"] = self.flagged_share()
        out["frames_over"] = self.frames_over()
        out["verdict"] = self.verdict()
        out["hardest"] = [{"frame": h.frame, "time_s": float(t[h.frame]), "severity": h.severity,
                           "run_s": [float(t[h.start]), float(t[h.stop])], "why": h.reasons} for h in self.hardest()]
        return out


def _contact_fit(base: np.ndarray, jac_base: np.ndarray, reg: np.ndarray, cfg: FeasibilityCfg) -> np.ndarray:
    """λ ≥ 0 (N along the cone edges) minimising ‖W(base − jac_base λ)‖² + Σ εᵢλᵢ² (NNLS on the
    stacked system; ``reg`` the εᵢ)."""
    from scipy.optimize import nnls

    n = jac_base.shape[1]
    w = np.array([1, 1, 1] + [1.0 / cfg.moment_length_m] * 3)
    a = np.vstack([w[:, None] * jac_base, np.diag(np.sqrt(reg))])
    b = np.concatenate([w * base, np.zeros(n)])
    lam, _ = nnls(a, b, maxiter=50 * n)
    return lam


def check_feasibility(reference, cfg: FeasibilityCfg | None = None, ground: Ground | None = None) -> FeasibilityReport:
    """Measure ``reference`` (an ``otr_gym.reference.Reference``) at ``cfg.fps`` standing on
    ``ground`` (default: the floor z = 0; see the module doc)."""
    import pinocchio as pin

    cfg = cfg or FeasibilityCfg()
    ground = ground or Ground.floor()
    ref = reference.resampled(cfg.fps)
    T = ref.num_frames
    mdl = g1_dynamics()
    m = mdl.pin_model
    data = m.createData()
    dt = 1.0 / cfg.fps
    if T < 3:
        raise ValueError(f"{reference.source}: {T} frames at {cfg.fps:g} fps; the feasibility check needs 3")
    q = robot.qpos_mujoco_to_pinocchio(ref.qpos())
    load = carried_object_load(ref, hand_points(q), cfg.object_mass, lowpass_hz=cfg.lowpass_hz)
    step = twist_steps(q, dt)
    v_raw, _ = velocity_acceleration(step, dt)
    v, a = velocity_acceleration(lowpass(step, cfg.lowpass_hz, cfg.fps), dt)
    weight = mdl.mass_kg * GRAVITY
    # one cone per ground normal: the floor's and each terrain face's (a handful), built once
    cones: dict[tuple[float, ...], np.ndarray] = {(0.0, 0.0, 1.0): cone_edges(cfg.friction)}

    def edges(n: np.ndarray) -> np.ndarray:
        key = tuple(n.tolist())
        if key not in cones:
            cones[key] = cone_edges(cfg.friction, n)
        return cones[key]

    sole_ids = [(k, fid) for k, ids in enumerate(mdl.sole_frames) for fid in ids]
    torque = np.zeros((T, robot.NUM_JOINTS))
    accel_limit = np.zeros((T, robot.NUM_JOINTS))
    foot_force = np.zeros((T, 2, 3))
    other_force = np.zeros((T, 3))
    other_support = np.zeros(T, bool)
    unsup_f = np.zeros(T)
    unsup_m = np.zeros(T)
    probe_radius = np.array([r for _, r, _ in mdl.probe_frames])
    # one ground query per frame: the sole points, then the probes (those of the other links
    # are their support points)
    point_frames = [fid for _, fid in sole_ids] + [fid for fid, _, _ in mdl.probe_frames]
    n_sole = len(sole_ids)
    depth = np.zeros(T)
    deepest: list[str] = [""] * T
    for t in range(T):
        tau = pin.rnea(m, data, q[t], v[t], a[t]).copy()
        mass = pin.crba(m, data, q[t])
        accel_limit[t] = robot.EFFORT_LIMIT / np.diag(mass)[6:]
        pin.computeJointJacobians(m, data, q[t])
        pin.updateFramePlacements(m, data)
        for k, fid in enumerate(mdl.hand_frames):  # what a carried object asks of the hands
            if load[t, k].any():
                tau -= pin.getFrameJacobian(m, data, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[:3].T @ load[t, k]
        height, normal = ground.under(np.array([data.oMf[fid].translation for fid in point_frames]))
        probe_height, probe_normal = height[n_sole:], normal[n_sole:]
        below = probe_radius - probe_height  # how far each geom's lowest reach lies under the ground
        i = int(np.argmax(below))
        if below[i] > 0.0:
            depth[t], deepest[t] = below[i], mdl.probe_frames[i][2]
        cols, owners, point_edges = [], [], []
        for i, (k, fid) in enumerate(sole_ids):
            if height[i] <= cfg.contact_height_m:
                jac = pin.getFrameJacobian(m, data, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[:3]
                point_edges.append(edges(normal[i]))
                cols.append(jac.T @ point_edges[-1])  # (nv, 4): generalised force of each cone edge
                owners.append(k)
        for i in mdl.link_probes:
            fid, radius, _ = mdl.probe_frames[i]
            if probe_height[i] - radius <= cfg.contact_height_m:
                jac = pin.getFrameJacobian(m, data, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
                # the sphere's point nearest the ground, r from the centre against the normal
                # (a box corner: r = 0): v = v_c + ω × (−r n)
                lowest = jac[:3] - skew(-radius * probe_normal[i]) @ jac[3:]
                point_edges.append(edges(probe_normal[i]))
                cols.append(lowest.T @ point_edges[-1])
                owners.append(2)
                other_support[t] = True
        if cols:
            gen = np.concatenate(cols, axis=1)
            owner = np.asarray(owners)
            reg = np.repeat(np.where(owner == 2, cfg.other_link_regularization, cfg.force_regularization), 4)
            lam = _contact_fit(tau[:6], gen[:6], reg, cfg)
            tau -= gen @ lam
            per_point = np.einsum("pij,pj->pi", np.stack(point_edges), lam.reshape(-1, 4))  # (P, 3) world forces
            for k in range(2):
                foot_force[t, k] = per_point[owner == k].sum(axis=0)
            other_force[t] = per_point[owner == 2].sum(axis=0)
        torque[t] = tau[6:]
        unsup_f[t] = np.linalg.norm(tau[:3])
        unsup_m[t] = np.linalg.norm(tau[3:6])

    root = ref.root_pos_w
    limbs = ref.body_pos_w[:, ref.body_index(list(robot.FEET + robot.HANDS))]
    jump = _off_neighbours_line(root)
    speed_ratio = np.abs(v_raw[:, 6:]) / robot.VELOCITY_LIMIT
    accel_ratio = np.abs(a[:, 6:]) / accel_limit
    stance, slide = _stance_and_sliding(ref, cfg, ground)
    return FeasibilityReport(
        source=str(reference.source), fps=cfg.fps, cfg=cfg, root_height_m=root[:, 2].copy(), root_jump_m=jump,
        limb_jump_m=_off_neighbours_line(limbs),
        joint_speed_ratio=speed_ratio, joint_accel_ratio=accel_ratio, torque_nm=torque,
        torque_ratio=np.abs(torque) / robot.EFFORT_LIMIT, foot_force_w=foot_force, other_force_w=other_force,
        other_support=other_support, unsupported_force_n=unsup_f,
        unsupported_moment_nm=unsup_m, stance=stance, slide_speed_mps=slide, weight_n=weight,
        ground=ground.describe(), object_load_w=load, penetration_m=depth, penetration_link=tuple(deepest))


def _off_neighbours_line(p: np.ndarray) -> np.ndarray:
    """(T, …) |p_t − (p_{t−1} + p_{t+1})/2| of positions (T, …, 3); 0 at the first and last frame."""
    out = np.zeros(p.shape[:-1])
    out[1:-1] = np.linalg.norm(p[1:-1] - 0.5 * (p[:-2] + p[2:]), axis=-1)
    return out


def _stance_and_sliding(ref, cfg: FeasibilityCfg, ground: Ground) -> tuple[np.ndarray, np.ndarray]:
    meshes = visual_meshes()
    idx = ref.body_index(list(robot.FEET))
    stance = np.zeros((ref.num_frames, 2), bool)
    slide = np.full((ref.num_frames, 2), np.nan)
    for k, (foot, i) in enumerate(zip(robot.FEET, idx)):
        verts = posed_vertices(meshes[foot], ref.body_pos_w[:, i], ref.body_quat_w[:, i])
        stance[:, k] = ground.under(verts)[0].min(axis=1) <= cfg.contact_height_m
        speed = least_moving_speed(verts, ref.fps)
        slide[stance[:, k], k] = speed[stance[:, k]]
    return stance, slide


def _runs(flags: np.ndarray, gap: int = 0) -> list[tuple[int, int]]:
    """[(first, last)] of the runs of True in ``flags`` (runs closer than ``gap`` frames merged)."""
    return [(a, b - 1) for a, b in true_intervals(flags, gap)]


def format_report(r: FeasibilityReport, worst: int = 10) -> str:
    """The summary lines and a table of the ``worst`` hardest frames."""
    s = r.summary()
    c = r.cfg
    lowpass = f"accelerations low-passed at {c.lowpass_hz:g} Hz" if c.lowpass_hz else "raw accelerations"
    lines = [(f"dynamic feasibility at {r.fps:g} fps ({s['frames']} frames, {s['duration_s']:.2f} s; friction "
              f"{c.friction:g}, {r.ground}, on it within {100 * c.contact_height_m:g} cm, {lowpass})")]
    j = s["jump"]
    lines.append(f"  {'jumps (pelvis off its path)':31s} peak {100 * j['peak_m']:.1f} cm (t {j['time_s']:.2f} s); "
                 f"{j['frames_over']} frames over {100 * c.jump_m:g} cm")
    j = s["limb_jump"]
    lines.append(f"  {'limb jumps (feet, hands)':31s} peak {100 * j['peak_m']:.1f} cm "
                 f"({j['limb']}, t {j['time_s']:.2f} s); "
                 f"{j['frames_over']} frames over {100 * c.limb_jump_m:g} cm")
    for key, label, unit in (("joint_speed", "joint speed", "x velocity limit"),
                             ("joint_accel", "joint acceleration", "x motor-alone limit"),
                             ("torque", "torque (contact-consistent ID)", "x effort limit")):
        d = s[key]
        extra = f", {d['peak_nm']:.0f} N·m" if "peak_nm" in d else ""
        lines.append(f"  {label:31s} peak {d['peak_ratio']:.2f}{unit} ({d['joint']}{extra}, t {d['time_s']:.2f} s); "
                     f"{d['frames_over']} frames over")
    u = s["unsupported"]
    lines.append(f"  {'unsupported base force':31s} peak {100 * u['peak_fraction_of_weight']:.0f}% of weight "
                 f"(t {u['time_s']:.2f} s), moment up to {u['peak_moment_nm']:.0f} N·m; {u['frames_over']} frames "
                 f"over {100 * c.unsupported_fraction:.0f}%")
    d = s["stance_sliding"]
    if d["peak_mps"] is None:
        lines.append(f"  {'sliding':31s} no foot ever on the ground")
    else:
        lines.append(f"  {'sliding (foot on the ground)':31s} median {100 * d['median_mps']:.1f} cm/s, "
                     f"peak {100 * d['peak_mps']:.1f} "
                     f"cm/s ({d['foot']} foot, t {d['time_s']:.2f} s); {d['frames_over']} frames over "
                     f"{100 * c.slide_speed_mps:g} cm/s")
    fl = s["flight"]
    phases = ", ".join(f"{x:.2f}" for x in fl["durations_s"]) or "none"
    lines.append(f"  {'flight (nothing on the ground)':31s} {fl['phases']} phase(s), {fl['total_s']:.2f} s in total "
                 f"(s: {phases}); other links than the feet on the ground {r.other_support.sum()} frames")
    p = s["penetration"]
    where = f" ({p['link']}, t {p['time_s']:.2f} s)" if p["link"] else ""
    lines.append(f"  {'collision geometry in the ground':31s} deepest {100 * p['peak_m']:.1f} cm{where}; "
                 f"{p['frames_over']} frames over {100 * c.penetration_m:g} cm")
    if fl["phases"]:
        airborne = ", ".join(f"{100 * x:.0f}%" for x in fl["unsupported_mean_fraction"])
        lines.append(f"  {'not ballistic in the air':31s} unsupported force, mean over each flight: {airborne} of "
                     "weight (a thrown body: 0)")
    hard = r.hardest(worst)
    if not hard:
        lines.append("no frame reaches a limit")
        return "\n".join(lines)
    lines.append(f"hardest frames ({s['flagged_frames']} of {s['frames']} flagged; severity = largest ratio to a "
                 f"limit; one per {c.peak_separation_s:g} s):")
    lines.append(f"  {'frame':>5} {'t (s)':>6} {'sev':>6}  {'run (s)':>11}  why")
    t = r.time_s
    for h in hard:
        why = "; ".join(f"{k}: {v}" for k, v in h.reasons.items())
        lines.append(f"  {h.frame:>5} {t[h.frame]:6.2f} {h.severity:6.1f}  {t[h.start]:5.2f}-{t[h.stop]:<5.2f}  {why}")
    return "\n".join(lines)


def plot_feasibility(r: FeasibilityReport, out_png: str | Path) -> Path:
    """Timeline PNG: joint speed / acceleration / torque ratios per body region, unsupported
    force, foot stance with sliding speed, root height; flight and flagged intervals shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from otr_gym.io import save_figure

    t = r.time_s
    regions = {"legs": slice(0, 12), "waist": slice(12, 15), "arms": slice(15, 29)}
    fig, axes = plt.subplots(6, 1, figsize=(10, 10), sharex=True, layout="constrained")
    panels = ((axes[0], r.joint_speed_ratio, "|q̇| / velocity limit"),
              (axes[1], r.joint_accel_ratio, "|q̈| / (τmax / Mii)"),
              (axes[2], r.torque_ratio, "|τ| / effort limit"))
    for ax, ratio, title in panels:
        for name, cols in regions.items():
            ax.plot(t, ratio[:, cols].max(axis=1), lw=1.1, label=name)
        ax.axhline(1.0, color="k", lw=0.8, ls="--")
        ax.set_ylabel(title, fontsize=8)
        ax.legend(fontsize=7, loc="upper right", ncol=3)
    ax = axes[3]
    ax.plot(t, 100 * r.unsupported_fraction, color="tab:red", lw=1.1, label="unsupported force")
    ax.plot(t, 100 * r.foot_force_w[:, 0, 2] / r.weight_n, lw=0.9, label="left foot Fz")
    ax.plot(t, 100 * r.foot_force_w[:, 1, 2] / r.weight_n, lw=0.9, label="right foot Fz")
    if r.other_support.any():
        ax.plot(t, 100 * r.other_force_w[:, 2] / r.weight_n, lw=0.9, label="other links Fz")
    ax.axhline(100 * r.cfg.unsupported_fraction, color="k", lw=0.8, ls="--")
    ax.set_ylabel("% of weight", fontsize=8)
    ax.legend(fontsize=7, loc="upper right", ncol=3)
    ax = axes[4]
    for k in range(len(FOOT_NAMES)):
        on = r.stance[:, k]
        speed = np.nan_to_num(r.slide_speed_mps[:, k], nan=0.0)
        sc = ax.scatter(t[on], np.full(on.sum(), k), c=100 * speed[on], cmap="plasma", vmin=0,
                        vmax=400 * r.cfg.slide_speed_mps, s=14, marker="s")
    ax.scatter(t[r.other_support], np.full(r.other_support.sum(), 2), color="tab:gray", s=14, marker="s")
    ax.set_yticks([0, 1, 2], [f"{n} foot" for n in FOOT_NAMES] + ["other link"], fontsize=8)
    ax.set_ylim(-0.7, 2.7)
    fig.colorbar(sc, ax=list(axes), pad=0.005, fraction=0.015, extend="max").set_label(
        "foot sliding (cm/s), stance panel", fontsize=7)
    ax.set_ylabel("stance", fontsize=8)
    axes[5].plot(t, r.root_height_m, color="tab:gray", label="pelvis height (m)")
    axes[5].plot(t, 10 * r.root_jump_m, color="tab:red", lw=0.9, label="pelvis jump (dm)")
    axes[5].axhline(10 * r.cfg.jump_m, color="k", lw=0.8, ls="--")
    axes[5].plot(t, 10 * r.limb_jump_m.max(axis=1), color="tab:purple", lw=0.9, label="largest limb jump (dm)")
    axes[5].axhline(10 * r.cfg.limb_jump_m, color="tab:purple", lw=0.8, ls=":")
    if r.penetration_m.any():
        axes[5].plot(t, 10 * r.penetration_m, color="tab:brown", lw=0.9, label="collision geometry in the ground (dm)")
        axes[5].axhline(10 * r.cfg.penetration_m, color="tab:brown", lw=0.8, ls=":")
    axes[5].set_ylabel("m / dm", fontsize=8)
    axes[5].legend(fontsize=7, loc="upper right", ncol=2)
    axes[5].set_xlabel("time (s)")
    for ax in axes:
        for a, b in r.flight_phases():
            ax.axvspan(t[a] - 0.5 / r.fps, t[b] + 0.5 / r.fps, color="tab:blue", alpha=0.12, lw=0)
        for a, b in r.intervals:
            ax.axvspan(t[a] - 0.5 / r.fps, t[b] + 0.5 / r.fps, color="tab:red", alpha=0.08, lw=0)
        ax.grid(alpha=0.3)
    fig.suptitle(f"dynamic feasibility: {Path(r.source).name} (blue: flight, red: flagged)", fontsize=10)
    return save_figure(fig, out_png, dpi=80)


def write_feasibility(reference, png: str | Path | None = None, json_path: str | Path | None = None,
                      cfg: FeasibilityCfg | None = None, ground: Ground | None = None) -> FeasibilityReport:
    """``otr verify``'s section: print the report, write the timeline and the summary; the verdict
    (``FeasibilityReport.verdict``) is the last line printed."""
    from otr_gym.io import write_json

    report = check_feasibility(reference, cfg, ground)
    print(format_report(report))
    if png:
        print(f"wrote {plot_feasibility(report, png)}")
    if json_path:
        print(f"wrote {write_json(json_path, report.summary())}")
    print(report.verdict())
    return report
