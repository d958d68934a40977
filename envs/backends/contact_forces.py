"""Net contact forces of bodies and object pairs on MuJoCo-Warp, without MuJoCo's contact sensors.

The simulation model declares one MuJoCo contact sensor per contact body and pair
(``envs.backends.model``: ``data="force"``, ``reduce="netforce"``); the CPU backend reads them.
MuJoCo-Warp evaluates such sensors generically: every substep it allocates match buffers of
(worlds × sensors × ``contact_sensor_maxmatch``), tests every sensor against every contact slot
of every world (``naconmax`` = worlds × ``nconmax``) and sorts the matches, which cost the G1's
18 sensors about a third of the bare physics step at 8192 worlds (docs/benchmarks.md,
*Environment throughput*). The tracking tasks need only the net force's norm, so the warp
backend disables its sensors and runs this instead, per substep: one pass over the contacts
that exist (``nacon``) that turns each into a world-frame force (``mujoco_warp.contact_force``),
tests it against the sensors with per-geom lookup tables built once on the host, and adds it to
the (world, sensor) sums; then the running maxima of the sums' norms.

Matching and signs are MuJoCo's (``mjSENS_CONTACT``): a contact counts for a sensor when one of
its geoms belongs to the sensor's object and, if the sensor names a second object, the other
geom to that one; the force (on geom 2 from geom 1, in the contact frame) enters with + when
geom 1 is the sensor's object (regular order) and with − otherwise. The sums use atomics, so
the last bits depend on the contacts' order, as they do in MuJoCo-Warp's own netforce sensor.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

try:  # a contact the constraint solver sees, not a collision sensor's or a passive one
    from mujoco_warp._src.types import ContactType

    _CONSTRAINT_CONTACT = int(ContactType.CONSTRAINT)
except ImportError:  # the enum is not exported; its value in MuJoCo-Warp 3.3-4.0
    _CONSTRAINT_CONTACT = 1

_SENSOR_PREFIX = "contact_force/"


@dataclass(frozen=True)
class ContactSensorTables:
    """Per-geom membership of every contact sensor's objects (host arrays, built from the MjModel).

    ``first[s, g]``/``second[s, g]``: geom g belongs to sensor s's object / second object
    (all True where the sensor names none); ``has_second[s]``: the sensor names a second object.
    """

    first: np.ndarray  # (S, ngeom) bool
    second: np.ndarray  # (S, ngeom) bool
    has_second: np.ndarray  # (S,) bool


def _members(model: mujoco.MjModel, objtype: int, objid: int) -> np.ndarray:
    """(ngeom,) bool: the geoms a sensor object (body, subtree, geom or none) covers."""
    geom_body = model.geom_bodyid
    if objtype == mujoco.mjtObj.mjOBJ_UNKNOWN or objid < 0:
        return np.ones(model.ngeom, dtype=bool)
    if objtype == mujoco.mjtObj.mjOBJ_GEOM:
        out = np.zeros(model.ngeom, dtype=bool)
        out[objid] = True
        return out
    if objtype == mujoco.mjtObj.mjOBJ_BODY:
        return geom_body == objid
    if objtype == mujoco.mjtObj.mjOBJ_XBODY:  # the body and every body below it
        inside = np.zeros(model.nbody, dtype=bool)
        for b in range(model.nbody):
            a = b
            while a > objid:
                a = model.body_parentid[a]
            inside[b] = a == objid
        return inside[geom_body]
    raise ValueError(f"contact sensor object type {objtype} is not supported (body, subtree, geom)")


def sensor_tables(model: mujoco.MjModel, names: Sequence[str]) -> ContactSensorTables:
    """The lookup tables of the contact sensors ``contact_force/NAME`` for ``names``, in order."""
    first, second, has_second = [], [], []
    for name in names:
        sid = model.sensor(_SENSOR_PREFIX + name).id
        if model.sensor_type[sid] != mujoco.mjtSensor.mjSENS_CONTACT:
            raise ValueError(f"sensor '{_SENSOR_PREFIX + name}' is not a contact sensor")
        first.append(_members(model, int(model.sensor_objtype[sid]), int(model.sensor_objid[sid])))
        ref = int(model.sensor_reftype[sid]), int(model.sensor_refid[sid])
        named = ref[0] != mujoco.mjtObj.mjOBJ_UNKNOWN and ref[1] >= 0
        second.append(_members(model, *ref) if named else np.ones(model.ngeom, dtype=bool))
        has_second.append(named)
    ngeom = model.ngeom
    return ContactSensorTables(np.array(first, dtype=bool).reshape(-1, ngeom),
                               np.array(second, dtype=bool).reshape(-1, ngeom), np.array(has_second, dtype=bool))


@wp.kernel
def _accumulate(nacon: wp.array(dtype=wp.int32), contact_type: wp.array(dtype=wp.int32),
                contact_geom: wp.array(dtype=wp.vec2i), contact_worldid: wp.array(dtype=wp.int32),
                force_w: wp.array(dtype=wp.spatial_vector), first: wp.array2d(dtype=wp.int8),
                second: wp.array2d(dtype=wp.int8), has_second: wp.array(dtype=wp.int8),
                net: wp.array2d(dtype=wp.vec3)):
    """net[w, s] += ±force of contact c for every sensor s it matches (one thread per contact slot)."""
    c = wp.tid()
    if c >= nacon[0]:
        return
    if (contact_type[c] & _CONSTRAINT_CONTACT) == 0:
        return
    g = contact_geom[c]
    w = contact_worldid[c]
    f = wp.spatial_top(force_w[c])
    for s in range(first.shape[0]):
        m11 = first[s, g[0]] != 0
        m12 = first[s, g[1]] != 0
        if has_second[s] != 0:
            regular = m11 and second[s, g[1]] != 0
            reverse = m12 and second[s, g[0]] != 0
            if regular:
                wp.atomic_add(net, w, s, f)
            elif reverse:
                wp.atomic_add(net, w, s, -f)
        elif m11:
            wp.atomic_add(net, w, s, f)
        elif m12:
            wp.atomic_add(net, w, s, -f)


@wp.kernel
def _running_max(net: wp.array2d(dtype=wp.vec3), out: wp.array2d(dtype=float)):
    """out[w, s] = max(out[w, s], |net[w, s]|), then net[w, s] = 0 for the next substep."""
    w, s = wp.tid()
    out[w, s] = wp.max(out[w, s], wp.length(net[w, s]))
    net[w, s] = wp.vec3(0.0, 0.0, 0.0)


class NetContactForces:
    """Per-substep net contact forces of MuJoCo-Warp worlds for a fixed list of contact sensors.

    ``update(m, d, out)`` folds the current substep into ``out`` (worlds, S), the running maxima of
    the net force norms (N); ``vectors(m, d)`` returns the current (worlds, S, 3) world-frame net
    forces (for tests and diagnostics). Both launch only device work (graph-capturable).
    """

    def __init__(self, model: mujoco.MjModel, names: Sequence[str], num_worlds: int, naconmax: int,
                 device: wp.context.Device):
        tables = sensor_tables(model, names)
        self.num_sensors = len(names)
        with wp.ScopedDevice(device):
            self._first = wp.array(tables.first.astype(np.int8), dtype=wp.int8)
            self._second = wp.array(tables.second.astype(np.int8), dtype=wp.int8)
            self._has_second = wp.array(tables.has_second.astype(np.int8), dtype=wp.int8)
            self._ids = wp.array(np.arange(naconmax, dtype=np.int32), dtype=wp.int32)
            self._force = wp.zeros(naconmax, dtype=wp.spatial_vector)
            self._net = wp.zeros((num_worlds, max(self.num_sensors, 1)), dtype=wp.vec3)

    def _accumulate(self, m, d) -> None:
        mjw.contact_force(m, d, self._ids, True, self._force)
        wp.launch(_accumulate, dim=self._ids.shape[0],
                  inputs=[d.nacon, d.contact.type, d.contact.geom, d.contact.worldid, self._force, self._first,
                          self._second, self._has_second], outputs=[self._net])

    def update(self, m, d, out: wp.array2d) -> None:
        if self.num_sensors == 0:
            return
        self._accumulate(m, d)
        wp.launch(_running_max, dim=out.shape, inputs=[self._net], outputs=[out])

    def vectors(self, m, d) -> np.ndarray:
        self._net.zero_()
        self._accumulate(m, d)
        out = self._net.numpy()[:, :self.num_sensors].copy()
        self._net.zero_()
        return out
