"""Everything downstream of a solve on the spatial robots: plot units per coordinate
type; (slow) on ``gough_stewart`` a solve re-simulated by ``resample``, the gradient
check, the sensitivity of the optimum against re-solves, and the CLI's ``dataset``
(joint- and task-space sampling), ``train`` and ``query``."""

import json
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj
import jtraj.robots as robots
from jtraj.plotting import coordinate_units, effort_units, plot_solution

from test_spatial import GOOD, LINK, _joint, _urdf

SLIDER = '<limit lower="-0.5" upper="0.5" effort="80" velocity="0.4"/>'


def test_units_per_coordinate_type():
    gs = robots.get("gough_stewart")
    assert coordinate_units(gs) == ["m"] * 3 + ["rad"] * 3 and effort_units(gs) == ["N"] * 6
    s3 = robots.get("serial3")
    assert coordinate_units(s3) == ["rad"] * 3 and effort_units(s3) == ["N m"] * 3
    assert coordinate_units(robots.get("pkm2")) == ["m", "m"] and effort_units(robots.get("pkm2")) == ["N", "N"]
    assert coordinate_units(robots.get("wmr")) == ["m", "m", "rad"] and effort_units(robots.get("wmr")) == ["N m"] * 2
    # a URDF arm with a prismatic joint: m and N on that joint, from its joint types
    arm = robots.from_urdf(_urdf(GOOD + LINK.format("c") + _joint("s", "b", "c", "prismatic", SLIDER)))
    assert arm.joint_types == ("revolute", "prismatic")
    assert coordinate_units(arm) == ["rad", "m"] and effort_units(arm) == ["N m", "N"]


@pytest.mark.slow
def test_figure_labels_carry_the_units():
    """The figure's axes and legends (a trajectory from the recursion, no solve)."""
    gs = robots.get("gough_stewart")
    problem = jtraj.Problem(gs, [0.0, 0.0, 1.0, 0.0, 0.0, 0.0], [0.05, -0.05, 1.05, 0.1, 0.0, -0.1], N=10)
    v = jnp.zeros((10, 6)).at[:5].set(0.2).at[5:].set(-0.2)
    h = jnp.full(10, 0.08)
    q, qd = jtraj.transcription.integrate(problem.q_start, problem.qd_start, v, h)
    tau = jax.vmap(gs.inverse_dynamics)(q[:-1], qd[:-1], v)
    fig = plot_solution(problem, types.SimpleNamespace(q=q, qd=qd, v=v, tau=tau, h=h), guess=False)
    labels = {ax.get_ylabel() for ax in fig.axes}
    assert {"q [m, rad]", "qd [m/s, rad/s]", "tau [N]"} <= labels
    legend = [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()]
    assert "q1 [m]" in legend and "q4 [rad]" in legend and "qd6 [rad/s]" in legend and "tau1 [N]" in legend


GS_START = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
GS_GOAL = np.array([0.08, -0.06, 1.1, 0.1, -0.05, 0.15])


@pytest.mark.slow
def test_gough_stewart_resample_gradcheck_sensitivity():
    from jtraj.gradcheck import gradcheck_robot
    from jtraj.resample import resample

    gs = robots.get("gough_stewart")
    W = jtraj.Weights(time=1.0, energy=0.1)
    problem = jtraj.Problem(gs, GS_START, GS_GOAL, N=12, weights=W)
    sol = jtraj.solve(problem)
    assert bool(sol.converged), sol.status_message
    # resample at the sample times gives the samples back, efforts by inverse dynamics
    t = np.concatenate([[0.0], np.cumsum(np.asarray(sol.h))])
    grid = resample(sol, gs, times=t[:-1])
    np.testing.assert_allclose(np.asarray(grid.q), np.asarray(sol.q)[:-1], atol=1e-9)
    np.testing.assert_allclose(np.asarray(grid.tau), np.asarray(sol.tau)[:12], atol=1e-6)
    fine = resample(sol, gs, dt=1e-3)
    np.testing.assert_allclose(np.asarray(fine.q)[-1], GS_GOAL, atol=1e-6)
    # the gradient check on the platform: adjoint, autodiff and differences agree
    res = gradcheck_robot("gough_stewart", N=6, points=1, seed=0)
    assert res.passed and res.status == "ok", res
    # the optimal cost's sensitivity to the platform mass against central differences
    # of re-solves warm-started from the optimum and refined as sensitivity() refines
    # (differences of default-tolerance re-solves differ from it by 6e-3 relative, of
    # refined ones by 1e-10)
    from jtraj.implicit import REFINE_IP, REFINE_IP_TIGHT

    sens = jtraj.sensitivity(problem, "platform_mass", solution=sol)
    m0, dm = float(gs.platform_mass), 1e-3 * float(gs.platform_mass)

    def cost(m):
        r = robots.with_params(gs, platform_mass=m)  # (stored as an array: one program for both)
        p = jtraj.Problem(r, GS_START, GS_GOAL, N=12, weights=W)
        s = jtraj.solve(p, init=(sol.v, sol.h))
        for stage in (REFINE_IP, REFINE_IP_TIGHT):
            s = jtraj.solve(p, solver=stage, init=(s.v, s.h))
        assert bool(s.converged), s.status_message
        return float(s.cost)

    fd = (cost(m0 + dm) - cost(m0 - dm)) / (2 * dm)
    assert abs(float(np.asarray(sens["cost"])) - fd) <= 1e-3 * abs(fd) + 1e-8, (sens["cost"], fd)


@pytest.mark.slow
@pytest.mark.parametrize("space", ["joint", "task"])
def test_gough_stewart_dataset_train_query(space, tmp_path):
    from jtraj.cli import main

    data = tmp_path / "data"
    assert main(["dataset", "build", "--robot", "gough_stewart", "--pairs", "6", "--N", "10", "--batch", "6",
                 "--space", space, "--out", str(data), "--no-progress", "--workers", "1"]) == 0
    assert main(["dataset", "verify", str(data)]) == 0
    from jtraj.dataset import load

    ds = load(str(data))
    gs = robots.get("gough_stewart")
    for key in ("q_start", "q_goal"):
        q = np.asarray(ds[key])
        assert q.shape == (6, 6)
        assert np.all(q >= np.asarray(gs.limits.q_min) - 1e-9) and np.all(q <= np.asarray(gs.limits.q_max) + 1e-9)
    model = tmp_path / "plan.anfis"
    # (6 pairs leave 4 training samples after the validation split: 2 rules)
    assert main(["train", "--data", str(data), "--mapping", "plan", "--out", str(model), "--epochs", "5",
                 "--rules", "2", "--no-progress"]) == 0
    out = tmp_path / "q.json"
    assert main(["query", "--model", str(model), "--start", ",".join(map(str, GS_START)),
                 "--goal", ",".join(map(str, GS_GOAL)), "--refine", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result
