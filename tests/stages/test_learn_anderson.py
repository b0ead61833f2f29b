"""Tests of the alternation's Anderson acceleration (stages/learn/anderson.py) and of when the loop restarts it."""

from __future__ import annotations

import numpy as np
from fluorocal.stages.learn.anderson import Anderson, anderson_step
from fluorocal.stages.learn.result import IterationRecord
from fluorocal.stages.learn.stopping import cost_raised


def _slow_linear_map(n=6, seed=3):
    """``x -> M x + b`` with M symmetric, eigenvalues 0.5 ... 0.97 (a plain iteration's error shrinks 3 % a step)."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    M = Q @ np.diag(np.linspace(0.5, 0.97, n)) @ Q.T
    b = rng.normal(size=n)
    return (lambda x: M @ x + b), np.linalg.solve(np.eye(n) - M, b)


def test_anderson_reaches_a_slow_linear_maps_fixed_point_where_plain_steps_creep():
    g, fixed = _slow_linear_map()
    x, acc, plain = np.zeros(6), Anderson(depth=10), np.zeros(6)
    for _ in range(8):
        x, acc = anderson_step(acc, x, g(x))
        plain = g(plain)
    # on a linear map Anderson with a full history is GMRES: exact after n + 1 = 7 steps up to rounding
    # (1e-8 allows the condition of the 6-column least squares); plain steps still 0.97^8 = 78 % away
    assert np.linalg.norm(x - fixed) < 1e-8 * np.linalg.norm(fixed)
    assert np.linalg.norm(plain - fixed) > 0.5 * np.linalg.norm(fixed)
    assert len(acc.dF) == 7  # the safeguard never fired: each combined step shrank the residual


def test_anderson_forgets_its_history_when_the_residual_grows():
    g, _ = _slow_linear_map()
    x, acc = np.zeros(6), Anderson(depth=10)
    for _ in range(3):
        x, acc = anderson_step(acc, x, g(x))
    # a map evaluated with an error (an inexact inner solve) whose residual exceeds the last one's
    noisy = g(x) + 10 * (g(x) - x)
    out, after = anderson_step(acc, x, noisy)
    np.testing.assert_array_equal(out, noisy)  # the plain step, no extrapolation of the noise
    assert after.dF == () and after.depth == 10
    np.testing.assert_array_equal(after.x, x)  # the new history starts here


def _record(i, phase, adjust, fit):
    return IterationRecord(i, phase, adjust, fit, adjust + fit, (0,), 0.1, 0.1)


def test_the_refinement_restarts_on_its_adjustment_cost_the_knn_phase_on_the_combined_cost():
    start = (_record(0, "adjust", 100.0, 0.0),)
    # the refinement: the combined cost rose through the in-sample regression cost, the adjustment's fell
    grid = start + (_record(1, "grid", 90.0, 10.0), _record(2, "grid", 80.0, 40.0))
    assert not cost_raised(grid)
    assert cost_raised(grid + (_record(3, "grid", 81.0, 1.0),))
    # the kNN phase reads the combined cost
    knn = start + (_record(1, "knn", 90.0, 10.0), _record(2, "knn", 80.0, 40.0))
    assert cost_raised(knn)
    # the first step of a phase has nothing to compare with
    assert not cost_raised(start + (_record(1, "knn", 120.0, 0.0),))
    assert not cost_raised(knn + (_record(3, "grid", 200.0, 0.0),))
