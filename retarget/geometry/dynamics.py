"""The G1's rigid-body dynamics as the feasibility check and the solver's trajectory pass both see
it: one Pinocchio model with the support points, friction cones, finite-difference twists, the
6 Hz low-pass, and the load that a carried object puts on the hands.

Frames and units: world z up, metres, newtons; Pinocchio configurations (free flyer xyz, xyzw
quaternion, joints) and tangents (base twist in the pelvis frame, then joints).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from otr_gym import robot
from otr_gym.robot_geometry import collision_capsules, collision_points
from otr_gym.rotations import quat_from_vector_pairs, quat_to_matrix

GRAVITY = 9.81
#: Where a hand meets what it holds, in its ``robot.HANDS`` link frame (m): the centre of the G1
#: hand between palm and fingers (the box environment's ``hand_point_offset_m``).
HAND_POINT_B = np.array([0.11, 0.0, 0.0])


@dataclass(frozen=True)
class G1Dynamics:
    """The Pinocchio G1 with one operational frame per sole point (the corners, 2-D convex hull,
    of each foot's collision capsules, on their underside), one per ``collision_points`` point
    (capsule end spheres and spheres, the hands' box corners) and one per hand contact point
    (``HAND_POINT_B``)."""

    pin_model: object
    sole_frames: tuple[tuple[int, ...], tuple[int, ...]]  # pinocchio frame ids per foot
    sole_points_b: tuple[np.ndarray, np.ndarray]  # (P, 3) in the ankle_roll_link frame
    link_probes: tuple[int, ...]  # indices into probe_frames of the links other than the feet
    probe_frames: tuple[tuple[int, float, str], ...]  # collision_points: (frame, radius, body)
    hand_frames: tuple[int, int]  # the hands' contact points, ``robot.HANDS`` order
    mass_kg: float


@lru_cache(maxsize=1)
def g1_dynamics() -> G1Dynamics:
    """The model (built once). The probes of the links other than the feet are also their
    support points: the geometry the simulation collides, the hands' boxes rather than the
    retargeter's coarse hand capsules."""
    from scipy.spatial import ConvexHull

    model = robot.load_pinocchio_model()
    frames, points = [], []
    for foot in robot.FEET:
        caps = [c for c in collision_capsules() if c.body == foot]
        ends = np.concatenate([[c.p0, c.p1] for c in caps])
        ends[:, 2] -= max(c.radius for c in caps)  # the underside of the sole
        corners = ends[ConvexHull(ends[:, :2]).vertices]
        frames.append(tuple(robot.add_point_frame(model, foot, p, f"{foot}_sole{k}") for k, p in enumerate(corners)))
        points.append(corners)
    probes = [(robot.add_point_frame(model, point.body, point.point, f"{point.geom}_probe{k}"),
               point.radius, point.body)
              for k, point in enumerate(collision_points())]
    links = tuple(i for i, (_, _, body) in enumerate(probes) if body not in robot.FEET)
    hands = tuple(robot.add_point_frame(model, hand, HAND_POINT_B, f"{hand}_grip") for hand in robot.HANDS)
    mass = float(sum(model.inertias[i].mass for i in range(model.njoints)))
    return G1Dynamics(model, tuple(frames), tuple(points), links, tuple(probes), (hands[0], hands[1]), mass)


def cone_edges(mu: float, normal: np.ndarray | None = None) -> np.ndarray:
    """(3, 4) unit generators of the linearised friction cone about ``normal`` (world, unit; +z
    if None): the +z pyramid turned onto the normal (upward normals, never parallel to x)."""
    edges = np.array([[mu, 0, 1], [-mu, 0, 1], [0, mu, 1], [0, -mu, 1]], dtype=np.float64).T
    edges /= np.linalg.norm(edges, axis=0)
    if normal is None:
        return edges
    x, z = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    return quat_to_matrix(quat_from_vector_pairs(z, x, np.asarray(normal, np.float64), x)) @ edges


def twist_steps(q: np.ndarray, dt: float) -> np.ndarray:
    """(T−1, nv) Δₖ = difference(qₖ, qₖ₊₁)/dt: the constant twist over [k, k+1] (Pinocchio's
    free-flyer convention: pelvis frame; joints: plain differences)."""
    import pinocchio as pin

    m = g1_dynamics().pin_model
    return np.stack([pin.difference(m, q[k], q[k + 1]) for k in range(q.shape[0] - 1)]) / dt


def lowpass(x: np.ndarray, cutoff_hz: float | None, fps: float) -> np.ndarray:
    """Zero-phase 4th-order Butterworth along axis 0 (unchanged when off or too short):
    ``scipy.signal.filtfilt(*scipy.signal.butter(2, cutoff_hz / (0.5 fps)), x, axis=0)``, bit
    for bit, without importing ``scipy.signal`` (~1 s of a run's start: it imports
    ``scipy.stats``); ``tests/retarget/checks/test_feasibility.py`` compares the two."""
    if not cutoff_hz or cutoff_hz >= 0.5 * fps or x.shape[0] < 16:
        return x
    b, a = butter2(cutoff_hz / (0.5 * fps))  # 2nd order, run forwards and backwards: 4th order
    return filtfilt3(b, a, np.asarray(x, np.float64))


def butter2(wn: float) -> tuple[np.ndarray, np.ndarray]:
    """``scipy.signal.butter(2, wn)`` (a digital low pass, 0 < wn < 1): scipy 1.17's own steps
    (analogue prototype, pre-warp, ``lp2lp_zpk``, ``bilinear_zpk``, ``zpk2tf``) in numpy."""
    order, fs = 2, 2.0
    p = -np.exp(1j * np.pi * np.arange(-order + 1, order, 2, dtype=np.float64) / (2 * order))  # buttap
    warped = float(2 * fs * np.tan(np.pi * np.asarray(wn, dtype=np.float64) / fs))
    p, k = warped * p, 1.0 * warped ** order  # lp2lp_zpk (no finite zeros)
    fs2 = 2.0 * fs  # bilinear_zpk
    p_z = (fs2 + p) / (fs2 - p)
    z_z = -np.ones(order)
    k_z = k * np.real(np.prod(fs2 - np.zeros(0)) / np.prod(fs2 - p))
    return k_z * _poly(z_z), np.real(_poly(p_z)).copy()  # zpk2tf: the poles are a conjugate pair


def _poly(roots: np.ndarray) -> np.ndarray:
    """The monic polynomial of ``roots`` (scipy's ``_polyutils.poly``, before its real part)."""
    a = np.ones((1,), dtype=roots.dtype)
    one = np.ones_like(roots[0])
    for root in roots:
        a = np.convolve(a, np.stack((one, -root)), mode="full")
    return a


def filtfilt3(b: np.ndarray, a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``scipy.signal.filtfilt(b, a, x, axis=0)`` for a second-order filter (3 taps): odd
    extension by 9 samples, the steady state of a step as the initial state, forwards, then
    backwards; each pass ``lfilter``'s direct form II transposed recurrence in its own order."""
    edge = 9  # 3 × the taps
    if x.shape[0] <= edge:
        raise ValueError(f"The length of the input vector x must be greater than padlen, which is {edge}.")
    ext = np.concatenate((2 * x[0:1] - x[edge:0:-1], x, 2 * x[-1:] - x[-2:-(edge + 2):-1]), axis=0)
    b, a = b / a[0], a / a[0]
    companion = np.zeros((2, 2))  # lfilter_zi
    companion[0, :] = -a[1:] / (1.0 * a[0:1])
    companion[1, 0] = 1
    zi = np.linalg.solve(np.eye(2) - companion.T, b[1:] - a[1:] * b[0]).reshape((2,) + (1,) * (x.ndim - 1))
    y = _lfilter3(b, a, ext, zi * ext[0:1])
    y = _lfilter3(b, a, y[::-1], zi * y[-1:])[::-1]
    return y[edge:-edge]


def _lfilter3(b: np.ndarray, a: np.ndarray, x: np.ndarray, zi: np.ndarray) -> np.ndarray:
    """``scipy.signal.lfilter(b, a, x, axis=0, zi=zi)[0]`` for 3 taps (a[0] = 1): per sample
    y = z₀ + b₀x, z₀ ← (z₁ + x b₁) − y a₁, z₁ ← x b₂ − y a₂, as scipy's C loop evaluates them."""
    y = np.empty_like(x)
    z0, z1 = zi[0].copy(), zi[1].copy()
    b0, b1, b2, a1, a2 = (float(v) for v in (b[0], b[1], b[2], a[1], a[2]))
    for n in range(x.shape[0]):
        xn = x[n]
        yn = z0 + b0 * xn
        z0 = z1 + xn * b1 - yn * a1
        z1 = xn * b2 - yn * a2
        y[n] = yn
    return y


def velocity_acceleration(step: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(v, a) (T, nv) from half-step twists (T−1, nv): v = mean of the two around a frame,
    a = their difference / dt (one-sided at the ends)."""
    T = step.shape[0] + 1
    v = np.empty((T, step.shape[1]))
    v[1:-1] = 0.5 * (step[1:] + step[:-1])
    v[0], v[-1] = step[0], step[-1]
    a = np.zeros_like(v)
    if T >= 3:
        a[1:-1] = (step[1:] - step[:-1]) / dt
        a[0], a[-1] = a[1], a[-2]
    return v, a


def hand_points(q: np.ndarray) -> np.ndarray:
    """(T, 2, 3) m, world: the hands' contact points (``retarget.geometry.dynamics.HAND_POINT_B``)
    of Pinocchio configurations ``q`` (T, nq)."""
    import pinocchio as pin

    mdl = g1_dynamics()
    data = mdl.pin_model.createData()
    out = np.empty((q.shape[0], 2, 3))
    for t in range(q.shape[0]):
        pin.framesForwardKinematics(mdl.pin_model, data, q[t])
        out[t] = [data.oMf[fid].translation for fid in mdl.hand_frames]
    return out


@dataclass(frozen=True)
class ObjectMass:
    """The mass a carried object puts on the hands (kg): ``default_kg`` for every moving object,
    ``per_object`` by the reference's object name. The default is the heaviest box the box
    environment draws (``envs.config.box.ObjectsCfg``: 1 kg plus up to 2 kg of randomisation)."""

    default_kg: float = 3.0
    per_object: Mapping[str, float] | None = None

    def of(self, name: str) -> float:
        return float((self.per_object or {}).get(name, self.default_kg))


def carried_object_load(reference, hand_points_w: np.ndarray, masses: ObjectMass | None = None,
                        lift_m: float = 0.02, reach_m: float = 0.10, lowpass_hz: float | None = 6.0) -> np.ndarray:
    """(T, 2, 3) N, world: the force each carried object puts on each hand (``robot.HANDS``
    order) at the hands' contact points ``hand_points_w`` (T, 2, 3), for ``reference`` at its own rate.

    An object is carried on the frames where it is lifted (its origin more than ``lift_m``
    above its lowest height over the clip: it left its support) and a hand's contact point is
    within ``reach_m`` of it (of its mesh's nearest vertex; of its origin without a mesh). The
    hands near it share equally what holding it takes, m (a + g ẑ), a its origin's acceleration
    (second differences low-passed at ``lowpass_hz``, as the torques are); the hands feel the
    opposite. A static object (moving less than 1 mm) and an object in flight (no hand near)
    load nothing."""
    masses = masses or ObjectMass()
    T = reference.num_frames
    dt = 1.0 / reference.fps
    load = np.zeros((T, 2, 3))
    for obj in reference.objects:
        pos = np.asarray(obj.pos_w, np.float64)
        if T < 3 or np.ptp(pos, axis=0).max() < 1e-3:
            continue
        vel = np.diff(lowpass(pos, lowpass_hz, reference.fps), axis=0) / dt
        acc = np.zeros_like(pos)
        acc[1:-1] = np.diff(vel, axis=0) / dt
        lifted = pos[:, 2] > pos[:, 2].min() + lift_m
        near = _hands_near(obj, hand_points_w, reach_m)
        share = near / np.maximum(near.sum(axis=1, keepdims=True), 1)
        need = masses.of(obj.name) * (acc + np.array([0.0, 0.0, GRAVITY]))  # (T, 3) what holding it takes
        load -= (lifted[:, None] * share)[..., None] * need[:, None, :]
    return load


def _hands_near(obj, hand_points_w: np.ndarray, reach_m: float) -> np.ndarray:
    """(T, 2) bool: each hand's contact point within ``reach_m`` of the object (of its mesh's
    surface, sampled every ~1 cm with its vertices, or of its origin when it has no mesh)."""
    rel = hand_points_w - obj.pos_w[:, None, :]  # (T, 2, 3)
    local = np.einsum("tji,tkj->tki", quat_to_matrix(obj.quat_w), rel)  # into the object frame
    if obj.mesh_vertices is None:
        return np.linalg.norm(local, axis=-1) <= reach_m
    import trimesh
    from scipy.spatial import cKDTree

    mesh = trimesh.Trimesh(np.asarray(obj.mesh_vertices, np.float64), np.asarray(obj.mesh_faces), process=False)
    # a coarse mesh (a box of 8 vertices) has its vertices far from the middle of its faces
    count = int(min(max(mesh.area / 1e-4, 100), 50_000))
    samples, _ = trimesh.sample.sample_surface(mesh, count, seed=0)
    dist, _ = cKDTree(np.concatenate([mesh.vertices, samples])).query(local.reshape(-1, 3))
    return dist.reshape(local.shape[:2]) <= reach_m
