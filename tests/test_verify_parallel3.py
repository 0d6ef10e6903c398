"""The independent parallel3 verifier (jtraj_peers/verify_parallel3.py: NumPy leg
kinematics, Pinocchio's RNEA per leg) against jtraj's robot and repair measures: its
restated data, its actuator torques, and its cost and violations on hand-built plans."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("pinocchio")

from jtraj import Weights, robots  # noqa: E402
from jtraj.repair import cost_of, goal_projection, rollout, trapezoid_profile, violation_parts  # noqa: E402
from jtraj_peers import verify_parallel3 as P  # noqa: E402

N = 20
#: (w_time, w_energy, w_kin): a kinetic weight, so that every term of the cost is compared
WEIGHTS = (1.0, 0.1, 0.05)


@pytest.fixture(scope="module")
def p3():
    return robots.get("parallel3")


@pytest.fixture(scope="module")
def measures(p3):
    """jtraj's states, efforts, cost and violation parts of a plan, from jtraj's rollout
    and inverse dynamics (one compiled program for every plan of N periods)."""
    W = Weights(time=WEIGHTS[0], energy=WEIGHTS[1], kinetic=WEIGHTS[2])

    @jax.jit
    def run(q0, v, h):
        q, qd = rollout(q0, jnp.zeros_like(q0), v, h)
        tau = jax.vmap(p3.inverse_dynamics)(q[:-1], qd[:-1], v)
        return q, qd, cost_of(p3, W, q, qd, tau, h), jnp.stack(violation_parts(p3, q, qd, v, tau, h))

    return lambda q0, v, h: [np.asarray(x) for x in run(jnp.asarray(q0), jnp.asarray(v), jnp.asarray(h))]


def _plan(q0, q1):
    """The trapezoid of jtraj's repair on N uniform periods, projected onto the goal at rest."""
    lim = robots.get("parallel3").limits
    q0, q1 = jnp.asarray(q0, float), jnp.asarray(q1, float)
    v, h = trapezoid_profile(q0, q1, N, lim.qd_max, lim.qdd_max)
    z = jnp.zeros(2)
    return np.asarray(goal_projection(q0, z, q1, z, v, h)), np.asarray(h)


def test_the_restated_robot_agrees_with_jtrajs(p3):
    lim = p3.limits
    np.testing.assert_allclose(P.BASE, np.asarray(p3.base), rtol=0, atol=1e-15)
    assert (P.LINK_LENGTH, P.LINK_MASS, P.LINK_COM, P.LINK_INERTIA) == (
        p3.link_length, p3.link_mass, p3.link_com, p3.link_inertia)
    assert (P.RHO_MIN, P.RHO_MAX) == (p3.rho_min, p3.rho_max)
    assert p3.gravity_accel == 0.0
    np.testing.assert_array_equal(P.TAU_MAX, np.asarray(lim.tau_max))
    np.testing.assert_array_equal(P.Q_MIN, np.asarray(lim.q_min))
    np.testing.assert_array_equal(P.Q_MAX, np.asarray(lim.q_max))
    np.testing.assert_array_equal(np.asarray(lim.workspace), [P.Q_MIN, P.Q_MAX])  # the same box
    np.testing.assert_array_equal(np.asarray(lim.qd_max), P.QD_MAX)
    np.testing.assert_array_equal(np.asarray(lim.qdd_max), P.QDD_MAX)
    assert (P.H_MIN, P.H_MAX) == (float(lim.h_min), float(lim.h_max))
    assert lim.qddd_max is None  # (the verifier has no jerk check)


def test_actuator_torques_agree_with_jtrajs_inverse_dynamics(p3):
    # 20 random states inside the box, every leg within rho/(2L) in [0.1, 0.95]; qd and qdd
    # up to 2x their bounds. Tolerance: 1e-9 relative to the largest torque (measured:
    # 3.3e-15; the two sides share nothing but the float64 arithmetic)
    assert jax.config.read("jax_enable_x64")
    rng = np.random.default_rng(0)
    inv = jax.jit(lambda q, qd, qdd: p3.inverse_dynamics(q, qd, qdd))
    count = 0
    while count < 20:
        q = rng.uniform(-0.5, 0.5, 2)
        s = P.leg_ratios(q)
        if not np.all((s >= 0.1) & (s <= 0.95)):
            continue
        count += 1
        qd, qdd = rng.uniform(-2.0, 2.0, 2), rng.uniform(-20.0, 20.0, 2)
        tau, ref = P.inverse_dynamics(q, qd, qdd), np.asarray(inv(q, qd, qdd))
        assert np.max(np.abs(tau - ref)) <= 1e-9 * np.max(np.abs(ref))
        # the actuated joints are jtraj's theta (mod 2 pi) and the second links' phi = theta + psi
        theta, phi = (np.asarray(x) for x in p3.leg_angles(jnp.asarray(q)))
        j = P.leg_joints(q)
        np.testing.assert_allclose(np.cos(j[:, 0] - theta), 1.0, atol=1e-14)
        np.testing.assert_allclose(np.cos(j[:, 0] + j[:, 1] - phi), 1.0, atol=1e-14)
        np.testing.assert_allclose(P.actuator_jacobian(q), np.asarray(p3.actuator_jacobian(jnp.asarray(q))),
                                   rtol=0, atol=1e-12)


def _bent(q0, q1, bump):
    """The plan of :func:`_plan` with ``bump`` (2,) added to its accelerations' first half
    and taken off their second, projected back onto the goal: its path bends sideways."""
    v, h = _plan(q0, q1)
    v = v + np.outer(np.where(np.arange(N) < N // 2, 1.0, -1.0), bump)
    z = jnp.zeros(2)
    return np.asarray(goal_projection(jnp.asarray(q0, float), z, jnp.asarray(q1, float), z, jnp.asarray(v),
                                      jnp.asarray(h))), h


def test_cost_and_violations_agree_with_jtrajs(measures):
    # jtraj's cost_of and violation_parts on jtraj's own rollout and inverse dynamics,
    # against the verifier's re-simulation: tolerance 1e-10 relative (atol 1e-14 for the
    # parts that are zero on both sides; measured: 2e-14 at most here, 1e-12 on a path
    # within 0.008 of a base point, where the two sides' closed forms of the leg angles
    # lose digits). jtraj measures the joint box relative to its width and the verifier
    # relative to its half-width; jtraj's one position part is the larger of the box's and
    # the legs' rows (the verifier's legs rows at the same samples 0..N, its box at 1..N).
    q0, q1 = np.array([-0.3, 0.2]), np.array([0.3, -0.3])
    v, h = _plan(q0, q1)  # the straight task at the kinematic bounds: torques 5.4x theirs
    cases = {"trapezoid": (q0, q1, v, h)}
    cases["slowed"] = (q0, q1, v / 2.5**2, h * 2.5)  # the same path, within every bound
    cases["hurried"] = (q0, q1, v / 0.1**2, h * 0.1)  # above the qd, v, h and tau bounds
    a, b = np.array([-0.45, -0.2]), np.array([-0.45, 0.2])
    cases["out of the box"] = (a, b, *_bent(a, b, [-40.0, 0.0]))  # out to x = -0.54
    a, b = np.array([-0.45, 0.40]), np.array([-0.05, 0.38])
    cases["past a base"] = (a, b, *_plan(a, b))  # within 0.043 of B_1 = (-0.25, 0.433)
    seen = set()
    for name, (a, b, va, ha) in cases.items():
        r = P.verify(a, b, va, ha, weights=WEIGHTS)
        q, qd, cost, parts = measures(a, va, ha)
        np.testing.assert_allclose(r["q"], q, rtol=0, atol=1e-14)
        np.testing.assert_allclose(r["qd"], qd, rtol=0, atol=1e-13)
        np.testing.assert_allclose(r["cost"], cost, rtol=1e-10, err_msg=name)
        m = r["max_rel_violation"]
        ours = [m["tau"], m["qd"], m["v"], max(m["legs"], m["q"] / 2), m["h"], 0.0]
        np.testing.assert_allclose(ours, parts, rtol=1e-10, atol=1e-14, err_msg=name)
        assert r["ok"] == (np.max(parts) <= 1e-6 and r["goal_error"] <= 1e-6), name
        seen |= {k for k, x in m.items() if x > 0}
        print(f"{name}: ok {r['ok']}, cost {r['cost']:.6g}, {m}")
    assert P.verify(q0, q1, v / 2.5**2, h * 2.5)["ok"]  # the slowed straight task
    assert seen == {"tau", "v", "qd", "q", "legs", "h"}  # every part measured non-zero somewhere


def test_failures_are_reported():
    # a path within 0.008 of the base point B_1 = (-0.25, 0.433): its leg folds
    a, b = np.array([-0.45, 0.45]), np.array([-0.05, 0.40])
    v, h = _plan(a, b)
    r = P.verify(a, b, v / 3.0**2, h * 3.0, h_max=0.2)  # (a dataset's period bound)
    assert not r["ok"] and r["max_rel_violation"]["legs"] > 0.5  # rho/(2L) = 0.0067 < 0.05
    assert r["max_rel_violation"]["h"] == 0.0
    assert r["goal_error"] <= 1e-12 and np.all(np.isfinite(r["tau"]))
    # the straight task a little slower than at its kinematic bounds: torques above 25 N m,
    # all else within
    a, b = np.array([-0.3, 0.2]), np.array([0.3, -0.3])
    v, h = _plan(a, b)
    v, h = v / 1.1**2, h * 1.1
    r = P.verify(a, b, v, h)
    m = r["max_rel_violation"]
    assert not r["ok"] and m["tau"] > 0.1 and max(m[k] for k in ("v", "qd", "q", "legs", "h")) <= 1e-12
    assert np.max(np.abs(r["tau"])) == pytest.approx(25.0 * (1 + m["tau"]), rel=1e-12)
    # non-finite input, a missed goal, a leg that cannot reach C: not ok, no exception
    bad = v.copy()
    bad[3, 1] = np.nan
    assert not P.verify(a, b, bad, h)["ok"]
    assert not P.verify(a, b, v, np.where(np.arange(N) == 5, np.inf, h))["ok"]
    assert not P.verify([np.nan, 0.0], b, v, h)["ok"]
    assert not P.verify(a, b + [0.0, 1e-4], v, h, tau_max=1e3)["ok"]
    assert P.verify(a, b, v, h, tau_max=1e3)["ok"]
    far = P.verify(a + [-1.5, 0.0], b + [-1.5, 0.0], v, h, tau_max=1e9, q_min=-9.0, q_max=9.0,
                   rho_min=0.0, rho_max=9.0)  # only the reach fails: leg 0 is 2.3 m away, 2 L = 1.2
    assert not far["ok"] and np.all(np.isnan(far["tau"]))
