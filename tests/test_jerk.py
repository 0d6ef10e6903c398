"""Jerk bounds (``Problem(jerk=...)``): the rows against their definition, the defaults,
the refusals, and (slow) optima with and without the bound against CasADi + IPOPT on the
same NLP with jerk rows (``jtraj_peers/ipopt_arm.py``)."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj
from jtraj.robots.serial import SERIAL3_LIMITS, serial_planar
from jtraj.transcription import Transcription, jerk_inequalities


J = 3.0  # rad/s^3: tight enough to bind on the move below
Q0, Q1 = np.array([0.0, 0.3, -0.2]), np.array([0.6, -0.2, 0.2])
N = 16
WEIGHTS = dict(time=1.0, energy=0.1)


def serial3_jerk(jerk=J):
    """serial3 (the thesis' arm) with a jerk bound added to its limits."""
    return serial_planar((1.0, 0.8, 0.45), (10.0, 8.0, 4.0), (9.23, 7.5, 5.21),
                         limits=dict(SERIAL3_LIMITS, qddd_max=jerk), name="serial3")


def jerk_ratio(v, h, jerk=J):
    """max over k, j of |v_{k+1,j} - v_kj| / (J (h_k + h_{k+1}) / 2): 1 on the bound."""
    v, h = np.asarray(v), np.asarray(h)
    return float(np.max(np.abs(np.diff(v, axis=0)) / (jerk * 0.5 * (h[1:] + h[:-1]))[:, None]))


def test_rows_match_their_definition():
    rng = np.random.default_rng(0)
    robot = jtraj.robots.serial.serial_planar((1.0, 0.8, 0.45), (10.0, 8.0, 4.0), (9.23, 7.5, 5.21),
                                              limits=dict(SERIAL3_LIMITS, qddd_max=(2.0, 3.0, 5.0)))
    lim = robot.limits
    v, h = rng.uniform(-3, 3, (6, 3)), rng.uniform(0.005, 0.1, 6)
    g = np.asarray(jerk_inequalities(jnp.asarray(v), jnp.asarray(h), lim))
    Jv = np.array([2.0, 3.0, 5.0])
    expect = []
    for k in range(5):
        for j in range(3):
            reach = Jv[j] * (h[k] + h[k + 1]) / 2
            expect += [(v[k + 1, j] - v[k, j] - reach) / (Jv[j] * 0.1), (v[k, j] - v[k + 1, j] - reach) / (Jv[j] * 0.1)]
    np.testing.assert_allclose(g, expect, rtol=1e-13, atol=1e-13)
    # a row is <= 0 exactly where its jump is within the bound
    ok = np.abs(np.diff(v, axis=0)) <= Jv * 0.5 * (h[1:] + h[:-1])[:, None]
    assert np.array_equal(g.reshape(5, 3, 2).max(axis=-1) <= 0, ok)


def test_defaults_and_global_rows():
    s3 = jtraj.robots.get("serial3")
    assert not jtraj.Problem(s3, Q0, Q1, N=N).jerk  # the thesis' arm has no jerk bound: off
    robot = serial3_jerk()
    p_on, p_off = jtraj.Problem(robot, Q0, Q1, N=N), jtraj.Problem(robot, Q0, Q1, N=N, jerk=False)
    assert p_on.jerk and not p_off.jerk  # on where the limits include one
    tr = Transcription("decoupled")
    lay = tr.layout(p_on)
    rng = np.random.default_rng(1)
    v, h = jnp.asarray(rng.uniform(-3, 3, (N, 3))), jnp.asarray(rng.uniform(0.005, 0.1, N))
    z = lay.pack(v, h)
    g_on, g_off = tr.global_inequalities(p_on, lay, z), tr.global_inequalities(p_off, lay, z)
    assert g_off.shape == (1,) and g_on.shape == (1 + 2 * (N - 1) * 3,)
    np.testing.assert_array_equal(g_on[:1], g_off)
    np.testing.assert_allclose(g_on[1:], jerk_inequalities(v, h, robot.limits), rtol=0, atol=1e-12)
    # the decoupled rows are linear in z (no curvature of their own)
    weighted = lambda zz: jnp.sum(jnp.sin(jnp.arange(g_on.size)) * tr.global_inequalities(p_on, lay, zz))  # noqa: E731
    H = jax.jit(jax.hessian(weighted))(z)
    assert float(jnp.max(jnp.abs(H))) == 0.0
    # the spline's rows bound its cubic's exact jerk, (qdd_{k+1} - qdd_k) / h_k
    sp = Transcription("spline")
    lay_s = sp.layout(p_on)
    knots = jnp.asarray(Q0 + np.cumsum(rng.uniform(-0.05, 0.05, (N, 3)), axis=0))
    u = jnp.concatenate([knots[:-1], jnp.asarray(Q1)[None]])
    g_s = np.asarray(jax.jit(lambda zz: sp.global_inequalities(p_on, lay_s, zz))(lay_s.pack(u, h))[1:]).reshape(N, 3, 2)
    _, _, qdd = jtraj.transcription.clamped_spline(jnp.asarray(Q0), jnp.zeros(3), jnp.zeros(3), u, h)
    jerk = np.diff(np.asarray(qdd), axis=0) / np.asarray(h)[:, None]
    np.testing.assert_allclose(g_s[..., 0], (jerk - J) * np.asarray(h)[:, None] / (J * 0.1), rtol=1e-10, atol=1e-12)


def test_refusals():
    s3 = jtraj.robots.get("serial3")
    with pytest.raises(ValueError, match="jerk=True needs a jerk bound"):
        jtraj.Problem(s3, Q0, Q1, N=N, jerk=True)
    with pytest.raises(ValueError, match="jerk must be True, False or None"):
        jtraj.Problem(serial3_jerk(), Q0, Q1, N=N, jerk="yes")
    p = jtraj.Problem(serial3_jerk(), Q0, Q1, N=N)
    with pytest.raises(ValueError, match="transcription 'shooting' has none"):
        jtraj.solve(p, transcription="shooting")
    with pytest.raises(ValueError, match="method='ip' does not handle Problem\\(jerk=True\\)"):
        jtraj.solve(p, options=jtraj.SolverOptions(method="ip"))
    with pytest.raises(ValueError, match="linear_solver='riccati' does not handle"):
        jtraj.solve(p, options=jtraj.SolverOptions(method="al", linear_solver="riccati"))
    with pytest.raises(ValueError, match="has a jerk bound"):
        jtraj.solve_batch(serial3_jerk(), Q0[None], Q1[None], N=N, transcription="shooting")
    # the default method is resolved to the AL loop (its dense Newton systems)
    from jtraj import _testing

    assert _testing.resolve_method(None, "decoupled", p.robot, True).method == "al"
    assert _testing.resolve_method(None, "decoupled", p.robot, False).method == "ip"
    assert not _testing.stagewise_directions(jtraj.SolverOptions(), Transcription("decoupled"), True)


def test_jerk_rows_implied_by_the_acceleration_bounds_are_left_out():
    """Where 2 qdd_max <= qddd_max h_min every jerk row holds whatever the solution (the
    Panda's published limits): the default leaves them out (so the interior-point method
    solves it); jerk=True keeps them. A shorter h_min puts them back by default."""
    pytest.importorskip("example_robot_data")
    panda = jtraj.robots.get("panda")
    lim = panda.limits
    assert np.all(2 * np.asarray(lim.qdd_max) <= np.asarray(lim.qddd_max) * float(lim.h_min))
    q0 = 0.5 * (np.asarray(lim.q_min) + np.asarray(lim.q_max))
    assert not jtraj.Problem(panda, q0, q0 + 0.1, N=N).jerk
    assert jtraj.Problem(panda, q0, q0 + 0.1, N=N, jerk=True).jerk
    short = jtraj.robots.get("panda", h_min=0.001)
    assert jtraj.Problem(short, q0, q0 + 0.1, N=N).jerk
    # the implication itself: random accelerations within the box meet every row
    rng = np.random.default_rng(3)
    v = jnp.asarray(rng.uniform(-1, 1, (N, 7)) * np.asarray(lim.qdd_max))
    h = jnp.asarray(rng.uniform(float(lim.h_min), float(lim.h_max), N))
    assert float(jnp.max(jerk_inequalities(v, h, lim))) <= 0.0


@pytest.mark.slow
def test_jerk_bound_binds_and_matches_ipopt():
    """Without the rows the optimum jumps its accelerations at 6x the bound; with them it
    meets the bound (active, to 1e-6) and its cost is IPOPT's on the same NLP with jerk
    rows (both from their own default starts; 3.7e-5 apart measured)."""
    pytest.importorskip("casadi")
    from jtraj_peers import ipopt_arm as A
    from jtraj_peers import ipopt_peer as P

    robot = serial3_jerk()
    W = jtraj.Weights(**WEIGHTS)
    off = jtraj.solve(jtraj.Problem(robot, Q0, Q1, N=N, weights=W, jerk=False))
    on = jtraj.solve(jtraj.Problem(robot, Q0, Q1, N=N, weights=W))
    assert off.converged and on.converged
    assert jerk_ratio(off.v, off.h) > 2.0
    # met to 1e-6 of the bound (the rows are normalised by J h_max; h <= h_max) and active
    assert jerk_ratio(on.v, on.h) <= 1 + 1e-6 * 0.1 / float(np.min(on.h))
    assert jerk_ratio(on.v, on.h) > 1 - 1e-6
    assert float(on.max_violation["jerk"]) <= 1e-6
    assert float(on.cost) > float(off.cost)
    # the other rows still hold: re-simulate from (v, h)
    q, qd = jtraj.transcription.integrate(jnp.asarray(Q0), jnp.zeros(3), on.v, on.h)
    np.testing.assert_allclose(q[-1], Q1, atol=1e-6)
    np.testing.assert_allclose(qd[-1], 0.0, atol=1e-6)
    tau = jax.vmap(robot.inverse_dynamics)(q[:-1], qd[:-1], on.v)
    assert np.all(np.abs(np.asarray(tau)) <= np.array([40.0, 25.0, 20.0]) * (1 + 1e-6))
    for jerk, sol in ((None, off), (J, on)):
        spec = A.ArmSpec.make(P.inverse_dynamics_function(), q_min=-np.inf, q_max=np.inf, qd_max=2.0, qdd_max=3.0,
                              tau_max=(40.0, 25.0, 20.0), h_min=0.005, h_max=0.1, jerk_max=jerk)
        r = A.solve_pair(spec, Q0, Q1, N=N, weights=(WEIGHTS["time"], WEIGHTS["energy"], 0.0))
        assert r["strict_success"], r["status"]
        if jerk is not None:
            assert jerk_ratio(r["v"], r["h"]) <= 1 + 1e-6
        assert abs(float(sol.cost) - r["cost"]) <= 2e-4 * r["cost"]
        # IPOPT started at jtraj's optimum stays at its cost (a KKT point of the same NLP)
        r2 = A.solve_pair(spec, Q0, Q1, N=N, weights=(WEIGHTS["time"], WEIGHTS["energy"], 0.0),
                          init=(np.asarray(sol.v), np.asarray(sol.h)))
        assert r2["strict_success"] and abs(float(sol.cost) - r2["cost"]) <= 2e-4 * r2["cost"]


@pytest.mark.slow
def test_sensitivity_to_the_jerk_bound():
    """The optimal cost's derivative in qddd_max by implicit differentiation (the jerk
    rows among the active constraints) against central differences of re-solves."""
    robot = serial3_jerk()
    W = jtraj.Weights(**WEIGHTS)
    problem = jtraj.Problem(robot, Q0, Q1, N=N, weights=W)
    tight = jtraj.SolverOptions(tol_optimality=1e-8)  # a traced option: the same programs
    sol = jtraj.solve(problem, options=tight)
    assert sol.converged
    sens = jtraj.sensitivity(problem, "qddd_max", solution=sol, options=tight)
    d = 0.02 * J

    def cost(jerk):
        r = jtraj.robots.with_params(robot, qddd_max=jnp.full(3, jerk))
        s = jtraj.solve(jtraj.Problem(r, Q0, Q1, N=N, weights=W), init=(sol.v, sol.h), options=tight)
        assert s.converged
        return float(s.cost)

    fd = (cost(J + d) - cost(J - d)) / (2 * d)
    total = float(np.sum(sens["cost"]))  # all three joints' bounds moved together
    assert fd < 0  # a looser bound, a cheaper move
    assert abs(total - fd) <= 2e-2 * abs(fd), (sens["cost"], fd)
