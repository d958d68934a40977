"""``otr sim-robot``: a MuJoCo G1 that behaves like the real one on the low-level DDS interface.

It subscribes to ``rt/lowcmd`` (``unitree_hg`` LowCmd_), drops commands whose CRC is wrong
(counting them), and before every physics step applies the motor law of the G1's joint
drivers, τ = τ_ff + kp(q* − q) + kd(dq* − dq), clipped to the effort limits (docs/environment.md §9). After
every step it publishes ``rt/lowstate`` (LowState_ with CRC): joint q/dq/ddq/τ, the pelvis IMU
(quaternion wxyz, gyroscope in the pelvis frame, accelerometer = specific force in the pelvis
frame, rpy), and tick = simulated time in ms.

Model: the training MJCF (``otr_gym/assets/g1/g1.xml``) on the ground plane (with
``--terrain``, also a reference's terrain as the training env simulates it: ``envs.terrain``),
turned into a torque-driven robot at run time: its position actuators become motors (gain 1,
no bias, ctrl = torque within ±effort), so the PD law runs here in Python exactly as the
firmware runs it, at ``physics_hz`` (default 500 Hz, timestep 2 ms). Joint armature stays as
trained.

Before the first valid LowCmd the robot is frozen in its initial pose (a real G1 would hang in
its gantry). With ``--gantry`` physics runs from the start, the joints damped as in the G1's
debug mode until a command comes, and a virtual gantry holds the torso link (where the real
gantry hooks in): a rope that only pulls up, a trolley spring in x/y and a harness torque that
keeps the torso upright, 5 cm above the ground, until ``--gantry-release`` seconds after the
first valid LowCmd (the controller's ramp happens hanging; lower it after the ramp, a robot
landing mid-ramp falls); then it lowers the robot onto its feet over 1 s and lets go.

Objects: given a reference with objects (``--reference``), the sim robot simulates them as the
box environment builds them (``envs.box.box_scene``: the same collision shapes, grasp-fitted
boxes, the nominal mass and friction of ``configs/env/box.yaml``, moving objects free and static
ones fixed), each at its pose on the reference's first frame; ``--stats`` and ``--trace`` record
their poses, and the stats say how far each moving object ended from the reference's last frame
and what it touched at the end. ``--object-draw SEED`` draws the moving objects' friction, mass
and inertia as the box environment does in training (``objects.randomization`` of
``configs/env/box.yaml``, ``envs.mdp.randomization.draw_object``); ``--object-mass NAME=KG`` and
``--object-friction NAME=MU`` set them (over a draw); the stats record the values used.

Motion capture: ``--publish-mocap [TOPIC]`` publishes what a marker system would see (the pelvis
and every object, ``SimRobot.capture``) at ``--mocap-rate`` Hz, ``--mocap-latency-ms`` late and with
``--mocap-noise-m`` of position noise (``agents.deploy.mocap``), for ``otr deploy --mocap``.

The loop keeps real time on absolute deadlines; ``--stats`` writes what happened (commands
accepted and dropped, real-time factor, step timing, whether the robot stayed upright).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import signal
import sys
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from agents.deploy import crc
from agents.deploy.messages import (
    MOTOR_MODE_ENABLE,
    JointCommand,
    LowState_,
    MotorState_,
    joint_command,
)
from agents.deploy.mocap import BASE_BODY, TOPIC_MOCAP, MocapFrame, mocap_message, now_ns
from agents.deploy.options import name_values, positive_float
from agents.deploy.safety import STARTUP_KD
from otr_gym import robot
from otr_gym.io import save_npz, write_json
from otr_gym.rotations import quat_apply, quat_error_angle, quat_from_yaw, quat_mul, quat_to_matrix, quat_yaw

UPRIGHT_MIN_PELVIS_Z = 0.5  # m: below this (or tilted past UPRIGHT_MAX_TILT) the robot has fallen
UPRIGHT_MAX_TILT = np.radians(60.0)
MODE_MACHINE = 5  # the value Holosoma sends; real G1s report their own
#: What the G1's joints do before any controller speaks (debug mode): damping only.
DEBUG_MODE_DAMPING = JointCommand(q=np.zeros(robot.NUM_JOINTS), dq=np.zeros(robot.NUM_JOINTS),
                                  kp=np.zeros(robot.NUM_JOINTS), kd=STARTUP_KD.copy(), tau=np.zeros(robot.NUM_JOINTS))


@dataclass
class SimRobotCfg:
    physics_hz: float = 500.0
    gantry: bool = False
    gantry_lift_m: float = 0.05  # feet this far above the ground while hanging
    gantry_release_s: float = 3.0  # after the first command
    gantry_stiffness: float = 50000.0  # N/m: a rope, ~7 mm of sag under the G1
    gantry_damping: float = 2000.0  # N·s/m (about critical for the G1's mass)
    harness_stiffness: float = 500.0  # N·m/rad: the harness keeps the torso upright while hanging
    harness_damping: float = 50.0  # N·m·s/rad
    yaw_rad: float = 0.0  # initial heading (the runner must align to it)


@dataclass(frozen=True)
class ObjectProperties:
    """A moving object's physical properties in the sim robot: its mass (kg), the sliding
    friction of its collision geoms and a scale on its inertia beyond the mass's (the inertia
    of the collision geometry at uniform density, × mass / nominal mass × ``inertia_scale``, as
    ``envs.mdp.randomization.randomize_objects`` sets it); ``source``: "nominal", "drawn" or
    "set" (an option gave the mass or the friction)."""

    mass_kg: float
    friction: float
    inertia_scale: float = 1.0
    source: str = "nominal"


def motorised_model(physics_hz: float, terrain=None, objects=None, condim: int = 3) -> mujoco.MjModel:
    """The G1 on the ground (and on ``terrain``, ``envs.terrain.SceneTerrain``, and with
    ``objects``, ``envs.objects.SceneObjects``, when given) with its position actuators turned
    into torque motors."""
    from otr_gym.scene import SceneSpec, build_scene

    spec = build_scene(SceneSpec(ground=True, visual=False)).spec
    if objects is not None:
        objects.add_to(spec, visual=False, condim=condim)
    if terrain is not None:
        terrain.add_to(spec)
    model = spec.compile()
    names = [model.actuator(i).name for i in range(model.nu)]
    joints = [model.joint(model.actuator_trnid[i, 0]).name for i in range(model.nu)]
    if tuple(joints) != robot.JOINT_NAMES:
        raise RuntimeError(f"{robot.G1_MJCF}: actuators {names} do not drive the joints in G1 order")
    model.opt.timestep = 1.0 / physics_hz
    model.actuator_gaintype[:] = mujoco.mjtGain.mjGAIN_FIXED
    model.actuator_biastype[:] = mujoco.mjtBias.mjBIAS_NONE
    model.actuator_gainprm[:] = 0.0
    model.actuator_gainprm[:, 0] = 1.0
    model.actuator_biasprm[:] = 0.0
    model.actuator_ctrllimited[:] = 1
    model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1] = -robot.EFFORT_LIMIT, robot.EFFORT_LIMIT
    return model


def pd_torque(cmd: JointCommand, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """τ = τ_ff + kp(q* − q) + kd(dq* − dq), clipped to ±effort (N·m)."""
    tau = cmd.tau + cmd.kp * (cmd.q - q) + cmd.kd * (cmd.dq - dq)
    return np.clip(tau, -robot.EFFORT_LIMIT, robot.EFFORT_LIMIT)


def quat_to_rpy(q: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (rad) of q = Rz(yaw)·Ry(pitch)·Rx(roll) (the inverse of
    ``otr_gym.rotations.quat_from_euler_xyz``)."""
    m = quat_to_matrix(q)
    return np.array([np.arctan2(m[2, 1], m[2, 2]), np.arcsin(np.clip(-m[2, 0], -1, 1)), np.arctan2(m[1, 0], m[0, 0])])


class SimRobot:
    """The physics and the message content, without the transport."""

    def __init__(self, cfg: SimRobotCfg, initial_qpos: np.ndarray | None = None, terrain=None, objects=None,
                 condim: int = 3, properties: dict[str, ObjectProperties] | None = None):
        self.cfg = cfg
        self.model = motorised_model(cfg.physics_hz, terrain, objects, condim)
        #: name -> the properties each moving object is simulated with (``ObjectProperties``)
        self.object_properties = {o.name: ObjectProperties(o.mass_kg, o.friction)
                                  for o in (objects.objects if objects is not None else ()) if not o.static}
        for name, props in (properties or {}).items():
            self._set_object_properties(objects, name, props)
        self.data = mujoco.MjData(self.model)
        qpos = robot.default_qpos() if initial_qpos is None else np.array(initial_qpos, dtype=np.float64)
        yaw = quat_from_yaw(np.float64(cfg.yaw_rad))
        root_xy = qpos[:2].copy()
        qpos[3:7] = quat_mul(yaw, qpos[3:7])
        if cfg.gantry:
            qpos[2] += cfg.gantry_lift_m
        self.data.qpos[: 7 + robot.NUM_JOINTS] = qpos
        # the moving objects (free joints after the robot's) at their first-frame poses, turned
        # with the robot about its root by --yaw: the scene keeps its layout around the robot
        self.moving = tuple(o for o in (objects.objects if objects is not None else ()) if not o.static)
        self._static_bodies = tuple((o.name, self.model.body(o.body).id)
                                    for o in (objects.objects if objects is not None else ()) if o.static)
        self._object_qpos = [int(self.model.jnt_qposadr[self.model.body(o.body).jntadr[0]]) for o in self.moving]
        #: name -> (7,) the reference's last-frame pose of a moving object (set by ``main``)
        self.object_goals: dict[str, np.ndarray] = {}
        for o, adr in zip(self.moving, self._object_qpos, strict=True):
            offset = np.append(o.pos_w[:2] - root_xy, 0.0)
            self.data.qpos[adr: adr + 3] = np.append(root_xy, 0.0) + quat_apply(yaw, offset) + [0.0, 0.0, o.pos_w[2]]
            self.data.qpos[adr + 3: adr + 7] = quat_mul(yaw, o.quat_w)
        mujoco.mj_forward(self.model, self.data)
        self._acc = self.model.sensor("imu_lin_acc").adr[0]
        self._pelvis = self.model.body("pelvis").id
        self._torso = self.model.body(robot.ANCHOR_BODY).id
        self._gantry_anchor = self.data.xpos[self._torso].copy()
        self.gantry_release_at_s: float | None = None  # sim time; set by release_gantry_in()
        self.tau = np.zeros(robot.NUM_JOINTS)
        self.msg = LowState_(mode_machine=MODE_MACHINE,
                             motor_state=[MotorState_(mode=MOTOR_MODE_ENABLE) for _ in range(35)])

    def _set_object_properties(self, objects, name: str, props: ObjectProperties) -> None:
        """Give the moving object ``name`` its mass, inertia and friction as the training env's
        randomisation does (``envs.mdp.randomization.randomize_objects`` on the compiled model)."""
        if name not in self.object_properties:
            raise ValueError(f"no moving object '{name}' (moving: {sorted(self.object_properties) or 'none'})")
        m = self.model
        (obj,) = [o for o in objects.objects if o.name == name]
        body = m.body(obj.body).id
        m.body_inertia[body] *= props.inertia_scale * props.mass_kg / m.body_mass[body]
        m.body_mass[body] = props.mass_kg
        from envs.mdp.randomization import collision_geoms

        m.geom_friction[collision_geoms(m, body), 0] = props.friction
        self.object_properties[name] = props

    def object_contacts(self) -> dict[str, list[str]]:
        """Per moving object, what it touches now (sorted): "ground" (the ground plane and any
        terrain), "robot", and other objects by name."""
        m, d = self.model, self.data
        owner = {m.body(o.body).id: o.name for o in self.moving} | dict((b, n) for n, b in self._static_bodies)
        out: dict[str, set[str]] = {name: set() for name in self.object_properties}

        def what(body: int) -> str:
            return owner.get(body) or ("ground" if body == 0 else "robot")

        for c in d.contact[: d.ncon]:
            a, b = what(int(m.geom_bodyid[c.geom1])), what(int(m.geom_bodyid[c.geom2]))
            for x, y in ((a, b), (b, a)):
                if x in out and y != x:
                    out[x].add(y)
        return {name: sorted(v) for name, v in out.items()}

    @property
    def time_s(self) -> float:
        return float(self.data.time)

    def step(self, cmd: JointCommand | None) -> None:
        """One physics step under ``cmd`` (None: zero torque)."""
        d = self.data
        q, dq = d.qpos[7 : 7 + robot.NUM_JOINTS], d.qvel[6 : 6 + robot.NUM_JOINTS]
        self.tau = np.zeros(robot.NUM_JOINTS) if cmd is None else pd_torque(cmd, q, dq)
        d.ctrl[:] = self.tau
        d.xfrc_applied[self._torso] = self._gantry_wrench() if self.cfg.gantry else 0.0
        mujoco.mj_step(self.model, d)

    def release_gantry_in(self, seconds: float) -> None:
        """Start lowering the gantry ``seconds`` of simulated time from now (once)."""
        if self.gantry_release_at_s is None:
            self.gantry_release_at_s = self.time_s + seconds

    def _gantry_wrench(self) -> np.ndarray:
        """(6,) force and torque on the torso (world): trolley spring in x/y, a rope in z that
        only pulls, and a harness torque that keeps the torso upright; lowered after the
        release time, the harness fading out as it goes down."""
        c = self.cfg
        if self.gantry_release_at_s is None:
            lowering = 0.0
        else:
            lowering = np.clip((self.time_s - self.gantry_release_at_s) / 1.0, 0.0, 1.0)
        if lowering >= 1.0:
            return np.zeros(6)
        anchor = self._gantry_anchor - np.array([0.0, 0.0, (c.gantry_lift_m + 0.05) * lowering])
        d = self.data
        velocity = np.zeros(6)  # [angular, linear] of the torso frame, world axes
        mujoco.mj_objectVelocity(self.model, d, mujoco.mjtObj.mjOBJ_BODY, self._torso, velocity, 0)
        p, w, v = d.xpos[self._torso], velocity[:3], velocity[3:]
        f = c.gantry_stiffness * (anchor - p) - c.gantry_damping * v
        f[2] = max(f[2], 0.0)
        z_body = d.xmat[self._torso].reshape(3, 3)[:, 2]
        upright = np.cross(z_body, [0.0, 0.0, 1.0])  # axis·sin(tilt) that turns the torso upright
        w_tilt = np.array([w[0], w[1], 0.0])  # yaw free: damping the light torso's yaw explicitly is unstable
        torque = (1.0 - lowering) * (c.harness_stiffness * upright - c.harness_damping * w_tilt)
        return np.concatenate([f, torque])

    def object_poses(self) -> np.ndarray:
        """(M, 7) the moving objects' poses: position (m, world) and quaternion (wxyz)."""
        return np.array([self.data.qpos[a: a + 7] for a in self._object_qpos]).reshape(-1, 7)

    def capture(self) -> tuple[tuple[str, ...], np.ndarray]:
        """What a motion-capture system sees: the names and (B, 7) poses (m, wxyz; world) of the
        pelvis (``mocap.BASE_BODY``), the moving objects and the static ones."""
        poses = [self.data.qpos[:7].copy(), *self.object_poses()]
        poses += [np.concatenate([self.data.xpos[b], self.data.xquat[b]]) for _, b in self._static_bodies]
        names = (BASE_BODY, *(o.name for o in self.moving), *(n for n, _ in self._static_bodies))
        return names, np.array(poses).reshape(-1, 7)

    def pelvis_height(self) -> float:
        return float(self.data.xpos[self._pelvis, 2])

    def torso_tilt(self) -> float:
        return float(np.arccos(np.clip(self.data.xmat[self._torso, 8], -1.0, 1.0)))

    def low_state(self) -> LowState_:
        """The current state as a LowState_ with its CRC (one message object, updated in place)."""
        d, msg = self.data, self.msg
        q, dq = d.qpos[7 : 7 + robot.NUM_JOINTS], d.qvel[6 : 6 + robot.NUM_JOINTS]
        ddq = d.qacc[6 : 6 + robot.NUM_JOINTS]
        for j, slot in enumerate(robot.MOTOR_INDEX):
            m = msg.motor_state[slot]
            m.q, m.dq, m.ddq, m.tau_est = float(q[j]), float(dq[j]), float(ddq[j]), float(self.tau[j])
        quat = d.qpos[3:7]
        imu = msg.imu_state
        imu.quaternion = quat.tolist()
        # the free joint's angular velocity is in the pelvis frame (the IMU site's orientation);
        # the gyro sensor would lag one step (sensors are evaluated before integration)
        imu.gyroscope = d.qvel[3:6].tolist()
        imu.accelerometer = d.sensordata[self._acc : self._acc + 3].tolist()
        imu.rpy = quat_to_rpy(quat).tolist()
        msg.tick = int(round(d.time * 1000.0)) & 0xFFFFFFFF
        return crc.with_crc(msg)


# ------------------------------------------------------------------ the DDS bridge


@dataclass
class BridgeStats:
    accepted: int = 0
    dropped_bad_crc: int = 0
    published: int = 0
    steps: int = 0
    resyncs: int = 0  # times the loop fell > 100 ms behind and gave up catching up
    first_command_wall_s: float | None = None
    last_command_wall_s: float | None = None
    first_damping_wall_s: float | None = None  # first accepted command with kp = 0 everywhere


@dataclass
class MocapPublisherCfg:
    topic: str = TOPIC_MOCAP
    rate_hz: float = 100.0  # captures per second (a marker system's 100-360 Hz)
    latency_ms: float = 0.0  # capture to publication
    noise_m: float = 0.0  # Gaussian position noise per axis (m, standard deviation)
    seed: int = 0


class MocapPublisher:
    """``SimRobot.capture`` as a motion-capture stream: a capture every 1/``rate_hz`` of simulated
    time, stamped with the wall clock (``mocap.now_ns``), published ``latency_ms`` later with
    ``noise_m`` of position noise."""

    def __init__(self, sim: SimRobot, dds, cfg: MocapPublisherCfg):
        self.sim, self.cfg = sim, cfg
        self.writer = dds.writer(dds.mocap_topic(cfg.topic))
        self.every = max(1, int(round(sim.cfg.physics_hz / cfg.rate_hz)))
        self.pending: deque[MocapFrame] = deque()
        self.rng = np.random.default_rng(cfg.seed)
        self.seq = 0
        self.published = 0

    def step(self, tick: int) -> None:
        """At the physics loop's iteration ``tick``: capture when due, publish what is old enough."""
        now = now_ns()
        if tick % self.every == 0:
            names, poses = self.sim.capture()
            pos = poses[:, :3] + (self.rng.normal(0.0, self.cfg.noise_m, poses[:, :3].shape) if self.cfg.noise_m
                                  else 0.0)
            self.seq += 1
            self.pending.append(MocapFrame(now, self.seq, names, pos, poses[:, 3:]))
        due = None
        while self.pending and now - self.pending[0].stamp_ns >= self.cfg.latency_ms * 1e6:
            due = self.pending.popleft()
        if due is not None:
            self.writer.write(mocap_message(due))
            self.published += 1


class Bridge:
    """``SimRobot`` on DDS: runs until ``duration_s`` (wall) or a signal."""

    def __init__(self, sim: SimRobot, domain_id: int, interface: str | None, mute_after_s: float | None = None,
                 idle_exit_s: float | None = None, mocap: MocapPublisherCfg | None = None):
        from agents.deploy.dds import G1Domain

        self.sim = sim
        self.dds = G1Domain(domain_id, interface)
        self.mocap = None if mocap is None else MocapPublisher(sim, self.dds, mocap)
        self.writer = self.dds.writer(self.dds.lowstate_topic)
        self.reader = self.dds.latest_reader(self.dds.lowcmd_topic)
        self.mute_after_s, self.idle_exit_s = mute_after_s, idle_exit_s
        self.stats = BridgeStats()
        self.command: JointCommand | None = None
        self._stop = False
        self.trace: dict[str, list] = {"wall_s": [], "sim_s": [], "qpos": [], "kp_mean": [], "object_pose": []}
        self.step_ns: list[int] = []
        self.lateness_ns: list[int] = []
        self.min_pelvis_z = sim.pelvis_height()
        self.max_tilt = sim.torso_tilt()

    def stop(self, *_) -> None:
        self._stop = True

    def _poll_command(self, wall_s: float) -> None:
        from agents.deploy.dds import take_latest

        msg = take_latest(self.reader)
        if msg is None:
            return
        if not crc.crc_ok(msg):
            self.stats.dropped_bad_crc += 1
            return
        self.command = joint_command(msg)
        self.sim.release_gantry_in(self.sim.cfg.gantry_release_s)
        self.stats.accepted += 1
        self.stats.first_command_wall_s = self.stats.first_command_wall_s or wall_s
        self.stats.last_command_wall_s = wall_s
        if self.stats.first_damping_wall_s is None and not self.command.kp.any():
            self.stats.first_damping_wall_s = wall_s

    def run(self, duration_s: float | None = None) -> BridgeStats:
        sim = self.sim
        dt_ns = int(round(1e9 / sim.cfg.physics_hz))
        trace_every = max(1, int(round(sim.cfg.physics_hz / 50.0)))
        t0 = time.perf_counter_ns()
        deadline = t0
        ticks = 0  # loop iterations at the physics rate (the sim is frozen until the first LowCmd)
        while not self._stop:
            now = time.perf_counter_ns()
            if now < deadline:
                time.sleep((deadline - now) * 1e-9)
                now = time.perf_counter_ns()
            self.lateness_ns.append(now - deadline)
            wall_s = (now - t0) * 1e-9
            if duration_s is not None and wall_s >= duration_s:
                break
            first, last = self.stats.first_command_wall_s, self.stats.last_command_wall_s
            if self.idle_exit_s is not None and last is not None and wall_s - last >= self.idle_exit_s:
                break
            self._poll_command(wall_s)
            if self.command is not None or sim.cfg.gantry:
                sim.step(self.command if self.command is not None else DEBUG_MODE_DAMPING)
                self.stats.steps += 1
            if self.mocap is not None:
                self.mocap.step(ticks)
            ticks += 1
            if self.mute_after_s is None or first is None or wall_s - first < self.mute_after_s:
                self.writer.write(sim.low_state())
                self.stats.published += 1
            if self.stats.first_damping_wall_s is None:  # a damped robot is meant to sink
                self.min_pelvis_z = min(self.min_pelvis_z, sim.pelvis_height())
                self.max_tilt = max(self.max_tilt, sim.torso_tilt())
            if self.stats.steps % trace_every == 0:
                self.trace["wall_s"].append(wall_s)
                self.trace["sim_s"].append(sim.time_s)
                self.trace["qpos"].append(sim.data.qpos[: 7 + robot.NUM_JOINTS].copy())
                self.trace["kp_mean"].append(float(self.command.kp.mean()) if self.command is not None else np.nan)
                self.trace["object_pose"].append(sim.object_poses())
            self.step_ns.append(time.perf_counter_ns() - now)
            deadline += dt_ns
            behind = time.perf_counter_ns() - deadline
            if behind > 100_000_000:
                deadline += (behind // dt_ns + 1) * dt_ns
                self.stats.resyncs += 1
        self.wall_s = (time.perf_counter_ns() - t0) * 1e-9
        return self.stats

    def summary(self) -> dict:
        step = np.array(self.step_ns) * 1e-6
        late = np.array(self.lateness_ns) * 1e-6
        s = self.stats
        sim_s = self.sim.time_s
        stepping_wall = (self.wall_s - (s.first_command_wall_s or 0.0)) if not self.sim.cfg.gantry else self.wall_s
        return {
            "physics_hz": self.sim.cfg.physics_hz,
            "wall_s": self.wall_s, "sim_s": sim_s,
            "realtime_factor": sim_s / stepping_wall if stepping_wall > 0 else float("nan"),
            "steps": s.steps, "published": s.published, "accepted": s.accepted, "dropped_bad_crc": s.dropped_bad_crc,
            "resyncs": s.resyncs,
            "step_ms": {"p50": float(np.percentile(step, 50)), "p99": float(np.percentile(step, 99)),
                        "max": float(step.max())} if step.size else {},
            "lateness_ms": {"p50": float(np.percentile(late, 50)), "p99": float(np.percentile(late, 99)),
                            "max": float(late.max())} if late.size else {},
            "first_command_wall_s": s.first_command_wall_s, "last_command_wall_s": s.last_command_wall_s,
            "first_damping_wall_s": s.first_damping_wall_s,
            # until the first damping command (a damped robot sinks by design)
            "min_pelvis_z_m": self.min_pelvis_z, "max_torso_tilt_rad": self.max_tilt,
            "upright": bool(self.min_pelvis_z > UPRIGHT_MIN_PELVIS_Z and self.max_tilt < UPRIGHT_MAX_TILT),
            "last_command_kp_mean": float(self.command.kp.mean()) if self.command is not None else None,
            "objects": object_summary(self.sim, np.array(self.trace["object_pose"])) if self.sim.moving else {},
            "mocap_published": None if self.mocap is None else self.mocap.published,
        }


def object_summary(sim: SimRobot, poses: np.ndarray) -> dict:
    """Per moving object: where it started and ended (m, wxyz), its lowest and highest centre
    over the run (m) and, where ``sim.object_goals`` gives the reference's last-frame pose, the
    distance (m) and angle (deg) of the end from it; what it touches at the end
    (``SimRobot.object_contacts``); the mass, friction and inertia scale it was simulated with.
    ``poses`` (T, M, 7) the 50 Hz trace."""
    out = {}
    now = sim.object_poses()
    contacts = sim.object_contacts()
    for k, o in enumerate(sim.moving):
        track = poses[:, k] if len(poses) else now[k][None]
        props = sim.object_properties[o.name]
        entry = {"mass_kg": props.mass_kg, "friction": props.friction, "inertia_scale": props.inertia_scale,
                 "properties": props.source, "start": track[0].tolist(), "end": now[k].tolist(),
                 "min_z_m": float(track[:, 2].min()), "max_z_m": float(track[:, 2].max()),
                 "end_contacts": contacts[o.name]}
        goal = sim.object_goals.get(o.name)
        if goal is not None:
            entry["goal"] = goal.tolist()
            entry["end_error_m"] = float(np.linalg.norm(now[k, :3] - goal[:3]))
            entry["end_error_deg"] = float(np.degrees(quat_error_angle(now[k, 3:], goal[3:])))
        out[o.name] = entry
    return out


def initial_pose(reference: str | None, default_pose: bool = False) -> np.ndarray | None:
    """qpos of the reference's first frame (root and joints), or None for the default pose.
    With ``default_pose``: the G1's default standing pose at the first frame's root x, y and
    heading (where a robot stands after its gantry start-up; a clip whose first frame does not
    balance open loop, such as ``otr demo``'s carry, topples the robot during the runner's ramp)."""
    if reference is None:
        return None
    from otr_gym.reference import Reference

    ref = Reference.load(reference)
    if default_pose:
        qpos = robot.default_qpos()
        qpos[:2] = ref.root_pos_w[0, :2]
        qpos[3:7] = quat_mul(quat_yaw(ref.root_quat_w[0]), qpos[3:7])
        return qpos
    return np.concatenate([ref.root_pos_w[0], ref.root_quat_w[0], ref.dof_pos[0]])


def sim_box_config(object_meshes: list[str] | None = None, env_sets: list[str] | None = None):
    """The box environment's config the sim robot builds its objects and draws with:
    ``configs/env/box.yaml`` with ``env_sets`` ("KEY=VALUE", dotted keys of that file, as a
    training run's ``--set env.KEY=VALUE``, e.g. objects.grasp_fit_quantile=0) and
    ``object_meshes`` ("NAME=FILE": a mesh for an object the file does not embed, Holosoma's)."""
    from envs.config import load_box_config
    from otr_gym.config import merge, parse_sets

    overrides = {name: {"mesh": mesh} for name, mesh in
                 name_values(object_meshes, "--object-mesh", "NAME=FILE", "largebox=largebox.obj").items()}
    try:
        return load_box_config(None, merge(parse_sets(env_sets or [], "--env-set"),
                                           {"objects": {"overrides": overrides}} if overrides else None))
    except (TypeError, KeyError, ValueError) as exc:  # a key the config does not have, a wrong type
        raise ValueError(f"--env-set {' '.join(env_sets or [])}: {exc}") from exc


def sim_objects(reference: str | None, object_meshes: list[str] | None = None, cfg=None):
    """(``envs.objects.SceneObjects`` or None, contact dimension, name -> (7,) last-frame pose of
    each moving object) of a reference's objects, built as the box environment builds them
    (``envs.box.box_scene`` with ``cfg``, default ``sim_box_config(object_meshes)``: configs/env/box.yaml
    with the meshes ``object_meshes`` ("NAME=FILE") give objects the file does not embed)."""
    if reference is None:
        return None, 3, {}
    from envs.box import box_scene
    from otr_gym.reference import Reference

    if not Reference.load(reference).objects:
        return None, 3, {}
    cfg = sim_box_config(object_meshes) if cfg is None else cfg
    refs, _, scene, _, _ = box_scene(reference, cfg)
    goals = {t.name: np.concatenate([t.pos_w[-1], t.quat_w[-1]]) for t in refs[0].objects
             if any(o.name == t.name for o in scene.moving)}
    return scene, cfg.objects.condim, goals


def object_properties(scene, masses: dict[str, float] | None = None, frictions: dict[str, float] | None = None,
                      draw_seed: int | None = None, randomization=None) -> dict[str, ObjectProperties]:
    """What each moving object of ``scene`` (``sim_objects``) is simulated with: nominal, or
    with ``draw_seed`` drawn as the box environment draws them in training (its
    ``objects.randomization``, default ``configs/env/box.yaml``'s; ``envs.mdp.randomization
    .draw_object`` from ``torch.Generator().manual_seed(draw_seed)``, one draw per object in
    order, as ``randomize_objects`` for one env), then ``masses`` (kg) and ``frictions`` by name
    over that. Empty when nothing changes the nominal values. A name that is not a moving object
    of the scene, or a draw without objects, raises ``ValueError``."""
    masses, frictions = masses or {}, frictions or {}
    moving = [o.name for o in scene.moving] if scene is not None else []
    static = [o.name for o in scene.static] if scene is not None else []
    for flag, given in (("--object-mass", masses), ("--object-friction", frictions)):
        unknown = sorted(set(given) - set(moving))
        if unknown:
            raise ValueError(f"{flag}: {', '.join(unknown)} is not a moving object of the reference (moving: "
                             f"{', '.join(moving) or 'none'}" + (f"; static, not changed: {', '.join(static)}"
                                                                  if static else "") + ")")
    if draw_seed is not None and not moving:
        raise ValueError("--object-draw: the reference has no moving objects to draw for (or --no-objects)")
    if draw_seed is None and not masses and not frictions:
        return {}
    generator = None
    if draw_seed is not None:
        import torch

        if randomization is None:
            from envs.config import load_box_config

            randomization = load_box_config().objects.randomization
        generator = torch.Generator().manual_seed(int(draw_seed))
    out = {}
    for o in scene.moving:
        mass, friction, scale, source = o.mass_kg, o.friction, 1.0, []
        if generator is not None:
            from envs.mdp.randomization import draw_object

            friction, mass, scale = draw_object(randomization, o.mass_kg, 1, generator)[0].tolist()
            source.append("drawn")
        if o.name in masses:
            mass = masses[o.name]
            source.append("mass set")
        if o.name in frictions:
            friction = frictions[o.name]
            source.append("friction set")
        out[o.name] = ObjectProperties(float(mass), float(friction), float(scale), ", ".join(source) or "nominal")
    return out


def sim_terrain(terrain: str, reference: str | None):
    """The ``envs.terrain.SceneTerrain`` of ``--terrain``: a mesh file (metres, in the
    reference's world frame), or a run folder whose config.yaml gives ``reference``'s clip a
    terrain (the one it was trained on), at the origin 0 with the run's collision settings."""
    from agents import runs
    from agents.config import train_config_from_dict
    from envs.config import TerrainCfg, load_env_config
    from envs.terrain import SceneTerrain, load_terrain, meshes_for_clips

    path = Path(terrain).expanduser()
    cfg, files = TerrainCfg(), {str(path.absolute())}
    if path.is_dir():
        if reference is None:
            raise ValueError(f"--terrain {path}: a run folder gives the terrain of a clip: pass --reference CLIP")
        train = train_config_from_dict(runs.run_config(path)["train"])
        cfg = load_env_config(train.task, overrides=train.env or None).terrain
        files = set(meshes_for_clips(cfg.meshes, [reference]).values())
        if len(files) != 1:
            raise ValueError(f"{path}: the run gives {reference} {len(files)} terrain meshes "
                             f"(env.terrain.meshes: {cfg.meshes or 'none'})")
    origin = np.zeros(3)
    return SceneTerrain((load_terrain(files.pop(), (reference or "the sim robot",), origin, cfg),), origin[None])


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--interface", default="lo", help="network interface for DDS (default lo: sim2sim on one machine)")
    p.add_argument("--domain-id", type=int, default=0, help="DDS domain id (the G1 uses 0; default: %(default)s)")
    p.add_argument("--reference", default=None, help="start on this reference's first frame, its objects too "
                   "(default: default pose, no objects)")
    p.add_argument("--start-pose", choices=("reference", "default"), default="reference",
                   help="with --reference: start on its first frame, or standing in the default pose at its first "
                        "frame's x, y and heading, as after a gantry start-up (default: %(default)s)")
    p.add_argument("--no-objects", action="store_true", help="do not simulate the reference's objects")
    p.add_argument("--object-mesh", action="append", default=None, metavar="NAME=FILE",
                   help="mesh of an object the reference does not embed (e.g. Holosoma's: largebox=largebox.obj)")
    p.add_argument("--env-set", action="append", default=None, metavar="KEY=VALUE",
                   help="a key of configs/env/box.yaml (dotted) for the objects and their draws, as the policy's "
                        "training run set it with --set env.KEY=VALUE (e.g. objects.grasp_fit_quantile=0)")
    p.add_argument("--object-draw", type=int, default=None, metavar="SEED",
                   help="draw the moving objects' friction, mass and inertia from this seed as the box environment "
                        "does in training (objects.randomization of configs/env/box.yaml); --stats records them "
                        "(default: the nominal mass and friction)")
    p.add_argument("--object-mass", action="append", default=None, metavar="NAME=KG",
                   help="mass of a moving object (kg, > 0; inertia scaled with it), over --object-draw's")
    p.add_argument("--object-friction", action="append", default=None, metavar="NAME=MU",
                   help="sliding friction of a moving object's geoms (> 0), over --object-draw's")
    p.add_argument("--terrain", default=None, help="simulate this terrain: a mesh file (m, the reference's world "
                   "frame), or a run folder (the terrain its config gives --reference's clip)")
    p.add_argument("--gantry", action="store_true", help="hang the robot in a virtual gantry until --gantry-release")
    p.add_argument("--gantry-release", type=float, default=SimRobotCfg.gantry_release_s,
                   help="seconds after the first LowCmd before the gantry lowers the robot onto its feet "
                        "(over 1 s) and lets go (s; default: %(default)s)")
    p.add_argument("--physics-hz", type=float, default=SimRobotCfg.physics_hz,
                   help="physics and LowState rate (Hz; default: %(default)s)")
    p.add_argument("--yaw", type=float, default=0.0, help="initial heading (degrees; default: %(default)s)")
    p.add_argument("--duration", type=float, default=None, help="exit after this many seconds (default: until Ctrl-C)")
    p.add_argument("--idle-exit", type=float, default=None,
                   help="exit when no LowCmd has come for this many seconds (after the first one; "
                        "default: never)")
    p.add_argument("--mute-after", type=float, default=None,
                   help="stop publishing LowState this many seconds after the first LowCmd, physics going on "
                        "(tests the runner's stale-state damping; default: never)")
    p.add_argument("--rt-priority", type=int, default=0,
                   help="run the physics loop at this SCHED_FIFO priority (1-99; 0 = normal scheduling; "
                        "default: %(default)s)")
    p.add_argument("--publish-mocap", nargs="?", const=TOPIC_MOCAP, default=None, metavar="TOPIC",
                   help="publish a motion-capture stream of the pelvis and the objects (agents/deploy/idl/"
                        f"otr_mocap.idl; default topic {TOPIC_MOCAP}) for `otr deploy --mocap`")
    p.add_argument("--mocap-rate", type=float, default=MocapPublisherCfg.rate_hz,
                   help="captures per second (Hz; default: %(default)s)")
    p.add_argument("--mocap-latency-ms", type=float, default=MocapPublisherCfg.latency_ms,
                   help="delay from capture to publication (ms; default: %(default)s)")
    p.add_argument("--mocap-noise-m", type=float, default=MocapPublisherCfg.noise_m,
                   help="Gaussian noise on captured positions, per axis (m; default: %(default)s)")
    p.add_argument("--stats", type=Path, default=None, help="write a JSON summary here at exit")
    p.add_argument("--trace", type=Path, default=None, help="write the 50 Hz ground truth (qpos, gains) .npz here")


def main(args: argparse.Namespace) -> int:
    from agents.deploy.dds import TransportError

    if args.physics_hz < 500.0:
        print(f"otr sim-robot: --physics-hz {args.physics_hz:g} is below the 500 Hz the G1's joint loop needs",
              file=sys.stderr)
        return 2
    try:
        box_cfg = sim_box_config(args.object_mesh, args.env_set) if args.reference is not None else None
        objects, condim, goals = (None, 3, {}) if args.no_objects else sim_objects(args.reference, cfg=box_cfg)
        masses = name_values(args.object_mass, "--object-mass", "NAME=KG", "box=2.5", positive_float)
        frictions = name_values(args.object_friction, "--object-friction", "NAME=MU", "box=0.9", positive_float)
        randomization = None if args.object_draw is None or box_cfg is None else box_cfg.objects.randomization
        properties = object_properties(objects, masses, frictions, args.object_draw, randomization)
        start = initial_pose(args.reference, args.start_pose == "default")
        sim = SimRobot(SimRobotCfg(physics_hz=args.physics_hz, gantry=args.gantry, gantry_release_s=args.gantry_release,
                                   yaw_rad=float(np.radians(args.yaw))), start,
                       None if args.terrain is None else sim_terrain(args.terrain, args.reference), objects, condim,
                       properties)
        sim.object_goals = goals if not args.yaw else {}  # a turned scene has no goal in the reference's frame
        if args.mocap_rate <= 0 or args.mocap_latency_ms < 0 or args.mocap_noise_m < 0:
            raise ValueError(f"--mocap-rate {args.mocap_rate:g} must be > 0, --mocap-latency-ms "
                             f"{args.mocap_latency_ms:g} and --mocap-noise-m {args.mocap_noise_m:g} >= 0")
        mocap = None if args.publish_mocap is None else MocapPublisherCfg(
            args.publish_mocap, args.mocap_rate, args.mocap_latency_ms, args.mocap_noise_m)
        bridge = Bridge(sim, args.domain_id, args.interface, args.mute_after, args.idle_exit, mocap)
        if args.rt_priority:
            from agents.deploy.runner import set_realtime_priority

            set_realtime_priority(args.rt_priority)
    except (TransportError, FileNotFoundError, ValueError, PermissionError) as exc:
        print(f"otr sim-robot: {exc}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, bridge.stop)
    signal.signal(signal.SIGINT, bridge.stop)
    print(f"sim-robot: G1 on domain {args.domain_id}, interface {args.interface}, {args.physics_hz:g} Hz physics"
          f"{', gantry' if args.gantry else ', frozen until the first LowCmd'}"
          + "".join(f", {o.name} ({o.method}, {p.mass_kg:.3g} kg, friction {p.friction:.3g}, {p.source})"
                    for o in sim.moving for p in [sim.object_properties[o.name]])
          + (f", mocap on {mocap.topic} ({mocap.rate_hz:g} Hz, {mocap.latency_ms:g} ms, {mocap.noise_m:g} m)"
             if mocap is not None else ""), flush=True)
    bridge.run(args.duration)
    summary = bridge.summary()
    if randomization is not None:
        summary["object_draw"] = {"seed": args.object_draw, "config": "configs/env/box.yaml objects.randomization",
                                  **dataclasses.asdict(randomization)}
    if args.env_set:
        summary["env_set"] = list(args.env_set)
    if args.stats:
        write_json(args.stats, summary)
    if args.trace:
        save_npz(args.trace, {k: np.asarray(v) for k, v in bridge.trace.items()})
    print(json.dumps({k: summary[k] for k in ("realtime_factor", "accepted", "dropped_bad_crc", "upright")}))
    return 0
