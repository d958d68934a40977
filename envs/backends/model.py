"""The simulation model of the tracking tasks: G1 + flat ground (+ objects), collision geometry only.

Both backends simulate this one model, so their physics agree. Differences from the scene
used for rendering (``otr_gym.scene`` with ``visual=True``):

- visual meshes are dropped (they never collide, and MuJoCo-Warp pays for every geom);
- the MJCF's IMU sensors are dropped: the MDP reads the state directly, and the
  accelerometer/angular-momentum sensors would force an extra ``rne_postconstraint`` pass
  per substep;
- one MuJoCo contact sensor per body in ``contact_bodies`` reports the net contact force on
  that body (``data="force"``, ``reduce="netforce"``), the same on CPU and GPU;
- with objects (OTR-G1-BoxTrack-v0, ``envs.objects``): their bodies, plus one contact sensor
  per ``ContactPair`` reporting the net force between exactly those two (a hand and the box,
  the box and the table or the ground);
- with terrain (``envs.terrain``): one fixed body of collision geoms per terrain mesh.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from otr_gym.scene import SceneSpec, build_scene

_CONTACT_SENSOR_PREFIX = "contact_force/"
_DATA_FORCE = 1 << int(mujoco.mjtConDataField.mjCONDATA_FORCE)
_REDUCE_NETFORCE = 3


@dataclass(frozen=True)
class ContactPair:
    """A contact sensor between two model objects, each ("body" | "subtree" | "geom", name);
    "subtree" matches the geoms of the body and of every body below it."""

    key: str
    first: tuple[str, str]
    second: tuple[str, str]


_OBJ_TYPES = {"body": mujoco.mjtObj.mjOBJ_BODY, "subtree": mujoco.mjtObj.mjOBJ_XBODY, "geom": mujoco.mjtObj.mjOBJ_GEOM}


def build_sim_model(contact_bodies: Sequence[str], objects=None, contact_pairs: Sequence[ContactPair] = (),
                    condim: int = 3, terrain=None) -> mujoco.MjModel:
    """Compile the G1 + ground model without visual meshes, with contact sensors on
    ``contact_bodies``; ``objects`` (``envs.objects.SceneObjects``) and their ``contact_pairs``
    sensors, and ``terrain`` (``envs.terrain.SceneTerrain``) are added when given."""
    spec = build_scene(SceneSpec(visual=False)).spec
    if objects is not None:
        objects.add_to(spec, visual=False, condim=condim)
    if terrain is not None:
        terrain.add_to(spec)
    for sensor in list(spec.sensors):
        spec.delete(sensor)
    body_names = {b.name for b in spec.bodies}
    unknown = [b for b in contact_bodies if b not in body_names]
    if unknown:
        raise KeyError(f"contact sensor bodies {unknown} are not in the G1 model")
    for body in contact_bodies:
        spec.add_sensor(name=_CONTACT_SENSOR_PREFIX + body, type=mujoco.mjtSensor.mjSENS_CONTACT,
                        objtype=mujoco.mjtObj.mjOBJ_BODY, objname=body, intprm=[_DATA_FORCE, _REDUCE_NETFORCE, 1])
    geom_names = {g.name for g in spec.geoms}
    for pair in contact_pairs:
        for kind, name in (pair.first, pair.second):
            if name not in (geom_names if kind == "geom" else body_names):
                raise KeyError(f"contact pair '{pair.key}': {kind} '{name}' is not in the simulation model")
        spec.add_sensor(name=_CONTACT_SENSOR_PREFIX + pair.key, type=mujoco.mjtSensor.mjSENS_CONTACT,
                        objtype=_OBJ_TYPES[pair.first[0]], objname=pair.first[1],
                        reftype=_OBJ_TYPES[pair.second[0]], refname=pair.second[1],
                        intprm=[_DATA_FORCE, _REDUCE_NETFORCE, 1])
    return spec.compile()


def contact_sensor_adr(model: mujoco.MjModel, contact_bodies: Sequence[str]) -> np.ndarray:
    """(C,) start of each body's (or contact pair key's) 3 force values in ``sensordata``."""
    return np.array([model.sensor_adr[model.sensor(_CONTACT_SENSOR_PREFIX + b).id] for b in contact_bodies],
                    dtype=np.int32)
