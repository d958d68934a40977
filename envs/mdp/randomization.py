"""Domain randomisation (docs/environment.md §6): friction, torso centre of mass and default-pose bias
drawn once per env at start-up; velocity pushes at random 1–3 s intervals; for the box task,
the objects' friction, mass and inertia at start-up (``randomize_objects``).

All draws use the environment's torch generator; pushes are masked updates of every env
(no host synchronisation).
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import torch

from envs.backends.base import PhysicsBackend
from envs.config import ObjectRandomizationCfg, RandomizationCfg
from otr_gym import robot
from otr_gym.rotations import quat_apply_inverse


class DomainRandomizer:
    def __init__(self, cfg: RandomizationCfg, backend: PhysicsBackend, step_dt: float, generator: torch.Generator,
                 extra_friction_geoms: Sequence[str] = ()):
        """``extra_friction_geoms`` take the friction draw with ``cfg.friction_geoms`` (the terrain)."""
        self.cfg, self.backend, self.step_dt, self.gen = cfg, backend, step_dt, generator
        self.friction_geoms = tuple(cfg.friction_geoms) + tuple(extra_friction_geoms)
        self.num_envs, self.device = backend.num_worlds, backend.device
        self._lin = torch.as_tensor(cfg.push_lin_vel_mps, dtype=torch.float32, device=self.device)
        self._ang = torch.as_tensor(cfg.push_ang_vel_radps, dtype=torch.float32, device=self.device)
        self.time_to_push_s = self._push_interval()

    def apply_startup(self) -> torch.Tensor:
        """Randomise friction and the COM in the backend; return the default-pose bias (N, 29) (rad)."""
        cfg, m = self.cfg, self.backend.model
        geoms = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in self.friction_geoms]
        missing = [g for g, i in zip(self.friction_geoms, geoms, strict=True) if i < 0]
        if missing:
            raise KeyError(f"randomization.friction_geoms {missing} are not geoms of the simulation model")
        lo, hi = cfg.friction_range
        draw = lo + (hi - lo) * self._rand(self.num_envs, 1)
        self.backend.set_geom_friction(geoms, draw.expand(-1, len(geoms)))
        com = torch.as_tensor(cfg.com_offset_m, dtype=torch.float32, device=self.device)
        body = self.backend.body_ids([cfg.com_body])[0]
        self.backend.set_body_com_offset(body, (2 * self._rand(self.num_envs, 3) - 1) * com)
        return (2 * self._rand(self.num_envs, robot.NUM_JOINTS) - 1) * cfg.joint_offset_rad

    def reset(self, mask: torch.Tensor) -> None:
        """Restart the push timer of the envs in ``mask``."""
        self.time_to_push_s = torch.where(mask, self._push_interval(), self.time_to_push_s)

    def push(self) -> None:
        """Count down the push timers; envs whose timer ran out get a random root velocity kick
        (linear in world, angular in world, converted to the pelvis frame of qvel)."""
        self.time_to_push_s = self.time_to_push_s - self.step_dt
        due = (self.time_to_push_s <= 0.0)[:, None]
        qvel = self.backend.qvel
        lin = (2 * self._rand(self.num_envs, 3) - 1) * self._lin
        ang_w = (2 * self._rand(self.num_envs, 3) - 1) * self._ang
        kick = torch.cat([lin, quat_apply_inverse(self.backend.qpos[:, 3:7], ang_w)], dim=-1)
        new = qvel.clone()
        new[:, :6] += kick * due
        self.backend.write_qvel(new)
        self.time_to_push_s = torch.where(due[:, 0], self._push_interval(), self.time_to_push_s)

    def _push_interval(self) -> torch.Tensor:
        lo, hi = self.cfg.push_interval_s
        return lo + (hi - lo) * self._rand(self.num_envs)

    def _rand(self, *shape: int) -> torch.Tensor:
        return torch.rand(*shape, device=self.device, generator=self.gen)


def randomize_objects(backend: PhysicsBackend, bodies: Sequence[str], mass_kg: Sequence[float],
                      cfg: ObjectRandomizationCfg, generator: torch.Generator) -> dict[str, torch.Tensor]:
    """Per env and object body (one draw each): the sliding friction of all its geoms, its mass
    (nominal + U[mass_add_kg]) and its inertia (× U[inertia_scale]). Returns the draws."""
    n, m = backend.num_worlds, backend.model
    out = {}
    for body, mass in zip(bodies, mass_kg, strict=True):
        bid = backend.body_ids([body])[0]
        geoms = collision_geoms(m, bid)
        draws = draw_object(cfg, mass, n, generator, backend.device)
        friction, added, scale = draws.unbind(-1)
        backend.set_geom_friction(geoms, friction[:, None].expand(-1, len(geoms)))
        # the MJCF inertia belongs to the nominal mass: scale it with the mass, then by the draw
        backend.set_body_mass(bid, added, scale * added / mass)
        out[body] = draws
    return out


def collision_geoms(model, body_id: int) -> list[int]:
    """The geoms of body ``body_id`` that collide (contype or conaffinity set): those whose
    friction the randomisation draws (``otr sim-robot --object-draw`` sets the same ones)."""
    return [g for g in range(model.ngeom)
            if model.geom_bodyid[g] == body_id and (model.geom_contype[g] or model.geom_conaffinity[g])]


def draw_object(cfg: ObjectRandomizationCfg, mass_kg: float, n: int, generator: torch.Generator,
                device: torch.device | str = "cpu") -> torch.Tensor:
    """(n, 3) one object's draws, as ``randomize_objects`` makes them (and in its order from
    ``generator``): friction U[friction_range], mass = ``mass_kg`` + U[mass_add_kg], inertia
    scale U[inertia_scale] (on top of the inertia scaled with the mass). ``otr sim-robot
    --object-draw`` draws with it too."""

    def uniform(lo: float, hi: float) -> torch.Tensor:
        return lo + (hi - lo) * torch.rand(n, device=device, generator=generator)

    friction = uniform(*cfg.friction_range)
    added = mass_kg + uniform(*cfg.mass_add_kg)
    scale = uniform(*cfg.inertia_scale)
    return torch.stack([friction, added, scale], dim=-1)
