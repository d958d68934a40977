"""The physics interface the tracking MDP is written against.

A backend owns ``num_worlds`` copies of one MuJoCo model and exposes their state as batched
torch tensors (leading axis = world). The MDP reads these tensors and writes only through
``reset``, ``write_qvel`` and ``step``, so it never knows which simulator runs underneath.

Frames and units: positions in m (world), quaternions wxyz (world), linear velocities in m/s
(world) of the body *origin*, angular velocities in rad/s (world). Body arrays follow the
MuJoCo model body order, world body included at index 0 (use ``body_ids``). ``qvel`` is
MuJoCo's: the free-joint angular velocity is in the pelvis (body) frame.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from contextlib import AbstractContextManager

import mujoco
import torch

from otr_gym import robot

#: |qpos| or |qvel| beyond this (m, rad, m/s, rad/s) means the world's physics diverged: no G1
#: state comes near it, and it keeps squares and exponentials of the MDP terms finite.
MAX_ABS_STATE = 1.0e6


class PhysicsBackend(ABC):
    """Batched MuJoCo-model physics with torch views of the state.

    Subclasses implement the raw views and the actions below; ``model`` is the host
    ``MjModel`` (names, sizes, sensor addresses), shared by all worlds.
    """

    def __init__(self, model: mujoco.MjModel, num_worlds: int, device: torch.device, decimation: int,
                 contact_body_names: Sequence[str], contact_pair_keys: Sequence[str] = ()):
        if num_worlds < 1:
            raise ValueError(f"num_worlds must be >= 1, got {num_worlds}")
        if decimation < 1:
            raise ValueError(f"decimation must be >= 1, got {decimation}")
        self.model = model
        self.num_worlds = int(num_worlds)
        self.device = torch.device(device)
        self.decimation = int(decimation)
        self.contact_body_names = tuple(contact_body_names)
        self.contact_pair_keys = tuple(contact_pair_keys)
        self._root_ids = torch.as_tensor(model.body_rootid, dtype=torch.long, device=self.device)

    # ------------------------------------------------------------ raw views (N, ...)
    @property
    @abstractmethod
    def qpos(self) -> torch.Tensor:
        """(N, nq) generalized positions: root xyz (m), root quat wxyz, joints (rad)."""

    @property
    @abstractmethod
    def qvel(self) -> torch.Tensor:
        """(N, nv) root linear velocity (m/s, world), root angular velocity (rad/s, body), joints."""

    @property
    @abstractmethod
    def body_pos_w(self) -> torch.Tensor:
        """(N, nbody, 3) body origin positions (m, world)."""

    @property
    @abstractmethod
    def body_quat_w(self) -> torch.Tensor:
        """(N, nbody, 4) body orientations (wxyz, world)."""

    @property
    @abstractmethod
    def _cvel(self) -> torch.Tensor:
        """(N, nbody, 6) MuJoCo com-based velocity [angular, linear] at the subtree com of the root."""

    @property
    @abstractmethod
    def _subtree_com(self) -> torch.Tensor:
        """(N, nbody, 3) subtree centres of mass (m, world)."""

    @property
    @abstractmethod
    def _contact_forces(self) -> torch.Tensor:
        """(N, C + P) contact-force maxima of the bodies, then of the pairs."""

    @property
    @abstractmethod
    def _qfrc_actuator(self) -> torch.Tensor:
        """(N, nv) MuJoCo's ``qfrc_actuator`` of the last physics substep."""

    @property
    def joint_torque_nm(self) -> torch.Tensor:
        """(N, 29) what the actuators applied to each robot joint (the dofs after the robot's free
        root, before any object's) in the last physics substep of the last ``step`` (N·m), after
        MuJoCo's clamp to the joint's ``actuatorfrcrange``: the torque the robot used, to set
        against ``otr_gym.robot.EFFORT_LIMIT``. Stale after ``reset``."""
        return self._qfrc_actuator[:, 6:6 + robot.NUM_JOINTS]

    @property
    def contact_force_n(self) -> torch.Tensor:
        """(N, C) per ``contact_body_names``: the largest net contact force norm (N) seen over
        the substeps of the last ``step`` (zero after ``reset``)."""
        return self._contact_forces[:, :len(self.contact_body_names)]

    @property
    def pair_force_n(self) -> torch.Tensor:
        """(N, P) per ``contact_pair_keys``: the largest norm (N) of the net force between the
        pair's two objects over the substeps of the last ``step`` (zero after ``reset``)."""
        return self._contact_forces[:, len(self.contact_body_names):]

    @property
    def unstable(self) -> torch.Tensor:
        """(N,) bool: worlds whose state after the last ``step`` is non-finite or beyond
        ``MAX_ABS_STATE`` (diverged physics). The MDP resets them (``envs.task``)."""
        return ~((self.qpos.abs() < MAX_ABS_STATE).all(-1) & (self.qvel.abs() < MAX_ABS_STATE).all(-1))

    # ------------------------------------------------------------ actions
    @abstractmethod
    def step(self, ctrl: torch.Tensor) -> None:
        """Hold actuator controls ``ctrl`` (N, nu) (position targets, rad) for ``decimation``
        physics steps, then recompute kinematics and velocities for the new state."""

    @abstractmethod
    def reset(self, env_ids: torch.Tensor, qpos: torch.Tensor, qvel: torch.Tensor) -> None:
        """Set the state of the worlds in ``env_ids`` and recompute their kinematics.

        ``env_ids`` is either a bool mask (N,) with full (N, nq)/(N, nv) state rows (rows
        outside the mask are ignored; this form needs no host synchronisation), or a long
        index tensor (K,) with (K, nq)/(K, nv) rows. Solver warm-starts and the contact-force
        maxima of those worlds are cleared.
        """

    #: whether ``joined_capture`` works: the backend's work can join a CUDA graph torch captures
    joins_cuda_graphs: bool = False

    def joined_capture(self) -> AbstractContextManager:
        """Inside ``torch.cuda.graph``: a context in which ``step`` and ``reset`` launch their work
        into torch's capture (``envs.step_graph``). Only where ``joins_cuda_graphs``."""
        raise NotImplementedError(f"{type(self).__name__} cannot join a CUDA graph capture")

    @abstractmethod
    def write_qvel(self, qvel: torch.Tensor) -> None:
        """Overwrite the velocities (N, nv) of all worlds (used for pushes before a step)."""

    @abstractmethod
    def set_geom_friction(self, geom_ids: Sequence[int], friction: torch.Tensor) -> None:
        """Set the sliding friction coefficient of ``geom_ids`` per world, ``friction`` (N, G)."""

    @abstractmethod
    def set_body_com_offset(self, body_id: int, offset: torch.Tensor) -> None:
        """Move the centre of mass of ``body_id`` by ``offset`` (N, 3) (m, body frame) from
        its MJCF value."""

    @abstractmethod
    def set_body_mass(self, body_id: int, mass_kg: torch.Tensor, inertia_scale: torch.Tensor) -> None:
        """Per world: the mass of ``body_id`` (N,) (kg) and its MJCF principal inertia scaled by
        ``inertia_scale`` (N,)."""

    # ------------------------------------------------------------ derived views
    @property
    def _contact_sensor_names(self) -> tuple[str, ...]:
        return self.contact_body_names + self.contact_pair_keys

    @property
    def body_ang_vel_w(self) -> torch.Tensor:
        """(N, nbody, 3) body angular velocities (rad/s, world)."""
        return self._cvel[..., :3]

    @property
    def body_lin_vel_w(self) -> torch.Tensor:
        """(N, nbody, 3) linear velocities of the body origins (m/s, world).

        ``cvel`` holds the velocity of the body-fixed point at the subtree com of the body's
        root; moving that point to the body origin p adds ω × (p − c).
        """
        cvel = self._cvel
        offset = self.body_pos_w - self._subtree_com[:, self._root_ids]
        return cvel[..., 3:] + torch.cross(cvel[..., :3], offset, dim=-1)

    def body_ids(self, names: Sequence[str]) -> list[int]:
        """Model body ids of ``names`` (world = 0); unknown names raise with the list of them."""
        ids = [mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, n) for n in names]
        unknown = [n for n, i in zip(names, ids, strict=True) if i < 0]
        if unknown:
            raise KeyError(f"bodies {unknown} are not in the simulation model")
        return ids

    def _env_mask(self, env_ids: torch.Tensor) -> torch.Tensor:
        if env_ids.dtype == torch.bool:
            if env_ids.shape != (self.num_worlds,):
                raise ValueError(f"reset mask must have shape ({self.num_worlds},), got {tuple(env_ids.shape)}")
            return env_ids.to(self.device)
        mask = torch.zeros(self.num_worlds, dtype=torch.bool, device=self.device)
        return mask.index_fill_(0, env_ids.to(self.device, torch.long), True)

    def _full_rows(self, env_ids: torch.Tensor, rows: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
        """``rows`` in the (N, ·) layout: as given for a mask, scattered into ``current`` for ids."""
        rows = rows.to(self.device, current.dtype)
        if env_ids.dtype == torch.bool:
            return rows
        return current.clone().index_copy_(0, env_ids.to(self.device, torch.long), rows)
