"""Interaction residuals (paper eq. m-residuals, m-energy) and their analytic Jacobian factors.

A probe x (world, on body A: a robot link or an object) faces a channel c (body B: an object,
static furniture or the ground) with pose (R_c, τ_c). Its proximity triple (d, w, n) lives in
the channel frame, x_c = R_cᵀ(x − τ_c). For each active pair the cost has up to three rows

    r^d = d − (d̂)₊,   r^x = ρ_c(w; ŵ) (as a 3-vector, see witness_vector),   r^n = (sign(d̂) n̂·(x_c − ŵ))₋

weighted f_ℓ/N_ℓ · λ · β² (r^d) or f_ℓ/N_ℓ · λ · β̄² (r^x, r^n). β̄ depends on the demonstration
only; β also on the current d, so the r^d row is the product β·r^d and is differentiated as such.

Jacobian factors. Every scalar row is linearised as r + φ_Aᵀ ν_A + φ_Bᵀ ν_B where ν_X is the
world-aligned twist of body X at its origin o_X (robot: LOCAL_WORLD_ALIGNED link Jacobian ×
δv; object: (δτ, δθ) of the retraction τ ← τ + δτ, R ← exp(δθ)R). With a = R_c ∂r/∂x_c the
world gradient of the row,

    φ_A = (a, (x − o_A) × a),     φ_B = −(a, (x − τ_c) × a)

because ẋ = v_A + ω_A × (x − o_A) and ẋ_c = R_cᵀ(ẋ − v_B − ω_B × (x − τ_c)). The solver turns
φ into QP rows with one 6×nv Jacobian per body (``retarget.kinematics``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from retarget.geometry import Channel, ProximityQuery

#: Body index of things that never move (ground, static furniture): no decision variable.
FIXED = -1


@dataclass(frozen=True)
class InteractionConfig:
    """Weights and kernels of E_int (paper eq. m-energy; METHOD.md "Interaction residuals")."""

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

    @property
    def object_weights(self) -> tuple[float, float, float]:
        return tuple(self.object_weight_factor * w for w in self.robot_weights)


def beta_bar(d_hat: np.ndarray, sigma: float) -> np.ndarray:
    """β̄ = (1 − (d̂)₊/σ)₊²: gates r^x, r^n to pairs in contact in the demonstration."""
    return np.clip(1.0 - np.maximum(d_hat, 0.0) / sigma, 0.0, None) ** 2


def beta(d_hat: np.ndarray, d: np.ndarray, sigma: float, beta_max: float) -> np.ndarray:
    """β = min((1 − min((d̂)₊, d)/σ)₊², β_max): gates r^d to pairs close in the demonstration or now."""
    return np.minimum(np.clip(1.0 - np.minimum(np.maximum(d_hat, 0.0), d) / sigma, 0.0, None) ** 2, beta_max)


def beta_and_slope(d_hat: np.ndarray, d: np.ndarray, sigma: float, beta_max: float) -> tuple[np.ndarray, np.ndarray]:
    """β (see :func:`beta`) and ∂β/∂d: −2(1 − d/σ)/σ where the current distance is the smaller
    one and the kernel is neither clipped at 0 nor capped at β_max, else 0."""
    b = beta(d_hat, d, sigma, beta_max)
    live = (d < np.maximum(d_hat, 0.0)) & (d < sigma) & (b < beta_max)
    return b, np.where(live, -2.0 * (1.0 - d / sigma) / sigma, 0.0)


@dataclass(frozen=True)
class Triples:
    """Proximity triples of N probes w.r.t. one channel (channel frame): d (N,) m, w (N, 3), n (N, 3)."""

    d: np.ndarray
    w: np.ndarray
    n: np.ndarray

    def take(self, index: np.ndarray) -> Triples:
        return Triples(self.d[index], self.w[index], self.n[index])


def to_channel_frame(x_w: np.ndarray, rot_c: np.ndarray, pos_c: np.ndarray) -> np.ndarray:
    """x_c = R_cᵀ (x − τ_c) for points (N, 3); row-vector form (x − τ) R."""
    return (x_w - pos_c) @ rot_c


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


def cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """u × v for (k, 3) arrays: np.cross without its axis handling, twice as fast on the hot path."""
    out = np.empty(np.broadcast_shapes(u.shape, v.shape))
    out[..., 0] = u[..., 1] * v[..., 2] - u[..., 2] * v[..., 1]
    out[..., 1] = u[..., 2] * v[..., 0] - u[..., 0] * v[..., 2]
    out[..., 2] = u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
    return out


def twist_factors(a_w: np.ndarray, x_w: np.ndarray, origin_a: np.ndarray, origin_b: np.ndarray) -> np.ndarray:
    """(k, 12) factors φ = (a, (x − o_A) × a, −a, −(x − o_B) × a) for world gradients a (k, 3)."""
    out = np.empty((len(a_w), 12))
    out[:, 0:3] = a_w
    out[:, 3:6] = cross(x_w - origin_a, a_w)
    out[:, 6:9] = -a_w
    out[:, 9:12] = -cross(x_w - origin_b, a_w)
    return out


@dataclass(frozen=True)
class PairSet:
    """Active probe–channel pairs of one probe family against one channel, at one iterate.

    Arrays are restricted to the active pairs. ``x_w`` world probe positions, ``origin_a`` the
    origin of the body carrying each probe, ``body_a`` that body; the channel is body ``body_b``
    at pose (``rot_c``, ``pos_c``). ``query`` is the channel's answer at ``x_c``; ``desired`` the
    demonstrated triples of the same pairs; ``norm`` = f_ℓ/N_ℓ per pair.
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


def far_field(q: ProximityQuery, x_c: np.ndarray, desired: Triples, is_ground: bool) -> ProximityQuery:
    """Replace out-of-band answers of an SDF channel by the demonstrated witness as attractor.

    A pair active in the demonstration but farther than the grid reaches has no gradient; the
    distance to ŵ (an upper bound of d, exact as the probe approaches ŵ) pulls it back in.
    """
    out = ~q.in_band
    if is_ground or not out.any():
        return q
    diff = x_c[out] - desired.w[out]
    dist = np.linalg.norm(diff, axis=1)
    unit = diff / np.maximum(dist, 1e-12)[:, None]
    d, w, n, grad = q.d.copy(), q.w.copy(), q.n.copy(), q.grad_d.copy()
    d[out], w[out], n[out], grad[out] = dist, desired.w[out], unit, unit
    dw = q.dw_dx.copy()
    dw[out] = 0.0
    return ProximityQuery(d=d, w=w, n=n, grad_d=grad, dw_dx=dw, in_band=q.in_band)


def witness_vector(channel: Channel, w: np.ndarray, w_hat: np.ndarray,
                   dw_dx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """r^x as the vector γ(w − ŵ) (k, 3), whose norm is the geodesic ρ_c(w; ŵ), and its
    Jacobian (k, 3, 3) w.r.t. the probe in the channel frame.

    Same cost ρ² as the scalar r^x, but a better Gauss–Newton model: the scalar's gradient is a
    unit vector that flips as w crosses ŵ, so its model has no curvature across that direction
    and the SQP steps overshoot back and forth. With γ = ρ/|w − ŵ| and u the unit chord,
    ∂(γ(w − ŵ))/∂w = γ(I − uuᵀ) + u (∂ρ/∂w)ᵀ (exact: along u it is ∂ρ/∂w, across it γ).
    """
    rho, drho = channel.geodesic(w, w_hat)
    chord = w - w_hat
    e = np.linalg.norm(chord, axis=1)
    apart = e > 1e-9
    gamma = np.where(apart, rho / np.where(apart, e, 1.0), 1.0)
    u = chord / np.where(apart, e, 1.0)[:, None]
    jw = gamma[:, None, None] * (np.eye(3) - u[:, :, None] * u[:, None, :]) + u[:, :, None] * drho[:, None, :]
    jw = np.where(apart[:, None, None], jw, np.eye(3))
    return gamma[:, None] * chord, jw @ dw_dx


def interaction_rows(pairs: PairSet, channel: Channel, weights: tuple[float, float, float],
                     cfg: InteractionConfig) -> Rows:
    """The r^d, r^x, r^n rows of the active pairs (eq. m-residuals, m-energy)."""
    k = len(pairs.norm)
    if k == 0:
        return Rows.empty()
    lam_d, lam_x, lam_n = weights
    q = far_field(pairs.query, pairs.x_c, pairs.desired, channel.is_ground)
    d_hat = pairs.desired.d
    d_hat_pos = np.maximum(d_hat, 0.0)
    b, db = beta_and_slope(d_hat, q.d, cfg.sigma_m, cfg.beta_max)
    bb = beta_bar(d_hat, cfg.sigma_m)
    rot = pairs.rot_c

    # r^d: every active pair, as the row β·r^d (its square is the term λ^d β² (r^d)²), whose
    # derivative (β + β′ r^d) ∇d keeps the kernel's own dependence on d: lagging β as a fixed
    # weight leaves the model's slope off by Σ ∂(β²)/∂d (r^d)², which rejects good steps.
    r_d = q.d - d_hat_pos
    value = [b * r_d]
    weight = [pairs.norm * lam_d]
    grad_c = [(b + db * r_d)[:, None] * q.grad_d]
    index = [np.arange(k)]

    # r^x, r^n: only where the demonstration is in contact range (β̄ > 0)
    tangential = np.flatnonzero(bb > 0.0)
    if len(tangential):
        vec, jac_x = witness_vector(channel, q.w[tangential], pairs.desired.w[tangential], q.dw_dx[tangential])
        w_x = pairs.norm[tangential] * lam_x * bb[tangential] ** 2
        value.append(vec.ravel())
        weight.append(np.repeat(w_x, 3))
        grad_c.append(jac_x.reshape(-1, 3))
        index.append(np.repeat(tangential, 3))

        sign = np.where(d_hat[tangential] < 0.0, -1.0, 1.0)
        n_hat = sign[:, None] * pairs.desired.n[tangential]
        proj = np.einsum("kj,kj->k", n_hat, pairs.x_c[tangential] - pairs.desired.w[tangential])
        below = proj < 0.0
        value.append(proj[below])
        weight.append(pairs.norm[tangential[below]] * lam_n * bb[tangential[below]] ** 2)
        grad_c.append(n_hat[below])
        index.append(tangential[below])

    idx = np.concatenate(index)
    a_w = np.concatenate(grad_c) @ rot.T  # R_c ∂r/∂x_c, row-vector form
    phi = twist_factors(a_w, pairs.x_w[idx], pairs.origin_a[idx], pairs.pos_c)
    return Rows(np.concatenate(value), np.concatenate(weight), phi, pairs.body_a[idx],
                np.full(len(idx), pairs.body_b, dtype=np.intp))


def distance_rows(pairs: PairSet) -> Rows:
    """Linearised signed distances d + ∇dᵀδ of the pairs (for non-penetration constraints)."""
    a_w = pairs.query.grad_d @ pairs.rot_c.T
    phi = twist_factors(a_w, pairs.x_w, pairs.origin_a, pairs.pos_c)
    return Rows(pairs.query.d.copy(), np.ones(len(a_w)), phi, pairs.body_a,
                np.full(len(a_w), pairs.body_b, dtype=np.intp))
