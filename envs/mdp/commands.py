"""The reference command: which clip and frame each env tracks, and how episodes start.

Timing convention (as in BeyondMimic's in-step resets): ``frame`` is the *target* frame, the
one the observation shows and the next step's rewards compare the robot with. A (re)start
places the robot on ``start_frame`` t₀ and sets ``frame`` = t₀ + 1; every step then advances
``frame`` by one.

Start frames follow BeyondMimic's adaptive sampling (docs/environment.md §2). Each clip c of T_c frames
has n_c = ⌊T_c / (fps·bin_duration)⌋ + 1 bins. A termination adds 1 to the bin of the env's
target frame; every step the per-bin failure rate follows f ← α·cur + (1−α)·f. A start bin is
drawn with p(bin) ∝ Σ_k λᵏ·(f + r/n_c)[bin + k] (k < kernel size, clamped inside the clip),
then t₀ = ⌊(j + U)/n_c · (T_c − 2)⌋ for local bin j (T_c − 2 rather than the spec's T_c − 1 so
that the first target t₀ + 1 exists). ``adaptive_floor = "relative"`` (ours) scales the floor r/n_c
by max(Σ_c f, 1), the clip's failure mass: §2's absolute floor is a count, negligible beside the
tens of failures a step of thousands of envs, and a bin that stops failing then stops being
started from, so it is forgotten; relative, it keeps r/(n_c(1 + r)) of the clip's starts. With
several clips (ours) a clip is drawn first:
p(c) = β/C + (1 − β)·m_c/Σm, where m_c is the clip's mass under that rule and β the
``library_clip_floor``, then a bin of the clip by the rule; β = 0 is one distribution over all
bins, and with no failures every clip gets the same mass either way. The floor matters because
failure counts feed back on themselves: a clip the policy cannot track gets more starts, hence
more failures, and took almost all starts of a library without it.

Everything is batched over envs and masked (``torch.where``) rather than indexed by the ids
of the envs to reset, so no step needs a device→host synchronisation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from envs.config import CommandCfg
from envs.mdp.motion import MotionLibrary
from otr_gym import robot
from otr_gym.rotations import quat_apply_inverse, quat_from_euler_xyz, quat_mul

START_MODES = ("adaptive", "uniform", "zero")
FLOOR_MODES = ("absolute", "relative")


def start_bin_counts(clip_length: torch.Tensor, frames_per_bin: float) -> torch.Tensor:
    """(C,) long: each clip's n_c = ⌊T_c / frames_per_bin⌋ + 1 start bins (``clip_length`` (C,) frames)."""
    return torch.div(clip_length, frames_per_bin, rounding_mode="floor").long() + 1


def local_bins(frame: torch.Tensor, bin_count: torch.Tensor, clip_length: torch.Tensor) -> torch.Tensor:
    """The bin of its clip (0 … n_c − 1) that each ``frame`` falls in: ⌊frame · n_c / T_c⌋,
    the last frame held in the last bin. All arguments broadcast (long tensors)."""
    local = torch.div(frame * bin_count, clip_length, rounding_mode="floor")
    return torch.minimum(local, bin_count - 1)


def bin_clips(bin_count: torch.Tensor) -> torch.Tensor:
    """(B,) long: the clip of each bin of a library whose clips have ``bin_count`` (C,) bins."""
    return torch.repeat_interleave(torch.arange(bin_count.numel(), device=bin_count.device), bin_count)


def start_probabilities(failure_rate: torch.Tensor, bin_count: torch.Tensor, bin_clip: torch.Tensor,
                        cfg: CommandCfg) -> torch.Tensor:
    """(B,) probability that a start falls in each bin (summing to 1) under ``cfg``'s rule (module
    docstring): ``failure_rate`` (B,) failures per step of every clip's bins in library order,
    ``bin_count`` (C,) long the bins of each clip (``start_bin_counts``), ``bin_clip`` (B,) their
    clips (``bin_clips``; passed in, as building it needs a host sync). The sampler draws from
    this; ``agents.failure_bins`` shows it beside the failures, also under another clip floor."""
    clips = bin_count.numel()
    floor = cfg.adaptive_uniform_ratio / bin_count[bin_clip].to(failure_rate.dtype)
    failures = failure_rate if cfg.start == "adaptive" else torch.zeros_like(floor)
    if cfg.adaptive_floor == "relative":
        clip_failures = torch.zeros(clips, dtype=failure_rate.dtype, device=failure_rate.device)
        floor = floor * clip_failures.index_add_(0, bin_clip, failures).clamp_min(1.0)[bin_clip]
    weight = floor + failures
    last_bin = (torch.cumsum(bin_count, 0) - 1)[bin_clip]
    index = torch.arange(weight.numel(), device=weight.device)
    p = torch.zeros_like(weight)
    for k in range(cfg.adaptive_kernel_size):
        p += cfg.adaptive_lambda**k * weight[torch.minimum(index + k, last_bin)]
    mass = torch.zeros(clips, dtype=p.dtype, device=p.device).index_add_(0, bin_clip, p)  # m_c
    beta = cfg.library_clip_floor
    share = beta / clips + (1.0 - beta) * mass / mass.sum()  # p(c)
    return p / mass[bin_clip] * share[bin_clip]


@dataclass(frozen=True)
class RootNoise:
    """The reset noise of the robot root: the start pose is (turn·q, p + shift) about the
    root, its velocities (v + lin, ω + ang), all world frame (N, ·)."""

    shift: torch.Tensor  # (N, 3) m
    turn: torch.Tensor  # (N, 4) wxyz
    lin: torch.Tensor  # (N, 3) m/s
    ang: torch.Tensor  # (N, 3) rad/s
CLIP_END_MODES = ("resample", "truncate")


class MotionCommand:
    """Per-env clip index and frame into a ``MotionLibrary``, with adaptive start sampling."""

    def __init__(self, motion: MotionLibrary, num_envs: int, cfg: CommandCfg, generator: torch.Generator):
        if cfg.start not in START_MODES:
            raise ValueError(f"command.start must be one of {START_MODES}, got '{cfg.start}'")
        if cfg.adaptive_floor not in FLOOR_MODES:
            raise ValueError(f"command.adaptive_floor must be one of {FLOOR_MODES}, got '{cfg.adaptive_floor}'")
        if cfg.on_clip_end not in CLIP_END_MODES:
            raise ValueError(f"command.on_clip_end must be one of {CLIP_END_MODES}, got '{cfg.on_clip_end}'")
        if not 0.0 <= cfg.library_clip_floor <= 1.0:
            raise ValueError(f"command.library_clip_floor must lie in [0, 1], got {cfg.library_clip_floor}")
        self.motion, self.cfg, self.num_envs, self.gen = motion, cfg, num_envs, generator
        device = self.device = motion.device
        self.bin_count = start_bin_counts(motion.clip_length, cfg.fps * cfg.bin_duration_s)  # (C,)
        self.bin_offset = torch.cumsum(self.bin_count, 0) - self.bin_count  # (C,)
        self.bin_clip = bin_clips(self.bin_count)
        num_bins = int(self.bin_clip.numel())
        self.failure_rate = torch.zeros(num_bins, device=device)  # EMA of failures per bin
        self._failures_now = torch.zeros(num_bins, device=device)
        self.clip = torch.arange(num_envs, device=device) % motion.num_clips
        self.start_frame = torch.zeros(num_envs, dtype=torch.long, device=device)
        self.frame = self.start_frame + 1
        lower, upper = robot.soft_joint_limits(cfg.reset_noise.soft_limit_factor)
        self._soft_lower = torch.as_tensor(lower, dtype=torch.float32, device=device)
        self._soft_upper = torch.as_tensor(upper, dtype=torch.float32, device=device)
        # Constants live on the device: a host→device copy inside step would synchronise.
        n = cfg.reset_noise
        self._noise = {k: torch.as_tensor(v, dtype=torch.float32, device=device) for k, v in {
            "pos": n.root_pos_m, "rpy": n.root_rpy_rad, "lin": n.root_lin_vel_mps, "ang": n.root_ang_vel_radps,
            "joint": (n.joint_pos_rad,) * robot.NUM_JOINTS}.items()}
        self._log_num_bins = math.log(max(num_bins, 2))
        self.root_noise: RootNoise | None = None  # of the last start_state

    # ------------------------------------------------------------ current frame
    @property
    def rows(self) -> torch.Tensor:
        """(N,) library row of each env's target frame."""
        return self.motion.clip_start[self.clip] + self.frame

    @property
    def start_rows(self) -> torch.Tensor:
        """(N,) library row of the frame each env was last (re)started on."""
        return self.motion.clip_start[self.clip] + self.start_frame

    @property
    def clip_length(self) -> torch.Tensor:
        """(N,) frames of each env's clip."""
        return self.motion.clip_length[self.clip]

    # ------------------------------------------------------------ episode flow
    def advance(self) -> torch.Tensor:
        """Move every env one frame on; returns (N,) bool: the env ran past the end of its clip
        (its frame is then held at the last one until it is re-sampled)."""
        self.frame += 1
        ended = self.frame >= self.clip_length
        self.frame = torch.minimum(self.frame, self.clip_length - 1)
        return ended

    def record_failures(self, terminated: torch.Tensor) -> None:
        """Count the bins in which ``terminated`` (N,) envs failed (before they are reset)."""
        bins = self.bin_offset[self.clip] + local_bins(self.frame, self.bin_count[self.clip], self.clip_length)
        self._failures_now.index_add_(0, bins, terminated.float())

    def update_failure_rate(self) -> None:
        """Once per step: f ← α·cur + (1−α)·f, then clear the current counts."""
        alpha = self.cfg.adaptive_alpha
        self.failure_rate.mul_(1.0 - alpha).add_(alpha * self._failures_now)
        self._failures_now.zero_()

    def sampling_probabilities(self) -> torch.Tensor:
        """(num_bins,) start-bin distribution (see module docstring)."""
        return start_probabilities(self.failure_rate, self.bin_count, self.bin_clip, self.cfg)

    def clip_probabilities(self) -> torch.Tensor:
        """(C,) total start probability of each clip's bins."""
        p = self.sampling_probabilities()
        return torch.zeros(self.motion.num_clips, device=self.device).index_add_(0, self.bin_clip, p)

    def sampling_entropy(self) -> torch.Tensor:
        """Normalised entropy (0-d, in [0, 1]) of the start distribution (HS logs it)."""
        p = self.sampling_probabilities()
        return -(p * torch.log(p.clamp_min(1e-12))).sum() / self._log_num_bins

    def resample(self, mask: torch.Tensor) -> None:
        """Draw a new (clip, start frame) for the envs in ``mask`` (N,) bool; their target
        becomes the frame after the start."""
        if self.cfg.start == "zero":
            clip = torch.arange(self.num_envs, device=self.device) % self.motion.num_clips
            frame = torch.zeros_like(self.frame)
        else:
            cdf = torch.cumsum(self.sampling_probabilities(), 0)
            u = torch.rand(self.num_envs, device=self.device, generator=self.gen)
            b = torch.searchsorted(cdf, u * cdf[-1]).clamp_max(cdf.numel() - 1)
            clip = self.bin_clip[b]
            n, length = self.bin_count[clip], self.motion.clip_length[clip]
            u = torch.rand(self.num_envs, device=self.device, generator=self.gen)
            phase = (b - self.bin_offset[clip]).float() + u
            frame = (phase / n.float() * (length - 2).float()).long().clamp(max=length - 2)
        self.clip = torch.where(mask, clip, self.clip)
        self.start_frame = torch.where(mask, frame, self.start_frame)
        self.frame = torch.where(mask, frame + 1, self.frame)

    # ------------------------------------------------------------ robot state at the start frame
    def start_state(self, noise: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """(qpos (N, 36), qvel (N, 35)) of every env's start frame, plus the uniform reset
        noise of §2 when ``noise`` (kept in ``root_noise`` for objects that move with the
        robot). qvel's angular part is in the pelvis frame."""
        m, rows = self.motion, self.start_rows
        pos, quat = m.root_pos_w[rows], m.root_quat_w[rows]
        lin, ang = m.root_lin_vel_w[rows], m.root_ang_vel_w[rows]
        joints = m.joint_pos[rows]
        self.root_noise = None
        if noise:
            rpy = self._uniform("rpy")
            turn = quat_from_euler_xyz(rpy[:, 0], rpy[:, 1], rpy[:, 2])
            shift = self._uniform("pos")
            pos = pos + shift
            quat = quat_mul(turn, quat)
            kick_lin = self._uniform("lin")
            lin = lin + kick_lin
            kick_ang = self._uniform("ang")
            ang = ang + kick_ang
            joints = torch.clamp(joints + self._uniform("joint"), self._soft_lower, self._soft_upper)
            self.root_noise = RootNoise(shift, turn, kick_lin, kick_ang)
        qpos = torch.cat([pos, quat, joints], dim=-1)
        qvel = torch.cat([lin, quat_apply_inverse(quat, ang), m.joint_vel[rows]], dim=-1)
        return qpos, qvel

    def _uniform(self, key: str) -> torch.Tensor:
        h = self._noise[key]
        return (2.0 * torch.rand(self.num_envs, h.numel(), device=self.device, generator=self.gen) - 1.0) * h
