"""The policy's observation rebuilt on the robot from the ONNX metadata alone.

``PolicySpec`` reads what ``otr export --onnx`` wrote (joint order, default pose, kp/kd,
action scale and clip, observation layout and clip, anchor and tracked bodies, fps).
``ObservationBuilder`` turns one LowState into the observation vector with the training code
itself: it fills an ``envs.mdp.state.TrackingState`` for one env and calls the term functions
of ``envs.mdp.observations`` named in the layout, in order, then clips like
``envs.task.TrackingTask.observations`` (deployment has no observation noise).

What the robot measures and how it maps onto the training state:

- joint positions/velocities: the motors (policy order = motor order);
- pelvis orientation (wxyz) and angular velocity (pelvis frame): the IMU;
- body poses (the 14 tracked bodies, the torso anchor among them): forward kinematics of the
  training MJCF (MuJoCo ``mj_kinematics``) from the IMU orientation and the joint angles, with
  the pelvis at the world origin. Orientations and anchor-relative positions are exact; world
  positions and linear velocities are not in the LowState: terms that need them
  (``TERM_SOURCES``: ``anchor_pos_b``, ``base_lin_vel_b`` of mjlab's state-estimation variant,
  the object's pose of the box task's ``mocap`` actor) need a source the runner is given —
  motion capture (``BaseEstimate``/``ObjectEstimate`` from ``agents.deploy.mocap``: the pelvis
  pose and velocity place the bodies in the capture's world) or the state estimator — and
  are refused at start-up, naming the terms and the flag, without one; any other term that
  reads an unmeasured field sees NaN there and is refused the same way.

Reference timing follows training (``envs.mdp.commands``): the robot stands on start frame 0,
the observation shows target frame 1, and every policy step advances the target by one frame.

Yaw alignment at policy start (docs/environment.md §9): the IMU's heading is arbitrary, so when tracking
starts the heading difference Δ = yaw(q_robotAnchor · q_refAnchor[0]⁻¹) is recorded, and the
whole clip is rotated by Δ about the world z axis (``otr_gym.rotations``, the same maths as
``envs.mdp.state.aligned_targets``). In training the robot starts on its reference, so Δ ≈ 0
there and the observation is the same. With motion capture the heading comes from the captured
pelvis, and the clip is also shifted in x, y so that its frame-0 anchor stands where the robot's
does (the floor is z = 0 in both worlds): the objects must be placed relative to the robot as
the reference has them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from agents.deploy.messages import RobotState
from envs.mdp import observations as obs_terms
from envs.mdp.metrics import mpjpe_root_relative
from envs.mdp.motion import MotionLibrary
from envs.mdp.state import ObjectState, TrackingState
from otr_gym import robot
from otr_gym.rotations import quat_apply, quat_apply_inverse, quat_conj, quat_mul, quat_yaw
from otr_gym.scene import robot_model

#: Sources beyond the LowState that an observation term can need: motion capture (``--mocap``,
#: ``agents.deploy.mocap``) gives the robot's world pose and the objects'; the state estimator
#: (``--state-estimator``) the robot's world position and velocity from the IMU and the legs.
MOCAP, ESTIMATOR = "mocap", "estimator"
#: term -> (what it needs, the sources that give it); an empty tuple: no deployment gives it.
TERM_SOURCES: dict[str, tuple[str, tuple[str, ...]]] = {
    "anchor_pos_b": ("the robot's world position", (MOCAP, ESTIMATOR)),
    "base_lin_vel_b": ("the pelvis linear velocity", (MOCAP, ESTIMATOR)),
    "static_object_pos_b": ("the robot's world position", (MOCAP, ESTIMATOR)),
    "static_object_ori_b": ("the robot's world heading", (MOCAP, ESTIMATOR)),
    "object_pos_b": ("the object's pose", (MOCAP,)),
    "object_ori_b": ("the object's pose", (MOCAP,)),
    "object_lin_vel_b": ("the object's velocity", (MOCAP,)),
    "object_ang_vel_b": ("the object's velocity", (MOCAP,)),
    "object_pos_error_b": ("the object's pose", (MOCAP,)),
    "object_contact_forces": ("the hands' and the object's contact forces", ()),
}
SOURCE_FLAGS = {MOCAP: "--mocap TOPIC (a motion-capture stream; `otr sim-robot --publish-mocap TOPIC` in "
                       "simulation)", ESTIMATOR: "--state-estimator"}
#: Box-task terms that read the reference only: a runner computes them from the clip.
REFERENCE_OBJECT_TERMS = ("object_command", "contact_schedule")


class PolicySpecError(ValueError):
    """The ONNX metadata cannot drive the G1 (missing field, wrong joints, unobservable term)."""


@dataclass(frozen=True)
class PolicySpec:
    """What the runner needs from an exported policy besides its weights (SI units, policy order)."""

    source: str
    default_joint_pos: np.ndarray  # (29,) rad
    kp: np.ndarray  # (29,) N·m/rad
    kd: np.ndarray  # (29,) N·m·s/rad
    action_scale: np.ndarray  # (29,) rad per unit action
    action_clip: float
    observation_layout: tuple[tuple[str, int], ...]  # (term function, dim) in order
    observation_clip: float
    anchor_body: str
    body_names: tuple[str, ...]
    fps: float
    policy_dt: float  # s

    @property
    def observation_dim(self) -> int:
        return sum(d for _, d in self.observation_layout)

    def needs(self) -> dict[str, tuple[str, tuple[str, ...]]]:
        """The layout's terms that need a source beyond the LowState (``TERM_SOURCES``)."""
        return {n: TERM_SOURCES[n] for n, _ in self.observation_layout if n in TERM_SOURCES}

    def check_sources(self, sources: frozenset[str]) -> None:
        """Refuse the policy, naming the terms and the flags, if ``sources`` cannot feed it."""
        unmet = {n: v for n, v in self.needs().items() if not set(v[1]) & sources}
        if not unmet:
            return
        flags = [f for f in SOURCE_FLAGS if any(f in srcs for _, srcs in unmet.values())]
        raise PolicySpecError(
            f"{self.source}: observation terms {', '.join(unmet)} need "
            f"{', '.join(dict.fromkeys(w for w, _ in unmet.values()))}, which the G1's low-level state does not "
            f"give: run with {' or '.join(SOURCE_FLAGS[f] for f in flags)}, or deploy a policy trained without "
            "them (the default actors: OTR-G1-Track-v0's 154 terms, OTR-G1-BoxTrack-v0's perception_free)")

    @classmethod
    def from_metadata(cls, meta: dict, source: str = "<metadata>") -> PolicySpec:
        need = ("joint_names", "default_joint_pos", "joint_stiffness", "joint_damping", "action_scale",
                "observation_layout", "observation_clip", "anchor_body_name", "body_names", "fps")
        missing = [k for k in need if k not in meta]
        if missing:
            raise PolicySpecError(f"{source}: metadata lacks {missing} (export it with `otr export --onnx`)")
        if list(meta["joint_names"]) != list(robot.JOINT_NAMES):
            raise PolicySpecError(f"{source}: joint order {meta['joint_names']} is not the G1 motor order "
                                  f"{list(robot.JOINT_NAMES)}")
        arrays = {}
        for key in ("default_joint_pos", "joint_stiffness", "joint_damping", "action_scale"):
            a = np.asarray(meta[key], dtype=np.float64)
            if a.shape != (robot.NUM_JOINTS,) or not np.isfinite(a).all():
                raise PolicySpecError(f"{source}: '{key}' must be {robot.NUM_JOINTS} finite numbers, got {meta[key]}")
            arrays[key] = a
        layout = tuple((str(t["name"]), int(t["dim"])) for t in meta["observation_layout"])
        for name, _ in layout:
            if name in TERM_SOURCES and not TERM_SOURCES[name][1]:
                raise PolicySpecError(f"{source}: observation term '{name}' needs {TERM_SOURCES[name][0]}, "
                                      "which no deployment measures; deploy a policy trained without it (the "
                                      "default actors: OTR-G1-Track-v0's 154 terms, OTR-G1-BoxTrack-v0's "
                                      "perception_free)")
        fps = float(meta["fps"])
        return cls(source=source, default_joint_pos=arrays["default_joint_pos"], kp=arrays["joint_stiffness"],
                   kd=arrays["joint_damping"], action_scale=arrays["action_scale"],
                   action_clip=float(meta.get("action_clip", np.inf)), observation_layout=layout,
                   observation_clip=float(meta["observation_clip"]), anchor_body=str(meta["anchor_body_name"]),
                   body_names=tuple(meta["body_names"]), fps=fps, policy_dt=float(meta.get("policy_dt", 1.0 / fps)))

    @classmethod
    def from_onnx(cls, path: str | Path) -> PolicySpec:
        from agents.export import read_metadata

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: policy file not found")
        return cls.from_metadata(read_metadata(path), str(path))


class RobotKinematics:
    """Forward kinematics of the G1 MJCF: tracked-body poses from IMU orientation + joints."""

    def __init__(self, body_names: tuple[str, ...]):
        import mujoco

        self._mj = mujoco
        self.model = robot_model(visual=False)
        self.data = mujoco.MjData(self.model)
        self.body_ids = np.array([self.model.body(b).id for b in body_names])

    def body_poses(self, quat_wxyz: np.ndarray, joint_pos: np.ndarray,
                   pelvis_pos_w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(K, 3) positions (m; the pelvis at ``pelvis_pos_w``, default the origin) and (K, 4)
        orientations (wxyz), world."""
        qpos = self.data.qpos
        qpos[:3] = 0.0 if pelvis_pos_w is None else pelvis_pos_w
        qpos[3:7] = quat_wxyz / np.linalg.norm(quat_wxyz)
        qpos[7:7 + robot.NUM_JOINTS] = joint_pos
        self._mj.mj_kinematics(self.model, self.data)
        return self.data.xpos[self.body_ids].copy(), self.data.xquat[self.body_ids].copy()


def torso_tilt_rad(anchor_quat_wxyz: np.ndarray) -> float:
    """Angle (rad) between the body's z axis and the world's vertical: the rotation matrix's
    z-z entry, 1 − 2(x² + y²), as ``quat_to_matrix`` computes it (the same float64 arithmetic,
    without building the 3×3 matrix: ~0.1 ms, twice a cycle, in the runner)."""
    _, x, y, _ = (float(v) for v in anchor_quat_wxyz)
    return float(np.arccos(np.clip(1 - 2 * (x * x + y * y), -1.0, 1.0)))


def reference_objects(reference, fps: float, num_frames: int):
    """The box task's ``ObjectLibrary`` of one clip (the reference's object track, its contact
    gates), built by the training code from ``configs/env/box.yaml``."""
    from envs.box import box_scene
    from envs.config import load_box_config
    from envs.mdp.objects import ObjectLibrary

    cfg = load_box_config()
    if abs(cfg.command.fps - fps) > 1e-6:
        raise PolicySpecError(f"{reference}: the policy runs at {fps:g} Hz, the box task's objects at "
                              f"{cfg.command.fps:g} Hz")
    refs, _, scene, _, model = box_scene(reference, cfg)
    library = ObjectLibrary.from_references(refs, scene, model, cfg.objects)
    if library.pos_w.shape[0] != num_frames:
        raise PolicySpecError(f"{reference}: {library.pos_w.shape[0]} object frames for {num_frames} robot frames")
    return library


@dataclass(frozen=True)
class BaseEstimate:
    """The pelvis in the world a source measures (motion capture, the state estimator)."""

    pos_w: np.ndarray  # (3,) m
    lin_vel_w: np.ndarray  # (3,) m/s
    quat_wxyz: np.ndarray | None = None  # (4,) its orientation in that world; None: the IMU's


@dataclass(frozen=True)
class ObjectEstimate:
    """The moving objects (M, in the reference's order) as motion capture measures them."""

    pos_w: np.ndarray  # (M, 3) m
    quat_wxyz: np.ndarray  # (M, 4)
    lin_vel_w: np.ndarray  # (M, 3) m/s
    ang_vel_w: np.ndarray  # (M, 3) rad/s


class AlignedFrames:
    """A reference array (frames, …, 3 or 4) turned by the heading ``delta`` (wxyz) about the
    origin, then shifted by ``offset`` (vectors), or turned (``quat``: orientations, Δ ⊗ q),
    computed ``BLOCK`` frames at a time when a frame is first read: turning a whole 64 s clip at
    once took 12-20 ms, all in the cycle tracking starts on; a block costs ~0.5 ms once a second.
    ``x[frame]``, ``x[frame, body]``: as indexing the whole turned array (the same values, the
    same arithmetic on fewer rows; ``tests/agents/deploy/test_deploy_observation.py``)."""

    BLOCK = 50

    def __init__(self, source: torch.Tensor, delta: torch.Tensor, offset: torch.Tensor | None = None,
                 quat: bool = False):
        self.source, self.delta, self.offset, self.quat = source, delta, offset, quat
        self._blocks: dict[int, torch.Tensor] = {}

    def __len__(self) -> int:
        return len(self.source)

    def block(self, b: int) -> torch.Tensor:
        if (out := self._blocks.get(b)) is None:
            v = self.source[b * self.BLOCK:(b + 1) * self.BLOCK]
            if self.quat:
                out = quat_mul(self.delta.expand_as(v), v)
            else:
                out = quat_apply(self.delta.expand(*v.shape[:-1], 4), v)
                out = out if self.offset is None else out + self.offset
            self._blocks[b] = out
        return out

    def __getitem__(self, index: int | tuple) -> torch.Tensor:
        frame, rest = (index[0], index[1:]) if isinstance(index, tuple) else (index, ())
        frame = int(frame) + (len(self.source) if frame < 0 else 0)
        if not 0 <= frame < len(self.source):
            raise IndexError(f"frame {frame} of {len(self.source)}")
        row = self.block(frame // self.BLOCK)[frame % self.BLOCK]
        return row[rest] if rest else row

    def full(self) -> torch.Tensor:
        """Every frame (all blocks)."""
        return torch.cat([self.block(b) for b in range((len(self.source) + self.BLOCK - 1) // self.BLOCK)])


class ObservationBuilder:
    """Observation vectors for a ``PolicySpec`` tracking one reference clip (see module doc);
    ``sources`` (``MOCAP``, ``ESTIMATOR``) are what the runner feeds beyond the LowState."""

    def __init__(self, spec: PolicySpec, reference, sources: frozenset[str] = frozenset()):
        spec.check_sources(sources)
        needs = spec.needs()
        self.needs_base = bool(needs)  # every such term reads the robot's world pose
        self.needs_objects = any(srcs == (MOCAP,) for _, srcs in needs.values())
        missing = [b for b in (spec.anchor_body, "pelvis") if b not in spec.body_names]
        if missing:
            raise PolicySpecError(f"{spec.source}: tracked bodies {spec.body_names} lack {missing}")
        self.spec = spec
        self.motion = MotionLibrary.load(reference, spec.body_names, fps=spec.fps)
        if self.motion.num_clips != 1:
            raise PolicySpecError(f"{reference}: deployment tracks one clip, got {self.motion.num_clips}")
        self.num_frames = int(self.motion.clip_length[0])
        self.anchor = spec.body_names.index(spec.anchor_body)
        self.kinematics = RobotKinematics(spec.body_names)
        self._terms = [(name, dim, getattr(obs_terms, name, None)) for name, dim in spec.observation_layout]
        unknown = [n for n, _, fn in self._terms if not callable(fn) or n.startswith("_")]
        if unknown:
            raise PolicySpecError(f"{spec.source}: unknown observation terms {unknown} (not in envs.mdp.observations)")
        self._default = torch.as_tensor(spec.default_joint_pos, dtype=torch.float32)[None]
        object_terms = (*REFERENCE_OBJECT_TERMS, *(n for n, _ in needs.items() if n.startswith(("object", "static"))))
        self.objects = (reference_objects(reference, spec.fps, self.num_frames)
                        if any(n in object_terms for n, _ in spec.observation_layout) else None)
        self._unmeasured = self._unmeasured_objects(self.objects) if self.objects is not None else {}
        self.align(np.array([1.0, 0.0, 0.0, 0.0]))
        self._check_terms()

    # ------------------------------------------------------------ reference alignment
    def align(self, delta_wxyz: np.ndarray, offset_w: np.ndarray | None = None) -> None:
        """Rotate the whole clip by the heading ``delta_wxyz`` (world z) about the origin, then
        shift it by ``offset_w`` (m, default none)."""
        m = self.motion
        d = torch.as_tensor(delta_wxyz, dtype=torch.float32)
        offset = torch.zeros(3) if offset_w is None else torch.as_tensor(offset_w, dtype=torch.float32)
        self.heading_delta = np.asarray(delta_wxyz, dtype=np.float64)
        self.offset_w = offset.double().numpy()

        def turned(v: torch.Tensor) -> torch.Tensor:  # vectors (…, 3) rotated by d
            return quat_apply(d.expand(*v.shape[:-1], 4), v)

        # per-frame arrays: turned a block of frames at a time, when first read (``AlignedFrames``)
        self.ref_body_pos_w, self.ref_body_lin_vel_w, self.ref_body_ang_vel_w, self.ref_body_quat_w = (
            AlignedFrames(m.body_pos_w, d, offset), AlignedFrames(m.body_lin_vel_w, d),
            AlignedFrames(m.body_ang_vel_w, d), AlignedFrames(m.body_quat_w, d, quat=True))
        if self.objects is not None:
            o = self.objects
            self.ref_object_pos_w, self.ref_object_lin_vel_w, self.ref_object_ang_vel_w, self.ref_object_quat_w = (
                AlignedFrames(o.pos_w, d, offset), AlignedFrames(o.lin_vel_w, d), AlignedFrames(o.ang_vel_w, d),
                AlignedFrames(o.quat_w, d, quat=True))
            # the table stands where the reference has it, relative to the robot's start
            self.ref_static_pos_w = turned(o.static_pos_w) + offset
            self.ref_static_quat_w = quat_mul(d.expand_as(o.static_quat_w), o.static_quat_w)

    def alignment(self, state: RobotState, base: BaseEstimate | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(Δ wxyz, offset m) that put the clip's frame 0 on the robot standing in ``state``:
        Δ = yaw(q_robotAnchor · q_refAnchor[0]⁻¹); with a measured ``base`` (motion capture) the
        offset also moves the reference anchor's x, y onto the robot's (heights stay: the floor
        is z = 0 in both), otherwise it is zero (the pelvis sits at the origin)."""
        quat = state.quat_wxyz if base is None or base.quat_wxyz is None else base.quat_wxyz
        body_pos, body_quat = self.kinematics.body_poses(quat, state.joint_pos, None if base is None else base.pos_w)
        ref_anchor = self.motion.body_quat_w[0, self.anchor].double().numpy()
        delta = quat_yaw(quat_mul(body_quat[self.anchor], quat_conj(ref_anchor)))
        offset = np.zeros(3)
        if base is not None:
            ref_pos = quat_apply(delta, self.motion.body_pos_w[0, self.anchor].double().numpy())
            offset[:2] = body_pos[self.anchor, :2] - ref_pos[:2]
        return delta, offset

    # ------------------------------------------------------------ per cycle
    def reference_joint_pos(self, frame: int) -> np.ndarray:
        """The reference's joint positions at ``frame`` (rad, G1 order; -1: the last frame)."""
        return self.motion.joint_pos[frame].double().numpy().copy()

    def reference_tilt_rad(self, frame: int) -> float:
        """The reference's torso (anchor) tilt from vertical at ``frame`` (rad)."""
        return torso_tilt_rad(self.ref_body_quat_w[frame, self.anchor].double().numpy())

    def tracking_state(self, state: RobotState, frame: int, action: np.ndarray, base: BaseEstimate | None = None,
                       objects: ObjectEstimate | None = None) -> TrackingState:
        """The one-env ``TrackingState`` of the robot in ``state`` against target ``frame``;
        ``action`` is the (clipped) raw action applied during the last policy step; ``base`` and
        ``objects``: what motion capture or the state estimator measure (else NaN there)."""
        quat = state.quat_wxyz if base is None or base.quat_wxyz is None else base.quat_wxyz
        body_pos, body_quat = self.kinematics.body_poses(quat, state.joint_pos, None if base is None else base.pos_w)
        root_lin_vel_b = (torch.full((1, 3), float("nan")) if base is None else
                          torch.as_tensor(quat_apply_inverse(quat, base.lin_vel_w), dtype=torch.float32)[None])

        def t(x) -> torch.Tensor:
            return torch.as_tensor(np.asarray(x), dtype=torch.float32)[None]

        K = len(self.spec.body_names)
        unknown = torch.full((1, K, 3), float("nan"))
        m = self.motion
        return TrackingState(
            body_names=self.spec.body_names, anchor=self.anchor,
            end_effectors=torch.as_tensor([i for i, b in enumerate(self.spec.body_names) if b in robot.END_EFFECTORS]),
            contact_body_names=(),
            joint_pos=t(state.joint_pos), joint_vel=t(state.joint_vel), root_quat_w=t(quat),
            root_lin_vel_b=root_lin_vel_b, root_ang_vel_b=t(state.gyro_b),
            body_pos_w=t(body_pos), body_quat_w=t(body_quat), body_lin_vel_w=unknown, body_ang_vel_w=unknown,
            contact_force_n=torch.zeros(1, 0),
            ref_joint_pos=m.joint_pos[frame][None], ref_joint_vel=m.joint_vel[frame][None],
            ref_body_pos_w=self.ref_body_pos_w[frame][None], ref_body_quat_w=self.ref_body_quat_w[frame][None],
            ref_body_lin_vel_w=self.ref_body_lin_vel_w[frame][None],
            ref_body_ang_vel_w=self.ref_body_ang_vel_w[frame][None],
            ref_body_pos_aligned_w=unknown, ref_body_quat_aligned_w=torch.full((1, K, 4), float("nan")),
            action=t(action), last_action=torch.full((1, robot.NUM_JOINTS), float("nan")),
            default_joint_pos=self._default, objects=self._object_state(frame, base is not None, objects),
        )

    def _object_state(self, frame: int, located: bool, measured: ObjectEstimate | None) -> ObjectState | None:
        """The box task's object state at ``frame``: the reference's part (aligned, gates); the
        objects' poses and velocities ``measured`` (else NaN); the table where the aligned
        reference has it once the robot is ``located`` in that world (else NaN); forces NaN."""
        o = self.objects
        if o is None:
            return None
        fields = dict(self._unmeasured)
        if measured is not None:
            fields.update({k: torch.as_tensor(v, dtype=torch.float32)[None] for k, v in (
                ("pos_w", measured.pos_w), ("quat_w", measured.quat_wxyz), ("lin_vel_w", measured.lin_vel_w),
                ("ang_vel_w", measured.ang_vel_w))})
        if located:
            fields.update(static_pos_w=self.ref_static_pos_w, static_quat_w=self.ref_static_quat_w)
        return ObjectState(
            names=o.names, support_names=o.support_names, **fields,
            ref_pos_w=self.ref_object_pos_w[frame][None], ref_quat_w=self.ref_object_quat_w[frame][None],
            ref_lin_vel_w=self.ref_object_lin_vel_w[frame][None], ref_ang_vel_w=self.ref_object_ang_vel_w[frame][None],
            hand_gate=o.hand_gate[frame][None], support_gate=o.support_gate[frame][None])

    @staticmethod
    def _unmeasured_objects(o) -> dict[str, torch.Tensor]:
        """The ``ObjectState`` fields a robot does not measure, as NaN (allocated once)."""
        M, H, S = o.pos_w.shape[1], len(o.hand_bodies), len(o.support_names)
        shapes = {"pos_w": (M, 3), "quat_w": (M, 4), "lin_vel_w": (M, 3), "ang_vel_w": (M, 3), "hand_pos_w": (H, 3),
                  "hand_target_w": (H, M, 3), "hand_force_n": (H, M), "support_force_n": (M, S)}
        nan = {k: torch.full((1, *shape), float("nan")) for k, shape in shapes.items()}
        return {**nan, "static_pos_w": torch.full_like(o.static_pos_w, float("nan")),
                "static_quat_w": torch.full_like(o.static_quat_w, float("nan"))}

    def observation(self, s: TrackingState) -> np.ndarray:
        """(D,) float32: the layout's terms in order, clipped to ±observation_clip."""
        parts = [fn(s) for _, _, fn in self._terms]
        clip = self.spec.observation_clip
        return torch.cat(parts, dim=-1).clamp(-clip, clip)[0].numpy()

    @staticmethod
    def mpjpe_m(s: TrackingState) -> float:
        """Root-relative MPJPE (m) over the tracked bodies (the evaluation's metric)."""
        return float(mpjpe_root_relative(s)[0])

    # ------------------------------------------------------------ start-up check
    def _check_terms(self) -> None:
        """Every term must have its layout dim and be finite on a standing robot: a term that
        reads a field the robot does not measure (NaN here) cannot be deployed."""
        stand = RobotState(joint_pos=self.spec.default_joint_pos.copy(), joint_vel=np.zeros(robot.NUM_JOINTS),
                           quat_wxyz=np.array([1.0, 0.0, 0.0, 0.0]), gyro_b=np.zeros(3), accel_b=np.zeros(3),
                           tick_ms=0, mode_machine=0, remote_keys=0)
        frame = min(1, self.num_frames - 1)
        base = BaseEstimate(self.motion.body_pos_w[0, 0].double().numpy(), np.zeros(3)) if self.needs_base else None
        objects = None
        if self.needs_objects and self.objects is not None:
            M = self.objects.pos_w.shape[1]
            objects = ObjectEstimate(self.objects.pos_w[frame].double().numpy(),
                                     self.objects.quat_w[frame].double().numpy(), np.zeros((M, 3)), np.zeros((M, 3)))
        s = self.tracking_state(stand, frame, np.zeros(robot.NUM_JOINTS), base, objects)
        for name, dim, fn in self._terms:
            value = fn(s)
            if value.shape[-1] != dim:
                raise PolicySpecError(f"{self.spec.source}: observation term '{name}' has {value.shape[-1]} values "
                                      f"here, the policy expects {dim}")
            if not torch.isfinite(value).all():
                raise PolicySpecError(f"{self.spec.source}: observation term '{name}' needs a quantity the G1's "
                                      "low-level state does not give")
