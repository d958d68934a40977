"""Base state estimation for the G1 from what it measures (IMU, joint encoders): the pelvis
position and linear velocity in the IMU's world, so a policy whose actor observes them
(``benchmarks/state_estimation.sets``: ``anchor_pos_b``, ``base_lin_vel_b``) runs without
motion capture.

A linear Kalman filter in the style of the MIT Cheetah 3 estimator (Bledt et al., IROS 2018;
also legged_control's ``LinearKalmanFilter``), 12 states, all in the world frame (m, m/s):

    x = [p_imu, v_imu, p_left_foot, p_right_foot]

- **State point.** The filter estimates the IMU site (``imu_in_pelvis``, 9.5 cm from the pelvis
  origin) rather than the pelvis origin, so the accelerometer drives it with no lever-arm terms
  (which would need the angular acceleration, a differentiated gyro). The pelvis origin is
  recovered exactly from the same kinematics: p = p_imu − R·r, v = v_imu − ω×(R·r).
- **Process.** a = R·f + g: the accelerometer's specific force f (pelvis frame) turned to the world
  by the IMU quaternion R, plus gravity. Feet stay where they are; a foot in contact may slip by
  ``stance_foot_noise``, a swinging one moves freely (``swing_foot_noise``).
- **Measurements**, from forward kinematics of the training MJCF (MuJoCo, the foot sites at the
  sole's centre) with the IMU orientation and gyro and the joint positions and velocities:
  each foot's position relative to the IMU (always); for a foot in contact its velocity is zero,
  i.e. v_imu = −(foot velocity relative to the IMU); and its sole is at the ground height
  found at ``reset`` (flat ground), which removes vertical drift. The last two have noise
  σ / c, c ∈ [0, 1] the contact confidence, so an uncertain contact counts for less.
- **Contact** without force sensing, from kinematics alone: c = c_height · c_apart. c_height ramps
  from 1 to 0 as the sole rises above the lower sole (world vertical); c_apart, for the higher
  foot only, as the feet's relative speed grows (the base's velocity cancels in it, so a wrong
  estimate cannot hide a lifting foot, as a foot speed under the estimated velocity did: the
  filter, fusing both feet, halves the lifting foot's apparent speed). The lower foot is thus
  always in contact: walking, not running or jumping. ``contacts`` = c > 0.5.

Horizontal position is not observable from these measurements: it drifts with foot slip and
kinematic error (``benchmarks/state_estimator.py`` measures how much per metre walked); the
heading likewise stays the IMU's own. Anything that corrects them (the reference, motion
capture) is the caller's design.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import mujoco
import numpy as np

from agents.deploy.messages import RobotState
from otr_gym import robot
from otr_gym.scene import robot_model

GRAVITY_W = np.array([0.0, 0.0, -9.81])  # m/s², world
IMU_SITE = "imu_in_pelvis"
FOOT_SITES = ("left_foot", "right_foot")  # the sole's centre, on each ankle_roll_link


@dataclass(frozen=True)
class EstimatorCfg:
    """Noise (standard deviations) and contact thresholds; defaults measured on the guided walk
    and the sway of ``benchmarks/state_estimator.py`` at 500 Hz and 50 Hz updates."""

    accel_noise: float = 0.5  # m/s²/√Hz: accelerometer noise and what one sample misses between updates
    stance_foot_noise: float = 0.02  # m/√s: slip of a foot in contact
    swing_foot_noise: float = 10.0  # m/√s: a foot in the air goes where kinematics says
    kinematic_pos_noise: float = 0.01  # m: foot position relative to the IMU (joint offsets, link lengths)
    contact_vel_noise: float = 0.2  # m/s: a contact foot's velocity (joint-velocity noise, rolling, slip)
    ground_height_noise: float | None = 0.01  # m: a contact sole on the ground; None: no height measurement
    contact_height_m: tuple[float, float] = (0.02, 0.05)  # sole above the lower one: contact below, none above
    contact_speed_mps: tuple[float, float] = (0.2, 0.5)  # feet's relative speed: the higher foot is off above
    initial_vel_std: float = 0.1  # m/s: standing still at reset
    initial_pos_std: float = 0.01  # m: the reset position's uncertainty (IMU and feet)


def _ramp(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """1 at or below ``lo``, 0 at or above ``hi``, linear between."""
    return np.clip((hi - x) / (hi - lo), 0.0, 1.0)


class LegFrames(NamedTuple):
    """Forward kinematics of one sample, the pelvis origin at rest at the world origin (world axes)."""

    rotation: np.ndarray  # (3, 3) pelvis to world
    imu_pos: np.ndarray  # (3,) IMU site relative to the pelvis origin (m)
    feet_pos: np.ndarray  # (2, 3) foot sites relative to the pelvis origin (m)
    imu_vel: np.ndarray  # (3,) IMU site velocity relative to the pelvis origin's (m/s)
    feet_vel: np.ndarray  # (2, 3) foot site velocities relative to the pelvis origin's (m/s)


class _LegKinematics:
    """The IMU and foot sites of the training MJCF (MuJoCo ``mj_kinematics``/``mj_jacSite``)."""

    def __init__(self):
        self.model = robot_model(visual=False)
        self.data = mujoco.MjData(self.model)
        self.pelvis = self.model.body(robot.ROOT_BODY).id
        self.sites = [self.model.site(s).id for s in (IMU_SITE, *FOOT_SITES)]
        self._jac = np.zeros((3, self.model.nv))
        self._qvel = np.zeros(self.model.nv)

    def solve(self, quat_wxyz: np.ndarray, joint_pos: np.ndarray, gyro_b: np.ndarray | None = None,
              joint_vel: np.ndarray | None = None) -> LegFrames:
        """The sites at orientation ``quat_wxyz`` (wxyz) and joints ``joint_pos`` (rad); their
        velocities under ``gyro_b`` (rad/s, pelvis frame) and ``joint_vel`` (rad/s), else zero."""
        d = self.data
        d.qpos[:3] = 0.0
        d.qpos[3:7] = quat_wxyz / np.linalg.norm(quat_wxyz)
        d.qpos[7:7 + robot.NUM_JOINTS] = joint_pos
        mujoco.mj_kinematics(self.model, d)
        pos = d.site_xpos[self.sites].copy()
        vel = np.zeros((3, 3))
        if gyro_b is not None and joint_vel is not None:
            mujoco.mj_comPos(self.model, d)  # the Jacobians read cdof
            qvel = self._qvel  # the free joint's linear velocity stays 0; its angular one is in the pelvis frame
            qvel[3:6], qvel[6:6 + robot.NUM_JOINTS] = gyro_b, joint_vel
            for row, site in enumerate(self.sites):
                mujoco.mj_jacSite(self.model, d, self._jac, None, site)
                vel[row] = self._jac @ qvel
        return LegFrames(d.xmat[self.pelvis].reshape(3, 3).copy(), pos[0], pos[1:], vel[0], vel[1:])


class BaseStateEstimator:
    """Pelvis position and linear velocity (world) from IMU and leg kinematics (see module doc)."""

    def __init__(self, cfg: EstimatorCfg = EstimatorCfg()):  # noqa: B008 (frozen: sharing the default is safe)
        self.cfg = cfg
        self.kinematics = _LegKinematics()
        self.x = np.zeros(12)
        self.P = np.eye(12)
        self.ground_z = 0.0
        self.contacts = np.ones(2, dtype=bool)  # (left, right) foot, last estimate
        self.contact_confidence = np.ones(2)  # c ∈ [0, 1] per foot, last estimate
        # measurement rows (fixed): 6 relative foot positions, 6 foot velocities, 2 sole heights
        H = np.zeros((14, 12))
        for i in range(2):
            H[3 * i:3 * i + 3, 6 + 3 * i:9 + 3 * i] = np.eye(3)
            H[3 * i:3 * i + 3, 0:3] = -np.eye(3)
            H[6 + 3 * i:9 + 3 * i, 3:6] = np.eye(3)
            H[12 + i, 8 + 3 * i] = 1.0
        self._H = H if cfg.ground_height_noise is not None else H[:12]

    def reset(self, pos_w: np.ndarray, quat_wxyz: np.ndarray, joint_pos: np.ndarray) -> None:
        """Start standing still with the pelvis at ``pos_w`` (m, world) in orientation ``quat_wxyz``;
        the lower sole's height becomes the ground's."""
        legs = self.kinematics.solve(np.asarray(quat_wxyz, float), np.asarray(joint_pos, float))
        pos_w = np.asarray(pos_w, dtype=np.float64)
        self.x = np.concatenate([pos_w + legs.imu_pos, np.zeros(3), (pos_w + legs.feet_pos).ravel()])
        self.ground_z = float(self.x[[8, 11]].min())
        c = self.cfg
        self.P = np.diag(np.r_[np.full(3, c.initial_pos_std), np.full(3, c.initial_vel_std),
                               np.full(6, c.initial_pos_std)] ** 2)
        self.contacts = np.ones(2, dtype=bool)
        self.contact_confidence = np.ones(2)

    def update(self, state: RobotState, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Pelvis position (m, world) and linear velocity (m/s, world) after this measurement;
        ``dt`` (s) is the time since the previous one."""
        c = self.cfg
        legs = self.kinematics.solve(state.quat_wxyz, state.joint_pos, state.gyro_b, state.joint_vel)
        # predict: this sample's specific force, turned to the world, held over dt
        acc = legs.rotation @ state.accel_b + GRAVITY_W
        x = self.x
        x[0:3] += x[3:6] * dt + 0.5 * acc * dt * dt
        x[3:6] += acc * dt
        confidence = self._contact_confidence(legs)
        F = np.eye(12)
        F[0:3, 3:6] = dt * np.eye(3)
        q_acc = c.accel_noise ** 2 * dt
        foot_q = np.where(confidence > 0.5, c.stance_foot_noise, c.swing_foot_noise) ** 2 * dt
        Q = np.diag(np.concatenate([np.full(3, q_acc * dt * dt / 3.0), np.full(3, q_acc), np.repeat(foot_q, 3)]))
        Q[0:3, 3:6] = Q[3:6, 0:3] = np.eye(3) * (q_acc * dt / 2.0)  # white acceleration moves p and v together
        P = F @ self.P @ F.T + Q
        # measure: feet relative to the IMU; contact feet still and on the ground
        weight = np.maximum(confidence, 1e-3)
        z = np.concatenate([(legs.feet_pos - legs.imu_pos).ravel(), -(legs.feet_vel - legs.imu_vel).ravel(),
                            np.full(2, self.ground_z)])
        std = np.concatenate([np.full(6, c.kinematic_pos_noise), np.repeat(c.contact_vel_noise / weight, 3),
                              (c.ground_height_noise or 0.0) / weight])
        H = self._H
        z, std = z[:H.shape[0]], std[:H.shape[0]]
        PHt = P @ H.T
        K = np.linalg.solve(H @ PHt + np.diag(std ** 2), PHt.T).T  # P Hᵀ S⁻¹ (S, P symmetric)
        self.x = x + K @ (z - H @ x)
        IKH = np.eye(12) - K @ H
        self.P = IKH @ P @ IKH.T + (K * std ** 2) @ K.T  # Joseph form: stays symmetric positive definite
        self.contact_confidence = confidence
        self.contacts = confidence > 0.5
        return self.x[0:3] - legs.imu_pos, self.x[3:6] - legs.imu_vel

    def _contact_confidence(self, legs: LegFrames) -> np.ndarray:
        """(2,) c ∈ [0, 1] from kinematics alone: a sole near the lower one's height and, while
        the feet move apart (their relative speed, in which the base's velocity cancels), the
        lower foot only."""
        c = self.cfg
        height = legs.feet_pos[:, 2] - legs.feet_pos[:, 2].min()
        apart = np.linalg.norm(legs.feet_vel[0] - legs.feet_vel[1])
        moving = np.where(height > 0.0, _ramp(np.array(apart), *c.contact_speed_mps), 1.0)
        return _ramp(height, *c.contact_height_m) * moving
