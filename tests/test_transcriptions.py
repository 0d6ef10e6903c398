"""Chettibi's transcriptions (collocation, shooting, spline) against independent
references: SciPy's clamped cubic spline, Pinocchio's dynamics (ABA for forward,
RNEA for inverse dynamics) and SciPy's adaptive ODE integrator.

Each solved trajectory is checked with NumPy/SciPy/Pinocchio code only, from the
returned fields (q, qd, v, tau, h): the model equations of its transcription hold to
1e-6 and the goal is reached; the optimal times of all transcriptions agree with the
decoupled one to within their discretisation differences.
"""

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicSpline

import jtraj
from jtraj.transcription import TRANSCRIPTIONS, Transcription, clamped_spline


N = 10
W = jtraj.Weights(time=1.0, energy=0.1)
Q0 = np.array([1.077, -0.096, 0.619])
Q1 = np.array([1.2, -0.049, 0.9])


def test_clamped_spline_matches_scipy():
    rng = np.random.default_rng(0)
    for n_int in (1, 2, 7):
        h = rng.uniform(0.05, 0.3, n_int)
        q0, knots = rng.normal(size=2), rng.normal(size=(n_int, 2))
        qd0, qdN = rng.normal(size=2), rng.normal(size=2)
        q, qd, qdd = map(np.asarray, clamped_spline(q0, qd0, qdN, knots, h))
        t = np.concatenate([[0.0], np.cumsum(h)])
        ref = CubicSpline(t, np.vstack([q0, knots]), bc_type=((1, qd0), (1, qdN)))
        np.testing.assert_allclose(q, ref(t), atol=1e-12)
        np.testing.assert_allclose(qd, ref(t, 1), atol=1e-10)
        np.testing.assert_allclose(qdd, ref(t, 2), atol=1e-9 * np.max(np.abs(qdd)))


def test_transcription_names_and_cli_choices_agree():
    import argparse

    from jtraj.commands import solve as cmd

    parser = argparse.ArgumentParser()
    cmd.configure(parser)
    action = next(a for a in parser._actions if a.dest == "transcription")
    assert tuple(action.choices) == TRANSCRIPTIONS
    with pytest.raises(ValueError, match="transcription must be one of"):
        Transcription("midpoint")


@pytest.fixture(scope="module")
def problem():
    return jtraj.Problem(jtraj.robots.get("serial3"), Q0, Q1, N=N, weights=W)


@pytest.fixture(scope="module")
def decoupled(problem):
    return jtraj.solve(problem)


def _pin():
    V = pytest.importorskip("jtraj_peers.verify")
    import pinocchio as pin

    model = V.serial3_model()
    return V, pin, model, model.createData()


def _check_common(problem, sol, name):
    lim = problem.robot.limits
    assert sol.converged, f"{name}: {sol.status_message}"
    q, qd, tau, h = (np.asarray(x) for x in (sol.q, sol.qd, sol.tau, sol.h))
    np.testing.assert_allclose(q[0], Q0, atol=1e-12)
    np.testing.assert_allclose(q[-1], Q1, atol=1e-6)
    np.testing.assert_allclose(qd[-1], 0.0, atol=1e-6)
    assert np.all(np.abs(tau) <= np.asarray(lim.tau_max) * (1 + 1e-6))
    assert np.all(np.abs(qd) <= np.asarray(lim.qd_max) * (1 + 1e-6))
    assert np.all((h >= lim.h_min * (1 - 1e-9)) & (h <= lim.h_max * (1 + 1e-9)))
    return q, qd, tau, h


@pytest.mark.slow
def test_collocation_satisfies_midpoint_rule_with_pinocchio(problem, decoupled):
    V, pin, model, data = _pin()
    sol = jtraj.solve(problem, transcription="collocation")
    q, qd, tau, h = _check_common(problem, sol, "collocation")
    for k in range(N):
        qm, qdm = (q[k] + q[k + 1]) / 2, (qd[k] + qd[k + 1]) / 2
        a = pin.aba(model, data, qm, qdm, tau[k])
        np.testing.assert_allclose(q[k + 1] - q[k], h[k] * qdm, atol=1e-6)
        np.testing.assert_allclose(qd[k + 1] - qd[k], h[k] * a, atol=1e-6 * 2.0)  # qd defect relative to qd_max
        np.testing.assert_allclose(np.asarray(sol.v[k]), a, rtol=1e-8, atol=1e-8)
    # a different O(h^2) discretisation of the same continuous problem
    assert float(sol.T) == pytest.approx(float(decoupled.T), rel=0.05)


@pytest.mark.slow  # a solver of its own (about a minute of compilation on 2 cores); the
# spline itself is checked against SciPy above, and the collocation solve stays in the default suite
def test_spline_is_the_clamped_spline_with_rnea_torques(problem, decoupled):
    V, pin, model, data = _pin()
    sol = jtraj.solve(problem, transcription="spline")
    q, qd, tau, h = _check_common(problem, sol, "spline")
    t = np.concatenate([[0.0], np.cumsum(h)])
    ref = CubicSpline(t, q, bc_type=((1, np.zeros(3)), (1, np.zeros(3))))
    np.testing.assert_allclose(qd, ref(t, 1), atol=1e-8)
    acc = ref(t, 2)
    np.testing.assert_allclose(np.asarray(sol.v), acc[:-1], rtol=1e-7, atol=1e-7)
    for k in range(N + 1):  # torques at every knot (the last one too) within the box
        tk = pin.rnea(model, data, q[k], qd[k], acc[k])
        if k < N:
            np.testing.assert_allclose(tau[k], tk, rtol=1e-9, atol=1e-9)
        assert np.all(np.abs(tk) <= np.asarray(problem.robot.limits.tau_max) * (1 + 1e-6))
    assert float(sol.T) == pytest.approx(float(decoupled.T), rel=0.05)


@pytest.mark.slow  # RK4 through forward dynamics: ~2 min to compile on 2 cores
def test_shooting_replayed_by_an_adaptive_integrator(problem, decoupled):
    V, pin, model, data = _pin()
    sol = jtraj.solve(problem, transcription="shooting")
    q, qd, tau, h = _check_common(problem, sol, "shooting")
    x = np.concatenate([q[0], qd[0]])
    for k in range(N):
        def f(_, s, u=tau[k]):
            return np.concatenate([s[3:], pin.aba(model, data, s[:3], s[3:], u)])

        x = solve_ivp(f, (0.0, h[k]), x, rtol=1e-11, atol=1e-12, method="DOP853").y[:, -1]
        # one RK4 step per interval against the exact flow: O(h^5) local error
        np.testing.assert_allclose(x, np.concatenate([q[k + 1], qd[k + 1]]), atol=1e-5)
    assert float(sol.T) == pytest.approx(float(decoupled.T), rel=0.05)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["collocation", pytest.param("spline", marks=pytest.mark.slow)])
def test_warm_start_through_controls_of(problem, name):
    """Transcription.controls_of turns a Solution back into its controls: a warm start
    from the optimum of each transcription stays there."""
    tr = Transcription(name)
    sol = jtraj.solve(problem, transcription=name)
    again = jtraj.solve(problem, transcription=name, init=(tr.controls_of(sol), sol.h))
    assert again.converged
    assert int(again.iterations) < int(sol.iterations) / 3
    assert float(again.cost) == pytest.approx(float(sol.cost), rel=1e-4)
