"""Interaction residuals (paper eq. m-residuals, m-energy) and their analytic Jacobian factors.

A probe x (world, on body A: a robot link or an object) faces a channel c (body B: an object,
static furniture or the ground) with pose (R_c, τ_c). Its proximity triple (d, w, n) lives in
the channel frame, x_c = R_cᵀ(x − τ_c). For each active pair the cost has up to three rows

    r^d = d − (d̂)₊,   r^x = ρ_c(w; ŵ) (as a 3-vector, see witness_vector),   r^n = (sign(d̂) n̂·(x_c − ŵ))₋

weighted f_ℓ/N_ℓ · λ · β² (r^d) or f_ℓ/N_ℓ · λ · β̄² (r^x, r^n) (ours, per link and channel, the
contact-state rows of ``retarget.solver.rows``: see ``InteractionConfig.hold_weight``). β̄ depends on the demonstration
only; β also on the current d, so the r^d row is the product β·r^d and is differentiated as such.

Jacobian factors. Every scalar row is linearised as r + φ_Aᵀ ν_A + φ_Bᵀ ν_B where ν_X is the
world-aligned twist of body X at its origin o_X (robot: LOCAL_WORLD_ALIGNED link Jacobian ×
δv; object: (δτ, δθ) of the retraction τ ← τ + δτ, R ← exp(δθ)R). With a = R_c ∂r/∂x_c the
world gradient of the row,

    φ_A = (a, (x − o_A) × a),     φ_B = −(a, (x − τ_c) × a)

because ẋ = v_A + ω_A × (x − o_A) and ẋ_c = R_cᵀ(ẋ − v_B − ω_B × (x − τ_c)). The solver turns
φ into QP rows with one 6×nv Jacobian per body (``retarget.geometry.kinematics``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from llvmlite import ir as llvm_ir
from numba import types
from numba.extending import intrinsic

from retarget.geometry.channels import Channel, ProximityQuery
from retarget.geometry.jit import helper, inlined, kernel_pose

#: Body index of things that never move (ground, static furniture): no decision variable.
FIXED = -1


@dataclass(frozen=True)
class InteractionConfig:
    """Weights and kernels of E_int (paper eq. m-energy; docs/method.md "Interaction residuals and cost")."""

    #: (λ^d, λ^x, λ^n) for probes carried by the robot (eq. m-energy).
    robot_weights: tuple[float, float, float] = (256.0, 625.0, 2500.0)
    #: Probes carried by an object weigh this many times the robot's (eq. m-energy: "four times").
    object_weight_factor: float = 4.0
    #: σ (m): width of the kernels β, β̄.
    sigma_m: float = 0.13
    #: β_max: cap of β when penetration (d < 0) drives the kernel above 1.
    beta_max: float = 5.0
    #: f_ℓ: per-link weight, kept at 1 in the paper.
    link_weight: float = 1.0
    #: Ours: contact-state rows, one per link and channel, on the link's closest active probe,
    #: with d̂_ℓ the smallest d̂ of the link's probes (its demonstrated part's gap). A link whose
    #: part touches ((d̂_ℓ)₊ < ``hold_m``, the evaluation's ε) is pulled in when farther than
    #: (d̂_ℓ)₊ (weight ``hold_weight``): a hand that touches in the demonstration touches. A link
    #: whose part stays off is pushed out to min(d̂_ℓ, ``clearance_m``) (``clearance_weight``):
    #: a part the person keeps off a surface does not touch it. r^d alone pulls both ways with
    #: λ^d/N_ℓ per probe, too weakly to keep a smaller robot's hands on the person's object, or
    #: its chest off it (OMOMO largebox: object recall 71 %, trunk on the box at 0 mm where the
    #: person's is 8–12 cm away). Not normalised by N_ℓ: 1 cm off costs 1 (per m² × 1e4).
    hold_weight: float = 1.0e4
    hold_m: float = 0.02
    clearance_weight: float = 1.0e4
    clearance_m: float = 0.03
    #: Ours: ``clearance_weight`` against the ground. The G1's shin ends lower than a person's:
    #: with the ankle at full dorsiflexion (−0.87 rad) its back edge comes within 2 cm of the
    #: floor where the person's shin is 6–8 cm above it (Bandai's walk: 18 frames, ground
    #: precision 93 %). 1e5 keeps it off (97 %); on objects the same weight pushed the free chair
    #: away (object recall 88 → 71 %), hence a weight of its own.
    ground_clearance_weight: float = 1.0e5

    @property
    def object_weights(self) -> tuple[float, float, float]:
        return tuple(self.object_weight_factor * w for w in self.robot_weights)


def beta_bar(d_hat: np.ndarray, sigma: float) -> np.ndarray:
    """β̄ = (1 − (d̂)₊/σ)₊²: gates r^x, r^n to pairs in contact in the demonstration."""
    d_hat = np.asarray(d_hat, np.float64)
    out = np.empty(d_hat.shape)
    _beta_bar_into(d_hat.ravel(), float(sigma), out.ravel())
    return out


def beta(d_hat: np.ndarray, d: np.ndarray, sigma: float, beta_max: float) -> np.ndarray:
    """β = min((1 − min((d̂)₊, d)/σ)₊², β_max): gates r^d to pairs close in the demonstration or now."""
    return beta_and_slope(d_hat, d, sigma, beta_max)[0]


def beta_and_slope(d_hat: np.ndarray, d: np.ndarray, sigma: float, beta_max: float) -> tuple[np.ndarray, np.ndarray]:
    """β (see :func:`beta`) and ∂β/∂d: −2(1 − d/σ)/σ where the current distance is the smaller
    one and the kernel is neither clipped at 0 nor capped at β_max, else 0."""
    d_hat, d = np.broadcast_arrays(np.asarray(d_hat, np.float64), np.asarray(d, np.float64))
    b, slope = np.empty(d.shape), np.empty(d.shape)
    _beta_and_slope_into(np.ascontiguousarray(d_hat).ravel(), np.ascontiguousarray(d).ravel(), float(sigma),
                         float(beta_max), b.ravel(), slope.ravel())
    return b, slope


@helper
def _positive(x):
    """(x)₊, as np.maximum(x, 0.0)."""
    return x if x > 0.0 else 0.0


@helper
def _beta_bar(d_hat, sigma):
    b = _positive(1.0 - _positive(d_hat) / sigma)
    return b * b


@helper
def _beta_and_slope(d_hat, d, sigma, beta_max):
    h = _positive(d_hat)
    b = _positive(1.0 - min(h, d) / sigma)
    b = min(b * b, beta_max)
    live = d < h and d < sigma and b < beta_max
    return b, (-2.0 * (1.0 - d / sigma) / sigma if live else 0.0)


@numba.njit(cache=True)
def _beta_bar_into(d_hat, sigma, out):
    for i in range(d_hat.shape[0]):
        out[i] = _beta_bar(d_hat[i], sigma)


@numba.njit(cache=True)
def _beta_and_slope_into(d_hat, d, sigma, beta_max, b, slope):
    for i in range(d.shape[0]):
        b[i], slope[i] = _beta_and_slope(d_hat[i], d[i], sigma, beta_max)


@dataclass(frozen=True)
class Triples:
    """Proximity triples of N probes w.r.t. one channel (channel frame): d (N,) m, w (N, 3), n (N, 3);
    ``geodesic``, when the channel has a geodesic table, the neighbours (N, k) and weights (N, k)
    of every w in it (``Channel.geodesic_weights``), kept for targets used over many iterates."""

    d: np.ndarray
    w: np.ndarray
    n: np.ndarray
    geodesic: tuple[np.ndarray, np.ndarray] | None = None

    def take(self, index: np.ndarray) -> Triples:
        geo = None if self.geodesic is None else tuple(g.take(index, axis=0) for g in self.geodesic)
        return Triples(self.d.take(index), self.w.take(index, axis=0), self.n.take(index, axis=0), geo)


def to_channel_frame(x_w: np.ndarray, rot_c: np.ndarray, pos_c: np.ndarray) -> np.ndarray:
    """x_c = R_cᵀ (x − τ_c) for points (N, 3); row-vector form (x − τ) R."""
    return (x_w - pos_c) @ rot_c


@intrinsic
def _fma(typingctx, a, b, c):
    """a·b + c rounded once (LLVM's fma), for numba kernels that must match BLAS bit for bit."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        d = llvm_ir.DoubleType()
        return builder.call(builder.module.declare_intrinsic("llvm.fma", [d], llvm_ir.FunctionType(d, [d, d, d])), args)

    return sig, codegen


@inlined
def _to_channel_point(x0, x1, x2, rot_c, pos_c):
    """:func:`to_channel_frame` of one point in a numba kernel, bit for bit: numpy's (k, 3) @ (3, 3)
    goes to OpenBLAS, whose kernel sums each entry as one FMA chain (checked for 1 to 5000 rows)."""
    d0, d1, d2 = x0 - pos_c[0], x1 - pos_c[1], x2 - pos_c[2]
    return (_fma(d2, rot_c[2, 0], _fma(d1, rot_c[1, 0], d0 * rot_c[0, 0])),
            _fma(d2, rot_c[2, 1], _fma(d1, rot_c[1, 1], d0 * rot_c[0, 1])),
            _fma(d2, rot_c[2, 2], _fma(d1, rot_c[1, 2], d0 * rot_c[0, 2])))


@helper
def _to_world_direction(g0, g1, g2, rot_c):
    """g @ R_cᵀ (a channel-frame gradient turned to the world) of one row, as numpy computes it
    (see :func:`_to_channel_point`)."""
    return (_fma(g2, rot_c[0, 2], _fma(g1, rot_c[0, 1], g0 * rot_c[0, 0])),
            _fma(g2, rot_c[1, 2], _fma(g1, rot_c[1, 1], g0 * rot_c[1, 0])),
            _fma(g2, rot_c[2, 2], _fma(g1, rot_c[2, 1], g0 * rot_c[2, 0])))


def query_triples(channel: Channel, x_w: np.ndarray, rot_c: np.ndarray, pos_c: np.ndarray) -> Triples:
    """Triples of world points against a channel at pose (R_c, τ_c); out of band d = band."""
    q = channel.query(to_channel_frame(x_w, rot_c, pos_c))
    return Triples(q.d, q.w, q.n)


@dataclass(frozen=True)
class Rows:
    """Scalar rows linearised as ``value + φ[:6]·ν_{body_a} + φ[6:]·ν_{body_b}`` (see module doc).

    ``weight`` multiplies the squared row in the cost (zero-weight rows are dropped upstream).
    Bodies are indices into the solver's body table, or FIXED.
    """

    value: np.ndarray  # (k,)
    weight: np.ndarray  # (k,)
    phi: np.ndarray  # (k, 12)
    body_a: np.ndarray  # (k,) int
    body_b: np.ndarray  # (k,) int

    def __len__(self) -> int:
        return len(self.value)

    @staticmethod
    def empty() -> Rows:
        return Rows(np.zeros(0), np.zeros(0), np.zeros((0, 12)), np.zeros(0, np.intp), np.zeros(0, np.intp))

    @staticmethod
    def concat(parts: list[Rows]) -> Rows:
        parts = [p for p in parts if len(p)]
        if not parts:
            return Rows.empty()
        return Rows(*(np.concatenate([getattr(p, f) for p in parts])
                      for f in ("value", "weight", "phi", "body_a", "body_b")))


def twist_factors(a_w: np.ndarray, x_w: np.ndarray, origin_a: np.ndarray, origin_b: np.ndarray | None) -> np.ndarray:
    """(k, 12) factors φ = (a, (x − o_A) × a, −a, −(x − o_B) × a) for world gradients a (k, 3)
    at points x (k, 3); origins (k, 3) or (3,).

    ``origin_b`` None: body B is FIXED (no decision variable), its half of φ is left zero.
    """
    k = len(a_w)
    out = np.empty((k, 12))

    def rows(v) -> np.ndarray:
        """One array type for every call (C-contiguous (·, 3) float64: each new type is another
        compilation, ~0.5 s): (k, 3), or (1, 3) for one point shared by every row (no copy k times)."""
        v = np.asarray(v, np.float64)
        if v.ndim == 1 or v.strides[0] == 0:
            return np.ascontiguousarray(v.reshape(-1, 3)[:1])
        return np.ascontiguousarray(v)

    _twist_factors(rows(a_w), rows(x_w), rows(origin_a), rows(np.zeros(3) if origin_b is None else origin_b),
                   origin_b is not None, out)
    return out


@numba.njit(cache=True)
def _twist_factors(a, x, origin_a, origin_b, with_b, out):
    """Rows of ``twist_factors``; an origin array of one row serves every row."""
    shared_a, shared_b = origin_a.shape[0] == 1, origin_b.shape[0] == 1
    for k in range(a.shape[0]):
        ia, ib = 0 if shared_a else k, 0 if shared_b else k
        if with_b:
            _twist_row(a[k, 0], a[k, 1], a[k, 2], x[k, 0], x[k, 1], x[k, 2], origin_a[ia, 0], origin_a[ia, 1],
                       origin_a[ia, 2], origin_b[ib, 0], origin_b[ib, 1], origin_b[ib, 2], out, k)
        else:
            _twist_half(a[k, 0], a[k, 1], a[k, 2], x[k, 0] - origin_a[ia, 0], x[k, 1] - origin_a[ia, 1],
                        x[k, 2] - origin_a[ia, 2], out, k, np.int64(0))
            for c in range(6, 12):
                out[k, c] = 0.0


@helper
def _twist_row(a0, a1, a2, x0, x1, x2, oa0, oa1, oa2, ob0, ob1, ob2, out, k):
    """Row k of ``twist_factors`` with both bodies moving: (a, (x − o_A) × a, −a, −(x − o_B) × a)."""
    _twist_half(a0, a1, a2, x0 - oa0, x1 - oa1, x2 - oa2, out, k, np.int64(0))
    _twist_half(-a0, -a1, -a2, x0 - ob0, x1 - ob1, x2 - ob2, out, k, np.int64(6))


@helper
def _twist_half(a0, a1, a2, r0, r1, r2, out, k, col):
    """out[k, col:col + 6] = (a, r × a)."""
    out[k, col], out[k, col + 1], out[k, col + 2] = a0, a1, a2
    out[k, col + 3] = r1 * a2 - r2 * a1
    out[k, col + 4] = r2 * a0 - r0 * a2
    out[k, col + 5] = r0 * a1 - r1 * a0


@dataclass(frozen=True)
class PairSet:
    """Active probe–channel pairs of one probe family against one channel, at one iterate.

    Arrays are restricted to the active pairs. ``x_w`` world probe positions, ``origin_a`` the
    origin of the body carrying each probe, ``body_a`` that body; the channel is body ``body_b``
    at pose (``rot_c``, ``pos_c``). ``query`` is the channel's answer at ``x_c``, with the far
    field (:func:`far_field`) where a pair lies beyond the band; ``desired`` the demonstrated
    triples of the same pairs; ``norm`` = f_ℓ/N_ℓ per pair.
    """

    x_w: np.ndarray  # (k, 3)
    x_c: np.ndarray  # (k, 3)
    origin_a: np.ndarray  # (k, 3)
    body_a: np.ndarray  # (k,)
    body_b: int
    rot_c: np.ndarray  # (3, 3)
    pos_c: np.ndarray  # (3,)
    query: ProximityQuery
    desired: Triples
    norm: np.ndarray  # (k,)


def far_field(q: ProximityQuery, index: np.ndarray, x_c: np.ndarray, desired: Triples,
              is_ground: bool) -> ProximityQuery:
    """The answers of ``index`` (k,) of ``q``, those out of band replaced, for an SDF channel, by
    the demonstrated witness as attractor; ``x_c`` (k, 3) and ``desired`` are the selected pairs'.

    A pair active in the demonstration but farther than the grid reaches has no gradient; the
    distance to ŵ (an upper bound of d, exact as the probe approaches ŵ) pulls it back in. One
    numba pass (|x − ŵ|² summed as numpy's einsum sums three terms, (x + z) + y).
    """
    k = len(index)
    d, w, grad, dw, in_band = np.empty(k), np.empty((k, 3)), np.empty((k, 3)), np.empty((k, 3, 3)), np.empty(k, bool)
    n = np.empty((k if q.n is not None else 0, 3))
    _far_field_into(q.d, np.ascontiguousarray(q.w), np.ascontiguousarray(q.grad_d), np.ascontiguousarray(q.dw_dx),
                    q.in_band, np.zeros((0, 3)) if q.n is None else q.n,
                    np.asarray(index, np.intp), x_c, desired.w, is_ground, d, w, grad, dw, in_band, n)
    return ProximityQuery(d=d, w=w, n=None if q.n is None else n, grad_d=grad, dw_dx=dw, in_band=in_band)


@numba.njit(cache=True)
def _far_field_into(d, w, grad_d, dw_dx, in_band, n, index, x_c, w_hat, ground, out_d, out_w, out_grad, out_dw,
                    out_in_band, out_n):
    for k in range(index.shape[0]):
        i = index[k]
        out_in_band[k] = in_band[i]
        if in_band[i] or ground:
            out_d[k] = d[i]
            for a in range(3):
                out_w[k, a], out_grad[k, a] = w[i, a], grad_d[i, a]
                for b in range(3):
                    out_dw[k, a, b] = dw_dx[i, a, b]
                if out_n.shape[0]:
                    out_n[k, a] = n[i, a]
            continue
        e0, e1, e2 = x_c[k, 0] - w_hat[k, 0], x_c[k, 1] - w_hat[k, 1], x_c[k, 2] - w_hat[k, 2]
        dist = np.sqrt((e0 * e0 + e2 * e2) + e1 * e1)
        scale = max(dist, 1e-12)
        out_d[k] = dist
        for a, e in ((0, e0), (1, e1), (2, e2)):
            out_w[k, a], out_grad[k, a] = w_hat[k, a], e / scale
            for b in range(3):
                out_dw[k, a, b] = 0.0
            if out_n.shape[0]:
                out_n[k, a] = e / scale


def witness_vector(channel: Channel, w: np.ndarray, w_hat: np.ndarray, dw_dx: np.ndarray,
                   hat_weights: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """r^x as the vector γ(w − ŵ) (k, 3), whose norm is the geodesic ρ_c(w; ŵ), and its
    Jacobian (k, 3, 3) w.r.t. the probe in the channel frame.

    Same cost ρ² as the scalar r^x, but a better Gauss–Newton model: the scalar's gradient is a
    unit vector that flips as w crosses ŵ, so its model has no curvature across that direction
    and the SQP steps overshoot back and forth. With γ = ρ/|w − ŵ| the geodesic/chord ratio,
    ∂(γ(w − ŵ))/∂w = γ I + (w − ŵ)(∂γ/∂w)ᵀ (exact: along the chord it is ∂ρ/∂w, across it γ).
    ``hat_weights``: the channel's ``geodesic_weights`` of ŵ, when known.
    """
    gamma, dgamma = channel.geodesic_ratio(w, w_hat, hat_weights)
    k = len(gamma)
    vec, jac = np.empty((k, 3)), np.empty((k, 3, 3))
    _witness_vectors(np.asarray(w, np.float64), np.asarray(w_hat, np.float64), np.asarray(dw_dx, np.float64),
                     gamma, dgamma, vec, jac)
    return vec, jac


@numba.njit(cache=True)
def _witness_vectors(w, w_hat, dw_dx, gamma, dgamma, vec, jac):
    flat_vec, flat_jac = vec.reshape(-1), jac.reshape(-1, 3)  # the row layout _witness_rows writes
    for p in range(w.shape[0]):
        _witness_rows(w, w_hat, dw_dx, p, gamma[p], dgamma, p, flat_vec, flat_jac, 3 * p)


@helper
def _witness_rows(w, w_hat, dw_dx, p, gamma, dgamma, t, out_value, out_grad, m):
    """The three rows of :func:`witness_vector` of pair p (ratio γ, its gradient dgamma[t]) into
    out_value[m:m + 3] and out_grad[m:m + 3]: γ(w − ŵ)ᵢ and γ ∂wᵢ/∂x + (w − ŵ)ᵢ (∂γ/∂w)ᵀ ∂w/∂x,
    in numpy's order (its einsum sums the three terms of (∂γ/∂w)ᵀ ∂w/∂x left to right)."""
    e0 = (dgamma[t, 0] * dw_dx[p, 0, 0] + dgamma[t, 1] * dw_dx[p, 1, 0]) + dgamma[t, 2] * dw_dx[p, 2, 0]
    e1 = (dgamma[t, 0] * dw_dx[p, 0, 1] + dgamma[t, 1] * dw_dx[p, 1, 1]) + dgamma[t, 2] * dw_dx[p, 2, 1]
    e2 = (dgamma[t, 0] * dw_dx[p, 0, 2] + dgamma[t, 1] * dw_dx[p, 1, 2]) + dgamma[t, 2] * dw_dx[p, 2, 2]
    for i in range(3):
        chord = w[p, i] - w_hat[p, i]
        out_value[m + i] = gamma * chord
        out_grad[m + i, 0] = gamma * dw_dx[p, i, 0] + chord * e0
        out_grad[m + i, 1] = gamma * dw_dx[p, i, 1] + chord * e1
        out_grad[m + i, 2] = gamma * dw_dx[p, i, 2] + chord * e2


def interaction_rows(pairs: PairSet, channel: Channel, weights: tuple[float, float, float],
                     cfg: InteractionConfig) -> Rows:
    """The r^d, r^x, r^n rows of the active pairs (eq. m-residuals, m-energy), in that order.

    r^d: every active pair, as the row β·r^d (its square is the term λ^d β² (r^d)²), whose
    derivative (β + β′ r^d) ∇d keeps the kernel's own dependence on d: lagging β as a fixed
    weight leaves the model's slope off by Σ ∂(β²)/∂d (r^d)², which rejects good steps.
    r^x (three rows, :func:`witness_vector`) and r^n (where it is negative): only where the
    demonstration is in contact range (β̄ > 0). One numba pass writes every row.
    """
    k = len(pairs.norm)
    if k == 0:
        return Rows.empty()
    q, desired = pairs.query, pairs.desired
    tangential = np.flatnonzero(beta_bar(desired.d, cfg.sigma_m) > 0.0)
    hat = desired.geodesic
    gamma, dgamma = channel.geodesic_ratio(q.w.take(tangential, axis=0), desired.w.take(tangential, axis=0),
                                           None if hat is None else tuple(h.take(tangential, axis=0) for h in hat))
    n = k + 4 * len(tangential)
    value, weight, grad_c, pair = np.empty(n), np.empty(n), np.empty((n, 3)), np.empty(n, np.intp)
    n = _interaction_rows_into(q.d, q.grad_d, q.w, q.dw_dx, desired.d, desired.w, desired.n, pairs.x_c, pairs.norm,
                               tangential, gamma, dgamma, *(float(v) for v in weights), float(cfg.sigma_m),
                               float(cfg.beta_max), value, weight, grad_c, pair)
    phi = channel_twist_factors(grad_c[:n], pair[:n], pairs.rot_c, pairs.x_w, pairs.origin_a,
                                None if pairs.body_b == FIXED else pairs.pos_c)
    return Rows(value[:n], weight[:n], phi, pairs.body_a.take(pair[:n]), np.full(n, pairs.body_b, dtype=np.intp))


@numba.njit(cache=True)
def _interaction_rows_into(d, grad_d, w, dw_dx, d_hat, w_hat, n_hat, x_c, norm, tangential, gamma, dgamma, lam_d,
                           lam_x, lam_n, sigma, beta_max, out_value, out_weight, out_grad, out_pair):
    """The rows of :func:`interaction_rows` (returns their count): value, weight, gradient in
    the channel frame and the pair of each, with numpy's arithmetic (its einsum sums n̂·(x − ŵ)
    as (x + z) + y)."""
    m = np.int64(0)  # not a literal 0: _witness_rows would compile twice
    for p in range(d.shape[0]):
        b, slope = _beta_and_slope(d_hat[p], d[p], sigma, beta_max)
        r = d[p] - _positive(d_hat[p])
        out_value[m], out_weight[m], out_pair[m] = b * r, norm[p] * lam_d, p
        for j in range(3):
            out_grad[m, j] = (b + slope * r) * grad_d[p, j]
        m += 1
    for t in range(tangential.shape[0]):
        p = tangential[t]
        bb = _beta_bar(d_hat[p], sigma)
        _witness_rows(w, w_hat, dw_dx, p, gamma[t], dgamma, t, out_value, out_grad, m)
        for i in range(3):
            out_weight[m + i], out_pair[m + i] = norm[p] * lam_x * (bb * bb), p
        m += 3
    for t in range(tangential.shape[0]):
        p = tangential[t]
        sign = -1.0 if d_hat[p] < 0.0 else 1.0
        n0, n1, n2 = sign * n_hat[p, 0], sign * n_hat[p, 1], sign * n_hat[p, 2]
        proj = (n0 * (x_c[p, 0] - w_hat[p, 0]) + n2 * (x_c[p, 2] - w_hat[p, 2])) + n1 * (x_c[p, 1] - w_hat[p, 1])
        if proj < 0.0:
            bb = _beta_bar(d_hat[p], sigma)
            out_value[m], out_weight[m], out_pair[m] = proj, norm[p] * lam_n * (bb * bb), p
            out_grad[m, 0], out_grad[m, 1], out_grad[m, 2] = n0, n1, n2
            m += 1
    return m


def channel_twist_factors(grad_c: np.ndarray, point: np.ndarray, rot_c: np.ndarray, x_w: np.ndarray,
                          origin_a: np.ndarray, origin_b: np.ndarray | None) -> np.ndarray:
    """``twist_factors(grad_c @ rot_c.T, x_w[point], origin_a[point], origin_b)``: the factors φ
    of rows whose gradients ``grad_c`` (k, 3) are in the channel frame, at the points ``point``
    (k,) of ``x_w`` (world) with body origins ``origin_a``; one pass without the gathered arrays.
    The rotation repeats numpy's: OpenBLAS sums each entry as one FMA chain, except for a
    single row (another kernel: numpy's own product then)."""
    if len(grad_c) == 1:
        return twist_factors(grad_c @ rot_c.T, x_w[point], origin_a[point], origin_b)
    phi = np.empty((len(grad_c), 12))
    _channel_twist_rows(grad_c, point, kernel_pose(rot_c), x_w, kernel_pose(origin_a),
                        np.zeros(3) if origin_b is None else np.asarray(origin_b, np.float64), origin_b is not None,
                        phi)
    return phi


@numba.njit(cache=True)
def _channel_twist_rows(grad_c, point, rot_c, x_w, origin_a, origin_b, with_b, out):
    for r in range(grad_c.shape[0]):
        p = point[r]
        a0, a1, a2 = _to_world_direction(grad_c[r, 0], grad_c[r, 1], grad_c[r, 2], rot_c)
        if with_b:
            _twist_row(a0, a1, a2, x_w[p, 0], x_w[p, 1], x_w[p, 2], origin_a[p, 0], origin_a[p, 1], origin_a[p, 2],
                       origin_b[0], origin_b[1], origin_b[2], out, r)
        else:
            _twist_half(a0, a1, a2, x_w[p, 0] - origin_a[p, 0], x_w[p, 1] - origin_a[p, 1],
                        x_w[p, 2] - origin_a[p, 2], out, r, np.int64(0))
            for c in range(6, 12):
                out[r, c] = 0.0


def distance_rows(pairs: PairSet) -> Rows:
    """Linearised signed distances d + ∇dᵀδ of the pairs (for non-penetration constraints)."""
    return signed_distance_rows(pairs.query.d.copy(), pairs.query.grad_d, pairs.x_w, pairs.origin_a, pairs.body_a,
                                pairs.body_b, pairs.rot_c, pairs.pos_c)


def signed_distance_rows(d: np.ndarray, grad_c: np.ndarray, x_w: np.ndarray, origin_a: np.ndarray,
                         body_a: np.ndarray, body_b: int, rot_c: np.ndarray, pos_c: np.ndarray) -> Rows:
    """Rows d + ∇dᵀδ of k points (world ``x_w`` on bodies ``body_a`` with origins ``origin_a``)
    against the channel body ``body_b`` at pose (R_c, τ_c); d (k,) m and its gradient
    ``grad_c`` (k, 3) in the channel frame. ``d`` becomes the rows' value (not copied)."""
    phi = channel_twist_factors(grad_c, np.arange(len(d)), rot_c, x_w, origin_a, None if body_b == FIXED else pos_c)
    return Rows(d, np.ones(len(d)), phi, body_a, np.full(len(d), body_b, dtype=np.intp))
