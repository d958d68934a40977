"""Physics backends behind one interface (``PhysicsBackend``): ``MuJoCoBackend`` (CPU MuJoCo,
one or a few worlds) and ``WarpBackend`` (MuJoCo-Warp, N worlds on a GPU or the warp CPU
device). ``WarpBackend`` is imported lazily so that importing this package never loads warp."""

from envs.backends.base import PhysicsBackend
from envs.backends.model import ContactPair, build_sim_model
from envs.backends.mujoco_backend import MuJoCoBackend

__all__ = ["ContactPair", "MuJoCoBackend", "PhysicsBackend", "build_sim_model", "make_backend"]


def make_backend(kind: str, model, num_worlds: int, device: str, decimation: int, contact_bodies,
                 nconmax: int, njmax: int, per_world_fields=(), contact_pairs=()) -> PhysicsBackend:
    """``kind`` "warp" (MuJoCo-Warp on ``device``) or "mujoco" (CPU MuJoCo; ``device`` must be "cpu")."""
    if kind == "warp":
        from envs.backends.warp_backend import WarpBackend

        return WarpBackend(model, num_worlds, device=device, decimation=decimation, contact_bodies=contact_bodies,
                           nconmax=nconmax, njmax=njmax, per_world_fields=per_world_fields,
                           contact_pairs=contact_pairs)
    if kind == "mujoco":
        if str(device) != "cpu":
            raise ValueError(f"the mujoco backend runs on the CPU only, got device '{device}'")
        return MuJoCoBackend(model, num_worlds, decimation=decimation, contact_bodies=contact_bodies,
                             contact_pairs=contact_pairs)
    raise ValueError(f"unknown physics backend '{kind}' (expected 'warp' or 'mujoco')")
