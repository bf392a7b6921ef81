"""The window BA's solver against scipy's sparse least squares on the same window."""

from __future__ import annotations

from rsvo_ros.tools import ba_solvers


def test_compiled_solver_reaches_at_least_scipys_cost_on_a_walk_window():
    prob = ba_solvers.collect_windows(60, 0.5, 1)[0]
    start = ba_solvers.cost_of(prob, prob.R, prob.p, prob.w, prob.v, prob.rho)
    ours = ba_solvers.cost_of(prob, *ba_solvers._compiled(prob)[:5])
    theirs = ba_solvers.cost_of(prob, *ba_solvers.solve_scipy(prob, 30)[:5])
    assert ours < start and ours <= theirs * 1.02
