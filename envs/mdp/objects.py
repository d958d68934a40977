"""Reference object motion and contact schedule, row-aligned with ``MotionLibrary``.

Per library row (frame ``t`` of clip ``c`` at row ``clip_start[c] + t``), for the M moving
objects, the H hands and the S supports (the ground when ``support_ground``, then the static
objects):

- object pose, velocity and linear acceleration (world; wxyz; finite differences of the
  resampled poses);
- ``hand_target_o`` (H, M, 3): the reference hand point p_eef (hand body origin + the hand
  offset in the hand frame) in the object's frame: placed on the *simulated* object it is the
  HDMI contact target, so the target moves with the box the robot actually holds;
- ``hand_gate`` (H, M) and ``support_gate`` (M, S) in [0, 1]: the proximity windows.

Windows (docs/environment.md §4: "gated by robot–box and box–table proximity windows taken from our
reference's contact annotations"): a frame is inside when the surface distance is below a
threshold: ``proximity_threshold_m`` (default 5 cm) for a hand and an object,
``support_threshold_m`` (2 cm) for an object and a support. Hand distances are the reference's
``contact_distance`` annotation of the hand body against the object's channel when the file
has it (ours do); otherwise (Holosoma's files) they are measured on the reference at load time
with MuJoCo's ``mj_geomDistance`` between the hand's collision geoms (those of the subtree of
its ``objects.hand_contact_roots`` body) and the object's collision shapes posed as in the
reference. Object–support distances always come from the
geometry (annotations are robot–channel only). Gaps shorter than ``window_min_gap_s`` are
closed; inside a window the gate ramps linearly from 1/k to 1 over its first k =
``window_ramp_s``·fps frames and is cut to 0 at its end (FK: "ramp the gate on and cut it off
at once").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields, replace

import mujoco
import numpy as np
import torch
from scipy.ndimage import uniform_filter1d

from envs.collision import BoxShape
from envs.config import ObjectsCfg
from envs.objects import GROUND_GEOM, SceneObjects
from otr_gym.flags import close_short_gaps
from otr_gym.reference import Reference
from otr_gym.rotations import quat_apply, quat_apply_inverse, quat_mul

#: Window of the moving average on the reference object acceleration (s).
_ACC_SMOOTHING_S = 0.2
#: Upper bound handed to mj_geomDistance (m): anything farther is "far", which is all a window needs.
_FAR_M = 0.5


@dataclass(frozen=True)
class ObjectLibrary:
    names: tuple[str, ...]  # moving objects (M)
    support_names: tuple[str, ...]  # supports (S): "ground" and/or static objects
    hand_bodies: tuple[str, ...]  # hands (H)
    window_source: tuple[str, ...]  # per clip: "annotations" or "geometry" (robot–object windows)
    pos_w: torch.Tensor  # (F, M, 3)
    quat_w: torch.Tensor  # (F, M, 4) wxyz
    lin_vel_w: torch.Tensor  # (F, M, 3)
    ang_vel_w: torch.Tensor  # (F, M, 3) world
    lin_acc_w: torch.Tensor  # (F, M, 3) m/s², finite differences of lin_vel_w, 0.2 s moving average
    hand_target_o: torch.Tensor  # (F, H, M, 3) reference hand point, object frame
    hand_gate: torch.Tensor  # (F, H, M) in [0, 1]
    support_gate: torch.Tensor  # (F, M, S) in [0, 1]
    static_pos_w: torch.Tensor  # (K, 3) static objects (fixed bodies)
    static_quat_w: torch.Tensor  # (K, 4)

    def to(self, device: str | torch.device) -> ObjectLibrary:
        return replace(self, **{f.name: getattr(self, f.name).to(device) for f in fields(self)
                                if isinstance(getattr(self, f.name), torch.Tensor)})

    @classmethod
    def from_references(cls, refs: Sequence[Reference], objects: SceneObjects, model: mujoco.MjModel,
                        cfg: ObjectsCfg, device: str | torch.device = "cpu") -> ObjectLibrary:
        """``refs`` as prepared for the ``MotionLibrary`` (resampled, same order); ``model``
        the simulation model holding ``objects`` (for the geometric windows)."""
        moving = [i for i, o in enumerate(objects.objects) if not o.static]
        static = [i for i, o in enumerate(objects.objects) if o.static]
        supports = (["ground"] if cfg.support_ground else []) + [objects.objects[i].name for i in static]
        geometry = _Geometry(model, objects, cfg)
        per_clip = [_clip_arrays(ref, moving, static, geometry, cfg) for ref in refs]

        def cat(key: str) -> torch.Tensor:
            return torch.as_tensor(np.concatenate([c[key] for c in per_clip]), dtype=torch.float32, device=device)

        def const(values, width: int) -> torch.Tensor:
            return torch.as_tensor(np.asarray(values, np.float64).reshape(len(static), width), dtype=torch.float32,
                                   device=device)

        return cls(
            names=tuple(objects.objects[i].name for i in moving), support_names=tuple(supports),
            hand_bodies=tuple(cfg.hand_bodies), window_source=tuple(c["source"] for c in per_clip),
            pos_w=cat("pos"), quat_w=cat("quat"), lin_vel_w=cat("lin"), ang_vel_w=cat("ang"),
            lin_acc_w=cat("acc"), hand_target_o=cat("target"), hand_gate=cat("hand_gate"),
            support_gate=cat("support_gate"),
            static_pos_w=const([objects.objects[i].pos_w for i in static], 3),
            static_quat_w=const([objects.objects[i].quat_w for i in static], 4),
        )


def fit_boxes_to_grasps(refs: Sequence[Reference], objects: SceneObjects, model: mujoco.MjModel,
                        cfg: ObjectsCfg) -> SceneObjects:
    """Narrow box-shaped moving objects so that the reference's grasps do not start inside them.

    A reference is retargeted against the object's *surface* and the robot's *visual* hand;
    the simulation collides the hand's collision boxes (fatter than the hand at the thumb) with
    the fitted box (an enclosing box, wider than a scan's bulging sides). On our OMOMO large-box
    reference both add up to 1.4 cm of penetration per hand (the 0.75 quantile inside the hand
    windows; 3.5 cm with the former single hand capsule), so every reset inside a grasp would
    eject the box. The grasped axis is the box axis the hands squeeze
    along: in frames where two hands are inside the box, the axis of their separation (in the
    box frame); in frames with one hand inside, the axis whose faces are nearest to it. The box
    axis that stands vertical while the object rests on a support (inside a support window,
    from the reference geometry) is never the grasped one: hands under a box's bottom edges
    (OMOMO's lift) would otherwise vote for it, and narrowing it would lift the box's bottom
    face off the floor (3.2 cm on OMOMO ``sub3_largebox_003``: the box then rests that much
    below its reference). The grasped axis's half-extent shrinks (both faces, the centre stays)
    by the ``grasp_fit_quantile`` of those frames' penetration depths, at most by half; a
    reference made with a designed squeeze (``metadata["grasp"]["squeeze_m"]``, the retargeter's
    grasp pass: hands that deep on purpose) counts only the depth beyond it. The
    height stays, so the box still rests on the floor and the table where the reference has
    it. The mass stays. Other shapes are kept; ``objects`` itself is returned when nothing
    changes.
    """
    geometry = _Geometry(model, objects, cfg)
    moving = [i for i, o in enumerate(objects.objects) if not o.static]
    static = [i for i, o in enumerate(objects.objects) if o.static]
    depth: dict[int, list[list[float]]] = {k: [[], [], []] for k in range(len(moving))}
    resting: dict[int, np.ndarray] = {k: np.zeros(3) for k in range(len(moving))}  # votes for the vertical axis
    for ref in refs:
        squeeze = float((ref.metadata.get("grasp") or {}).get("squeeze_m", 0.0))  # retarget.solver.grasp
        hand_d, support_d = geometry.distances(ref, moving, static, hands=True)
        target = _hand_points_in_object(ref, moving, cfg)  # (T, H, M, 3)
        for k, i in enumerate(moving):
            shapes = objects.objects[i].shapes
            if len(shapes) != 1 or not isinstance(shapes[0], BoxShape):
                continue
            box = shapes[0]
            # the box axis that stands vertical in the frames the object rests on a support
            rests = (support_d[:, k] < cfg.support_threshold_m).any(-1)
            if rests.any():
                up = np.abs(_vertical_in_box(quat_mul(ref.objects[i].quat_w[rests], box.quat_wxyz)))
                resting[k] += np.bincount(np.argmax(up, axis=-1), minlength=3)
            local = quat_apply_inverse(np.broadcast_to(box.quat_wxyz, target[:, :, k].shape[:-1] + (4,)),
                                       target[:, :, k] - box.pos)
            axis = np.argmax(np.abs(local) / box.half_extents, axis=-1)  # (T, H): the face the hand is at
            inside = hand_d[:, :, k] < 0.0
            both = inside.sum(-1) >= 2
            if both.any():  # two hands inside: they squeeze along their separation
                h0, h1 = np.argsort(~inside, axis=-1, kind="stable")[:, :2].T
                rows = np.arange(len(local))
                apart = np.argmax(np.abs(local[rows, h0] - local[rows, h1]), axis=-1)
                axis = np.where(both[:, None], apart[:, None], axis)
            for a in range(3):  # the squeeze the reference was made with is meant: only the excess counts
                depth[k][a].extend((-hand_d[:, :, k][inside & (axis == a)] - squeeze).tolist())
    out, changed = list(objects.objects), False
    for k, i in enumerate(moving):
        obj = objects.objects[i]
        counts = np.array([len(d) for d in depth[k]], float)
        if resting[k].any():
            counts[int(np.argmax(resting[k]))] = -1.0  # never the axis the object stands on
        if counts.max() < 5:
            continue
        axis = int(np.argmax(counts))  # the grasped axis: the one most hand frames vote for
        box = obj.shapes[0]
        shrink = np.zeros(3)
        shrink[axis] = min(max(float(np.quantile(depth[k][axis], cfg.grasp_fit_quantile)), 0.0),
                           0.5 * box.half_extents[axis])
        if shrink[axis] > 1e-3:
            fitted = BoxShape(box.half_extents - shrink, box.pos, box.quat_wxyz)
            out[i] = replace(obj, shapes=(fitted,), grasp_shrink_m=shrink)
            changed = True
    return replace(objects, objects=tuple(out)) if changed else objects


def _hand_points_in_object(ref: Reference, moving: list[int], cfg: ObjectsCfg) -> np.ndarray:
    """(T, H, M, 3) reference hand points p_eef in each moving object's frame."""
    pos = np.stack([ref.objects[i].pos_w for i in moving], axis=1)
    quat = np.stack([ref.objects[i].quat_w for i in moving], axis=1)
    hands = ref.body_index(cfg.hand_bodies)  # raises naming the file if a hand body is missing
    hand_pos = ref.body_pos_w[:, hands] + quat_apply(ref.body_quat_w[:, hands],
                                                     np.broadcast_to(cfg.hand_point_offset_m, (len(hands), 3)))
    rel = hand_pos[:, :, None] - pos[:, None]  # (T, H, M, 3)
    return quat_apply_inverse(np.broadcast_to(quat[:, None], rel.shape[:-1] + (4,)), rel)


def proximity_gate(distance_m: np.ndarray, threshold_m: float, fps: float, ramp_s: float,
                   min_gap_s: float) -> np.ndarray:
    """(T,) gate in [0, 1] of a (T,) distance series (see the module docstring)."""
    # interior gaps shorter than round(min_gap_s · fps) frames are closed
    inside = close_short_gaps(np.asarray(distance_m) < threshold_m, int(round(min_gap_s * fps)) - 1)
    ramp = max(int(round(ramp_s * fps)), 1)
    gate = np.zeros(inside.shape)
    k = 0
    for t, on in enumerate(inside):
        k = k + 1 if on else 0
        gate[t] = min(k / ramp, 1.0)
    return gate


class _Geometry:
    """Surface distances between model geoms at reference poses (CPU MuJoCo)."""

    def __init__(self, model: mujoco.MjModel, objects: SceneObjects, cfg: ObjectsCfg):
        self.model, self.data = model, mujoco.MjData(model)
        self.cfg = cfg

        def geoms_of(body: str, subtree: bool = False) -> list[int]:
            b = model.body(body).id
            bodies = {b} | ({c for c in range(model.nbody) if _descends(model, c, b)} if subtree else set())
            return [g for g in range(model.ngeom)
                    if model.geom_bodyid[g] in bodies and model.geom_contype[g] | model.geom_conaffinity[g]]

        self.hand_geoms = []
        for hand, root in zip(cfg.hand_bodies, cfg.hand_roots):  # roots: checked by the model's contact pairs
            if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, hand) < 0:
                raise KeyError(f"objects.hand_bodies: '{hand}' is not a body of the simulation model")
            if not _descends(model, model.body(hand).id, model.body(root).id):
                raise KeyError(f"objects.hand_contact_roots: '{root}' is not '{hand}' or a body above it")
            self.hand_geoms.append(geoms_of(root, subtree=True))
        self.object_geoms = {o.name: geoms_of(o.body) for o in objects.objects}
        self.ground = [model.geom(GROUND_GEOM).id]
        self.robot_nq = model.nq - 7 * len(objects.moving)
        self._fromto = np.zeros(6)  # mj_geomDistance's nearest points, reused by every query

    def distances(self, ref: Reference, moving: list[int], static: list[int], hands: bool,
                  hand_points: np.ndarray | None = None,
                  hand_centres: np.ndarray | None = None) -> tuple[np.ndarray | None, np.ndarray]:
        """((T, H, M) hand–object distances or None, (T, M, S) object–support distances), m.
        With ``hands``, a (T, H, M, 3) ``hand_points`` is filled with the world point of each
        object nearest each hand (NaN where farther than ``_FAR_M``) and a (T, H, 3)
        ``hand_centres`` with the mean world centre of each hand's collision geoms, in the same
        pass."""
        d = self.data
        names = [ref.objects[i].name for i in moving]
        supports = ([self.ground] if self.cfg.support_ground else []) + \
            [self.object_geoms[ref.objects[i].name] for i in static]
        T = ref.num_frames
        hand_d = np.full((T, len(self.hand_geoms), len(moving)), _FAR_M) if hands else None
        support_d = np.full((T, len(moving), len(supports)), _FAR_M)
        qpos = ref.qpos()
        for t in range(T):
            self._pose(ref, qpos[t], moving, t)
            if hands and hand_centres is not None:
                for h, hand in enumerate(self.hand_geoms):
                    hand_centres[t, h] = d.geom_xpos[hand].mean(axis=0)
            for k, name in enumerate(names):
                obj = self.object_geoms[name]
                if hands:
                    for h, hand in enumerate(self.hand_geoms):
                        hand_d[t, h, k], point = self._closest(hand, obj)
                        if hand_points is not None:
                            hand_points[t, h, k] = point
                for s, support in enumerate(supports):
                    support_d[t, k, s] = self._closest(obj, support)[0]
        return hand_d, support_d

    def _pose(self, ref: Reference, qpos: np.ndarray, moving: list[int], t: int) -> None:
        """The robot at ``qpos`` and the moving objects at frame t of ``ref``, as the reference has them."""
        d = self.data
        d.qpos[:self.robot_nq] = qpos
        for k, i in enumerate(moving):
            d.qpos[self.robot_nq + 7 * k:self.robot_nq + 7 * k + 7] = np.r_[
                ref.objects[i].pos_w[t], ref.objects[i].quat_w[t]]
        mujoco.mj_kinematics(self.model, d)

    def overlaps(self, ref: Reference, moving: list[int]) -> dict[int, list[float]]:
        """Robot collision geom -> its signed distances (m, < 0) at the frames where it is inside
        a moving object's collision geoms, robot and objects on their reference poses."""
        objects = [g for i in moving for g in self.object_geoms[ref.objects[i].name]]
        others = set(self.ground) | {g for gs in self.object_geoms.values() for g in gs}
        robot = [g for g in range(self.model.ngeom)
                 if g not in others and self.model.geom_contype[g] | self.model.geom_conaffinity[g]]
        out: dict[int, list[float]] = {}
        qpos = ref.qpos()
        for t in range(ref.num_frames):
            self._pose(ref, qpos[t], moving, t)
            for g in robot:
                depth = min(mujoco.mj_geomDistance(self.model, self.data, g, o, 0.0, self._fromto) for o in objects)
                if depth < 0.0:
                    out.setdefault(g, []).append(depth)
        return out

    def _closest(self, geoms_a: list[int], geoms_b: list[int]) -> tuple[float, np.ndarray]:
        """Surface distance between two geom sets as posed (capped at ``_FAR_M``) and the point
        of ``geoms_b`` nearest ``geoms_a`` (world; NaN when farther than the cap)."""
        best, point, fromto = _FAR_M, None, self._fromto
        for a in geoms_a:
            for b in geoms_b:
                dist = mujoco.mj_geomDistance(self.model, self.data, a, b, _FAR_M, fromto)
                if dist < best:  # fromto: the point on a, then the point on b
                    best, point = dist, fromto[3:].copy()
        return best, (np.full(3, np.nan) if point is None else point)


@dataclass(frozen=True)
class HeldGrasp:
    """Where a reference holds its first moving object, a box, in the frames it is held: some
    hand within ``proximity_threshold_m`` of it, the box farther than ``support_threshold_m`` from
    every support (distances on the reference geometry, as the geometric windows)."""

    frames: int
    #: the box point nearest the hand (its collision geoms) above the box centre along the box's
    #: up axis, in half-heights: -1 the bottom face, 0 the centre, +1 the top face; mean over the
    #: held frames and the hands within reach
    hand_height: float
    #: the same for the mean centre of the hand's collision geoms: it tells a hand on the box's
    #: side (between -1 and +1) from one under its bottom face (below -1), which ``hand_height``
    #: reads alike when the hand wraps the bottom edge (-1 for both)
    hand_centre_height: float
    centre_height_m: float  # box centre, world z, mean over the held frames
    tilt_deg: float  # the box's up axis against the world vertical, mean over the held frames


def held_grasp(ref: Reference, objects: SceneObjects, model: mujoco.MjModel, cfg: ObjectsCfg) -> HeldGrasp | None:
    """How ``ref`` holds its first moving object (``objects`` as built for it, one box shape;
    ``model`` the simulation model holding them). The box's up axis is the one nearest the
    vertical while it rests on a support (its first frame if it never does). A box held below
    its centre hangs over its hands, an inverted pendulum: it tips unless squeezed firmly. None
    when the box is never held or is not one box."""
    moving = [i for i, o in enumerate(objects.objects) if not o.static]
    static = [i for i, o in enumerate(objects.objects) if o.static]
    shapes = objects.objects[moving[0]].shapes if moving else ()
    if len(shapes) != 1 or not isinstance(shapes[0], BoxShape):
        return None
    box = shapes[0]
    geometry = _Geometry(model, objects, cfg)
    points_w = np.full((ref.num_frames, len(geometry.hand_geoms), 1, 3), np.nan)
    centres_w = np.full((ref.num_frames, len(geometry.hand_geoms), 3), np.nan)
    hand_d, support_d = geometry.distances(ref, moving[:1], static, hands=True, hand_points=points_w,
                                           hand_centres=centres_w)
    near = hand_d[:, :, 0] < cfg.proximity_threshold_m  # (T, H)
    resting = (support_d[:, 0] < cfg.support_threshold_m).any(-1)  # (T,)
    held = near.any(-1) & ~resting
    if not held.any():
        return None
    obj = ref.objects[moving[0]]
    box_quat_w = quat_mul(obj.quat_w, box.quat_wxyz)  # (T, 4)
    vertical_b = _vertical_in_box(box_quat_w)  # (T, 3)
    up = int(np.argmax(np.abs(vertical_b[resting if resting.any() else [0]]).sum(0)))
    frames = np.flatnonzero(held)
    centre_w = obj.pos_w[frames] + quat_apply(obj.quat_w[frames], box.pos)  # (N, 3)

    def height(points: np.ndarray) -> float:  # (N, H, 3) world -> mean height over the hands within reach
        points_b = quat_apply_inverse(np.broadcast_to(box_quat_w[frames, None], points.shape[:-1] + (4,)),
                                      points - centre_w[:, None])
        return float(np.nanmean((points_b[..., up] / box.half_extents[up])[near[frames]]))

    tilt = np.degrees(np.arccos(np.clip(np.abs(vertical_b[frames, up]), 0.0, 1.0)))
    return HeldGrasp(len(frames), height(points_w[frames, :, 0]), height(centres_w[frames]),
                     float(centre_w[:, 2].mean()), float(tilt.mean()))


@dataclass(frozen=True)
class GeomOverlap:
    """A robot collision geom inside a moving object's collision shapes on the reference itself
    (robot and object on their reference poses): what the simulation pushes apart at once when a
    policy tracks the reference exactly. Hand geoms (``objects.hand_contact_roots``) are the
    squeeze a grasp asks for; any other link inside the box shoves it."""

    geom: str
    body: str
    hand: bool
    frames: int  # frames where it is inside
    deepest_m: float  # its largest depth (positive)
    median_m: float  # median depth over those frames


def reference_overlaps(ref: Reference, objects: SceneObjects, model: mujoco.MjModel,
                       cfg: ObjectsCfg) -> list[GeomOverlap]:
    """Every robot collision geom of ``model`` that is inside one of the moving objects'
    collision geoms at some frame of ``ref`` (``objects`` as built for it), deepest first."""
    moving = [i for i, o in enumerate(objects.objects) if not o.static]
    if not moving:
        return []
    geometry = _Geometry(model, objects, cfg)
    hands = {g for hand in geometry.hand_geoms for g in hand}
    out = [GeomOverlap(model.geom(g).name, model.body(model.geom_bodyid[g]).name, g in hands, len(d),
                       float(-min(d)), float(-np.median(d)))
           for g, d in geometry.overlaps(ref, moving).items()]
    return sorted(out, key=lambda o: -o.deepest_m)


def _vertical_in_box(box_quat_w: np.ndarray) -> np.ndarray:
    """(T, 3) the world vertical in the box's frame, for box orientations ``box_quat_w`` (T, 4)
    wxyz, world (the object's orientation times the box shape's)."""
    return quat_apply_inverse(box_quat_w, np.broadcast_to([0.0, 0.0, 1.0], (len(box_quat_w), 3)))


def _descends(model: mujoco.MjModel, body: int, root: int) -> bool:
    """Whether ``body`` is ``root`` or below it in the kinematic tree."""
    while body > root:
        body = int(model.body_parentid[body])
    return body == root


def _annotated_hand_distances(ref: Reference, moving: list[int], hands: Sequence[str]) -> np.ndarray | None:
    """(T, H, M) from the reference's contact annotations, or None when any is missing."""
    c = ref.contacts
    if c is None:
        return None
    names = [ref.objects[i].name for i in moving]
    if any(h not in c.body_names for h in hands) or any(n not in c.channel_names for n in names):
        return None
    rows = [c.body_names.index(h) for h in hands]
    cols = [c.channel_names.index(n) for n in names]
    return c.distance[:, rows][:, :, cols]


def _clip_arrays(ref: Reference, moving: list[int], static: list[int], geometry: _Geometry,
                 cfg: ObjectsCfg) -> dict:
    tracks = [ref.objects[i] for i in moving]
    pos = np.stack([o.pos_w for o in tracks], axis=1)
    quat = np.stack([o.quat_w for o in tracks], axis=1)
    target = _hand_points_in_object(ref, moving, cfg)
    annotated = _annotated_hand_distances(ref, moving, cfg.hand_bodies)
    hand_d, support_d = geometry.distances(ref, moving, static, hands=annotated is None)
    if annotated is not None:
        hand_d = annotated

    def gate(dist: np.ndarray, threshold: float) -> np.ndarray:
        flat = dist.reshape(dist.shape[0], -1)
        if flat.shape[1] == 0:
            return np.zeros(dist.shape)
        out = np.stack([proximity_gate(flat[:, j], threshold, ref.fps, cfg.window_ramp_s, cfg.window_min_gap_s)
                        for j in range(flat.shape[1])], axis=1)
        return out.reshape(dist.shape)

    lin = np.stack([o.lin_vel_w for o in tracks], axis=1)
    # a 0.2 s moving average: the raw second differences of mocap poses swing ±13 m/s² frame to
    # frame on our OMOMO box lift, a grip force that follows them would flicker
    acc = np.gradient(lin, 1.0 / ref.fps, axis=0) if len(lin) > 1 else np.zeros_like(lin)
    acc = uniform_filter1d(acc, size=max(int(round(_ACC_SMOOTHING_S * ref.fps)), 1), axis=0, mode="nearest")
    return {
        "pos": pos, "quat": quat, "lin": lin, "acc": acc, "ang": np.stack([o.ang_vel_w for o in tracks], axis=1),
        "target": target, "hand_gate": gate(hand_d, cfg.proximity_threshold_m),
        "support_gate": gate(support_d, cfg.support_threshold_m),
        "source": "annotations" if annotated is not None else "geometry",
    }
