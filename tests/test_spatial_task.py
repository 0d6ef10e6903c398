"""Spatial tasks: the rotation log, the angular Jacobian and the 6 x n manipulability
against closed forms and the analytic geometric Jacobian; pose IK and
``Problem.from_task`` with positions and orientations on the Gough-Stewart platform
(whose pose is its coordinates: a closed-form inverse) and (slow) on URDF arms, checked
with Pinocchio's forward kinematics of the same file; a 3-D workspace box on a solve."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj
import jtraj.robots as robots
from jtraj.robots.gough_stewart import rpy_matrix
from jtraj.robots.spatial_ik import angular_jacobian, pose_ik, rotation_log, solve_pose

from test_spatial import BUILTIN, PinocchioArm, _data_dir


def _expm(w):
    """Rodrigues' formula: the rotation of rotation vector w."""
    th = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / max(th, 1e-300)
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def test_rotation_log_inverts_rodrigues():
    rng = np.random.default_rng(0)
    for th in (1e-9, 1e-3, 0.5, 2.0, 3.0, np.pi - 1e-4, np.pi):
        axis = rng.standard_normal(3)
        axis /= np.linalg.norm(axis)
        w = np.asarray(rotation_log(jnp.asarray(_expm(th * axis))))
        np.testing.assert_allclose(_expm(w), _expm(th * axis), atol=1e-9)
        assert abs(np.linalg.norm(w) - th) < 1e-7
    assert np.linalg.norm(np.asarray(rotation_log(jnp.eye(3)))) == 0.0


@pytest.fixture(scope="module")
def ur5():
    _data_dir()
    return robots.get("ur5")


def test_angular_jacobian_and_6xn_manipulability(ur5):
    rng = np.random.default_rng(1)
    q = jnp.asarray(rng.uniform(-2, 2, 6))
    J6 = np.asarray(jax.jit(lambda x: ur5.geometric_jacobian(x))(q))
    # autodiff of the rotation against the analytic angular rows
    np.testing.assert_allclose(np.asarray(jax.jit(lambda x: angular_jacobian(ur5, x))(q)), J6[3:], atol=1e-12)
    # a 6-joint arm's manipulability is |det| of the full 6 x 6 Jacobian (wrist included)
    assert float(ur5.manipulability(q)) == pytest.approx(abs(np.linalg.det(J6)), rel=1e-9)
    # the UR5's wrist singularity (q_5 = 0: axes of joints 4 and 6 aligned) is seen by
    # the 6 x n measure and not by the positional one
    qs = q.at[4].set(0.0)
    Jp = np.asarray(ur5.jacobian(qs))
    assert float(ur5.manipulability(qs)) < 1e-12
    assert np.sqrt(np.linalg.det(Jp @ Jp.T)) > 1e-3
    # the singularity term of the cost is the inverse of it
    p = jtraj.Problem(ur5, np.asarray(q), np.asarray(q) + 0.1, N=4, weights=jtraj.Weights(singularity=1.0))
    tr = jtraj.transcription.Transcription("decoupled")
    w = jnp.concatenate([q, jnp.zeros(6), jnp.zeros(6), jnp.asarray([0.05])])
    sd = jax.tree.map(lambda a: a[0], tr.stage_data(p))
    term = jax.jit(lambda w_: tr.stage_cost_terms(p, w_, sd)["singularity"])(w)
    assert float(term) == pytest.approx(0.05 / abs(np.linalg.det(J6)), rel=1e-9)


def test_gough_stewart_pose_ik_and_from_task():
    """The platform's coordinates are its pose: the IK must return the pose itself."""
    gs = robots.get("gough_stewart")
    q_true = np.array([0.05, -0.04, 1.05, 0.1, -0.15, 0.2])
    p, R = q_true[:3], np.asarray(rpy_matrix(jnp.asarray(q_true[3:])))
    res = pose_ik(gs, p, R)
    assert int(res.status) == 0 and float(res.error) <= 1e-10 and float(res.rot_error) <= 1e-10
    np.testing.assert_allclose(np.asarray(res.q), q_true, atol=1e-9)
    q_goal = np.array([-0.05, 0.06, 1.1, -0.1, 0.1, -0.2])
    prob = jtraj.Problem.from_task(gs, p, q_goal[:3], R_start=R, R_goal=np.asarray(rpy_matrix(jnp.asarray(q_goal[3:]))),
                                   N=10)
    np.testing.assert_allclose(np.asarray(prob.q_start), q_true, atol=1e-9)
    np.testing.assert_allclose(np.asarray(prob.q_goal), q_goal, atol=1e-9)
    # an unreachable goal: the message carries the status and the residuals
    with pytest.raises(ValueError, match=r"p_goal = .*unreachable.*IK status 1.*position residual .* m, "
                                         r"orientation residual"):
        jtraj.Problem.from_task(gs, p, [0.0, 0.0, 3.0], R_start=R, R_goal=R, N=10)
    with pytest.raises(ValueError, match="R_goal needs a spatial robot"):
        jtraj.Problem.from_task(robots.get("serial3"), [1.0, 0.5], [0.5, 1.0], R_goal=np.eye(3))
    with pytest.raises(ValueError, match="rotation must be a rotation matrix"):
        pose_ik(gs, p, 2 * np.eye(3))


def _pin_pose(name, robot, q):
    path, tip = BUILTIN[name]
    ref = PinocchioArm(_data_dir() / path, robot.joint_names, tip)
    _, _, p, R, _ = ref.evaluate(np.asarray(q), np.zeros(robot.n), np.zeros(robot.n))
    return p, R


@pytest.mark.slow
@pytest.mark.parametrize("name", ["ur5", "panda"])
def test_pose_ik_on_urdf_arms_against_pinocchio(name):
    pytest.importorskip("pinocchio")
    robot = robots.get(name)
    lim = robot.limits
    lo, hi = np.asarray(lim.q_min), np.asarray(lim.q_max)
    lo, hi = np.where(np.isfinite(lo), lo, -np.pi), np.where(np.isfinite(hi), hi, np.pi)
    rng = np.random.default_rng(2)
    Q = rng.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), (4, robot.n))
    for q in Q:
        p, R = _pin_pose(name, robot, q)  # targets from Pinocchio, not from jtraj
        res = solve_pose(robot, p, R)
        assert int(res.status) == 0, (int(res.status), float(res.error), float(res.rot_error))
        p2, R2 = _pin_pose(name, robot, np.asarray(res.q))
        assert np.linalg.norm(p2 - p) < 1e-9 and np.linalg.norm(R2 - R) < 1e-9
        assert np.all(np.asarray(res.q) >= np.asarray(lim.q_min)) and np.all(np.asarray(res.q) <= np.asarray(lim.q_max))
        # position only, vmapped over starts: every start reaches the point
        starts = jnp.asarray(rng.uniform(lo, hi, (3, robot.n)))
        many = jax.vmap(lambda q0: pose_ik(robot, p, None, q0))(starts)
        ok = np.asarray(many.status) == 0
        assert ok.any()
        for qq in np.asarray(many.q)[ok]:
            assert np.linalg.norm(_pin_pose(name, robot, qq)[0] - p) < 1e-9
    if robot.n > 6:  # redundant: the null-space term pulls towards mid-range, same pose
        mid = (lo + hi) / 2
        half2 = ((hi - lo) / 2) ** 2
        w = half2.min() / half2
        q0 = jnp.asarray(Q[0] + 0.3 * (hi - Q[0]))
        p, R = _pin_pose(name, robot, Q[1])
        with_null = pose_ik(robot, p, R, q0, max_iter=600)
        without = pose_ik(robot, p, R, q0, null_gain=0.0, max_iter=600)
        assert int(with_null.status) == 0 and int(without.status) == 0

        def spread(q):
            return float(np.sum(w * (np.asarray(q) - mid) ** 2))

        assert spread(with_null.q) < spread(without.q)


@pytest.mark.slow
def test_from_task_pose_on_ur5_and_workspace_box():
    """Problem.from_task with positions and orientations on the UR5, the ends checked
    with Pinocchio; then a 3-D workspace box whose face cuts the free optimum's path:
    the bounded solve keeps every sample's tool point (by Pinocchio) inside it."""
    pytest.importorskip("pinocchio")
    ur5 = robots.get("ur5")
    # a swing of the base joint through 1.6 rad: the tool moves on an arc that bulges out
    # of the box spanned by its ends
    qa = np.array([-0.8, -1.2, 1.4, -1.6, -1.5, 0.0])
    qb = qa + np.array([1.6, 0.2, -0.2, 0.2, 0.2, 0.3])
    (pa, Ra), (pb, Rb) = _pin_pose("ur5", ur5, qa), _pin_pose("ur5", ur5, qb)
    prob = jtraj.Problem.from_task(ur5, pa, pb, R_start=Ra, R_goal=Rb, N=20,
                                   weights=jtraj.Weights(time=1.0, energy=0.1))
    for q, (p, R) in ((prob.q_start, (pa, Ra)), (prob.q_goal, (pb, Rb))):
        p2, R2 = _pin_pose("ur5", ur5, np.asarray(q))
        assert np.linalg.norm(p2 - p) < 1e-9 and np.linalg.norm(R2 - R) < 1e-9
    free = jtraj.solve(prob)
    assert bool(free.converged), free.status_message
    # the face of the box: halfway into the free path's largest excursion beyond the
    # ends' range (an axis and a side along which the free motion bulges out)
    path = np.asarray(jax.vmap(ur5.forward_kinematics)(free.q))
    ends = np.stack([pa, pb])
    over, under = path.max(axis=0) - ends.max(axis=0), ends.min(axis=0) - path.min(axis=0)
    axis = int(np.argmax(np.maximum(over, under)))
    upper = over[axis] >= under[axis]
    bulge = max(over[axis], under[axis])
    assert bulge > 0.01
    ws = np.array([[-2.0, -2.0, -2.0], [2.0, 2.0, 2.0]])
    if upper:
        ws[1, axis] = ends[:, axis].max() + bulge / 2
    else:
        ws[0, axis] = ends[:, axis].min() - bulge / 2
    boxed_robot = robots.get("ur5", workspace=ws)
    boxed = jtraj.solve(jtraj.Problem(boxed_robot, prob.q_start, prob.q_goal, N=20,
                                      weights=jtraj.Weights(time=1.0, energy=0.1)))
    assert bool(boxed.converged), boxed.status_message
    tool = np.array([_pin_pose("ur5", ur5, q)[0] for q in np.asarray(boxed.q)])  # Pinocchio's tool points
    assert np.all(tool >= ws[0] - 1e-6) and np.all(tool <= ws[1] + 1e-6)
    assert float(boxed.cost) >= float(free.cost) * (1 - 1e-6)
