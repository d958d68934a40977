"""Quaternion and SO(3) maths: the one implementation used by every package.

Conventions: quaternions are **wxyz** (scalar first) unless a name says ``xyzw``; rotation
vectors (axis·angle, radians) are the SO(3) log; rotation matrices act on column vectors.
Every function is batched over leading axes and accepts NumPy arrays or torch tensors
(returning the same kind), so the retargeter (NumPy) and the environments (torch, GPU)
share the same maths.
"""

from __future__ import annotations

import sys
from typing import Any

import numba
import numpy as np

#: torch, once something has imported it: a tensor cannot exist before, and the retargeter
#: (NumPy only) then never pays torch's ~2.5 s import. Every torch call below follows _is_torch.
torch: Any = None


def _is_torch(x) -> bool:
    global torch
    if torch is None:
        torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def _stack(xs, axis: int = -1):
    return torch.stack(xs, dim=axis) if _is_torch(xs[0]) else np.stack(xs, axis=axis)


def _norm(x, keepdims: bool = False):
    if _is_torch(x):
        return torch.linalg.norm(x, dim=-1, keepdim=keepdims)
    return np.linalg.norm(x, axis=-1, keepdims=keepdims)


def _where(c, a, b):
    return torch.where(c, a, b) if _is_torch(c) else np.where(c, a, b)


def _clip(x, lo, hi):
    return torch.clamp(x, lo, hi) if _is_torch(x) else np.clip(x, lo, hi)


def _atan2(y, x):
    return torch.atan2(y, x) if _is_torch(y) else np.arctan2(y, x)


def _sin(x):
    return torch.sin(x) if _is_torch(x) else np.sin(x)


def _cos(x):
    return torch.cos(x) if _is_torch(x) else np.cos(x)


def _sqrt(x):
    return torch.sqrt(x) if _is_torch(x) else np.sqrt(x)


def _as_float(x):
    if _is_torch(x):
        return x if x.is_floating_point() else x.float()
    return np.asarray(x, dtype=np.float64) if np.asarray(x).dtype.kind != "f" else np.asarray(x)


# ------------------------------------------------------------------ conversions


def xyzw_to_wxyz(q):
    return q[..., [3, 0, 1, 2]]


def wxyz_to_xyzw(q):
    return q[..., [1, 2, 3, 0]]


def quat_normalize(q):
    q = _as_float(q)
    return q / _norm(q, keepdims=True)


def quat_canonical(q):
    """Sign-fix so that w ≥ 0 (q and −q are the same rotation)."""
    return _where(q[..., :1] < 0, -q, q)


# ------------------------------------------------------------------ algebra


# Torch paths with few kernels: on a GPU the environments' quaternion maths runs on thousands of
# worlds at once, where each elementwise op is one kernel launch; the component-by-component
# formulas below cost ~30 launches per product, the gathered form 4. Same arithmetic, summed in
# another order (float32 results agree to rounding).
_TABLES: dict = {}


def _torch_tables(like) -> dict:
    key = (like.device, like.dtype)
    t = _TABLES.get(key)
    if t is None:
        kw = {"device": like.device}
        # a ⊗ b: out_i = Σ_j sign_ij · a_j · b_{index_ij}
        product_index = torch.tensor([0, 1, 2, 3, 1, 0, 3, 2, 2, 3, 0, 1, 3, 2, 1, 0], **kw)
        product_sign = torch.tensor([1, -1, -1, -1, 1, 1, 1, -1, 1, -1, 1, 1, 1, 1, -1, 1], dtype=like.dtype, **kw)
        # R(q) for unit q: R_flat = I + Σ_k coeff[:, k] · q_{i_k} q_{j_k} over the 9 products below
        pairs = [(0, 1), (0, 2), (0, 3), (1, 1), (1, 2), (1, 3), (2, 2), (2, 3), (3, 3)]
        #        wx       wy       wz       xx       xy       xz       yy       yz       zz
        coeff = [[0, 0, 0, 0, 0, 0, -2, 0, -2], [0, 0, -2, 0, 2, 0, 0, 0, 0], [0, 2, 0, 0, 0, 2, 0, 0, 0],
                 [0, 0, 2, 0, 2, 0, 0, 0, 0], [0, 0, 0, -2, 0, 0, 0, 0, -2], [-2, 0, 0, 0, 0, 0, 0, 2, 0],
                 [0, -2, 0, 0, 0, 2, 0, 0, 0], [2, 0, 0, 0, 0, 0, 0, 2, 0], [0, 0, 0, -2, 0, 0, -2, 0, 0]]
        t = _TABLES[key] = {
            "product_index": product_index, "product_sign": product_sign.view(4, 4),
            "conj": torch.tensor([1, -1, -1, -1], dtype=like.dtype, **kw),
            "pair_i": torch.tensor([i for i, _ in pairs], **kw), "pair_j": torch.tensor([j for _, j in pairs], **kw),
            "matrix_coeff": torch.tensor(coeff, dtype=like.dtype, **kw),
            "identity": torch.eye(3, dtype=like.dtype, **kw).reshape(9),
        }
    return t


def quat_mul(a, b):
    """Hamilton product a ⊗ b (wxyz)."""
    if _is_torch(a) and _is_torch(b) and a.dtype == b.dtype:
        t = _torch_tables(a)
        gathered = b[..., t["product_index"]].unflatten(-1, (4, 4)) * t["product_sign"]
        return (a[..., None, :] * gathered).sum(-1)
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return _stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])


def quat_conj(q):
    """Conjugate = inverse for unit quaternions."""
    if _is_torch(q) and q.is_floating_point():
        return q * _torch_tables(q)["conj"]
    return _stack([q[..., 0], -q[..., 1], -q[..., 2], -q[..., 3]])


def quat_apply(q, v):
    """Rotate vectors v (…, 3) by unit quaternions q (…, 4)."""
    w, xyz = q[..., :1], q[..., 1:]
    t = 2.0 * _cross(xyz, v)
    return v + w * t + _cross(xyz, t)


def quat_apply_inverse(q, v):
    """Rotate v by q⁻¹ (world → body frame when q is the body orientation)."""
    return quat_apply(quat_conj(q), v)


def _cross(a, b):
    if _is_torch(a):
        return torch.cross(*torch.broadcast_tensors(a, b), dim=-1)
    return np.cross(a, b)


# ------------------------------------------------------------------ exp / log


def quat_from_rotvec(r):
    """SO(3) exp: rotation vector (…, 3) → unit quaternion (…, 4)."""
    r = _as_float(r)
    angle = _norm(r, keepdims=True)
    half = 0.5 * angle
    small = angle < 1e-8
    # sin(θ/2)/θ, with its Taylor expansion near 0
    k = _where(small, 0.5 - angle**2 / 48.0, _sin(half) / _where(small, 1.0 + 0 * angle, angle))
    xyz = k * r
    return _stack([_cos(half)[..., 0], xyz[..., 0], xyz[..., 1], xyz[..., 2]])


def quat_to_rotvec(q):
    """SO(3) log: unit quaternion → rotation vector (angle in [0, π])."""
    q = quat_canonical(_as_float(q))
    xyz = q[..., 1:]
    s = _norm(xyz, keepdims=True)
    angle = 2.0 * _atan2(s, q[..., :1])
    small = s < 1e-8
    k = _where(small, 2.0 / _where(small, q[..., :1], 1.0 + 0 * s), angle / _where(small, 1.0 + 0 * s, s))
    return k * xyz


def quat_angle(q):
    """Rotation angle of q in [0, π]."""
    q = _as_float(q)
    return 2.0 * _atan2(_norm(q[..., 1:]), _abs(q[..., 0]))


def _abs(x):
    return torch.abs(x) if _is_torch(x) else np.abs(x)


def quat_error_angle(a, b):
    """Angle (rad) of the rotation between a and b."""
    return quat_angle(quat_mul(quat_conj(a), b))


# ------------------------------------------------------------------ matrices


def quat_to_matrix(q):
    """Unit quaternion (…, 4) → rotation matrix (…, 3, 3)."""
    if _is_torch(q) and q.is_floating_point():
        t = _torch_tables(q)
        products = q[..., t["pair_i"]] * q[..., t["pair_j"]]  # (…, 9)
        flat = (products[..., None, :] * t["matrix_coeff"]).sum(-1) + t["identity"]
        return flat.unflatten(-1, (3, 3))
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        _stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
        _stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
        _stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
    ]
    return _stack(rows, axis=-2)


def matrix_to_quat(m):
    """Rotation matrix (…, 3, 3) → unit quaternion (…, 4), w ≥ 0 (Shepperd's method)."""
    m = _as_float(m)
    if isinstance(m, np.ndarray) and m.dtype == np.float64 and m.ndim >= 2 and m.shape[-2:] == (3, 3):
        # the same arithmetic, element by element, without ~40 small array operations
        flat = np.ascontiguousarray(m).reshape(-1, 3, 3)
        out = np.empty((len(flat), 4))
        _matrix_to_quat_f64(flat, out)
        return out.reshape(*m.shape[:-2], 4)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    candidates = _stack([
        _stack([1 + m00 + m11 + m22, m[..., 2, 1] - m[..., 1, 2],
                m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]]),
        _stack([m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22,
                m[..., 1, 0] + m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0]]),
        _stack([m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] + m[..., 0, 1],
                1 - m00 + m11 - m22, m[..., 2, 1] + m[..., 1, 2]]),
        _stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0],
                m[..., 2, 1] + m[..., 1, 2], 1 - m00 - m11 + m22]),
    ], axis=-2)  # (…, 4 candidates, 4)
    diag = _stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22])
    if _is_torch(m):
        best = torch.argmax(diag, dim=-1)
        q = torch.gather(candidates, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    else:
        best = np.argmax(diag, axis=-1)
        q = np.take_along_axis(candidates, best[..., None, None], axis=-2)[..., 0, :]
    return quat_canonical(quat_normalize(q))


@numba.njit(cache=True)
def _matrix_to_quat_f64(m, out):
    """:func:`matrix_to_quat` of float64 matrices (n, 3, 3) into out (n, 4): Shepperd's
    candidate of the largest diagonal term (the first on ties, as argmax), normalised by the
    square root of its squares summed in order, then w ≥ 0."""
    for i in range(m.shape[0]):
        m00, m01, m02 = m[i, 0, 0], m[i, 0, 1], m[i, 0, 2]
        m10, m11, m12 = m[i, 1, 0], m[i, 1, 1], m[i, 1, 2]
        m20, m21, m22 = m[i, 2, 0], m[i, 2, 1], m[i, 2, 2]
        d0, d1, d2, d3 = 1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22
        best, top = 0, d0
        if d1 > top or np.isnan(d1) and not np.isnan(top):
            best, top = 1, d1
        if d2 > top or np.isnan(d2) and not np.isnan(top):
            best, top = 2, d2
        if d3 > top or np.isnan(d3) and not np.isnan(top):
            best, top = 3, d3
        if best == 0:
            q0, q1, q2, q3 = d0, m21 - m12, m02 - m20, m10 - m01
        elif best == 1:
            q0, q1, q2, q3 = m21 - m12, d1, m10 + m01, m02 + m20
        elif best == 2:
            q0, q1, q2, q3 = m02 - m20, m10 + m01, d2, m21 + m12
        else:
            q0, q1, q2, q3 = m10 - m01, m02 + m20, m21 + m12, d3
        norm = np.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        q0, q1, q2, q3 = q0 / norm, q1 / norm, q2 / norm, q3 / norm
        if q0 < 0:
            q0, q1, q2, q3 = -q0, -q1, -q2, -q3
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = q0, q1, q2, q3


def so3_exp(r):
    """Rotation vector (…, 3) → rotation matrix (…, 3, 3)."""
    return quat_to_matrix(quat_from_rotvec(r))


def so3_log(m):
    """Rotation matrix (…, 3, 3) → rotation vector (…, 3)."""
    return quat_to_rotvec(matrix_to_quat(m))


def skew(v):
    """[v]× (…, 3, 3) such that skew(v) @ u = v × u."""
    z = 0 * v[..., 0]
    return _stack([
        _stack([z, -v[..., 2], v[..., 1]]),
        _stack([v[..., 2], z, -v[..., 0]]),
        _stack([-v[..., 1], v[..., 0], z]),
    ], axis=-2)


def so3_left_jacobian_inverse(r):
    """J_l⁻¹(r) (…, 3, 3): log(exp(δ) exp(r)) ≈ r + J_l⁻¹(r) δ for a small world-frame δ.

    J_l⁻¹ = I − ½[r]× + (1/θ² − (1 + cos θ)/(2θ sin θ)) [r]×², with the series 1/12 + θ²/720 near 0.
    """
    r = _as_float(r)
    theta = _norm(r)
    small = theta < 1e-4
    safe = _where(small, 1.0 + 0 * theta, theta)
    coef = _where(small, 1.0 / 12.0 + theta**2 / 720.0,
                  1.0 / safe**2 - (1.0 + _cos(safe)) / (2.0 * safe * _sin(safe)))
    k = skew(r)
    eye = torch.eye(3, dtype=r.dtype, device=r.device) if _is_torch(r) else np.eye(3)
    return eye - 0.5 * k + coef[..., None, None] * (k @ k)


def quat_from_vector_pairs(a_from, b_from, a_to, b_to):
    """The rotation taking direction a_from exactly onto a_to, with b_from turned into the
    half-plane spanned by a_to and b_to (the TRIAD method). The b's only fix the roll about a:
    they need not be unit nor orthogonal to a, only not parallel to it. Returns wxyz (…, 4).
    """

    def frame(a, b):  # orthonormal columns (a, b ⟂ a, a × b)
        e1 = a / _norm(a, keepdims=True)
        e2 = b - (e1 * b).sum(-1)[..., None] * e1
        e2 = e2 / _norm(e2, keepdims=True)
        return _stack([e1, e2, _cross(e1, e2)], axis=-1)

    f_from, f_to = frame(_as_float(a_from), _as_float(b_from)), frame(_as_float(a_to), _as_float(b_to))
    return matrix_to_quat(f_to @ f_from.swapaxes(-1, -2))


# ------------------------------------------------------------------ yaw, gravity, 6D


def quat_yaw(q):
    """The yaw-only part of q (rotation about world z), wxyz."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    yaw = _atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    zero = 0 * yaw
    return _stack([_cos(0.5 * yaw), zero, zero, _sin(0.5 * yaw)])


def quat_from_yaw(yaw):
    zero = 0 * yaw
    return _stack([_cos(0.5 * yaw), zero, zero, _sin(0.5 * yaw)])


def quat_from_euler_xyz(roll, pitch, yaw):
    """q = Rz(yaw)·Ry(pitch)·Rx(roll) (extrinsic x-y-z), wxyz."""
    zero = 0 * roll
    qx = _stack([_cos(0.5 * roll), _sin(0.5 * roll), zero, zero])
    qy = _stack([_cos(0.5 * pitch), zero, _sin(0.5 * pitch), zero])
    qz = _stack([_cos(0.5 * yaw), zero, zero, _sin(0.5 * yaw)])
    return quat_mul(qz, quat_mul(qy, qx))


def projected_gravity(q):
    """World gravity direction (0, 0, −1) expressed in the body frame of q."""
    if _is_torch(q):
        g = torch.zeros(*q.shape[:-1], 3, dtype=q.dtype, device=q.device)
    else:
        g = np.zeros((*q.shape[:-1], 3))
    g[..., 2] = -1.0
    return quat_apply_inverse(q, g)


def matrix_first_two_columns(q):
    """The 6-D orientation feature: first two columns of R(q), flattened row-major (…, 6)."""
    m = quat_to_matrix(q)[..., :, :2]
    return m.reshape(*m.shape[:-2], 6)


# ------------------------------------------------------------------ time derivatives


def angular_velocity_from_quats(q, dt: float):
    """World-frame angular velocity (rad/s) of a quaternion track (T, …, 4) by central differences.

    ω_t = log(q_{t+1} ⊗ q_{t−1}⁻¹) / (2 dt) inside; one-sided at the ends.
    """
    q = _as_float(q)
    if q.shape[0] < 2:
        return 0 * q[..., 1:]
    fwd = quat_to_rotvec(quat_mul(q[1:], quat_conj(q[:-1]))) / dt  # (T-1, …, 3)
    out = (torch.empty(*q.shape[:-1], 3, dtype=q.dtype, device=q.device) if _is_torch(q)
           else np.empty((*q.shape[:-1], 3)))
    out[0], out[-1] = fwd[0], fwd[-1]
    if q.shape[0] > 2:
        out[1:-1] = quat_to_rotvec(quat_mul(q[2:], quat_conj(q[:-2]))) / (2 * dt)
    return out


def linear_velocity_from_positions(p, dt: float):
    """Velocity (T, …, 3) of a position track by central differences, one-sided at the ends."""
    p = _as_float(p)
    if p.shape[0] < 2:
        return 0 * p
    if _is_torch(p):
        return torch.gradient(p, spacing=dt, dim=0)[0]
    return np.gradient(p, dt, axis=0)


def quat_slerp(a, b, t):
    """Spherical interpolation between unit quaternions a and b at fraction t (broadcast)."""
    a, b = _as_float(a), _as_float(b)
    dot = (a * b).sum(-1) if _is_torch(a) else np.sum(a * b, axis=-1)
    b = _where(dot[..., None] < 0, -b, b)
    dot = _abs(dot)
    theta = _atan2(_sqrt(_clip(1 - dot**2, 0.0, 1.0)), dot)
    small = theta < 1e-6
    safe = _where(small, 1.0 + 0 * theta, _sin(theta))
    wa = _where(small, 1 - t, _sin((1 - t) * theta) / safe)
    wb = _where(small, t, _sin(t * theta) / safe)
    return quat_normalize(wa[..., None] * a + wb[..., None] * b)


