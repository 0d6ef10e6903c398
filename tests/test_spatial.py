"""Spatial serial arms from URDF against Pinocchio models of the same files (RNEA, CRBA,
tip placement, frame Jacobian), the Lagrangian path against the Newton-Euler one, and
from_urdf's validation of bad input."""

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj
import jtraj.robots as robots
from jtraj.problem import orientation_error
from jtraj.robots import Robot, from_urdf
from jtraj import _testing

BUILTIN = {  # name -> (file under the robots folder, tip frame)
    "panda": ("panda_description/urdf/panda.urdf", "panda_link8"),
    "ur5": ("ur_description/urdf/ur5_robot.urdf", "tool0"),
    "ur10": ("ur_description/urdf/ur10_robot.urdf", "tool0"),
    "kinova": ("kinova_description/robots/kinova.urdf", "j2s6s200_end_effector"),
    "so100": ("so_arm_description/urdf/so100.urdf", "gripper"),
}


def _data_dir():
    from jtraj.robots.urdf import robot_data_dir

    try:
        return robot_data_dir()
    except ImportError:
        pytest.skip("example-robot-data is not installed")


def rel_err(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)


class PinocchioArm:
    """The full Pinocchio model of a URDF file, evaluated on one chain of it: the other
    joints at 0 (where jtraj locks them), at rest; continuous joints as (cos, sin)."""

    def __init__(self, path, joint_names, tip):
        import pinocchio as pin

        self.pin = pin
        self.model = pin.buildModelFromUrdf(str(path))
        self.data = self.model.createData()
        frames = [i for i, f in enumerate(self.model.frames) if f.name == tip
                  and f.type in (pin.FrameType.BODY, pin.FrameType.FIXED_JOINT)]
        self.frame = frames[0]
        ids = [self.model.getJointId(nm) for nm in joint_names]
        self.q_idx = [self.model.idx_qs[j] for j in ids]
        self.nq_of = [self.model.nqs[j] for j in ids]
        self.v_idx = [self.model.idx_vs[j] for j in ids]

    def q(self, q):
        qp = self.pin.neutral(self.model)
        for k, (i, nq) in enumerate(zip(self.q_idx, self.nq_of)):
            qp[i:i + nq] = (np.cos(q[k]), np.sin(q[k])) if nq == 2 else (q[k],)
        return qp

    def v(self, v):
        out = np.zeros(self.model.nv)
        out[self.v_idx] = v
        return out

    def evaluate(self, q, qd, qdd):
        pin, m, d = self.pin, self.model, self.data
        qp = self.q(q)
        tau = pin.rnea(m, d, qp, self.v(qd), self.v(qdd))[self.v_idx]
        M = pin.crba(m, d, qp)
        M = (np.triu(M) + np.triu(M, 1).T)[np.ix_(self.v_idx, self.v_idx)]
        pin.framesForwardKinematics(m, d, qp)
        placement = d.oMf[self.frame]
        J = pin.computeFrameJacobian(m, d, qp, self.frame, pin.LOCAL_WORLD_ALIGNED)[:, self.v_idx]
        return tau, M, np.array(placement.translation), np.array(placement.rotation), J


def _states(robot, rng, count):
    lim = robot.limits
    lo = np.where(np.isfinite(lim.q_min), lim.q_min, -np.pi) if lim.q_min is not None else -np.pi * np.ones(robot.n)
    hi = np.where(np.isfinite(lim.q_max), lim.q_max, np.pi) if lim.q_max is not None else np.pi * np.ones(robot.n)
    q = rng.uniform(lo, hi, (count, robot.n))
    qd = rng.uniform(-1, 1, (count, robot.n)) * np.asarray(lim.qd_max)
    qdd = rng.uniform(-1, 1, (count, robot.n)) * np.asarray(lim.qdd_max)
    return q, qd, qdd


@pytest.mark.parametrize("newton_euler", ["world", "bodies"])
@pytest.mark.parametrize("name", sorted(BUILTIN))
def test_builtin_against_pinocchio(name, newton_euler):
    """100 random states within the limits: inverse dynamics (both formulations of the
    recursive Newton-Euler pass), mass matrix, tip placement and tip Jacobian within
    1e-10 relative (per state, relative to its largest entry)."""
    pytest.importorskip("pinocchio")
    path, tip = BUILTIN[name]
    ref = PinocchioArm(_data_dir() / path, robots.get(name).joint_names, tip)
    robot = robots.get(name).replace(newton_euler=newton_euler)

    @jax.jit
    @jax.vmap
    def ours(q, qd, qdd):
        p, R = robot.tip_pose(q)
        return (robot.inverse_dynamics(q, qd, qdd), robot.mass_matrix(q), p, R, robot.geometric_jacobian(q))

    q, qd, qdd = _states(robot, np.random.default_rng(7), 100)
    got = [np.asarray(x) for x in ours(q, qd, qdd)]
    for k in range(100):
        tau, M, p, R, J = ref.evaluate(q[k], qd[k], qdd[k])
        assert rel_err(got[0][k], tau) < 1e-10, k
        assert rel_err(got[1][k], M) < 1e-10, k
        assert np.max(np.abs(got[2][k] - p)) < 1e-10 * max(1.0, np.abs(p).max()), k
        assert np.max(np.abs(got[3][k] - R)) < 1e-10, k
        assert rel_err(got[4][k], J) < 1e-10, k


def test_effort_jacobian_against_pinocchio_and_forward_mode():
    """The efforts' Jacobian of the interior-point model (reverse mode through the
    Newton-Euler pass, :func:`jtraj.solver.curvature.effort_jacobian`) on the Panda at 20
    random states: Pinocchio's analytical derivatives of its RNEA (d tau/dq, d tau/dqd,
    and M = d tau/dqdd) within 1e-9 relative, forward mode within 1e-12."""
    pytest.importorskip("pinocchio")
    import pinocchio as pin

    from jtraj.solver.curvature import effort_jacobian

    robot = robots.get("panda")
    n = robot.n
    ref = PinocchioArm(_data_dir() / BUILTIN["panda"][0], robot.joint_names, BUILTIN["panda"][1])

    def tau_of(x, a):
        return robot.inverse_dynamics(x[:n], x[n:], a)

    @jax.jit
    @jax.vmap
    def both(x, a):
        tau, J = effort_jacobian(tau_of, x, a)
        Jx, Ja = jax.jacfwd(tau_of, argnums=(0, 1))(x, a)
        return tau, J, jnp.concatenate([Jx, Ja], axis=1)

    q, qd, qdd = _states(robot, np.random.default_rng(11), 20)
    tau, J, J_fwd = (np.asarray(x) for x in both(np.concatenate([q, qd], 1), qdd))
    v = ref.v_idx
    for k in range(20):
        pin.computeRNEADerivatives(ref.model, ref.data, ref.q(q[k]), ref.v(qd[k]), ref.v(qdd[k]))
        M = np.triu(ref.data.M) + np.triu(ref.data.M, 1).T
        J_pin = np.concatenate([ref.data.dtau_dq[np.ix_(v, v)], ref.data.dtau_dv[np.ix_(v, v)], M[np.ix_(v, v)]], 1)
        assert rel_err(J[k], J_pin) < 1e-9, k
        assert rel_err(J[k], J_fwd[k]) < 1e-12, k
        assert rel_err(tau[k], ref.evaluate(q[k], qd[k], qdd[k])[0]) < 1e-10, k


def test_builtin_structure():
    pytest.importorskip("pinocchio")
    _data_dir()
    panda = robots.get("panda")
    assert panda.n == 7 and panda.joint_names == tuple(f"panda_joint{i}" for i in range(1, 8))
    assert np.allclose(panda.limits.qdd_max, (15, 7.5, 10, 12.5, 15, 20, 20))
    assert np.allclose(panda.limits.tau_max, (87, 87, 87, 87, 12, 12, 12))
    assert np.allclose(panda.limits.q_max[3], -0.0698)
    ur5 = robots.get("ur5")
    assert ur5.n == 6 and ur5.joint_names[0] == "shoulder_pan_joint"
    kinova = robots.get("kinova")
    assert np.isinf(np.asarray(kinova.limits.q_min)[[0, 3, 5]]).all()  # continuous joints
    assert {"panda", "ur5"} <= set(robots.names())
    # the payload: masses are a parameter, overridable and positive
    assert "masses" in robots.parameter_names("panda")
    heavier = robots.get("panda", masses=np.asarray(panda.masses) + np.r_[np.zeros(6), 1.0])
    assert float(heavier.masses[-1]) == pytest.approx(float(panda.masses[-1]) + 1.0)
    with pytest.raises(ValueError, match="masses must be > 0"):
        robots.get("panda", masses=np.zeros(7))


# ----- a small hand-written arm (no package data): both dynamics paths -----------------
ARM = """<robot name="arm3">
  <link name="base"/>
  <link name="l1"><inertial><origin xyz="0 0 0.2" rpy="0.1 0 0"/><mass value="2.0"/>
    <inertia ixx="0.03" ixy="0.001" ixz="0" iyy="0.025" iyz="0" izz="0.01"/></inertial></link>
  <link name="l2"><inertial><origin xyz="0.15 0.02 0" rpy="0 0.3 0.2"/><mass value="1.5"/>
    <inertia ixx="0.004" ixy="0" ixz="0.0005" iyy="0.02" iyz="0" izz="0.02"/></inertial></link>
  <link name="l3"><inertial><origin xyz="0 0 0.05"/><mass value="0.8"/>
    <inertia ixx="0.002" ixy="0" ixz="0" iyy="0.002" iyz="0" izz="0.001"/></inertial></link>
  <link name="flange"/>
  <link name="tool"><inertial><origin xyz="0 0 0.03"/><mass value="0.3"/>
    <inertia ixx="0.0002" ixy="0" ixz="0" iyy="0.0002" iyz="0" izz="0.0001"/></inertial></link>
  <joint name="j1" type="continuous"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.1"/><axis xyz="0 0 1"/><limit effort="50" velocity="2"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0 0 0.4" rpy="-1.5707963 0 0.2"/><axis xyz="0 1 1"/>
    <limit lower="-2" upper="2" effort="30" velocity="2"/></joint>
  <joint name="j3" type="prismatic"><parent link="l2"/><child link="l3"/>
    <origin xyz="0.3 0 0" rpy="0 1.5707963 0"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="0.3" effort="100" velocity="0.5"/></joint>
  <joint name="fl" type="fixed"><parent link="l3"/><child link="flange"/><origin xyz="0 0 0.1" rpy="0 0 0.5"/></joint>
  <joint name="tl" type="fixed"><parent link="flange"/><child link="tool"/><origin xyz="0.01 0 0.02"/></joint>
</robot>"""


@pytest.fixture(scope="module")
def arm():
    return from_urdf(ARM)


def test_small_arm_paths_agree(arm):
    """Newton-Euler (rigid_body_forces), Jacobian mass matrix and the overridden
    Coriolis/gravity terms against the Lagrangian path of the energies; forward dynamics
    inverts inverse dynamics; the positional Jacobian is the derivative of the tip."""
    assert arm.joint_names == ("j1", "j2", "j3") and arm.n == 3
    assert arm.joint_types == ("revolute", "revolute", "prismatic")

    @jax.jit
    def both(q, qd, qdd):
        lagrange = (_testing.mass_matrix_mechanism(arm, q) @ qdd + Robot.coriolis(arm, q, qd)
                    + Robot.gravity(arm, q))
        tau = arm.inverse_dynamics(q, qd, qdd)
        return (arm.rigid_body_forces(q, qd, qdd), lagrange, arm.mass_matrix(q), _testing.mass_matrix_mechanism(arm, q),
                arm.forward_dynamics(q, qd, tau), arm.jacobian(q), jax.jacfwd(arm.forward_kinematics)(q),
                arm.coriolis(q, qd), Robot.coriolis(arm, q, qd))

    rng = np.random.default_rng(3)
    for _ in range(10):
        q = np.r_[rng.uniform(-3, 3), rng.uniform(-2, 2), rng.uniform(0, 0.3)]
        qd, qdd = rng.uniform(-2, 2, 3), rng.uniform(-3, 3, 3)
        ne, lag, M, M_lag, qdd_back, J, J_ad, c, c_lag = (np.asarray(x) for x in both(q, qd, qdd))
        assert rel_err(ne, lag) < 1e-11
        assert rel_err(M, M_lag) < 1e-12
        assert rel_err(c, c_lag) < 1e-11
        assert np.max(np.abs(qdd_back - qdd)) < 1e-10
        assert rel_err(J, J_ad) < 1e-12
        assert np.linalg.eigvalsh(M).min() > 0


def _forms_agree(robot, q, qd, qdd):
    """The body-frame Newton-Euler pass (``newton_euler="bodies"``) against the world-frame
    one on a batch of states: the efforts, Coriolis and gravity terms within 1e-12
    relative (per state), their first derivatives (reverse and forward mode) within
    1e-12 and the forward-over-reverse Hessian of ``lam . tau`` within 1e-10 relative."""
    n = robot.n
    lam = jnp.linspace(0.5, 1.5, n)

    def pieces(r, q, qd, qdd):
        def tau(x):
            return r.rigid_body_forces(x[:n], x[n:2 * n], x[2 * n:])

        x = jnp.concatenate([q, qd, qdd])
        return (r.rigid_body_forces(q, qd, qdd), r.coriolis(q, qd), r.gravity(q), jax.jacrev(tau)(x),
                jax.jacfwd(tau)(x), jax.jacfwd(jax.grad(lambda x: lam @ tau(x)))(x))

    run = jax.jit(jax.vmap(pieces, in_axes=(None, 0, 0, 0)))
    world = run(robot.replace(newton_euler="world"), q, qd, qdd)
    bodies = run(robot.replace(newton_euler="bodies"), q, qd, qdd)
    for k, (a, b) in enumerate(zip(world, bodies)):
        a, b = np.asarray(a), np.asarray(b)
        for j in range(len(q)):
            assert rel_err(b[j], a[j]) < (1e-10 if k == 5 else 1e-12), (k, j)


# (each robot compiles its derivatives twice, about 20 s: the default suite checks the panda;
# the other arm and the prismatic one, which the Pinocchio tests also cover, run with -m slow)
@pytest.mark.parametrize("name", ["panda", pytest.param("ur5", marks=pytest.mark.slow)])
def test_newton_euler_forms_agree(name):
    pytest.importorskip("pinocchio")
    _data_dir()
    robot = robots.get(name)
    _forms_agree(robot, *_states(robot, np.random.default_rng(5), 30))


@pytest.mark.slow
def test_newton_euler_forms_agree_with_a_prismatic_joint(arm):
    rng = np.random.default_rng(6)
    q = np.c_[rng.uniform(-3, 3, 30), rng.uniform(-2, 2, 30), rng.uniform(0, 0.3, 30)]
    _forms_agree(arm, q, rng.uniform(-2, 2, (30, 3)), rng.uniform(-3, 3, (30, 3)))


def test_newton_euler_form_is_validated(arm):
    with pytest.raises(ValueError, match="newton_euler must be one of"):
        arm.replace(newton_euler="body")


def test_small_arm_against_pinocchio(arm, tmp_path):
    pytest.importorskip("pinocchio")
    path = tmp_path / "arm3.urdf"
    path.write_text(ARM)
    ref = PinocchioArm(path, arm.joint_names, "tool")
    tool = from_urdf(path, tip_link="tool")  # a tip behind two fixed joints
    assert rel_err(tool.masses, arm.masses) < 1e-15  # the tool rides on body 3 either way
    bodies = tool.replace(newton_euler="bodies")
    ours = jax.jit(lambda q, qd, qdd: (tool.inverse_dynamics(q, qd, qdd), tool.mass_matrix(q), *tool.tip_pose(q),
                                       tool.geometric_jacobian(q), bodies.inverse_dynamics(q, qd, qdd)))
    rng = np.random.default_rng(4)
    for _ in range(10):
        q = np.r_[rng.uniform(-3, 3), rng.uniform(-2, 2), rng.uniform(0, 0.3)]
        qd, qdd = rng.uniform(-2, 2, 3), rng.uniform(-3, 3, 3)
        tau, M, p, R, J = ref.evaluate(q, qd, qdd)
        tau_o, M_o, p_o, R_o, J_o, tau_b = (np.asarray(x) for x in ours(q, qd, qdd))
        assert rel_err(tau_o, tau) < 1e-10
        assert rel_err(tau_b, tau) < 1e-10
        assert rel_err(M_o, M) < 1e-10
        assert np.max(np.abs(p_o - p)) < 1e-12 and np.max(np.abs(R_o - R)) < 1e-12
        assert rel_err(J_o, J) < 1e-10


def test_small_arm_limits_and_manipulability(arm):
    lim = arm.limits
    assert np.isinf(lim.q_min[0]) and np.isinf(lim.q_max[0])  # continuous
    assert np.allclose(lim.q_min[1:], (-2, 0)) and np.allclose(lim.q_max[1:], (2, 0.3))
    assert np.allclose(lim.tau_max, (50, 30, 100)) and np.allclose(lim.qd_max, (2, 2, 0.5))
    assert np.allclose(lim.qdd_max, 10.0) and lim.qddd_max is None
    q = jnp.array([0.3, 0.4, 0.1])
    J6 = arm.geometric_jacobian(q)
    assert J6.shape == (6, 3)
    w = float(arm.manipulability(q))  # 3 x 3 positional Jacobian: |det J|
    assert w == pytest.approx(abs(float(jnp.linalg.det(J6[:3]))), rel=1e-12)
    custom = from_urdf(ARM, limits=dict(tau_max=(10, 10, 10)), qdd_max=(1, 2, 3), qddd_max=100.0)
    assert np.allclose(custom.limits.tau_max, 10) and np.allclose(custom.limits.qdd_max, (1, 2, 3))
    assert np.allclose(custom.limits.qddd_max, 100)


def test_manipulability_of_an_arm_with_fewer_joints_than_task_coordinates():
    """Two joints and a 3-D task point: ``J J^T`` (3 x 3) is singular everywhere, so the
    manipulability is the product of J's singular values, ``sqrt(det(J^T J))`` (NumPy's
    SVD the reference), with a gradient that matches central differences; at a
    singular configuration (serial3 stretched out) it is 0 with a zero gradient, not NaN."""
    from helpers import arm_urdf

    arm2 = from_urdf(arm_urdf(), tip_link="tool")
    assert arm2.n == 2
    w, jac = jax.jit(lambda q: arm2.manipulability(q)), jax.jit(lambda q: arm2.jacobian(q))
    grad = jax.jit(jax.grad(lambda q: arm2.manipulability(q)))
    for q in (jnp.array([0.3, 0.4]), jnp.array([-1.0, 1.2])):
        sv = np.linalg.svd(np.asarray(jac(q)), compute_uv=False)
        assert float(w(q)) == pytest.approx(float(np.prod(sv)), rel=1e-12)
        assert float(np.prod(sv)) > 1e-3
        fd = [(float(w(q + d)) - float(w(q - d))) / 2e-6 for d in 1e-6 * jnp.eye(2)]
        assert rel_err(np.asarray(grad(q)), np.array(fd)) < 1e-7
    s3 = jtraj.robots.get("serial3")
    ws, gs = s3.manipulability(jnp.zeros(3)), jax.grad(s3.manipulability)(jnp.zeros(3))
    assert float(ws) == 0.0 and np.all(np.asarray(gs) == 0.0)


def test_payload_sensitivity_is_differentiable(arm):
    """d tau / d (mass of body 3) by autodiff against a central difference."""
    q, qd, qdd = jnp.array([0.2, 0.5, 0.1]), jnp.array([0.3, -0.2, 0.1]), jnp.array([1.0, -0.5, 0.2])

    def tau(m3):
        r = dataclasses.replace(arm, masses=arm.masses.at[2].set(m3))
        return r.inverse_dynamics(q, qd, qdd)

    m3 = float(arm.masses[2])
    fd = (np.asarray(tau(m3 + 1e-6)) - np.asarray(tau(m3 - 1e-6))) / 2e-6
    assert rel_err(jax.jacfwd(tau)(m3), fd) < 1e-7


# ----- bad input -------------------------------------------------------------------------
def _urdf(body):
    return f'<robot name="bad">{body}</robot>'


LINK = ('<link name="{}"><inertial><mass value="1"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" '
        'izz="0.01"/></inertial></link>')
LIMIT = '<limit lower="-1" upper="1" effort="10" velocity="1"/>'


def _joint(name, parent, child, kind="revolute", extra=LIMIT):
    return f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>{extra}</joint>'


GOOD = LINK.format("a") + LINK.format("b") + _joint("j", "a", "b")

BAD = {
    "missing file": ("/nonexistent/arm.urdf", {}, "no URDF file"),
    "malformed XML": ("<robot><link name='a'></robot>", {}, "malformed XML"),
    "floating joint": (_urdf(GOOD + LINK.format("c") + _joint("f", "b", "c", "floating", "")), {},
                       "'f'.*floating or planar"),
    "planar joint": (_urdf(GOOD + LINK.format("c") + _joint("f", "b", "c", "planar", "")), {}, "'f'.*planar"),
    "closed loop": (_urdf(GOOD + LINK.format("c") + _joint("k", "a", "c") + _joint("loop", "c", "b")), {},
                    "'b'.*two parent joints.*closed kinematic loop"),
    "unknown tip": (_urdf(GOOD), {"tip_link": "hand"}, "tip_link 'hand' is not a link"),
    "tip not below base": (_urdf(GOOD + LINK.format("c") + _joint("k", "a", "c")), {"base_link": "b", "tip_link": "c"},
                           "tip_link 'c' is not in the tree below base_link 'b'"),
    "mimic in chain": (_urdf(GOOD + LINK.format("c") + _joint("m", "b", "c", extra=LIMIT + '<mimic joint="j"/>')), {},
                       "'m'.*mimic joint in the chain"),
    "zero mass": (_urdf(LINK.format("a") + '<link name="b"/>' + _joint("j", "a", "b")), {},
                  "'b'.*no mass.*expected a positive <mass>"),
    "indefinite inertia": (_urdf(LINK.format("a") + '<link name="b"><inertial><mass value="1"/><inertia ixx="0.01" '
                                 'ixy="0.5" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>'
                                 + _joint("j", "a", "b")), {}, "'b'.*positive semidefinite"),
    "singular inertia": (_urdf(LINK.format("a") + '<link name="b"><inertial><mass value="1"/><inertia ixx="0" '
                               'ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/></inertial></link>'
                               + _joint("j", "a", "b")), {}, "'b'.*positive definite"),
    "no limit": (_urdf(LINK.format("a") + LINK.format("b") + _joint("j", "a", "b", extra="")), {},
                 "'j'.*expected <limit lower=... upper=...>"),
    "ambiguous tip": (_urdf(GOOD + LINK.format("c") + _joint("k", "a", "c")), {},
                      r"end in \['b', 'c'\]; expected exactly one"),
    "no movable joint": (_urdf(GOOD + LINK.format("c") + _joint("k", "b", "c", "fixed", "")),
                         {"base_link": "b", "tip_link": "c"}, "no movable joint"),
    "bad origin": (_urdf(LINK.format("a") + LINK.format("b") + _joint("j", "a", "b", extra=LIMIT + '<origin xyz="0 1"/>')),
                   {}, "'j'.*<origin xyz>: expected 3 finite numbers"),
    "xacro macros": ('<robot name="x" xmlns:xacro="http://wiki.ros.org/xacro"><xacro:include filename="arm.xacro"/>'
                     + GOOD + '</robot>', {}, "holds xacro macros, not plain URDF; expand the file first: xacro"),
    "xacro expression": (_urdf(LINK.format("a") + LINK.format("b").replace('value="1"', 'value="${m}"')
                               + _joint("j", "a", "b")), {},
                         r"'b'.*<mass>: attribute value must be a number, got '\$\{m\}' \(a xacro expression"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input(case):
    source, kwargs, message = BAD[case]
    with pytest.raises(ValueError, match=message):
        from_urdf(source, **kwargs)


def test_a_bad_inertia_counts_only_where_it_moves_with_the_chain():
    """A link with an indefinite inertia (a tiny part's rounded data, as on some mobile
    manipulators' bases) fixed to the base or on a branch the chain does not reach leaves
    the arm loadable; fixed to a moving body it is refused, naming the link."""
    bad = ('<link name="antenna"><inertial><mass value="1e-6"/><inertia ixx="2.4e-8" ixy="6.1e-8" ixz="1.2e-8" '
           'iyy="2.8e-8" iyz="7.7e-9" izz="3.8e-8"/></inertial></link>')
    on_base = from_urdf(_urdf(GOOD + bad + _joint("fix", "a", "antenna", "fixed", "")))
    assert on_base.n == 1 and np.allclose(on_base.masses, from_urdf(_urdf(GOOD)).masses)
    with pytest.raises(ValueError, match="'antenna'.*positive semidefinite"):
        from_urdf(_urdf(GOOD + bad + _joint("fix", "b", "antenna", "fixed", "")))


def test_massless_link_carrying_a_fixed_child_is_merged():
    """A massless moving link is fine when a fixed child gives the body its mass; the
    body's inertia is the child's moved by the parallel-axis theorem."""
    src = _urdf(LINK.format("a") + '<link name="b"/>' + LINK.format("c") + _joint("j", "a", "b")
                + '<joint name="f" type="fixed"><parent link="b"/><child link="c"/><origin xyz="0 0 0.5"/></joint>')
    robot = from_urdf(src)
    assert robot.n == 1 and float(robot.masses[0]) == 1.0
    assert np.allclose(robot.com[0], (0, 0, 0.5)) and np.allclose(robot.inertias[0], 0.01 * np.eye(3))
    assert np.allclose(robot.tip_translation, (0, 0, 0))  # the default tip: the last movable joint's child
    assert np.allclose(from_urdf(src, tip_link="c").tip_translation, (0, 0, 0.5))


def test_missing_package_message(monkeypatch, tmp_path):
    from jtraj.robots import urdf

    monkeypatch.setenv("JTRAJ_ROBOT_DATA", str(tmp_path))
    with pytest.raises(ImportError, match=r"pip install 'jtraj\[robots\]'"):
        robots.get("panda")


def test_limits_missing_or_zero_in_the_file_come_from_the_arguments(tmp_path, capsys):
    """A file written for simulation only (example-robot-data's double pendulum writes
    lower = upper = effort = velocity = 0) is refused with every joint's problem and
    every limit to give in one message, in the command line's words there; given as
    arguments (``limits=``, the overrides, ``--robot-param``), the limits replace the
    file's and the arm loads with them."""
    from jtraj import cli

    zero = ARM.replace('effort="50" velocity="2"', 'effort="0" velocity="0"').replace(
        '<limit lower="-2" upper="2" effort="30" velocity="2"/>', '<limit lower="0" upper="0" effort="0" velocity="0"/>')
    with pytest.raises(ValueError) as info:
        from_urdf(zero)
    msg = str(info.value)
    assert "'j1'" in msg and "'j2'" in msg and "lower < upper, got 0.0 and 0.0" in msg, msg
    assert msg.endswith("(or limits=dict(q_min=..., q_max=..., qd_max=..., tau_max=...))"), msg
    box = dict(q_min=(-3.0, -2.0, 0.0), q_max=(3.0, 2.0, 0.3))
    a = from_urdf(zero, limits=box, qd_max=(1.5, 2.5, 0.5), tau_max=40.0)
    np.testing.assert_array_equal(np.asarray(a.limits.qd_max), [1.5, 2.5, 0.5])
    np.testing.assert_array_equal(np.asarray(a.limits.tau_max), [40.0, 40.0, 40.0])
    np.testing.assert_array_equal(np.asarray(a.limits.q_max), box["q_max"])

    from jtraj import dataset  # a dataset records the file and the limits, and loads the arm with them

    spec = dataset.make_spec(None, 4, 0, urdf=zero, robot_params={**box, "qd_max": 1.5, "tau_max": 40.0})
    np.testing.assert_array_equal(np.asarray(spec.robot_model().limits.qd_max), [1.5, 1.5, 1.5])

    path = tmp_path / "zero.urdf"
    path.write_text(zero)
    assert cli.main(["robots", "--urdf", str(path), "--robot-param", "qd_max=1.5"]) == 2
    err = capsys.readouterr().err
    assert "(or --robot-param q_min=... --robot-param q_max=... --robot-param tau_max=...)" in err, err
    given = ["--robot-param", "q_min=-3,-2,0", "--robot-param", "q_max=3,2,0.3", "--robot-param", "qd_max=1.5",
             "--robot-param", "tau_max=40"]
    assert cli.main(["robots", "--urdf", str(path), *given]) == 0
    out = capsys.readouterr().out
    assert re.search(r"qd_max +\[1\.5 1\.5 1\.5\]", out) and re.search(r"tau_max +\[40\. 40\. 40\.\]", out), out


# ----- the command line and the plots -----------------------------------------------------
@pytest.mark.parametrize("argv, needle", [
    (["--tip-link", "l3", "--start-q", "0,0,0", "--goal-q", "0,0,0"], "--tip-link needs --urdf"),
    (["--urdf", "/nonexistent/arm.urdf", "--start-q", "0,0,0", "--goal-q", "0,0,0"], "no URDF file"),
    (["--urdf", "{arm}", "--tip-link", "hand", "--start-q", "0,0,0", "--goal-q", "0,0,0"], "tip_link 'hand'"),
    (["--urdf", "{arm}", "--start-q", "0,0", "--goal-q", "0,0,0"], "--start-q must have 3 values"),
    (["--urdf", "{arm}", "--start-q", "0,0,0.1", "--goal-q", "0,0,0.4"], "--goal-q"),  # prismatic beyond 0.3 m
])
def test_cli_urdf_bad_input_exits_2(argv, needle, tmp_path, capsys):
    from jtraj import cli

    path = tmp_path / "arm3.urdf"
    path.write_text(ARM)
    rc = cli.main(["solve", *(a.format(arm=path) for a in argv)])
    err = capsys.readouterr().err
    assert rc == 2 and needle in err, err


def test_plot_path_in_3d(arm):
    """The tip path of a spatial arm is drawn in 3-D (the data of the drawn line is the
    forward kinematics of the given joint path)."""
    import types

    pytest.importorskip("matplotlib")
    from jtraj import Problem
    from jtraj.plotting import plot_path

    q0, q1 = np.array([0.0, 0.3, 0.05]), np.array([0.8, -0.2, 0.2])
    s = np.linspace(0, 1, 6)[:, None]
    q = q0 + s * (q1 - q0)
    sol = types.SimpleNamespace(q=q, qd=np.zeros_like(q), v=np.zeros((5, 3)), tau=np.zeros((5, 3)), h=np.full(5, 0.1))
    fig = plot_path(Problem(arm, q0, q1, N=5, validate=False), sol)
    ax = fig.axes[0]
    assert ax.name == "3d"
    line = [ln for ln in ax.lines if ln.get_label() == "optimum"][0]
    x, y, z = line.get_data_3d()
    tip = np.asarray(jax.vmap(arm.forward_kinematics)(q))
    assert np.allclose(np.c_[x, y, z], tip)


def test_continuous_joint_has_no_position_row(arm):
    """The decoupled transcription's joint box of an arm with a continuous joint: no row
    (-1) for that joint at any angle, finite rows for the others."""
    from jtraj import Problem
    from jtraj.transcription import Transcription

    problem = Problem(arm, np.array([0.0, 0.3, 0.05]), np.array([0.8, -0.2, 0.2]), N=20)
    tr = Transcription("decoupled")
    sd = tr.stage_data(problem)
    k = 5  # an inner sample
    sdk = jax.tree_util.tree_map(lambda x: x[k], sd)
    n = arm.n
    for q1 in (0.0, 7.0, -40.0):  # far beyond +-2 pi: still no row
        w = jnp.concatenate([jnp.array([q1, 1.9, 0.29]), jnp.zeros(n), jnp.zeros(n), jnp.array([0.05])])
        g = np.asarray(tr.stage_constraints(problem, w, sdk)[1]["q"])
        assert np.isfinite(g).all() and np.all(g[0] == -1.0)
        assert g[1, 0] == pytest.approx(1.9 / 2 - 1) and g[2, 0] == pytest.approx(0.29 / 0.15 - 1 - 1)


def test_orientation_passage_on_a_urdf_arm():
    """A URDF arm takes orientation passages: ``rotation(q)`` is the tip frame's rotation
    (Pinocchio-checked through ``tip_pose``), its passage error is 0 at the configuration
    that defines the passage, and sin(0.3) after an extra 0.3 rad turn of the last joint
    (the flange is fixed to the last body: the two orientations differ by that turn)."""
    robot = jtraj.robots.get("panda")
    lo, hi = np.asarray(robot.limits.q_min), np.asarray(robot.limits.q_max)
    q_mid = jnp.asarray((lo + hi) / 2)
    R_l = robot.rotation(q_mid)
    np.testing.assert_allclose(R_l, robot.tip_pose(q_mid)[1], atol=0)
    p = robot.forward_kinematics(q_mid)
    problem = jtraj.Problem(robot, q_mid - 0.1, q_mid + 0.1, N=10,
                            via_points=[jtraj.ViaPoint(point=p, tol=1e-3, rotation=R_l, rot_tol=1e-3)])
    assert problem.via_points[0].rotation.shape == (3, 3)
    assert float(jnp.linalg.norm(orientation_error(robot.rotation(q_mid), R_l))) < 1e-14
    turned = q_mid.at[6].add(0.3)
    err = float(jnp.linalg.norm(orientation_error(robot.rotation(turned), R_l)))
    assert abs(err - np.sin(0.3)) < 1e-12
