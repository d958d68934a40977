"""ProxQP dense problems kept alive between SQP iterations and frames (``QPWorkspace``)."""

from __future__ import annotations

import numpy as np
from proxsuite import proxqp


class QPWorkspace:
    """ProxQP dense problems kept alive per (n, padded n_in): updated, not re-initialised, when
    the sizes repeat, so their buffers (and, with ``warm_start``, their last primal/dual
    solution) carry over between SQP iterations and frames. Constraint rows are padded with inactive rows to a
    multiple of ``pad`` so that sizes repeat.

    If ProxQP does not converge (linearised constraints in conflict within the trust region),
    the step is re-solved in elastic mode (``_solve_elastic``): each row's violation gets a
    price far above the objective's, so the step removes as much of the violation as the
    boxes allow instead of giving the rows up. The trust-region test then judges the step.
    """

    def __init__(self, eps_abs: float, warm_start: bool = False, pad: int = 16, elastic_batch: int = 32) -> None:
        self.eps_abs = eps_abs
        self.warm_start = warm_start
        self.pad = pad
        self.elastic_batch = elastic_batch
        self._qps: dict[tuple[int, int], proxqp.dense.QP] = {}
        self.solves = 0
        self.failures = 0
        self.elastic_ipm = 0  # failed QPs answered by ``elastic_ipm`` (the rest: the working set)

    def solve(self, H, g, C, lower, box_lo, box_hi) -> np.ndarray:
        x, ok = self._solve(H, g, C, lower, box_lo, box_hi)
        if not ok:
            self.failures += 1
            x = self._solve_elastic(H, g, C, lower, box_lo, box_hi)
        return x

    def _solve_elastic(self, H, g, C, lower, box_lo, box_hi) -> np.ndarray:
        """min ½xᵀHx + gᵀx + ρ Σ s + ½ρ‖s‖² s.t. C x + s ≥ lower, s ≥ 0, box_lo ≤ x ≤ box_hi.

        Always feasible (the boxes contain 0). ρ = 100 × (1 + max diag H) per m of slack: a
        millimetre of remaining violation costs a tenth of the stiffest term's curvature, more
        than any step inside the trust region can gain (measured on the woodchair carry, where
        dropping the rows instead let the hands 4.8 mm into the seat). Before this, a failed
        QP was re-solved without its constraint rows.

        Solved by ``elastic_ipm``, an interior-point method whose Newton systems are n × n (the
        slacks eliminated), whatever the number of rows. Before it, ProxQP solved the slack QP
        densely (n + m variables) over a growing working set of rows (``_solve_elastic_working``,
        still the fallback should the interior-point method not converge): on Bandai's
        ``walk_musical_002`` a frame with 843 self-collision rows, 586 of them still violated at
        the answer, grew the set 32 rows a pass to 687 (a 722-variable dense QP, seconds a solve)
        and took 127 s; the interior-point method answers the same QP in ~15 ms, at a merit as
        low or lower (the working set's answers stopped ~1e-4 short of the optimum in x, their
        merits 1e-9–1e-6 relative above it)."""
        rho = 100.0 * (1.0 + float(np.abs(np.diag(H)).max()))
        x = elastic_ipm(H, g, C, lower, box_lo, box_hi, rho)
        if x is not None:
            self.elastic_ipm += 1
            return x
        return self._solve_elastic_working(H, g, C, lower, box_lo, box_hi)

    def _solve_elastic_working(self, H, g, C, lower, box_lo, box_hi) -> np.ndarray:
        """``_solve_elastic``'s QP by ProxQP over a working set of rows (constraint generation):
        the QP takes only the rows of
        the set, each with its slack; a row left out costs nothing and bends nothing while it
        holds, so once no row outside the set is violated (by more than ``eps_abs``) the answer
        is the whole problem's. Otherwise the ``elastic_batch`` most violated rows join the set
        and it is solved again. Why: the dense slack QP has n + m variables. Restoring a box six
        times too wide took every penetrating row, m = 1962, and 85 s; with the working set, 12
        QPs of at most 322 rows gave the same step (to 7 µm) in 3.5 s. At the optimum most rows
        hold (1804 of those 1962)."""
        working = np.zeros(C.shape[0], dtype=bool)
        while True:  # the first pass, with no row, minimises the objective inside the boxes alone
            x = self._solve_with_slacks(H, g, C[working], lower[working], box_lo, box_hi)
            violation = lower - C @ x
            outside = np.flatnonzero(~working & (violation > self.eps_abs))
            if outside.size == 0:
                return x
            worst = np.argsort(-violation[outside], kind="stable")[:self.elastic_batch]
            working[outside[worst]] = True

    def _solve_with_slacks(self, H, g, C, lower, box_lo, box_hi) -> np.ndarray:
        """The slack QP of ``_solve_elastic`` over the rows given (none: the boxes alone); its x."""
        n, m = H.shape[0], C.shape[0]
        rho = 100.0 * (1.0 + float(np.abs(np.diag(H)).max()))
        H_e = np.zeros((n + m, n + m))
        H_e[:n, :n] = H
        H_e[n:, n:] = rho * np.eye(m)
        g_e = np.concatenate([g, np.full(m, rho)])
        C_e = np.hstack([C, np.eye(m)])
        x, _ = self._solve(H_e, g_e, C_e, lower, np.concatenate([box_lo, np.zeros(m)]),
                           np.concatenate([box_hi, np.full(m, 1e20)]))
        return x[:n]

    def _solve(self, H, g, C, lower, box_lo, box_hi) -> tuple[np.ndarray, bool]:
        self.solves += 1
        n, m = H.shape[0], C.shape[0]
        m_pad = max(self.pad, -(-m // self.pad) * self.pad)
        upper = np.full(m_pad, 1e20)
        if m_pad != m:
            C = np.vstack([C, np.zeros((m_pad - m, n))])
            lower = np.concatenate([lower, np.full(m_pad - m, -1e20)])
        key = (n, m_pad)
        qp = self._qps.get(key)
        if qp is None:
            # measured on the box carry: the primal-dual factorisation is 1.5× faster at these sizes
            qp = proxqp.dense.QP(n, 0, m_pad, True, proxqp.dense.HessianType.Dense,
                                 proxqp.dense.DenseBackend.PrimalDualLDLT)
            qp.settings.eps_abs = self.eps_abs
            qp.settings.eps_rel = 0.0
            # Measured on 1076 QPs of the OMOMO box carry: at most 21 outer iterations when solved,
            # and the same solutions (to 2e-15) with these caps as with 1000 × 1500. A QP whose
            # linearised constraints conflict is not detected as infeasible: with the defaults it
            # took up to 40 s to give up (with 30 × 100, ≤ 0.5 s even at 1300 rows); ``solve`` then
            # re-solves it in elastic mode, as for any failure.
            qp.settings.max_iter = 30
            qp.settings.max_iter_in = 100
            qp.settings.initial_guess = (proxqp.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT if self.warm_start
                                         else proxqp.InitialGuess.NO_INITIAL_GUESS)
            qp.init(H, g, None, None, C, lower, upper, box_lo, box_hi)
            self._qps[key] = qp
        else:
            qp.update(H, g, None, None, C, lower, upper, box_lo, box_hi, update_preconditioner=True)
        qp.solve()
        ok = qp.results.info.status == proxqp.QPSolverOutput.PROXQP_SOLVED
        return qp.results.x.copy(), ok



def elastic_ipm(H, g, C, lower, box_lo, box_hi, rho: float, tol: float = 1e-10,
                max_iter: int = 60) -> np.ndarray | None:
    """x of min ½xᵀHx + gᵀx + ρ Σ s + ½ρ‖s‖² s.t. C x + s ≥ lower, s ≥ 0, box_lo ≤ x ≤ box_hi
    (bounds beyond ±1e19 absent), or None if not converged in ``max_iter`` iterations.

    Mehrotra's predictor–corrector on z = (x, s) with a slack t ≥ 0 and a multiplier y ≥ 0 per
    inequality (rows, s ≥ 0, the two box sides). Each Newton system (Q + AᵀDA) dz = r, D = y/t,
    is reduced to x: s's block is diagonal (ρ + D₁ + D₂), so one n × n Cholesky factor of
    H + Cᵀ diag(D₁(ρ + D₂)/(ρ + D₁ + D₂)) C + D_box serves both steps, O(m n²) a iteration
    whatever m. Converged when the dual residual is ≤ tol × max(1, |g|∞, ρ, |Aᵀy|∞), the primal one
    ≤ tol × max(1, |bounds|∞) and the mean complementarity ≤ 1e-13 × their product; where
    rounding holds the residuals above tol once the complementarity is there, the iterate with
    the smallest residuals, if within 100 × tol (5 iterations without a better one end it). On the
    dumped failures of ``walk_musical_002`` 15–40 iterations, the merit at or below the working
    set's answer. ``tol`` 1e-10: at 1e-11 the residuals of a 300-row test QP stalled between 1e-9
    and 1e-8 on an AMD EPYC VM with NumPy 2.4 (rounding), so every such QP fell back to the
    working set (2026-12-08)."""
    n = H.shape[0]
    lo_i, hi_i = np.flatnonzero(box_lo > -1e19), np.flatnonzero(box_hi < 1e19)
    blo, bhi = box_lo[lo_i], box_hi[hi_i]

    def residual_rows(x, s):  # the four blocks of A z − b
        return [C @ x + s - lower, s, x[lo_i] - blo, bhi - x[hi_i]]

    def a_transpose(v):
        ax = C.T @ v[0]
        ax[lo_i] += v[2]
        ax[hi_i] -= v[3]
        return ax, v[0] + v[1]

    x = np.clip(np.zeros(n), box_lo, box_hi)
    s = np.maximum(lower - C @ x, 0.0) + 1.0
    t = [np.maximum(a, 1.0) for a in residual_rows(x, s)]
    y = [np.ones_like(a) for a in t]
    count = sum(a.size for a in t)
    c_norm = max(1.0, float(np.abs(g).max(initial=0.0)), rho)
    b_norm = max(1.0, float(np.abs(lower).max(initial=0.0)), float(np.abs(blo).max(initial=0.0)),
                 float(np.abs(bhi).max(initial=0.0)))
    best, since = (np.inf, None), 0
    for _ in range(max_iter):
        rp = [a - ti for a, ti in zip(residual_rows(x, s), t)]
        aty_x, aty_s = a_transpose(y)
        rd_x, rd_s = H @ x + g - aty_x, rho + rho * s - aty_s
        mu = sum(float(ti @ yi) for ti, yi in zip(t, y)) / count
        dual_scale = max(c_norm, float(np.abs(aty_x).max()), float(np.abs(aty_s).max(initial=0.0)))
        error = max(max(float(np.abs(rd_x).max()), float(np.abs(rd_s).max(initial=0.0))) / dual_scale,
                    max(float(np.abs(r).max(initial=0.0)) for r in rp) / b_norm)
        if mu <= 1e-13 * c_norm * b_norm:
            if error <= tol:
                return x
            if error < best[0]:  # rounding may hold the residuals above tol: keep the best iterate
                best, since = (error, x), 0
            else:
                since += 1
                if since >= 5:
                    break
        d = [yi / ti for yi, ti in zip(y, t)]
        s_diag = rho + d[0] + d[1]
        m_x = H + (C.T * (d[0] * (rho + d[1]) / s_diag)) @ C
        m_x[lo_i, lo_i] += d[2]
        m_x[hi_i, hi_i] += d[3]
        try:
            factor = np.linalg.cholesky(m_x)
        except np.linalg.LinAlgError:
            factor = np.linalg.cholesky(m_x + 1e-12 * max(1.0, float(np.abs(np.diag(m_x)).max())) * np.eye(n))
        system = (t, d, rp, rd_x, rd_s, factor, s_diag)

        def newton(target, system=system):  # target: the complementarity each block aims at, per element
            t, d, rp, rd_x, rd_s, factor, s_diag = system
            v = [ci / ti - di * ri for ci, ti, di, ri in zip(target, t, d, rp)]
            r_x, r_s = a_transpose(v)
            r_x, r_s = r_x - rd_x, r_s - rd_s
            dx = np.linalg.solve(factor.T, np.linalg.solve(factor, r_x - C.T @ (d[0] * r_s / s_diag)))
            ds = (r_s - d[0] * (C @ dx)) / s_diag
            a_dz = [C @ dx + ds, ds, dx[lo_i], -dx[hi_i]]
            return dx, ds, [a + ri for a, ri in zip(a_dz, rp)], [vi - di * a for vi, di, a in zip(v, d, a_dz)]

        _, _, dt, dy = newton([-ti * yi for ti, yi in zip(t, y)])  # affine predictor
        ap, ad = _longest_step(t, dt), _longest_step(y, dy)
        mu_aff = sum(float((ti + ap * a) @ (yi + ad * b)) for ti, a, yi, b in zip(t, dt, y, dy)) / count
        sigma = (mu_aff / mu) ** 3
        dx, ds, dt, dy = newton([sigma * mu - ti * yi - a * b for ti, yi, a, b in zip(t, y, dt, dy)])
        alpha = min(1.0, 0.995 * min(_longest_step(t, dt), _longest_step(y, dy)))
        x, s = x + alpha * dx, s + alpha * ds
        t = [ti + alpha * a for ti, a in zip(t, dt)]
        y = [yi + alpha * b for yi, b in zip(y, dy)]
    return best[1] if best[0] <= 100.0 * tol else None


def _longest_step(values: list[np.ndarray], steps: list[np.ndarray]) -> float:
    """The largest α ≤ 1 with every values + α·steps ≥ 0."""
    alpha = 1.0
    for vi, di in zip(values, steps):
        neg = di < 0
        if neg.any():
            alpha = min(alpha, float(np.min(-vi[neg] / di[neg])))
    return alpha
