"""The benchmark scripts' plumbing (results, JSON summary, plot) with the fast stand-in
solver: the figures themselves come from real runs (docs/benchmarks.md), not from tests."""

import json
import os

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))

FAKE = "jtraj.dataset.testing:fake_solve_batch"


def test_bench_dataset_writes_its_summary(tmp_path):
    import bench_dataset

    out = tmp_path / "out"
    summary = bench_dataset.main(["--quick", "--no-ipopt", "--workers", "1", "--solver", FAKE,
                                  "--out-dir", str(out)])
    with open(out / "bench_dataset.json") as f:
        saved = json.load(f)
    assert saved == json.loads(json.dumps(summary))
    (r,) = saved["results"]
    # --quick: one chunk of 64 pairs warms the worker, one more is timed
    assert r["batch"] == 64 and r["pairs"] == 128 and r["timed_pairs"] == 64
    assert r["pairs_per_s"] > 0 and r["h_max"] == pytest.approx(0.2)
    # the stand-in flags the pairs with sum(q_goal) > 1 as failures
    assert 0.0 < r["converged_fraction"] < 1.0
    assert saved["ipopt"] is None and (out / "bench_dataset.png").stat().st_size > 0


def test_peer_starts_are_jtrajs_starting_points():
    import bench_solver
    import jax.numpy as jnp
    import numpy as np

    import jtraj
    from jtraj.initial_guess import cycloidal_torque

    q0 = np.array([[0.0, 0.3, -0.2], [0.5, -1.0, 0.1]])
    q1 = q0 + np.array([[0.7, -0.6, 0.5], [-0.4, 0.8, 0.2]])
    assert bench_solver.peer_starts(q0, q1, 20, "cycloidal") is None  # the peer's own guess
    starts = bench_solver.peer_starts(q0, q1, 20, "same", {"method": "auto"}, h_max=0.2)
    robot = jtraj.robots.get("serial3", h_max=0.2)
    for (v, h), a, b in zip(starts, q0, q1):
        v_ref, h_ref = cycloidal_torque(jtraj.Problem(robot, a, b, N=20))
        assert v.shape == (20, 3) and h.shape == (20,)
        np.testing.assert_allclose(v, np.asarray(v_ref), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(h, np.asarray(h_ref), rtol=1e-12)
        assert float(jnp.sum(h)) > 0
    # another guess through the options
    (v, h), _ = bench_solver.peer_starts(q0, q1, 20, "same", {"guess": "cycloidal"})
    v_k, h_k = jtraj.initial_guess.cycloidal(jtraj.Problem(jtraj.robots.get("serial3"), q0[0], q1[0], N=20))
    np.testing.assert_allclose(h, np.asarray(h_k), rtol=1e-12)


@pytest.mark.parametrize("label", ["so101", "baxter_left", "tiago_pro_left"])
def test_urdf_arm_peer_model_is_jtrajs_arm(label):
    """bench_urdf_arms' Pinocchio model of a file (every joint off the chain locked) and
    jtraj's arm from the same file give the same efforts (1e-10 relative): a gripper
    beyond the tip merged into the last body (SO-101), a second arm and a head off the
    chain (Baxter), a prismatic torso and a wheeled base (TIAGo Pro)."""
    pytest.importorskip("pinocchio")
    import bench_urdf_arms as B

    try:
        path = B.urdf_path(label)
    except FileNotFoundError:
        pytest.skip("example-robot-data is not installed")
    robot = B.jtraj_arm(label)
    model = B.pinocchio_chain(path, robot.joint_names)
    assert model.nv == robot.n and list(model.names)[1:] == list(robot.joint_names)
    assert B.rnea_gap(robot, model, count=16) < 1e-10
