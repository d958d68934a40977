"""CPU MuJoCo backend: one ``MjData`` (and one ``MjModel`` copy, for per-world randomisation)
per world, stepped in turn. Meant for one or a few worlds: rendering, evaluation, tests.

MuJoCo computes in float64; after every ``step``/``reset`` the state is copied once into
float32 torch tensors (CPU), the dtype the MDP uses on every backend.

MuJoCo answers a NaN or overflowing state by resetting that world to the model's qpos0 and
counting a warning (mjWARN_BADQPOS/BADQVEL/BADQACC); such a silent teleport is reported as
``unstable`` too, so the MDP ends and restarts the episode instead of tracking from qpos0.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import mujoco
import numpy as np
import torch

from envs.backends.base import PhysicsBackend
from envs.backends.model import contact_sensor_adr

_DIVERGED = (mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL, mujoco.mjtWarning.mjWARN_BADQACC)


def _divergence_count(d: mujoco.MjData) -> int:
    return sum(int(d.warning[w].number) for w in _DIVERGED)


class MuJoCoBackend(PhysicsBackend):
    """``num_worlds`` independent MuJoCo simulations of ``model`` (CPU)."""

    def __init__(self, model: mujoco.MjModel, num_worlds: int = 1, decimation: int = 4,
                 contact_bodies: Sequence[str] = (), contact_pairs: Sequence[str] = ()):
        super().__init__(model, num_worlds, torch.device("cpu"), decimation, contact_bodies, contact_pairs)
        self._models = [copy.deepcopy(model) for _ in range(num_worlds)]
        self._datas = [mujoco.MjData(m) for m in self._models]
        for m, d in zip(self._models, self._datas, strict=True):
            if m.nkey > 0:
                mujoco.mj_resetDataKeyframe(m, d, 0)
            mujoco.mj_forward(m, d)
        adr = contact_sensor_adr(model, self._contact_sensor_names)
        self._force_cols = (adr[:, None] + np.arange(3)).reshape(-1)
        self._body_ipos0 = model.body_ipos.copy()
        self._body_inertia0 = model.body_inertia.copy()
        self._contact = torch.zeros(num_worlds, len(self._contact_sensor_names))
        self._reset_by_mujoco = torch.zeros(num_worlds, dtype=torch.bool)
        self._pull()

    # ------------------------------------------------------------ views
    def world_model(self, world: int = 0) -> mujoco.MjModel:
        """World ``world``'s own MjModel, with its randomised parameters (friction, mass, ...)."""
        return self._models[world]

    @property
    def qpos(self) -> torch.Tensor:
        return self._qpos

    @property
    def qvel(self) -> torch.Tensor:
        return self._qvel

    @property
    def body_pos_w(self) -> torch.Tensor:
        return self._xpos

    @property
    def body_quat_w(self) -> torch.Tensor:
        return self._xquat

    @property
    def _cvel(self) -> torch.Tensor:
        return self._cvel_t

    @property
    def _subtree_com(self) -> torch.Tensor:
        return self._subtree_com_t

    @property
    def _contact_forces(self) -> torch.Tensor:
        return self._contact

    @property
    def _qfrc_actuator(self) -> torch.Tensor:
        # read on demand (diagnostics only): nothing touches qfrc_actuator between mj_step and
        # here, so this is the last substep's, without a per-step copy of every world's
        return torch.from_numpy(np.stack([d.qfrc_actuator for d in self._datas])).float()

    @property
    def unstable(self) -> torch.Tensor:
        return super().unstable | self._reset_by_mujoco

    # ------------------------------------------------------------ actions
    def step(self, ctrl: torch.Tensor) -> None:
        ctrl = ctrl.detach().to("cpu", torch.float64).numpy()
        forces = np.zeros((self.num_worlds, len(self._contact_sensor_names)))
        reset_by_mujoco = np.zeros(self.num_worlds, bool)
        for w, (m, d) in enumerate(zip(self._models, self._datas, strict=True)):
            d.ctrl[:] = ctrl[w]
            diverged = _divergence_count(d)
            for _ in range(self.decimation):
                mujoco.mj_step(m, d)
                f = np.linalg.norm(d.sensordata[self._force_cols].reshape(-1, 3), axis=-1)
                np.maximum(forces[w], f, out=forces[w])
            reset_by_mujoco[w] = _divergence_count(d) > diverged
            self._refresh(m, d)
        self._contact = torch.from_numpy(forces).float()
        self._reset_by_mujoco = torch.from_numpy(reset_by_mujoco)
        self._pull()

    def reset(self, env_ids: torch.Tensor, qpos: torch.Tensor, qvel: torch.Tensor) -> None:
        mask = self._env_mask(env_ids).numpy()
        qpos = self._full_rows(env_ids, qpos, self._qpos).double().numpy()
        qvel = self._full_rows(env_ids, qvel, self._qvel).double().numpy()
        for w in np.flatnonzero(mask):
            m, d = self._models[w], self._datas[w]
            d.qpos[:], d.qvel[:] = qpos[w], qvel[w]
            d.qacc_warmstart[:] = 0.0
            self._refresh(m, d)
        self._contact[torch.from_numpy(mask)] = 0.0
        self._reset_by_mujoco[torch.from_numpy(mask)] = False
        self._pull()

    def write_qvel(self, qvel: torch.Tensor) -> None:
        qvel = qvel.detach().to("cpu", torch.float64).numpy()
        for w, d in enumerate(self._datas):
            d.qvel[:] = qvel[w]
        self._qvel = torch.from_numpy(qvel).float()

    def set_geom_friction(self, geom_ids: Sequence[int], friction: torch.Tensor) -> None:
        friction = friction.detach().cpu().double().numpy()
        for w, m in enumerate(self._models):
            m.geom_friction[list(geom_ids), 0] = friction[w]

    def set_body_com_offset(self, body_id: int, offset: torch.Tensor) -> None:
        offset = offset.detach().cpu().double().numpy()
        for w, m in enumerate(self._models):
            m.body_ipos[body_id] = self._body_ipos0[body_id] + offset[w]

    def set_body_mass(self, body_id: int, mass_kg: torch.Tensor, inertia_scale: torch.Tensor) -> None:
        mass = mass_kg.detach().cpu().double().numpy()
        scale = inertia_scale.detach().cpu().double().numpy()
        for w, m in enumerate(self._models):
            m.body_mass[body_id] = mass[w]
            m.body_inertia[body_id] = self._body_inertia0[body_id] * scale[w]

    # ------------------------------------------------------------ internals
    @staticmethod
    def _refresh(m: mujoco.MjModel, d: mujoco.MjData) -> None:
        """Kinematics and com velocities of the current qpos/qvel (mj_step leaves them one substep behind)."""
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_comVel(m, d)

    def _pull(self) -> None:
        def stack(name: str) -> torch.Tensor:
            return torch.from_numpy(np.stack([getattr(d, name) for d in self._datas])).float()

        self._qpos, self._qvel = stack("qpos"), stack("qvel")
        self._xpos, self._xquat = stack("xpos"), stack("xquat")
        self._cvel_t, self._subtree_com_t = stack("cvel"), stack("subtree_com")
