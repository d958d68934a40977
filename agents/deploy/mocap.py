"""Motion capture as a deployment input: the DDS pose stream, and what the runner makes of it.

The stream (``agents/deploy/idl/otr_mocap.idl``, ``MocapFrame_`` on ``rt/otr/mocap`` by
default) carries, per capture, a timestamp and the poses of named rigid bodies: the robot's
pelvis and the objects of the reference, by the names the reference gives them (``--mocap-name
POLICY=STREAM`` maps other names). Positions in metres and quaternions wxyz, in the capture
system's world frame, which must be z-up with z = 0 on the floor; its origin and heading are
free (the runner aligns the clip to the robot's pose when tracking starts). ``otr sim-robot
--publish-mocap`` publishes one from the simulation, with latency and noise if asked.

``MocapTracker`` is the pure part (no I/O, so a log replays it): the newest frame's poses of the
bodies a policy needs, their linear and angular velocities as the least-squares slope over the
last ``velocity_window_s`` of frames (capture timestamps, so latency jitter does not bias them),
and the faults the safety rules act on: stale (no new frame for ``stale_cycles`` cycles), a
non-finite pose, a needed body the stream does not carry.
"""

# No ``from __future__ import annotations``: CycloneDDS resolves the field annotations at run time.
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

try:
    import cyclonedds.idl as idl
    import cyclonedds.idl.annotations as annotate
    import cyclonedds.idl.types as types
except ImportError as exc:  # the `deploy` extra is optional for training-only installs
    raise ImportError("deployment needs CycloneDDS: pip install 'otr-gym[deploy]' (cyclonedds>=11)") from exc

from agents.deploy.options import name_values
from otr_gym.rotations import quat_conj, quat_mul, quat_to_rotvec

TOPIC_MOCAP = "rt/otr/mocap"
MAX_BODIES = 32
NAME_CHARS = 32
#: The name of the robot's base in the stream (the pelvis: the G1's root and IMU body).
BASE_BODY = "pelvis"


@dataclass
@annotate.final
@annotate.autoid("sequential")
class RigidBodyPose_(idl.IdlStruct, typename="otr.msg.dds_.RigidBodyPose_"):
    name: types.bounded_str[NAME_CHARS] = ""
    position: types.array[types.float64, 3] = field(default_factory=lambda: [0.0] * 3)  # m, capture world
    quaternion: types.array[types.float64, 4] = field(default_factory=lambda: [1.0, 0.0, 0.0, 0.0])  # wxyz


@dataclass
@annotate.final
@annotate.autoid("sequential")
class MocapFrame_(idl.IdlStruct, typename="otr.msg.dds_.MocapFrame_"):
    stamp_ns: types.uint64 = 0  # capture time, ns since the Unix epoch (CLOCK_REALTIME)
    seq: types.uint32 = 0
    bodies: types.sequence[RigidBodyPose_, MAX_BODIES] = field(default_factory=list)


@dataclass(frozen=True)
class MocapFrame:
    """One capture as arrays: ``names`` (B,), ``pos_w`` (B, 3) m, ``quat_wxyz`` (B, 4)."""

    stamp_ns: int
    seq: int
    names: tuple[str, ...]
    pos_w: np.ndarray
    quat_wxyz: np.ndarray


def mocap_frame(msg: MocapFrame_) -> MocapFrame:
    b = msg.bodies
    return MocapFrame(int(msg.stamp_ns), int(msg.seq), tuple(p.name for p in b),
                      np.array([p.position for p in b], dtype=np.float64).reshape(-1, 3),
                      np.array([p.quaternion for p in b], dtype=np.float64).reshape(-1, 4))


def mocap_message(frame: MocapFrame) -> MocapFrame_:
    if len(frame.names) > MAX_BODIES:
        raise ValueError(f"a mocap frame carries at most {MAX_BODIES} bodies, got {len(frame.names)}")
    too_long = [n for n in frame.names if len(n.encode()) > NAME_CHARS]
    if too_long:
        raise ValueError(f"mocap body names are at most {NAME_CHARS} bytes: {too_long}")
    return MocapFrame_(stamp_ns=frame.stamp_ns, seq=frame.seq & 0xFFFFFFFF, bodies=[
        RigidBodyPose_(n, p.tolist(), q.tolist())
        for n, p, q in zip(frame.names, frame.pos_w, frame.quat_wxyz, strict=True)])


def now_ns() -> int:
    """The capture clock: CLOCK_REALTIME, shared by processes on one host (and by PTP-synced hosts)."""
    return time.time_ns()


def name_map(items: list[str] | None) -> dict[str, str]:
    """``--mocap-name POLICY=STREAM`` items as {policy name: stream name}."""
    return name_values(items, "--mocap-name", "POLICY=STREAM", "largebox=box_1")


class MocapFault:
    STALE = "stale_mocap"
    NAN = "nan_mocap"
    MISSING_BODY = "mocap_body"


@dataclass(frozen=True)
class BodyMotion:
    """Poses and velocities of B bodies in the capture world: pos (B, 3) m, quat (B, 4) wxyz,
    lin_vel (B, 3) m/s, ang_vel (B, 3) rad/s (world axes)."""

    pos_w: np.ndarray
    quat_wxyz: np.ndarray
    lin_vel_w: np.ndarray
    ang_vel_w: np.ndarray


def velocity_slope(t_s: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The least-squares slope dx/dt over samples ``t_s`` (T,), ``x`` (T, …); zeros for T < 2."""
    if len(t_s) < 2:
        return np.zeros(x.shape[1:])
    dt = t_s - t_s.mean()
    return np.tensordot(dt, x - x.mean(axis=0), axes=1) / float(dt @ dt)


@dataclass
class MocapTrackerCfg:
    bodies: tuple[str, ...]  # the bodies followed and logged, by the reference's names (the base first)
    required: tuple[str, ...] = ()  # those the policy reads: missing or not finite, a fault
    names: dict[str, str] = field(default_factory=dict)  # reference name -> stream name, where they differ
    stale_cycles: int = 3  # a fault after this many cycles without a new frame
    velocity_window_s: float = 0.1  # frames in this window give the velocities


class MocapTracker:
    """The newest capture of ``cfg.bodies``, their velocities and the stream's faults (module doc)."""

    def __init__(self, cfg: MocapTrackerCfg):
        self.cfg = cfg
        self.history: deque[tuple[float, np.ndarray, np.ndarray]] = deque()  # (stamp s, pos, quat)
        self.frame: MocapFrame | None = None  # the newest frame (as received, stream names)
        self.cycles_without_frame = 0
        self.fault: tuple[str, str] | None = None  # (MocapFault, message) of the newest frame
        # computed once per new frame: the controller reads the motion several times a cycle
        # and the log the rows of the frame the tracker has just taken apart
        self._motion: BodyMotion | None = None
        self._rows: tuple[MocapFrame | None, np.ndarray, np.ndarray] = (None, np.empty(0), np.empty(0))

    def stream_name(self, body: str) -> str:
        return self.cfg.names.get(body, body)

    def update(self, frame: MocapFrame | None) -> None:
        """One control cycle's input: the frame taken this cycle, or None."""
        if frame is None or (self.frame is not None and frame.seq == self.frame.seq
                             and frame.stamp_ns == self.frame.stamp_ns):
            if self.frame is not None:
                self.cycles_without_frame += 1
            return
        self.frame, self.cycles_without_frame, self.fault = frame, 0, None
        pos, quat = self.rows(frame)
        missing = [b for b in self.cfg.required if self.stream_name(b) not in frame.names]
        if missing:
            mapped = [f"{b} (as '{self.stream_name(b)}')" if self.stream_name(b) != b else b for b in missing]
            self.fault = (MocapFault.MISSING_BODY,
                          f"the mocap frame carries {list(frame.names)}, not {', '.join(mapped)} that the policy "
                          "needs (--mocap-name POLICY=STREAM maps a name)")
            return
        norm = np.linalg.norm(quat, axis=-1)
        good = np.isfinite(pos).all(axis=-1) & np.isfinite(quat).all(axis=-1) & (norm > 0.5)
        bad = [b for b, g in zip(self.cfg.bodies, good, strict=True) if b in self.cfg.required and not g]
        if bad:
            self.fault = (MocapFault.NAN, f"the mocap pose of {', '.join(bad)} is not finite (or not a unit "
                                          f"quaternion) in frame {frame.seq}")
            return
        quat = quat / np.where(good, norm, 1.0)[:, None]
        t = frame.stamp_ns * 1e-9
        if self.history and t <= self.history[-1][0]:  # a frame older than one already used: out of order
            return
        self.history.append((t, pos, quat))
        while self.history and self.history[0][0] < t - self.cfg.velocity_window_s - 1e-9:
            self.history.popleft()
        self._motion = self._window_motion()

    def rows(self, frame: MocapFrame) -> tuple[np.ndarray, np.ndarray]:
        """(B, 3) positions and (B, 4) quaternions of ``cfg.bodies`` in ``frame`` (NaN where absent)."""
        if frame is self._rows[0]:
            return self._rows[1], self._rows[2]
        index = {n: i for i, n in enumerate(frame.names)}
        pos, quat = np.full((len(self.cfg.bodies), 3), np.nan), np.full((len(self.cfg.bodies), 4), np.nan)
        for k, b in enumerate(self.cfg.bodies):
            i = index.get(self.stream_name(b))
            if i is not None:
                pos[k], quat[k] = frame.pos_w[i], frame.quat_wxyz[i]
        self._rows = (frame, pos, quat)
        return pos, quat

    def current_fault(self) -> tuple[str, str] | None:
        """(MocapFault, message) if the stream cannot feed the policy now."""
        if self.frame is None:
            return MocapFault.STALE, "no mocap frame has arrived"
        if self.cycles_without_frame >= self.cfg.stale_cycles:
            return MocapFault.STALE, f"no new mocap frame for {self.cycles_without_frame} cycles"
        return self.fault

    def motion(self) -> BodyMotion | None:
        """The newest good capture of ``cfg.bodies`` with velocities, or None before one."""
        return self._motion

    def _window_motion(self) -> BodyMotion:
        t = np.array([h[0] for h in self.history])
        pos = np.stack([h[1] for h in self.history])
        quat = np.stack([h[2] for h in self.history])
        # angular velocity: the slope of the rotation vectors of q_k·q_last⁻¹ (small over the window)
        relative = quat_mul(quat, np.broadcast_to(quat_conj(quat[-1]), quat.shape))
        return BodyMotion(pos_w=pos[-1], quat_wxyz=quat[-1], lin_vel_w=velocity_slope(t, pos),
                          ang_vel_w=velocity_slope(t, quat_to_rotvec(relative)))
