"""The simulation model of the tracking task: G1 + flat ground, collision geometry only.

Both backends simulate this one model, so their physics agree. Differences from the scene
used for rendering (``otr_gym.scene`` with ``visual=True``):

- visual meshes are dropped (they never collide, and MuJoCo-Warp pays for every geom);
- the MJCF's IMU sensors are dropped: the MDP reads the state directly, and the
  accelerometer/angular-momentum sensors would force an extra ``rne_postconstraint`` pass
  per substep;
- one MuJoCo contact sensor per body in ``contact_bodies`` reports the net contact force on
  that body (``data="force"``, ``reduce="netforce"``), the same on CPU and GPU.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from otr_gym.scene import SceneSpec, build_scene

_CONTACT_SENSOR_PREFIX = "contact_force/"
_DATA_FORCE = 1 << int(mujoco.mjtConDataField.mjCONDATA_FORCE)
_REDUCE_NETFORCE = 3


def build_sim_model(contact_bodies: Sequence[str]) -> mujoco.MjModel:
    """Compile the G1 + ground model without visual meshes, with contact sensors on ``contact_bodies``."""
    spec = build_scene(SceneSpec(visual=False)).spec
    for sensor in list(spec.sensors):
        spec.delete(sensor)
    body_names = {b.name for b in spec.bodies}
    unknown = [b for b in contact_bodies if b not in body_names]
    if unknown:
        raise KeyError(f"contact sensor bodies {unknown} are not in the G1 model")
    for body in contact_bodies:
        spec.add_sensor(name=_CONTACT_SENSOR_PREFIX + body, type=mujoco.mjtSensor.mjSENS_CONTACT,
                        objtype=mujoco.mjtObj.mjOBJ_BODY, objname=body, intprm=[_DATA_FORCE, _REDUCE_NETFORCE, 1])
    return spec.compile()


def contact_sensor_adr(model: mujoco.MjModel, contact_bodies: Sequence[str]) -> np.ndarray:
    """(C,) start of each body's 3 force values in ``sensordata``."""
    return np.array([model.sensor_adr[model.sensor(_CONTACT_SENSOR_PREFIX + b).id] for b in contact_bodies],
                    dtype=np.int32)
