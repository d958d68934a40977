"""The contact-state rows a step would cross are priced in the QP (``retarget.solver.qp.qp_step``).

A contact-state row costs only while its unit is out of its demonstrated state (a foot the
person keeps off the floor, come within its clearance). Left out of the Gauss–Newton model while
in its state, the step that carries it across pays a cost the model never predicted, and the
trust-region test refused it: on Bandai's walk 177 of 222 refused steps, and 38 of 241 frames
took no step at all (docs/results/feasibility.md, *Refused steps*)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

import retarget.solver.sqp as sqp
from retarget.clip import problem_from_config
from retarget.config import RetargetConfig
from retarget.solver.problem import resample_demonstration

from clips import clip


def _refused(problem) -> tuple[int, int]:
    sol = sqp.solve_sequence(problem)
    rejected = np.array([s.rejected for s in sol.stats[1:]])
    return int(rejected.sum()), sol.qp_failures


def test_pricing_the_crossed_rows_leaves_fewer_steps_refused(monkeypatch):
    cfg = RetargetConfig()
    cfg = replace(cfg, solver=replace(cfg.solver, price_contact_state=True))  # as configs/retarget/executable.yaml
    problem = problem_from_config(resample_demonstration(clip("walk", 0, 90), 50.0), cfg)
    priced, failures = _refused(problem)
    step = sqp.qp_step
    monkeypatch.setattr(sqp, "qp_step", lambda *a, **k: step(*a, **{**k, "price_hinges": False}))
    unpriced, _ = _refused(problem)
    assert priced < unpriced  # measured 41 against 51 refused steps over 149 frames
    assert failures == 0


def test_a_row_in_its_state_is_a_hinge_candidate_not_a_cost():
    """The linearisation splits the selected contact-state rows: out of state → cost rows,
    in state → ``hinge`` with the side each keeps (+1 clear of the surface, −1 touching it)."""
    from retarget.solver.iterate import new_state
    from retarget.solver.rows import linearise
    from retarget.solver.targets import frame_targets

    cfg = RetargetConfig()
    priced = replace(cfg, solver=replace(cfg.solver, price_contact_state=True))
    demo = resample_demonstration(clip("walk", 0, 10), 50.0)
    problem = problem_from_config(demo, priced)
    state = new_state(problem)
    lin = linearise(problem, state, frame_targets(problem, 0), {})
    assert lin.hinge is not None and len(lin.hinge) == len(lin.hinge_side) > 0
    assert set(np.unique(lin.hinge_side)) <= {-1.0, 1.0}
    # in its state: a clear unit's row is ≥ 0, a touching unit's ≤ 0
    assert np.all(lin.hinge_side * lin.hinge.value >= 0.0)
    # unpriced (the default), the candidates are not built
    plain = problem_from_config(demo, cfg)
    assert len(linearise(plain, new_state(plain), frame_targets(plain, 0), {}).hinge) == 0
