"""Planted feet: while the person stands on a foot, the robot's sole stays on the floor, still.

The interaction residuals alone let a stance foot slide (its ground witnesses follow the
person's foot, which slides in the capture, and trade against every other term) and hover
(the person's sole hovers or sinks by a centimetre in most captures). Planting is therefore
a term of its own, stiff enough to act as a constraint while the QP stays well posed:

* **stance** comes from the demonstration, with the evaluation protocol's definition: frame t
  is a stance frame of a foot when the person's foot unit (ankle and foot parts) comes within
  ``contact_m`` of the floor (paper Sec. IV-A, ε_eval), unless it sweeps past the body
  (faster than the pelvis, ``sweep_ratio``): a foot skimming the floor in its swing is held
  on the floor but free to move horizontally;
* **sole points**: the hull vertices of the G1 foot link that lie on its flat sole (within
  ``sole_band_m`` of the lowest one, link frame);
* **pivots**: a person turns on a standing foot (on the ball or the heel). Per stance frame
  the demonstrated foot's yaw change Δψ and the vertical axis it turned about (the rotation
  centre of its ankle's planar motion) are measured; the centre, placed relative to the
  person's sole (fractions of its length and width along the foot's heading), is mapped to
  the same place on the G1 sole. Below ``pivot_min_rad`` per frame the foot holds still;
* **roll-off**: at push-off a person rolls onto the ball of a standing foot (heel up, toes
  down). While the person's ankle-to-toe line pitches more than ``roll_tilt_rad`` toes-down
  from that foot's flat stance pitch, only the G1 sole's front edge (within ``roll_edge_m``
  of its tip) is held: the G1 has no toe joint, so any held point behind the edge would
  keep the whole sole flat (measured on the AMASS jog: holding the front 40 % of the sole left
  the foot at 6° where the person's was at 53°). This holds whether the foot stands or sweeps:
  a rolled foot flattened onto the floor for one sweeping frame jumped 37 cm on the box carry;
* **targets**, per stance frame: the sole points that touched the floor (within ``touch_m``
  of it) at the previous frame's solution keep their horizontal position, turned by Δψ about
  the mapped pivot, and stay on the floor. The position kept is the one the point was held
  at (its anchor), not where the previous solution left it: a planted foot slips a fraction
  of a millimetre per frame against the other terms, and chained from solution to solution
  those slips added up to 1-3 cm/s of skate; on the first stance frame
  (touch-down), or when none touched, every sole point goes to the floor (a flat landing) and
  may move horizontally. The pivot point itself does not move, so the foot never slides. "On the floor"
  means at the link's surface margin above z = 0, so that Unitree's original sole, not only
  the shipped mesh, touches it (``otr_gym.true_surface``);
* **rows**: one per held coordinate, r = x_i(q) − target_i, weighted ``weight / k`` over the
  k points of a foot (eq. m-energy's f_ℓ/N_ℓ normalisation): a 1 mm slip costs as much as
  the whole interaction term of a link at 3 cm of error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from otr_gym.flags import close_short_gaps
from retarget.geometry.kinematics import LinkFrames
from retarget.solver.residuals import FIXED, Rows, _twist_half


@dataclass(frozen=True)
class StanceConfig:
    """Planted-foot settings (ours; the paper has no separate stance term)."""

    #: A foot is in stance while the person's foot unit is this close to the floor (ε_eval) ...
    contact_m: float = 0.02
    #: ... and its least-moving surface point is no faster (horizontally) than the person's
    #: pelvis (``sweep_ratio`` × its speed), or than ``sweep_floor_m_s``. A foot that skims
    #: the floor while it overtakes the body is swinging, not standing: in a walk the standing
    #: foot rests while the pelvis passes over it and the swing foot moves at about twice the
    #: pelvis's speed. Measured (2026-11-25): Bandai's walk keeps its left foot within 2 cm of
    #: the floor in 308 of 324 frames, 30 % of them faster than the pelvis (up to 3 m/s);
    #: planted there, the G1 fell 1.3 m behind the person. ganimator's person slides its
    #: standing feet at 0.4-0.5 m/s (a third of its pelvis speed): those stay planted. The
    #: 1 m/s floor keeps the AMASS jog's slow-pelvis steps planted (0.3 m/s: ground J 98 → 92 %).
    sweep_ratio: float = 1.0
    sweep_floor_m_s: float = 1.0
    #: A break in a foot's stance shorter than this (s) is a flicker of the two tests above, not
    #: a step (no foot lifts and lands in 60 ms), and is closed. Left open, it releases the
    #: planted foot for a frame or two and plants it again wherever it went: on the AMASS jog the
    #: left foot's lowest point rose to 2.8 and 2.2 cm (frames 31-32 at 50 fps) and came back
    #: before its push-off; the G1 foot jumped 5 cm out and was re-planted 4 cm from where it
    #: stood; closed (0.07), its ankle stays on its path (<= 1.2 cm off) and its lift-off jump
    #: falls 7.7 -> 4.9 cm. 0 keeps every break (the default; not yet trained on).
    min_lift_s: float = 0.0
    #: ... and only a break through which the foot's least-moving point stays slower than this
    #: (m/s): a still foot whose lowest point flickers over ``contact_m``, not one that shuffles
    #: (the AMASS squat's breaks include feet moving at 0.5-1.35 m/s; closing those too made its
    #: hands jump more, 41 -> 60 frames over 3 cm, where the still ones alone give 42).
    flicker_speed_m_s: float = 0.2
    #: A sweeping foot's sole is held this high above the floor, free horizontally
    #: (``stance_targets``). 0 holds it on the floor, where the G1 would drag it: the AMASS jog's
    #: swing feet skim at 2.6-3.1 m/s, `retarget.checks.verify`'s hardest frames. Below ``contact_m``
    #: the evaluation still counts the person's near-contact as kept.
    sweep_clearance_m: float = 0.0
    #: Weight of the planting rows per foot (per m², shared by its sole points).
    weight: float = 1.0e6
    #: Sole points: hull vertices of the foot link within this height of its lowest one (m).
    sole_band_m: float = 0.004
    #: A sole point "touched" the floor at the previous frame within this height (m).
    touch_m: float = 0.002
    #: A standing foot turning by less than this per frame holds still (rad; 0.005 = 14°/s at 50 fps).
    pivot_min_rad: float = 0.005
    #: The planting weight grows over the first frames of a stance (1/3, 2/3, 1): a foot that
    #: lands is brought to the floor over a few frames, not snapped to it in one.
    ramp_frames: int = 3
    #: A held sole point keeps its anchor (where it was first held) while the solution stays
    #: within this distance of it; a foot dragged farther (the leg at its reach, the person's
    #: own foot sliding away) is held where it went instead of fighting the whole body (m).
    anchor_slip_m: float = 0.002
    #: A standing or sweeping foot rolls (only its front edge is held, see the module doc)
    #: while the person's ankle-to-toe line pitches toes-down by more than this from the foot's
    #: median stance pitch (rad; 0.17 ≈ 10°; ``inf`` holds the whole sole flat through a roll).
    #: Measured 2026-11-27 (``retarget.checks.verify``'s limb jumps over 3 cm, frames; the jog's jump
    #: into its first leap; ``benchmarks/grasp_playback.py`` on the box carry; the fidelity
    #: targets on the five clips): flat 42 frames, 9.9 cm, box carried at 10.5 cm;
    #: 0.05: 26, 5.3 cm, but the box's orientation drifts 20-35° and it is lost at frame 299;
    #: 0.1: 28, 5.7 cm, box 8.8 cm, but 5.8 mm into the chair; 0.17: 29, 7.7 cm, box 9.6 cm,
    #: every fidelity target met. Small tilts toggle the hold on the OMOMO captures' feet.
    roll_tilt_rad: float = 0.17
    #: Sole points within this distance of the sole's front tip (link frame x, m) form its
    #: front edge.
    roll_edge_m: float = 0.005


@dataclass(frozen=True)
class StanceTargets:
    """Planting targets of one frame: per held point, its link, its position in the link frame
    and the world coordinates it must keep (NaN where a coordinate is free)."""

    link: np.ndarray  # (k,) link index
    points: np.ndarray  # (k, 3) link frame (m)
    target_w: np.ndarray  # (k, 3) world (m); NaN = free
    gain: np.ndarray  # (k,) share of the full planting weight (the touch-down ramp)
    #: per foot, the world xy (m) each of its sole points is held at (NaN: not held); the next
    #: frame's targets start from these
    anchors: tuple[np.ndarray, ...] = ()

    @staticmethod
    def empty() -> StanceTargets:
        return StanceTargets(np.zeros(0, np.intp), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))


def demonstrated_stance(foot_lowest_z: np.ndarray, foot_speed: np.ndarray, pelvis_speed: np.ndarray,
                        cfg: StanceConfig, fps: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
    """(stance, sweep) flags (T, F) from the person's foot units' lowest surface heights (T, F)
    (m), the horizontal speeds of their least-moving surface points (T, F) and of the pelvis
    (T,) (m/s) at ``fps``: a foot near the floor stands, unless it sweeps past the body
    (``StanceConfig.sweep_ratio``); breaks in a stance shorter than ``min_lift_s`` are closed."""
    near = np.maximum(foot_lowest_z, 0.0) < cfg.contact_m
    fast = foot_speed > np.maximum(cfg.sweep_ratio * pelvis_speed, cfg.sweep_floor_m_s)[:, None]
    stance = close_short_gaps(near & ~fast, int(np.ceil(cfg.min_lift_s * fps - 1e-9)) - 1,
                              foot_speed <= cfg.flicker_speed_m_s)
    return stance, near & fast & ~stance


def sole_points(hull_points: np.ndarray, band_m: float) -> np.ndarray:
    """The hull points (link frame) of a foot link that lie on its flat sole."""
    z = hull_points[:, 2]
    return hull_points[z < z.min() + band_m]


@dataclass(frozen=True)
class FootTurns:
    """Demonstrated stance turns: per frame t and foot, the yaw change Δψ from t − 1 (rad, 0
    when the foot holds still or is not in stance at t − 1 and t) and the pivot on the G1 sole
    (foot link frame, xy, m); and whether the foot rolls onto its toes (``demonstrated_roll``;
    None: never)."""

    yaw: np.ndarray  # (T, F)
    pivot: np.ndarray  # (T, F, 2)
    rolling: np.ndarray | None = None  # (T, F) bool


def demonstrated_turns(ankle_pos_w: np.ndarray, ankle_rot_w: np.ndarray, toe_pos_w: np.ndarray,
                       foot_vertices_w: list[np.ndarray], stance: np.ndarray, sole_boxes: np.ndarray,
                       min_rad: float) -> FootTurns:
    """Stance turns of the person's feet mapped onto the G1 soles (see the module doc).

    ``ankle_pos_w`` (T, F, 3), ``ankle_rot_w`` (T, F, 3, 3): the person's ankle parts (world);
    ``toe_pos_w`` (T, F, 3) the toe joints (the heading is ankle → toe); ``foot_vertices_w`` per
    foot its surface (T, V, 3); ``stance`` (T, F); ``sole_boxes`` (F, 2, 2): per G1 foot the
    [min, max] of its sole's x (forward) and y (left) in the link frame.
    """
    T, F = stance.shape
    yaw = np.zeros((T, F))
    pivot = np.zeros((T, F, 2))
    for f in range(F):
        d_rot = ankle_rot_w[1:, f] @ np.swapaxes(ankle_rot_w[:-1, f], -1, -2)
        d_yaw = np.arctan2(d_rot[:, 1, 0], d_rot[:, 0, 0])
        for t in np.flatnonzero(stance[1:, f] & stance[:-1, f] & (np.abs(d_yaw) >= min_rad)) + 1:
            c, s = np.cos(d_yaw[t - 1]), np.sin(d_yaw[t - 1])
            rz = np.array([[c, -s], [s, c]])
            p0, p1 = ankle_pos_w[t - 1, f, :2], ankle_pos_w[t, f, :2]
            centre = np.linalg.solve(np.eye(2) - rz, p1 - rz @ p0)  # p1 = c + Rz (p0 − c)
            heading = toe_pos_w[t, f, :2] - p1
            heading /= max(np.linalg.norm(heading), 1e-9)
            frame = np.stack([heading, [-heading[1], heading[0]]])  # rows: forward, left
            sole = (foot_vertices_w[f][t, :, :2] - p1) @ frame.T
            lo, hi = sole.min(axis=0), sole.max(axis=0)
            frac = np.clip(((centre - p1) @ frame.T - lo) / np.maximum(hi - lo, 1e-9), 0.0, 1.0)
            yaw[t, f] = d_yaw[t - 1]
            pivot[t, f] = sole_boxes[f, 0] + frac * (sole_boxes[f, 1] - sole_boxes[f, 0])
    return FootTurns(yaw, pivot)


def demonstrated_roll(ankle_pos_w: np.ndarray, toe_pos_w: np.ndarray, stance: np.ndarray,
                      tilt_rad: float) -> np.ndarray:
    """(T, F) bool: the frames where the person's foot rolls onto its toes, i.e. its ankle-to-toe
    line (``ankle_pos_w``, ``toe_pos_w``: (T, F, 3), world) pitches toes-down by more than
    ``tilt_rad`` from its median pitch over the foot's stance frames (the person's flat foot;
    the toe joint need not be level with the ankle)."""
    v = toe_pos_w - ankle_pos_w
    pitch = np.arctan2(-v[..., 2], np.linalg.norm(v[..., :2], axis=-1))  # + = toes below the ankle
    out = np.zeros(stance.shape, dtype=bool)
    for f in range(stance.shape[1]):
        if stance[:, f].any():
            out[:, f] = pitch[:, f] - np.median(pitch[stance[:, f], f]) > tilt_rad
    return out


def stance_targets(stance: np.ndarray, t: int, feet: np.ndarray, soles: tuple[np.ndarray, ...],
                   floor: np.ndarray, previous: LinkFrames | None, cfg: StanceConfig,
                   turns: FootTurns | None = None, sweep: np.ndarray | None = None,
                   before: StanceTargets | None = None) -> StanceTargets:
    """Targets of frame t. ``stance`` (T, F); ``feet`` (F,) link indices; ``soles`` per foot its
    sole points (link frame); ``floor`` (F,) m the height a sole point must sit at; ``previous``
    the link frames of frame t − 1's solution (None on the first frame); ``cfg`` the settings
    used here: ``touch_m``, ``ramp_frames`` (the frames over which the weight grows to its full
    value once a foot comes near the floor), ``anchor_slip_m``, ``sweep_clearance_m`` and
    ``roll_edge_m``;
    ``turns`` the demonstrated stance turns and roll-offs (None: every standing foot holds
    still and flat; a rolling foot holds only its sole's front edge, ``roll_edge_m``); ``sweep``
    (T, F) the frames where a foot skims the floor while it swings: its sole stays
    ``sweep_clearance_m`` above the floor, free to move horizontally (like a touch-down);
    ``before`` frame t − 1's targets (their anchors: a point held then keeps that xy, not the
    previous solution's, unless the solution slipped farther than ``anchor_slip_m`` from it:
    then it is held where it went)."""
    touch_m, ramp_frames, slip_m = cfg.touch_m, cfg.ramp_frames, cfg.anchor_slip_m
    links, points, targets, gains = [], [], [], []
    anchors = [np.full((len(sole), 2), np.nan) for sole in soles]
    window = slice(max(t - max(ramp_frames, 1) + 1, 0), t + 1)  # the frames the ramp looks back on
    near = stance[window] if sweep is None else stance[window] | sweep[window]
    for f, link in enumerate(feet):
        if not near[-1, f]:
            continue
        since = 1  # frames on or near the floor so far, t included
        while since < len(near) and near[-1 - since, f]:
            since += 1
        pts = soles[f]
        use = np.ones(len(pts), dtype=bool)  # the sole points held at t
        if turns is not None and turns.rolling is not None and turns.rolling[t, f]:  # standing or sweeping
            use = pts[:, 0] >= pts[:, 0].max() - cfg.roll_edge_m
        target = np.full((len(pts), 3), np.nan)
        target[:, 2] = floor[f] if stance[t, f] else floor[f] + cfg.sweep_clearance_m
        if stance[t, f] and previous is not None and t > 0 and stance[t - 1, f]:
            prev_w = pts @ previous.rot[link].T + previous.pos[link]
            touched = use & (prev_w[:, 2] < floor[f] + touch_m)
            if touched.any():
                use = touched
                held = prev_w[:, :2].copy()
                if before is not None and before.anchors:
                    slip = np.linalg.norm(held - before.anchors[f], axis=1)  # NaN where not held
                    kept = slip < slip_m
                    held[kept] = before.anchors[f][kept]
                held = held[touched]
                if turns is not None and turns.yaw[t, f] != 0.0:
                    c, s = np.cos(turns.yaw[t, f]), np.sin(turns.yaw[t, f])
                    pivot = np.r_[turns.pivot[t, f], soles[f][:, 2].min()]
                    centre = (previous.rot[link] @ pivot + previous.pos[link])[:2]
                    held = centre + (held - centre) @ np.array([[c, s], [-s, c]])
                target[touched, :2] = held
                anchors[f][touched] = held
        pts, target = pts[use], target[use]
        links.append(np.full(len(pts), link, np.intp))
        points.append(pts)
        targets.append(target)
        gains.append(np.full(len(pts), min(1.0, since / max(ramp_frames, 1))))
    if not links:
        return StanceTargets.empty()
    return StanceTargets(np.concatenate(links), np.concatenate(points), np.concatenate(targets),
                         np.concatenate(gains), tuple(anchors))


def stance_rows(targets: StanceTargets, frames: LinkFrames, weight: float) -> Rows:
    """Rows r = x(q) − target for every held coordinate (see the module doc for the weights)."""
    if len(targets.link) == 0:
        return Rows.empty()
    n = int(np.count_nonzero(np.isfinite(targets.target_w)))
    value, weights, phi, link = np.empty(n), np.empty(n), np.empty((n, 12)), np.empty(n, np.intp)
    _stance_rows_into(targets.link, targets.points, targets.target_w, targets.gain, frames.rot, frames.pos,
                      float(weight), value, weights, phi, link)
    return Rows(value, weights, phi, link, np.full(n, FIXED, np.intp))


@numba.njit(cache=True)
def _stance_rows_into(link, points, target_w, gain, rot, pos, weight, out_value, out_weight, out_phi, out_link):
    """The rows of ``stance_rows``, one per held coordinate (point, then axis): the point posed
    as numpy's einsum sums R p ((x + z) + y, then the origin), x − target, weight × gain over the
    link's count of held coordinates, and φ = (e_axis, (x − o) × e_axis, 0)."""
    per_link = np.zeros(rot.shape[0], np.int64)
    for k in range(link.shape[0]):
        for a in range(3):
            if np.isfinite(target_w[k, a]):
                per_link[link[k]] += 1
    m = np.int64(0)  # not a literal 0: _twist_half would compile twice
    for k in range(link.shape[0]):
        b = link[k]
        x = np.empty(3)
        for i in range(3):
            x[i] = (((rot[b, i, 0] * points[k, 0] + rot[b, i, 2] * points[k, 2]) + rot[b, i, 1] * points[k, 1])
                    + pos[b, i])
        for a in range(3):
            if not np.isfinite(target_w[k, a]):
                continue
            out_value[m] = x[a] - target_w[k, a]
            out_weight[m] = weight * gain[k] / per_link[b]
            out_link[m] = b
            _twist_half(1.0 if a == 0 else 0.0, 1.0 if a == 1 else 0.0, 1.0 if a == 2 else 0.0, x[0] - pos[b, 0],
                        x[1] - pos[b, 1], x[2] - pos[b, 2], out_phi, m, np.int64(0))
            for c in range(6, 12):
                out_phi[m, c] = 0.0
            m += 1
