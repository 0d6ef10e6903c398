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
    gs = robots.get("gough_stewart")
    W = jtraj.Weights(time=1.0, energy=0.1)
    problem = jtraj.Problem(gs, GS_START, GS_GOAL, N=12, weights=W)
    sol = jtraj.solve(problem)
    assert bool(sol.converged), sol.status_message
    # resample: the exact constant-acceleration motion through the samples
    grid = jtraj.resample.resample(sol, gs, dt=1e-3)
    t = np.concatenate([[0.0], np.cumsum(np.asarray(sol.h))])
    for k in (0, 5, 12):
        i = int(np.argmin(np.abs(np.asarray(grid.t) - t[k])))
        if abs(float(grid.t[i]) - t[k]) < 1e-12:
            np.testing.assert_allclose(np.asarray(grid.q)[i], np.asarray(sol.q)[k], atol=1e-9)
    np.testing.assert_allclose(np.asarray(grid.q)[-1], GS_GOAL, atol=1e-6)
    # the gradient check on the platform: adjoint, autodiff and differences agree
    report = jtraj.gradcheck.check(robots=["gough_stewart"], points=1, N=6, seed=0)
    res = report.results[0] if hasattr(report, "results") else report[0]
    assert res.passed, res
    # sensitivity of the optimum's cost to the goal's height against re-solves
    sens = jtraj.sensitivity.sensitivity(problem, sol) if hasattr(jtraj.sensitivity, "sensitivity") else None
    dz = 1e-4

    def cost(z):
        return float(jtraj.solve(jtraj.Problem(gs, GS_START, GS_GOAL + np.array([0, 0, z, 0, 0, 0]), N=12,
                                               weights=W), init=(sol.v, sol.h)).cost)

    fd = (cost(dz) - cost(-dz)) / (2 * dz)
    grad = jax.grad(lambda g: jtraj.solve(jtraj.Problem(gs, GS_START, g, N=12, weights=W, validate=False)).cost)(
        jnp.asarray(GS_GOAL))
    assert abs(float(grad[2]) - fd) <= 1e-3 * max(1.0, abs(fd)), (float(grad[2]), fd, sens)


@pytest.mark.slow
@pytest.mark.parametrize("space", ["joint", "task"])
def test_gough_stewart_dataset_train_query(space, tmp_path):
    from jtraj.cli import main

    data = tmp_path / "data"
    assert main(["dataset", "build", "--robot", "gough_stewart", "--pairs", "6", "--N", "10", "--batch", "6",
                 "--space", space, "--out", str(data), "--no-progress", "--workers", "1"]) == 0
    assert main(["dataset", "verify", str(data)]) == 0
    ds = jtraj.dataset.load(str(data)) if hasattr(jtraj.dataset, "load") else None
    if ds is not None:
        gs = robots.get("gough_stewart")
        q0 = np.asarray(ds.q_start)
        assert q0.shape[1] == 6
        assert np.all(q0 >= np.asarray(gs.limits.q_min) - 1e-9) and np.all(q0 <= np.asarray(gs.limits.q_max) + 1e-9)
    model = tmp_path / "plan.anfis"
    assert main(["train", "--data", str(data), "--mapping", "plan", "--out", str(model), "--epochs", "5",
                 "--no-progress"]) == 0
    out = tmp_path / "q.json"
    assert main(["query", "--model", str(model), "--start", ",".join(map(str, GS_START)),
                 "--goal", ",".join(map(str, GS_GOAL)), "--refine", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result
