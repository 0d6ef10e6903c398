"""A converged solution's reported KKT error meets the documented bound
(``Solution.kkt_error``: at most ``max(tol_optimality, ip_tol)``), over a dataset-like
batch: the dataset's joint-space sampling law, its period bound (twice the robot's) and
its weights, solved by ``solve_batch`` and, for a few pairs, by ``solve``."""

import numpy as np
import pytest

import jtraj
from jtraj.dataset.build import DEFAULT_WEIGHTS, H_MAX_FACTOR
from jtraj.dataset.sampling import Distribution, sample_pairs
from jtraj.solver import SolverOptions

N = 10  # the suite's other serial3 solves' N: the same programs


@pytest.fixture(scope="module")
def batch():
    base = jtraj.robots.get("serial3")
    robot = jtraj.robots.get("serial3", h_max=H_MAX_FACTOR * base.limits.h_max)
    qs, qg = sample_pairs(robot, Distribution(), seed=0, start=0, stop=32)
    weights = jtraj.Weights.parse(DEFAULT_WEIGHTS)
    sol = jtraj.solve_batch(robot, qs, qg, N=N, weights=weights)
    return robot, qs, qg, weights, sol


def test_converged_kkt_error_within_documented_bound(batch):
    _, _, _, _, sol = batch
    opts = SolverOptions()
    bound = max(opts.tol_optimality, opts.ip_tol)
    conv = np.asarray(sol.converged)
    kkt = np.asarray(sol.kkt_error)
    assert conv.sum() >= 24, f"only {conv.sum()} of 32 converged: the check would be vacuous"
    assert np.all(np.isfinite(kkt[conv]))
    over = np.flatnonzero(conv & (kkt > bound))
    assert over.size == 0, f"converged samples {over.tolist()} report kkt_error {kkt[over].tolist()} > {bound}"


def test_single_solve_reports_the_same_kkt_error(batch):
    robot, qs, qg, weights, sol = batch
    for i in (0, 1, 2):
        one = jtraj.solve(jtraj.Problem(robot, qs[i], qg[i], N=N, weights=weights))
        assert int(one.status) == int(sol.status[i])
        if bool(one.converged):
            assert float(one.kkt_error) <= SolverOptions().tol_optimality
        # the same method, the same multipliers: the same value up to rounding
        np.testing.assert_allclose(float(one.kkt_error), float(sol.kkt_error[i]), rtol=1e-6, atol=1e-12)
