"""The solver on the URDF arms (slow: a 7-DOF solver compiles for minutes on 2 cores):
a joint-space move of 0.5 rad per joint from the middle of the ranges converges, and the
returned trajectory, re-simulated from its own accelerations and periods, meets the
bounds with efforts recomputed by Pinocchio from the same URDF file."""

import numpy as np
import pytest

import jtraj
import jtraj.robots as robots

from test_spatial import BUILTIN, PinocchioArm, _data_dir


def _move(robot, seed):
    lo, hi = np.asarray(robot.limits.q_min), np.asarray(robot.limits.q_max)
    rng = np.random.default_rng(seed)
    q0 = (lo + hi) / 2 + 0.1 * (hi - lo) * rng.uniform(-1, 1, robot.n)
    return q0, q0 + rng.choice([-0.5, 0.5], robot.n)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["panda", "ur5"])
def test_joint_space_move_converges_and_verifies(name, tmp_path):
    pytest.importorskip("pinocchio")
    robot = robots.get(name)
    path, tip = BUILTIN[name]
    ref = PinocchioArm(_data_dir() / path, robot.joint_names, tip)
    q0, q1 = _move(robot, 0)
    problem = jtraj.Problem(robot, q0, q1, N=40, weights=jtraj.Weights(time=1.0, energy=0.1))
    sol = jtraj.solve(problem)
    assert bool(sol.converged), sol.status_message
    lim = robot.limits
    v, h = np.asarray(sol.v), np.asarray(sol.h)
    # the recursion re-run in NumPy from (v, h): constant acceleration per interval
    q, qd = [q0], [np.zeros(robot.n)]
    for k in range(problem.N):
        q.append(q[-1] + h[k] * qd[-1] + 0.5 * h[k] ** 2 * v[k])
        qd.append(qd[-1] + h[k] * v[k])
    q, qd = np.array(q), np.array(qd)
    assert np.abs(q[-1] - q1).max() < 1e-6 and np.abs(qd[-1]).max() < 1e-6
    assert np.abs(q - np.asarray(sol.q)).max() < 1e-9
    tau = np.array([ref.evaluate(q[k], qd[k], v[k])[0] for k in range(problem.N)])
    assert np.abs(tau - np.asarray(sol.tau)[:problem.N]).max() < 1e-8 * np.asarray(lim.tau_max).max()
    assert (np.abs(tau) <= np.asarray(lim.tau_max) * (1 + 1e-6)).all()
    assert (np.abs(qd) <= np.asarray(lim.qd_max) * (1 + 1e-6)).all()
    assert (np.abs(v) <= np.asarray(lim.qdd_max) * (1 + 1e-6)).all()
    assert ((q >= np.asarray(lim.q_min) - 1e-9) & (q <= np.asarray(lim.q_max) + 1e-9)).all()
    assert (h >= float(lim.h_min) * (1 - 1e-9)).all() and (h <= float(lim.h_max) * (1 + 1e-9)).all()
    # the cost is the weighted time plus the normalised effort integral of the returned trajectory
    energy = np.sum(h * np.sum((tau / np.asarray(lim.tau_max)) ** 2, axis=1))
    assert float(sol.cost) == pytest.approx(h.sum() + 0.1 * energy, rel=1e-6)
    # the full figure of a spatial arm (the tip path in 3-D) draws
    pytest.importorskip("matplotlib")
    from jtraj.plotting import plot_solution, save

    save(plot_solution(problem, sol), str(tmp_path / "sol.png"))
    assert (tmp_path / "sol.png").stat().st_size > 0
