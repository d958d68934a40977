"""The ``unitree_hg`` low-level messages of the G1 (docs/environment.md §9), as CycloneDDS IDL structs.

Our own definitions of Unitree's ``unitree_hg::msg::dds_`` types: same DDS type names, field
order, field types and array sizes as the IDL shipped with Unitree SDK2 (``LowCmd_.idl``,
``LowState_.idl``, ``MotorCmd_.idl``, ``MotorState_.idl``, ``IMUState_.idl``), all ``@final``,
so a robot or a controller built on the SDK reads what we write, byte for byte
(``tests/test_deploy_messages.py`` checks the layout, and the bytes against the SDK when it is
importable). We do not depend on the SDK's Python package: ``unitree_sdk2`` 1.0.1 pins
``cyclonedds==0.10.2`` (no CPython 3.11 wheel) and its wheel does not import (its ``__init__``
imports a ``b2`` subpackage the wheel lacks).

Conversions to and from NumPy arrays in policy joint order live here too, so nothing else
touches the message objects field by field. Units: rad, rad/s, N·m; the IMU quaternion is
**wxyz**; the gyroscope is in the pelvis (IMU) frame.
"""

# No ``from __future__ import annotations``: CycloneDDS resolves the field annotations at run
# time and cannot look up string annotations such as "types.uint8".
import struct
from dataclasses import dataclass, field

try:
    import cyclonedds.idl as idl
    import cyclonedds.idl.annotations as annotate
    import cyclonedds.idl.types as types
    from cyclonedds.idl import Endianness
except ImportError as exc:  # the `deploy` extra is optional for training-only installs
    raise ImportError("deployment needs CycloneDDS: pip install 'otr-gym[deploy]' (cyclonedds>=11)") from exc
import numpy as np

from otr_gym import robot

NUM_MOTORS = robot.NUM_MOTOR_SLOTS  # 35 slots; the 29-DoF G1 uses 0..28
WIRELESS_REMOTE_BYTES = 40

TOPIC_LOWSTATE = "rt/lowstate"
TOPIC_LOWCMD = "rt/lowcmd"

#: LowCmd mode fields used on the G1 (docs/environment.md §9): pitch/roll ankle mode, motors enabled.
MODE_PR = 0
MOTOR_MODE_ENABLE = 1


@dataclass
@annotate.final
@annotate.autoid("sequential")
class MotorCmd_(idl.IdlStruct, typename="unitree_hg.msg.dds_.MotorCmd_"):
    mode: types.uint8 = 0
    q: types.float32 = 0.0
    dq: types.float32 = 0.0
    tau: types.float32 = 0.0
    kp: types.float32 = 0.0
    kd: types.float32 = 0.0
    reserve: types.uint32 = 0


@dataclass
@annotate.final
@annotate.autoid("sequential")
class MotorState_(idl.IdlStruct, typename="unitree_hg.msg.dds_.MotorState_"):
    mode: types.uint8 = 0
    q: types.float32 = 0.0
    dq: types.float32 = 0.0
    ddq: types.float32 = 0.0
    tau_est: types.float32 = 0.0
    temperature: types.array[types.int16, 2] = field(default_factory=lambda: [0, 0])
    vol: types.float32 = 0.0
    sensor: types.array[types.uint32, 2] = field(default_factory=lambda: [0, 0])
    motorstate: types.uint32 = 0
    reserve: types.array[types.uint32, 4] = field(default_factory=lambda: [0] * 4)


@dataclass
@annotate.final
@annotate.autoid("sequential")
class IMUState_(idl.IdlStruct, typename="unitree_hg.msg.dds_.IMUState_"):
    quaternion: types.array[types.float32, 4] = field(default_factory=lambda: [1.0, 0.0, 0.0, 0.0])  # wxyz
    gyroscope: types.array[types.float32, 3] = field(default_factory=lambda: [0.0] * 3)  # rad/s, body
    accelerometer: types.array[types.float32, 3] = field(default_factory=lambda: [0.0] * 3)  # m/s², body
    rpy: types.array[types.float32, 3] = field(default_factory=lambda: [0.0] * 3)  # rad
    temperature: types.int16 = 0


@dataclass
@annotate.final
@annotate.autoid("sequential")
class LowCmd_(idl.IdlStruct, typename="unitree_hg.msg.dds_.LowCmd_"):
    mode_pr: types.uint8 = 0
    mode_machine: types.uint8 = 0
    motor_cmd: types.array[MotorCmd_, 35] = field(default_factory=lambda: [MotorCmd_() for _ in range(NUM_MOTORS)])
    reserve: types.array[types.uint32, 4] = field(default_factory=lambda: [0] * 4)
    crc: types.uint32 = 0

    def serialize(self, buffer=None, endianness=None, use_version_2=None) -> bytes:
        """The XCDR1 little-endian sample in one ``struct`` call, as ``LowState_.serialize``:
        CycloneDDS's field-by-field serializer took ~0.55 ms of the runner's cycle (the largest
        single part of it). Same bytes (``tests/agents/deploy/test_deploy_messages.py``); other
        encodings take CycloneDDS's way."""
        if buffer is None and not use_version_2 and (endianness or Endianness.native()) == Endianness.Little:
            return _LOWCMD_XCDR1.pack(_XCDR1_LITTLE_ENDIAN, *low_cmd_fields(self))
        return super().serialize(buffer=buffer, endianness=endianness, use_version_2=use_version_2)

    @classmethod
    def deserialize(cls, data: bytes, has_header: bool = True, use_version_2: bool | None = None) -> "LowCmd_":
        """The inverse of ``serialize``'s fast path (the sim robot reads each LowCmd); other
        encodings take CycloneDDS's way."""
        if has_header and not use_version_2 and len(data) >= _LOWCMD_XCDR1.size \
                and bytes(data[:2]) == _XCDR1_LITTLE_ENDIAN[:2]:
            v = _LOWCMD_XCDR1.unpack_from(data)[1:]
            motors = [MotorCmd_(*v[k:k + 7]) for k in range(2, 2 + 7 * NUM_MOTORS, 7)]
            tail = 2 + 7 * NUM_MOTORS
            return LowCmd_(v[0], v[1], motors, list(v[tail:tail + 4]), v[tail + 4])
        return super().deserialize(data, has_header=has_header, use_version_2=use_version_2)


def low_cmd_fields(msg: LowCmd_) -> list:
    """Every primitive of a LowCmd_ in declaration order (what both byte layouts pack)."""
    values: list = [msg.mode_pr, msg.mode_machine]
    for m in msg.motor_cmd:
        values += (m.mode, m.q, m.dq, m.tau, m.kp, m.kd, m.reserve)
    values += (*msg.reserve, msg.crc)
    return values


@dataclass
@annotate.final
@annotate.autoid("sequential")
class LowState_(idl.IdlStruct, typename="unitree_hg.msg.dds_.LowState_"):
    version: types.array[types.uint32, 2] = field(default_factory=lambda: [0, 0])
    mode_pr: types.uint8 = 0
    mode_machine: types.uint8 = 0
    tick: types.uint32 = 0  # ms
    imu_state: IMUState_ = field(default_factory=IMUState_)
    motor_state: types.array[MotorState_, 35] = field(
        default_factory=lambda: [MotorState_() for _ in range(NUM_MOTORS)])
    wireless_remote: types.array[types.uint8, 40] = field(default_factory=lambda: [0] * WIRELESS_REMOTE_BYTES)
    reserve: types.array[types.uint32, 4] = field(default_factory=lambda: [0] * 4)
    crc: types.uint32 = 0

    def serialize(self, buffer=None, endianness=None, use_version_2=None) -> bytes:
        """The XCDR1 little-endian sample in one ``struct`` call: CycloneDDS's serializer walks the
        35 motor records field by field in Python (~1 ms a message on a 2.5 GHz Xeon, half of
        a 500 Hz physics step). Same bytes (``tests/test_deploy_messages.py``); other encodings
        take CycloneDDS's way."""
        if buffer is None and not use_version_2 and (endianness or Endianness.native()) == Endianness.Little:
            return _LOWSTATE_XCDR1.pack(_XCDR1_LITTLE_ENDIAN, *low_state_fields(self))
        return super().serialize(buffer=buffer, endianness=endianness, use_version_2=use_version_2)

    @classmethod
    def deserialize(cls, data: bytes, has_header: bool = True, use_version_2: bool | None = None) -> "LowState_":
        """The inverse of ``serialize``'s fast path for a little-endian XCDR1 sample (what the
        G1 and ``otr sim-robot`` send): one ``struct`` call instead of CycloneDDS's field-by-field
        walk, which cost ~0.4 ms of the runner's 20 ms cycle. Same object (``tests/agents/deploy/
        test_deploy_messages.py``); other encodings take CycloneDDS's way."""
        if has_header and not use_version_2 and len(data) >= _LOWSTATE_XCDR1.size \
                and bytes(data[:2]) == _XCDR1_LITTLE_ENDIAN[:2]:
            return low_state_from_fields(_LOWSTATE_XCDR1.unpack_from(data)[1:])
        return super().deserialize(data, has_header=has_header, use_version_2=use_version_2)


def low_state_from_fields(v: tuple) -> LowState_:
    """The LowState_ of ``low_state_fields``'s values (the inverse)."""
    motors = [MotorState_(v[k], v[k + 1], v[k + 2], v[k + 3], v[k + 4], [v[k + 5], v[k + 6]], v[k + 7],
                          [v[k + 8], v[k + 9]], v[k + 10], [v[k + 11], v[k + 12], v[k + 13], v[k + 14]])
              for k in range(19, 19 + 15 * NUM_MOTORS, 15)]
    tail = 19 + 15 * NUM_MOTORS
    imu = IMUState_(list(v[5:9]), list(v[9:12]), list(v[12:15]), list(v[15:18]), v[18])
    # uint8 arrays as bytes, as CycloneDDS's deserializer gives them
    return LowState_([v[0], v[1]], v[2], v[3], v[4], imu, motors, bytes(v[tail:tail + WIRELESS_REMOTE_BYTES]),
                     list(v[tail + WIRELESS_REMOTE_BYTES:tail + WIRELESS_REMOTE_BYTES + 4]), v[-1])


def low_state_fields(msg: LowState_) -> list:
    """Every primitive of a LowState_ in declaration order (what both byte layouts pack)."""
    imu = msg.imu_state
    values: list = [*msg.version, msg.mode_pr, msg.mode_machine, msg.tick,
                    *imu.quaternion, *imu.gyroscope, *imu.accelerometer, *imu.rpy, imu.temperature]
    for m in msg.motor_state:
        values += (m.mode, m.q, m.dq, m.ddq, m.tau_est, *m.temperature, m.vol, *m.sensor, m.motorstate, *m.reserve)
    values += (*msg.wireless_remote, *msg.reserve, msg.crc)
    return values


#: The wire layout: the encapsulation header (CDR, little endian), then each field at its own
#: alignment counted from after the header. Unlike the C struct (``crc.LOWSTATE_FORMAT``),
#: IMUState_ gets no tail padding, so the first motor record's uint8 ``mode`` sits at offset 70
#: and one pad byte aligns its ``q``; every later record starts 4-aligned (three pad bytes).
_XCDR1_LITTLE_ENDIAN = b"\x00\x01\x00\x00"
_LOWSTATE_XCDR1 = struct.Struct("<4s2I2B2xI13fh" + "Bx4f2hf7I" + "B3x4f2hf7I" * (NUM_MOTORS - 1) + "40B5I")
#: LowCmd_ the same way: the first motor record's ``mode`` at offset 2 takes one pad byte.
_LOWCMD_XCDR1 = struct.Struct("<4s2B" + "Bx5fI" + "B3x5fI" * (NUM_MOTORS - 1) + "5I")
LOWSTATE_XCDR1 = _LOWSTATE_XCDR1  # public: crc.py reads the wire layout of each field from it

#: What the runner reads of a LowState, as a NumPy view of the XCDR1 little-endian bytes (offsets
#: with the header): every motor record's float part sits on a 56-byte stride from the first
#: ``q`` (the first record's one pad byte and the later records' three put each ``q`` 4 bytes
#: after its ``mode``), so one strided field reads all 35.
_MOTOR_RECORD = struct.calcsize("<B3x4f2hf7I")
_MOTOR_Q = struct.calcsize("<4s2I2B2xI13fhBx")
LOWSTATE_XCDR1_DTYPE = np.dtype({
    "names": ["mode_machine", "tick", "imu", "motor", "wireless_remote", "crc"],
    "formats": ["u1", "<u4", ("<f4", (13,)),
                (np.dtype({"names": ["q", "dq"], "formats": ["<f4", "<f4"], "offsets": [0, 4],
                           "itemsize": _MOTOR_RECORD}), (NUM_MOTORS,)),
                ("u1", (WIRELESS_REMOTE_BYTES,)), "<u4"],
    "offsets": [struct.calcsize("<4s2IB"), struct.calcsize("<4s2I2B2x"), struct.calcsize("<4s2I2B2xI"), _MOTOR_Q,
                _LOWSTATE_XCDR1.size - WIRELESS_REMOTE_BYTES - 20, _LOWSTATE_XCDR1.size - 4],
    "itemsize": _LOWSTATE_XCDR1.size,
})


def is_low_state_xcdr1(data: bytes) -> bool:
    """Whether ``data`` is a LowState sample in the layout the fast paths read (XCDR1, little endian)."""
    return len(data) >= _LOWSTATE_XCDR1.size and bytes(data[:2]) == _XCDR1_LITTLE_ENDIAN[:2]


# ------------------------------------------------------------------ NumPy views


@dataclass(frozen=True)
class JointCommand:
    """One LowCmd in policy joint order (29,) each: PD targets and gains, feed-forward torque."""

    q: np.ndarray  # rad
    dq: np.ndarray  # rad/s
    kp: np.ndarray  # N·m/rad
    kd: np.ndarray  # N·m·s/rad
    tau: np.ndarray  # N·m

    def as_array(self) -> np.ndarray:
        """(5, 29): q, dq, kp, kd, tau (the log's layout)."""
        return np.stack([self.q, self.dq, self.kp, self.kd, self.tau])


@dataclass(frozen=True)
class RobotState:
    """What a LowState says about the robot, in policy joint order; float64."""

    joint_pos: np.ndarray  # (29,) rad
    joint_vel: np.ndarray  # (29,) rad/s
    quat_wxyz: np.ndarray  # (4,) pelvis IMU orientation
    gyro_b: np.ndarray  # (3,) rad/s, pelvis frame
    accel_b: np.ndarray  # (3,) m/s², pelvis frame
    tick_ms: int
    mode_machine: int
    remote_keys: int  # 16 button bits of the wireless remote (see REMOTE_KEYS)

    def is_finite(self) -> bool:
        return bool(np.isfinite(self.joint_pos).all() and np.isfinite(self.joint_vel).all()
                    and np.isfinite(self.quat_wxyz).all() and np.isfinite(self.gyro_b).all())


#: Button bits of the 16-bit key field of the wireless remote (bytes 2..3 of ``wireless_remote``,
#: little-endian), as in Unitree SDK2's gamepad key union.
REMOTE_KEYS = {name: 1 << i for i, name in enumerate(
    ("R1", "L1", "start", "select", "R2", "L2", "F1", "F2", "A", "B", "X", "Y", "up", "right", "down", "left"))}


def low_cmd(command: JointCommand, mode_machine: int) -> LowCmd_:
    """A LowCmd_ (CRC not yet set) driving motors 0..28 with ``command``; slots 29..34 disabled."""
    motors = [MotorCmd_() for _ in range(NUM_MOTORS)]
    for j, slot in enumerate(robot.MOTOR_INDEX):
        motors[slot] = MotorCmd_(mode=MOTOR_MODE_ENABLE, q=float(command.q[j]), dq=float(command.dq[j]),
                                 tau=float(command.tau[j]), kp=float(command.kp[j]), kd=float(command.kd[j]))
    return LowCmd_(mode_pr=MODE_PR, mode_machine=int(mode_machine), motor_cmd=motors)


def joint_command(msg: LowCmd_) -> JointCommand:
    """The policy-order arrays of a LowCmd_ (float64)."""
    m = [msg.motor_cmd[slot] for slot in robot.MOTOR_INDEX]
    return JointCommand(q=np.array([c.q for c in m]), dq=np.array([c.dq for c in m]),
                        kp=np.array([c.kp for c in m]), kd=np.array([c.kd for c in m]),
                        tau=np.array([c.tau for c in m]))


def robot_state(msg: LowState_) -> RobotState:
    """The policy-order arrays of a LowState_."""
    m = [msg.motor_state[slot] for slot in robot.MOTOR_INDEX]
    remote = msg.wireless_remote
    return RobotState(
        joint_pos=np.array([s.q for s in m]), joint_vel=np.array([s.dq for s in m]),
        quat_wxyz=np.array(msg.imu_state.quaternion, dtype=np.float64),
        gyro_b=np.array(msg.imu_state.gyroscope, dtype=np.float64),
        accel_b=np.array(msg.imu_state.accelerometer, dtype=np.float64),
        tick_ms=int(msg.tick), mode_machine=int(msg.mode_machine),
        remote_keys=int(remote[2]) | (int(remote[3]) << 8))


def robot_state_from_cdr(data: bytes) -> RobotState:
    """``robot_state(LowState_.deserialize(data))`` read straight from the sample's bytes (one
    NumPy view, no message object: 35 motor records and their lists cost ~0.1 ms a cycle in
    Python); ``data`` must be XCDR1 little endian (``is_low_state_xcdr1``). Equal field for field
    (``tests/agents/deploy/test_deploy_messages.py``)."""
    rec = np.frombuffer(data, LOWSTATE_XCDR1_DTYPE, count=1)[0]
    motor, imu, remote = rec["motor"], rec["imu"].astype(np.float64), rec["wireless_remote"]
    return RobotState(
        joint_pos=motor["q"][robot.MOTOR_INDEX].astype(np.float64),
        joint_vel=motor["dq"][robot.MOTOR_INDEX].astype(np.float64),
        quat_wxyz=imu[0:4], gyro_b=imu[4:7], accel_b=imu[7:10],
        tick_ms=int(rec["tick"]), mode_machine=int(rec["mode_machine"]),
        remote_keys=int(remote[2]) | (int(remote[3]) << 8))


def remote_bytes(keys: int) -> list[int]:
    """A 40-byte ``wireless_remote`` field with the given key bits set (sticks centred)."""
    out = [0] * WIRELESS_REMOTE_BYTES
    out[2], out[3] = keys & 0xFF, (keys >> 8) & 0xFF
    return out
