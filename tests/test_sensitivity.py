"""jtraj.sensitivity (a layer over jtraj.implicit) against re-solves.

The comparison uses tight solver tolerances (1e-10): the optimal *cost* is insensitive
to first-order errors in z (envelope theorem), but the optimal *T* is not, so central
differences of T over a 1e-4 relative mass change (signal ~1e-5 s) need re-solves far
more accurate than the default 1e-5 tolerance.
"""

import numpy as np
import pytest

import jtraj
from jtraj.sensitivity import sensitivity, solve_with_multipliers

START, GOAL = (0.2, -0.3, 0.4), (0.3, -0.2, 0.3)  # converges at N = 10 (the brief's
# (0.6, 0.1, -0.1) goal needs T > N h_max = 1 s, infeasible at N = 10)
WEIGHTS = jtraj.Weights(time=1.0, energy=0.1)
TIGHT = jtraj.SolverOptions(tol_feasibility=1e-10, tol_optimality=1e-10, max_iter=1000)


def _problem(**overrides):
    return jtraj.Problem(jtraj.robots.get("serial3", **overrides), START, GOAL, N=10, weights=WEIGHTS)


def test_unknown_parameter_names_the_accepted_ones():
    with pytest.raises(ValueError, match="masses"):
        sensitivity(_problem(), "payload")


def test_unconverged_solution_is_rejected():
    problem = _problem()

    class Fake:  # a solution object that did not converge
        converged = np.asarray(False)
        status = np.asarray(1)

    with pytest.raises(ValueError, match="converged KKT point"):
        sensitivity(problem, "masses", solution=Fake())


def _check_against_resolves(base_solve, resolve):
    problem = _problem()
    base = base_solve(problem)
    assert bool(base.converged), base.status_message
    d = sensitivity(problem, "masses", solution=base, options=TIGHT, details=True)
    assert d["cost"].shape == (3,) and d["T"].shape == (3,)
    assert bool(d["solution"].converged)
    # envelope theorem and chain rule through the implicit tangent agree
    np.testing.assert_allclose(d["cost"], d["cost_chain"], rtol=1e-4, atol=1e-9)

    m0 = np.asarray(problem.robot.masses)
    fd_cost, fd_T = np.zeros(3), np.zeros(3)
    for i in range(3):
        out = []
        for sign in (1.0, -1.0):
            m = m0.copy()
            m[i] += sign * 1e-4 * m0[i]
            s = resolve(_problem(masses=m), (base.v, base.h))
            assert float(s.max_violation["overall"]) < 1e-8
            out.append((float(s.cost), float(s.T)))
        fd_cost[i] = (out[0][0] - out[1][0]) / (2e-4 * m0[i])
        fd_T[i] = (out[0][1] - out[1][1]) / (2e-4 * m0[i])
    np.testing.assert_allclose(d["cost"], fd_cost, rtol=0.02)
    np.testing.assert_allclose(d["T"], fd_T, rtol=0.02)


@pytest.mark.slow  # about two minutes of compilation on a 2-core machine
def test_masses_against_central_differences_of_resolves():
    """Re-solves with the solver core that sensitivity() already compiled (same _run and
    _finish as jtraj.solve), so the test pays for one compilation (~60 s)."""

    def run(problem, init=None):
        return solve_with_multipliers(problem, options=TIGHT, init=init)[0]

    _check_against_resolves(run, run)


@pytest.mark.slow
def test_masses_against_central_differences_of_jtraj_solve():
    """The same check with the public jtraj.solve for every solve (a second compilation)."""
    _check_against_resolves(lambda p: jtraj.solve(p, options=TIGHT),
                            lambda p, init: jtraj.solve(p, options=TIGHT, init=init))


@pytest.mark.slow  # N = 20, the default solver, the refinement and the reverse program: minutes
def test_time_dominant_serial3_task_against_central_differences():
    """The serial3 example's time-dominant case (a tip-to-point task, time 1 / energy 0.1,
    N = 20): the default solve ends on the interior point's central path, where the
    torque bounds with small multipliers lie up to 2e-3 inside their bounds; the
    derivatives (of the refined optimum) are finite and agree with central differences
    of re-solves."""
    import equinox as eqx
    import jax.numpy as jnp

    from jtraj.sensitivity import REFINE

    robot = jtraj.robots.get("serial3")
    q0 = np.deg2rad([0.0, 30.0, 30.0])

    problem = jtraj.Problem.from_task(robot, robot.forward_kinematics(jnp.asarray(q0)), (1.35, 1.30), q_init=q0,
                                      N=20, weights=WEIGHTS, T_max=3.0)

    def make(masses):  # the same start and goal (an IK per mass would add its own noise)
        return eqx.tree_at(lambda p: p.robot.masses, problem, jnp.asarray(masses))

    m0 = np.asarray(robot.masses)
    d = sensitivity(problem, "masses", details=True)
    assert np.all(np.isfinite(d["cost"])) and np.all(np.isfinite(d["T"]))
    base = d["solution"]
    fd = np.zeros((2, 3))
    for i in range(3):
        out = []
        for sign in (1.0, -1.0):
            m = m0.copy()
            m[i] += sign * 1e-4 * m0[i]
            s = jtraj.solve(make(m), solver=REFINE, init=(base.v, base.h))
            assert bool(s.converged), s.status_message
            out.append((float(s.cost), float(s.T)))
        fd[:, i] = (np.array(out[0]) - np.array(out[1])) / (2e-4 * m0[i])
    np.testing.assert_allclose(d["cost"], fd[0], rtol=1e-5, atol=1e-9)
    # the re-solves' T carries about 5e-9 of noise: 5e-9 / (2 * 8e-4) = 3e-6 in the
    # differences of the 8 kg link's mass
    np.testing.assert_allclose(d["T"], fd[1], rtol=1e-4, atol=5e-6)


@pytest.mark.slow  # one solve, its refinement and the reverse program: minutes
def test_scalar_parameter_held_as_a_python_float():
    """A robot parameter that is a Python float (serial3_vertical's gravity_accel; the
    Gough-Stewart platform's masses) has both derivatives, as numbers, equal to central
    differences of re-solves; the cost's is the envelope theorem's, which needs the
    parameter as an array leaf of the problem. On this problem the AL method at 1e-10
    stops at its iteration limit from the first refinement stage's point; the second
    interior-point stage (REFINE_IP_TIGHT) converges, and its solve is the one
    differentiated."""
    from jtraj.implicit import REFINE_IP, REFINE_IP_TIGHT

    robot = jtraj.robots.get("serial3_vertical")
    assert isinstance(robot.gravity_accel, float)
    problem = jtraj.Problem(robot, START, GOAL, N=10, weights=WEIGHTS)
    d = sensitivity(problem, "gravity_accel", details=True)
    assert d["cost"].shape == () and d["T"].shape == () and d["cost"].dtype == float
    np.testing.assert_allclose(d["cost"], d["cost_chain"], rtol=1e-4, atol=1e-9)
    base, g0 = d["solution"], robot.gravity_accel
    out = []
    for g in (g0 * (1 + 1e-3), g0 * (1 - 1e-3)):
        p = jtraj.Problem(jtraj.robots.get("serial3_vertical", gravity_accel=g), START, GOAL, N=10, weights=WEIGHTS)
        s = jtraj.solve(p, solver=REFINE_IP, init=(base.v, base.h))  # the two stages sensitivity() runs
        s = jtraj.solve(p, solver=REFINE_IP_TIGHT, init=(s.v, s.h))
        assert bool(s.converged), s.status_message
        out.append((float(s.cost), float(s.T)))
    fd = (np.array(out[0]) - np.array(out[1])) / (2e-3 * g0)
    np.testing.assert_allclose(float(d["cost"]), fd[0], rtol=1e-5)
    # (the re-solves' T carries about 5e-9 s of noise: 3e-7 in the differences)
    np.testing.assert_allclose(float(d["T"]), fd[1], rtol=1e-2, atol=1e-6)
