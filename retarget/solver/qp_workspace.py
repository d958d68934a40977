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

        Solved over a working set of rows (constraint generation): the QP takes only the rows of
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

