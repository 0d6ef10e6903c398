"""jtraj.resample: the constant-acceleration motion between the samples, its efforts, and
the refusals. The efforts between the samples are checked against the work-energy
theorem (an independent reference: the work of tau along the motion equals the change
of the robot's energy from its own kinetic and potential energy functions)."""

import dataclasses

import jax
import numpy as np
import pytest

import jtraj
from jtraj.resample import intersample_effort, interval_times, resample
from jtraj.transcription import integrate

jax.config.update("jax_enable_x64", True)


def _solution(robot, seed=0, N=8, qd0=None):
    """A Solution holding a random constant-acceleration trajectory (the fields resample
    does not read are zeros)."""
    rng = np.random.default_rng(seed)
    n = robot.n
    v = rng.uniform(-3, 3, (N, n))
    h = rng.uniform(0.02, 0.1, N)
    q0 = rng.uniform(-1, 1, n)
    qd0 = rng.uniform(-0.5, 0.5, n) if qd0 is None else qd0
    q, qd = (np.asarray(x) for x in integrate(q0, qd0, v, h))
    tau = np.asarray(jax.vmap(robot.inverse_dynamics)(q[:-1], qd[:-1], v))
    z = np.zeros(())
    return jtraj.Solution(q=q, qd=qd, v=v, tau=tau, h=h, T=h.sum(), cost=z, cost_terms={}, energy=z,
                          max_violation={}, converged=np.asarray(True), status=np.asarray(0), iterations=z,
                          outer_iterations=z, history=np.zeros((1, 3)), kkt_error=z)


def _stack(sols):
    return jax.tree.map(lambda *x: np.stack(x), *sols)


@pytest.mark.parametrize("name", ["serial3", "serial3_vertical"])
def test_work_of_the_efforts_equals_the_energy_change(name):
    # Gauss-Legendre (5 nodes, exact to degree 9) on each interval: the work of tau(t)
    # along qd(t) up to every sample equals E(q_k, qd_k) - E(q_0, qd_0)
    robot = jtraj.robots.get(name)
    if robot.actuator is not None:  # no motor damping: the motion is conservative
        robot = robot.replace(actuator=dataclasses.replace(robot.actuator, b_m=0 * robot.actuator.b_m,
                                                           b_s=0 * robot.actuator.b_s))
    sol = _solution(robot, seed=1)
    h = np.asarray(sol.h)
    x, w = np.polynomial.legendre.leggauss(5)
    starts = np.cumsum(h) - h
    t = (starts[:, None] + h[:, None] * (x + 1) / 2).ravel()
    s = resample(sol, robot, times=t)
    # the actuators' efforts as generalised forces (motor torques times the gear ratio)
    Q = np.asarray(jax.vmap(robot.actuator_to_generalized)(s.q, s.tau))
    power = np.sum(Q * np.asarray(s.qd), axis=1).reshape(len(h), 5)
    work = np.concatenate([[0.0], np.cumsum((power * w).sum(axis=1) * h / 2)])
    energy = np.asarray(jax.vmap(robot.energy)(sol.q, sol.qd))
    np.testing.assert_allclose(work, energy - energy[0], rtol=0, atol=1e-9 * np.abs(energy).max())
    assert np.abs(work).max() > 1e-2  # a real test: the energy changes


def test_samples_and_continuity():
    robot = jtraj.robots.get("serial3")
    sol = _solution(robot, seed=2)
    t_k = np.concatenate([[0.0], np.cumsum(np.asarray(sol.h))])
    s = resample(sol, robot, times=t_k[:-1])  # sample instants: the solution's own states and efforts
    np.testing.assert_allclose(s.q, sol.q[:-1], atol=1e-12)
    np.testing.assert_allclose(s.qd, sol.qd[:-1], atol=1e-12)
    np.testing.assert_allclose(s.tau, sol.tau, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(s.interval, np.arange(len(t_k) - 1))
    # q and qd are continuous across the samples; qd and qdd are the derivatives of q and qd
    left, right = resample(sol, robot, times=t_k[1:-1] - 1e-12), resample(sol, robot, times=t_k[1:-1])
    np.testing.assert_array_equal(left.interval + 1, right.interval)
    np.testing.assert_allclose(left.q, right.q, atol=1e-10)
    np.testing.assert_allclose(left.qd, right.qd, atol=1e-10)
    mid = interval_times(sol.h, 4)[1::4]  # a third of the way into each interval
    a, b = resample(sol, robot, times=mid - 1e-5), resample(sol, robot, times=mid + 1e-5)
    c = resample(sol, robot, times=mid)
    np.testing.assert_allclose((b.q - a.q) / 2e-5, c.qd, atol=1e-8)
    np.testing.assert_allclose((b.qd - a.qd) / 2e-5, c.qdd, atol=1e-8)
    # the dt grid: uniform steps below T, then T itself (the goal state)
    g = resample(sol, robot, dt=0.01)
    T = float(sol.T)
    assert g.t[0] == 0 and g.t[-1] == pytest.approx(T, abs=1e-15) and np.allclose(np.diff(g.t[:-1]), 0.01)
    assert 0 < T - g.t[-2] <= 0.01
    np.testing.assert_allclose(g.q[-1], sol.q[-1], atol=1e-12)
    np.testing.assert_allclose(g.qd[-1], sol.qd[-1], atol=1e-12)


def test_batch_equals_one_by_one_and_the_effort_ratio():
    robot = jtraj.robots.get("serial3")
    sols = [_solution(robot, seed=s) for s in (3, 4, 5)]
    batch = resample(_stack(sols), robot, num=33)
    ratios = np.asarray(intersample_effort(_stack(sols), robot, per_interval=9))
    tau_max = np.asarray(robot.limits.tau_max)
    for i, sol in enumerate(sols):
        one = resample(sol, robot, num=33)
        np.testing.assert_allclose(batch.q[i], one.q, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(batch.tau[i], one.tau, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(one.t, np.linspace(0, float(sol.T), 33), rtol=1e-13)
        # the ratio is the largest |tau| / tau_max over the interval grid, at least the samples'
        dense = resample(sol, robot, times=interval_times(sol.h, 9))
        assert ratios[i] == pytest.approx(np.max(np.abs(dense.tau) / tau_max), rel=1e-12)
        assert ratios[i] >= np.max(np.abs(sol.tau) / tau_max) - 1e-12


def test_refusals():
    robot = jtraj.robots.get("serial3")
    sol = _solution(robot)
    for kwargs, needle in [({}, "exactly one"), ({"dt": 0.01, "num": 5}, "exactly one"), ({"dt": 0.0}, "dt"),
                           ({"dt": float("nan")}, "dt"), ({"num": 1}, "num"), ({"num": 2.5}, "num"),
                           ({"times": [0.0, 1e3]}, "times"), ({"times": [[0.0]]}, "times")]:
        with pytest.raises(ValueError, match=needle):
            resample(sol, robot, **kwargs)
    with pytest.raises(ValueError, match="batch"):
        resample(_stack([sol, sol]), robot, dt=0.01)
    with pytest.raises(ValueError, match="joints"):
        resample(sol, jtraj.robots.get("ibm7535"), num=3)
    with pytest.raises(ValueError, match="Solution"):
        resample({"q": sol.q}, robot, num=3)
    # states that do not follow the constant-acceleration recursion (a spline solution, say)
    bent = jax.tree.map(lambda x: x, sol)
    bent = bent.__class__(**{**{k: getattr(sol, k) for k in sol.__dataclass_fields__},
                             "q": np.asarray(sol.q) + np.linspace(0, 0.01, sol.q.shape[0])[:, None]})
    with pytest.raises(ValueError, match="constant-acceleration"):
        resample(bent, robot, num=3)
    nan = bent.__class__(**{**{k: getattr(sol, k) for k in sol.__dataclass_fields__}, "h": np.full(8, np.nan)})
    with pytest.raises(ValueError, match="non-finite"):
        resample(nan, robot, num=3)
    with pytest.raises(ValueError, match="per_interval"):
        intersample_effort(sol, robot, per_interval=1)


@pytest.mark.slow  # two minutes or more of compilation on a 2-core machine
def test_efforts_intervals_bounds_the_executed_motion():
    # the thesis' sample constraints leave the efforts at the interval ends above tau_max;
    # Problem(efforts="intervals") bounds them, checked by Pinocchio's RNEA (independent
    # of jtraj's dynamics) at every interval's end and by the dense effort ratio between
    V = pytest.importorskip("jtraj_peers.verify")
    from jtraj_peers.pairs import benchmark_pairs

    robot = jtraj.robots.get("serial3")
    q0, q1 = (x[2] for x in benchmark_pairs(8, 5))  # a pair whose sample-bounded optimum exceeds by 3.7 %
    w = jtraj.Weights(time=1.0, energy=0.1)
    tau_max = np.asarray(robot.limits.tau_max)
    sols = {e: jtraj.solve(jtraj.Problem(robot, q0, q1, N=20, weights=w, efforts=e)) for e in ("samples", "intervals")}
    for e, sol in sols.items():
        assert bool(sol.converged), e
        q, qd, v = (np.asarray(x) for x in (sol.q, sol.qd, sol.v))
        ends = np.array([V.rnea(q[k + 1], qd[k + 1], v[k]) for k in range(20)]) / tau_max
        ratio = float(intersample_effort(sol, robot, per_interval=64))
        if e == "samples":
            assert "tau_end" not in sol.max_violation
            assert np.abs(ends).max() > 1.02 and ratio > 1.02
        else:
            assert float(sol.max_violation["tau_end"]) <= 1e-6
            assert np.abs(ends).max() <= 1 + 1e-6
            assert ratio <= 1 + 1e-3  # between the ends: measured 1 + 2.4e-4 at most on 57 benchmark pairs
    # a smaller feasible set: no lower optimum (same start point, same local basin)
    assert float(sols["intervals"].cost) >= float(sols["samples"].cost) * (1 - 1e-6)
    # pair 44 of `jtraj dataset --pairs 96 --seed 5` (h_max 0.2 s): the holding feasibility
    # polish left its certified optimum 6.6e-6 outside the effort box (nearly parallel
    # rows); the releasing one (jtraj.solver.certify.final_polish) makes it verify
    long_steps = jtraj.robots.get("serial3", h_max=0.2)
    a, b = [-0.17935802040533577, -0.2729153904459174, 0.43714046091579206], \
        [0.2820074688736016, -0.5362270260943265, 0.34308692781562267]
    sol = jtraj.solve(jtraj.Problem(long_steps, a, b, N=20, weights=w, efforts="intervals"))
    assert bool(sol.converged), sol.status_message
    r = V.verify(a, b, sol.v, sol.h, h_max=0.2, tol=1e-6)
    assert r["ok"], (r["goal_error"], r["max_rel_violation"])
    q, qd, v = (np.asarray(x) for x in (sol.q, sol.qd, sol.v))
    assert max(np.abs(V.rnea(q[k + 1], qd[k + 1], v[k]) / tau_max).max() for k in range(20)) <= 1 + 1e-6
    with pytest.raises(ValueError, match="efforts"):
        jtraj.Problem(robot, q0, q1, efforts="midpoints")
    with pytest.raises(ValueError, match="decoupled"):
        jtraj.solve(jtraj.Problem(robot, q0, q1, efforts="intervals"), transcription="coupled")
