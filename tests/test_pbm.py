"""The penalty-barrier multiplier (PBM) inequality term (``SolverOptions.pbm()``).

* its function phi against the closed form -log(1 - t) and its twice-differentiable
  quadratic continuation (values, first and second derivatives by autodiff);
* a batch solved with it: the converged trajectory re-simulated by the independent NumPy +
  Pinocchio verifier and its cost against CasADi + IPOPT, an infeasible problem stopped
  as likely infeasible, a non-finite sample flagged, all in one compiled batch;
* a restart runs with PHR (the phase flag of ``jtraj.solver.al.with_phase``), and a PBM run cut
  short falls back to PHR's cold run and reaches the same optimum.

In its own file so that pytest-xdist compiles it beside test_solver.py.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj
from helpers import N_SMALL as N, Q0, Q1, W_SMALL as W, three_sample_batch, verified_ipopt_cost
from jtraj import Status
from jtraj import _testing as S
from jtraj.solver import SolverOptions
from jtraj.transcription import Transcription


@pytest.mark.slow
def test_phi_is_the_log_barrier_continued_twice_differentiably():
    t = np.linspace(-5.0, 0.5, 23)
    np.testing.assert_allclose(np.asarray(S.pbm_phi(jnp.asarray(t))), -np.log1p(-t), rtol=1e-14, atol=1e-15)
    d1, d2 = jax.grad(S.pbm_phi), jax.grad(jax.grad(S.pbm_phi))
    assert float(S.pbm_phi(0.0)) == 0.0 and float(d1(0.0)) == pytest.approx(1.0, abs=1e-15)
    # value, slope and curvature continuous across t = 1/2 (left: 1 / (1 - t)^k)
    for f, left in ((S.pbm_phi, np.log(2.0)), (d1, 2.0), (d2, 4.0)):
        assert float(f(0.5 - 1e-9)) == pytest.approx(left, rel=1e-7)
        assert float(f(0.5 + 1e-9)) == pytest.approx(left, rel=1e-7)
    # the multiplier update's slope is phi' everywhere, and phi stays convex
    for x in (-3.0, -0.2, 0.3, 0.7, 4.0):
        assert float(S.pbm_slope(x)) == pytest.approx(float(d1(x)), rel=1e-12)
        assert float(d2(x)) > 0
    # the term vanishes with its multipliers and is finite for any violation
    g = jnp.array([-1.0, 0.0, 0.2, 3.0])
    assert float(S.pbm(g, jnp.zeros(4), 100.0)) == 0.0
    assert np.isfinite(float(S.pbm(g, jnp.ones(4), 1e6)))


@pytest.mark.slow
def test_multiplier_update_is_bounded_and_floored():
    problem = jtraj.Problem(jtraj.robots.get("serial3"), Q0, Q1, N=N, weights=W)
    tr = Transcription("decoupled")
    nlp = S.NLP(problem=problem, tr=tr, layout=tr.layout(problem), sd=tr.stage_data(problem),
                ineq_penalty="pbm", pbm_ratio=4.0)
    rho = jnp.full(4, 0.1)
    new = np.asarray(nlp.ineq_update(jnp.array([-1.0, 0.0, 1e-3, 1.0]), rho, 100.0))
    # phi'(-100) = 1/101 -> clipped to 1/4; phi'(0) = 1; phi'(0.1) = 1/0.9; phi'(100) -> 4
    np.testing.assert_allclose(new, [0.025, 0.1, 0.1 / 0.9, 0.4], rtol=1e-12)
    assert float(nlp.ineq_update(jnp.array(-1.0), jnp.array(1e-9), 100.0)) == S.PBM_FLOOR
    # after a restart (phase off) the same NLP takes PHR's term and update
    state = S.init_state(nlp, jnp.zeros(nlp.layout.nz), SolverOptions.pbm())
    assert S.with_phase(nlp, state).pbm_on
    nlp = S.with_phase(nlp, state._replace(restarts=jnp.asarray(1)))
    g, rho, mu = jnp.array([-1.0, 0.01]), jnp.array([0.5, 0.5]), 100.0
    assert float(nlp.ineq_term(g, rho, mu)) == pytest.approx(float(S.phr(g, rho, mu)), rel=1e-14)
    np.testing.assert_allclose(np.asarray(nlp.ineq_update(g, rho, mu)), [0.0, 1.5], rtol=1e-14)


def test_pbm_preset_and_validation():
    opts = SolverOptions.pbm(max_iter=300)
    assert opts.inequality_penalty == "pbm" and opts.max_iter == 300 and opts.penalty_init == 100.0
    assert SolverOptions().inequality_penalty == "phr"
    with pytest.raises(ValueError, match="inequality_penalty"):
        SolverOptions(inequality_penalty="log")
    with pytest.raises(ValueError, match="pbm_ratio"):
        SolverOptions(pbm_ratio=1.0)
    with pytest.raises(ValueError, match="pbm_init"):
        SolverOptions(pbm_init=0.0)


@pytest.fixture(scope="module")
def batch():
    return three_sample_batch(SolverOptions.pbm())


@pytest.mark.slow
def test_pbm_batch_converges_to_ipopts_optimum_and_flags_the_rest(batch):
    q0, q1, sol = batch
    status = np.asarray(sol.status)
    assert status[0] == Status.CONVERGED
    ref_cost = verified_ipopt_cost(sol, 0, Q0, Q1, N)
    assert ref_cost * 0.99 <= float(sol.cost[0]) <= ref_cost * 1.005
    assert float(sol.kkt_error[0]) <= SolverOptions().tol_optimality
    assert status[1] == Status.LIKELY_INFEASIBLE, status
    assert float(sol.max_violation["overall"][1]) > 1e-3
    assert int(sol.iterations[1]) < SolverOptions().max_iter
    assert status[2] == Status.INVALID_INPUT and int(sol.iterations[2]) == 0
    assert np.all(np.isfinite(np.asarray(sol.q)))
    # converged by the PBM run itself, before its fallback to PHR
    assert int(sol.iterations[0]) < SolverOptions.pbm().pbm_fallback_iter


@pytest.mark.slow
def test_pbm_run_cut_short_falls_back_to_phr_and_reaches_the_same_optimum(batch):
    """A PBM run still uncertified after pbm_fallback_iter iterations restarts as PHR's
    own cold run from the same start (jtraj.solver.al.restart_state): cut to 8 iterations, the pair
    must still converge, to the PBM run's optimum, in more iterations than 8. (The whole
    batch again: pbm_fallback_iter is traced, so the fixture's compiled solver serves.)"""
    q0, q1, ref = batch
    robot = jtraj.robots.get("serial3")
    sol = jtraj.solve_batch(robot, q0, q1, N=N, weights=W, options=SolverOptions.pbm(pbm_fallback_iter=8),
                            slots=2)
    assert int(sol.status[0]) == Status.CONVERGED, int(sol.status[0])
    assert int(sol.iterations[0]) > 8
    assert float(sol.cost[0]) == pytest.approx(float(ref.cost[0]), rel=1e-4)
    with pytest.raises(ValueError, match="pbm_fallback_iter"):
        SolverOptions(pbm_fallback_iter=-1)


@pytest.mark.slow
def test_fallback_takes_phrs_own_subproblem_tolerance():
    """The PBM phase takes pbm_inner_tol_ratio, the PHR fallback and restart the plain
    inner_tol_ratio, so the fallback is PHR's own run (with one ratio, 0.1, for both, the
    fallback fails dataset-family pairs that PHR solves)."""
    pbm, phr = SolverOptions.pbm(), SolverOptions()
    assert pbm.inner_tol_ratio == phr.inner_tol_ratio == 0.01 and pbm.pbm_inner_tol_ratio == 0.1
    viol = 5e-2
    assert float(S.next_inner_tol(pbm, 1e-3, viol, jnp.asarray(True))) == pytest.approx(5e-3, rel=1e-12)
    for flag in (jnp.asarray(False), False):
        assert float(S.next_inner_tol(pbm, 1e-3, viol, flag)) == pytest.approx(
            float(S.next_inner_tol(phr, 1e-3, viol)), rel=1e-12)
    # a PHR run ignores the flag and pbm_inner_tol_ratio
    assert float(S.next_inner_tol(SolverOptions(pbm_inner_tol_ratio=0.5), 1e-3, viol, True)) == pytest.approx(5e-4)
    with pytest.raises(ValueError, match="pbm_inner_tol_ratio"):
        SolverOptions.pbm(pbm_inner_tol_ratio=-0.1)
