"""Reference datasets: robot (and object) motion for whole-body tracking.

File format: one ``.npz`` in the Holosoma / BeyondMimic whole-body-tracking layout, so that
their files load here unchanged and ours load in their tools:

===================  ==============  ===================================================
key                  shape           meaning
===================  ==============  ===================================================
fps                  (1,)            frames per second
joint_names          (29,)           G1 joint names, in the column order of joint_pos
joint_pos            (T, 36)         root xyz (m, world), root quat **wxyz**, 29 joints (rad)
joint_vel            (T, 35)         root linear velocity (world), root angular velocity
                                     (world), 29 joint velocities (IsaacLab convention;
                                     MuJoCo's free-joint qvel wants the angular part in the
                                     body frame: see ``Reference.qvel``)
body_names           (B,)            bodies of the arrays below (may include 'world', objects)
body_pos_w           (T, B, 3)       body origin positions (m, world)
body_quat_w          (T, B, 4)       body orientations, wxyz
body_lin_vel_w       (T, B, 3)       body origin velocities (m/s, world)
body_ang_vel_w       (T, B, 3)       body angular velocities (rad/s, world)
object_pos_w, …      (T, 3/4/3/3)    first object: pos, quat wxyz, lin/ang velocity (world)
===================  ==============  ===================================================

Our extras (ignored by other tools): ``object_names`` (O,), ``objects_pos_w`` (T, O, 3),
``objects_quat_w`` (T, O, 4), ``objects_lin_vel_w``, ``objects_ang_vel_w`` (T, O, 3), per object
``object_mesh_vertices_<i>`` (V, 3, object frame, m) / ``object_mesh_faces_<i>`` (F, 3);
contact annotations ``contact_body_names`` (U,), ``contact_channel_names`` (C,),
``contact_distance`` (T, U, C) signed distance (m) of each body unit to each channel
(ground, objects), ``contact_witness_c`` (T, U, C, 3) closest point on the channel in the
channel's frame; ``otr_metadata`` a JSON string (retarget mode, scale, weights, source).

mjlab's layout (``joint_pos``/``joint_vel`` (T, 29), no names, bodies in model order) is
read too. Saving is atomic (temporary file + rename).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from otr_gym import robot
from otr_gym.io import NpzError, load_npz, save_npz
from otr_gym.rotations import (
    angular_velocity_from_quats,
    linear_velocity_from_positions,
    quat_normalize,
    quat_slerp,
)
from otr_gym.scene import robot_model

QUAT_UNIT_TOL = 1e-3
REQUIRED_KEYS = ("fps", "joint_pos", "joint_vel", "body_pos_w", "body_quat_w", "body_lin_vel_w", "body_ang_vel_w")


class InvalidReferenceError(ValueError):
    """A reference file or array set that cannot be used; the message names the file and the problem."""


@dataclass
class ObjectTrack:
    """One rigid object's motion (world frame) and, when known, its mesh (object frame, m)."""

    name: str
    pos_w: np.ndarray  # (T, 3)
    quat_w: np.ndarray  # (T, 4) wxyz
    lin_vel_w: np.ndarray  # (T, 3)
    ang_vel_w: np.ndarray  # (T, 3)
    mesh_vertices: np.ndarray | None = None  # (V, 3)
    mesh_faces: np.ndarray | None = None  # (F, 3)


@dataclass
class ContactAnnotations:
    """Per-(body unit, channel) proximity over time, from the demonstration or the retarget."""

    body_names: tuple[str, ...]
    channel_names: tuple[str, ...]
    distance: np.ndarray  # (T, U, C) signed distance (m)
    witness_c: np.ndarray | None = None  # (T, U, C, 3) witness in the channel frame (m)

    def in_contact(self, threshold_m: float = 0.02) -> np.ndarray:
        """(T, U, C) boolean: (d)₊ < threshold (the paper's ε_eval = 20 mm by default)."""
        return np.maximum(self.distance, 0.0) < threshold_m

    def at(self, frames) -> ContactAnnotations:
        """The annotations of ``frames`` (a slice or an index array into the time axis)."""
        return replace(self, distance=self.distance[frames],
                       witness_c=None if self.witness_c is None else self.witness_c[frames])


@dataclass
class Reference:
    """A G1 reference motion. Arrays are float64 NumPy; quaternions wxyz; frames world."""

    fps: float
    joint_names: tuple[str, ...]
    joint_pos: np.ndarray  # (T, 36)
    joint_vel: np.ndarray  # (T, 35)
    body_names: tuple[str, ...]
    body_pos_w: np.ndarray  # (T, B, 3)
    body_quat_w: np.ndarray  # (T, B, 4)
    body_lin_vel_w: np.ndarray  # (T, B, 3)
    body_ang_vel_w: np.ndarray  # (T, B, 3)
    objects: list[ObjectTrack] = field(default_factory=list)
    contacts: ContactAnnotations | None = None
    metadata: dict = field(default_factory=dict)
    source: str = "<memory>"

    # ------------------------------------------------------------ views
    @property
    def num_frames(self) -> int:
        return int(self.joint_pos.shape[0])

    @property
    def duration_s(self) -> float:
        return (self.num_frames - 1) / self.fps

    @property
    def root_pos_w(self) -> np.ndarray:
        return self.joint_pos[:, :3]

    @property
    def root_quat_w(self) -> np.ndarray:
        return self.joint_pos[:, 3:7]

    @property
    def _g1_columns(self) -> list[int]:
        """Column of each G1 joint (G1 order) in this file's joint order."""
        return [self.joint_names.index(n) for n in robot.JOINT_NAMES]

    @property
    def dof_pos(self) -> np.ndarray:
        """(T, 29) joint positions in G1 order."""
        return self.joint_pos[:, 7:][:, self._g1_columns]

    @property
    def dof_vel(self) -> np.ndarray:
        """(T, 29) joint velocities in G1 order."""
        return self.joint_vel[:, 6:][:, self._g1_columns]

    def qpos(self) -> np.ndarray:
        """(T, 36) MuJoCo qpos of the G1 (root xyz, wxyz, joints in G1 order)."""
        return np.concatenate([self.joint_pos[:, :7], self.dof_pos], axis=1)

    def qvel(self) -> np.ndarray:
        """(T, 35) MuJoCo qvel: free-joint angular velocity in the **body** frame."""
        from otr_gym.rotations import quat_apply_inverse

        ang_b = quat_apply_inverse(self.root_quat_w, self.joint_vel[:, 3:6])
        return np.concatenate([self.joint_vel[:, :3], ang_b, self.dof_vel], axis=1)

    def body_index(self, names) -> np.ndarray:
        index = {n: i for i, n in enumerate(self.body_names)}
        missing = [n for n in names if n not in index]
        if missing:
            raise InvalidReferenceError(f"{self.source}: bodies {missing} are not in the reference")
        return np.array([index[n] for n in names], dtype=np.int64)

    # ------------------------------------------------------------ construction
    @classmethod
    def from_qpos(
        cls,
        qpos: np.ndarray,
        fps: float,
        objects: list[ObjectTrack] | None = None,
        contacts: ContactAnnotations | None = None,
        metadata: dict | None = None,
    ) -> Reference:
        """Build a reference from G1 configurations (T, 36) [xyz, wxyz, joints in G1 order].

        Body poses come from MuJoCo forward kinematics of our G1 model; all velocities are
        finite differences of the poses (central inside, one-sided at the ends; angular via
        the SO(3) log), so they are consistent with the poses by construction.
        """
        import mujoco

        qpos = np.asarray(qpos, dtype=np.float64)
        if qpos.ndim != 2 or qpos.shape[1] != 7 + robot.NUM_JOINTS:
            raise InvalidReferenceError(f"qpos must be (T, 36), got {qpos.shape}")
        _check_finite("<qpos>", "qpos", qpos)
        qpos = qpos.copy()
        qpos[:, 3:7] = quat_normalize(qpos[:, 3:7])
        model = robot_model(visual=False)
        data = mujoco.MjData(model)
        body_ids = [model.body(n).id for n in robot.BODY_NAMES]
        T = qpos.shape[0]
        pos = np.empty((T, len(body_ids), 3))
        quat = np.empty((T, len(body_ids), 4))
        for t in range(T):
            data.qpos[:] = qpos[t]
            mujoco.mj_kinematics(model, data)
            pos[t] = data.xpos[body_ids]
            quat[t] = data.xquat[body_ids]
        dt = 1.0 / fps
        joint_vel = np.concatenate([
            linear_velocity_from_positions(qpos[:, :3], dt),
            angular_velocity_from_quats(qpos[:, 3:7], dt),
            linear_velocity_from_positions(qpos[:, 7:], dt),
        ], axis=1)
        ref = cls(
            fps=float(fps), joint_names=robot.JOINT_NAMES, joint_pos=qpos, joint_vel=joint_vel,
            body_names=robot.BODY_NAMES, body_pos_w=pos, body_quat_w=quat,
            body_lin_vel_w=linear_velocity_from_positions(pos, dt),
            body_ang_vel_w=angular_velocity_from_quats(quat, dt),
            objects=list(objects or []), contacts=contacts, metadata=dict(metadata or {}),
        )
        ref.validate()
        return ref

    def with_recomputed_velocities(self) -> Reference:
        """A copy whose velocities are finite differences of its poses (fixes peers' quirks)."""
        dt = 1.0 / self.fps
        jp = self.joint_pos
        joint_vel = np.concatenate([
            linear_velocity_from_positions(jp[:, :3], dt),
            angular_velocity_from_quats(jp[:, 3:7], dt),
            linear_velocity_from_positions(jp[:, 7:], dt),
        ], axis=1)
        objects = [replace(o, lin_vel_w=linear_velocity_from_positions(o.pos_w, dt),
                           ang_vel_w=angular_velocity_from_quats(o.quat_w, dt)) for o in self.objects]
        return replace(self, joint_vel=joint_vel,
                       body_lin_vel_w=linear_velocity_from_positions(self.body_pos_w, dt),
                       body_ang_vel_w=angular_velocity_from_quats(self.body_quat_w, dt), objects=objects)

    def translated(self, offset_m) -> Reference:
        """A copy moved by ``offset_m`` (3,) (m, world): root, body and object positions shift;
        orientations, velocities and contact annotations (witnesses in channel frames) do not."""
        offset = np.asarray(offset_m, np.float64).reshape(3)
        joint_pos = self.joint_pos.copy()
        joint_pos[:, :3] += offset
        objects = [replace(o, pos_w=o.pos_w + offset) for o in self.objects]
        return replace(self, joint_pos=joint_pos, body_pos_w=self.body_pos_w + offset, objects=objects)

    def subclip(self, start: int, stop: int | None = None) -> Reference:
        """Frames ``start`` … ``stop − 1`` (``stop`` None: to the end) of every time series:
        robot, objects and contact annotations; meshes, names and fps unchanged. The source
        stays (terrain and clip-list options keep applying); ``metadata["subclip"]`` records
        [start, stop] in the original numbering. A range outside the clip, or shorter than two
        frames, raises naming the source."""
        n = self.num_frames
        stop = n if stop is None else stop
        if not 0 <= start < stop <= n or stop - start < 2:
            raise InvalidReferenceError(f"{self.source}: frames {start}:{stop} are not a range of at least 2 of "
                                        f"its {n} frames")
        s = slice(start, stop)
        objects = [replace(o, pos_w=o.pos_w[s], quat_w=o.quat_w[s], lin_vel_w=o.lin_vel_w[s],
                           ang_vel_w=o.ang_vel_w[s]) for o in self.objects]
        contacts = None if self.contacts is None else self.contacts.at(s)
        return replace(self, joint_pos=self.joint_pos[s], joint_vel=self.joint_vel[s], body_pos_w=self.body_pos_w[s],
                       body_quat_w=self.body_quat_w[s], body_lin_vel_w=self.body_lin_vel_w[s],
                       body_ang_vel_w=self.body_ang_vel_w[s], objects=objects, contacts=contacts,
                       metadata={**self.metadata, "subclip": [int(start), int(stop)]})

    def resampled(self, fps: float) -> Reference:
        """Resample to ``fps`` (linear for positions and joints, slerp for quaternions);
        velocities are recomputed by finite differences. Contacts use the nearest frame."""
        if abs(fps - self.fps) < 1e-9:
            return self
        t_src = np.arange(self.num_frames) / self.fps
        n = int(np.floor(t_src[-1] * fps + 1e-9)) + 1
        t_dst = np.arange(n) / fps
        i0 = np.clip(np.floor(t_dst * self.fps).astype(int), 0, self.num_frames - 1)
        i1 = np.minimum(i0 + 1, self.num_frames - 1)
        a = np.clip(t_dst * self.fps - i0, 0.0, 1.0)

        def lerp(x):
            w = a.reshape((-1,) + (1,) * (x.ndim - 1))
            return (1 - w) * x[i0] + w * x[i1]

        def slerp(q):
            w = np.broadcast_to(a.reshape((-1,) + (1,) * (q.ndim - 2)), q[i0].shape[:-1])
            return quat_slerp(q[i0], q[i1], w)

        jp = lerp(self.joint_pos)
        jp[:, 3:7] = slerp(self.joint_pos[:, 3:7])
        objects = [replace(o, pos_w=lerp(o.pos_w), quat_w=slerp(o.quat_w)) for o in self.objects]
        nearest = np.clip(np.rint(t_dst * self.fps).astype(int), 0, self.num_frames - 1)
        contacts = None if self.contacts is None else self.contacts.at(nearest)
        out = replace(self, fps=float(fps), joint_pos=jp, body_pos_w=lerp(self.body_pos_w),
                      body_quat_w=slerp(self.body_quat_w), objects=objects, contacts=contacts)
        return out.with_recomputed_velocities()

    # ------------------------------------------------------------ validation
    def validate(self) -> None:
        """Raise InvalidReferenceError naming ``self.source`` and the first problem found."""
        src = self.source
        if not np.isfinite(self.fps) or self.fps <= 0:
            raise InvalidReferenceError(f"{src}: fps must be > 0, got {self.fps}")
        T = self.joint_pos.shape[0] if self.joint_pos.ndim == 2 else -1
        if T < 2:
            raise InvalidReferenceError(f"{src}: joint_pos must be (T ≥ 2, 36), got {self.joint_pos.shape}")
        unknown = [n for n in self.joint_names if n not in robot.JOINT_NAMES]
        if unknown:
            raise InvalidReferenceError(f"{src}: unknown joint names {unknown}")
        missing = [n for n in robot.JOINT_NAMES if n not in self.joint_names]
        if missing or len(self.joint_names) != robot.NUM_JOINTS:
            raise InvalidReferenceError(f"{src}: joint_names must list the 29 G1 joints once; missing {missing}")
        B = len(self.body_names)
        expected = {
            "joint_pos": (T, 7 + robot.NUM_JOINTS), "joint_vel": (T, 6 + robot.NUM_JOINTS),
            "body_pos_w": (T, B, 3), "body_quat_w": (T, B, 4),
            "body_lin_vel_w": (T, B, 3), "body_ang_vel_w": (T, B, 3),
        }
        for key, shape in expected.items():
            arr = getattr(self, key)
            if arr.shape != shape:
                raise InvalidReferenceError(f"{src}: {key} has shape {arr.shape}, expected {shape}")
            _check_finite(src, key, arr)
        _check_unit(src, "joint_pos[:, 3:7] (root quaternion)", self.joint_pos[:, 3:7])
        _check_unit(src, "body_quat_w", self.body_quat_w)
        for o in self.objects:
            for key, shape in (("pos_w", (T, 3)), ("quat_w", (T, 4)), ("lin_vel_w", (T, 3)), ("ang_vel_w", (T, 3))):
                arr = getattr(o, key)
                if arr.shape != shape:
                    raise InvalidReferenceError(f"{src}: object '{o.name}' {key} has shape {arr.shape}, "
                                                f"expected {shape}")
                _check_finite(src, f"object '{o.name}' {key}", arr)
            _check_unit(src, f"object '{o.name}' quat_w", o.quat_w)
        if self.contacts is not None:
            c = self.contacts
            shape = (T, len(c.body_names), len(c.channel_names))
            if c.distance.shape != shape:
                raise InvalidReferenceError(f"{src}: contact_distance has shape {c.distance.shape}, expected {shape}")
            if np.isnan(c.distance).any():
                raise InvalidReferenceError(f"{src}: contact_distance contains NaN")

    def velocity_consistency(self) -> dict[str, float]:
        """Max deviation of stored velocities from finite differences of the poses (interior frames)."""
        fd = self.with_recomputed_velocities()
        inner = slice(1, -1) if self.num_frames > 2 else slice(None)
        return {
            "joint_vel": float(np.abs(fd.joint_vel[inner] - self.joint_vel[inner]).max()),
            "body_lin_vel_w": float(np.abs(fd.body_lin_vel_w[inner] - self.body_lin_vel_w[inner]).max()),
            "body_ang_vel_w": float(np.abs(fd.body_ang_vel_w[inner] - self.body_ang_vel_w[inner]).max()),
        }

    # ------------------------------------------------------------ IO
    def to_arrays(self) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {
            # Holosoma stores fps as int64 [50]; keep integers integral
            "fps": np.array([int(self.fps)]) if float(self.fps).is_integer() else np.array([self.fps]),
            "joint_names": np.array(self.joint_names),
            "joint_pos": self.joint_pos, "joint_vel": self.joint_vel,
            "body_names": np.array(self.body_names),
            "body_pos_w": self.body_pos_w, "body_quat_w": self.body_quat_w,
            "body_lin_vel_w": self.body_lin_vel_w, "body_ang_vel_w": self.body_ang_vel_w,
        }
        if self.objects:
            first = self.objects[0]
            out.update(object_pos_w=first.pos_w, object_quat_w=first.quat_w,
                       object_lin_vel_w=first.lin_vel_w, object_ang_vel_w=first.ang_vel_w)
            out["object_names"] = np.array([o.name for o in self.objects])
            for key in ("pos_w", "quat_w", "lin_vel_w", "ang_vel_w"):
                out[f"objects_{key}"] = np.stack([getattr(o, key) for o in self.objects], axis=1)
            for i, o in enumerate(self.objects):
                if o.mesh_vertices is not None:
                    out[f"object_mesh_vertices_{i}"] = np.asarray(o.mesh_vertices, np.float32)
                    out[f"object_mesh_faces_{i}"] = np.asarray(o.mesh_faces, np.int32)
        if self.contacts is not None:
            c = self.contacts
            out.update(contact_body_names=np.array(c.body_names), contact_channel_names=np.array(c.channel_names),
                       contact_distance=np.asarray(c.distance, np.float32))
            if c.witness_c is not None:
                out["contact_witness_c"] = np.asarray(c.witness_c, np.float32)
        if self.metadata:
            out["otr_metadata"] = np.array(json.dumps(self.metadata, sort_keys=True))
        return out

    def save(self, path: str | Path) -> Path:
        """Validate, then write atomically (temporary file in the same folder + rename)."""
        self.validate()
        return save_npz(path, self.to_arrays())

    @classmethod
    def load(cls, path: str | Path) -> Reference:
        """Load and validate a reference; any problem raises InvalidReferenceError naming the file."""
        path = Path(path)
        if not path.is_file():
            raise InvalidReferenceError(f"{path}: no such reference file")
        try:
            data = load_npz(path)
        except (NpzError, OSError) as exc:  # the message names the file and the problem
            raise InvalidReferenceError(str(exc)) from exc
        return cls.from_arrays(data, source=str(path))

    @classmethod
    def from_arrays(cls, data: dict[str, np.ndarray], source: str = "<memory>") -> Reference:
        missing = [k for k in REQUIRED_KEYS if k not in data]
        if missing:
            raise InvalidReferenceError(f"{source}: missing keys {missing}")
        fps_arr = np.asarray(data["fps"]).ravel()
        if fps_arr.size != 1:
            raise InvalidReferenceError(f"{source}: fps must be one number, got shape {np.shape(data['fps'])}")
        fps = float(fps_arr[0])
        jp = np.asarray(data["joint_pos"], np.float64)
        jv = np.asarray(data["joint_vel"], np.float64)
        bp = np.asarray(data["body_pos_w"], np.float64)
        if jp.ndim != 2 or jv.ndim != 2 or bp.ndim != 3:
            raise InvalidReferenceError(
                f"{source}: joint_pos/joint_vel must be 2-D and body_pos_w 3-D, got "
                f"{jp.shape}, {jv.shape}, {bp.shape}")
        if "joint_names" in data:
            joint_names = tuple(str(n) for n in data["joint_names"])
        elif jp.shape[1] in (robot.NUM_JOINTS, 7 + robot.NUM_JOINTS):
            joint_names = robot.JOINT_NAMES
        else:
            raise InvalidReferenceError(f"{source}: no joint_names and joint_pos has {jp.shape[1]} columns")
        if "body_names" in data:
            body_names = tuple(str(n) for n in data["body_names"])
        elif bp.shape[1] == len(robot.BODY_NAMES):
            body_names = robot.BODY_NAMES
        else:
            raise InvalidReferenceError(f"{source}: no body_names and body_pos_w has {bp.shape[1]} bodies "
                                        f"(mjlab layout needs the {len(robot.BODY_NAMES)} G1 bodies)")
        bq = np.asarray(data["body_quat_w"], np.float64)
        if jp.shape[1] == robot.NUM_JOINTS and jv.shape[1] == robot.NUM_JOINTS:
            # mjlab layout: joints only; the root is the first body ('pelvis').
            root = body_names.index(robot.ROOT_BODY) if robot.ROOT_BODY in body_names else 0
            T = jp.shape[0]
            if bp.shape[0] != T or bq.shape[:2] != bp.shape[:2]:
                raise InvalidReferenceError(f"{source}: body arrays have {bp.shape[0]} frames, joint_pos {T}")
            jp = np.concatenate([bp[:, root], bq[:, root], jp], axis=1)
            jv = np.concatenate([np.asarray(data["body_lin_vel_w"], np.float64)[:, root],
                                 np.asarray(data["body_ang_vel_w"], np.float64)[:, root], jv], axis=1)
        objects = _objects_from_arrays(data, body_names, source)
        contacts = None
        if "contact_distance" in data:
            for key in ("contact_body_names", "contact_channel_names"):
                if key not in data:
                    raise InvalidReferenceError(f"{source}: contact_distance present but {key} missing")
            contacts = ContactAnnotations(
                body_names=tuple(str(n) for n in data["contact_body_names"]),
                channel_names=tuple(str(n) for n in data["contact_channel_names"]),
                distance=np.asarray(data["contact_distance"], np.float64),
                witness_c=np.asarray(data["contact_witness_c"], np.float64) if "contact_witness_c" in data else None,
            )
        metadata = {}
        if "otr_metadata" in data:
            try:
                metadata = json.loads(str(data["otr_metadata"]))
            except json.JSONDecodeError as exc:
                raise InvalidReferenceError(f"{source}: otr_metadata is not valid JSON ({exc})") from exc
        ref = cls(fps=fps, joint_names=joint_names, joint_pos=jp, joint_vel=jv, body_names=body_names,
                  body_pos_w=bp, body_quat_w=bq,
                  body_lin_vel_w=np.asarray(data["body_lin_vel_w"], np.float64),
                  body_ang_vel_w=np.asarray(data["body_ang_vel_w"], np.float64),
                  objects=objects, contacts=contacts, metadata=metadata, source=source)
        ref.validate()
        return ref


def _objects_from_arrays(data, body_names, source) -> list[ObjectTrack]:
    if "objects_pos_w" in data:
        names = [str(n) for n in data.get("object_names",
                                          [f"object{i}" for i in range(data["objects_pos_w"].shape[1])])]
        out = []
        for i, name in enumerate(names):
            out.append(ObjectTrack(
                name=name,
                pos_w=np.asarray(data["objects_pos_w"][:, i], np.float64),
                quat_w=np.asarray(data["objects_quat_w"][:, i], np.float64),
                lin_vel_w=np.asarray(data["objects_lin_vel_w"][:, i], np.float64),
                ang_vel_w=np.asarray(data["objects_ang_vel_w"][:, i], np.float64),
                mesh_vertices=data.get(f"object_mesh_vertices_{i}"),
                mesh_faces=data.get(f"object_mesh_faces_{i}"),
            ))
        return out
    if "object_pos_w" not in data:
        return []
    for key in ("object_quat_w", "object_lin_vel_w"):
        if key not in data:
            raise InvalidReferenceError(f"{source}: object_pos_w present but {key} missing")
    # Holosoma: the object is also a body of their model (e.g. 'largebox_link')
    extra = [n for n in body_names if n != "world" and n not in robot.BODY_NAMES and
             not n.startswith(("left_", "right_", "waist_", "pelvis", "torso", "head", "logo"))]
    name = extra[-1].removesuffix("_link") if extra else "object"
    pos = np.asarray(data["object_pos_w"], np.float64)
    ang = data.get("object_ang_vel_w")
    return [ObjectTrack(name=name, pos_w=pos, quat_w=np.asarray(data["object_quat_w"], np.float64),
                        lin_vel_w=np.asarray(data["object_lin_vel_w"], np.float64),
                        ang_vel_w=np.zeros_like(pos) if ang is None else np.asarray(ang, np.float64))]


def _check_finite(src: str, key: str, arr: np.ndarray) -> None:
    if not np.isfinite(arr).all():
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise InvalidReferenceError(f"{src}: {key} contains NaN/inf (first at index {tuple(int(i) for i in bad)})")


def _check_unit(src: str, key: str, q: np.ndarray) -> None:
    err = np.abs(np.linalg.norm(q, axis=-1) - 1.0)
    if err.size and err.max() > QUAT_UNIT_TOL:
        idx = np.unravel_index(np.argmax(err), err.shape)
        raise InvalidReferenceError(
            f"{src}: {key} is not unit-norm (|q| = {1 + err[idx]:.4f} at index {tuple(int(i) for i in idx)})")


#: Suffixes of clip-list files: one reference path per line, relative to the list's folder.
LIST_SUFFIXES = (".txt", ".list")
#: Options a clip-list line may give after its path, as ``KEY=VALUE`` words.
CLIP_OPTIONS = ("terrain",)


@dataclass(frozen=True)
class ClipEntry:
    """One clip named by ``clip_entries``, with the options its clip-list line gave."""

    path: Path
    terrain: Path | None = None  # terrain mesh of the clip (envs.terrain), None: flat floor


def list_references(path: str | Path) -> list[Path]:
    """A single file, every ``*.npz`` of a folder (sorted), or the entries of a list file
    (``.txt``/``.list``: one file or folder per line, relative to the list's folder; blank lines
    and ``#`` comments ignored), each expanded the same way; a missing path raises naming it."""
    return [e.path for e in clip_entries(path)]


def clip_entries(path: str | Path) -> list[ClipEntry]:
    """``list_references`` with the options of clip-list lines: after the path, words
    ``KEY=VALUE`` with KEY in ``CLIP_OPTIONS``; ``terrain=MESH`` (relative to the list's folder)
    applies to every clip the line names (a folder: all its clips). An unknown option raises
    naming the list and the line."""
    path = Path(path)
    if path.is_dir():
        files = sorted(path.glob("*.npz"))
        if not files:
            raise InvalidReferenceError(f"{path}: folder holds no .npz references")
        return [ClipEntry(f) for f in files]
    if not path.is_file():
        raise InvalidReferenceError(f"{path}: no such reference file or folder")
    if path.suffix.lower() not in LIST_SUFFIXES:
        return [ClipEntry(path)]
    out: list[ClipEntry] = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        entry = line.split("#", 1)[0].strip()
        if not entry:
            continue
        where = f"{path}, line {n}"
        entry, options = _clip_options(entry, where)
        item = _relative_to(path, entry)
        terrain = _relative_to(path, options["terrain"]) if "terrain" in options else None
        try:
            out.extend(replace(e, terrain=terrain or e.terrain) for e in clip_entries(item))
        except InvalidReferenceError as exc:
            raise InvalidReferenceError(f"{where}: {exc}") from exc
    if not out:
        raise InvalidReferenceError(f"{path}: clip list names no reference")
    return out


def _clip_options(entry: str, where: str) -> tuple[str, dict[str, str]]:
    """(path, {option: value}) of a clip-list line: trailing ``KEY=VALUE`` words are options
    (a path may hold spaces, not a last word with '=')."""
    words = entry.split()
    options: dict[str, str] = {}
    while len(words) > 1 and "=" in words[-1]:
        key, _, value = words.pop().partition("=")
        if key not in CLIP_OPTIONS:
            raise InvalidReferenceError(f"{where}: unknown option '{key}' (options: {', '.join(CLIP_OPTIONS)})")
        if not value:
            raise InvalidReferenceError(f"{where}: option '{key}' has no value ({key}=PATH)")
        options[key] = value
    return (" ".join(words) if options else entry), options


def _relative_to(list_file: Path, entry: str) -> Path:
    item = Path(entry).expanduser()
    return item if item.is_absolute() else list_file.parent / item
