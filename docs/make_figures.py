"""Regenerate the figures of the getting-started page (``docs/img/first_*.png``).

Run it by hand after a change that alters them (a few minutes on 2 cores)::

    python docs/make_figures.py            # the missing figures
    python docs/make_figures.py --force    # all of them

The documentation build never runs it (it does not run the solver); the figures are
committed. Each figure shows the result of the code on the page it belongs to.
"""

from __future__ import annotations

import os
import sys
import tempfile

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jtraj  # noqa: E402
from jtraj import dataset, plotting  # noqa: E402
from jtraj.dataset import plot as dataset_plot  # noqa: E402
from jtraj.mappings import train_mapping, view  # noqa: E402
from jtraj.online import Planner  # noqa: E402

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "img")


def _save(fig, name):
    os.makedirs(OUT, exist_ok=True)
    fig.savefig(os.path.join(OUT, name), dpi=90, bbox_inches="tight")
    plt.close(fig)
    print("wrote", os.path.join(OUT, name))


def _missing(name, force):
    return force or not os.path.exists(os.path.join(OUT, name))


def main(force: bool = False):
    robot = jtraj.robots.get("serial3")
    weights = jtraj.Weights(time=1.0, energy=0.1)

    # first solve
    if _missing("first_solve.png", force):
        _first_solve(robot, weights)
    if _missing("first_batch.png", force):
        _first_batch(robot, weights)
    if any(_missing(f"first_{k}.png", force) for k in ("dataset", "model", "query")):
        _learning(robot, weights)


def _first_solve(robot, weights):
    problem = jtraj.Problem(robot, [0.2, -0.3, 0.4], [0.6, 0.1, -0.1], N=20, weights=weights)
    sol = jtraj.solve(problem)
    _save(plotting.plot_solution(problem, sol, title=f"{sol.status_message}, T = {float(sol.T):.3f} s"),
          "first_solve.png")


def _first_batch(robot, weights):
    rng = np.random.default_rng(0)
    q_starts = rng.uniform(-1.0, 1.0, (16, 3))
    q_goals = q_starts + rng.uniform(-0.8, 0.8, (16, 3))
    batch = jtraj.solve_batch(robot, q_starts, q_goals, N=20, weights=weights)
    fig, ax = plt.subplots(figsize=(6, 3.2))
    t = np.concatenate([np.zeros((16, 1)), np.cumsum(np.asarray(batch.h), axis=1)], axis=1)
    for b in range(16):
        ax.plot(t[b], np.asarray(batch.q)[b, :, 0], color="C0" if bool(batch.converged[b]) else "C3", lw=1)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("q1 [rad]")
    ax.set_title(f"16 problems in one solve_batch: {int(np.sum(batch.converged))} converged")
    _save(fig, "first_batch.png")


def _learning(robot, weights):
    with tempfile.TemporaryDirectory() as tmp:
        # first dataset
        path = os.path.join(tmp, "ds")
        spec = dataset.make_spec("serial3", pairs=64, seed=0, N=20)
        dataset.build(spec, path, workers=1, progress=False)
        dataset_plot.plot(path, os.path.join(OUT, "first_dataset.png"))
        print("wrote", os.path.join(OUT, "first_dataset.png"))

        # first model: nefotc's predicted torques against the optimal ones on test trajectories
        model, report, _ = train_mapping(path, "nefotc")
        X, Y, traj, _, _ = view(dataset.load(path), "nefotc", goal="relative", phase=True)
        test = traj >= np.quantile(traj, 0.9)
        pred = np.asarray(model.predict(X[test]))
        fig, ax = plt.subplots(figsize=(4, 4))
        ax.plot(Y[test].ravel(), pred.ravel(), ".", ms=3)
        lim = float(np.max(np.abs(Y[test])))
        ax.plot([-lim, lim], [-lim, lim], "k--", lw=0.8)
        ax.set_xlabel("optimal tau [N m]")
        ax.set_ylabel("ANFIS tau [N m]")
        ax.set_title(f"nefotc: test RMSE / linear = {report['ratio_to_linear']:.2f}")
        _save(fig, "first_model.png")

        # first query: the open-loop planner's plan and its refinement
        plan_model, _, _ = train_mapping(path, "plan", order=0)
        planner = Planner(plan_model)
        q0, q1 = np.array([0.3, -0.8, 0.3]), np.array([0.4, -0.15, 0.3])
        p = planner.plan(q0, q1)
        refined = jtraj.solve(jtraj.Problem(robot, q0, q1, N=20, weights=weights), init=(p.v, p.h), warm="primal")
        fig, ax = plt.subplots(figsize=(6, 3.2))
        for q, h, style, label in ((p.q, p.h, "--", "ANFIS plan"), (refined.q, refined.h, "-", "refined")):
            t = np.concatenate([[0.0], np.cumsum(np.asarray(h))])
            for j in range(3):
                ax.plot(t, np.asarray(q)[:, j], style, color=f"C{j}", label=f"{label}, q{j + 1}")
        ax.set_xlabel("t [s]")
        ax.set_ylabel("q [rad]")
        ax.legend(fontsize=7, ncol=2)
        ax.set_title("a plan in under a millisecond, refined by jtraj.solve")
        _save(fig, "first_query.png")


if __name__ == "__main__":
    main(force="--force" in sys.argv[1:])
