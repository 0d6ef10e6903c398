"""A batch of spatial-arm problems is the same problems as their single solves: the
jerk rows a batch's problems carry are the robot's default on its concrete limits (the
Panda's published limits imply its jerk bound, so neither carries them and the
interior-point method solves both), and (slow) ``solve_batch`` on Panda pairs takes the
iterations and reaches the costs of ``jtraj.solve`` on each, also on pairs of the panda
dataset's family that the interior-point method finishes without the AL loop."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj
from jtraj import _testing
from jtraj.problem import default_jerk

try:  # the Panda's URDF comes from example-robot-data (the 'robots' extra)
    from jtraj.robots.urdf import robot_data_dir

    robot_data_dir()
except ImportError:
    pytest.skip("example-robot-data is not installed", allow_module_level=True)

WEIGHTS = jtraj.Weights(time=1.0, energy=0.1)


def _pairs(robot, count, seed=0):
    """bench_spatial's family: starts in the middle 60 % of each range, goals within 0.5 rad."""
    lo, hi = np.asarray(robot.limits.q_min), np.asarray(robot.limits.q_max)
    u = np.random.default_rng(seed).random((count, 2, robot.n))
    q0 = (lo + hi) / 2 + 0.6 * (hi - lo) / 2 * (2 * u[:, 0] - 1)
    return q0, np.clip(q0 + (u[:, 1] - 0.5), lo, hi)


@pytest.mark.parametrize("h_min", [None, 0.001])
def test_batch_problems_carry_the_robots_default_jerk_rows(h_min):
    """The batch builds its problems inside a compiled program, where the limits are
    traced; the jerk rows follow the concrete robot's default all the same: off for the
    Panda's limits (2 qdd_max <= qddd_max h_min), on with h_min = 1 ms; equal to the
    single Problem's choice either way, and so are the global rows' count and values."""
    robot = jtraj.robots.get("panda") if h_min is None else jtraj.robots.get("panda", h_min=h_min)
    q0, q1 = _pairs(robot, 2)
    B, n = q0.shape
    jerk = default_jerk(robot)
    assert jerk == (h_min is not None)
    batch = _testing.problems_jit(robot, q0, q1, np.zeros((B, n)), np.zeros((B, n)), np.full(B, np.inf), 12, WEIGHTS,
                                  "samples", jerk)
    single = jtraj.Problem(robot, q0[1], q1[1], N=12, weights=WEIGHTS)
    assert batch.jerk == single.jerk == jerk
    tr = jtraj.transcription.Transcription("decoupled")
    rng = np.random.default_rng(1)
    v = jnp.asarray(rng.uniform(-1, 1, (12, n)) * np.asarray(robot.limits.qdd_max))
    h = jnp.asarray(rng.uniform(float(robot.limits.h_min), 0.05, 12))
    layout = tr.layout(single)
    z = layout.pack(v, h)
    lane = jax.tree.map(lambda x: x[1] if eqx.is_array(x) else x, batch)  # the batch's problem 1
    g1 = tr.global_inequalities(single, layout, z)
    g2 = tr.global_inequalities(lane, tr.layout(lane), z)
    # the bound on T, then (with jerk) two rows per joint and pair of consecutive intervals
    assert g1.shape == g2.shape == ((1 + 2 * (12 - 1) * n,) if jerk else (1,))
    np.testing.assert_array_equal(np.asarray(g1), np.asarray(g2))


@pytest.mark.slow
def test_panda_batch_equals_single_solves():
    """Four Panda pairs of bench_spatial's family (N = 20): ``solve_batch`` (the
    interior-point pool, 2 lanes) and ``jtraj.solve`` one by one take the same iterations,
    all converge, and reach the same costs to 1e-9 relative (lanes are independent: only
    the rounding of vectorised operations may differ)."""
    robot = jtraj.robots.get("panda")
    q0, q1 = _pairs(robot, 4)
    batch = jtraj.solve_batch(robot, q0, q1, N=20, weights=WEIGHTS, slots=2)
    singles = [jtraj.solve(jtraj.Problem(robot, a, b, N=20, weights=WEIGHTS)) for a, b in zip(q0, q1)]
    assert np.asarray(batch.converged).all(), np.asarray(batch.status)
    assert "jerk" not in batch.max_violation  # no jerk rows: the Panda's limits imply them
    assert all(bool(s.converged) for s in singles)
    np.testing.assert_array_equal(np.asarray(batch.iterations), [int(s.iterations) for s in singles])
    np.testing.assert_allclose(np.asarray(batch.cost), [float(s.cost) for s in singles], rtol=1e-9)


@pytest.mark.slow
def test_panda_dataset_pairs_finish_in_the_interior_point_method():
    """Pairs of the panda dataset's family (``jtraj dataset --robot panda``: moves up to
    0.8 rad per joint, periods up to 0.2 s) whose violation stays above 1 for a while
    (pairs 0 and 5 of seed 0) finish solved in the interior-point method with the
    Gauss-Newton model, without the AL loop (``outer_iterations`` 0), and the batch and
    the single solves agree."""
    from jtraj import dataset
    from jtraj.dataset import sampling

    spec = dataset.make_spec("panda", 16, 0, N=40, batch=4)
    robot = spec.robot_model()
    q0, q1 = sampling.sample_pairs(robot, spec.distribution, 0, 0, 16)
    q0, q1 = q0[[0, 5]], q1[[0, 5]]
    singles = [jtraj.solve(jtraj.Problem(robot, a, b, N=40, weights=spec.weights_obj())) for a, b in zip(q0, q1)]
    for s in singles:
        assert bool(s.converged), s.status_message
        assert int(s.outer_iterations) == 0 and int(s.iterations) <= 100
    batch = jtraj.solve_batch(robot, q0, q1, N=40, weights=spec.weights_obj(), slots=2)
    np.testing.assert_array_equal(np.asarray(batch.iterations), [int(s.iterations) for s in singles])
    np.testing.assert_allclose(np.asarray(batch.cost), [float(s.cost) for s in singles], rtol=1e-9)
