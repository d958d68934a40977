"""otr_gym.flags.true_intervals: runs of True in a per-frame mask."""

from __future__ import annotations

import numpy as np

from otr_gym.flags import true_intervals


def test_runs_of_true_are_half_open_and_merge_across_short_gaps():
    mask = [False, True, True, False, True, False, False, True]
    assert true_intervals(mask) == [(1, 3), (4, 5), (7, 8)]
    assert true_intervals(mask, gap=1) == [(1, 5), (7, 8)]  # one False between: merged
    assert true_intervals(mask, gap=2) == [(1, 8)]
    assert true_intervals([]) == [] and true_intervals(np.zeros(5, bool)) == []
    assert true_intervals(np.ones(4, bool)) == [(0, 4)]


def test_the_runs_cover_exactly_the_true_frames():
    rng = np.random.default_rng(0)
    for _ in range(200):
        mask = rng.random(int(rng.integers(1, 50))) < 0.4
        covered = np.zeros(mask.size, bool)
        for a, b in true_intervals(mask):
            assert a < b and mask[a:b].all() and (a == 0 or not mask[a - 1]) and (b == mask.size or not mask[b])
            covered[a:b] = True
        assert np.array_equal(covered, mask)
