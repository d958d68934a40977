"""Configuration of OTR-G1-BoxTrack-v0: the tracking MDP's (``envs.config.tracking``) with the
reference's objects in the loop (docs/environment.md §3 object variant, §4 object terms, §5, §6).

``configs/env/box.yaml`` lists the same values for users to edit and is loaded by
``load_box_config``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from envs.collision import CollisionCfg
from envs.config.tracking import (
    CommandCfg,
    ObservationCfg,
    ObsTermCfg,
    RewardTermCfg,
    SimCfg,
    TerminationTermCfg,
    TrackEnvCfg,
    critic_obs_terms,
    policy_obs_terms,
    reward_terms,
    termination_terms,
)
from otr_gym import robot
from otr_gym.config import from_dict, load_yaml_mapping, merge

BOX_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "env" / "box.yaml"


@dataclass
class ObjectOverrideCfg:
    """Per-object settings that replace what the reference provides or the defaults."""

    #: Mesh file (any trimesh-readable format, metres, in the frame of the reference's object
    #: pose) for references that embed none (Holosoma's), or to replace the embedded one.
    mesh: str | None = None
    #: A box primitive instead of any mesh (half-extents, m, centred on the object frame).
    box_half_extents: tuple[float, float, float] | None = None
    mass_kg: float | None = None
    friction: float | None = None


@dataclass
class ObjectRandomizationCfg:
    """Object randomisation at start-up, one draw per env (§6 HS object; see configs/env/box.yaml
    for why the friction range is not HS's raw numbers)."""

    friction_range: tuple[float, float] = (0.8, 1.0)  # rubber hands on cardboard
    mass_add_kg: tuple[float, float] = (0.0, 2.0)
    inertia_scale: tuple[float, float] = (0.5, 1.5)  # §6 HS: Ixx ×[0.5, 1.5]; all three axes, one draw


@dataclass
class ObjectsCfg:
    """How the reference's objects enter the simulation and the contact schedule."""

    mass_kg: float = 1.0  # moving objects; inertia from their collision geometry at uniform density
    #: Sliding friction of the objects. Object geoms get MuJoCo priority 1, so this coefficient
    #: (not the max with the robot's 1.0) governs their contacts with hands, table and ground:
    #: rubber hands on cardboard (below 0.8 the robot put on the OMOMO large-box reference loses
    #: the box; configs/env/box.yaml has the measurements).
    friction: float = 1.0
    #: The pair's condim (objects' priority): 6 measured no better than 3 on that lift.
    condim: int = 3
    #: An object whose position moves less than this over every clip (and whose orientation
    #: turns less than ``static_tolerance_rad``) is static: a fixed body (tables).
    static_tolerance_m: float = 1e-3
    static_tolerance_rad: float = 1e-3
    overrides: dict[str, ObjectOverrideCfg] = field(default_factory=dict)
    collision: CollisionCfg = field(default_factory=CollisionCfg)
    #: Hands of the contact terms: bodies and the contact point p_eef in their frame (m): the
    #: centre of the G1 hand's (retargeting) collision capsule, between palm and fingers.
    hand_bodies: tuple[str, ...] = robot.HANDS
    hand_point_offset_m: tuple[float, float, float] = (0.11, 0.0, 0.0)
    #: Per hand, the body whose subtree's collision geoms are that hand in contact: its hand–object
    #: force pairs, the grasp fit and the geometric windows. Empty: each hand body's own subtree
    #: (the G1's wrist_yaw link: palm and fingers). The wrist_pitch links add the wrist boxes.
    hand_contact_roots: tuple[str, ...] = ()
    #: Robot–object proximity windows: hand surface within this distance (m) of the object
    #: surface, from the reference's contact annotations (``contact_distance``) when present,
    #: else from the reference geometry (hand collision boxes vs. object collision shapes).
    proximity_threshold_m: float = 0.05
    #: Object–support windows (supports: static objects and the ground): object collision
    #: shapes within this distance (m) of the support's in the reference (geometry only).
    support_threshold_m: float = 0.02
    support_ground: bool = True
    #: Narrow box objects where the reference's hands (their collision boxes) would start
    #: inside them (envs.mdp.objects.fit_boxes_to_grasps): by this quantile of the depths.
    grasp_fit: bool = True
    grasp_fit_quantile: float = 0.75
    window_ramp_s: float = 0.1  # a gate ramps 0 → 1 over the first frames of its window
    window_min_gap_s: float = 0.1  # shorter gaps between two windows are closed
    #: Uniform ± noise on free-standing objects' start position (m, world; §2 HS object). An
    #: object held at the start frame (a hand window open) instead follows the robot's root noise.
    reset_noise_pos_m: tuple[float, float, float] = (0.05, 0.05, 0.0)
    randomization: ObjectRandomizationCfg = field(default_factory=ObjectRandomizationCfg)

    @property
    def hand_roots(self) -> tuple[str, ...]:
        """Per hand, the root of its contact subtree (``hand_contact_roots`` or the hand bodies)."""
        if not self.hand_contact_roots:
            return tuple(self.hand_bodies)
        if len(self.hand_contact_roots) != len(self.hand_bodies):
            raise ValueError(f"objects.hand_contact_roots {list(self.hand_contact_roots)}: one body per hand of "
                             f"objects.hand_bodies {list(self.hand_bodies)}")
        return tuple(self.hand_contact_roots)


def _box_sim() -> SimCfg:
    # A carried box adds box–hand (2 × 2), box–ground/table (≤ 8) and robot–table contacts.
    return SimCfg(nconmax=64, njmax=400)


def _box_command() -> CommandCfg:
    cmd = CommandCfg()
    # Arm noise of ±0.1 rad moves a hand ~5 cm: into a held box. Half of it keeps starts
    # inside a grasp penetration-free within a few cm (see configs/env/box.yaml).
    cmd.reset_noise = replace(cmd.reset_noise, joint_pos_rad=0.05)
    return cmd


def _box_policy_obs() -> list[ObsTermCfg]:
    # The perception-free actor (the default): what a G1 measures itself (§3's 154 actor: joint
    # encoders, the IMU's orientation and angular velocity, the last action) plus the reference:
    # the robot's (command) and the object's in the reference anchor frame (object_command), and
    # the contact schedule. The object's pose and the robot's world position go to the critic only.
    return policy_obs_terms(state_estimation=False) + [ObsTermCfg("object_command", 0.0),
                                                       ObsTermCfg("contact_schedule", 0.0)]


def _box_mocap_policy_obs() -> list[ObsTermCfg]:
    # The motion-capture actor (``observations.actor: mocap``, the default until 2026-12-07): §3's
    # actor with state estimation (160) + FK actor additions (object pose n 0.02/0.05, supports) +
    # the object command and contact schedule. Told where its reference is in the world, the
    # seed-4 policies ran 0.2 cm ahead of it and ended at 4.7 cm of box error after 20 minutes
    # (with the 154 actor and the object pose: 6-9 cm ahead, 7.1-8.2 cm; docs/results/box.md).
    # Deployment needs the object's pose and the robot's world position (motion capture).
    return policy_obs_terms(state_estimation=True) + [
        ObsTermCfg("object_pos_b", 0.02), ObsTermCfg("object_ori_b", 0.05), ObsTermCfg("object_command", 0.0),
        ObsTermCfg("contact_schedule", 0.0), ObsTermCfg("static_object_pos_b", 0.02),
        ObsTermCfg("static_object_ori_b", 0.05)]


#: The box task's named actors: ``observations.actor`` in configs/env/box.yaml picks one (an
#: explicit ``observations.policy`` list wins over it).
BOX_ACTORS = {"perception_free": _box_policy_obs, "mocap": _box_mocap_policy_obs}
BOX_DEFAULT_ACTOR = "perception_free"  # configs/env/box.yaml's observations.actor; BoxEnvCfg's policy


def _box_critic_obs() -> list[ObsTermCfg]:
    # §3 critic (286) + HS object additions (pose, velocity as a pure rotation) + privileged terms
    return critic_obs_terms() + [ObsTermCfg(n) for n in (
        "object_pos_b", "object_ori_b", "object_lin_vel_b", "object_ang_vel_b", "object_command",
        "object_pos_error_b", "contact_schedule", "object_contact_forces", "static_object_pos_b",
        "static_object_ori_b")]


def _box_observations() -> ObservationCfg:
    return ObservationCfg(policy=_box_policy_obs(), critic=_box_critic_obs())


def _box_rewards() -> dict[str, RewardTermCfg]:
    return {
        **reward_terms(),
        # §4 HS object terms, plus FK's fine object position (σ 0.12 there): the ≤ 8 cm target
        # needs a gradient at a few cm, where exp(−e²/0.3²) is flat (0.93 at 8 cm; σ 0.1: 0.53)
        "object_pos": RewardTermCfg("object_position_error_exp", 1.0, {"sigma": 0.3}),
        "object_pos_fine": RewardTermCfg("object_position_error_exp", 1.0, {"sigma": 0.1}),
        "object_ori": RewardTermCfg("object_orientation_error_exp", 1.0, {"sigma": 0.4}),
        # §4 FK object velocity tracking
        "object_lin_vel": RewardTermCfg("object_linear_velocity_error_exp", 0.5, {"sigma": 0.5}),
        "object_ang_vel": RewardTermCfg("object_angular_velocity_error_exp", 0.5, {"sigma": 0.3}),
        # §4 HDMI force set-point per hand, gated by the robot–object windows; F_th sized to hold
        # this env's box by friction at the reference's acceleration (×1.5), HDMI's 10 N at least
        "hand_contact": RewardTermCfg("hand_grip_force_setpoint", 1.0, {
            "sigma_pos_m": 0.3, "tolerance_m": 0.05, "sigma_force_n": 40.0, "gain": 5.0,
            "min_force_n": 10.0, "max_force_n": 60.0, "safety": 1.5}),
        # object–support contact gated by the object–support windows (FK weight 0.5)
        "support_contact": RewardTermCfg("support_contact_force_setpoint", 0.5, {
            "force_threshold_n": 5.0, "sigma_force_n": 10.0, "gain": 5.0}),
    }


def _box_terminations() -> dict[str, TerminationTermCfg]:
    return {**termination_terms(), "object_pos": TerminationTermCfg("object_position_error", {"threshold_m": 0.25})}


@dataclass
class BoxEnvCfg(TrackEnvCfg):
    sim: SimCfg = field(default_factory=_box_sim)
    command: CommandCfg = field(default_factory=_box_command)
    observations: ObservationCfg = field(default_factory=_box_observations)
    rewards: dict[str, RewardTermCfg] = field(default_factory=_box_rewards)
    terminations: dict[str, TerminationTermCfg] = field(default_factory=_box_terminations)
    objects: ObjectsCfg = field(default_factory=ObjectsCfg)


def load_box_config(path: str | Path | None = None, overrides: dict | None = None) -> BoxEnvCfg:
    """As ``load_track_config`` for OTR-G1-BoxTrack-v0 (default ``configs/env/box.yaml``);
    ``observations.actor`` names one of ``BOX_ACTORS`` as the policy's terms unless
    ``observations.policy`` lists them."""
    data = merge(load_yaml_mapping(path, BOX_CONFIG, "environment"), overrides)
    observations = dict(data.get("observations") or {})
    actor = observations.pop("actor", None)
    if actor is not None:
        if actor not in BOX_ACTORS:
            raise ValueError(f"{path or BOX_CONFIG}: observations.actor '{actor}' is none of {sorted(BOX_ACTORS)}")
        if "policy" not in (overrides or {}).get("observations", {}):
            observations["policy"] = [{"fn": t.fn, "noise": t.noise} for t in BOX_ACTORS[actor]()]
        data = {**data, "observations": observations}
    return from_dict(BoxEnvCfg, data, "box")

