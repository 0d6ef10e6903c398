"""Reduced runs of the two gradient examples (examples/inverse_payload.py and
examples/design_by_gradient.py): a few optimiser iterations on two tasks. Each checks
the gradient that drives the descent against central finite differences of re-solved
batches (the loss and the mean optimal time re-solved at the shifted parameters, warm
started), then that the descent lowers its objective and moves the parameter the right
way. Both compile a vmapped solver and a vmapped derivative program: minutes on two
cores, hence slow."""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))

pytestmark = pytest.mark.slow


def test_inverse_payload_gradient_and_descent():
    import inverse_payload as ex

    q_start, q_goal = ex.tasks(count=2)
    observed, _ = ex.observe(q_start, q_goal)
    assert np.all(np.asarray(observed.status) == 0)

    # the gradient of the matching loss in log(payload) at the guess against central
    # differences of re-solves (energy weight known)
    def loss(log_theta):
        sol = ex.solve(jnp.exp(log_theta), q_start, q_goal, init=(observed.v, observed.h))
        return ex.matching_loss(sol, observed)

    x0 = jnp.log(jnp.array([ex.GUESS["payload"], ex.TRUE["energy"]]))
    grad = jax.grad(loss)(x0)
    step = 1e-3
    fd = (float(loss(x0.at[0].add(step))) - float(loss(x0.at[0].add(-step)))) / (2 * step)
    assert grad[0] < 0  # a heavier payload brings the trajectories closer to the observed ones
    np.testing.assert_allclose(float(grad[0]), fd, rtol=1e-3)

    hist = ex.identify("payload", observed, q_start, q_goal, {"energy": ex.TRUE["energy"]},
                       ex.GUESS["payload"], iterations=4)
    assert min(hist["valid"]) == 2
    assert all(b < a for a, b in zip(hist["loss"], hist["loss"][1:]))  # monotone in this range
    assert hist["loss"][-1] < 0.75 * hist["loss"][0]
    err = [abs(v - ex.TRUE["payload"]) for v in hist["value"]]
    assert err[-1] < err[0]


def test_design_gradient_and_descent():
    import design_by_gradient as ex

    tips = tuple(jnp.asarray(p) for p in ex.task_points(count=2))
    x0 = ex.project(jnp.asarray(ex.START, float))
    (value, sol), grad = jax.value_and_grad(ex.mean_time, has_aux=True)(x0, tips)  # cold, as in descend
    assert np.all(np.asarray(jax.device_get(sol.status)) == 0)

    # central differences of re-solves; the inverse kinematics moves the start and the goal
    step = 1e-4
    fd = []
    for i in range(2):
        plus = float(ex.mean_time(x0.at[i].add(step), tips, (sol.v, sol.h))[0])
        minus = float(ex.mean_time(x0.at[i].add(-step), tips, (sol.v, sol.h))[0])
        fd.append((plus - minus) / (2 * step))
    np.testing.assert_allclose(np.asarray(grad), fd, rtol=1e-3, atol=1e-5)

    hist = ex.descend(tips, iterations=4)
    assert min(hist["valid"]) == 2
    assert hist["objective"][-1] < hist["objective"][0]
    total = hist["design"].sum(axis=1)  # the projection keeps every design in the band
    assert np.all((total >= ex.REACH - 1e-12) & (total <= ex.BUDGET + 1e-12))
