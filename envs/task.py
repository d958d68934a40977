"""The batched tracking MDP (one implementation for every backend and both env classes).

Per ``step(actions)`` (N envs at once, torch on the backend's device, no host sync):

1. clip the raw actions; PD targets q* = q_default(+bias) + ACTION_SCALE·a go to the MJCF
   position actuators (kp/kd/effort of docs/environment.md §1) for ``decimation`` physics steps, after a
   velocity push for envs whose push timer ran out (domain randomisation);
2. build the ``TrackingState`` (robot after physics vs. the target frame) and evaluate the
   terminations and the rewards (Σ weight·value·dt) listed in the config;
3. count failures for adaptive sampling, advance every env's reference by one frame;
4. time-out (episode length) and, with ``on_clip_end: truncate``, clip end truncate; with
   ``on_clip_end: resample`` an env past its clip's end is re-started (robot reset onto a newly
   sampled frame) without ending the episode (docs/environment.md §2);
5. with ``autoreset`` (vector env, same-step mode) finished envs are reset in the same call;
6. observations of the new state.

Non-finite worlds: a world whose physics diverged in the step (``backend.unstable``: NaN/inf or
absurd values in qpos/qvel, or a state the simulator reset by itself) or whose observation came
out non-finite at the previous step ends with the termination ``non_finite`` and is reset like
any other; its reward is 0 and it is left out of the logged means, so one bad world never
poisons the batch. Non-finite observation entries are zeroed when they are returned (the world
is reset at the next step). ``log["metric/non_finite_worlds"]`` counts them per step.
"""

from __future__ import annotations

import torch

from envs.backends.base import PhysicsBackend
from envs.config import TrackEnvCfg
from envs.mdp import observations as obs_terms
from envs.mdp import rewards as reward_terms
from envs.mdp import terminations as termination_terms
from envs.mdp.commands import MotionCommand
from envs.mdp.motion import MotionLibrary
from envs.mdp.randomization import DomainRandomizer
from envs.mdp.state import TrackingState, aligned_targets, root_velocities_b
from envs.step_graph import StepGraph
from envs.terrain import SceneTerrain, flat
from otr_gym import robot

OBS_GROUPS = ("policy", "critic")
NON_FINITE = "non_finite"  # the built-in termination of worlds whose physics or observation diverged


def masked_mean(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean over the envs in ``valid`` (N,) bool of ``x`` (N, ...) (0-d; 0 when none is valid)."""
    x = torch.where(valid.view(-1, *([1] * (x.dim() - 1))), x, torch.zeros_like(x))
    per_env = x.reshape(x.shape[0], -1).mean(-1)
    return per_env.sum() / valid.sum().clamp_min(1)


def _resolve(module, name: str, kind: str):
    """The term function ``name`` defined in ``module`` (names it merely imports do not count)."""
    fn = getattr(module, name, None)
    if not callable(fn) or name.startswith("_") or getattr(fn, "__module__", None) != module.__name__:
        raise ValueError(f"unknown {kind} term function '{name}' (not defined in {module.__name__})")
    return fn


class TrackingTask:
    """Tracking MDP for ``backend.num_worlds`` envs on ``motion`` clips, configured by ``cfg``."""

    def __init__(self, cfg: TrackEnvCfg, motion: MotionLibrary, backend: PhysicsBackend, seed: int = 0,
                 autoreset: bool = True, terrain: SceneTerrain | None = None):
        self.cfg, self.motion, self.backend, self.autoreset = cfg, motion, backend, autoreset
        #: the terrain in ``backend``'s model and every clip's origin (``motion`` is shifted by it)
        self.terrain = terrain if terrain is not None else flat(motion.num_clips)
        self.num_envs, self.device = backend.num_worlds, backend.device
        self.num_actions = robot.NUM_JOINTS
        self.step_dt = float(backend.model.opt.timestep) * cfg.sim.decimation
        self.max_episode_length = int(round(cfg.sim.episode_length_s / self.step_dt))
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(seed)

        c = cfg.command
        if c.anchor_body not in c.tracked_bodies:
            raise ValueError(f"command.anchor_body '{c.anchor_body}' must be one of the tracked bodies")
        missing = [b for b in c.end_effectors if b not in c.tracked_bodies]
        if missing:
            raise ValueError(f"command.end_effectors {missing} must be tracked bodies")
        self._body_ids = torch.as_tensor(backend.body_ids(c.tracked_bodies), device=self.device)
        self._anchor = c.tracked_bodies.index(c.anchor_body)
        self._end_effectors = torch.as_tensor([c.tracked_bodies.index(b) for b in c.end_effectors],
                                              device=self.device)
        self.command = MotionCommand(motion, self.num_envs, c, self.generator)

        self._action_scale = torch.as_tensor(robot.ACTION_SCALE, dtype=torch.float32, device=self.device)
        self._obs_non_finite = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        self.action = torch.zeros(self.num_envs, self.num_actions, device=self.device)
        self.last_action = torch.zeros_like(self.action)
        self.episode_length_buf = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)

        self.randomizer = None
        default = torch.as_tensor(robot.DEFAULT_JOINT_POS, dtype=torch.float32, device=self.device)
        self.default_joint_pos = default.repeat(self.num_envs, 1)
        if cfg.randomization.enabled:
            self.randomizer = DomainRandomizer(cfg.randomization, backend, self.step_dt, self.generator,
                                               extra_friction_geoms=self.terrain.geom_names())
            self.default_joint_pos = self.default_joint_pos + self.randomizer.apply_startup()

        self._rewards = [(n, _resolve(reward_terms, t.fn, "reward"), t.weight, t.params)
                         for n, t in cfg.rewards.items()]
        self._terminations = [(n, _resolve(termination_terms, t.fn, "termination"), t.params)
                              for n, t in cfg.terminations.items()]
        groups = {g: getattr(cfg.observations, g) for g in OBS_GROUPS}
        self._obs = {g: [(t.fn, _resolve(obs_terms, t.fn, "observation"), t.noise) for t in terms]
                     for g, terms in groups.items()}

        self.state: TrackingState
        self.tracking_state: TrackingState
        #: the step as one CUDA graph, captured on its first calls (envs.step_graph)
        self.step_graph = (StepGraph(self, self._step) if cfg.sim.cuda_graph and self.device.type == "cuda"
                           and backend.joins_cuda_graphs else None)
        self.reset()
        self.obs_layout = {g: [(name, int(fn(self.state).shape[-1])) for name, fn, _ in terms]
                           for g, terms in self._obs.items()}
        self.obs_dims = {g: sum(d for _, d in layout) for g, layout in self.obs_layout.items()}

    # ------------------------------------------------------------ episode control
    def reset(self, mask: torch.Tensor | None = None, seed: int | None = None) -> dict[str, torch.Tensor]:
        """Reset the envs in ``mask`` (all if None): new start frame, robot on it (plus reset
        noise), cleared action history and episode length. Returns the observations."""
        if seed is not None:
            self.generator.manual_seed(seed)
        if mask is None:
            mask = torch.ones(self.num_envs, dtype=torch.bool, device=self.device)
        self._restart(mask)
        self._clear_episode(mask)
        self.state = self.tracking_state = self._build_state()
        return self._finite_observations(self.state)

    def step(self, actions: torch.Tensor):
        """Advance all envs by one policy step. Returns (obs, reward (N,), terminated (N,) bool,
        truncated (N,) bool, extras) — see ``TrackEnv``/``TrackVecEnv`` for the extras. With
        ``step_graph`` the step is a CUDA graph replay; the results are the same."""
        if self.step_graph is not None:
            return self.step_graph(actions)
        return self._step(actions)

    def _step(self, actions: torch.Tensor):
        actions = torch.as_tensor(actions, dtype=torch.float32, device=self.device)
        clip = self.cfg.action.clip
        self.last_action = self.action
        self.action = actions.clamp(-clip, clip)
        if self.randomizer is not None:
            self.randomizer.push()
        self.backend.step(self.default_joint_pos + self._action_scale * self.action)
        self.episode_length_buf += 1

        s = self.tracking_state = self._build_state()
        bad = self.backend.unstable | self._obs_non_finite
        valid = ~bad
        fired = {name: fn(s, **params) & valid for name, fn, params in self._terminations}
        fired[NON_FINITE] = bad
        terminated = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        for flag in fired.values():
            terminated |= flag
        zero = torch.zeros(self.num_envs, device=self.device)
        terms = {name: torch.where(valid, fn(s, **params) * (weight * self.step_dt), zero)
                 for name, fn, weight, params in self._rewards}
        reward = torch.stack(list(terms.values())).sum(0) if terms else zero

        self.command.record_failures(terminated)
        self.command.update_failure_rate()
        segment_clip, segment_frames = self.command.clip, self.command.frame - self.command.start_frame
        clip_ended = self.command.advance()
        truncated = self.episode_length_buf >= self.max_episode_length
        if self.cfg.command.on_clip_end == "truncate":
            truncated = truncated | clip_ended
        truncated = truncated & ~terminated
        done = terminated | truncated
        restart = clip_ended & ~done

        extras = {
            "time_outs": truncated,
            "success": self._success(terminated, truncated, clip_ended),
            "terminations": fired,
            "log": self._log(terms, fired, s, valid),
            # the stretch of clip each env tracked since its last (re)start: on which clip, how
            # many frames so far, and whether it ended now (termination, truncation, clip end)
            "segment": {"clip": segment_clip, "frames": segment_frames, "ended": done | clip_ended},
        }
        if self.autoreset:
            if self.cfg.final_obs:
                final = self.observations(self._build_state())
                extras["final_obs"] = {g: torch.nan_to_num(o, nan=0.0, posinf=0.0, neginf=0.0)
                                       for g, o in final.items()}
                extras["_final_obs"] = done
            restart = restart | done
        self._restart(restart)
        if self.autoreset:
            self._clear_episode(done)
        self.state = self._build_state()
        return self._finite_observations(self.state), reward, terminated, truncated, extras

    def observations(self, s: TrackingState) -> dict[str, torch.Tensor]:
        """{"policy": (N, 154), "critic": (N, 286)} with the default config; each term with a
        noise level gets uniform ±noise when noise is enabled, then the group is clipped."""
        cfg = self.cfg.observations
        values: dict[str, torch.Tensor] = {}  # a term shared by both groups is computed once
        out = {}
        for group, terms in self._obs.items():
            parts = []
            for name, fn, noise in terms:
                if name not in values:
                    values[name] = fn(s)
                x = values[name]
                if cfg.noise_enabled and noise > 0.0:
                    x = x + (2.0 * torch.rand(x.shape, device=self.device, generator=self.generator) - 1.0) * noise
                parts.append(x)
            out[group] = torch.cat(parts, dim=-1).clamp(-cfg.clip, cfg.clip)
        return out

    def _finite_observations(self, s: TrackingState) -> dict[str, torch.Tensor]:
        """``observations`` with non-finite entries zeroed; their worlds are reset at the next step."""
        obs = self.observations(s)
        bad = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        for o in obs.values():
            bad |= ~torch.isfinite(o).all(dim=-1)
        self._obs_non_finite = bad
        return {g: torch.nan_to_num(o, nan=0.0, posinf=0.0, neginf=0.0) for g, o in obs.items()}

    # ------------------------------------------------------------ spec for export / evaluation
    def policy_metadata(self) -> dict:
        """What a deployment or ONNX export needs to run the policy outside this env."""
        return {
            "joint_names": list(robot.JOINT_NAMES),
            "default_joint_pos": robot.DEFAULT_JOINT_POS.tolist(),
            "joint_stiffness": robot.KP.tolist(),
            "joint_damping": robot.KD.tolist(),
            "effort_limit": robot.EFFORT_LIMIT.tolist(),
            "action_scale": robot.ACTION_SCALE.tolist(),
            "action_clip": self.cfg.action.clip,
            "observation_names": {g: [n for n, _ in layout] for g, layout in self.obs_layout.items()},
            "observation_dims": {g: [d for _, d in layout] for g, layout in self.obs_layout.items()},
            "observation_clip": self.cfg.observations.clip,
            "anchor_body_name": self.cfg.command.anchor_body,
            "body_names": list(self.cfg.command.tracked_bodies),
            "fps": self.motion.fps,
            "policy_dt": self.step_dt,
            "physics_dt": float(self.backend.model.opt.timestep),
            "decimation": self.cfg.sim.decimation,
            **({"terrain": self.terrain.info()} if self.terrain.terrains else {}),
        }

    # ------------------------------------------------------------ internals
    def _restart(self, mask: torch.Tensor) -> None:
        """New start frame for the envs in ``mask`` and the robot put on it (episode goes on)."""
        if self.device.type == "cpu" and not bool(mask.any()):
            return  # free to test on the host; on a GPU the masked path runs to avoid a sync
        self.command.resample(mask)
        qpos, qvel = self.start_state()
        self.backend.reset(mask, qpos, qvel)

    def start_state(self, noise: bool | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Full (qpos, qvel) rows of every env at its start frame, with the reset noise when
        ``noise`` (default: the config's ``reset_noise_enabled``)."""
        return self.command.start_state(noise=self.cfg.command.reset_noise_enabled if noise is None else noise)

    def _success(self, terminated: torch.Tensor, truncated: torch.Tensor, clip_ended: torch.Tensor) -> torch.Tensor:
        """(N,) bool: the episode ended this step without a termination (time-out or clip end)."""
        return truncated

    def _clear_episode(self, mask: torch.Tensor) -> None:
        rows = mask[:, None]
        # new action tensors (states built earlier keep theirs); the length buffer in place,
        # since trainers hold on to it
        self.action = self.action.masked_fill(rows, 0.0)
        self.last_action = self.last_action.masked_fill(rows, 0.0)
        self.episode_length_buf.masked_fill_(mask, 0)
        if self.randomizer is not None:
            self.randomizer.reset(mask)

    def _build_state(self) -> TrackingState:
        b, m, ids, rows = self.backend, self.motion, self._body_ids, self.command.rows
        # Copies: backend views change in place when the envs are stepped or reset.
        qpos, qvel = b.qpos.clone(), b.qvel.clone()
        body_pos, body_quat = b.body_pos_w[:, ids], b.body_quat_w[:, ids]
        ref_pos, ref_quat = m.body_pos_w[rows], m.body_quat_w[rows]
        aligned_pos, aligned_quat = aligned_targets(body_pos[:, self._anchor], body_quat[:, self._anchor],
                                                    ref_pos, ref_quat, self._anchor)
        lin_b, ang_b = root_velocities_b(qpos, qvel)
        return TrackingState(
            body_names=self.cfg.command.tracked_bodies, anchor=self._anchor, end_effectors=self._end_effectors,
            contact_body_names=b.contact_body_names,
            joint_pos=qpos[:, 7:7 + robot.NUM_JOINTS], joint_vel=qvel[:, 6:6 + robot.NUM_JOINTS],
            root_quat_w=qpos[:, 3:7],
            root_lin_vel_b=lin_b, root_ang_vel_b=ang_b,
            body_pos_w=body_pos, body_quat_w=body_quat,
            body_lin_vel_w=b.body_lin_vel_w[:, ids], body_ang_vel_w=b.body_ang_vel_w[:, ids],
            contact_force_n=b.contact_force_n.clone(),
            ref_joint_pos=m.joint_pos[rows], ref_joint_vel=m.joint_vel[rows],
            ref_body_pos_w=ref_pos, ref_body_quat_w=ref_quat,
            ref_body_lin_vel_w=m.body_lin_vel_w[rows], ref_body_ang_vel_w=m.body_ang_vel_w[rows],
            ref_body_pos_aligned_w=aligned_pos, ref_body_quat_aligned_w=aligned_quat,
            action=self.action, last_action=self.last_action, default_joint_pos=self.default_joint_pos,
        )

    def _log(self, terms: dict[str, torch.Tensor], fired: dict[str, torch.Tensor], s: TrackingState,
             valid: torch.Tensor) -> dict:
        """Means over the ``valid`` (finite) envs as 0-d device tensors (call ``.item()`` only
        when writing a log)."""
        # one reduction for all reward terms and one for all terminations (a kernel each, not one per term)
        log: dict = {}
        if terms:
            rewards = torch.where(valid, torch.stack(list(terms.values())), 0.0).sum(-1) / valid.sum().clamp_min(1)
            log.update({f"reward/{n}": rewards[i] for i, n in enumerate(terms)})
        rates = torch.stack(list(fired.values())).float().mean(-1)
        log.update({f"termination/{n}": rates[i] for i, n in enumerate(fired)})
        log["metric/anchor_pos_error_m"] = masked_mean(torch.linalg.norm(s.ref_anchor_pos_w - s.anchor_pos_w, dim=-1),
                                                       valid)
        log["metric/body_pos_error_m"] = masked_mean(torch.linalg.norm(s.ref_body_pos_aligned_w - s.body_pos_w, dim=-1),
                                                     valid)
        log["metric/joint_pos_error_rad"] = masked_mean(torch.abs(s.ref_joint_pos - s.joint_pos), valid)
        log["metric/sampling_entropy"] = self.command.sampling_entropy()
        log["metric/non_finite_worlds"] = fired[NON_FINITE].sum()
        return log
