"""Inverse kinematics: round trips, unreachable targets, vmap, joint-limit null-space
motion, bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj.robots as robots
from jtraj.robots.ik import JOINT_LIMITS, NOT_CONVERGED, SUCCESS, ik


def tip_serial3(q):
    """serial3's tip written out by hand (independent of the library)."""
    l = (1.0, 0.8, 0.45)
    a = np.cumsum(q)
    return np.array([np.dot(l, np.cos(a)), np.dot(l, np.sin(a))])


@pytest.fixture(scope="module")
def serial3():
    return robots.get("serial3")


@pytest.fixture(scope="module")
def targets():
    rng = np.random.default_rng(0)
    qs = rng.uniform(-2.0, 2.0, (64, 3))
    return np.stack([tip_serial3(q) for q in qs])


@pytest.mark.parametrize("method", ["weighted", "dls"])
def test_vmap_reaches_random_targets(serial3, targets, method):
    solve = jax.jit(jax.vmap(lambda p, q0: ik(serial3, p, q0, method=method)))
    res = solve(jnp.asarray(targets), jnp.full((64, 3), 0.5))
    assert res.q.shape == (64, 3) and res.status.shape == (64,)
    # the easy majority converges from one common start; the rest from a second start
    ok = np.asarray(res.status) == SUCCESS
    assert ok.mean() > 0.9
    for i in np.flatnonzero(~ok):
        r = ik(serial3, targets[i], -np.sign(targets[i][1]) * np.array([0.3, 1.0, 1.0]), method=method)
        assert int(r.status) == SUCCESS
    for q, p, s in zip(np.asarray(res.q), targets, np.asarray(res.status)):
        if s == SUCCESS:
            assert np.linalg.norm(tip_serial3(q) - p) < 1e-10


def test_single_call_and_round_trip(serial3):
    q_true = np.array([0.0, np.pi / 6, np.pi / 6])
    p = tip_serial3(q_true)
    res = ik(serial3, p, q_init=q_true + 0.2)
    assert int(res.status) == SUCCESS and float(res.error) < 1e-10
    assert np.linalg.norm(tip_serial3(np.asarray(res.q)) - p) < 1e-10
    assert int(res.iterations) >= 1
    res_default = ik(serial3, p)  # default start
    assert int(res_default.status) == SUCCESS
    assert np.linalg.norm(tip_serial3(np.asarray(res_default.q)) - p) < 1e-10


@pytest.mark.parametrize("method", ["weighted", "dls"])
def test_unreachable(serial3, method):
    res = ik(serial3, jnp.array([2.5, 1.0]), method=method)  # reach is 2.25 m
    assert int(res.status) == NOT_CONVERGED and float(res.error) > 0.1


def test_joint_limit_null_space_motion():
    """Plain weighted pseudo-inverse leaves joint 3's box; the null-space motion keeps
    it inside while reaching the same target."""
    robot = robots.get("serial3", q_min=(-3.0, -3.0, -0.6), q_max=(3.0, 3.0, 0.6))
    q_target = np.array([-0.09, -1.1, -0.1])
    p = tip_serial3(q_target)
    q0 = np.array([0.0, 0.3, 0.5])
    plain = ik(robot, p, q0, null_gain=0.0)
    guided = ik(robot, p, q0)
    assert int(plain.status) == JOINT_LIMITS and abs(float(plain.q[2])) > 0.6
    assert int(guided.status) == SUCCESS
    q = np.asarray(guided.q)
    assert np.all(q >= np.array([-3, -3, -0.6])) and np.all(q <= np.array([3, 3, 0.6]))
    assert np.linalg.norm(tip_serial3(q) - p) < 1e-10


def test_other_robots():
    # the platform robots' configuration is the platform position: IK must return the target
    p3 = robots.get("parallel3")
    res = ik(p3, jnp.array([0.2, -0.1]))
    assert int(res.status) == SUCCESS
    np.testing.assert_allclose(np.asarray(res.q), [0.2, -0.1], atol=1e-10)
    assert int(ik(p3, jnp.array([1.5, 1.5])).status) == NOT_CONVERGED  # legs cannot close
    pkm = robots.get("pkm2")
    res = ik(pkm, jnp.array([0.3, -1.0]), method="dls")
    assert int(res.status) == SUCCESS
    np.testing.assert_allclose(np.asarray(res.q), [0.3, -1.0], atol=1e-10)
    assert int(ik(pkm, jnp.array([1.5, -1.0]), method="dls").status) == NOT_CONVERGED
    w = robots.get("wmr")
    res = ik(w, jnp.array([10.0, 12.0]), method="dls")
    assert int(res.status) == SUCCESS and np.allclose(res.q[:2], [10.0, 12.0], atol=1e-10)


def test_bad_input(serial3):
    with pytest.raises(ValueError, match="p"):
        ik(serial3, jnp.array([1.0, 0.5, 0.0]))
    with pytest.raises(ValueError, match="p"):
        ik(serial3, [np.nan, 1.0])
    with pytest.raises(ValueError, match="q_init"):
        ik(serial3, [1.0, 0.5], q_init=[0.0, 0.0])
    with pytest.raises(ValueError, match="q_init"):
        ik(serial3, [1.0, 0.5], q_init=[0.0, np.inf, 0.0])
    with pytest.raises(ValueError, match="method"):
        ik(serial3, [1.0, 0.5], method="newton")
    with pytest.raises(ValueError, match="max_iter"):
        ik(serial3, [1.0, 0.5], max_iter=0)
    with pytest.raises(ValueError, match="robot"):
        ik("serial3", [1.0, 0.5])


def test_bad_settings_raise_naming_the_argument(serial3):
    """``ik`` and ``pose_ik`` reject a bad robot, iteration bound, gain or tolerance before
    tracing, with a message naming the argument."""
    from jtraj.robots.spatial_ik import pose_ik

    p = np.array([1.0, 0.5])
    cases = [(dict(robot="serial3"), "robot must be"), (dict(max_iter=0), "max_iter must be"),
             (dict(max_iter=True), "max_iter must be"), (dict(tol=-1e-6), "tol must be"),
             (dict(damping=float("nan")), "damping must be"), (dict(null_gain=-1.0), "null_gain must be"),
             (dict(method="newton"), "method must be")]
    for kw, message in cases:
        robot = kw.pop("robot", serial3)
        with pytest.raises(ValueError, match=message):
            ik(robot, p, **kw)
    panda = robots.get("panda")
    with pytest.raises(ValueError, match="rot_tol must be"):
        pose_ik(panda, np.array([0.4, 0.0, 0.5]), rot_tol=0.0)
    with pytest.raises(ValueError, match="max_iter must be"):
        pose_ik(panda, np.array([0.4, 0.0, 0.5]), max_iter=-3)
