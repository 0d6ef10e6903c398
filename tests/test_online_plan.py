"""The online planner's feasibility repair (jtraj.repair), batches and coverage
(jtraj.coverage), every plan re-verified independently: states re-simulated in NumPy,
efforts from Pinocchio's RNEA (jtraj_peers/verify.py), bounds and goal checked
with stated tolerances."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtraj import Weights, coverage, robots
from jtraj.repair import (cost_of, goal_projection, is_homogeneous, is_quadratic_in_rate, make_repair, trapezoid_profile,
                          switch_profile)

V = pytest.importorskip("jtraj_peers.verify")

W = Weights(time=1.0, energy=0.1)
N, n = 20, 3


def _prediction(rng, scale=1.0):
    """A start/goal pair and a predicted (v, h) of the kind a model makes: the cycloid's
    accelerations over random periods, plus noise of relative size ``scale``."""
    qs = rng.uniform(-1.2, 1.2, n)
    qg = qs + rng.uniform(-0.4, 0.4, n)  # within reach of T <= N h_max = 2 s
    h = rng.uniform(0.05, 0.09, N)
    t = np.cumsum(h) - h / 2
    T = h.sum()
    v = np.outer(np.sin(2 * np.pi * t / T), (qg - qs) * 2 * np.pi / T**2)
    v = v * (1 + scale * rng.normal(0.0, 1.0, (N, n))) + 0.1 * scale * rng.normal(0.0, 1.0, (N, n))
    return qs, qg, v, h


def _recursion(q0, qd0, v, h):
    """The decoupled recursion, written out step by step."""
    q, qd = [np.asarray(q0, float)], [np.asarray(qd0, float) * np.ones(n)]
    for k in range(len(h)):
        q.append(q[-1] + h[k] * qd[-1] + 0.5 * h[k] ** 2 * v[k])
        qd.append(qd[-1] + h[k] * v[k])
    return np.array(q), np.array(qd)


def test_goal_projection_is_the_weighted_least_change_onto_the_goal():
    rng = np.random.default_rng(1)
    qs, qg, v, h = _prediction(rng)
    qd0, qdg = rng.normal(0, 0.3, n), rng.normal(0, 0.3, n)
    w = np.asarray(goal_projection(*map(jnp.asarray, (qs, qd0, qg, qdg, v, h))))
    q, qd = _recursion(qs, qd0, w, h)
    np.testing.assert_allclose(q[-1], qg, atol=1e-12)
    np.testing.assert_allclose(qd[-1], qdg, atol=1e-12)
    # the minimiser of sum_k h_k |dv_k|^2 subject to the terminal state, from the KKT system
    # built here from the step-by-step recursion's linear map (unit impulses)
    E = np.zeros((2, N))
    for k in range(N):
        e = np.zeros((N, n))
        e[k] = 1.0
        qe, qde = _recursion(np.zeros(n), np.zeros(n), e, h)
        E[:, k] = qde[-1, 0], qe[-1, 0]
    q0, qd0_end = _recursion(qs, qd0, v, h)
    r = np.stack([qdg - qd0_end[-1], qg - q0[-1]])
    K = np.block([[np.diag(2 * h), E.T], [E, np.zeros((2, 2))]])
    dv = np.linalg.solve(K, np.r_[np.zeros((N, n)), r])[:N]
    np.testing.assert_allclose(w - v, dv, rtol=1e-9, atol=1e-10)


def test_effort_step_solves_the_linearised_least_effort_problem_on_the_goal():
    from jtraj.repair import effort_step

    rb = robots.get("serial3")
    rng = np.random.default_rng(7)
    qs, qg, v, h = _prediction(rng, 0.3)
    z = np.zeros(n)
    v0 = np.asarray(goal_projection(*map(jnp.asarray, (qs, z, qg, z, v, h))))
    U = np.asarray(W.matrices(rb)[0])
    rho = 0.05
    v1 = np.asarray(effort_step(rb, jnp.asarray(U), *map(jnp.asarray, (qs, z, qg, z, v0, h)), rho))
    q, qd = _recursion(qs, z, v1, h)
    np.testing.assert_allclose(q[-1], qg, atol=1e-10)
    np.testing.assert_allclose(qd[-1], 0.0, atol=1e-10)
    # the same quadratic programme, dense: efforts linearised by central differences of the
    # inverse dynamics at the states of v0, the goal's equations from the recursion
    q0, qd0 = _recursion(qs, z, v0, h)
    ID = lambda a, b, c: np.asarray(rb.inverse_dynamics(jnp.asarray(a), jnp.asarray(b), jnp.asarray(c)))  # noqa
    Hd = np.zeros((N * n, N * n))
    gd = np.zeros(N * n)
    for k in range(N):
        J = np.stack([(ID(q0[k], qd0[k], v0[k] + 1e-6 * e) - ID(q0[k], qd0[k], v0[k] - 1e-6 * e)) / 2e-6
                      for e in np.eye(n)], axis=1)
        c = ID(q0[k], qd0[k], v0[k]) - J @ v0[k]
        Hd[k * n:(k + 1) * n, k * n:(k + 1) * n] = h[k] * (J.T @ U @ J + rho * np.eye(n))
        gd[k * n:(k + 1) * n] = h[k] * (J.T @ U @ c - rho * v0[k])
    E = np.zeros((2 * n, N * n))  # rows: qd_N then q_N, per joint
    for k in range(N):
        for j in range(n):
            e = np.zeros((N, n))
            e[k, j] = 1.0
            qe, qde = _recursion(np.zeros(n), np.zeros(n), e, h)
            E[:n, k * n + j], E[n:, k * n + j] = qde[-1], qe[-1]
    K = np.block([[Hd, E.T], [E, np.zeros((2 * n, 2 * n))]])
    rhs = np.r_[-gd, np.zeros(n), qg - qs]
    ref = np.linalg.solve(K, rhs)[:N * n].reshape(N, n)
    np.testing.assert_allclose(v1, ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())
    # the linearisation the step uses: the states of the recursion, the efforts and their
    # derivatives (central differences above)
    from jtraj.repair import linearise

    ql, qdl, taul, Jl = (np.asarray(x) for x in linearise(rb, *map(jnp.asarray, (qs, z, v0, h))))
    np.testing.assert_allclose(ql, q0, atol=1e-12)
    np.testing.assert_allclose(qdl, qd0, atol=1e-12)
    for k in (0, N // 2, N - 1):
        np.testing.assert_allclose(taul[k], ID(q0[k], qd0[k], v0[k]), rtol=1e-12, atol=1e-12)
        Jfd = np.stack([(ID(q0[k], qd0[k], v0[k] + 1e-6 * e) - ID(q0[k], qd0[k], v0[k] - 1e-6 * e)) / 2e-6
                        for e in np.eye(n)], axis=1)
        np.testing.assert_allclose(Jl[k], Jfd, rtol=1e-6, atol=1e-8)


def test_switch_profile_holds_opposite_accelerations_around_a_linear_switch_and_ends_on_the_goal():
    from jtraj.repair import switch_profile

    rng = np.random.default_rng(8)
    qs, qg, _, _ = _prediction(rng)
    z = np.zeros(n)
    for h in (np.full(N, 0.07), rng.uniform(0.05, 0.09, N)):
        v = np.asarray(switch_profile(*map(jnp.asarray, (qs, z, qg, h)), width=0.3))
        q, qd = _recursion(qs, z, v, h)
        np.testing.assert_allclose(q[-1], qg, atol=1e-12)
        t = np.cumsum(h) - h / 2
        x = (t - h.sum() / 2) / (0.15 * h.sum())  # position in the switch, -1 to 1
        a = v[np.argmin(x)]  # the first interval's accelerations
        for k in range(N):
            np.testing.assert_allclose(v[k], a * min(1.0, max(-1.0, -x[k])) / min(1.0, -x.min()), rtol=1e-12,
                                       atol=1e-14)
        if np.ptp(h) == 0:  # uniform periods: rest at the end too, by symmetry
            np.testing.assert_allclose(qd[-1], 0.0, atol=1e-12)


def test_homogeneity_test_tells_the_horizontal_arm_from_the_geared_vertical_one():
    assert is_homogeneous(robots.get("serial3"))
    assert not is_homogeneous(robots.get("serial3_vertical"))  # gravity and motor damping
    # parallel3 has neither: the test states lie in its joint box, since outside it the
    # legs do not reach the common point and the efforts are not defined
    p3 = robots.get("parallel3")
    assert not np.any(np.isfinite(np.asarray(p3.inverse_dynamics(jnp.array([0.9, -0.9]), jnp.zeros(2), jnp.ones(2)))))
    assert is_homogeneous(p3) and is_quadratic_in_rate(p3)


def _p3_rows(p3, q):
    """parallel3's position rows in NumPy: the joint box relative to its width, then the
    legs' folded and stretched margins (its module doc), for q (..., 2)."""
    lo, hi = np.asarray(p3.limits.q_min), np.asarray(p3.limits.q_max)
    s = np.linalg.norm(q[..., None, :] - np.asarray(p3.base), axis=-1) / (2 * float(p3.link_length))
    return np.concatenate([(lo - q) / (hi - lo), (q - hi) / (hi - lo), 1 - s / float(p3.rho_min),
                           s / float(p3.rho_max) - 1], axis=-1)


def test_position_step_bends_paths_around_parallel3s_leg_singularities():
    # straight-line trapezoids between pairs of the dataset law: those whose samples
    # cross a leg's singularity margin (a leg folded near its base point) are bent inside
    # every position row, with the goal state kept; the others come back unchanged.
    # Positions from a NumPy recursion, rows in NumPy.
    from jtraj.dataset.sampling import Distribution, sample_pairs
    from jtraj.repair import position_step

    p3 = robots.get("parallel3")
    lim, N = p3.limits, 20
    qs, qg = sample_pairs(p3, Distribution(), 2, 0, 2048)

    @jax.jit
    @jax.vmap
    def step(q0, q1):
        z = jnp.zeros_like(q0)
        v, h = trapezoid_profile(q0, q1, N, lim.qd_max, lim.qdd_max)
        v = goal_projection(q0, z, q1, z, v, h)
        return v, position_step(p3, q0, z, q1, z, v, h), h

    v0, v1, h = (np.asarray(x) for x in step(jnp.asarray(qs), jnp.asarray(qg)))

    def recursion(v, h, q0):
        q, qd = [q0], [np.zeros(2)]
        for k in range(N):
            q.append(q[-1] + h[k] * qd[-1] + 0.5 * h[k] ** 2 * v[k])
            qd.append(qd[-1] + h[k] * v[k])
        return np.array(q), np.array(qd)

    before, after = [], []
    for i in range(len(qs)):
        q, _ = recursion(v0[i], h[i], qs[i])
        before.append(np.max(_p3_rows(p3, q)))
        q, qd = recursion(v1[i], h[i], qs[i])
        after.append(np.max(_p3_rows(p3, q)))
        np.testing.assert_allclose(q[-1], qg[i], atol=1e-10)
        np.testing.assert_allclose(qd[-1], 0.0, atol=1e-10)
    before, after = np.array(before), np.array(after)
    crossing = before > 0
    assert 40 <= crossing.sum() <= 120  # about 4 % of the pairs
    np.testing.assert_array_equal(v1[~crossing], v0[~crossing])
    assert np.mean(after[crossing] <= 0) >= 0.9  # 96 % of 4,096 pairs' crossings


@pytest.fixture(scope="module")
def serial3_repair():
    return jax.jit(jax.vmap(make_repair(robots.get("serial3"), W), in_axes=(0, None, 0, None, 0, 0)))


def test_repaired_plans_are_feasible_and_the_cheapest_time_scaling(serial3_repair):
    rng = np.random.default_rng(2)
    P = [_prediction(rng, scale) for scale in (0.3, 1.0, 0.0, 0.05, 0.5, 0.2)]
    qs, qg, v, h = (np.array([p[i] for p in P]) for i in range(4))
    z = jnp.zeros(n)
    r = serial3_repair(jnp.asarray(qs), z, jnp.asarray(qg), z, jnp.asarray(v), jnp.asarray(h))
    lim = robots.get("serial3").limits
    costs_checked = feasible = 0
    for i in range(len(P)):
        vi, hi = np.asarray(r.v[i]), np.asarray(r.h[i])
        chk = V.verify(qs[i], qg[i], vi, hi, weights=(1.0, 0.1, 0.0), tol=1e-9)
        # the goal to 1e-9 (rounding), every box to 1e-9 relative, unless the time scaling
        # ran into the period bound (then the remaining excess is the efforts')
        if not chk["ok"]:
            assert chk["goal_error"] <= 1e-9 and hi.max() == pytest.approx(float(lim.h_max), rel=1e-12)
            continue
        feasible += 1
        np.testing.assert_allclose(r.q[i], chk["q"], atol=1e-12)
        np.testing.assert_allclose(r.tau[i], chk["tau"], rtol=1e-9, atol=1e-9)
        assert float(r.cost[i]) == pytest.approx(chk["cost"], rel=1e-12)
        # the samples q_k are those of the projected prediction (time scaling keeps them) or
        # of its uniform-period twin
        # a uniform time scaling s(1 +- 1e-3) of the plan is either infeasible or dearer
        for f in (1 - 1e-3, 1 + 1e-3):
            hs = hi * f
            if hs.max() > float(lim.h_max) or hs.min() < float(lim.h_min):
                continue
            other = V.verify(qs[i], qg[i], vi / f**2, hs, weights=(1.0, 0.1, 0.0), tol=1e-9)
            assert not other["ok"] or other["cost"] >= chk["cost"] - 1e-12
            costs_checked += other["ok"]
    assert feasible >= 4 and costs_checked >= 1  # a time scaling set by the cost


def test_the_repair_returns_the_cheapest_feasible_scaled_candidate():
    """The planner's repair (the projected prediction and the switching profiles on both
    periods), candidate by candidate: each rebuilt from the public functions, its time
    scaling from the module doc's formulas on Pinocchio's efforts (jtraj_peers.verify),
    the scaled plan verified; the repair returns the feasible one of least verified
    cost, with that cost. Predictions: noisy cycloids, and the repaired plans again with
    periods perturbed by up to 10 % (closer to the switching shape: other winners)."""
    rb = robots.get("serial3")
    lim = rb.limits
    tau_max, qd_max, qdd_max = (np.asarray(x, float) for x in (lim.tau_max, lim.qd_max, lim.qdd_max))
    h_min, h_max = float(lim.h_min), float(lim.h_max)
    rep = make_repair(rb, W, effort=False, uniform_projection=False, trapezoid=False)  # (trapezoid: its own tests)
    assert rep.candidates == ("projected", "switch", "switch_uniform")
    batch = jax.jit(jax.vmap(rep, in_axes=(0, None, 0, None, 0, 0)))
    z = jnp.zeros(n)

    def reference(qs, qg, v, h):
        """The verified cost of each candidate's scaled plan (inf where infeasible)."""
        hc = np.clip(h, h_min, h_max)
        cands = [(np.asarray(goal_projection(qs, z, qg, z, v, hc)), hc)]
        for hh in (hc, np.full(N, hc.mean())):
            w = switch_profile(jnp.asarray(qs), z, jnp.asarray(qg), jnp.asarray(hh))
            cands.append((np.asarray(goal_projection(qs, z, qg, z, w, hh)), hh))
        costs = []
        for vk, hk in cands:
            u = V.verify(qs, qg, vk, hk, weights=(1.0, 0.1, 0.0), tol=np.inf)  # unscaled
            s_f = max(np.max(np.abs(u["qd"]) / qd_max), np.sqrt(np.max(np.abs(vk) / qdd_max)),
                      np.sqrt(np.max(np.abs(u["tau"]) / tau_max))) * (1 + 1e-12)
            A = float(W.time) * hk.sum()
            B = float(W.energy) * np.sum(hk * np.sum((u["tau"] / tau_max) ** 2, axis=1))
            s_opt = (3 * B / A) ** 0.25  # the minimiser of A s + B / s^3
            s = min(max(s_opt, s_f, np.max(h_min / hk)), np.min(h_max / hk))
            chk = V.verify(qs, qg, vk / s**2, hk * s, weights=(1.0, 0.1, 0.0), tol=1e-9)
            costs.append(chk["cost"] if chk["ok"] else np.inf)
        return np.array(costs)

    rng = np.random.default_rng(5)
    P = [_prediction(rng, scale) for scale in (0.3, 1.0, 0.0, 0.05, 0.5, 0.2, 0.1, 0.7)]
    qs, qg, v, h = (np.array([p[i] for p in P]) for i in range(4))
    r = batch(jnp.asarray(qs), z, jnp.asarray(qg), z, jnp.asarray(v), jnp.asarray(h))
    v2, h2 = np.asarray(r.v), np.asarray(r.h) * rng.uniform(0.9, 1.1, h.shape)
    chosen = set()
    for v, h in ((v, h), (v2, h2)):
        r = batch(jnp.asarray(qs), z, jnp.asarray(qg), z, jnp.asarray(v), jnp.asarray(h))
        for i in range(len(P)):
            costs = reference(qs[i], qg[i], v[i], h[i])
            best = int(np.argmin(costs))
            assert np.isfinite(costs[best])
            assert int(r.candidate[i]) == best
            assert float(r.cost[i]) == pytest.approx(costs[best], rel=1e-12)
            chosen.add(best)
    assert chosen == {0, 1, 2}  # every candidate wins somewhere


def test_repair_of_an_optimum_keeps_it():
    # an optimal trajectory (time scaling at its cost minimum, on the goal) is a fixed
    # point up to the active bounds' rounding: cost and time within 1e-6
    rb = robots.get("serial3")
    rep = jax.jit(make_repair(rb, W))
    rng = np.random.default_rng(3)
    qs, qg, v, h = _prediction(rng, 0.3)
    z = jnp.zeros(n)
    r1 = rep(jnp.asarray(qs), z, jnp.asarray(qg), z, jnp.asarray(v), jnp.asarray(h))
    r2 = rep(jnp.asarray(qs), z, jnp.asarray(qg), z, r1.v, r1.h)
    assert float(r2.cost) == pytest.approx(float(r1.cost), rel=1e-9)
    assert float(r2.scale) == pytest.approx(1.0, abs=1e-9)


def test_non_homogeneous_robot_takes_the_cheapest_feasible_grid_scaling():
    rb = robots.get("serial3_vertical", h_max=0.3)
    rep = jax.jit(make_repair(rb, W, grid=16))
    rng = np.random.default_rng(4)
    qs, qg, v, h = _prediction(rng, 0.5)
    z = jnp.zeros(n)
    r = rep(jnp.asarray(qs), z, jnp.asarray(qg), z, jnp.asarray(v), jnp.asarray(h))
    q, qd = _recursion(qs, z, np.asarray(r.v), np.asarray(r.h))
    np.testing.assert_allclose(q[-1], qg, atol=1e-10)
    np.testing.assert_allclose(qd[-1], 0.0, atol=1e-10)
    tau = np.asarray(jax.vmap(rb.inverse_dynamics)(jnp.asarray(q[:-1]), jnp.asarray(qd[:-1]), r.v))
    lim = rb.limits
    assert np.max(np.abs(tau) / np.asarray(lim.tau_max)) <= 1 + 1e-9
    assert np.max(np.abs(qd) / np.asarray(lim.qd_max)) <= 1 + 1e-9
    assert np.max(np.abs(np.asarray(r.v)) / np.asarray(lim.qdd_max)) <= 1 + 1e-9
    assert float(lim.h_min) - 1e-12 <= np.min(np.asarray(r.h)) and np.max(np.asarray(r.h)) <= float(lim.h_max) + 1e-12
    assert float(r.cost) == pytest.approx(float(cost_of(rb, W, jnp.asarray(q), jnp.asarray(qd), jnp.asarray(tau),
                                                        r.h)), rel=1e-9)


def test_efforts_polynomial_in_the_rate_give_the_scaling_of_efforts_evaluated_at_every_grid_point():
    # serial3_vertical (gravity, drive damping): the efforts of tau(q, qd / s, v / s^2) are a
    # quadratic in 1 / s; the repair's grid from that polynomial picks the candidate, the
    # scaling and the plan of the grid with the inverse dynamics run at every point. Tighter
    # effort bounds and a larger energy weight put the cheapest scalings inside the feasible
    # range, where the efforts set them (efforts 5 % off in their 1 / s^2 term change picks)
    tau_max = 0.6 * np.asarray(robots.get("serial3_vertical").limits.tau_max)
    rb = robots.get("serial3_vertical", h_max=0.3, tau_max=tau_max)
    assert not is_homogeneous(rb) and is_quadratic_in_rate(rb)
    w = Weights(time=1.0, energy=3.0)
    poly = jax.jit(make_repair(rb, w, grid=128))
    evaluated = jax.jit(make_repair(rb, w, grid=128, quadratic=False))
    rng = np.random.default_rng(5)
    z = jnp.zeros(n)
    scales = []
    for _ in range(8):
        qs, qg, v, h = (jnp.asarray(a) for a in _prediction(rng, 0.5))
        a, b = poly(qs, z, qg, z, v, h), evaluated(qs, z, qg, z, v, h)
        assert int(a.candidate) == int(b.candidate)
        np.testing.assert_allclose(float(a.scale), float(b.scale), rtol=1e-12)
        for x, y in zip((a.v, a.h, a.tau, a.cost), (b.v, b.h, b.tau, b.cost)):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-9, atol=1e-9)
        scales.append(float(a.scale))
    assert len(set(scales)) > 1  # not one scaling for all (the grid is exercised)
    # a smoothed Coulomb friction is not a polynomial in the rate: the repair evaluates
    from jtraj.robots import Friction

    args = ((1.0, 0.8, 0.45), (10.0, 8.0, 4.0), (9.23, 7.5, 5.21))
    coulomb = robots.serial_planar(*args, gravity=9.81, friction=Friction(jnp.full(3, 0.2), jnp.full(3, 0.5)))
    viscous = robots.serial_planar(*args, gravity=9.81, friction=Friction(jnp.full(3, 0.2), jnp.zeros(3)))
    assert not is_quadratic_in_rate(coulomb) and is_quadratic_in_rate(viscous)


def test_time_scaling_with_gravity_is_the_cheapest_feasible_one_to_the_second_grids_step():
    # serial3_vertical (gravity, drive damping: the efforts' polynomial in 1 / s), one
    # candidate (the projected prediction): the repair's scaling against a brute-force
    # search over 6,000 scalings of the period box, each plan by the recursion written out
    # and its efforts by the inverse dynamics. The repair's cost is within twice the second
    # grid's step of the cheapest feasible one found, and the first grid's points alone
    # miss it by more than that on most pairs (so the test tells the two apart)
    rb = robots.get("serial3_vertical", h_max=0.3)
    lim = rb.limits
    G = 32
    rep = jax.jit(make_repair(rb, W, grid=G, switch=False, effort=False, uniform_projection=False, trapezoid=False))
    ID = jax.jit(jax.vmap(jax.vmap(rb.inverse_dynamics)))
    cost = jax.jit(jax.vmap(lambda q, qd, tau, h: cost_of(rb, W, q, qd, tau, h)))
    rng = np.random.default_rng(7)
    z = jnp.zeros(n)
    first_grid_misses = 0
    for _ in range(6):
        qs, qg, v, h = _prediction(rng, 0.5)
        r = rep(jnp.asarray(qs), z, jnp.asarray(qg), z, jnp.asarray(v), jnp.asarray(h))
        w = np.asarray(goal_projection(jnp.asarray(qs), z, jnp.asarray(qg), z, jnp.asarray(v), jnp.asarray(h)))
        lo, hi = np.max(float(lim.h_min) / h), np.min(float(lim.h_max) / h)

        def costs(ss):  # the cost of each scaled plan, inf where it breaks a bound
            S = len(ss)
            hs, vs = h[None] * ss[:, None], w[None] / ss[:, None, None] ** 2  # (S, N), (S, N, n)
            q, qd = [np.broadcast_to(qs, (S, n))], [np.zeros((S, n))]
            for k in range(N):  # the recursion written out, all scalings at once
                q.append(q[-1] + hs[:, k, None] * qd[-1] + 0.5 * hs[:, k, None] ** 2 * vs[:, k])
                qd.append(qd[-1] + hs[:, k, None] * vs[:, k])
            q, qd = np.stack(q, axis=1), np.stack(qd, axis=1)
            tau = np.asarray(ID(jnp.asarray(q[:, :-1]), jnp.asarray(qd[:, :-1]), jnp.asarray(vs)))
            ok = ((np.max(np.abs(tau) / np.asarray(lim.tau_max), axis=(1, 2)) <= 1)
                  & (np.max(np.abs(qd) / np.asarray(lim.qd_max), axis=(1, 2)) <= 1)
                  & (np.max(np.abs(vs) / np.asarray(lim.qdd_max), axis=(1, 2)) <= 1))
            c = np.asarray(cost(jnp.asarray(q), jnp.asarray(qd), jnp.asarray(tau), jnp.asarray(hs)))
            return np.where(ok, c, np.inf)

        best = np.min(costs(np.exp(np.linspace(np.log(lo), np.log(hi), 6000))))
        assert np.isfinite(best)
        step2 = (hi / lo) ** (2 / (G - 1) ** 2)  # the second grid's step
        assert best * (1 - 1e-3) <= float(r.cost) <= best * (1 + 2 * (step2 - 1))
        first = np.min(costs(np.exp(np.linspace(np.log(lo), np.log(hi), G))))
        first_grid_misses += first > best * (1 + 2 * (step2 - 1))
    assert first_grid_misses >= 3  # (measured: 6 of 6, by 3 % to 12 %, with the repair within 0.3 % to 0.7 %)


def test_trapezoid_profile_is_the_least_time_synchronised_trapezoid_within_the_bounds():
    # against a brute-force search over 20,000 shares f of the acceleration phase, the
    # time of the synchronised trapezoid written out per joint, and the closed form of a
    # single joint's time-optimal profile (D / V + V / A, or 2 sqrt(D / A) for a triangle)
    N = 40
    V, A = np.array([2.0, 1.5, 3.0]), np.array([10.0, 4.0, 20.0])
    prof = jax.jit(lambda q0, q1: trapezoid_profile(q0, q1, N, jnp.asarray(V), jnp.asarray(A)))
    rng = np.random.default_rng(3)
    for D in [rng.uniform(-2, 2, 3) for _ in range(5)] + [np.array([1.5, 0.0, 0.0]), np.array([0.0, 0.1, 0.0])]:
        q0 = rng.uniform(-1, 1, 3)
        v, h = (np.asarray(x) for x in prof(jnp.asarray(q0), jnp.asarray(q0 + D)))
        T = float(np.sum(h))
        f = np.linspace(1e-4, 0.5, 20000)[:, None]
        best = np.min(np.max(np.maximum(np.abs(D) / ((1 - f) * V), np.sqrt(np.abs(D) / (f * (1 - f) * A))), axis=1))
        assert best * (1 - 1e-12) <= T <= best * (1 + 0.02)  # (the profile's 32 shares against the search's 20,000)
        assert np.allclose(h, T / N, rtol=1e-14)
        q, qd = _recursion(q0, np.zeros(3), v, h)
        assert np.max(np.abs(v) / A) <= 1 + 1e-12 and np.max(np.abs(qd) / V) <= 1 + 1e-12
        np.testing.assert_allclose(qd[-1], 0.0, atol=1e-12)  # rest to rest
        np.testing.assert_allclose(q[-1], q0 + D, atol=0.05 * np.max(np.abs(D)))  # near the goal (projection: exact)
        moving = np.abs(D) > 0
        if moving.sum() == 1:  # one joint: its time-optimal profile
            j = int(np.flatnonzero(moving)[0])
            d = abs(D[j])
            exact = d / V[j] + V[j] / A[j] if d >= V[j] ** 2 / A[j] else 2 * np.sqrt(d / A[j])
            assert exact * (1 - 1e-12) <= T <= exact * 1.02
    v, h = prof(jnp.zeros(3), jnp.zeros(3))  # no motion: a zero profile, finite periods
    assert np.all(np.asarray(v) == 0) and np.all(np.isfinite(np.asarray(h)))


def test_trapezoid_candidate_gives_velocity_bounded_plans_their_time():
    # a robot whose efforts never bind (serial3 with 100x its effort bounds and a low
    # velocity bound, no energy weight): the optimum is the motion of the velocity and acceleration bounds. With the
    # trapezoid the repaired plan's time is within 3 % of the least synchronised
    # trapezoid's (the time scaling then meets a bound); without it, the projected
    # prediction and the switching profiles are slower on these pairs
    rb = robots.get("serial3", tau_max=100 * np.asarray(robots.get("serial3").limits.tau_max), qd_max=0.8, h_max=0.2)
    lim = rb.limits
    w = Weights(time=1.0, energy=0.0)
    on = jax.jit(make_repair(rb, w, effort=False, uniform_projection=False))
    off = jax.jit(make_repair(rb, w, effort=False, uniform_projection=False, trapezoid=False))
    assert on.candidates[-1] == "trapezoid" and "trapezoid" not in off.candidates
    with pytest.raises(ValueError, match="qd_max and qdd_max"):
        make_repair(robots.serial_planar((1.0, 1.0), (1.0, 1.0), (0.1, 0.1)), w, trapezoid=True)
    rng = np.random.default_rng(9)
    z = jnp.zeros(n)
    slower = 0
    for _ in range(6):
        qs, _, v, h = (jnp.asarray(a) for a in _prediction(rng, 0.5))
        qg = qs + jnp.asarray(rng.choice([-1, 1], n) * rng.uniform(1.0, 2.0, n))  # long: the velocity bound binds
        a, b = on(qs, z, qg, z, v, h), off(qs, z, qg, z, v, h)
        D = np.abs(np.asarray(qg - qs))
        f = np.linspace(1e-4, 0.5, 20000)[:, None]
        V, A = np.broadcast_to(np.asarray(lim.qd_max), (n,)), np.broadcast_to(np.asarray(lim.qdd_max), (n,))
        best = np.min(np.max(np.maximum(D / ((1 - f) * V), np.sqrt(D / (f * (1 - f) * A))), axis=1))
        assert float(a.cost) <= float(b.cost) * (1 + 1e-12)
        assert best * (1 - 0.03) <= float(jnp.sum(a.h)) <= best * 1.03
        slower += float(jnp.sum(b.h)) > best * 1.2
    assert slower >= 3  # (measured: 6 of 6, 1.3x to 1.6x)


@pytest.mark.parametrize("name, bound", [("serial3", 4.0), ("serial3_vertical", 20.0)])  # closed form, grids
def test_repaired_plans_keep_the_acceleration_jumps_within_a_jerk_bound(name, bound):
    # a jerk bound tight enough to set the time scaling: every repaired plan keeps each
    # jump |v_{k+1} - v_k| within qddd_max (h_k + h_{k+1}) / 2 (jtraj.Problem's rows,
    # written out here), and is slower than without the bound
    base = robots.get(name, h_max=0.3)
    rb = robots.get(name, h_max=0.3, qddd_max=bound)
    loose = jax.jit(make_repair(base, W, effort=False, uniform_projection=False))
    tight = jax.jit(make_repair(rb, W, effort=False, uniform_projection=False))
    rng = np.random.default_rng(12)
    z = jnp.zeros(n)
    slower = 0
    for _ in range(6):
        qs, qg, v, h = (jnp.asarray(a) for a in _prediction(rng, 0.5))
        a, b = tight(qs, z, qg, z, v, h), loose(qs, z, qg, z, v, h)
        va, ha = np.asarray(a.v), np.asarray(a.h)
        jumps = np.abs(np.diff(va, axis=0)) / (bound * 0.5 * (ha[1:] + ha[:-1]))[:, None]
        assert np.max(jumps) <= 1 + 1e-9
        q, qd = _recursion(np.asarray(qs), np.zeros(n), va, ha)
        np.testing.assert_allclose(q[-1], np.asarray(qg), atol=1e-10)
        vb, hb = np.asarray(b.v), np.asarray(b.h)
        slower += np.max(np.abs(np.diff(vb, axis=0)) / (bound * 0.5 * (hb[1:] + hb[:-1]))[:, None]) > 1.01
        assert float(jnp.sum(a.h)) >= float(jnp.sum(b.h)) * (1 - 1e-12)
    assert slower >= 3  # the loose plans break the bound: it is what sets the tight ones' time


def test_coverage_radius_and_distances_by_brute_force():
    rng = np.random.default_rng(5)
    starts = rng.uniform(-1, 1, (30, 3))
    steps = rng.uniform(-0.5, 0.5, (30, 3))
    steps[:, 2] = 0.25  # a constant feature keeps span 1
    pairs = np.c_[starts, starts + steps]
    F = np.c_[starts, steps]  # the features, written out
    lo, span = F.min(0), np.where(np.ptp(F, 0) > 0, np.ptp(F, 0), 1.0)
    A = (F - lo) / span
    D = np.linalg.norm(A[:, None] - A[None], axis=2)
    np.fill_diagonal(D, np.inf)
    assert coverage.radius(pairs) == pytest.approx(D.min(1).max(), rel=1e-12)
    assert coverage.radius(pairs, chunk=7) == pytest.approx(D.min(1).max(), rel=1e-12)
    dist = coverage.distance_fn(pairs)
    x = np.r_[starts[0] + 0.01, starts[0] + 0.01 + steps[0]]
    u = (np.r_[x[:3], x[3:] - x[:3]] - lo) / span
    near, box = dist(jnp.asarray(x))
    assert float(near) == pytest.approx(np.linalg.norm(u - A, axis=1).min(), rel=1e-7)
    assert float(box) == pytest.approx(np.linalg.norm(np.maximum(np.maximum(-u, u - 1), 0)), abs=1e-12)
    near, box = dist(jnp.asarray(pairs[4]))
    assert float(near) == pytest.approx(0.0, abs=1e-7) and float(box) <= 1e-12
    # a step longer than any training step lies outside the box, from a training start
    i = int(np.argmax(steps[:, 0]))
    long = np.r_[starts[i], starts[i] + steps[i] + 0.4 * np.r_[1, 0, 0]]
    assert float(dist(jnp.asarray(long))[1]) == pytest.approx(0.4 / span[3], rel=1e-9)
    boxd = coverage.box_distance_fn(lo, span)
    assert float(boxd(jnp.asarray(lo))[1]) == 0.0
    assert float(boxd(jnp.asarray(lo - span))[1]) == pytest.approx(np.sqrt(6), rel=1e-12)
    # more pairs than one block of the search (coverage.BLOCK), the last block partial
    P = 3 * coverage.BLOCK + 5
    starts, steps = rng.uniform(-1, 1, (P, 3)), rng.uniform(-0.5, 0.5, (P, 3))
    F = np.c_[starts, steps]
    lo, span = F.min(0), np.ptp(F, 0)
    A = (F - lo) / span
    dist = jax.jit(jax.vmap(coverage.distance_fn(np.c_[starts, starts + steps])))
    X = np.c_[starts, starts + steps][rng.integers(0, P, 40)] + rng.normal(0.0, 0.1, (40, 6))
    U = (np.c_[X[:, :3], X[:, 3:] - X[:, :3]] - lo) / span
    near = np.asarray(dist(jnp.asarray(X))[0])
    np.testing.assert_allclose(near, np.linalg.norm(U[:, None] - A[None], axis=2).min(1), rtol=1e-7)


@pytest.fixture(scope="module")
def planner_and_data():
    from jtraj import mappings
    from jtraj.online import Planner

    data = mappings.synthetic_dataset(P=24, N=10, seed=0)
    model = mappings.train_mapping(data, "plan", n_rules=2, epochs=2)[0]
    # the synthetic trajectories take 3 s over 10 periods: a period bound that admits them
    return Planner(model, robots.get("serial3", h_max=1.5), weights=W), data


def test_planner_batch_plans_re_verified(planner_and_data, tmp_path):
    planner, data = planner_and_data
    qs, qg = data["q_start"][:8], data["q_goal"][:8]
    pb = planner.plan(qs, qg)
    assert pb.q.shape == (8, 11, 3) and pb.h.shape == (8, 10)
    ok = planner.feasible(pb)
    assert ok.shape == (8,) and ok.all()
    for i in range(8):
        chk = V.verify(qs[i], qg[i], np.asarray(pb.v[i]), np.asarray(pb.h[i]), h_max=1.5,
                       weights=(1.0, 0.1, 0.0), tol=1e-9)
        assert chk["ok"], chk["max_rel_violation"]
        assert float(pb.cost[i]) == pytest.approx(chk["cost"], rel=1e-12)
        assert float(pb.violation[i]) <= 1e-9 and float(pb.goal_error[i]) <= 1e-9
        # one query equals its row of the batch
        p1 = planner.plan(qs[i], qg[i])
        np.testing.assert_allclose(np.asarray(p1.v), np.asarray(pb.v[i]), rtol=1e-12, atol=1e-12)
    # a batch larger than the chunk runs as calls of the chunk's size (the program above),
    # the last one padded: the same plans
    planner.chunk = 8
    try:
        pc = planner.plan(np.r_[qs, qs[:5]], np.r_[qg, qg[:5]])
    finally:
        planner.chunk = 256
    assert pc.v.shape == (13, 10, 3)
    np.testing.assert_array_equal(pc.v, np.r_[pb.v, pb.v[:5]])
    np.testing.assert_array_equal(pc.cost, np.r_[pb.cost, pb.cost[:5]])
    # without the switching candidates: feasible too, never cheaper (fewer candidates)
    from jtraj.online import Planner

    fewer = Planner(planner.model, planner.robot, weights=W, switch=False).plan(qs, qg)
    assert planner.feasible(fewer).all()
    assert np.all(np.asarray(fewer.cost) >= np.asarray(pb.cost) * (1 - 1e-12))
    # each plan names the repair's candidate it is: the one of the repair run alone on the
    # model's prediction, whose plan it returns
    from jtraj.repair import make_repair

    rep = make_repair(planner.robot, W, effort=False, uniform_projection=False)
    assert planner.candidates == rep.candidates
    predict = planner._predict()
    for i in range(8):
        _, _, v, h = predict(jnp.asarray(qs[i]), jnp.asarray(qg[i]))
        z = jnp.zeros(n)
        r = rep(jnp.asarray(qs[i]), z, jnp.asarray(qg[i]), z, v, h)
        assert int(pb.candidate[i]) == int(r.candidate)
        np.testing.assert_allclose(np.asarray(pb.v[i]), np.asarray(r.v), rtol=1e-12, atol=1e-12)
    assert planner.report(planner.plan(qs[0], qg[0]))["candidate"] == planner.candidates[int(pb.candidate[0])]
    # the raw prediction misses the goal: the repair is what lands on it
    assert float(np.median(np.asarray(pb.predicted_goal_error))) > 1e-3
    # coverage: training pairs lie at distance 0, far queries are flagged
    assert np.all(np.asarray(pb.coverage_distance)[:5] <= 1e-7) and not np.asarray(pb.ood)[:5].any()
    far = planner.plan(qs[0] + 2.5, qg[0])
    assert bool(far.ood) and float(far.coverage_box) > 0
    out = planner.query(qs[0], qg[0])
    assert out["feasible"] and out["coverage"]["kind"] == "nearest training pair"
    assert json.loads(json.dumps(out))["cost"] == pytest.approx(float(pb.cost[0]), rel=1e-12)


@pytest.mark.slow  # two more programs; plan()'s fields are re-verified in the test above
def test_packed_plan_equals_the_jitted_plan(planner_and_data):
    """plan() returns through one packed buffer: field by field the jitted Plan's, dtypes
    and shapes kept, for one pair and for a batch."""
    planner, data = planner_and_data
    qs, qg = data["q_start"][:8], data["q_goal"][:8]
    for packed, direct in ((planner.plan(qs, qg), planner._plan_batch(jnp.asarray(qs), jnp.asarray(qg))),
                           (planner.plan(qs[0], qg[0]), planner._plan(jnp.asarray(qs[0]), jnp.asarray(qg[0])))):
        for name, a, b in zip(packed._fields, packed, direct):
            assert isinstance(a, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape, name
            np.testing.assert_array_equal(a, np.asarray(b), err_msg=name)


def test_query_command_prints_and_writes_cost_violation_and_coverage(planner_and_data, tmp_path, capsys):
    from jtraj.commands import query as cmd

    planner, data = planner_and_data
    planner.model.save(tmp_path / "plan.anfis")
    qs, qg = data["q_start"][1], data["q_goal"][1]
    for label, start, flagged in (("in", qs, False), ("far", qs + 2.5, True)):
        args = type("A", (), dict(model=str(tmp_path / "plan.anfis"), periods=None, start=list(start),
                                  goal=list(qg), refine=False, warm="primal", json=str(tmp_path / f"{label}.json")))
        assert cmd.run(args) == 0
        text = capsys.readouterr().out
        with open(args.json) as f:
            out = json.load(f)
        assert ("OUT OF DISTRIBUTION" in text) == flagged == out["out_of_distribution"]
        assert "cost" in text and "worst violation" in text
        assert out["candidate"] in planner.candidates and f"the repair's {out['candidate']} candidate" in text
        # the model's robot (serial3, h_max 0.1): the plan lands on the goal whatever its bounds
        assert out["goal_error"] <= 1e-9 and len(out["v"]) == 10 and len(out["tau"]) == 10
        assert out["feasible"] == (out["violation"] <= 1e-6)


def test_planner_refuses_bad_input(planner_and_data):
    from jtraj.online import Planner

    planner, data = planner_and_data
    with pytest.raises(ValueError, match="q_start must be finite"):
        planner.plan([np.nan, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match="q_goal must have shape"):
        planner.plan([0, 0, 0], [0, 0])
    with pytest.raises(ValueError, match="q_start and q_goal must both have shape"):
        planner.plan(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="q_start and q_goal must both have shape"):
        planner.plan(np.zeros((2, 2, 3)), np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match="do not match robot"):
        Planner(planner.model, robots.get("ibm7535"))
    # a robot of the same shape but another name, weights other than the model's
    with pytest.raises(ValueError, match="robot: the model was trained on optima of robot 'serial3'"):
        Planner(planner.model, robots.get("serial3_vertical"))
    recorded = planner.model.with_metadata(weights="time=1,energy=0.1")
    with pytest.raises(ValueError, match="weights: the model was trained on optima for weights 'time=1,energy=0.1'"):
        Planner(recorded, planner.robot, weights=Weights(time=1.0, energy=0.5))
    assert float(Planner(recorded, planner.robot, weights=Weights(time=1.0, energy=0.1)).weights.energy) == 0.1
    assert float(Planner(recorded, planner.robot).weights.energy) == 0.1
    with pytest.raises(ValueError, match="correct must be"):
        Planner(planner.model, correct="yes")
    with pytest.raises(ValueError, match="effort must be"):
        Planner(planner.model, effort=1)
    with pytest.raises(ValueError, match="projection must be"):
        Planner(planner.model, projection=None)
    with pytest.raises(ValueError, match="trapezoid must be"):
        Planner(planner.model, trapezoid="yes")
    with pytest.raises(ValueError, match="positions must be"):
        Planner(planner.model, positions=1)
    with pytest.raises(ValueError, match="no candidate"):
        Planner(planner.model, projection=False, switch=False, trapezoid=False)


@pytest.mark.slow
def test_a_feasible_plan_never_beats_the_exact_optimum_and_its_cost_is_the_solvers():
    """The plan is feasible for the exact problem, so its cost is at least the optimum's
    (up to the solver's tolerances); the plan's cost function equals the solver's at the
    optimum; query(refine=True) reports the gap between them."""
    from jtraj import Problem, solve
    from jtraj import mappings
    from jtraj.online import Planner

    data = mappings.synthetic_dataset(P=24, N=20, seed=0)
    model = mappings.train_mapping(data, "plan", n_rules=2, epochs=1)[0]
    rb = robots.get("serial3", h_max=0.2)  # the synthetic trajectories are slow: room to slow the plans
    planner = Planner(model, rb, weights=W)
    rng = np.random.default_rng(6)
    checked = 0
    for _ in range(3):
        qs = rng.uniform(-1, 1, n)
        qg = qs + rng.uniform(-0.4, 0.4, n)
        p = planner.plan(qs, qg)
        sol = solve(Problem(rb, qs, qg, N=20, weights=W))
        if not (bool(sol.converged) and planner.feasible(p)):
            continue
        checked += 1
        assert float(cost_of(rb, W, sol.q, sol.qd, sol.tau, sol.h)) == pytest.approx(float(sol.cost), rel=1e-12)
        assert float(p.cost) >= float(sol.cost) * (1 - 1e-5)
        out = planner.query(qs, qg, refine=True)
        assert out["refined_converged"] and out["gap"] == pytest.approx(
            (out["cost"] - out["refined_cost"]) / out["refined_cost"], rel=1e-12)
        assert out["gap"] >= -1e-5
    assert checked >= 2


def test_cumulative_sums_and_small_products_match_numpy():
    from jtraj._math import small_matmul as _mm
    from jtraj.repair import UNROLL, _cumsum

    rng = np.random.default_rng(11)
    for shape in ((20,), (20, 3), (7, 2, 3), (UNROLL + 5, 2)):
        x = rng.normal(size=shape)
        np.testing.assert_allclose(np.asarray(_cumsum(jnp.asarray(x))), np.cumsum(x, axis=0), rtol=1e-13, atol=1e-13)
    a, b, c = rng.normal(size=(2, 20)), rng.normal(size=(20, 3)), rng.normal(size=(4, 3, 5))
    np.testing.assert_allclose(np.asarray(_mm(jnp.asarray(a), jnp.asarray(b))), a @ b, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(np.asarray(_mm(jnp.asarray(c), jnp.asarray(c[0].T[None].repeat(4, 0)))),
                               c @ c[0].T, rtol=1e-13, atol=1e-13)


def test_repair_candidates_are_named_and_an_empty_set_refused():
    rb = robots.get("serial3")
    assert make_repair(rb, W).candidates == ("projected", "projected_uniform", "effort", "effort_uniform",
                                             "switch", "switch_uniform", "trapezoid")
    assert make_repair(rb, W, uniform_projection=False).candidates == ("projected", "effort", "effort_uniform",
                                                                       "switch", "switch_uniform", "trapezoid")
    assert make_repair(rb, W, effort=False, projection=False, trapezoid=False).candidates == (
        "projected_uniform", "switch", "switch_uniform")
    assert make_repair(rb, W, effort=False, projection=False, uniform_projection=False).candidates == (
        "switch", "switch_uniform", "trapezoid")
    assert make_repair(rb, W, effort=False, switch=False, projection=False, uniform_projection=False).candidates == (
        "trapezoid",)
    with pytest.raises(ValueError, match="no candidates"):
        make_repair(rb, W, effort=False, switch=False, projection=False, uniform_projection=False, trapezoid=False)
    for bad in (1, "on"):
        with pytest.raises(ValueError, match="positions must be None, True, False or 'flag'"):
            make_repair(rb, W, positions=bad)


@pytest.mark.slow  # one more repair program
def test_without_the_uniform_projection_the_repair_picks_among_the_others(serial3_repair):
    """A repair without the projection on uniform periods (the planner's): the same plan
    as the full repair wherever that one chose another candidate, never a cheaper one,
    and the chosen candidate named."""
    rb = robots.get("serial3")
    full = make_repair(rb, W)
    rep = make_repair(rb, W, uniform_projection=False)
    rng = np.random.default_rng(2)
    P = [_prediction(rng, scale) for scale in (0.3, 1.0, 0.0, 0.05, 0.5, 0.2)]
    qs, qg, v, h = (jnp.asarray(np.array([p[i] for p in P])) for i in range(4))
    z = jnp.zeros(n)
    a = serial3_repair(qs, z, qg, z, v, h)
    b = jax.jit(jax.vmap(rep, in_axes=(0, None, 0, None, 0, 0)))(qs, z, qg, z, v, h)
    for i in range(len(P)):
        name = full.candidates[int(a.candidate[i])]
        assert float(b.cost[i]) >= float(a.cost[i]) * (1 - 1e-12)
        if name != "projected_uniform":
            assert rep.candidates[int(b.candidate[i])] == name
            np.testing.assert_allclose(np.asarray(b.v[i]), np.asarray(a.v[i]), rtol=1e-12, atol=1e-12)
            assert float(b.cost[i]) == pytest.approx(float(a.cost[i]), rel=1e-12)
        assert bool(b.uniform[i]) == rep.candidates[int(b.candidate[i])].endswith("_uniform")


@pytest.mark.slow  # one more batched program
def test_planner_without_the_projection_plans_re_verified_and_never_cheaper(planner_and_data):
    """projection=False: feasible plans (re-verified), never cheaper than the default
    planner's (it chooses among a subset of the same candidates)."""
    from jtraj.online import Planner

    planner, data = planner_and_data
    other = Planner(planner.model, planner.robot, weights=W, projection=False)
    qs, qg = data["q_start"][:8], data["q_goal"][:8]
    pa, pb = planner.plan(qs, qg), other.plan(qs, qg)
    for i in range(8):
        chk = V.verify(qs[i], qg[i], np.asarray(pb.v[i]), np.asarray(pb.h[i]), h_max=1.5,
                       weights=(1.0, 0.1, 0.0), tol=1e-9)
        assert chk["ok"], chk["max_rel_violation"]
        assert float(pb.cost[i]) == pytest.approx(chk["cost"], rel=1e-12)
        assert float(pb.cost[i]) >= float(pa.cost[i]) * (1 - 1e-12)


def test_planner_on_the_panda_plans_re_verified_by_pinocchio():
    # a spatial arm with gravity (the repair's grid from the efforts' polynomial in 1 / s):
    # every plan re-simulated and its efforts from Pinocchio's RNEA of example-robot-data's
    # URDF (jtraj_peers/verify_arm.py), bounds (the jerk bound's too) and goal within 1e-9
    VA = pytest.importorskip("jtraj_peers.verify_arm")
    from jtraj import mappings
    from jtraj.online import Planner
    from jtraj_peers.casadi_rnea import panda_model

    data = mappings.synthetic_dataset(P=12, N=8, seed=0, robot="panda")
    model = mappings.train_mapping(data, "plan", n_rules=2, epochs=2)[0]
    # the synthetic trajectories take 3 s over 8 periods: a period bound that admits them
    rb = robots.get("panda", h_max=0.5)
    planner = Planner(model, rb, weights=W)
    qs, qg = data["q_start"], data["q_goal"]
    pb = planner.plan(qs, qg)
    assert pb.q.shape == (12, 9, 7) and pb.tau.shape == (12, 8, 7)
    assert planner.feasible(pb).all()
    lim = rb.limits
    kw = {k: np.asarray(getattr(lim, k)) for k in ("tau_max", "qd_max", "qdd_max", "q_min", "q_max")}
    pin_model = panda_model()
    scales = np.asarray(pb.scale)
    assert np.ptp(scales) > 0  # the time scaling is at work, not one scaling for all
    for i in range(len(qs)):
        chk = VA.verify(pin_model, qs[i], qg[i], pb.v[i], pb.h[i], h_min=float(lim.h_min), h_max=float(lim.h_max),
                        weights=(1.0, 0.1, 0.0), tol=1e-9, jerk_max=np.asarray(lim.qddd_max), **kw)
        assert chk["ok"] and "jerk" in chk["max_rel_violation"], chk["max_rel_violation"]
        np.testing.assert_allclose(pb.tau[i], chk["tau"], rtol=1e-9, atol=1e-9)
        assert float(pb.cost[i]) == pytest.approx(chk["cost"], rel=1e-12)


def test_repair_of_a_homogeneous_robot_with_a_joint_box():
    # serial3 (no gravity: the repair compares its candidates from the unscaled plans'
    # reductions) with a joint box that the goal leaves: the box term of the repaired
    # plan's violation against NumPy's, under the tests' rank promotion 'raise'
    import equinox as eqx

    from jtraj.repair import position_excess, violation

    base = robots.get("serial3")
    assert is_homogeneous(base)
    lo, hi = np.array([-3.0, -3.0, -3.0]), np.array([0.4, 3.0, 3.0])
    rb = eqx.tree_at(lambda r: (r.limits.q_min, r.limits.q_max), base, (jnp.asarray(lo), jnp.asarray(hi)),
                     is_leaf=lambda x: x is None)
    rep = jax.jit(make_repair(rb, Weights()))
    z = jnp.zeros(3)
    out = rep(z, z, jnp.array([0.5, 0.2, -0.3]), z, jnp.zeros((20, 3)), jnp.full(20, 0.1))
    q = np.asarray(out.q)
    expected = np.max(np.maximum(np.maximum(lo - q, q - hi) / (hi - lo), 0.0))
    assert expected >= 0.1 / 3.4 - 1e-12  # the goal's first joint 0.1 past a box 3.4 wide
    assert float(position_excess(rb, out.q)) == pytest.approx(expected, rel=1e-13)  # (no workspace box)
    assert float(violation(rb, out.q, out.qd, out.v, out.tau, out.h)) >= expected - 1e-15


def test_position_and_velocity_constraints_of_parallel_robots_enter_the_violation():
    # violation_parts against NumPy on hand-built motions: a parallel3 motion through the
    # workspace centre and out past its path constraints (a leg's reach), a Gough-Stewart
    # motion whose legs outrun their speed bound, a serial3 arm with a workspace box; the
    # box terms alone would call every one of them feasible
    import equinox as eqx

    from jtraj.repair import position_excess, rollout, violation_parts

    @eqx.filter_jit
    def motion(rb, q0, v, h):
        q, qd = rollout(q0, jnp.zeros_like(q0), v, h)
        tau = jax.vmap(rb.inverse_dynamics)(q[:-1], qd[:-1], v)
        return q, qd, violation_parts(rb, q, qd, v, tau, h)

    def parts(rb, q0, v, h):
        q, qd, vp = motion(rb, jnp.asarray(q0, float), jnp.asarray(v), jnp.asarray(h))
        return np.asarray(q), np.asarray(qd), [float(x) for x in vp]

    p3 = robots.get("parallel3")
    Nh = 8
    v = np.zeros((Nh, 2))
    v[: Nh // 2, 0], v[Nh // 2:, 0] = 2.0, -2.0  # rest to rest along x, far towards the box's edge
    q, qd, got = parts(p3, [0.0, 0.0], v, np.full(Nh, 0.15))
    path = np.stack([np.asarray(p3.path_constraints(jnp.asarray(x))) for x in q])
    box = np.max(np.maximum(np.maximum(-0.5 - q, q - 0.5) / 1.0, 0.0))
    expected = max(box, float(np.max(np.maximum(path, 0.0))))
    assert np.max(path) > 1e-3  # the motion leaves the path constraints
    assert got[3] == pytest.approx(expected, rel=1e-12)
    assert float(position_excess(p3, jnp.asarray(q))) == pytest.approx(expected, rel=1e-12)

    gs = robots.get("gough_stewart")
    q0 = 0.5 * (np.asarray(gs.limits.q_min) + np.asarray(gs.limits.q_max))  # the joint box's centre
    v = np.zeros((Nh, 6))
    v[: Nh // 2, 2], v[Nh // 2:, 2] = 4.0, -4.0  # a fast heave
    q, qd, got = parts(gs, q0, v, np.full(Nh, 0.06))
    g = np.stack([np.asarray(gs.velocity_constraints(jnp.asarray(a), jnp.asarray(b))) for a, b in zip(q[1:], qd[1:])])
    box = np.max(np.abs(qd[1:]) / np.asarray(gs.limits.qd_max)) - 1.0
    assert np.max(g) > 1e-3
    assert got[1] == pytest.approx(max(box, float(np.max(g)), 0.0), rel=1e-12)

    s3 = robots.get("serial3")
    ws = np.array([[0.5, -2.0], [2.5, 2.0]])
    s3w = eqx.tree_at(lambda r: r.limits.workspace, s3, jnp.asarray(ws), is_leaf=lambda x: x is None)
    v = np.zeros((Nh, 3))
    v[: Nh // 2, 0], v[Nh // 2:, 0] = 3.0, -3.0  # the first joint swings the tip up and in
    q, qd, got = parts(s3w, [0.0, 0.5, 0.5], v, np.full(Nh, 0.2))
    tip = np.stack([np.asarray(s3w.forward_kinematics(jnp.asarray(x))) for x in q])
    expected = np.max(np.maximum(np.maximum(ws[0] - tip, tip - ws[1]) / (ws[1] - ws[0]), 0.0))
    assert expected > 1e-3
    assert got[3] == pytest.approx(expected, rel=1e-12)


def test_planner_batch_runs_the_position_step_only_on_the_plans_it_flags():
    # a parallel3 batch runs the repair without the position step, flags the plans with
    # a candidate's path across a position row, and plans those again with the step: the
    # plans of the program that runs the step (a select) for every pair, bit for bit.
    # Pairs whose straight line passes a base point within the folded margin are flagged
    # (their trapezoid candidate crosses it); the single-plan program flags the same.
    from jtraj import mappings
    from jtraj.dataset.sampling import Distribution, sample_pairs
    from jtraj.online import Planner

    p3 = robots.get("parallel3")
    qs, qg = sample_pairs(p3, Distribution(), 2, 0, 512)
    t = np.clip(np.einsum("pbi,pi->pb", np.asarray(p3.base)[None] - qs[:, None], qg - qs)[..., None]
                / np.sum((qg - qs) ** 2, axis=1)[:, None, None], 0, 1)
    near = np.linalg.norm(qs[:, None] + t * (qg - qs)[:, None] - np.asarray(p3.base)[None], axis=-1).min(axis=1)
    margin = float(p3.rho_min) * 2 * float(p3.link_length)
    pick = np.r_[np.flatnonzero(near < 0.5 * margin)[:5], np.flatnonzero(near > 2 * margin)[:11]]
    assert len(pick) == 16
    qs, qg = qs[pick], qg[pick]
    data = mappings.synthetic_dataset(P=10, N=6, seed=0, robot="parallel3")
    model = mappings.train_mapping(data, "plan", n_rules=2, epochs=2)[0]
    planner = Planner(model, p3, weights=W)
    planner.chunk = planner.bend_chunk = 16  # (one compiled program with the step serves both)
    p = planner.plan(qs, qg)
    bent = np.asarray(p.bent)
    assert bent[:5].all() and 0 < bent.sum() < 16
    full = planner._unpack(np.asarray(planner._bend_batch(np.concatenate([qs, qg], axis=1))))
    for name in p._fields:
        np.testing.assert_array_equal(getattr(p, name), getattr(full, name), err_msg=name)
    for i in (0, 15):
        assert planner.report(planner.plan(qs[i], qg[i]))["bent"] is bool(bent[i])
    # without the step nothing is flagged, and the flagged plans cost no less with it unless
    # it made them feasible
    off = Planner(model, p3, weights=W, positions=False)
    off.chunk = 16
    po = off.plan(qs, qg)
    assert not np.asarray(po.bent).any() and off._bend_batch is None
    np.testing.assert_array_equal(po.v[~bent], p.v[~bent])
    assert np.all(np.asarray(p.q_violation)[bent] <= np.asarray(po.q_violation)[bent])


def test_planner_of_a_robot_with_lapack_calls_runs_its_chunks_on_one_thread():
    # a robot of a user's own whose dynamics solve with jnp.linalg (LAPACK on a CPU; the
    # built-in robots use jtraj.robots.small_solve), here parallel3 with its minimum-norm
    # torques through jnp.linalg.solve: jaxlib's CPU kernels do not survive on two threads
    # at once over large batches (the process hangs), so the planner finds the call in its
    # program and runs the chunks one after the other, with the plans of one call; a
    # planner without such calls keeps its threads. Its plans report the path constraints
    # (re-computed here).
    from jtraj import mappings
    from jtraj.online import Planner, _holds_custom_call
    from jtraj.robots.parallel3 import Parallel3

    class LapackParallel3(Parallel3):
        def generalized_to_actuator(self, q, Q):
            Ja = self.actuator_jacobian(q)
            return Ja @ jnp.linalg.solve(Ja.T @ Ja, Q)

    f = jax.jit(lambda A: jax.vmap(jnp.linalg.solve)(A, A[:, 0]))
    assert _holds_custom_call(f, np.ones((4, 2, 2)) + np.eye(2), ("lapack_",))
    assert not _holds_custom_call(jax.jit(jnp.sin), np.ones(3), ("lapack_",))
    data = mappings.synthetic_dataset(P=10, N=6, seed=0, robot="parallel3")
    model = mappings.train_mapping(data, "plan", n_rules=2, epochs=2)[0]
    base = robots.get("parallel3", h_max=1.0)
    rb = LapackParallel3.__new__(LapackParallel3)
    for field in dataclasses.fields(base):
        object.__setattr__(rb, field.name, getattr(base, field.name))
    qs, qg = data["q_start"], data["q_goal"]
    plain = Planner(model, base, weights=W)
    plain.plan(qs[:4], qg[:4])
    assert plain._serial is False  # the built-in parallel3 holds no LAPACK call
    planner = Planner(model, rb, weights=W)
    planner.chunk, planner.threads = 4, 2
    first = planner.plan(qs[:4], qg[:4])  # one call
    chunked = planner.plan(qs, qg)  # three calls of the same program
    assert planner._serial is True
    np.testing.assert_array_equal(chunked.v[:4], first.v)
    # calls from the user's threads take turns: the plans of the calls made one by one
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as pool:
        both = list(pool.map(lambda i: planner.plan(qs[4 * i:4 * i + 4], qg[4 * i:4 * i + 4]), range(2)))
    np.testing.assert_array_equal(np.r_[both[0].v, both[1].v], chunked.v[:8])
    q = np.asarray(chunked.q)
    path = np.max(np.maximum(np.asarray(jax.vmap(jax.vmap(rb.path_constraints))(q)), 0.0), axis=(1, 2))
    box = np.max(np.maximum(np.maximum(np.asarray(rb.limits.q_min) - q, q - np.asarray(rb.limits.q_max))
                            / (np.asarray(rb.limits.q_max) - np.asarray(rb.limits.q_min)), 0.0), axis=(1, 2))
    np.testing.assert_allclose(np.asarray(chunked.q_violation), np.maximum(path, box), rtol=1e-12, atol=1e-15)


def test_planner_refuses_a_robot_with_path_equalities():
    from jtraj import mappings
    from jtraj.online import Planner

    data = mappings.synthetic_dataset(P=8, N=6, seed=0, robot="wmr")
    model = mappings.train_mapping(data, "plan", n_rules=2, epochs=2)[0]
    with pytest.raises(ValueError, match="robot: 'wmr' has path equalities"):
        Planner(model, robots.get("wmr"), weights=W)
    Planner(model, robots.get("wmr"), weights=W, correct=False)  # the raw prediction is allowed
