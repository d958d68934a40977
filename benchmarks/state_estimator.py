"""Sim2sim error of ``agents.deploy.estimator.BaseStateEstimator`` against the simulator's truth.

    python benchmarks/state_estimator.py [--seconds 20] [--noise-seed 0]

``agents.deploy.sim_robot.SimRobot`` (MuJoCo, 500 Hz, the firmware's PD law) runs two motions;
every physics step's LowState goes through ``messages.robot_state`` as the runner receives it,
and the estimator runs on that stream offline, twice: on every sample (500 Hz, an estimator
thread) and on every tenth (50 Hz, the runner's cycle, which sees only the newest LowState).
The sim robot's IMU and encoders are exact; each run is repeated with seeded sensor noise
(``SensorNoise``, the test's). Truth: the pelvis free joint's ``qpos[:3]`` and ``qvel[:3]``
(MuJoCo: the body origin's linear velocity, world axes) and, per foot, whether any of the
ankle_roll_link's geoms touches the ground (``data.contact``).

The motions, both driven by joint targets at the stiff start-up gains (``STARTUP_KP/KD``), as
the open-loop reference player (``otr reference-policy``) does:

- **sway**: the procedural sway (4 cm squats, 2 cm side sway, waist twist, arm waves), the robot
  free on its planted feet; targets held for 20 ms like the runner's;
- **guided walk**: the procedural walk (0.25 m steps, 0.5 s a step). No trained walking policy is
  at hand and the open-loop player falls within 3 s of a walk, so a virtual harness leads the
  pelvis along the reference (a horizontal spring and an upright torque; the legs carry the
  weight) while the joints track the walk's targets (linearly interpolated). Its accelerations,
  impacts and foot slip are the simulator's; its gait is not a policy's.

Prints a Markdown table: velocity error (RMS and p95 of |v̂ − v|, m/s), horizontal position error
at the end per metre walked (net displacement; the sway walks ~0 m, so its error is given in mm),
the largest height error (mm), contact agreement with the simulator (% of samples, both feet) and
the estimator's cost per update; then how far the simulator's stance feet slipped, which no leg
odometry can see.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


@dataclass(frozen=True)
class SensorNoise:
    """Seeded sensor imperfections (white noise std unless said): encoders, IMU."""

    joint_pos_rad: float = 1e-3
    joint_vel_radps: float = 0.05
    gyro_radps: float = 0.01
    accel_mps2: float = 0.1
    tilt_bias_deg: float = 0.3  # a constant roll error of the IMU's orientation: gravity leaks in


@dataclass(frozen=True)
class Harness:
    """The guided walk's virtual harness on the pelvis (world): a horizontal spring to the
    reference's pelvis and a torque towards its orientation."""

    stiffness: float = 3000.0  # N/m
    damping: float = 300.0  # N·s/m
    rot_stiffness: float = 400.0  # N·m/rad
    rot_damping: float = 40.0  # N·m·s/rad


def record(reference, seconds: float, harness: Harness | None, hold_targets: bool):
    """Run ``reference`` on a ``SimRobot`` for ``seconds`` (or the clip): the RobotState of every
    physics step and the truth (pelvis pos, vel, foot contacts)."""
    import mujoco

    from agents.deploy.messages import JointCommand, robot_state
    from agents.deploy.safety import STARTUP_KD, STARTUP_KP
    from agents.deploy.sim_robot import SimRobot, SimRobotCfg
    from otr_gym import robot
    from otr_gym.rotations import quat_conj, quat_mul, quat_to_rotvec

    sim = SimRobot(SimRobotCfg(), reference.qpos()[0])
    m, d = sim.model, sim.data
    dt = m.opt.timestep
    qpos, fps = reference.qpos(), reference.fps
    steps = int(min(seconds, reference.duration_s) / dt)
    pelvis = m.body("pelvis").id
    foot_bodies = [m.body(f).id for f in robot.FEET]
    ground = m.geom("ground/ground").id
    sites = [m.site(f).id for f in ("left_foot", "right_foot")]
    states, pos, vel, contact, feet = [], [], [], [], []
    for k in range(steps):
        s = k * dt * fps  # reference frame (fractional)
        if hold_targets:  # the runner: a new target every policy step
            s = np.floor(s * 50.0 / fps) * fps / 50.0
        i = min(int(s), len(qpos) - 2)
        target = qpos[i] + (s - i) * (qpos[i + 1] - qpos[i])
        cmd = JointCommand(q=target[7:], dq=np.zeros(robot.NUM_JOINTS), kp=STARTUP_KP, kd=STARTUP_KD,
                           tau=np.zeros(robot.NUM_JOINTS))
        if harness is not None:
            h = harness
            force = h.stiffness * (target[:3] - d.qpos[:3]) - h.damping * d.qvel[:3]
            force[2] = 0.0
            rot = quat_to_rotvec(quat_mul(target[3:7] / np.linalg.norm(target[3:7]), quat_conj(d.qpos[3:7])))
            omega_w = d.xmat[pelvis].reshape(3, 3) @ d.qvel[3:6]
            d.xfrc_applied[pelvis] = np.r_[force, h.rot_stiffness * rot - h.rot_damping * omega_w]
        sim.step(cmd)
        states.append(robot_state(sim.low_state()))
        pos.append(d.qpos[:3].copy())
        vel.append(d.qvel[:3].copy())
        touching = np.zeros(2, dtype=bool)
        for c in d.contact[: d.ncon]:
            bodies = (m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2])
            if ground in (c.geom1, c.geom2):
                touching |= [f in bodies for f in foot_bodies]
        contact.append(touching)
        feet.append(d.site_xpos[sites, :2].copy())  # as of the step's start: slip is summed over steps
    mujoco.mj_forward(m, d)
    touch, soles = np.array(contact), np.array(feet)
    held = touch[1:] & touch[:-1]
    slip = np.mean([np.linalg.norm((np.diff(soles[:, i], axis=0) * held[:, i, None]).sum(0)) for i in range(2)])
    return states, np.array(pos), np.array(vel), touch, sim.pelvis_height() > 0.5, float(slip)


def noisy(states, noise: SensorNoise, seed: int):
    """The states with ``noise`` added (a new list; seeded)."""
    from dataclasses import replace

    from otr_gym.rotations import quat_mul

    rng = np.random.default_rng(seed)
    half = np.radians(noise.tilt_bias_deg) / 2
    bias = np.array([np.cos(half), np.sin(half), 0.0, 0.0])
    return [replace(s, joint_pos=s.joint_pos + rng.normal(0, noise.joint_pos_rad, 29),
                    joint_vel=s.joint_vel + rng.normal(0, noise.joint_vel_radps, 29),
                    quat_wxyz=quat_mul(s.quat_wxyz, bias), gyro_b=s.gyro_b + rng.normal(0, noise.gyro_radps, 3),
                    accel_b=s.accel_b + rng.normal(0, noise.accel_mps2, 3)) for s in states]


def evaluate(states, pos, vel, contact, every: int, dt: float) -> dict:
    """Run the estimator on every ``every``-th sample; errors against the truth at those samples."""
    from agents.deploy.estimator import BaseStateEstimator

    est = BaseStateEstimator()
    first = states[0]
    est.reset(pos[0], first.quat_wxyz, first.joint_pos)
    idx = np.arange(every, len(states), every)
    p_hat, v_hat, c_hat = [], [], []
    t0 = time.perf_counter()
    for k in idx:
        p, v = est.update(states[k], every * dt)
        p_hat.append(p)
        v_hat.append(v)
        c_hat.append(est.contacts.copy())
    cost_us = (time.perf_counter() - t0) / len(idx) * 1e6
    err = np.linalg.norm(np.array(v_hat) - vel[idx], axis=1)
    perr = np.array(p_hat) - pos[idx]
    walked = float(np.linalg.norm(pos[-1, :2] - pos[0, :2]))
    return {"rms": float(np.sqrt(np.mean(err ** 2))), "p95": float(np.percentile(err, 95)),
            "drift_m": float(np.linalg.norm(perr[-1, :2])), "walked_m": walked,
            "max_dz_mm": float(np.abs(perr[:, 2]).max() * 1e3),
            "contact_pct": float(np.mean(np.array(c_hat) == contact[idx]) * 100), "cost_us": cost_us}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seconds", type=float, default=20.0, help="at most this much of each motion")
    p.add_argument("--noise-seed", type=int, default=0)
    args = p.parse_args()

    from agents.procedural import SwaySpec, WalkSpec, sway_reference, walking_reference

    motions = {"sway": (sway_reference(SwaySpec(duration_s=args.seconds)), None, True),
               "guided walk": (walking_reference(WalkSpec(steps=16)), Harness(), False)}
    print(f"{platform.processor() or platform.machine()}, {time.strftime('%Y-%m-%d')}\n")
    print("| motion | sensors | rate | vel RMS (m/s) | vel p95 (m/s) | drift | max height err (mm) "
          "| contact agreement | µs/update |")
    print("|---|---|---|---|---|---|---|---|---|")
    slips = []
    for name, (reference, harness, hold) in motions.items():
        states, pos, vel, contact, upright, slip = record(reference, args.seconds, harness, hold)
        slips.append(f"{name}: {slip * 1e3:.0f} mm over {np.linalg.norm(pos[-1, :2] - pos[0, :2]):.2f} m")
        dt = 0.002
        for sensors, stream in (("exact", states), ("noisy", noisy(states, SensorNoise(), args.noise_seed))):
            for every, rate in ((1, "500 Hz"), (10, "50 Hz")):
                r = evaluate(stream, pos, vel, contact, every, dt)
                drift = (f"{r['drift_m'] / r['walked_m'] * 100:.1f} cm/m ({r['walked_m']:.1f} m)"
                         if r["walked_m"] > 1.0 else f"{r['drift_m'] * 1e3:.0f} mm")
                print(f"| {name}{'' if upright else ' (fell)'} | {sensors} | {rate} | {r['rms']:.3f} | "
                      f"{r['p95']:.3f} | {drift} | {r['max_dz_mm']:.0f} | {r['contact_pct']:.1f} % | "
                      f"{r['cost_us']:.0f} |", flush=True)
    print("\nNet slip of a foot while the simulator has it on the ground (mean of both feet; leg odometry "
          "cannot see it): " + "; ".join(slips))
    return 0


if __name__ == "__main__":
    sys.exit(main())
