"""Quick tests of the benchmark peers: the CasADi/IPOPT solver and the Pinocchio verifier."""

import numpy as np
import pytest

pytest.importorskip("casadi")
pytest.importorskip("pinocchio")


from jtraj_peers import ipopt_peer as P  # noqa: E402
from jtraj_peers import verify as V  # noqa: E402


@pytest.fixture(scope="module")
def solved():
    """Three benchmark pairs (seed 0) solved by IPOPT."""
    q0, q1 = P.benchmark_pairs(3, seed=0)
    return q0, q1, [P.solve_pair(a, b) for a, b in zip(q0, q1)]


def test_constants_agree():
    for name in ("LENGTHS", "MASSES", "INERTIAS", "TAU_MAX", "QD_MAX", "QDD_MAX", "H_MIN", "H_MAX"):
        assert getattr(P, name) == getattr(V, name), name
    assert P.CANONICAL_WEIGHTS == V.WEIGHTS


@pytest.mark.parametrize("masses", [None, (12.0, 5.0, 3.0)])
def test_pinocchio_matches_casadi_inverse_dynamics(masses):
    idf = P.inverse_dynamics_function(P.MASSES if masses is None else masses)
    rng = np.random.default_rng(0)
    for _ in range(50):
        q, qd, qdd = rng.uniform(-3, 3, (3, 3))
        tau_ca = np.array(idf(q, qd, qdd)).ravel()
        tau_pin = V.rnea(q, qd, qdd, masses)
        np.testing.assert_allclose(tau_pin, tau_ca, rtol=0, atol=1e-10)


def test_pinocchio_static_checks():
    """Hand-checkable cases: no gravity -> zero torque at rest; M_33 = m3 d3^2 + I3."""
    z = np.zeros(3)
    np.testing.assert_allclose(V.rnea([0.3, -1.0, 2.0], z, z), 0.0, atol=1e-14)
    tau = V.rnea([0.3, -1.0, 2.0], z, [0.0, 0.0, 1.0])
    assert tau[2] == pytest.approx(4.0 * 0.225**2 + 5.21, abs=1e-12)


def _cycloid(q_start, q_goal, T, N=20):
    """A continuous-time cycloid sampled with constant h (goal missed by discretisation)."""
    dq = np.asarray(q_goal) - np.asarray(q_start)
    t = np.arange(N) * T / N
    v = dq * (2 * np.pi / T**2) * np.sin(2 * np.pi * t / T)[:, None]
    return v, np.full(N, T / N)


def test_verify_catches_torque_violation(solved):
    q0, q1, res = solved
    r = res[0]
    # same goal reached exactly but with a torque spike: scale time down uniformly
    # (q_N is unchanged when v -> v / s^2, h -> s h) so the torques grow by 1/s^2
    s = 0.8
    c = V.verify(q0[0], q1[0], r["v"] / s**2, r["h"] * s, qdd_max=1e9, h_min=0.0)
    assert c["goal_error"] < 1e-6
    assert c["max_rel_violation"]["tau"] > 0.1
    assert not c["ok"]


def test_verify_catches_missed_goal(solved):
    q0, q1, res = solved
    r = res[1]
    c = V.verify(q0[1], q1[1] + np.array([0.0, 1e-4, 0.0]), r["v"], r["h"])
    assert c["goal_error"] == pytest.approx(1e-4, rel=1e-3)
    assert all(x <= 1e-6 for x in c["max_rel_violation"].values())
    assert not c["ok"]
    # a moving end state is a missed goal too
    v = r["v"].copy()
    v[-1] += 0.01
    assert not V.verify(q0[1], q1[1], v, r["h"])["ok"]


def test_verify_catches_box_violations():
    q0, q1 = np.zeros(3), np.array([0.2, -0.1, 0.1])
    v, h = _cycloid(q0, q1, T=2.0)
    c = V.verify(q0, q1, v, h, tol=1e-2)  # the sampled cycloid misses the goal a little
    assert c["max_rel_violation"]["tau"] == 0.0
    h_bad = h.copy()
    h_bad[3] = 0.2
    assert V.verify(q0, q1, v, h_bad)["max_rel_violation"]["h"] == pytest.approx(1.0)
    v_bad = v.copy()
    v_bad[5, 1] = 3.3
    assert V.verify(q0, q1, v_bad, h)["max_rel_violation"]["v"] == pytest.approx(0.1)


def test_ipopt_solutions_verified(solved):
    q0, q1, res = solved
    for a, b, r in zip(q0, q1, res):
        assert r["success"], r["status"]
        assert r["v"].shape == (20, 3) and r["h"].shape == (20,)
        assert r["q"].shape == (21, 3) and r["tau"].shape == (20, 3)
        assert r["seconds"] > 0 and r["iterations"] > 0
        c = V.verify(a, b, r["v"], r["h"], tol=1e-6)
        assert c["ok"], (c["goal_error"], c["max_rel_violation"])
        assert c["cost"] == pytest.approx(r["cost"], rel=1e-10)
        assert c["T"] == pytest.approx(r["T"], rel=1e-12)
        np.testing.assert_allclose(c["tau"], r["tau"], atol=1e-9)
        np.testing.assert_allclose(c["q"], r["q"], atol=1e-12)
    batch = V.verify_batch(q0, q1, [r["v"] for r in res], [r["h"] for r in res])
    assert batch["ok"].all() and batch["cost"].shape == (3,)


def test_warm_start_and_cycloidal_init(solved):
    q0, q1, res = solved
    r = res[2]
    warm = P.solve_pair(q0[2], q1[2], init=(r["v"], r["h"]))
    assert warm["success"] and warm["iterations"] < r["iterations"]
    # IPOPT's default tol (1e-8 on the scaled KKT error) leaves ~1e-4 relative slack in the
    # cost along this flat valley; the warm re-solve may only improve on the cold one.
    assert warm["cost"] <= r["cost"] * (1 + 1e-6)
    assert warm["cost"] == pytest.approx(r["cost"], rel=1e-3)
    v, h = P.cycloidal_init(np.zeros(3), np.zeros(3), 20)
    assert np.all(v == 0) and np.allclose(h, P.H_MIN)
    v, h = P.cycloidal_init(np.zeros(3), np.array([0.6, -0.3, 0.0]), 20)
    T = max(2 * 0.6 / 2.0, np.sqrt(2 * np.pi * 0.6 / 3.0))
    np.testing.assert_allclose(h, T / 20)
    assert v[0, 0] == 0.0 and v[5, 0] == pytest.approx(0.6 * 2 * np.pi / T**2)


def test_solve_many_two_processes(solved):
    q0, q1, res = solved
    out = P.solve_many(q0[:2], q1[:2], processes=2)
    assert len(out) == 2 and out.processes == 2 and out.wall_seconds > 0
    for r, ref in zip(out, res):
        assert r["success"]
        np.testing.assert_allclose(r["cost"], ref["cost"], rtol=1e-9)


def test_lifted_and_condensed_forms_reach_the_same_optimum(solved):
    """The two CasADi forms of the transcription (states as variables, or eliminated) are
    the same NLP after elimination: on pairs with one optimum they agree, each verified."""
    q0, q1, res = solved
    for i in (0, 1):
        c = P.solve_pair(q0[i], q1[i], formulation="condensed")
        assert c["strict_success"] and res[i]["strict_success"]
        # IPOPT's tol leaves ~1e-7 relative slack in the cost along flat directions
        assert c["cost"] == pytest.approx(res[i]["cost"], rel=1e-6)
        np.testing.assert_allclose(c["q"], res[i]["q"], atol=1e-4)
        assert V.verify(q0[i], q1[i], c["v"], c["h"], tol=1e-6)["ok"]
    with pytest.raises(ValueError, match="formulation"):
        P.solve_pair(q0[0], q1[0], formulation="sparse")
