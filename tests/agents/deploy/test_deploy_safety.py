"""Every stage change of the deployment controller, driven with synthetic LowStates (no DDS)."""

from __future__ import annotations

import numpy as np
import pytest

from agents.deploy.controller import KEY_ESTOP, KEY_START, KEY_STOP, Controller, ControllerCfg, CycleInput
from agents.deploy.messages import REMOTE_KEYS, RobotState
from agents.deploy.observation import ObservationBuilder, PolicySpec
from agents.deploy.reference_policy import training_metadata
from agents.deploy.safety import STARTUP_KD, STARTUP_KP, SafetyCfg, Stage
from agents.procedural import standing_reference
from otr_gym import robot
from otr_gym.rotations import quat_from_euler_xyz, quat_from_yaw

DT = 0.02


@pytest.fixture(scope="module")
def stand(tmp_path_factory):
    return standing_reference(duration_s=1.0).save(tmp_path_factory.mktemp("ref") / "stand.npz")


@pytest.fixture(scope="module")
def spec(stand):
    return PolicySpec.from_metadata(training_metadata(stand), "test-metadata")


def make(spec, stand, policy=None, **cfg):
    """A controller; without the hold → track blend and the end hold unless asked (the tests of
    the other stages start tracking on the start cycle and damp at the clip's end)."""
    safety = SafetyCfg(ramp_s=cfg.pop("ramp_s", 0.1), blend_s=cfg.pop("blend_s", 0.0),
                       end_hold_s=cfg.pop("end_hold_s", 0.0),
                       **{k: cfg.pop(k) for k in list(cfg) if k in ("stale_cycles", "tilt_limit_rad",
                                                                     "soft_limit_factor")})
    policy = policy or (lambda obs: np.zeros(29, np.float32))
    return Controller(spec, ObservationBuilder(spec, stand), policy, ControllerCfg(safety, **cfg))


def state(q=None, quat=(1.0, 0.0, 0.0, 0.0), keys=0) -> RobotState:
    return RobotState(joint_pos=robot.DEFAULT_JOINT_POS.copy() if q is None else np.asarray(q, float),
                      joint_vel=np.zeros(29), quat_wxyz=np.asarray(quat, float), gyro_b=np.zeros(3),
                      accel_b=np.array([0, 0, 9.81]), tick_ms=0, mode_machine=5, remote_keys=keys)


def run(c, n, t0=0.0, **kw):
    return [c.step(CycleInput(t_s=t0 + k * DT, state=kw.get("s", state()), keys=kw.get("keys", 0))) for k in range(n)]


def tracking(spec, stand, **kw):
    c = make(spec, stand, auto_start=True, **kw)
    run(c, 6)
    assert c.stage == Stage.TRACK
    return c


def test_nothing_is_sent_before_the_first_lowstate(spec, stand):
    c = make(spec, stand)
    out = c.step(CycleInput(t_s=0.0, state=None))
    assert out.stage == Stage.WAIT and out.command is None


def test_ramp_interpolates_from_the_measured_pose_with_the_startup_gains(spec, stand):
    c = make(spec, stand, ramp_s=1.0)
    q0 = robot.DEFAULT_JOINT_POS + 0.2
    first = c.step(CycleInput(0.0, state(q0)))
    half = c.step(CycleInput(0.5, state(q0)))
    assert first.stage == half.stage == Stage.RAMP
    np.testing.assert_allclose(first.command.q, q0)
    np.testing.assert_allclose(half.command.q, q0 - 0.1)
    np.testing.assert_array_equal(half.command.kp, STARTUP_KP)
    np.testing.assert_array_equal(half.command.kd, STARTUP_KD)
    done = c.step(CycleInput(1.0, state(q0)))
    assert done.stage == Stage.HOLD
    np.testing.assert_allclose(done.command.q, robot.DEFAULT_JOINT_POS)


def test_hold_waits_for_the_operator_then_tracks_with_the_policy_gains(spec, stand):
    c = make(spec, stand)
    outs = run(c, 30)
    assert outs[-1].stage == Stage.HOLD  # no start, no tracking
    out = c.step(CycleInput(1.0, state(), keys=KEY_START))
    assert out.stage == Stage.TRACK and out.frame == 1
    np.testing.assert_array_equal(out.command.kp, spec.kp)
    assert [t.reason for t in c.stages.transitions] == ["state", "ramp_done", "operator"]


def test_the_remote_start_button_starts_on_its_press(spec, stand):
    c = make(spec, stand)
    held = state(keys=REMOTE_KEYS["start"])
    run(c, 10, s=held)  # held since before HOLD: a press, not a level, starts
    assert c.stage == Stage.HOLD
    run(c, 1, t0=1.0)  # released
    out = c.step(CycleInput(1.1, held))
    assert out.stage == Stage.TRACK


@pytest.mark.parametrize("missing", [2, 3])
def test_stale_lowstate_damps_on_the_third_cycle_without_one(spec, stand, missing):
    c = tracking(spec, stand)
    outs = [c.step(CycleInput(1.0 + k * DT, None)) for k in range(missing)]
    if missing < 3:
        assert outs[-1].stage == Stage.TRACK
    else:
        assert outs[-1].stage == Stage.DAMP and c.stages.damp_reason == "stale_state"
        assert not outs[-1].command.kp.any() and outs[-1].command.kd.any()


def test_a_lowstate_with_a_bad_crc_damps(spec, stand):
    c = tracking(spec, stand)
    out = c.step(CycleInput(1.0, state(), crc_ok=False))
    assert out.stage == Stage.DAMP and c.stages.damp_reason == "bad_crc"


def test_a_lowstate_with_nan_damps(spec, stand):
    c = tracking(spec, stand)
    q = robot.DEFAULT_JOINT_POS.copy()
    q[5] = np.nan
    out = c.step(CycleInput(1.0, state(q)))
    assert out.stage == Stage.DAMP and c.stages.damp_reason == "nan_state"


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_a_nan_or_inf_action_damps_without_sending_it(spec, stand, bad):
    calls = []

    def policy(obs):
        calls.append(obs)
        a = np.zeros(29, np.float32)
        a[3] = bad if len(calls) > 2 else 0.0
        return a

    c = tracking(spec, stand, policy=policy)
    outs = run(c, 3, t0=1.0)
    assert outs[-1].stage == Stage.DAMP and c.stages.damp_reason == "nan_action"
    assert not outs[-1].command.kp.any() and np.isfinite(outs[-1].command.q).all()


def test_torso_tilt_beyond_the_limit_damps(spec, stand):
    c = tracking(spec, stand, tilt_limit_rad=0.5)
    out = c.step(CycleInput(1.0, state(quat=quat_from_euler_xyz(0.0, 0.45, 0.0))))
    assert out.stage == Stage.TRACK and out.tilt_rad == pytest.approx(0.45, abs=1e-6)
    out = c.step(CycleInput(1.02, state(quat=quat_from_euler_xyz(0.55, 0.0, 0.0))))
    assert out.stage == Stage.DAMP and c.stages.damp_reason == "tilt"


@pytest.mark.parametrize("how", ["keyboard", "remote"])
def test_the_estop_damps_from_any_stage(spec, stand, how):
    c = make(spec, stand)
    run(c, 2)
    assert c.stage == Stage.RAMP
    if how == "keyboard":
        out = c.step(CycleInput(0.1, state(), keys=KEY_ESTOP))
    else:
        out = c.step(CycleInput(0.1, state(keys=REMOTE_KEYS["select"])))
    assert out.stage == Stage.DAMP and c.stages.damp_reason == "estop"


def test_damping_is_latched(spec, stand):
    c = tracking(spec, stand)
    c.step(CycleInput(1.0, state(), keys=KEY_STOP))
    assert c.stages.damp_reason == "stop"
    outs = run(c, 5, t0=1.1, keys=KEY_START)
    assert all(o.stage == Stage.DAMP and not o.command.kp.any() for o in outs)


def test_clip_end_and_duration_damp(spec, stand):
    c = tracking(spec, stand)
    frames = c.builder.num_frames
    outs = run(c, frames, t0=1.0)
    assert [o.frame for o in outs[: frames - 2]] == list(range(2, frames))
    assert c.stage == Stage.DAMP and c.stages.damp_reason == "clip_end"
    d = tracking(spec, stand, duration_s=0.2)
    run(d, 15, t0=0.2)
    assert d.stages.damp_reason == "duration"


def test_joint_targets_are_clamped_to_the_soft_limits(spec, stand):
    c = tracking(spec, stand, policy=lambda obs: np.full(29, 1e3, np.float32))
    out = run(c, 1, t0=1.0)[0]
    lower, upper = robot.soft_joint_limits(0.9)
    assert (out.command.q <= upper + 1e-12).all() and (out.command.q >= lower - 1e-12).all()
    np.testing.assert_allclose(out.command.q, upper)


def test_yaw_is_aligned_at_policy_start(spec, stand):
    """A robot facing 90° away from the clip sees the same observation as one facing along it."""
    seen = {}
    for yaw in (0.0, np.pi / 2):
        obs = []
        c = make(spec, stand, auto_start=True,
                 policy=lambda o, obs=obs: (obs.append(o), np.zeros(29, np.float32))[1])
        run(c, 8, s=state(quat=quat_from_yaw(np.float64(yaw))))
        seen[yaw] = obs[-1]
        assert c.builder.mpjpe_m(c.builder.tracking_state(state(quat=quat_from_yaw(np.float64(yaw))), 2,
                                                          np.zeros(29))) < 1e-3
    np.testing.assert_allclose(seen[0.0], seen[np.pi / 2], atol=1e-5)


@pytest.fixture(scope="module")
def bent(tmp_path_factory):
    """A clip whose every frame bends the knees and arms away from the default pose."""
    from otr_gym.reference import Reference

    qpos = np.tile(robot.default_qpos(), (50, 1))
    qpos[:, 7:] += np.where(np.arange(29) % 3 == 0, 0.3, -0.1)
    return Reference.from_qpos(qpos, 50.0).save(tmp_path_factory.mktemp("ref") / "bent.npz")


def test_the_start_blends_targets_and_gains_from_the_hold_to_the_first_frame(spec, bent):
    calls = []
    c = make(spec, bent, blend_s=1.0, policy=lambda obs: (calls.append(1), np.zeros(29, np.float32))[1])
    run(c, 10)
    assert c.stage == Stage.HOLD
    first = c.builder.reference_joint_pos(0)
    lower, upper = robot.soft_joint_limits(0.9)
    start = c.step(CycleInput(1.0, state(), keys=KEY_START))
    assert start.stage == Stage.BLEND and start.frame == -1
    np.testing.assert_allclose(start.command.q, robot.DEFAULT_JOINT_POS)
    np.testing.assert_allclose(start.command.kp, STARTUP_KP)
    half = c.step(CycleInput(1.5, state()))  # smoothstep(0.5) = 0.5: half way, targets and gains
    np.testing.assert_allclose(half.command.q, np.clip((robot.DEFAULT_JOINT_POS + first) / 2, lower, upper))
    np.testing.assert_allclose(half.command.kp, (STARTUP_KP + spec.kp) / 2)
    np.testing.assert_allclose(half.command.kd, (STARTUP_KD + spec.kd) / 2)
    late = c.step(CycleInput(1.9, state()))
    late_q = robot.DEFAULT_JOINT_POS + 0.972 * (first - robot.DEFAULT_JOINT_POS)  # smoothstep(0.9)
    np.testing.assert_allclose(late.command.q, np.clip(late_q, lower, upper))
    assert not calls  # the policy is not run while blending
    out = c.step(CycleInput(2.0, state()))
    assert out.stage == Stage.TRACK and out.frame == 1 and calls
    np.testing.assert_array_equal(out.command.kp, spec.kp)
    assert [t.reason for t in c.stages.transitions] == ["state", "ramp_done", "operator", "blend_done"]


def test_the_clip_end_holds_the_last_frame_then_damps(spec, bent):
    c = make(spec, bent, auto_start=True, end_hold_s=0.5)
    outs = run(c, 6 + c.builder.num_frames + 40)
    end = [o for o in outs if o.stage == Stage.END]
    assert len(end) == 25  # 0.5 s at 50 Hz
    lower, upper = robot.soft_joint_limits(0.9)
    for o in end:
        np.testing.assert_allclose(o.command.q, np.clip(c.builder.reference_joint_pos(-1), lower, upper))
        np.testing.assert_array_equal(o.command.kp, spec.kp)
    assert c.stage == Stage.DAMP and c.stages.damp_reason == "clip_end"
    assert [(t.source, t.target) for t in c.stages.transitions][-2:] == [(Stage.TRACK, Stage.END),
                                                                        (Stage.END, Stage.DAMP)]


@pytest.mark.parametrize("name", ["blend_s", "end_hold_s"])
def test_a_negative_blend_or_end_hold_is_refused(name):
    with pytest.raises(ValueError, match=name):
        SafetyCfg(**{name: -0.5})
