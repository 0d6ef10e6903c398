"""Initial guesses (jtraj.initial_guess): the torque-scaled cycloid against the robot's
own inverse dynamics along the returned profile."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj
from jtraj.initial_guess import GUESSES, cycloid_path, cycloidal, cycloidal_time, torque_scaled_time


def _peak_torque_ratio(problem, T, points=41):
    """max |tau| / tau_max along the continuous cycloid of duration T (the closed form of
    its acceleration, the robot's inverse dynamics)."""
    robot = problem.robot
    s = np.linspace(0.0, 1.0, points)
    q, qd = cycloid_path(problem, T, s * T)
    dq = problem.q_goal - problem.q_start
    qdd = dq[None] * (2 * np.pi / T**2 * np.sin(2 * np.pi * s))[:, None]
    tau = jax.vmap(robot.inverse_dynamics)(q, qd, qdd)
    return float(jnp.max(jnp.abs(tau) / robot.limits.tau_max[None]))


def _vertical_arm():
    # serial3's arm in a vertical plane, no gearbox, joint limits that can hold it
    return jtraj.robots.serial_planar((1.0, 0.8, 0.45), (10.0, 8.0, 4.0), (9.23, 7.5, 5.21), gravity=9.81,
                                      limits=dict(tau_max=(300.0, 100.0, 25.0), qd_max=2.0, qdd_max=3.0))


@pytest.mark.parametrize("name", ["serial3", "ibm7535", "vertical"])
def test_torque_scaled_cycloid_meets_torque_bounds_exactly(name):
    # no friction: along the path slowed c times the efforts are D / c^2 + G(q), so the
    # peak over the same 2N + 1 points is the bound itself (with gravity too)
    robot = _vertical_arm() if name == "vertical" else jtraj.robots.get(name)
    rng = np.random.default_rng(3)
    n = robot.n
    active = 0
    for _ in range(4):
        q0 = rng.uniform(-1.0, 1.0, n)
        p = jtraj.Problem(robot, q0, q0 + rng.uniform(-1.5, 1.5, n), N=20, validate=False)
        Tk = float(cycloidal_time(p))
        T = float(torque_scaled_time(p, cycloidal_time(p)))
        before = _peak_torque_ratio(p, Tk, 2 * p.N + 1)
        assert T >= Tk
        if before > 1.0:
            active += 1
            assert _peak_torque_ratio(p, T, 2 * p.N + 1) == pytest.approx(1.0, rel=1e-9)
            if name != "vertical":  # no gravity: tau scales as a whole
                assert T == pytest.approx(Tk * np.sqrt(before), rel=1e-9)
            # between the points the continuous peak may exceed the bound a little
            assert _peak_torque_ratio(p, T, 401) <= 1.01
        else:
            assert T == Tk
    assert active  # the scaling was exercised


def test_torque_scaled_cycloid_edge_cases():
    # gravity alone over the bound somewhere on the path: the slowest admissible duration
    weak = jtraj.robots.serial_planar((1.0, 0.8, 0.45), (10.0, 8.0, 4.0), (9.23, 7.5, 5.21), gravity=9.81,
                                      limits=dict(tau_max=(40.0, 25.0, 20.0), qd_max=2.0, qdd_max=3.0))
    p = jtraj.Problem(weak, np.zeros(3), np.array([1.0, -0.8, 0.5]), N=20, validate=False)
    v, h = GUESSES["cycloidal_torque"](p)
    assert np.all(np.isfinite(v)) and np.allclose(h, weak.limits.h_max)
    # start == goal: no motion, no NaN, the shortest admissible duration
    p0 = jtraj.Problem(jtraj.robots.get("serial3"), np.ones(3), np.ones(3), N=20, validate=False)
    v0, h0 = GUESSES["cycloidal_torque"](p0)
    assert np.all(v0 == 0) and np.allclose(h0, p0.robot.limits.h_min)
    # the torque scaling respects T_max (clipped like the kinematic guess)
    pT = jtraj.Problem(jtraj.robots.get("serial3"), np.zeros(3), np.full(3, 1.2), N=20, T_max=1.0, validate=False)
    assert float(jnp.sum(GUESSES["cycloidal_torque"](pT)[1])) == pytest.approx(1.0)


def test_default_guess_is_the_torque_scaled_cycloid():
    assert jtraj.SolverOptions().guess == "cycloidal_torque"
    with pytest.raises(ValueError, match="guess"):
        jtraj.SolverOptions(guess="spline")
