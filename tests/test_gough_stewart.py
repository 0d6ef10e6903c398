"""The Gough-Stewart platform against independent references: geometry from SciPy's
rotations, the leg Jacobian against autodiff and central differences, the Lagrangian
inverse dynamics against the platform's Newton-Euler equations (massless legs), the leg
energies against finite differences of the bodies' positions, the actuator mapping and
its power balance, orientation passages, and a solve. Energy conservation and the
structural checks run for every registered robot in test_robots.py."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj
import jtraj.robots as robots
from jtraj.problem import orientation_error
from jtraj.robots.gough_stewart import rpy_rate_matrix

Rotation = pytest.importorskip("scipy.spatial.transform").Rotation


@pytest.fixture(scope="module")
def robot():
    return robots.get("gough_stewart")


def random_poses(robot, rng, k):
    lo, hi = np.asarray(robot.limits.q_min), np.asarray(robot.limits.q_max)
    return lo + (hi - lo) * rng.uniform(0.1, 0.9, (k, 6))


def scipy_rotation(q):
    # intrinsic z-y'-x'' (yaw psi, pitch theta, roll phi) = Rz(psi) Ry(theta) Rx(phi)
    return Rotation.from_euler("ZYX", [q[5], q[4], q[3]]).as_matrix()


def test_inverse_kinematics_against_geometry(robot):
    rng = np.random.default_rng(0)
    A, B = np.asarray(robot.base_points), np.asarray(robot.platform_points)
    lengths = eqx.filter_jit(robot.leg_lengths)
    rot = eqx.filter_jit(robot.rotation)
    for q in random_poses(robot, rng, 20):
        R = scipy_rotation(q)
        ref = np.array([np.linalg.norm(q[:3] + R @ B[i] - A[i]) for i in range(6)])
        np.testing.assert_allclose(rot(q), R, atol=1e-14)
        np.testing.assert_allclose(lengths(q), ref, rtol=1e-14)
        np.testing.assert_allclose(robot.forward_kinematics(jnp.asarray(q)), q[:3], atol=0)
    # the layout: base radius 1, platform radius 0.5, home legs all equal
    np.testing.assert_allclose(np.linalg.norm(A, axis=1), 1.0, rtol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(B, axis=1), 0.5, rtol=1e-14)
    home = jnp.array([0, 0, 1.0, 0, 0, 0])
    rho = np.asarray(lengths(home))
    assert np.ptp(rho) < 1e-14 and abs(rho[0] - 1.1764) < 1e-4


def test_rate_matrix_is_the_angular_velocity(robot):
    """omega = E(angles) angle_rates, with omega from central differences of R."""
    rng = np.random.default_rng(1)
    for q in random_poses(robot, rng, 5):
        rates = rng.uniform(-1, 1, 3)
        eps = 1e-6
        qp, qm = q.copy(), q.copy()
        qp[3:] += eps * rates
        qm[3:] -= eps * rates
        Rd = (scipy_rotation(qp) - scipy_rotation(qm)) / (2 * eps)
        W = Rd @ scipy_rotation(q).T  # world-frame skew(omega)
        omega = np.array([W[2, 1], W[0, 2], W[1, 0]])
        np.testing.assert_allclose(np.asarray(rpy_rate_matrix(jnp.asarray(q[3:]))) @ rates, omega, atol=1e-9)
        assert abs(np.linalg.det(np.asarray(rpy_rate_matrix(jnp.asarray(q[3:])))) - np.cos(q[4])) < 1e-14


def test_leg_jacobian_against_autodiff_and_differences(robot):
    rng = np.random.default_rng(2)
    J = eqx.filter_jit(robot.actuator_jacobian)
    J_ad = jax.jit(lambda q: jax.jacfwd(robot.leg_lengths)(q))
    lengths = eqx.filter_jit(robot.leg_lengths)
    for q in random_poses(robot, rng, 10):
        Jq = np.asarray(J(q))
        np.testing.assert_allclose(Jq, J_ad(q), atol=1e-13)
        eps = 1e-6
        fd = np.stack([(np.asarray(lengths(q + eps * e)) - np.asarray(lengths(q - eps * e))) / (2 * eps)
                       for e in np.eye(6)], axis=1)
        np.testing.assert_allclose(Jq, fd, atol=1e-8)


def newton_euler_leg_forces(robot, q, qd, qdd):
    """Leg forces of the platform with massless legs: each leg pushes the platform along
    its axis, so m (pdd + g e_z) = sum_i tau_i u_i and, about the centre of mass,
    I_w omegad + omega x I_w omega = sum_i (R b_i) x tau_i u_i (a 6 x 6 linear system)."""
    A, B = np.asarray(robot.base_points), np.asarray(robot.platform_points)
    m, I_b, g = float(robot.platform_mass), np.asarray(robot.platform_inertia), float(robot.gravity_accel)
    R = scipy_rotation(q)
    E = np.asarray(rpy_rate_matrix(jnp.asarray(q[3:])))
    eps = 1e-6  # dE/dt by central differences along the angle rates
    Ed = (np.asarray(rpy_rate_matrix(jnp.asarray(q[3:] + eps * qd[3:])))
          - np.asarray(rpy_rate_matrix(jnp.asarray(q[3:] - eps * qd[3:])))) / (2 * eps)
    omega = E @ qd[3:]
    omega_d = E @ qdd[3:] + Ed @ qd[3:]
    I_w = R @ I_b @ R.T
    Rb = B @ R.T
    d = q[:3] + Rb - A
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    G = np.concatenate([u.T, np.cross(Rb, u).T], axis=0)  # (6, 6): wrench of unit leg forces
    wrench = np.concatenate([m * (qdd[:3] + np.array([0, 0, g])), I_w @ omega_d + np.cross(omega, I_w @ omega)])
    return np.linalg.solve(G, wrench)


def test_inverse_dynamics_against_newton_euler(robot):
    """With massless legs the Lagrangian inverse dynamics is the platform's Newton-Euler
    balance; an asymmetric inertia tensor checks the rotational terms."""
    inertia = jnp.array([[4.0, 0.3, -0.2], [0.3, 3.0, 0.1], [-0.2, 0.1, 6.5]])
    light = robot.replace(cyl_mass=0.0, piston_mass=0.0, cyl_inertia=0.0, piston_inertia=0.0,
                          platform_inertia=inertia)
    ID = eqx.filter_jit(light.inverse_dynamics)
    rng = np.random.default_rng(3)
    for q in random_poses(robot, rng, 8):
        qd, qdd = rng.uniform(-0.5, 0.5, 6), rng.uniform(-3, 3, 6)
        ref = newton_euler_leg_forces(light, q, qd, qdd)
        np.testing.assert_allclose(ID(q, qd, qdd), ref, rtol=1e-7, atol=1e-7 * np.abs(ref).max())


def test_leg_energy_against_body_positions(robot):
    """The leg and platform energies from velocities of the bodies' points by central
    differences along qd: cylinder and piston centres on the leg axis, the legs'
    perpendicular angular velocity u x ud, the platform's body angular velocity."""
    A, B = np.asarray(robot.base_points), np.asarray(robot.platform_points)

    def bodies(q):
        R = scipy_rotation(q)
        d = q[:3] + B @ R.T - A
        rho = np.linalg.norm(d, axis=1)
        u = d / rho[:, None]
        Gc = A + float(robot.cyl_com) * u
        Gp = A + (rho - float(robot.piston_com))[:, None] * u
        return R, u, Gc, Gp

    T = eqx.filter_jit(robot.kinetic_energy)
    V = eqx.filter_jit(robot.potential_energy)
    rng = np.random.default_rng(4)
    g = float(robot.gravity_accel)
    for q in random_poses(robot, rng, 5):
        qd = rng.uniform(-0.5, 0.5, 6)
        eps = 1e-6
        (Rp, up, Gcp, Gpp), (Rm, um, Gcm, Gpm) = bodies(q + eps * qd), bodies(q - eps * qd)
        R, u, Gc, Gp = bodies(q)
        Rd, ud, vc, vp = ((a - b) / (2 * eps) for a, b in ((Rp, Rm), (up, um), (Gcp, Gcm), (Gpp, Gpm)))
        W = R.T @ Rd
        w = np.array([W[2, 1], W[0, 2], W[1, 0]])
        omega_leg = np.cross(u, ud)
        ref = (0.5 * float(robot.platform_mass) * qd[:3] @ qd[:3] + 0.5 * w @ np.asarray(robot.platform_inertia) @ w
               + 0.5 * float(robot.cyl_mass) * np.sum(vc**2) + 0.5 * float(robot.piston_mass) * np.sum(vp**2)
               + 0.5 * (float(robot.cyl_inertia) + float(robot.piston_inertia)) * np.sum(omega_leg**2))
        assert abs(float(T(q, qd)) - ref) < 1e-8 * ref
        V_ref = g * (float(robot.platform_mass) * q[2] + float(robot.cyl_mass) * Gc[:, 2].sum()
                     + float(robot.piston_mass) * Gp[:, 2].sum())
        assert abs(float(V(q)) - V_ref) < 1e-12 * V_ref


def test_actuator_mapping_and_power_balance(robot):
    """tau = J^-T Q and Q = J^T tau are inverse to each other; the legs' power
    tau . rhod equals the generalised power Q . qd (rhod by differences of the IK)."""
    rng = np.random.default_rng(5)
    to_act, to_gen = eqx.filter_jit(robot.generalized_to_actuator), eqx.filter_jit(robot.actuator_to_generalized)
    ID, gf = eqx.filter_jit(robot.inverse_dynamics), eqx.filter_jit(robot.generalized_forces)
    lengths = eqx.filter_jit(robot.leg_lengths)
    for q in random_poses(robot, rng, 8):
        Q = rng.uniform(-100, 100, 6)
        tau = np.asarray(to_act(q, Q))
        np.testing.assert_allclose(to_gen(q, tau), Q, rtol=1e-11, atol=1e-11 * np.abs(Q).max())
        np.testing.assert_allclose(to_act(q, to_gen(q, tau)), tau, rtol=1e-10, atol=1e-10 * np.abs(tau).max())
        qd, qdd = rng.uniform(-0.5, 0.5, 6), rng.uniform(-2, 2, 6)
        tau = np.asarray(ID(q, qd, qdd))
        Q = np.asarray(gf(q, qd, qdd))
        eps = 1e-6
        rhod = (np.asarray(lengths(q + eps * qd)) - np.asarray(lengths(q - eps * qd))) / (2 * eps)
        assert abs(tau @ rhod - Q @ qd) < 1e-7 * np.abs(tau).max()
    # holding the platform at home: six equal leg forces, together carrying the weight
    home = jnp.array([0, 0, 1.0, 0, 0, 0])
    tau = np.asarray(ID(home, jnp.zeros(6), jnp.zeros(6)))
    assert np.ptp(tau) < 1e-9 and 100 < tau[0] < 140


def test_singularity_measure(robot):
    """1 at home, falls towards the Fichter singularity (platform turned 90 degrees
    about z) and the gimbal lock; path constraints see the leg-length box."""
    m = eqx.filter_jit(robot.manipulability)
    home = np.array([0, 0, 1.0, 0, 0, 0])
    assert abs(float(m(home)) - 1.0) < 1e-12
    turned = [float(m(home + np.array([0, 0, 0, 0, 0, a]))) for a in (0.0, 0.5, 1.0, 1.4, np.pi / 2)]
    assert all(a > b for a, b in zip(turned, turned[1:])) and turned[-1] < 1e-10
    assert float(m(home + np.array([0, 0, 0, 0, np.pi / 2, 0]))) < 1e-10
    g = eqx.filter_jit(robot.path_constraints)
    assert np.all(np.asarray(g(home)) < 0)
    low = home.copy()
    low[2] = 0.3  # legs shorter than rho_min = 0.85
    assert np.asarray(g(low))[:6].max() > 0
    ic = float(robot.inverse_condition(jnp.asarray(home)))
    assert 0 < ic < 1


def test_orientation_error_and_via_validation(robot):
    rng = np.random.default_rng(6)
    for _ in range(5):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(0, 1.5)
        R_l = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        R = R_l @ Rotation.from_rotvec(angle * axis).as_matrix()  # R^T R_l = rot(-angle about axis)
        e = np.asarray(orientation_error(jnp.asarray(R), jnp.asarray(R_l)))
        np.testing.assert_allclose(e, -np.sin(angle) * axis, atol=1e-14)
    start = jnp.array([0, 0, 1.0, 0, 0, 0])
    goal = jnp.array([0.1, 0.05, 1.1, 0.1, -0.1, 0.2])
    with pytest.raises(ValueError, match=r"via_points\[0\].rotation must be a rotation"):
        jtraj.Problem(robot, start, goal, via_points=[jtraj.ViaPoint(jnp.zeros(3), rotation=2 * jnp.eye(3))])
    with pytest.raises(ValueError, match=r"via_points\[0\].rotation must be a \(3, 3\)"):
        jtraj.Problem(robot, start, goal, via_points=[jtraj.ViaPoint(jnp.zeros(3), rotation=jnp.eye(2))])
    with pytest.raises(ValueError, match="rot_tol"):
        jtraj.Problem(robot, start, goal, via_points=[jtraj.ViaPoint(jnp.zeros(3), rotation=jnp.eye(3), rot_tol=0.0)])
    with pytest.raises(ValueError, match="has none"):
        jtraj.Problem(robots.get("serial3"), jnp.zeros(3), jnp.array([0.1, 0.1, 0.1]),
                      via_points=[jtraj.ViaPoint(jnp.zeros(2), rotation=jnp.eye(3))])


START = (0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
GOAL = (0.15, -0.1, 1.1, 0.1, -0.1, 0.2)


@pytest.mark.slow
def test_solve_platform_move(robot):
    """A short move, N = 20, time 1 / energy 0.1, converges and its verified result
    keeps leg lengths, leg speeds and leg forces within their bounds (rechecked here from
    the returned states). The problem carries an orientation passage with an inactive
    tolerance (0.999), the free move of examples/gough_stewart.py."""
    weights = jtraj.Weights(time=1.0, energy=0.1)
    R_l = np.asarray(scipy_rotation(np.array([0, 0, 0, 0.2, 0.15, -0.1])))
    plain = jtraj.Problem(robot, jnp.asarray(START), jnp.asarray(GOAL), N=20, weights=weights,
                          via_points=[jtraj.ViaPoint(jnp.array([0.05, 0.0, 1.05]), tol=0.5,
                                                     rotation=jnp.asarray(R_l), rot_tol=0.999)])
    sol = jtraj.solve(plain)
    assert bool(sol.converged), jtraj.Status(int(sol.status)).name
    q, qd, tau = (np.asarray(a) for a in (sol.q, sol.qd, sol.tau))
    rho = np.asarray(jax.vmap(robot.leg_lengths)(q))
    rhod = np.einsum("kij,kj->ki", np.asarray(jax.vmap(robot.actuator_jacobian)(q)), qd)
    assert rho.min() >= 0.85 - 1e-6 and rho.max() <= 1.6 + 1e-6
    assert np.abs(rhod).max() <= 0.5 * (1 + 1e-6)
    assert np.abs(tau).max() <= 1500 * (1 + 1e-6)
    np.testing.assert_allclose(q[-1], GOAL, atol=1e-6)
    k = plain.via_samples()[0]
    err = np.linalg.norm(np.asarray(orientation_error(robot.rotation(jnp.asarray(q[k])), jnp.asarray(R_l))))
    assert 0.01 < err < 0.999  # the passage is inactive: the orientation at sample k is elsewhere


def test_orientation_passage_constraint_rows(robot):
    """The transcription's orientation passage: at the via sample the rows are
    ``(+-e - w) / (1 + w)`` with ``e = vect(R(q_k)^T R_l)`` and ``w = rot_tol / sqrt(3)``
    (the box inscribed in the ball of radius rot_tol), -1 at every other sample; a
    position-only via point leaves the stage data without orientation fields."""
    from jtraj.initial_guess import cycloidal
    from jtraj.transcription import Transcription

    R_l = jnp.asarray(scipy_rotation(np.array([0, 0, 0, 0.2, 0.15, -0.1])))
    via = jtraj.ViaPoint(jnp.array([0.05, 0.0, 1.05]), tol=0.5, rotation=R_l, rot_tol=0.01)
    problem = jtraj.Problem(robot, jnp.asarray(START), jnp.asarray(GOAL), N=6, via_points=[via])
    tr = Transcription("decoupled")
    layout, sd = tr.layout(problem), tr.stage_data(problem)
    z = layout.pack(*cycloidal(problem))
    W = tr.stage_vectors(problem, layout, z)
    ineq = eqx.filter_jit(jax.vmap(lambda w, s: tr.stage_constraints(problem, w, s)[1]["via_rotation"]))(W, sd)
    k = problem.via_samples()[0]
    q_k = W[k, :6]
    e = np.asarray(orientation_error(robot.rotation(q_k), R_l))
    w = 0.01 / np.sqrt(3)
    np.testing.assert_allclose(np.asarray(ineq[k]), np.stack([(e - w) / (1 + w), (-e - w) / (1 + w)], axis=-1),
                               atol=1e-14)
    others = np.delete(np.asarray(ineq), k, axis=0)
    assert np.all(others == -1.0)
    plain = jtraj.Problem(robot, jnp.asarray(START), jnp.asarray(GOAL), N=6,
                          via_points=[jtraj.ViaPoint(jnp.array([0.05, 0.0, 1.05]), tol=0.5)])
    assert tr.stage_data(plain).via_rotation is None
