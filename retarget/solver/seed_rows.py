"""Which constraint rows seed a QP: among the surface rows closer than a margin, per group (body,
channel, binned distance gradient), the extreme points under small tilts of the gradient
(``initial_constraints``). The QP adds any other row it violates (``retarget.solver.qp``), so the
seed only has to be a good guess, and a small one."""

from __future__ import annotations

import numba
import numpy as np

from retarget.geometry.jit import helper
from retarget.solver.residuals import Rows

#: Rows are grouped by the nearest of these 6 directions to their distance gradient; each group
#: keeps its extreme points under tilts in 8 directions perpendicular to the group's gradient.
_BINS = np.concatenate([np.eye(3), -np.eye(3)])


_ANGLES = np.arange(8) * (np.pi / 4)


def initial_constraints(rows: Rows, channel: np.ndarray, margin: float, tilt_rad: float = 0.2) -> np.ndarray:
    """Rows to put in the first QP: among those closer than ``margin``, per group (body,
    channel, binned gradient a), the rows that are smallest after a small rotation ω of the
    body perpendicular to a (|ω| = ``tilt_rad``, 8 directions, and ω = 0).

    A row reads d_p + a·v + ω·((x_p − o) × a). Over a group a is nearly constant, so the row
    that binds first for a step (v, ω) is the minimiser of d_p + ω·φ_p[3:6]: an extreme point
    of the group (for a plane, a vertex of the convex hull); ω along a does not change it. The
    others are implied to first order; ``qp_step`` checks every candidate row after each QP and
    adds any violated one, so this choice affects speed, never feasibility.
    """
    close = np.flatnonzero(rows.value < margin)
    if len(close) == 0:
        return close
    chosen = np.zeros(len(rows), dtype=bool)
    _choose_extreme_rows(rows.value, rows.phi, rows.body_a, np.asarray(channel, np.intp), close, float(tilt_rad), _COS,
                         _SIN, chosen)
    return np.flatnonzero(chosen)


_COS, _SIN = np.cos(_ANGLES), np.sin(_ANGLES)


@numba.njit(cache=True)
def _choose_extreme_rows(value, phi, body, channel, close, tilt, cos, sin, chosen):
    """chosen[r] ← row r of ``close`` is an extreme row of its group (``initial_constraints``):
    the rows grouped by key in a stable sort, then ``_extreme_rows`` per group."""
    key = _group_keys(phi, body, channel, close)
    order = _stable_order(key)
    starts = np.empty(order.shape[0] + 1, np.intp)
    starts[0], count = 0, 1
    for i in range(1, order.shape[0]):
        if key[order[i]] != key[order[i - 1]]:
            starts[count] = i
            count += 1
    starts[count] = order.shape[0]
    grouped = close[order]
    extreme = np.empty(grouped.shape[0], np.bool_)
    _extreme_rows(value, phi, grouped, starts[:count + 1], tilt, cos, sin, extreme)
    for i in range(grouped.shape[0]):
        chosen[grouped[i]] = extreme[i]


@helper
def _stable_order(key):
    """The permutation of numpy's stable argsort of small non-negative integer keys, by counting."""
    lo, hi = key[0], key[0]
    for k in key:  # a loop: np.min / np.max would each compile numba's reduction machinery
        lo, hi = min(lo, k), max(hi, k)
    start = np.zeros(hi - lo + 2, np.intp)
    for k in key:
        start[k - lo + 1] += 1
    for i in range(1, start.shape[0]):
        start[i] += start[i - 1]
    order = np.empty(key.shape[0], np.intp)
    for i in range(key.shape[0]):
        order[start[key[i] - lo]] = i
        start[key[i] - lo] += 1
    return order


@helper
def _group_keys(phi, body, channel, close):
    """(body · 64 + channel) · 32 + bin of each close row, the bin the argmax of a·(±e_x, ±e_y,
    ±e_z) (first on ties, as ``np.argmax(a @ _BINS.T)``, whose entries are exactly ±a_j)."""
    out = np.empty(close.shape[0], np.intp)
    for m in range(close.shape[0]):
        r = close[m]
        best, top = 0, phi[r, 0]
        if phi[r, 1] > top:
            best, top = 1, phi[r, 1]
        if phi[r, 2] > top:
            best, top = 2, phi[r, 2]
        if -phi[r, 0] > top:
            best, top = 3, -phi[r, 0]
        if -phi[r, 1] > top:
            best, top = 4, -phi[r, 1]
        if -phi[r, 2] > top:
            best = 5
        out[m] = (body[r] * 64 + channel[r]) * 32 + best
    return out


@helper
def _pairwise_sum(x, rows, col, lo, n):
    """Σ x[rows[lo:lo + n], col] in numpy's order (``pairwise_sum`` of its add loops: 8
    accumulators up to 128 terms, halves beyond), so that sums match np.add.reduce bit for bit."""
    if n < 8:
        res = -0.0
        for i in range(lo, lo + n):
            res += x[rows[i], col]
        return res
    if n <= 128:
        r = np.empty(8)
        for j in range(8):
            r[j] = x[rows[lo + j], col]
        i = 8
        while i < n - n % 8:
            for j in range(8):
                r[j] += x[rows[lo + i + j], col]
            i += 8
        res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
        while i < n:
            res += x[rows[lo + i], col]
            i += 1
        return res
    half = n // 2
    half -= half % 8
    return _pairwise_sum(x, rows, col, lo, half) + _pairwise_sum(x, rows, col, lo + half, n - half)


@helper
def _extreme_rows(value, phi, rows, bounds, tilt, cos, sin, out):
    """For each group g (rows[bounds[g]:bounds[g + 1]]): its mean gradient direction ā, two
    unit tangents, the 8 tilts ω (|ω| = ``tilt``) and the rows whose d + ω·φ[3:6], or d, is
    the group's smallest; ``out`` marks them. The arithmetic of the array form, sums in its
    order (reduceat's pairwise sums, the einsum's (x + z) + y)."""
    tilt_w, best = np.empty((8, 3)), np.empty(9)  # a group's tilts ω / tilt, its smallest scores
    for g in range(bounds.shape[0] - 1):
        lo, hi = bounds[g], bounds[g + 1]
        # np.add.reduceat: the first row, plus numpy's pairwise sum of the others
        # (column indices as int64, not literals: one compilation of the recursive sum, not three)
        c0, c1, c2, rest = np.int64(0), np.int64(1), np.int64(2), hi - lo - 1
        m0 = phi[rows[lo], 0] + _pairwise_sum(phi, rows, c0, lo + 1, rest) if rest > 0 else phi[rows[lo], 0]
        m1 = phi[rows[lo], 1] + _pairwise_sum(phi, rows, c1, lo + 1, rest) if rest > 0 else phi[rows[lo], 1]
        m2 = phi[rows[lo], 2] + _pairwise_sum(phi, rows, c2, lo + 1, rest) if rest > 0 else phi[rows[lo], 2]
        n = max(np.sqrt(m0 * m0 + m1 * m1 + m2 * m2), 1e-12)
        m0, m1, m2 = m0 / n, m1 / n, m2 / n
        # e = the axis of the smallest |ā_j| (first on ties); t1 = ā × e
        b0, b1, b2 = abs(m0), abs(m1), abs(m2)
        e = 0
        if b1 < b0:
            e = 1
        if b2 < (b1 if e == 1 else b0):
            e = 2
        e0, e1, e2 = 1.0 if e == 0 else 0.0, 1.0 if e == 1 else 0.0, 1.0 if e == 2 else 0.0
        t10, t11, t12 = m1 * e2 - m2 * e1, m2 * e0 - m0 * e2, m0 * e1 - m1 * e0
        n = max(np.sqrt(t10 * t10 + t11 * t11 + t12 * t12), 1e-12)
        t10, t11, t12 = t10 / n, t11 / n, t12 / n
        t20, t21, t22 = m1 * t12 - m2 * t11, m2 * t10 - m0 * t12, m0 * t11 - m1 * t10
        for d in range(8):
            tilt_w[d, 0] = cos[d] * t10 + sin[d] * t20
            tilt_w[d, 1] = cos[d] * t11 + sin[d] * t21
            tilt_w[d, 2] = cos[d] * t12 + sin[d] * t22
        best[:] = np.inf
        for i in range(lo, hi):
            r = rows[i]
            best[0] = min(best[0], value[r])
            for d in range(8):
                score = value[r] + tilt * ((phi[r, 3] * tilt_w[d, 0] + phi[r, 5] * tilt_w[d, 2])
                                           + phi[r, 4] * tilt_w[d, 1])
                best[d + 1] = min(best[d + 1], score)
        for i in range(lo, hi):
            r = rows[i]
            hit = value[r] <= best[0]
            for d in range(8):
                if hit:
                    break
                hit = value[r] + tilt * ((phi[r, 3] * tilt_w[d, 0] + phi[r, 5] * tilt_w[d, 2])
                                         + phi[r, 4] * tilt_w[d, 1]) <= best[d + 1]
            out[i] = hit
