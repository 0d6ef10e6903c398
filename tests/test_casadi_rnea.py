"""The benchmark peers' CasADi RNEA against Pinocchio's: the 7-DOF Panda of
example-robot-data and a synthetic tree with every supported joint type."""

import numpy as np
import pytest

ca = pytest.importorskip("casadi")
pin = pytest.importorskip("pinocchio")


from jtraj_peers import casadi_rnea as CR  # noqa: E402


def rel_err(a, b):
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)


def check_against_pinocchio(model, rng, states=100, tol=1e-10):
    fn = CR.rnea_function(model)
    data = model.createData()
    lim = CR.model_limits(model)
    lo = np.where(np.isfinite(lim["q_min"]), lim["q_min"], -np.pi)
    hi = np.where(np.isfinite(lim["q_max"]), lim["q_max"], np.pi)
    worst = 0.0
    for _ in range(states):
        q = rng.uniform(lo, hi)
        qd, qdd = rng.uniform(-2, 2, model.nv), rng.uniform(-5, 5, model.nv)
        ref = np.array(pin.rnea(model, data, CR.pinocchio_configuration(model, q), qd, qdd))
        worst = max(worst, rel_err(np.array(fn(q, qd, qdd)).ravel(), ref))
    assert worst < tol, worst
    return fn


def test_panda_against_pinocchio():
    try:
        model = CR.panda_model()
    except FileNotFoundError as err:
        pytest.skip(str(err))
    assert model.nv == 7 and np.linalg.norm(model.gravity.linear - [0, 0, -9.81]) == 0
    fn = check_against_pinocchio(model, np.random.default_rng(0))
    # the mass matrix (d tau / d qdd) against CRBA, and gravity alone at rest
    q, qdd = ca.SX.sym("q", 7), ca.SX.sym("qdd", 7)
    M = ca.Function("M", [q], [ca.jacobian(fn(q, ca.SX.zeros(7), qdd), qdd)])
    data = model.createData()
    rng = np.random.default_rng(1)
    for _ in range(10):
        qq = rng.uniform(model.lowerPositionLimit, model.upperPositionLimit)
        ref = pin.crba(model, data, qq)
        ref = np.triu(ref) + np.triu(ref, 1).T
        assert rel_err(np.array(M(qq)), ref) < 1e-10
        z = np.zeros(7)
        assert rel_err(np.array(fn(qq, z, z)).ravel(), pin.computeGeneralizedGravity(model, data, qq)) < 1e-10


def test_mixed_joint_tree_against_pinocchio():
    """A branching tree: revolute about x/y/z, an unaligned revolute, a continuous joint,
    aligned and unaligned prismatic joints; random placements and inertias; gravity
    along a skew direction."""
    rng = np.random.default_rng(2)
    model = pin.Model()
    kinds = [pin.JointModelRX(), pin.JointModelPY(), pin.JointModelRevoluteUnaligned(np.array([0.3, -0.5, 0.8]) / np.sqrt(0.98)),
             pin.JointModelRUBZ(), pin.JointModelPrismaticUnaligned(np.array([0.6, 0.0, -0.8])),
             pin.JointModelRY(), pin.JointModelRZ()]
    parents = [0, 1, 2, 3, 2, 5, 1]  # joints 5 and 7 start new branches
    for i, (jm, par) in enumerate(zip(kinds, parents)):
        placement = pin.SE3(pin.exp3(rng.normal(size=3)), rng.uniform(-0.5, 0.5, 3))
        jid = model.addJoint(par, jm, placement, f"j{i}")
        A = rng.normal(size=(3, 3))
        model.appendBodyToJoint(jid, pin.Inertia(rng.uniform(0.5, 3), rng.uniform(-0.2, 0.2, 3),
                                                 A @ A.T + 0.1 * np.eye(3)), pin.SE3.Identity())
    model.gravity = pin.Motion(np.array([1.0, -2.0, -9.0]), np.zeros(3))
    model.lowerPositionLimit[:] = -2.0
    model.upperPositionLimit[:] = 2.0
    check_against_pinocchio(model, np.random.default_rng(3))


def test_unsupported_joint_is_named():
    model = pin.Model()
    model.addJoint(0, pin.JointModelSpherical(), pin.SE3.Identity(), "ball")
    with pytest.raises(ValueError, match="ball"):
        CR.rnea_function(model)
