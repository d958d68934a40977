"""The warp backend's own net contact forces (envs/backends/contact_forces.py) against MuJoCo-Warp's
contact sensors on the same worlds, and the tables that match geoms to sensors."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from envs.backends import ContactPair, build_sim_model
from envs.backends.contact_forces import NetContactForces, sensor_tables
from envs.backends.model import contact_sensor_adr
from envs.config import TrackEnvCfg
from envs.objects import GROUND_GEOM

wp = pytest.importorskip("warp")
mjw = pytest.importorskip("mujoco_warp")

BODIES = TrackEnvCfg().sim.contact_bodies
# Pairs of every kind and both orders: the sign rule and the subtree walk are exercised.
PAIRS = (ContactPair("left_foot|ground", ("body", "left_ankle_roll_link"), ("geom", GROUND_GEOM)),
         ContactPair("ground|right_leg", ("geom", GROUND_GEOM), ("subtree", "right_hip_roll_link")),
         ContactPair("pelvis_tree|ground", ("subtree", "pelvis"), ("geom", GROUND_GEOM)))


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return build_sim_model(BODIES, contact_pairs=PAIRS)


def test_tables_cover_exactly_the_named_geoms(model):
    names = [*BODIES, *(p.key for p in PAIRS)]
    t = sensor_tables(model, names)
    left_foot = model.body("left_ankle_roll_link").id
    assert np.array_equal(t.first[BODIES.index("left_ankle_roll_link")], model.geom_bodyid == left_foot)
    assert not t.has_second[:len(BODIES)].any() and t.has_second[len(BODIES):].all()
    ground = model.geom(GROUND_GEOM).id
    assert t.second[len(BODIES)].nonzero()[0].tolist() == [ground]
    # the whole robot hangs below the pelvis: every geom but the ground's is in its subtree
    whole = t.first[len(BODIES) + 2]
    assert not whole[ground] and whole.sum() == int((model.geom_bodyid > 0).sum())
    with pytest.raises(KeyError):
        sensor_tables(model, ["no_such_body"])


def test_net_forces_equal_mujoco_warps_contact_sensors(model):
    """Worlds dropped onto the floor in different poses: for every world and sensor the net force
    vector equals what MuJoCo-Warp's own netforce sensor reports for the same contacts."""
    rng = np.random.default_rng(0)
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    worlds = 4
    device = wp.get_device("cpu")
    with wp.ScopedDevice(device):
        m = mjw.put_model(model)
        d = mjw.put_data(model, data, nworld=worlds, nconmax=48, njmax=300)
        qpos = d.qpos.numpy()
        qpos[:, 2] -= np.array([0.0, 0.02, 0.05, 0.30])  # standing, sunk feet, on the knees
        qpos[:, 7:] += rng.uniform(-0.3, 0.3, (worlds, qpos.shape[1] - 7))
        wp.copy(d.qpos, wp.array(qpos.astype(np.float32), dtype=float))
        for _ in range(3):
            mjw.step(m, d)
        forces = NetContactForces(model, [*BODIES, *(p.key for p in PAIRS)], worlds, d.naconmax, device)
        ours = forces.vectors(m, d)
    adr = contact_sensor_adr(model, [*BODIES, *(p.key for p in PAIRS)])
    sensordata = d.sensordata.numpy()
    theirs = np.stack([sensordata[:, a:a + 3] for a in adr], axis=1)
    assert int(d.nacon.numpy()[0]) > 4 * worlds  # contacts in every world, not a vacuous match
    assert np.abs(theirs).max() > 100.0
    np.testing.assert_allclose(ours, theirs, rtol=1e-4, atol=1e-2)
