"""MuJoCo-Warp backend: N worlds of one model in device memory, state exposed as zero-copy
torch views of the warp arrays (``wp.to_torch``).

Per env step the host only launches work: ``step`` copies the controls into ``d.ctrl`` (a
device-to-device copy) and replays one captured graph holding the ``decimation`` physics
steps, the contact-force maxima and the kinematics refresh; ``reset`` writes the new state
with masked torch ops and replays a second, small graph (kinematics refresh). Nothing is read
back to the host. Warp 1.19 also captures and replays graphs on its "cpu" device, where it
removes the per-kernel Python launch cost (measured 4.6 → 0.7 ms per G1 step with 4 worlds) and
lets CI exercise the same captured path as the GPU; ``graph_capture=False`` runs eagerly.

Ordering between torch and warp: torch works on the legacy default CUDA stream and warp on its
own *blocking* stream, which CUDA orders against the legacy stream implicitly, so the views
are always read after the graph that wrote them, without explicit synchronisation.

Memory (float32): the warp arrays of Model + Data take ~110 KB per world with nconmax 40 and
njmax 256 (counted on the G1 model: 0.43 GiB at 4096 worlds, 0.85 GiB at 8192), dominated by
the per-world constraint arrays; the MDP's torch tensors add a few KB per world.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import mujoco
import mujoco_warp as mjw
import torch
import warp as wp

from envs.backends.base import PhysicsBackend
from envs.backends.contact_forces import NetContactForces

#: Set (to anything but empty or 0) to keep Warp's start-up banner and its "Module … load on
#: device … took … ms" line per kernel module (~44 on every environment start, cached or not).
VERBOSE_ENV = "OTR_WARP_VERBOSE"


def quiet_warp() -> None:
    """Show only Warp's warnings and errors unless ``$OTR_WARP_VERBOSE`` asks for its info lines.
    Runs before ``wp.init`` (the banner) and any module's first launch (its load line)."""
    if os.environ.get(VERBOSE_ENV, "").strip() not in ("", "0"):
        return
    if hasattr(wp, "LOG_WARNING"):  # newer Warp (1.19): one log threshold, ``config.quiet`` is gone
        wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    else:
        wp.config.quiet = True


quiet_warp()


class WarpBackend(PhysicsBackend):
    """``num_worlds`` worlds of ``model`` on MuJoCo-Warp (device "cuda", "cuda:K" or "cpu").

    ``nconmax``/``njmax`` are per world (MuJoCo-Warp 4.0). ``per_world_fields`` lists Model
    fields that get one copy per world (domain randomisation: ``geom_friction``, ``body_ipos``,
    ``body_mass``, ``body_inertia``); the others are shared. ``contact_pairs`` are the keys of
    the model's pair contact sensors (``envs.backends.model.ContactPair``).
    """

    def __init__(self, model: mujoco.MjModel, num_worlds: int, device: str = "cuda", decimation: int = 4,
                 contact_bodies: Sequence[str] = (), nconmax: int = 40, njmax: int = 256,
                 per_world_fields: Sequence[str] = (), graph_capture: bool = True,
                 contact_pairs: Sequence[str] = ()):
        wp.init()
        try:
            wp_device = wp.get_device(device)
        except (RuntimeError, ValueError) as exc:
            raise RuntimeError(f"warp device '{device}' is not available ({exc}); "
                               f"available: {[str(d) for d in wp.get_devices()]}") from exc
        super().__init__(model, num_worlds, torch.device(wp.device_to_torch(wp_device)), decimation, contact_bodies,
                         contact_pairs)
        self._wp_device = wp_device
        data = mujoco.MjData(model)
        if model.nkey > 0:
            mujoco.mj_resetDataKeyframe(model, data, 0)
        mujoco.mj_forward(model, data)
        with wp.ScopedDevice(wp_device):
            self._m = mjw.put_model(model, batch_sizes={f: num_worlds for f in per_world_fields})
            # A capped solver (docs/environment.md §1: 10 iterations, 20 line-search steps) is the design,
            # not an error: keep warnings for dropped contacts/constraints only, since a device
            # printf from thousands of worlds per substep would flood the log and stall the step.
            self._m.opt.warn_overflow &= ~(mjw.OverflowType.ITERATIONS | mjw.OverflowType.LS_ITERATIONS)
            self._d = mjw.put_data(model, data, nworld=num_worlds, nconmax=nconmax, njmax=njmax)
            # The model's only sensors are the contact sensors, evaluated here by NetContactForces
            # at a fraction of MuJoCo-Warp's generic cost (envs/backends/contact_forces.py).
            self._m.opt.disableflags |= mjw.DisableBit.SENSOR
            self._net_forces = NetContactForces(model, self._contact_sensor_names, num_worlds,
                                                self._d.naconmax, wp_device)
            self._contact_max = wp.zeros((num_worlds, len(self._contact_sensor_names)), dtype=float)
        d, m = self._d, self._m
        self._qpos_t, self._qvel_t, self._ctrl_t = wp.to_torch(d.qpos), wp.to_torch(d.qvel), wp.to_torch(d.ctrl)
        self._warmstart_t, self._qfrc_actuator_t = wp.to_torch(d.qacc_warmstart), wp.to_torch(d.qfrc_actuator)
        self._xpos_t, self._xquat_t = wp.to_torch(d.xpos), wp.to_torch(d.xquat)
        self._cvel_v, self._subtree_com_v = wp.to_torch(d.cvel), wp.to_torch(d.subtree_com)
        self._contact_t = wp.to_torch(self._contact_max)
        self._friction_t = wp.to_torch(m.geom_friction)
        self._body_ipos_t = wp.to_torch(m.body_ipos)
        self._body_ipos0 = self._body_ipos_t[0].clone()
        self._body_mass_t, self._body_inertia_t = wp.to_torch(m.body_mass), wp.to_torch(m.body_inertia)
        self._body_inertia0 = self._body_inertia_t[0].clone()
        self._step_graph = self._refresh_graph = None
        self._joined = False  # inside a torch capture (joined_capture): launch eagerly into it
        self.joins_cuda_graphs = wp_device.is_cuda
        if graph_capture:
            with wp.ScopedDevice(wp_device):
                with wp.ScopedCapture(device=wp_device) as capture:
                    self._physics()
                self._step_graph = capture.graph
                with wp.ScopedCapture(device=wp_device) as capture:
                    self._refresh()
                self._refresh_graph = capture.graph

    # ------------------------------------------------------------ views (zero-copy)
    @property
    def qpos(self) -> torch.Tensor:
        return self._qpos_t

    @property
    def qvel(self) -> torch.Tensor:
        return self._qvel_t

    @property
    def body_pos_w(self) -> torch.Tensor:
        return self._xpos_t

    @property
    def body_quat_w(self) -> torch.Tensor:
        return self._xquat_t

    @property
    def _cvel(self) -> torch.Tensor:
        return self._cvel_v

    @property
    def _subtree_com(self) -> torch.Tensor:
        return self._subtree_com_v

    @property
    def _contact_forces(self) -> torch.Tensor:
        return self._contact_t

    @property
    def _qfrc_actuator(self) -> torch.Tensor:
        return self._qfrc_actuator_t

    @property
    def warp_model(self) -> mjw.Model:
        return self._m

    @property
    def warp_data(self) -> mjw.Data:
        return self._d

    # ------------------------------------------------------------ actions
    def step(self, ctrl: torch.Tensor) -> None:
        self._ctrl_t.copy_(ctrl)
        if self._step_graph is not None and not self._joined:
            wp.capture_launch(self._step_graph)
        else:
            with wp.ScopedDevice(self._wp_device):
                self._physics()

    def reset(self, env_ids: torch.Tensor, qpos: torch.Tensor, qvel: torch.Tensor) -> None:
        mask = self._env_mask(env_ids)
        rows = mask[:, None]
        self._qpos_t.copy_(torch.where(rows, self._full_rows(env_ids, qpos, self._qpos_t), self._qpos_t))
        self._qvel_t.copy_(torch.where(rows, self._full_rows(env_ids, qvel, self._qvel_t), self._qvel_t))
        self._warmstart_t.masked_fill_(rows, 0.0)
        self._contact_t.masked_fill_(rows, 0.0)
        if self._refresh_graph is not None and not self._joined:
            wp.capture_launch(self._refresh_graph)
        else:
            with wp.ScopedDevice(self._wp_device):
                self._refresh()

    def write_qvel(self, qvel: torch.Tensor) -> None:
        self._qvel_t.copy_(qvel)

    @contextmanager
    def joined_capture(self) -> Iterator[None]:
        """Warp on the stream torch is capturing, the capture registered with warp as external
        (warp's documented way into a torch graph); the physics launched kernel by kernel, since a
        captured graph cannot be launched into another capture."""
        if not self.joins_cuda_graphs:
            raise NotImplementedError(f"warp device {self._wp_device} cannot join a CUDA graph capture")
        stream = wp.stream_from_torch(torch.cuda.current_stream(self.device))
        # no sync on entry: making the capturing stream wait on warp's own (uncaptured) stream
        # would invalidate the capture
        with wp.ScopedStream(stream, sync_enter=False):
            wp.capture_begin(stream=stream, external=True, force_module_load=False)
            self._joined = True
            try:
                yield
            finally:
                self._joined = False
                wp.capture_end(stream=stream)

    def set_geom_friction(self, geom_ids: Sequence[int], friction: torch.Tensor) -> None:
        self._require_per_world(self._friction_t, "geom_friction")
        self._friction_t[:, list(geom_ids), 0] = friction.to(self.device, torch.float32)

    def set_body_com_offset(self, body_id: int, offset: torch.Tensor) -> None:
        self._require_per_world(self._body_ipos_t, "body_ipos")
        self._body_ipos_t[:, body_id] = self._body_ipos0[body_id] + offset.to(self.device, torch.float32)

    def set_body_mass(self, body_id: int, mass_kg: torch.Tensor, inertia_scale: torch.Tensor) -> None:
        self._require_per_world(self._body_mass_t, "body_mass")
        self._require_per_world(self._body_inertia_t, "body_inertia")
        self._body_mass_t[:, body_id] = mass_kg.to(self.device, torch.float32)
        scale = inertia_scale.to(self.device, torch.float32)[:, None]
        self._body_inertia_t[:, body_id] = self._body_inertia0[body_id] * scale

    # ------------------------------------------------------------ internals
    def _physics(self) -> None:
        self._contact_max.zero_()
        for _ in range(self.decimation):
            mjw.step(self._m, self._d)
            self._net_forces.update(self._m, self._d, self._contact_max)
        self._refresh()

    def _refresh(self) -> None:
        """Kinematics and com velocities of the current qpos/qvel (mjw.step leaves them one substep behind)."""
        mjw.kinematics(self._m, self._d)
        mjw.com_pos(self._m, self._d)
        mjw.com_vel(self._m, self._d)

    def _require_per_world(self, view: torch.Tensor, name: str) -> None:
        if view.shape[0] != self.num_worlds:
            raise RuntimeError(f"Model field {name} is shared by all worlds: construct WarpBackend with "
                               f"per_world_fields containing '{name}' to randomise it")

