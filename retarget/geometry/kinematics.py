"""G1 kinematics for the retargeting solver: link poses, link Jacobians, capsule self-distance.

Everything is batched over the 30 G1 links (``otr_gym.robot.BODY_NAMES`` order). Pinocchio
configurations are ``[xyz, quat xyzw, 29 joints]``; its tangent ``δv`` (35) is the free-flyer
twist in the **base frame** followed by the joint rates, and ``q ⊕ δv = pin.integrate``.

A link Jacobian ``J6`` (6, nv) is Pinocchio's LOCAL_WORLD_ALIGNED Jacobian at the link origin:
rows 0–2 the world velocity of the origin, rows 3–5 the world angular velocity. A point ``x``
rigidly attached to the link moves as ``ẋ = [I, −[x − o]×] J6 δv``; a scalar residual whose
world gradient is ``a`` therefore has the row ``φᵀ J6`` with ``φ = (a, (x − o) × a)``. Every
residual and constraint of the solver is written through such 6-vectors φ (see
``retarget.solver.residuals``), which is what lets the solver merge rows per link.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np
import pinocchio as pin

from otr_gym import robot
from otr_gym.robot_geometry import collision_capsules
from retarget.geometry.jit import helper

NUM_LINKS = len(robot.BODY_NAMES)


def tree_distance(parents: np.ndarray) -> np.ndarray:
    """(L, L) number of joints between links of a kinematic tree (parents[i] < 0 at roots)."""
    L = len(parents)
    depth = np.zeros(L, dtype=np.int64)
    chains = []
    for i in range(L):
        chain = [i]
        while parents[chain[-1]] >= 0:
            chain.append(int(parents[chain[-1]]))
        chains.append(chain)
        depth[i] = len(chain) - 1
    dist = np.zeros((L, L), dtype=np.int64)
    for i in range(L):
        for j in range(L):
            common = set(chains[i]) & set(chains[j])
            lca_depth = max(depth[k] for k in common) if common else -1
            dist[i, j] = depth[i] + depth[j] - 2 * lca_depth if common else L
    return dist


def link_pairs_beyond(parents: np.ndarray, hops: int = 2) -> np.ndarray:
    """(P, 2) link pairs i < j more than ``hops`` joints apart in the tree: the pairs whose
    meshes must not overlap (closer ones interpenetrate around their joints by design)."""
    dist = tree_distance(parents)
    i, j = np.triu_indices(len(parents), k=1)
    keep = dist[i, j] > hops
    return np.stack([i[keep], j[keep]], axis=1)


@dataclass(frozen=True)
class LinkFrames:
    """World poses and LOCAL_WORLD_ALIGNED Jacobians of the 30 links at one configuration."""

    rot: np.ndarray  # (L, 3, 3) link → world
    pos: np.ndarray  # (L, 3) link origin, world (m)
    jac: np.ndarray  # (L, 6, nv) [linear; angular], world-aligned, at the link origin


class RobotKinematics:
    """Immutable G1 model (Pinocchio) and the link tables the solver needs.

    Scratch ``pin.Data`` is created by :meth:`new_data` and owned by the caller's state, in the
    model/data style of Pinocchio.
    """

    def __init__(self) -> None:
        self.model = robot.load_pinocchio_model()
        m = self.model
        self.nq, self.nv = m.nq, m.nv
        frame_ids = [m.getFrameId(name, pin.BODY) for name in robot.BODY_NAMES]
        for name, fid in zip(robot.BODY_NAMES, frame_ids):
            if not np.allclose(m.frames[fid].placement.homogeneous, np.eye(4)):
                raise RuntimeError(f"G1 body '{name}' is offset from its joint frame; link Jacobians assume none")
        #: Pinocchio joint carrying each link (its body frame coincides with the joint frame).
        self.joint_ids = [int(m.frames[fid].parentJoint) for fid in frame_ids]
        joint_to_link = {j: k for k, j in enumerate(self.joint_ids)}
        #: Parent link of each link (−1 for the pelvis).
        self.parents = np.array([joint_to_link.get(int(m.parents[j]), -1) for j in self.joint_ids])
        mask = np.zeros((NUM_LINKS, self.nv), dtype=bool)
        for k, j in enumerate(self.joint_ids):
            for s in m.supports[j]:
                if s > 0:
                    mask[k, m.idx_vs[s]:m.idx_vs[s] + m.nvs[s]] = True
        #: (L, nv): which velocity coordinates move each link.
        self.support = mask
        #: Translation of each link origin in its parent's frame (constant: revolute joints).
        self.offsets_parent = np.array([m.jointPlacements[j].translation for j in self.joint_ids])
        self.joint_lower = robot.JOINT_LOWER.copy()
        self.joint_upper = robot.JOINT_UPPER.copy()

    def new_data(self) -> pin.Data:
        return self.model.createData()

    def frames(self, data: pin.Data, q: np.ndarray) -> LinkFrames:
        """Link poses and Jacobians at Pinocchio configuration ``q`` (nq,)."""
        pin.computeJointJacobians(self.model, data, q)
        # (L, 4, 4); tolist() first: indexing or iterating Pinocchio's vector costs ~0.4 µs an element
        placement = np.array([m.homogeneous for m in data.oMi.tolist()])[self.joint_ids]
        rot = placement[:, :3, :3]
        pos = placement[:, :3, 3]
        jac = np.empty((NUM_LINKS, 6, self.nv))
        _link_jacobians(data.J, pos, self.support, jac)  # data.J (6, nv) WORLD: spatial velocity at the origin
        return LinkFrames(rot, pos, jac)

    def integrate(self, q: np.ndarray, dv: np.ndarray) -> np.ndarray:
        return pin.integrate(self.model, q, dv)

    def difference(self, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
        """q1 ⊖ q0 in the tangent space (nv,)."""
        return pin.difference(self.model, q0, q1)

    @cached_property
    def self_collision(self) -> SelfCollision:
        return SelfCollision.build(self)


@numba.njit(cache=True)
def _link_jacobians(jw, pos, support, jac):
    """jac[l] ← the LOCAL_WORLD_ALIGNED Jacobian of link l from the WORLD one ``jw`` (6, nv): the
    velocity of the link origin o is v_0 + ω × o, i.e. J_lin − [o]× J_ang, on the coordinates
    that move the link (``support``, others zero)."""
    for link in range(jac.shape[0]):
        x, y, z = pos[link, 0], pos[link, 1], pos[link, 2]
        for v in range(jac.shape[2]):
            s = 1.0 if support[link, v] else 0.0
            jac[link, 0, v] = (jw[0, v] - (y * jw[5, v] - z * jw[4, v])) * s
            jac[link, 1, v] = (jw[1, v] - (z * jw[3, v] - x * jw[5, v])) * s
            jac[link, 2, v] = (jw[2, v] - (x * jw[4, v] - y * jw[3, v])) * s
            for r in range(3, 6):
                jac[link, r, v] = jw[r, v] * s


@dataclass(frozen=True)
class SelfCollision:
    """Capsule pairs that may collide: not on the same or adjacent links, apart at rest."""

    link: np.ndarray  # (K,) link of each capsule
    p0: np.ndarray  # (K, 3) segment ends, link frame
    p1: np.ndarray  # (K, 3)
    radius: np.ndarray  # (K,)
    pairs: np.ndarray  # (M, 2) capsule indices

    @classmethod
    def build(cls, kin: RobotKinematics, rest_clearance_m: float = 0.01) -> SelfCollision:
        """Keep pairs on non-adjacent links whose capsules are ``rest_clearance_m`` apart both
        in the zero pose and in the default pose: capsules that overlap at rest model
        structure (hip covers reaching into the pelvis), not collisions to prevent."""
        caps = collision_capsules()
        index = {n: k for k, n in enumerate(robot.BODY_NAMES)}
        link = np.array([index[c.body] for c in caps])
        p0 = np.array([c.p0 for c in caps])
        p1 = np.array([c.p1 for c in caps])
        radius = np.array([c.radius for c in caps])
        i, j = np.triu_indices(len(caps), k=1)
        li, lj = link[i], link[j]
        adjacent = (li == lj) | (kin.parents[li] == lj) | (kin.parents[lj] == li)
        keep = ~adjacent
        data = kin.new_data()
        for qpos in (np.concatenate([[0, 0, 0.8, 1, 0, 0, 0], np.zeros(robot.NUM_JOINTS)]), robot.default_qpos()):
            fr = kin.frames(data, robot.qpos_mujoco_to_pinocchio(qpos))
            probe = cls(link, p0, p1, radius, np.stack([i, j], axis=1))
            keep &= probe.distances(fr).dist > rest_clearance_m
        return cls(link, p0, p1, radius, np.stack([i[keep], j[keep]], axis=1))

    def distances(self, fr: LinkFrames, within: float | None = None) -> CapsuleDistances:
        """Signed distance between the capsules of every pair, with closest points (world).

        With ``within``, only pairs whose segments' bounding spheres come closer than that
        are measured (the others are provably farther).
        """
        if within is not None:
            n = len(self.pairs)
            dist, point_a, point_b, normal = np.empty(n), np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
            link_a, link_b = np.empty(n, np.intp), np.empty(n, np.intp)
            k = _capsule_distances(self.link, self.p0, self.p1, self.radius, self.pairs, fr.rot, fr.pos, float(within),
                                   dist, point_a, point_b, normal, link_a, link_b)
            return CapsuleDistances(dist[:k], point_a[:k], point_b[:k], normal[:k], link_a[:k], link_b[:k])
        a0, a1 = _posed(self, fr, self.p0), _posed(self, fr, self.p1)
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        if within is not None:
            centre, half = 0.5 * (a0 + a1), 0.5 * np.linalg.norm(a1 - a0, axis=1)
            bound = np.linalg.norm(centre[i] - centre[j], axis=1) - half[i] - half[j] - self.radius[i] - self.radius[j]
            i, j = i[bound < within], j[bound < within]
        ca, cb = segment_closest_points(a0[i], a1[i], a0[j], a1[j])
        delta = ca - cb
        length = np.linalg.norm(delta, axis=1)
        normal = delta / np.maximum(length, 1e-12)[:, None]
        dist = length - self.radius[i] - self.radius[j]
        # surface points: the closest points pushed out by each radius along the normal
        return CapsuleDistances(dist, ca - self.radius[i, None] * normal, cb + self.radius[j, None] * normal, normal,
                                self.link[i], self.link[j])


@dataclass(frozen=True)
class CapsuleDistances:
    dist: np.ndarray  # (M,) m, negative when overlapping
    point_a: np.ndarray  # (M, 3) world, on capsule a
    point_b: np.ndarray  # (M, 3) world, on capsule b
    normal: np.ndarray  # (M, 3) unit, from b towards a
    link_a: np.ndarray  # (M,) link carrying capsule a
    link_b: np.ndarray  # (M,)


def _posed(sc: SelfCollision, fr: LinkFrames, p: np.ndarray) -> np.ndarray:
    return np.einsum("kij,kj->ki", fr.rot[sc.link], p) + fr.pos[sc.link]


@helper
def _dot3(x0, x1, x2, y0, y1, y2):
    """x·y summed as numpy's einsum sums three terms on our builds: (x₀y₀ + x₂y₂) + x₁y₁."""
    return (x0 * y0 + x2 * y2) + x1 * y1


@numba.njit(cache=True)
def _capsule_distances(link, p0, p1, radius, pairs, rot, pos, within, out_dist, out_a, out_b, out_n, out_la, out_lb):
    """``SelfCollision.distances`` with ``within``, one pass (returns the pair count): the
    arithmetic of ``_posed``, the bounding test and ``segment_closest_points``, in numpy's sums
    (einsum's three-term order, norms summed in order), so that the bits are the array form's."""
    n_caps = link.shape[0]
    a0, a1 = np.empty((n_caps, 3)), np.empty((n_caps, 3))
    centre, half = np.empty((n_caps, 3)), np.empty(n_caps)
    for c in range(n_caps):
        m = link[c]
        for r in range(3):
            a0[c, r] = _dot3(rot[m, r, 0], rot[m, r, 1], rot[m, r, 2], p0[c, 0], p0[c, 1], p0[c, 2]) + pos[m, r]
            a1[c, r] = _dot3(rot[m, r, 0], rot[m, r, 1], rot[m, r, 2], p1[c, 0], p1[c, 1], p1[c, 2]) + pos[m, r]
            centre[c, r] = 0.5 * (a0[c, r] + a1[c, r])
        d0, d1, d2 = a1[c, 0] - a0[c, 0], a1[c, 1] - a0[c, 1], a1[c, 2] - a0[c, 2]
        half[c] = 0.5 * np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    eps = 1e-12
    k = 0
    for q in range(pairs.shape[0]):
        i, j = pairs[q, 0], pairs[q, 1]
        e0, e1, e2 = centre[i, 0] - centre[j, 0], centre[i, 1] - centre[j, 1], centre[i, 2] - centre[j, 2]
        if not np.sqrt(e0 * e0 + e1 * e1 + e2 * e2) - half[i] - half[j] - radius[i] - radius[j] < within:
            continue
        u0, u1, u2 = a1[i, 0] - a0[i, 0], a1[i, 1] - a0[i, 1], a1[i, 2] - a0[i, 2]
        v0, v1, v2 = a1[j, 0] - a0[j, 0], a1[j, 1] - a0[j, 1], a1[j, 2] - a0[j, 2]
        w0, w1, w2 = a0[i, 0] - a0[j, 0], a0[i, 1] - a0[j, 1], a0[i, 2] - a0[j, 2]
        a, e = _dot3(u0, u1, u2, u0, u1, u2), _dot3(v0, v1, v2, v0, v1, v2)
        f, c = _dot3(v0, v1, v2, w0, w1, w2), _dot3(u0, u1, u2, w0, w1, w2)
        b = _dot3(u0, u1, u2, v0, v1, v2)
        denom = a * e - b * b
        s = min(max((b * f - c * e) / denom, 0.0), 1.0) if denom > eps else 0.0
        t = (b * s + f) / e if e > eps else 0.0
        t_clamped = min(max(t, 0.0), 1.0)
        if t != t_clamped:
            s = min(max((b * t_clamped - c) / a, 0.0), 1.0) if a > eps else 0.0
        ca0, ca1, ca2 = a0[i, 0] + s * u0, a0[i, 1] + s * u1, a0[i, 2] + s * u2
        cb0, cb1, cb2 = a0[j, 0] + t_clamped * v0, a0[j, 1] + t_clamped * v1, a0[j, 2] + t_clamped * v2
        g0, g1, g2 = ca0 - cb0, ca1 - cb1, ca2 - cb2
        length = np.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        unit = max(length, 1e-12)
        n0, n1, n2 = g0 / unit, g1 / unit, g2 / unit
        out_dist[k] = length - radius[i] - radius[j]
        out_a[k, 0], out_a[k, 1], out_a[k, 2] = ca0 - radius[i] * n0, ca1 - radius[i] * n1, ca2 - radius[i] * n2
        out_b[k, 0], out_b[k, 1], out_b[k, 2] = cb0 + radius[j] * n0, cb1 + radius[j] * n1, cb2 + radius[j] * n2
        out_n[k, 0], out_n[k, 1], out_n[k, 2] = n0, n1, n2
        out_la[k], out_lb[k] = link[i], link[j]
        k += 1
    return k


def segment_closest_points(p0, p1, q0, q1):
    """Closest points of segments [p0, p1] and [q0, q1] (batched (M, 3)); degenerate
    segments (spheres) are handled. Classic clamped two-parameter projection."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a = np.einsum("ij,ij->i", d1, d1)
    e = np.einsum("ij,ij->i", d2, d2)
    f = np.einsum("ij,ij->i", d2, r)
    c = np.einsum("ij,ij->i", d1, r)
    b = np.einsum("ij,ij->i", d1, d2)
    denom = a * e - b * b
    eps = 1e-12
    s = np.where(denom > eps, np.clip((b * f - c * e) / np.where(denom > eps, denom, 1.0), 0.0, 1.0), 0.0)
    t = np.where(e > eps, (b * s + f) / np.where(e > eps, e, 1.0), 0.0)
    # t outside [0, 1]: clamp it and recompute s for the clamped t
    t_clamped = np.clip(t, 0.0, 1.0)
    s_clamped = np.where(a > eps, np.clip((b * t_clamped - c) / np.where(a > eps, a, 1.0), 0.0, 1.0), 0.0)
    s = np.where(t != t_clamped, s_clamped, s)
    return p0 + s[:, None] * d1, q0 + t_clamped[:, None] * d2
