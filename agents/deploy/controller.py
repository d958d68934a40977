"""One policy cycle of the deployment, without any I/O: inputs in, a LowCmd and a log row out.

The live runner (``agents.deploy.runner``) feeds it what DDS and the keyboard delivered; the
replay (``otr deploy --replay``) feeds it the same inputs read back from a log. Because the
controller is a deterministic function of its input sequence, a replay reproduces the
recorded actions exactly (same observation code, same ONNX session).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agents.deploy import safety
from agents.deploy.estimator import BaseStateEstimator
from agents.deploy.messages import REMOTE_KEYS, JointCommand, RobotState
from agents.deploy.mocap import BASE_BODY, MocapFrame, MocapTracker, MocapTrackerCfg
from agents.deploy.observation import BaseEstimate, ObjectEstimate, ObservationBuilder, PolicySpec, torso_tilt_rad
from agents.deploy.safety import DampReason, SafetyCfg, Stage, StageMachine
from otr_gym import robot

#: Operator key bits (keyboard events and the remote's buttons map onto these).
KEY_START = 1
KEY_ESTOP = 2
KEY_STOP = 4


@dataclass(frozen=True)
class CycleInput:
    t_s: float  # time since the runner started (steady clock), s
    state: RobotState | None  # the LowState taken this cycle; None when none arrived
    crc_ok: bool = True  # that LowState's CRC matched
    keys: int = 0  # KEY_* bits pressed on the keyboard since the last cycle
    mocap: MocapFrame | None = None  # the motion-capture frame taken this cycle (with ``--mocap``)


@dataclass
class CycleOutput:
    command: JointCommand | None  # None: send nothing (no state yet)
    stage: Stage
    frame: int  # target reference frame while tracking, else -1
    observation: np.ndarray | None
    action: np.ndarray | None  # raw policy output (before the clip)
    tilt_rad: float
    mpjpe_m: float
    ref_tilt_rad: float = float("nan")  # the reference's torso tilt on the frame the robot should be on
    #: (M,) m: each moving object's captured position from the aligned reference's (the frame the
    #: robot should be on; its last frame after tracking), once tracking has begun
    object_error_m: np.ndarray | None = None
    base: BaseEstimate | None = None  # the pelvis as the policy saw it (motion capture or the estimator)


@dataclass
class ControllerCfg:
    safety: SafetyCfg
    auto_start: bool = False  # track as soon as the ramp ends (sim2sim, tests)
    duration_s: float | None = None  # stop tracking after this long
    #: motion capture (``--mocap``): reference body name -> stream name where they differ; None: no mocap
    mocap_names: dict[str, str] | None = None
    #: the base state estimator (``--state-estimator``, ``agents.deploy.estimator``) gives the
    #: robot's world position and velocity while tracking, where motion capture does not
    state_estimator: bool = False


Policy = Callable[[np.ndarray], np.ndarray]  # (D,) float32 -> (29,)


def remote_keys_to_operator(keys: int) -> int:
    """Remote buttons → KEY_* bits: Start starts, Select is the e-stop."""
    out = 0
    if keys & REMOTE_KEYS["start"]:
        out |= KEY_START
    if keys & REMOTE_KEYS["select"]:
        out |= KEY_ESTOP
    return out


class Controller:
    def __init__(self, spec: PolicySpec, builder: ObservationBuilder, policy: Policy, cfg: ControllerCfg):
        self.spec, self.builder, self.policy, self.cfg = spec, builder, policy, cfg
        self.stages = StageMachine()
        self.cycle = -1
        self.state: RobotState | None = None
        self.cycles_without_state = 0
        self._ramp_q0: np.ndarray | None = None
        self._ramp_t0 = 0.0
        self._track_t0 = 0.0
        self._blend_t0 = 0.0
        self._end_t0 = 0.0
        self.frame = -1
        self.last_action = np.zeros(robot.NUM_JOINTS)
        self._remote_prev = 0
        self.fault_detail = ""  # the message of a damping fault that has more to say than its reason
        self.mocap = None if cfg.mocap_names is None else MocapTracker(self.mocap_cfg(builder, cfg))
        self._tracked = False  # tracking has begun (the clip is aligned to the robot)
        self.estimator = BaseStateEstimator() if cfg.state_estimator else None
        self._estimate: BaseEstimate | None = None  # the estimator's latest, while tracking
        self._estimated_at = 0.0

    @staticmethod
    def mocap_cfg(builder: ObservationBuilder, cfg: ControllerCfg) -> MocapTrackerCfg:
        """The bodies to follow: the pelvis and the reference's moving objects; those the policy
        reads are required."""
        objects = tuple(builder.objects.names) if builder.objects is not None else ()
        required = ((BASE_BODY,) if builder.needs_base else ()) + (objects if builder.needs_objects else ())
        return MocapTrackerCfg(bodies=(BASE_BODY, *objects), required=required, names=dict(cfg.mocap_names or {}),
                               stale_cycles=cfg.safety.stale_cycles)

    @property
    def stage(self) -> Stage:
        return self.stages.stage

    def _damp(self, reason: str, detail: str = "") -> None:
        if self.stage != Stage.DAMP and detail:
            self.fault_detail = detail
        self.stages.go(Stage.DAMP, self.cycle, reason)

    def _mocap_fault(self) -> bool:
        """Damp (True) when the policy reads motion capture and the stream cannot feed it."""
        if self.mocap is None or not self.mocap.cfg.required:
            return False
        fault = self.mocap.current_fault()
        if fault is not None:
            self._damp(*fault)
        return fault is not None

    def step(self, inp: CycleInput) -> CycleOutput:
        self.cycle += 1
        self._ingest(inp)
        if self.mocap is not None:
            self.mocap.update(inp.mocap)
        if self.estimator is not None and self._estimate is not None and inp.state is self.state:
            pos, vel = self.estimator.update(self.state, inp.t_s - self._estimated_at)
            self._estimate, self._estimated_at = BaseEstimate(pos, vel), inp.t_s
        keys = inp.keys
        if self.state is not None:
            remote = remote_keys_to_operator(self.state.remote_keys)
            keys |= remote & ~self._remote_prev  # button presses (rising edges)
            self._remote_prev = remote
        if keys & KEY_ESTOP:
            self._damp(DampReason.ESTOP)
        elif keys & KEY_STOP:
            self._damp(DampReason.STOP)

        tilt = float("nan")
        if self.state is not None and self.stage != Stage.DAMP:
            _, body_quat = self.builder.kinematics.body_poses(self.state.quat_wxyz, self.state.joint_pos)
            tilt = torso_tilt_rad(body_quat[self.builder.anchor])
            if fault := safety.tilt_fault(tilt, self.cfg.safety):
                self._damp(fault)

        out = CycleOutput(command=None, stage=self.stage, frame=-1, observation=None, action=None,
                          tilt_rad=tilt, mpjpe_m=float("nan"))
        if self.stage == Stage.WAIT:
            if self.state is None:
                return out
            self._ramp_q0, self._ramp_t0 = self.state.joint_pos.copy(), inp.t_s
            self.stages.go(Stage.RAMP, self.cycle, "state")
        if self.stage == Stage.RAMP:
            progress = 1.0 if self.cfg.safety.ramp_s == 0 else (inp.t_s - self._ramp_t0) / self.cfg.safety.ramp_s
            if progress >= 1.0:
                self.stages.go(Stage.HOLD, self.cycle, "ramp_done")
            else:
                out.command = safety.ramp_command(self._ramp_q0, self.spec.default_joint_pos, progress)
        if self.stage == Stage.HOLD:
            if self.cfg.auto_start or keys & KEY_START:
                self._start(inp.t_s, "auto_start" if self.cfg.auto_start else "operator")
            else:
                out.command = safety.ramp_command(self.spec.default_joint_pos, self.spec.default_joint_pos, 1.0)
        if self.stage in (Stage.BLEND, Stage.TRACK):
            self._mocap_fault()
        if self.stage == Stage.BLEND:
            progress = (inp.t_s - self._blend_t0) / self.cfg.safety.blend_s
            if progress >= 1.0:
                self._start_tracking(inp.t_s, "blend_done")
            else:
                out.command = safety.blend_command(self.spec.default_joint_pos, self.builder.reference_joint_pos(0),
                                                   self.spec.kp, self.spec.kd, progress, self.cfg.safety)
        if self.stage == Stage.TRACK:
            self._track(inp.t_s, out)
        if self.stage == Stage.END:
            if inp.t_s - self._end_t0 >= self.cfg.safety.end_hold_s:
                self._damp(DampReason.CLIP_END)
            else:
                out.command = safety.policy_command(self.builder.reference_joint_pos(-1), self.spec.kp,
                                                    self.spec.kd, self.cfg.safety)
        if self.stage == Stage.DAMP:
            out.command = safety.damping_command(self.cfg.safety)
        out.stage = self.stage
        out.object_error_m = self._object_error(out.frame)
        return out

    # ------------------------------------------------------------ internals
    def _ingest(self, inp: CycleInput) -> None:
        if inp.state is None:
            if self.state is not None:
                self.cycles_without_state += 1
                if self.cycles_without_state >= self.cfg.safety.stale_cycles:
                    self._damp(DampReason.STALE_STATE)
            return
        if fault := safety.state_fault(inp.crc_ok, inp.state.is_finite()):
            self._damp(fault)
            return  # the last good state stays
        self.state = inp.state
        self.cycles_without_state = 0

    def _start(self, t_s: float, reason: str) -> None:
        """From HOLD: the blend to the reference's first frame, or straight to tracking."""
        if self._mocap_fault():
            return
        if self.cfg.safety.blend_s > 0.0:
            self._blend_t0 = t_s
            self.stages.go(Stage.BLEND, self.cycle, reason)
        else:
            self._start_tracking(t_s, reason)

    def _base(self) -> BaseEstimate | None:
        """The pelvis as motion capture measures it or, without it, as the estimator estimates it,
        when the policy reads it."""
        if not self.builder.needs_base:
            return None
        if self.mocap is not None:
            m = self.mocap.motion()
            return None if m is None else BaseEstimate(m.pos_w[0], m.lin_vel_w[0], m.quat_wxyz[0])
        return self._estimate

    def _objects(self) -> ObjectEstimate | None:
        """The moving objects as motion capture measures them, when the policy reads them."""
        if self.mocap is None or not self.builder.needs_objects:
            return None
        m = self.mocap.motion()
        return None if m is None else ObjectEstimate(m.pos_w[1:], m.quat_wxyz[1:], m.lin_vel_w[1:], m.ang_vel_w[1:])

    def _object_error(self, frame: int) -> np.ndarray | None:
        if self.mocap is None or not self._tracked or self.builder.objects is None:
            return None
        m = self.mocap.motion()
        if m is None:
            return None
        on = self.builder.num_frames - 1 if frame < 0 else frame - 1
        ref = self.builder.ref_object_pos_w[on].double().numpy()
        return np.linalg.norm(m.pos_w[1:] - ref, axis=-1)

    def _start_tracking(self, t_s: float, reason: str) -> None:
        self.builder.align(*self.builder.alignment(self.state, self._base()))
        self._tracked = True
        if self.estimator is not None and self.mocap is None:
            # the robot stands on the clip's first frame: the estimate starts at its pelvis, at rest
            pelvis = self.builder.ref_body_pos_w[0, self.builder.spec.body_names.index("pelvis")].double().numpy()
            self.estimator.reset(pelvis, self.state.quat_wxyz, self.state.joint_pos)
            self._estimate, self._estimated_at = BaseEstimate(pelvis, np.zeros(3)), t_s
        self.frame = 1  # the robot stands on frame 0; the observation shows the target frame 1
        self.last_action = np.zeros(robot.NUM_JOINTS)
        self._track_t0 = t_s
        self.stages.go(Stage.TRACK, self.cycle, reason)

    def _track(self, t_s: float, out: CycleOutput) -> None:
        if self.frame >= self.builder.num_frames:
            if self.cfg.safety.end_hold_s > 0.0:
                self._end_t0 = t_s
                self.stages.go(Stage.END, self.cycle, DampReason.CLIP_END)
            else:
                self._damp(DampReason.CLIP_END)
            return
        if self.cfg.duration_s is not None and t_s - self._track_t0 >= self.cfg.duration_s:
            self._damp(DampReason.DURATION)
            return
        out.base = self._base()
        s = self.builder.tracking_state(self.state, self.frame, self.last_action, out.base, self._objects())
        obs = self.builder.observation(s)
        raw = np.asarray(self.policy(obs), dtype=np.float64).reshape(-1)
        out.observation, out.action, out.frame = obs, raw, self.frame
        out.mpjpe_m = self.builder.mpjpe_m(s)
        out.ref_tilt_rad = self.builder.reference_tilt_rad(self.frame - 1)
        if fault := safety.action_fault(raw):
            self._damp(fault)
            return
        clip = self.spec.action_clip
        action = np.clip(raw, -clip, clip)
        targets = self.spec.default_joint_pos + self.spec.action_scale * action
        out.command = safety.policy_command(targets, self.spec.kp, self.spec.kd, self.cfg.safety)
        self.last_action = action
        self.frame += 1
