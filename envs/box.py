"""OTR-G1-BoxTrack-v0: whole-body tracking with the reference's objects in the loop.

The same batched MDP as OTR-G1-Track-v0 (``envs.task.TrackingTask``) on the same two
backends, with the reference's objects simulated (``envs.objects``: moving objects as free
bodies, static ones fixed) and object terms in the config (``configs/env/box.yaml``)::

    import gymnasium, otr_gym
    env = gymnasium.make("OTR-G1-BoxTrack-v0", reference="box_carry.npz", render_mode="rgb_array")
    envs = gymnasium.make_vec("OTR-G1-BoxTrack-v0", num_envs=4096, vectorization_mode="vector_entry_point",
                              device="cuda", reference="box_carry.npz")

What the objects add (docs/environment.md §3 object variant, §4 object terms, §5, §6):

- reset: every moving object on its reference pose and velocity at the start frame. With reset
  noise, an object held at that frame (a hand window open) takes the robot root's noise
  (shift, turn about the root, velocity kicks) so the grasp is kept; a free-standing one gets
  ``objects.reset_noise_pos_m`` (HS ±5 cm in x, y);
- state: ``TrackingState.objects`` (``envs.mdp.state.ObjectState``): object poses and
  velocities, their references, the hand points and targets, contact gates and forces;
- success: the clip's last frame reached without a termination (HDMI), also in training
  where the episode then goes on with a new start (``on_clip_end: resample``);
- object randomisation at start-up (per env): friction, added mass, inertia scale;
- ``policy_metadata()["objects"]``: moving/static object names, supports, hands and the frames
  of the object observations (named in ``observation_names`` like every term).

Extra keyword argument: none; objects without an embedded mesh take theirs from the config
(``objects.overrides.<name>.mesh``), terrain as in OTR-G1-Track-v0 (``cfg.terrain``,
``envs.terrain``). A reference without objects, an object without a mesh, a mesh that cannot
be decomposed and a static object in a library whose terrain puts clips at several origins
raise ``InvalidReferenceError`` naming file and object.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from envs.backends import ContactPair, PhysicsBackend, build_sim_model, make_backend
from envs.clips import PreparedClips, placed_clips
from envs.config import BoxEnvCfg, load_box_config
from envs.mdp.metrics import object_orientation_error_rad, object_position_error_m
from envs.mdp.motion import MotionLibrary, ReferenceSource
from envs.mdp.objects import ObjectLibrary, fit_boxes_to_grasps
from envs.mdp.randomization import randomize_objects
from envs.mdp.state import ObjectState, TrackingState
from envs.objects import GROUND_GEOM, SceneObjects, is_static, object_qpos, object_qvel, scene_objects
from envs.task import TrackingTask, masked_mean
from envs.terrain import SceneTerrain, contact_buffers
from envs.tracking import TrackEnv, TrackVecEnv
from otr_gym.reference import InvalidReferenceError
from otr_gym.rotations import quat_apply, quat_mul

_PER_WORLD_FIELDS = ("geom_friction", "body_ipos", "body_mass", "body_inertia")  # §6, robot and objects


def contact_pairs(objects: SceneObjects, hands, hand_roots,
                  support_ground: bool) -> tuple[list[ContactPair], list[ContactPair]]:
    """(hand–object pairs, H-major then M; object–support pairs, M-major then S). A hand's pair
    takes every geom of the subtree of its root in ``hand_roots``."""
    hand_pairs = [ContactPair(f"{h}|{o.body}", ("subtree", r), ("body", o.body))
                  for h, r in zip(hands, hand_roots, strict=True) for o in objects.moving]
    supports = ([("ground", ("geom", GROUND_GEOM))] if support_ground else []) + \
        [(s.name, ("body", s.body)) for s in objects.static]
    support_pairs = [ContactPair(f"{o.body}|{name}", ("body", o.body), ref)
                     for o in objects.moving for name, ref in supports]
    return hand_pairs, support_pairs


class BoxTrackingTask(TrackingTask):
    """``TrackingTask`` with simulated objects (see the module docstring)."""

    cfg: BoxEnvCfg

    def __init__(self, cfg: BoxEnvCfg, motion: MotionLibrary, objects: ObjectLibrary, scene: SceneObjects,
                 backend: PhysicsBackend, seed: int = 0, autoreset: bool = True, terrain: SceneTerrain | None = None):
        self.objects, self.scene = objects, scene
        d = backend.device
        moving = [o.body for o in scene.moving]
        self._object_ids = torch.as_tensor(backend.body_ids(moving), device=d)
        self._hand_ids = torch.as_tensor(backend.body_ids(cfg.objects.hand_bodies), device=d)
        self._hand_offset = torch.as_tensor(cfg.objects.hand_point_offset_m, dtype=torch.float32, device=d)
        self._object_noise = torch.as_tensor(cfg.objects.reset_noise_pos_m, dtype=torch.float32, device=d)
        self._num_hands, self._num_objects = len(cfg.objects.hand_bodies), len(moving)
        self._num_supports = len(objects.support_names)
        n = backend.num_worlds
        # (N, M) mass and friction of each moving object per env: nominal, or this env's draw
        self._object_mass = torch.tensor([o.mass_kg for o in scene.moving], device=d).expand(n, -1).clone()
        self._object_friction = torch.tensor([o.friction for o in scene.moving], device=d).expand(n, -1).clone()
        self._gravity_w = torch.as_tensor(backend.model.opt.gravity, dtype=torch.float32, device=d)
        super().__init__(cfg, motion, backend, seed=seed, autoreset=autoreset, terrain=terrain)
        if cfg.randomization.enabled:
            draws = randomize_objects(backend, moving, [o.mass_kg for o in scene.moving], cfg.objects.randomization,
                                      self.generator)
            for k, body in enumerate(moving):
                self._object_friction[:, k], self._object_mass[:, k] = draws[body][:, 0], draws[body][:, 1]

    # ------------------------------------------------------------ hooks of TrackingTask
    def start_state(self, noise: bool | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        qpos, qvel = super().start_state(noise)
        lib, rows = self.objects, self.command.start_rows
        pos, quat = lib.pos_w[rows], lib.quat_w[rows]  # (N, M, ·)
        lin, ang = lib.lin_vel_w[rows], lib.ang_vel_w[rows]
        root_noise = self.command.root_noise
        if root_noise is not None:
            held = (lib.hand_gate[rows] > 0).any(dim=1)[..., None]  # (N, M, 1): a hand window is open
            root = self.motion.root_pos_w[rows][:, None]
            turn = root_noise.turn[:, None].expand_as(quat)
            carried = root + root_noise.shift[:, None] + quat_apply(turn, pos - root)
            lever = carried - root - root_noise.shift[:, None]
            kick = root_noise.lin[:, None] + torch.cross(root_noise.ang[:, None].expand_as(pos), lever, dim=-1)
            loose = pos + (2.0 * torch.rand(pos.shape, device=self.device, generator=self.generator) - 1.0) * \
                self._object_noise
            pos = torch.where(held, carried, loose)
            quat = torch.where(held, quat_mul(turn, quat), quat)
            lin = torch.where(held, lin + kick, lin)
            ang = torch.where(held, ang + root_noise.ang[:, None], ang)
        return (torch.cat([qpos, object_qpos(pos, quat)], dim=-1),
                torch.cat([qvel, object_qvel(quat, lin, ang)], dim=-1))

    def _success(self, terminated: torch.Tensor, truncated: torch.Tensor, clip_ended: torch.Tensor) -> torch.Tensor:
        return clip_ended & ~terminated

    def _build_state(self) -> TrackingState:
        s = super()._build_state()
        b, lib, rows = self.backend, self.objects, self.command.rows
        ids = self._object_ids
        pos, quat = b.body_pos_w[:, ids], b.body_quat_w[:, ids]
        hand_quat = b.body_quat_w[:, self._hand_ids]
        hand_pos = b.body_pos_w[:, self._hand_ids] + quat_apply(hand_quat,
                                                                self._hand_offset.expand_as(hand_quat[..., :3]))
        target_o = lib.hand_target_o[rows]  # (N, H, M, 3)
        obj_quat = quat[:, None].expand(-1, self._num_hands, -1, -1)
        target_w = pos[:, None] + quat_apply(obj_quat, target_o)
        forces = b.pair_force_n
        n_hand = self._num_hands * self._num_objects
        return replace(s, objects=ObjectState(
            names=lib.names, support_names=lib.support_names,
            pos_w=pos, quat_w=quat, lin_vel_w=b.body_lin_vel_w[:, ids], ang_vel_w=b.body_ang_vel_w[:, ids],
            ref_pos_w=lib.pos_w[rows], ref_quat_w=lib.quat_w[rows],
            ref_lin_vel_w=lib.lin_vel_w[rows], ref_ang_vel_w=lib.ang_vel_w[rows],
            hand_pos_w=hand_pos, hand_target_w=target_w, hand_gate=lib.hand_gate[rows],
            hand_force_n=forces[:, :n_hand].reshape(-1, self._num_hands, self._num_objects).clone(),
            support_gate=lib.support_gate[rows],
            support_force_n=forces[:, n_hand:].reshape(-1, self._num_objects, self._num_supports).clone(),
            static_pos_w=lib.static_pos_w, static_quat_w=lib.static_quat_w,
            grip_force_n=self._object_mass * torch.linalg.norm(lib.lin_acc_w[rows] - self._gravity_w, dim=-1)
            / (self._num_hands * self._object_friction),
        ))

    def _log(self, terms, fired, s: TrackingState, valid: torch.Tensor) -> dict:
        log = super()._log(terms, fired, s, valid)
        o = s.objects
        assert o is not None  # the box task always tracks objects
        log["metric/object_pos_error_m"] = masked_mean(object_position_error_m(s), valid)
        log["metric/object_ori_error_rad"] = masked_mean(object_orientation_error_rad(s), valid)
        log["metric/hand_gate"] = masked_mean(o.hand_gate, valid)
        log["metric/hand_force_n"] = masked_mean(o.hand_force_n, valid)
        return log

    def policy_metadata(self) -> dict:
        meta = super().policy_metadata()
        c = self.cfg.objects
        meta["objects"] = {
            "moving": list(self.objects.names),
            "static": [o.name for o in self.scene.static],
            "supports": list(self.objects.support_names),
            "hands": list(c.hand_bodies),
            "hand_contact_roots": list(c.hand_roots),
            "hand_point_offset_m": list(c.hand_point_offset_m),
            "collision": {o.name: o.method for o in self.scene.objects},
            "grasp_shrink_m": {o.name: o.grasp_shrink_m.tolist() for o in self.scene.objects
                               if o.grasp_shrink_m is not None},
            "mass_kg": {o.name: o.mass_kg for o in self.scene.moving},
            "window_source": list(self.objects.window_source),
            "frames": "object_pos_b/ori_b/lin_vel_b/ang_vel_b: simulated object in the robot anchor (torso) "
                      "frame; object_command: reference object pos/ori/lin vel/ang vel in the reference anchor "
                      "frame; contact_schedule: reference gates hand-object (H x M) then object-support (M x S); "
                      "orientations as the first two columns of the rotation matrix",
        }
        return meta


def box_scene(reference: ReferenceSource | PreparedClips, cfg: BoxEnvCfg):
    """(clips, terrain, objects, contact pairs, simulation model) of the box task: the clips
    placed on their terrain, the objects as the environment collides them (grasp-fitted), the
    hand–object and object–support sensor pairs and the compiled G1 + objects model. ``otr
    sim-robot`` builds its objects from the same call."""
    refs, terrain = placed_clips(reference, cfg)
    if np.ptp(terrain.clip_origin_w, axis=0).any():
        static = sorted({t.name for r in refs for t in r.objects if is_static(t, cfg.objects)})
        if static:
            raise InvalidReferenceError(
                f"{refs[0].source}: static object(s) {static} in a library whose terrain clips lie at other origins "
                f"(x = {', '.join(f'{x:g}' for x in np.unique(terrain.clip_origin_w[:, 0]))} m): a fixed body has one "
                "pose, so train the terrain clips and the clips with static objects separately")
    scene = scene_objects(refs, cfg.objects)
    hand_pairs, support_pairs = contact_pairs(scene, cfg.objects.hand_bodies, cfg.objects.hand_roots,
                                              cfg.objects.support_ground)
    pairs = hand_pairs + support_pairs
    model = build_sim_model(cfg.sim.contact_bodies, scene, pairs, condim=cfg.objects.condim, terrain=terrain)
    if cfg.objects.grasp_fit:
        fitted = fit_boxes_to_grasps(refs, scene, model, cfg.objects)
        if fitted is not scene:
            scene = fitted
            model = build_sim_model(cfg.sim.contact_bodies, scene, pairs, condim=cfg.objects.condim, terrain=terrain)
    return refs, terrain, scene, pairs, model


def make_box_task(reference: ReferenceSource | PreparedClips, num_envs: int, backend: str, device: str,
                  cfg: BoxEnvCfg | str | Path | None = None, evaluation: bool = False, seed: int = 0,
                  autoreset: bool = True) -> BoxTrackingTask:
    """Load the references (failing fast on bad ones and on bad objects), build the objects,
    the backend and the MDP."""
    if not isinstance(cfg, BoxEnvCfg):
        cfg = load_box_config(cfg)
    if evaluation:
        cfg = cfg.for_evaluation()
    refs, terrain, scene, pairs, model = box_scene(reference, cfg)
    motion = MotionLibrary.from_references(refs, cfg.command.tracked_bodies, cfg.command.fps)
    objects = ObjectLibrary.from_references(refs, scene, model, cfg.objects)
    physics = make_backend(backend, model, num_envs, device, cfg.sim.decimation, cfg.sim.contact_bodies,
                           *contact_buffers(cfg.sim, cfg.terrain, terrain),
                           per_world_fields=_PER_WORLD_FIELDS if cfg.randomization.enabled else (),
                           contact_pairs=[p.key for p in pairs])
    return BoxTrackingTask(cfg, motion.to(physics.device), objects.to(physics.device), scene, physics, seed=seed,
                           autoreset=autoreset, terrain=terrain)


class BoxTrackEnv(TrackEnv):
    """One box-tracking env on CPU MuJoCo (Gymnasium single-env API); ``render()`` shows the
    robot, the objects and a translucent ghost of the reference robot and moving objects."""

    task: BoxTrackingTask
    make_task = staticmethod(make_box_task)

    def _make_renderer(self):
        from envs.render import TrackingRenderer

        task = self.task
        return TrackingRenderer(*self._render_size, objects=task.scene, condim=task.cfg.objects.condim,
                                terrain=task.terrain)

    def _ghost_qpos(self) -> np.ndarray:
        task = self.task
        rows = task.command.rows
        qpos = torch.cat([task.motion.qpos(rows), object_qpos(task.objects.pos_w[rows], task.objects.quat_w[rows])],
                         dim=-1)
        return qpos[0].double().numpy()


class BoxTrackVecEnv(TrackVecEnv):
    """N box-tracking envs on one device (torch in/out, same-step autoreset)."""

    make_task = staticmethod(make_box_task)

