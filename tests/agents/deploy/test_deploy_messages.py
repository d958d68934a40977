"""The unitree_hg messages and CRC are Unitree SDK2's, byte for byte.

Reference values were produced with Unitree's own Python SDK (``unitree_sdk2py``, the hg IDL
and ``utils/crc.py`` of ``unitree_sdk2`` 1.0.1, run through CycloneDDS 11): the CRCs by its
``CRC().Crc(msg)`` (its compiled ``crc_amd64.so``), the digests of the CDR bytes by its IDL
types' ``serialize()``, on the deterministic messages ``golden_low_cmd``/``golden_low_state``.
When the SDK is importable the comparison also runs live on random messages.
"""

from __future__ import annotations

import dataclasses
import hashlib

import numpy as np
import pytest
from cyclonedds.idl._type_normalize import get_extended_type_hints

from agents.deploy import crc
from agents.deploy import messages as m
from otr_gym import robot


def f32(x: float) -> float:
    return float(np.float32(x))


def golden_low_cmd() -> m.LowCmd_:
    msg = m.LowCmd_(mode_pr=0, mode_machine=5)
    for i in range(35):
        msg.motor_cmd[i] = m.MotorCmd_(mode=1 if i < 29 else 0, q=f32(0.01 * i), dq=f32(-0.002 * i),
                                       tau=f32(0.5 - 0.03 * i), kp=f32(10.0 + i), kd=f32(0.1 * i), reserve=0)
    return msg


def golden_low_state() -> m.LowState_:
    msg = m.LowState_(version=[1, 2], mode_pr=0, mode_machine=5, tick=123456)
    msg.imu_state = m.IMUState_(quaternion=[f32(0.9), f32(0.1), f32(-0.2), f32(0.3)],
                                gyroscope=[f32(0.01), f32(-0.02), f32(0.03)],
                                accelerometer=[f32(0.1), f32(0.2), f32(9.8)],
                                rpy=[f32(0.1), f32(-0.1), f32(0.2)], temperature=40)
    for i in range(35):
        msg.motor_state[i] = m.MotorState_(mode=1, q=f32(0.02 * i), dq=f32(0.1 - 0.01 * i), ddq=0.0,
                                           tau_est=f32(-0.4 + 0.05 * i), temperature=[30 + i, 31 + i], vol=f32(48.0),
                                           sensor=[i, 2 * i], motorstate=0, reserve=[0, 0, 0, 0])
    msg.wireless_remote = list(range(40))
    return msg


# Unitree SDK2's IDL (unitree_hg/msg/dds_): field, CDR type, array length (0 = scalar)
SDK_LAYOUT = {
    m.MotorCmd_: ("unitree_hg.msg.dds_.MotorCmd_", [("mode", "uint8", 0), ("q", "float32", 0), ("dq", "float32", 0),
                                                    ("tau", "float32", 0), ("kp", "float32", 0), ("kd", "float32", 0),
                                                    ("reserve", "uint32", 0)]),
    m.MotorState_: ("unitree_hg.msg.dds_.MotorState_", [
        ("mode", "uint8", 0), ("q", "float32", 0), ("dq", "float32", 0), ("ddq", "float32", 0),
        ("tau_est", "float32", 0), ("temperature", "int16", 2), ("vol", "float32", 0), ("sensor", "uint32", 2),
        ("motorstate", "uint32", 0), ("reserve", "uint32", 4)]),
    m.IMUState_: ("unitree_hg.msg.dds_.IMUState_", [
        ("quaternion", "float32", 4), ("gyroscope", "float32", 3), ("accelerometer", "float32", 3),
        ("rpy", "float32", 3), ("temperature", "int16", 0)]),
    m.LowCmd_: ("unitree_hg.msg.dds_.LowCmd_", [
        ("mode_pr", "uint8", 0), ("mode_machine", "uint8", 0), ("motor_cmd", "MotorCmd_", 35),
        ("reserve", "uint32", 4), ("crc", "uint32", 0)]),
    m.LowState_: ("unitree_hg.msg.dds_.LowState_", [
        ("version", "uint32", 2), ("mode_pr", "uint8", 0), ("mode_machine", "uint8", 0), ("tick", "uint32", 0),
        ("imu_state", "IMUState_", 0), ("motor_state", "MotorState_", 35), ("wireless_remote", "uint8", 40),
        ("reserve", "uint32", 4), ("crc", "uint32", 0)]),
}


def _describe(hint) -> tuple[str, int]:
    """(type name, array length or 0) of an extended type hint."""
    from cyclonedds.idl.types import array

    if isinstance(hint, array):
        return _name(hint.subtype), hint.length
    return _name(hint), 0


def _name(hint) -> str:
    meta = getattr(hint, "__metadata__", None)
    if meta and isinstance(meta[0], str):  # Annotated[int, 'uint8']
        return meta[0]
    return hint.__name__  # a nested IDL struct


@pytest.mark.parametrize("cls", list(SDK_LAYOUT), ids=lambda c: c.__name__)
def test_type_names_field_order_types_and_array_sizes_match_the_sdk_idl(cls):
    typename, fields = SDK_LAYOUT[cls]
    assert cls.__idl_typename__ == typename
    got = [(name, *_describe(hint)) for name, hint in get_extended_type_hints(cls).items()]
    assert got == fields


def test_cdr_bytes_equal_the_sdk_serialisation():
    cmd, state = golden_low_cmd().serialize(), golden_low_state().serialize()
    assert len(cmd) == 1004 and len(state) == 2092
    assert hashlib.sha256(cmd).hexdigest() == "32a044ec669e33e5f7ef174911f68947133d69b25ac5d5476e62aabdb2584c20"
    assert hashlib.sha256(state).hexdigest() == "6a1cbcce7461a5a2d6e16622ea652137ce807d1070864e33273a686c8e770520"
    assert m.LowState_.deserialize(state).serialize() == state


def random_low_state(rng: np.random.Generator) -> m.LowState_:
    """A LowState_ with random values over every field's range."""
    msg = m.LowState_(version=rng.integers(0, 2**32, 2).tolist(), mode_pr=int(rng.integers(0, 256)),
                      mode_machine=int(rng.integers(0, 256)), tick=int(rng.integers(0, 2**32)),
                      wireless_remote=rng.integers(0, 256, 40).tolist(), reserve=rng.integers(0, 2**32, 4).tolist(),
                      crc=int(rng.integers(0, 2**32)))
    msg.imu_state = m.IMUState_(*(rng.normal(size=n).astype(np.float32).tolist() for n in (4, 3, 3, 3)),
                                temperature=int(rng.integers(-2**15, 2**15)))
    for i in range(35):
        msg.motor_state[i] = m.MotorState_(
            int(rng.integers(0, 256)), *rng.normal(size=4).astype(np.float32).tolist(),
            rng.integers(-2**15, 2**15, 2).tolist(), float(np.float32(rng.normal())),
            rng.integers(0, 2**32, 2).tolist(), int(rng.integers(0, 2**32)), rng.integers(0, 2**32, 4).tolist())
    return msg


def test_the_one_call_lowstate_serialiser_writes_cyclonedds_bytes():
    """LowState_.serialize packs the sample in one struct call (it is published at 500 Hz) and
    LowState_.deserialize unpacks it in one (the runner reads one every 20 ms cycle);
    random values over every field's range give CycloneDDS's own bytes, and the encodings it
    does not cover (XCDR2, big endian) are CycloneDDS's."""
    from cyclonedds.idl import Endianness

    rng = np.random.default_rng(3)
    for _ in range(20):
        msg = random_low_state(rng)
        generic = m.LowState_.__idl__.serialize(msg)
        assert msg.serialize() == generic
        assert m.LowState_.deserialize(generic).serialize() == generic  # uint8 arrays come back as bytes
        # the one-call deserialiser gives CycloneDDS's own object, field for field
        assert m.LowState_.deserialize(generic) == m.LowState_.__idl__.deserialize(generic, has_header=True)
        big = m.LowState_.__idl__.serialize(msg, endianness=Endianness.Big)
        assert m.LowState_.deserialize(big) == m.LowState_.__idl__.deserialize(big, has_header=True)
        assert msg.serialize(use_version_2=True) == m.LowState_.__idl__.serialize(msg, use_version_2=True)
        assert msg.serialize(endianness=Endianness.Big) == m.LowState_.__idl__.serialize(msg, endianness=Endianness.Big)
    assert msg.serialize(use_version_2=True) != generic


def test_the_one_call_lowcmd_serialiser_writes_cyclonedds_bytes():
    """LowCmd_.serialize and .deserialize in one struct call each (the runner writes one every
    cycle, the sim robot reads it): CycloneDDS's own bytes and object on random values over every
    field's range; XCDR2 and big endian go CycloneDDS's way."""
    from cyclonedds.idl import Endianness

    rng = np.random.default_rng(5)
    for _ in range(20):
        motors = [m.MotorCmd_(int(rng.integers(0, 256)), *rng.normal(size=5).astype(np.float32).tolist(),
                              int(rng.integers(0, 2**32))) for _ in range(35)]
        msg = m.LowCmd_(mode_pr=int(rng.integers(0, 256)), mode_machine=int(rng.integers(0, 256)), motor_cmd=motors,
                        reserve=rng.integers(0, 2**32, 4).tolist(), crc=int(rng.integers(0, 2**32)))
        generic = m.LowCmd_.__idl__.serialize(msg)
        assert msg.serialize() == generic
        assert m.LowCmd_.deserialize(generic) == m.LowCmd_.__idl__.deserialize(generic, has_header=True) == msg
        big = m.LowCmd_.__idl__.serialize(msg, endianness=Endianness.Big)
        assert m.LowCmd_.deserialize(big) == msg
        assert msg.serialize(use_version_2=True) == m.LowCmd_.__idl__.serialize(msg, use_version_2=True)
        assert msg.serialize(endianness=Endianness.Big) == big


def test_the_runner_reads_a_lowstate_from_its_bytes_as_from_the_message():
    """``runner.read_low_state`` (a NumPy view of the wire bytes and the CRC from them, no
    LowState_ object) equals ``robot_state`` and ``crc_ok`` of the deserialised message on the
    sim robot's real LowStates (remote keys set, CRC good and corrupted), on random samples
    over every field's range, and through the fallback for big-endian bytes."""
    from cyclonedds.idl import Endianness

    from agents.deploy.runner import read_low_state
    from agents.deploy.sim_robot import SimRobot, SimRobotCfg

    def old_way(data: bytes) -> tuple[m.RobotState, bool]:
        msg = m.LowState_.__idl__.deserialize(data, has_header=True)  # CycloneDDS's own object
        return m.robot_state(msg), crc.crc_ok(msg)

    def assert_same(a: tuple[m.RobotState, bool], b: tuple[m.RobotState, bool]) -> None:
        assert a[1] == b[1]
        for f in dataclasses.fields(m.RobotState):
            x, y = getattr(a[0], f.name), getattr(b[0], f.name)
            assert type(x) is type(y) and np.array_equal(x, y, equal_nan=True), f.name
            assert getattr(x, "dtype", None) == getattr(y, "dtype", None), f.name

    sim = SimRobot(SimRobotCfg())
    samples = []
    for k in range(40):
        sim.step(None)
        msg = sim.low_state()
        msg.wireless_remote = m.remote_bytes(k * 977 % 65536)
        samples.append(crc.with_crc(msg).serialize())
    rng = np.random.default_rng(7)
    for data in list(samples):
        assert read_low_state(data)[1]
        for _ in range(3):  # one flipped bit anywhere but the pads
            bad = bytearray(data)
            bad[int(rng.integers(4, len(bad)))] ^= 1 << int(rng.integers(0, 8))
            samples.append(bytes(bad))
    msg = m.LowState_.deserialize(samples[0])
    msg.motor_state[3].q = float("nan")
    samples.append(crc.with_crc(msg).serialize())
    for _ in range(20):
        msg = random_low_state(rng)
        samples += [msg.serialize(), crc.with_crc(msg).serialize()]  # a random CRC, then the right one
    for data in samples:
        assert_same(read_low_state(data), old_way(data))
    big = m.LowState_.__idl__.serialize(m.LowState_.deserialize(samples[0]), endianness=Endianness.Big)
    assert_same(read_low_state(big), old_way(samples[0]))


def test_crc_equals_the_sdk_values():
    assert crc.low_cmd_crc(golden_low_cmd()) == 0x24BDF568
    assert crc.low_state_crc(golden_low_state()) == 0x099EDA2F
    assert crc.low_cmd_crc(m.LowCmd_()) == 0xFE172F9F  # all-zero LowCmd


def test_packed_layouts_are_the_sdk_c_structs():
    assert crc.LOWCMD_PACKED_BYTES == 1004 and crc.LOWSTATE_PACKED_BYTES == 2092
    packed = crc.pack_low_cmd(golden_low_cmd())
    # motor 3's q sits at 4 + 3·28 + 4 in the C struct (not where CDR puts it)
    assert np.frombuffer(packed, "<f4", count=1, offset=4 + 3 * 28 + 4)[0] == np.float32(0.03)


def test_fast_crc_equals_the_bit_by_bit_definition():
    rng = np.random.default_rng(1)
    for n in (1, 7, 250, 522):
        words = rng.integers(0, 2**32, n, dtype=np.uint64).astype("<u4")
        assert crc.crc32_words(words.tobytes()) == crc.crc32_reference(words.tolist())
    with pytest.raises(ValueError, match="whole 32-bit words"):
        crc.crc32_words(b"abc")


def test_with_crc_and_crc_ok_detect_a_flipped_bit():
    msg = crc.with_crc(golden_low_cmd())
    assert crc.crc_ok(msg)
    msg.motor_cmd[7].kp = f32(msg.motor_cmd[7].kp + 1.0)
    assert not crc.crc_ok(msg)
    state = crc.with_crc(golden_low_state())
    assert crc.crc_ok(m.LowState_.deserialize(state.serialize()))


def test_low_cmd_puts_policy_joints_on_motors_0_to_28_and_reads_back():
    q = np.linspace(-1, 1, 29)
    cmd = m.JointCommand(q=q, dq=q * 0.1, kp=robot.KP, kd=robot.KD, tau=np.zeros(29))
    msg = m.low_cmd(cmd, mode_machine=5)
    assert msg.mode_pr == 0 and msg.mode_machine == 5
    assert [c.mode for c in msg.motor_cmd] == [1] * 29 + [0] * 6
    back = m.joint_command(m.LowCmd_.deserialize(crc.with_crc(msg).serialize()))
    np.testing.assert_allclose(back.q, q, atol=1e-7)
    np.testing.assert_allclose(back.kp, robot.KP, rtol=1e-6)


def test_robot_state_reads_joints_imu_and_remote_buttons():
    msg = golden_low_state()
    msg.wireless_remote = m.remote_bytes(m.REMOTE_KEYS["start"] | m.REMOTE_KEYS["A"])
    s = m.robot_state(msg)
    assert s.joint_pos.shape == (29,) and s.joint_pos[3] == pytest.approx(0.06)
    np.testing.assert_allclose(s.quat_wxyz, [0.9, 0.1, -0.2, 0.3], atol=1e-7)
    assert s.tick_ms == 123456 and s.mode_machine == 5
    assert s.remote_keys == (1 << 2) | (1 << 8)
    # SDK's gamepad union: start = byte 2 bit 2, A = byte 3 bit 0
    assert msg.wireless_remote[2] == 0b100 and msg.wireless_remote[3] == 0b1
    msg.motor_state[4].dq = float("nan")
    assert not m.robot_state(msg).is_finite()


def _sdk():
    try:
        from unitree_sdk2py.idl.unitree_hg.msg import dds_ as sdk_hg
        from unitree_sdk2py.utils.crc import CRC
    except Exception as exc:  # the SDK is optional (see agents/deploy/messages.py)
        pytest.skip(f"unitree_sdk2py not importable here ({type(exc).__name__}); reference values above cover it")
    return sdk_hg, CRC()


def test_random_messages_match_the_sdk_live():
    sdk_hg, sdk_crc = _sdk()
    rng = np.random.default_rng(0)
    for _ in range(5):
        motors = [dict(mode=int(rng.integers(0, 256)), q=f32(rng.normal()), dq=f32(rng.normal()), tau=f32(rng.normal()),
                       kp=f32(rng.uniform(0, 400)), kd=f32(rng.uniform(0, 10)), reserve=int(rng.integers(0, 2**32)))
                  for _ in range(35)]
        ours = m.LowCmd_(mode_pr=0, mode_machine=5, motor_cmd=[m.MotorCmd_(**d) for d in motors])
        theirs = sdk_hg.LowCmd_(mode_pr=0, mode_machine=5, motor_cmd=[sdk_hg.MotorCmd_(**d) for d in motors],
                                reserve=[0] * 4, crc=0)
        assert ours.serialize() == theirs.serialize()
        assert crc.low_cmd_crc(ours) == sdk_crc.Crc(theirs)


def test_loopback_discovery_is_unicast_and_real_interfaces_use_the_sdk_configuration():
    from agents.deploy.dds import cyclonedds_config

    lo = cyclonedds_config("lo")
    assert '<NetworkInterface name="lo"' in lo and "<AllowMulticast>false</AllowMulticast>" in lo
    assert '<Peer address="127.0.0.1"/>' in lo and "<ParticipantIndex>auto</ParticipantIndex>" in lo
    eth = cyclonedds_config("eth0")
    assert '<NetworkInterface name="eth0"' in eth and "AllowMulticast" not in eth and "Peer" not in eth
    assert cyclonedds_config(None) is None
