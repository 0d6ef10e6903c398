"""The interior-point method's Gauss-Newton curvature of the dynamics (jtraj.solver.curvature):
its stage Hessian is the exact one less the effort multipliers' second derivatives of
the inverse dynamics (that term computed independently by jax.hessian of lam . tau),
every value, gradient and effort Jacobian is the exact one, and a solve with it ends at
the exact-curvature solve's optimum."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj
from jtraj import _testing as T
from jtraj.solver import curvature, ipm
from jtraj.robots import from_urdf
from jtraj.transcription import Transcription

from test_spatial import ARM


@pytest.fixture(scope="module")
def arm():
    return from_urdf(ARM)


def _move(robot):
    lo, hi = np.asarray(robot.limits.q_min), np.asarray(robot.limits.q_max)
    lo, hi = np.where(np.isfinite(lo), lo, -1.0), np.where(np.isfinite(hi), hi, 1.0)
    q0 = lo + 0.4 * (hi - lo)
    return q0, q0 + 0.2 * (hi - lo)


def test_auto_picks_gauss_newton_for_spatial_arms_only(arm):
    assert curvature.resolve("auto", arm) == "gauss_newton"
    assert curvature.resolve("auto", jtraj.robots.get("serial3")) == "exact"
    assert curvature.resolve("exact", arm) == "exact"
    with pytest.raises(ValueError, match="ip_curvature"):
        jtraj.SolverOptions(ip_curvature="newton")
    with pytest.raises(ValueError, match="ip_curvature"):
        curvature.resolve("newton", arm)


@eqx.filter_jit
def _stage_pieces(problem, seed):
    """Exact and Gauss-Newton stage derivatives (with efforts) of the interior-point
    model at the default guess, random positive multipliers on the inequalities, and the
    effort multipliers lam = d phi / d tau per stage."""
    tr = Transcription("decoupled")
    opts = jtraj.SolverOptions()
    nlp, state, _ = T.prepare(problem, opts, tr, T.initial_guess(problem, opts, tr))
    lag = dataclasses.replace(nlp, ineq_penalty="lagrangian")
    st = ipm.init(lag, state.z)
    scale = jax.random.uniform(jax.random.PRNGKey(seed), st.y.shape, st.y.dtype, 0.5, 20.0)
    mult = ipm.multipliers(lag, st._replace(y=st.y * scale, yT=st.yT + 1.0))
    W, mu = nlp.W(state.z), jnp.asarray(0.0, state.z.dtype)
    exact = dataclasses.replace(lag, ip_curvature="exact").stage_derivatives(W, mult, mu, efforts=True)
    gn = dataclasses.replace(lag, ip_curvature="gauss_newton").stage_derivatives(W, mult, mu, efforts=True)
    n = problem.robot.n

    def lam_of(w, sdk, mk, tau):
        return jax.grad(lambda t: lag._stage_al_parts(w, sdk, mk, mu, None, t)[0])(tau)

    lam = jax.vmap(lam_of, in_axes=(0, 0, T.stage_axes(mult), 0))(W, lag.sd, T.stage_mult(mult), exact[3])

    def curvature_term(w, lam_k):  # sum_i lam_i d2 tau_i / dw2, tau from the robot itself
        return jax.hessian(lambda w_: lam_k @ problem.robot.inverse_dynamics(w_[:n], w_[n:2 * n], w_[2 * n:3 * n]))(w)

    def jacobian(w):  # the efforts' Jacobian in w, by jacfwd of the robot's inverse dynamics
        return jax.jacfwd(lambda w_: problem.robot.inverse_dynamics(w_[:n], w_[n:2 * n], w_[2 * n:3 * n]))(w)

    return exact, gn, jax.vmap(curvature_term)(W, lam), jax.vmap(jacobian)(W)


@pytest.mark.slow  # two second derivatives of the dynamics compile: about 2 minutes on 2 busy cores
def test_gauss_newton_drops_only_the_dynamics_second_derivatives(arm):
    q0, q1 = _move(arm)
    problem = jtraj.Problem(arm, q0, q1, N=8, weights=jtraj.Weights(time=1.0, energy=0.1))
    exact, gn, term, J_ref = (jax.tree.map(np.asarray, x) for x in _stage_pieces(problem, 0))
    val, g, H, tau, J = exact
    val_gn, g_gn, H_gn, tau_gn, J_gn = gn
    # values, gradients, efforts and their Jacobians: the exact ones
    for got, want in ((val_gn, val), (g_gn, g), (tau_gn, tau), (J_gn, J)):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * max(1.0, np.abs(want).max()))
    # the efforts' Jacobian against the robot's inverse dynamics differentiated by jacfwd
    np.testing.assert_allclose(J, J_ref, rtol=0, atol=1e-11 * np.abs(J_ref).max())
    # the term dropped is the multipliers' curvature of the dynamics, and it is not small
    assert np.abs(term).max() > 1e-3 * np.abs(H).max()
    np.testing.assert_allclose(H - H_gn, term, rtol=0, atol=1e-10 * np.abs(H).max())
    np.testing.assert_allclose(H_gn, np.swapaxes(H_gn, 1, 2), rtol=0, atol=1e-12 * np.abs(H_gn).max())


@pytest.mark.slow
def test_gauss_newton_solve_ends_at_the_exact_curvature_optimum(arm):
    """Both curvatures solve the small arm's move to the same optimum within the default
    tolerances' accuracy (``tol_optimality`` 3e-4: costs within about 0.01 %): the same
    cost to 1e-4 and the same total time to 1e-3 relative, each certified by its own KKT
    error."""
    q0, q1 = _move(arm)
    problem = jtraj.Problem(arm, q0, q1, N=12, weights=jtraj.Weights(time=1.0, energy=0.1))
    sols = {c: jtraj.solve(problem, options=jtraj.SolverOptions(ip_curvature=c)) for c in ("exact", "gauss_newton")}
    for c, sol in sols.items():
        assert bool(sol.converged), (c, sol.status_message)
        assert float(sol.kkt_error) <= 3e-4, c
    ex, gn = sols["exact"], sols["gauss_newton"]
    assert float(gn.cost) == pytest.approx(float(ex.cost), rel=1e-4)
    assert float(np.sum(gn.h)) == pytest.approx(float(np.sum(ex.h)), rel=1e-3)
