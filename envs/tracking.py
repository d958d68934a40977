"""OTR-G1-Track-v0: whole-body motion tracking of the 29-DoF Unitree G1 (docs/environment.md).

Two front-ends on one batched MDP (``envs.task.TrackingTask``)::

    import gymnasium, otr_gym
    env = gymnasium.make("OTR-G1-Track-v0", reference="clip.npz", render_mode="rgb_array")
    envs = gymnasium.make_vec("OTR-G1-Track-v0", num_envs=4096, vectorization_mode="vector_entry_point",
                              device="cuda", reference="clips/")

``TrackEnv`` (``make``): one env on CPU MuJoCo, NumPy in/out, no autoreset (Gymnasium's
single-env API; passes ``gymnasium.utils.env_checker.check_env``). ``render()`` returns an
RGB frame of the robot with a translucent ghost of the reference pose.

``TrackVecEnv`` (``make_vec``): N envs on MuJoCo-Warp (``backend="warp"``, ``device`` "cuda"
or "cpu") or on CPU MuJoCo (``backend="mujoco"``). Everything stays on ``device`` as torch
tensors (zero-copy views of the warp state); the physics of one env step is one captured graph.
Autoreset: ``AutoresetMode.SAME_STEP`` (``metadata["autoreset_mode"]``): an env that ends is
reset inside ``step``; the returned observation is its first one of the new episode and,
with ``cfg.final_obs``, ``info["final_obs"]`` holds the last one (rows where
``info["_final_obs"]``).

Common keyword arguments: ``reference`` (file, folder of ``*.npz`` = multi-clip library,
clip list, ``Reference`` or list of them; resampled to 50 fps; bad files raise
``InvalidReferenceError`` naming the file; or ``PreparedClips``, a library read and prepared
once by ``envs.clips.prepare_clips`` or ``agents.library``), ``cfg`` (``TrackEnvCfg``, YAML path or None for
``configs/env/track.yaml``; ``cfg.terrain`` gives clips a terrain mesh, as do ``terrain=``
options in clip lists: ``envs.terrain``), ``evaluation`` (True: no randomisation, no noise,
every clip from frame 0, the episode ends with the clip), ``seed``.

Spaces: observation ``Dict(policy=Box(154), critic=Box(286))`` float32 clipped to ±100
(docs/environment.md §3; layout in ``obs_layout``); action ``Box(29)`` in [−100, 100], joint order
``otr_gym.robot.JOINT_NAMES``; the PD target is q_default + ACTION_SCALE·a (docs/environment.md §1).

Interface for training / evaluation / export (vector env):

- ``num_envs``, ``device``, ``num_actions`` (29), ``obs_dims`` {"policy": 154, "critic": 286},
  ``obs_layout`` (term names and dims per group), ``step_dt`` (0.02 s);
- ``episode_length_buf`` (N,) long, settable (e.g. random initial lengths), ``max_episode_length`` (500);
- ``step`` info: ``time_outs`` (N,) bool (truncations, for bootstrapping), ``success`` (N,)
  bool (the episode ended without a termination), ``terminations`` {name: (N,) bool} (with the
  built-in ``non_finite``: worlds whose physics diverged, reset like any other termination),
  ``segment`` {"clip", "frames", "ended": (N,)} (the stretch of clip tracked since the last
  (re)start, for per-clip statistics),
  ``log`` {"reward/<term>", "termination/<term>", "metric/…": 0-d tensors, means over envs};
- command state: ``command.clip`` (N,) and ``command.frame`` (N,), the *target* frame (shown
  in the observation; the next step's rewards compare the robot with it), ``command.start_frame``
  (the frame the robot was last put on; target = start + 1 right after a reset),
  ``motion`` (the clip library: ``names``, ``clip_length``, per-frame arrays); ``tracking_state``
  (the state the last rewards were computed on, before any reset: ``body_pos_w`` robot and
  ``ref_body_pos_w`` reference positions of the 14 tracked bodies ``body_names``; MPJPE:
  ``envs.mdp.metrics.mpjpe_root_relative(env.tracking_state)``);
- ``policy_metadata()``: joint order, default pose, kp/kd, action scale, observation names and
  dims, observation clip, anchor and tracked bodies, fps, dt — what ONNX export needs.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from envs.backends import build_sim_model, make_backend
from envs.clips import PreparedClips, placed_clips
from envs.config import TrackEnvCfg, load_track_config
from envs.mdp.motion import MotionLibrary, ReferenceSource
from envs.task import TrackingTask
from envs.terrain import contact_buffers

_PER_WORLD_FIELDS = ("geom_friction", "body_ipos")  # randomised per env (§6)


def make_task(reference: ReferenceSource | PreparedClips, num_envs: int, backend: str, device: str,
              cfg: TrackEnvCfg | str | Path | None = None, evaluation: bool = False, seed: int = 0,
              autoreset: bool = True) -> TrackingTask:
    """Load the references (failing fast on bad ones), build the backend and the MDP."""
    if not isinstance(cfg, TrackEnvCfg):
        cfg = load_track_config(cfg)
    if evaluation:
        cfg = cfg.for_evaluation()
    refs, terrain = placed_clips(reference, cfg)
    motion = MotionLibrary.from_references(refs, cfg.command.tracked_bodies, cfg.command.fps)
    model = build_sim_model(cfg.sim.contact_bodies, terrain=terrain)
    physics = make_backend(backend, model, num_envs, device, cfg.sim.decimation, cfg.sim.contact_bodies,
                           *contact_buffers(cfg.sim, cfg.terrain, terrain),
                           per_world_fields=_PER_WORLD_FIELDS if cfg.randomization.enabled else ())
    return TrackingTask(cfg, motion.to(physics.device), physics, seed=seed, autoreset=autoreset, terrain=terrain)


def _obs_space(task: TrackingTask) -> spaces.Dict:
    clip = task.cfg.observations.clip
    return spaces.Dict({g: spaces.Box(-clip, clip, (d,), np.float32) for g, d in task.obs_dims.items()})


def _action_space(task: TrackingTask) -> spaces.Box:
    clip = task.cfg.action.clip
    return spaces.Box(-clip, clip, (task.num_actions,), np.float32)


class TrackEnv(gym.Env):
    """One tracking env on CPU MuJoCo (Gymnasium single-env API, NumPy arrays)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}
    #: builds the batched MDP; a task's env class names its own (``envs.box``)
    make_task: Callable[..., TrackingTask] = staticmethod(make_task)

    def __init__(self, reference: ReferenceSource | PreparedClips, render_mode: str | None = None,
                 cfg: TrackEnvCfg | str | Path | None = None, evaluation: bool = False, seed: int = 0,
                 width: int = 640, height: int = 480):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        self.task = self.make_task(reference, 1, "mujoco", "cpu", cfg, evaluation, seed, autoreset=False)
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self.task.step_dt))}
        self.observation_space = _obs_space(self.task)
        self.action_space = _action_space(self.task)
        self._render_size = (width, height)
        self._renderer = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs = self.task.reset(seed=seed)
        return self._numpy(obs), self._info()

    def step(self, action):
        obs, reward, terminated, truncated, extras = self.task.step(torch.as_tensor(np.asarray(action))[None])
        info = self._info()
        info["success"] = bool(extras["success"][0])
        info["terminations"] = {k: bool(v[0]) for k, v in extras["terminations"].items()}
        info["log"] = {k: float(v) for k, v in extras["log"].items()}
        return self._numpy(obs), float(reward[0]), bool(terminated[0]), bool(truncated[0]), info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            self._renderer = self._make_renderer()
        return self._renderer.render(self.task.backend.qpos[0].double().numpy(), self._ghost_qpos())

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def policy_metadata(self) -> dict:
        return self.task.policy_metadata()

    def _make_renderer(self):
        from envs.render import TrackingRenderer

        return TrackingRenderer(*self._render_size, terrain=self.task.terrain)

    def _ghost_qpos(self) -> np.ndarray:
        """The reference configuration at the target frame, in the simulation's qpos layout."""
        return self.task.motion.qpos(self.task.command.rows)[0].double().numpy()

    def _numpy(self, obs: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
        return {k: v[0].numpy().astype(np.float32, copy=True) for k, v in obs.items()}

    def _info(self) -> dict:
        c = self.task.command
        return {"clip": int(c.clip[0]), "start_frame": int(c.start_frame[0]), "frame": int(c.frame[0]),
                "episode_length": int(self.task.episode_length_buf[0])}


class TrackVecEnv(VectorEnv):
    """N tracking envs on one device (torch in/out, same-step autoreset). See the module docstring."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}
    make_task: Callable[..., TrackingTask] = staticmethod(make_task)

    def __init__(self, num_envs: int, reference: ReferenceSource | PreparedClips, device: str = "cuda",
                 backend: str = "warp", cfg: TrackEnvCfg | str | Path | None = None, evaluation: bool = False,
                 seed: int = 0):
        self.task = self.make_task(reference, num_envs, backend, device, cfg, evaluation, seed, autoreset=True)
        self.num_envs = num_envs
        self.device = self.task.device
        self.single_observation_space = _obs_space(self.task)
        self.single_action_space = _action_space(self.task)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Reset all envs, or those in ``options["reset_mask"]`` ((N,) bool)."""
        super().reset(seed=seed)
        mask = None if not options or "reset_mask" not in options else torch.as_tensor(
            options["reset_mask"], dtype=torch.bool, device=self.device)
        return self.task.reset(mask, seed=seed), {}

    def step(self, actions):
        return self.task.step(actions)

    # ------------------------------------------------------------ trainer / evaluation interface
    @property
    def num_actions(self) -> int:
        return self.task.num_actions

    @property
    def obs_dims(self) -> dict[str, int]:
        return dict(self.task.obs_dims)

    @property
    def obs_layout(self) -> dict[str, list[tuple[str, int]]]:
        return {g: list(v) for g, v in self.task.obs_layout.items()}

    @property
    def step_dt(self) -> float:
        return self.task.step_dt

    @property
    def max_episode_length(self) -> int:
        return self.task.max_episode_length

    @property
    def episode_length_buf(self) -> torch.Tensor:
        return self.task.episode_length_buf

    @episode_length_buf.setter
    def episode_length_buf(self, value: torch.Tensor) -> None:
        self.task.episode_length_buf = torch.as_tensor(value, dtype=torch.long, device=self.device)

    @property
    def command(self):
        return self.task.command

    @property
    def motion(self) -> MotionLibrary:
        return self.task.motion

    @property
    def tracking_state(self):
        return self.task.tracking_state

    def policy_metadata(self) -> dict:
        return self.task.policy_metadata()
