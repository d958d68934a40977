"""Configuration of the tracking MDP (OTR-G1-Track-v0), which OTR-G1-BoxTrack-v0 extends
with its objects (``envs.config.box``).

Defaults are the numbers of docs/environment.md (section cited per field);
``configs/env/track.yaml`` lists the same values for users to edit and is loaded by
``load_track_config``. MDP terms are named by function: a reward ``fn`` is looked up in
``envs.mdp.rewards``, a termination in ``envs.mdp.terminations``, an observation in
``envs.mdp.observations``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Self

from envs.collision import CollisionCfg
from otr_gym import robot
from otr_gym.config import from_dict, load_yaml_mapping, merge

DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "env" / "track.yaml"


@dataclass
class SimCfg:
    decimation: int = 4  # §1 Timing: 200 Hz physics, 50 Hz policy
    episode_length_s: float = 10.0  # §1 Timing
    # Per-world MuJoCo-Warp buffers (§1: MJ 35/250). A flat stance alone makes 28 contacts
    # (14 foot capsules × 2 against the plane), so nconmax leaves room for knees/hands.
    nconmax: int = 40
    njmax: int = 256
    #: The whole env step as one replayed CUDA graph (warp backend on a CUDA device;
    #: ``envs.step_graph``) instead of the MDP's ~700 small torch kernels launched one by one.
    #: Off: on an H100 (2026-12-08) it gained 3 % (481 k against 467 k env-steps/s at 8192 envs)
    #: and its agreement with the eager step is not shown (docs/environment.md §1).
    cuda_graph: bool = False
    #: Bodies with a contact-force sensor: every G1 body that has collision geometry.
    contact_bodies: tuple[str, ...] = (
        "pelvis", "left_hip_roll_link", "left_hip_yaw_link", "left_knee_link", "left_ankle_roll_link",
        "right_hip_roll_link", "right_hip_yaw_link", "right_knee_link", "right_ankle_roll_link", "torso_link",
        "left_shoulder_yaw_link", "left_elbow_link", "left_wrist_pitch_link", "left_wrist_yaw_link",
        "right_shoulder_yaw_link", "right_elbow_link", "right_wrist_pitch_link", "right_wrist_yaw_link",
    )


@dataclass
class ActionCfg:
    clip: float = 100.0  # §1 Action: HS clips raw actions to ±100 (MJ does not clip)


@dataclass
class ResetNoiseCfg:
    """Uniform half-widths added to the reference state at reset (§2 Reset noise)."""

    root_pos_m: tuple[float, float, float] = (0.05, 0.05, 0.01)
    root_rpy_rad: tuple[float, float, float] = (0.1, 0.1, 0.2)
    root_lin_vel_mps: tuple[float, float, float] = (0.5, 0.5, 0.2)
    root_ang_vel_radps: tuple[float, float, float] = (0.52, 0.52, 0.78)
    joint_pos_rad: float = 0.1
    soft_limit_factor: float = 0.9  # joints are clipped to the soft limits (§4: 90 % of range)


@dataclass
class CommandCfg:
    fps: float = 50.0  # §2: the clip advances one frame per 50 Hz policy step
    anchor_body: str = robot.ANCHOR_BODY  # §2
    tracked_bodies: tuple[str, ...] = robot.TRACKED_BODIES  # §2 (14 bodies)
    end_effectors: tuple[str, ...] = robot.END_EFFECTORS  # §2: ankle_roll and wrist_yaw links
    #: "adaptive" (§2 BeyondMimic failure-driven bins), "uniform" (bins without failures) or
    #: "zero" (frame 0, clip = env index mod #clips: evaluation).
    start: str = "adaptive"
    #: "resample" (§2: re-sample and reset the robot, episode continues) or "truncate" (episode ends).
    on_clip_end: str = "resample"
    bin_duration_s: float = 1.0  # §2: n = ⌊T/50⌋ + 1 bins at 50 fps
    adaptive_alpha: float = 0.001  # §2: f ← α·cur + (1−α)·f
    #: r of the floor (§2: 0.1; ours 0.5 with the relative floor: half of a clip's starts spread evenly).
    adaptive_uniform_ratio: float = 0.5
    #: "absolute" (§2: the floor r/n is added to failure *counts* per step) or "relative" (ours,
    #: the default: r/n times the clip's failure mass Σf when that exceeds 1, so a bin without
    #: failures keeps r/(n(1+r)) of the clip's starts however many envs fail). With thousands of
    #: envs Σf is tens per step and §2's floor vanishes: a bin the policy stopped failing in gets
    #: no starts, hence no failures, and is forgotten. It happened to the box clip's first second
    #: (box.yaml) and to the AMASS jog's: under §2's floor its first second drew 1.7 % of the
    #: starts and a 19-minute policy fell at frame 60 from frame 0; with this one, 100 % and
    #: 45.4 mm (docs/results/real_mocap.md).
    adaptive_floor: str = "relative"
    adaptive_kernel_size: int = 1  # §2: λⁱ kernel of size 1 (no smoothing)
    adaptive_lambda: float = 0.8  # §2
    #: Motion libraries (ours): this share of the starts is spread evenly over the clips, the
    #: rest follows each clip's failures. Without it one clip the policy cannot track yet (then
    #: Holosoma's crawl, its slope not yet simulated) drew 93 % of all starts after 700
    #: iterations of an 8-clip library and starved the others. 0 = one distribution over all bins (§2).
    #: One clip: no effect.
    library_clip_floor: float = 0.5
    #: Clips shorter than this are rejected at load (a half-second clip is almost surely a bad export).
    min_clip_frames: int = 25
    reset_noise: ResetNoiseCfg = field(default_factory=ResetNoiseCfg)
    reset_noise_enabled: bool = True


@dataclass
class ObsTermCfg:
    fn: str
    noise: float = 0.0  # uniform ±noise, actor terms only (§3)


def policy_obs_terms(state_estimation: bool = False) -> list[ObsTermCfg]:
    """The actor's observation terms with their noise (the box task's actor adds its own)."""
    # §3 Actor, HS = MJ "No-State-Estimation": 58 + 6 + 3 + 29 + 29 + 29 = 154; with state
    # estimation (MJ's default) + anchor_pos_b and base_lin_vel_b = 160
    sensed = [ObsTermCfg("anchor_pos_b", 0.25)] if state_estimation else []
    moving = [ObsTermCfg("base_lin_vel_b", 0.5)] if state_estimation else []
    return [ObsTermCfg("command", 0.0), *sensed, ObsTermCfg("anchor_ori_b", 0.05), *moving,
            ObsTermCfg("base_ang_vel_b", 0.2), ObsTermCfg("joint_pos_rel", 0.01), ObsTermCfg("joint_vel", 0.5),
            ObsTermCfg("last_action", 0.0)]


def critic_obs_terms() -> list[ObsTermCfg]:
    """The critic's observation terms (the box task's critic adds its own)."""
    # §3 Critic: 58 + 3 + 6 + 42 + 84 + 3 + 3 + 29 + 29 + 29 = 286, no noise
    return [ObsTermCfg(n) for n in ("command", "anchor_pos_b", "anchor_ori_b", "body_pos_b", "body_ori_b",
                                    "base_lin_vel_b", "base_ang_vel_b", "joint_pos_rel", "joint_vel", "last_action")]


@dataclass
class ObservationCfg:
    policy: list[ObsTermCfg] = field(default_factory=policy_obs_terms)
    critic: list[ObsTermCfg] = field(default_factory=critic_obs_terms)
    clip: float = 100.0  # §3: HS clips observations at ±100
    noise_enabled: bool = True


@dataclass
class RewardTermCfg:
    fn: str
    weight: float
    params: dict[str, Any] = field(default_factory=dict)


def reward_terms() -> dict[str, RewardTermCfg]:
    """The tracking reward terms by name (the box task adds object terms)."""
    # §4: tracking terms exp(−e/σ²), weights; all scaled by weight·value·dt (§1 Timing)
    return {
        "anchor_pos": RewardTermCfg("anchor_position_error_exp", 0.5, {"sigma": 0.3}),
        "anchor_ori": RewardTermCfg("anchor_orientation_error_exp", 0.5, {"sigma": 0.4}),
        "body_pos": RewardTermCfg("body_position_error_exp", 1.0, {"sigma": 0.3}),
        "body_ori": RewardTermCfg("body_orientation_error_exp", 1.0, {"sigma": 0.4}),
        "body_lin_vel": RewardTermCfg("body_linear_velocity_error_exp", 1.0, {"sigma": 1.0}),
        "body_ang_vel": RewardTermCfg("body_angular_velocity_error_exp", 1.0, {"sigma": 3.14}),
        "action_rate": RewardTermCfg("action_rate_l2", -0.1),
        "joint_limits": RewardTermCfg("joint_pos_limits", -10.0, {"soft_limit_factor": 0.9}),
        "undesired_contacts": RewardTermCfg("undesired_contacts", -0.1, {
            "threshold_n": 1.0, "exclude": ["ankle_roll", "wrist_yaw"]}),
    }


@dataclass
class TerminationTermCfg:
    fn: str
    params: dict[str, Any] = field(default_factory=dict)


def termination_terms() -> dict[str, TerminationTermCfg]:
    """The tracking termination terms by name (the box task adds the object's)."""
    # §5, MJ column
    return {
        "anchor_height": TerminationTermCfg("anchor_height_error", {"threshold_m": 0.25}),
        "anchor_ori": TerminationTermCfg("anchor_gravity_error", {"threshold": 0.8}),
        "ee_height": TerminationTermCfg("end_effector_height_error", {"threshold_m": 0.25}),
    }


@dataclass
class RandomizationCfg:
    """Domain randomisation (§6, MJ column unless noted)."""

    enabled: bool = True
    #: Sliding friction, one draw per env shared by the foot geoms, the ground and the terrain
    #: (MuJoCo combines a pair's friction by max, so the ground must take the same draw).
    friction_range: tuple[float, float] = (0.3, 1.2)
    friction_geoms: tuple[str, ...] = ("ground/ground",) + tuple(
        f"{side}_foot{i}_collision" for side in ("left", "right") for i in range(1, 8))
    com_body: str = robot.ANCHOR_BODY
    com_offset_m: tuple[float, float, float] = (0.025, 0.05, 0.05)  # ± per axis, body frame
    push_interval_s: tuple[float, float] = (1.0, 3.0)
    push_lin_vel_mps: tuple[float, float, float] = (0.5, 0.5, 0.2)  # ± per axis, world
    push_ang_vel_radps: tuple[float, float, float] = (0.52, 0.52, 0.78)  # ± per axis, world
    #: HS default-pose bias: shifts both the PD target and the joint_pos_rel observation.
    joint_offset_rad: float = 0.01


@dataclass
class TerrainCfg:
    """Terrain of references recorded on uneven ground (``envs.terrain``; ours; docs/environment.md §2)."""

    #: Clip -> terrain mesh file (any trimesh-readable format; metres, in the clip's own world
    #: frame, z up, floor at z = 0). A clip is named by its file stem (its label), a trailing
    #: part of its path ("holosoma/motion_crawl_slope", ".npz" optional) or its path. Clip
    #: lists can give it per line instead (``crawl.npz terrain=slope.obj``).
    meshes: dict[str, str] = field(default_factory=dict)
    #: Libraries: each terrain gets its own origin this far apart along +x (m); clips without
    #: terrain stay at the origin.
    library_spacing_m: float = 50.0
    #: A clip whose reference (bounding box grown by this, m) comes near another origin's
    #: terrain is refused: its robot could wander onto it.
    reach_margin_m: float = 2.0
    #: Collision pieces whose top lies at most this high (m) are dropped: the floor plane
    #: provides them (a mesh's floor slab).
    floor_tolerance_m: float = 1e-3
    #: MuJoCo-Warp per-world buffers of a model with terrain, at least (``sim`` values when
    #: larger): a body on the terrain can touch the ramp and the floor plane at once (Holosoma's
    #: crawl on its slope, replayed kinematically: up to 38 contacts in a frame; 40 is the flat
    #: default), 4 rows per pyramidal contact.
    nconmax: int = 64
    njmax: int = 400
    collision: CollisionCfg = field(default_factory=CollisionCfg)


@dataclass
class TrackEnvCfg:
    sim: SimCfg = field(default_factory=SimCfg)
    action: ActionCfg = field(default_factory=ActionCfg)
    command: CommandCfg = field(default_factory=CommandCfg)
    observations: ObservationCfg = field(default_factory=ObservationCfg)
    rewards: dict[str, RewardTermCfg] = field(default_factory=reward_terms)
    terminations: dict[str, TerminationTermCfg] = field(default_factory=termination_terms)
    randomization: RandomizationCfg = field(default_factory=RandomizationCfg)
    terrain: TerrainCfg = field(default_factory=TerrainCfg)
    #: Vector env, same-step autoreset: also return the pre-reset observation of finished envs
    #: in info["final_obs"] (Gymnasium convention; costs one more observation pass per step).
    final_obs: bool = True

    def for_evaluation(self) -> Self:
        """A copy for evaluation: start every clip at frame 0, end the episode with the clip,
        no domain randomisation, no observation or reset noise."""
        return replace(
            self,
            command=replace(self.command, start="zero", on_clip_end="truncate", reset_noise_enabled=False),
            observations=replace(self.observations, noise_enabled=False),
            randomization=replace(self.randomization, enabled=False),
        )


def load_track_config(path: str | Path | None = None, overrides: dict | None = None) -> TrackEnvCfg:
    """Read a YAML file (default ``configs/env/track.yaml``; dataclass defaults if that file is
    absent) and apply ``overrides`` (nested dict, same layout) on top."""
    data = merge(load_yaml_mapping(path, DEFAULT_CONFIG, "environment"), overrides)
    return from_dict(TrackEnvCfg, data, "track")
