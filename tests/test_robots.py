"""Robot models against independent references (closed forms, Pinocchio, Lagrange
multipliers, per-leg Pinocchio models) and structural properties of the dynamics."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj.robots as robots
from jtraj.robots import Robot, SpatialSerial, serial_planar
from jtraj import _testing

from helpers import (catalogue, pin_mass, pin_rnea, pin_tip, pinocchio_planar, sample_state,
                     two_link_closed_form)


def rel_err(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)


# ----- 2-link arm vs textbook closed form ----------------------------------------------
def test_two_link_closed_form():
    l1, l2, m1, m2, d1, d2, I1, I2, g = 0.7, 0.5, 3.0, 1.5, 0.3, 0.2, 0.12, 0.05, 9.81
    arm = serial_planar((l1, l2), (m1, m2), (I1, I2), com=(d1, d2), gravity=g)
    model = jax.jit(lambda q, qd: (arm.mass_matrix(q), arm.coriolis(q, qd), arm.gravity(q),
                                   arm.forward_kinematics(q)))
    rng = np.random.default_rng(0)
    for _ in range(5):
        q, qd = rng.uniform(-np.pi, np.pi, 2), rng.uniform(-2, 2, 2)
        M, c, G = two_link_closed_form(q, qd, l1, m1, m2, d1, d2, I1, I2, g)
        M_m, c_m, G_m, tip_m = (np.asarray(x) for x in model(q, qd))
        assert rel_err(M_m, M) < 1e-13
        assert np.allclose(c_m, c, atol=1e-13 * np.abs(M).max() * 4)
        assert rel_err(G_m, G) < 1e-13
        tip = [l1 * np.cos(q[0]) + l2 * np.cos(q[0] + q[1]), l1 * np.sin(q[0]) + l2 * np.sin(q[0] + q[1])]
        assert np.allclose(tip_m, tip, atol=1e-14)


# ----- serial chains vs Pinocchio -----------------------------------------------------
SERIAL_CASES = {
    "serial3": lambda: robots.get("serial3"),
    "serial3_vertical": lambda: robots.get("serial3_vertical"),
    "serial5": lambda: serial_planar((0.5, 0.4, 0.35, 0.3, 0.2), (5.0, 4.0, 3.0, 2.0, 1.0),
                                     (0.2, 0.15, 0.1, 0.05, 0.02), gravity=9.81, name="serial5"),
}


@pytest.mark.parametrize("case", sorted(SERIAL_CASES))
def test_serial_against_pinocchio(case):
    pytest.importorskip("pinocchio")
    arm = SERIAL_CASES[case]()
    model, data, tip = pinocchio_planar(np.asarray(arm.lengths), np.asarray(arm.masses),
                                        np.asarray(arm.inertias), np.asarray(arm.com),
                                        float(arm.gravity_accel))
    rigid_lagrange = jax.jit(lambda q, qd, qdd: Robot.rigid_body_forces(arm, q, qd, qdd))
    rigid_rnea = jax.jit(lambda q, qd, qdd: arm.rigid_body_forces(q, qd, qdd))
    mass = jax.jit(lambda q: _testing.mass_matrix_mechanism(arm, q))
    rng = np.random.default_rng(1)
    for _ in range(5):
        q, qd, qdd = rng.uniform(-np.pi, np.pi, arm.n), rng.uniform(-2, 2, arm.n), rng.uniform(-3, 3, arm.n)
        M_ref = pin_mass(model, data, q)
        tau_ref = pin_rnea(model, data, q, qd, qdd)
        assert rel_err(mass(q), M_ref) < 1e-10
        assert rel_err(rigid_rnea(q, qd, qdd), tau_ref) < 1e-10
        assert rel_err(rigid_lagrange(q, qd, qdd), tau_ref) < 1e-10
        assert np.max(np.abs(np.asarray(arm.forward_kinematics(q)) - pin_tip(model, data, tip, q))) < 1e-12
        if arm.actuator is None:
            assert rel_err(arm.inverse_dynamics(q, qd, qdd), tau_ref) < 1e-10
        else:  # rotary gear: tau_m = (tau_joint + N^2 J_m qdd + N^2 b_m qd) / N
            N, Jm, bm = 20.0, 1e-3, 1e-3
            tau_m = (tau_ref + N**2 * Jm * qdd + N**2 * bm * qd) / N
            assert rel_err(arm.inverse_dynamics(q, qd, qdd), tau_m) < 1e-10
            assert rel_err(arm.mass_matrix(q), M_ref + N**2 * Jm * np.eye(arm.n)) < 1e-10


def test_friction_and_ballscrew_drive_against_pinocchio():
    """Khoukhi's drive model written out here, tau_m = M_a qdd + V_a qd + K_a (f_rigid +
    f_friction) with M_a = 2 pi / (n p) (J_s + n^2 J_m), V_a = 2 pi / (n p) (b_s + n^2 b_m),
    K_a = p / (2 pi n), on Pinocchio's rigid-body efforts; a ballscrew pitch (not the
    rotary 2 pi) and friction with both terms, which no built-in robot has."""
    pytest.importorskip("pinocchio")
    base = SERIAL_CASES["serial5"]()
    n = base.n
    ratio, pitch = np.array([10.0, 20, 30, 15, 25]), np.array([0.01, 0.02, 0.005, 0.01, 0.04])
    Js, Jm, bs, bm = np.full(n, 2e-4), np.full(n, 1e-4), np.full(n, 3e-3), np.full(n, 5e-4)
    visc, coul, sharp = np.array([0.5, 0.4, 0.3, 0.2, 0.1]), np.array([2.0, 1.5, 1.0, 0.5, 0.25]), 40.0
    arm = dataclasses.replace(
        base, friction=robots.Friction(viscous=jnp.asarray(visc), coulomb=jnp.asarray(coul), sharpness=sharp),
        actuator=robots.Actuator(gear_ratio=jnp.asarray(ratio), pitch=jnp.asarray(pitch), J_s=jnp.asarray(Js),
                                 J_m=jnp.asarray(Jm), b_s=jnp.asarray(bs), b_m=jnp.asarray(bm)))
    model, data, _ = pinocchio_planar(np.asarray(arm.lengths), np.asarray(arm.masses), np.asarray(arm.inertias),
                                      np.asarray(arm.com), float(arm.gravity_accel))
    Ka = pitch / (2 * np.pi * ratio)
    Ma = 2 * np.pi / (ratio * pitch) * (Js + ratio**2 * Jm)
    Va = 2 * np.pi / (ratio * pitch) * (bs + ratio**2 * bm)
    rng = np.random.default_rng(7)
    for _ in range(4):
        q, qd, qdd = rng.uniform(-np.pi, np.pi, n), rng.uniform(-2, 2, n), rng.uniform(-3, 3, n)
        friction = visc * qd + coul * (2 / np.pi) * np.arctan(sharp * qd)
        tau_m = Ma * qdd + Va * qd + Ka * (pin_rnea(model, data, q, qd, qdd) + friction)
        assert rel_err(arm.inverse_dynamics(q, qd, qdd), tau_m) < 1e-10
        # forward dynamics inverts it
        assert rel_err(arm.forward_dynamics(q, qd, jnp.asarray(tau_m)), qdd) < 1e-9


# ----- catalogue-wide structure -------------------------------------------------------
# the URDF arms (example-robot-data): panda and ur5 in the default suite, the others (the
# same code, each checked against Pinocchio in test_spatial.py) with -m slow
SPATIAL = ("panda", "ur5", "ur10", "kinova", "so100")
SPATIAL_SLOW = ("ur10", "kinova", "so100")


def frictionless(robot):
    """The robot with friction and actuator damping removed (for energy conservation)."""
    act = robot.actuator
    if act is not None:
        act = dataclasses.replace(act, b_s=jnp.zeros_like(act.b_s), b_m=jnp.zeros_like(act.b_m))
    return dataclasses.replace(robot, friction=None, actuator=act)


@pytest.mark.parametrize("name", catalogue(slow=SPATIAL_SLOW))
def test_dynamics_structure(name):
    """M symmetric positive definite, dM/dt - 2C skew-symmetric, C qd = c, inverse and
    forward dynamics inverse to each other, Jacobian = finite differences of the
    forward kinematics; all at random states, through one jitted function."""
    robot = robots.get(name)
    rng = np.random.default_rng(2)
    eps = 1e-6

    @jax.jit
    def parts(q, qd, qdd):
        M = robot.mass_matrix(q)
        Mdot = jax.jvp(robot.mass_matrix, (q,), (qd,))[1]
        tau = robot.inverse_dynamics(q, qd, qdd)
        fk = jax.vmap(robot.forward_kinematics)
        dq = eps * jnp.eye(robot.n)
        J_fd = ((fk(q[None] + dq) - fk(q[None] - dq)) / (2 * eps)).T
        return (M, robot.coriolis_matrix(q, qd), Mdot, robot.coriolis(q, qd), tau,
                robot.forward_dynamics(q, qd, tau), robot.jacobian(q), J_fd)

    for _ in range(3):
        q, qd, qdd = sample_state(robot, rng)
        M, C, Mdot, c, tau, qdd_back, J, J_fd = (np.asarray(x) for x in parts(q, qd, qdd))
        scale = max(np.abs(M).max(), 1.0)
        assert np.allclose(M, M.T, rtol=0, atol=1e-12 * scale)
        assert np.linalg.eigvalsh(M).min() > 0
        S = Mdot - 2 * C
        assert np.abs(S + S.T).max() < 1e-10 * scale
        assert np.allclose(C @ qd, c, atol=1e-10 * scale)
        assert tau.shape == (robot.n_actuators,)
        if robot.name != "wmr":  # wmr: qdd must satisfy the constraint (test_wmr_reduced_equations)
            assert rel_err(qdd_back, qdd) < 1e-9
        assert np.abs(J - J_fd).max() < 1e-7


#: robots whose torque-free motion must be checked without gravity: the Gough-Stewart
#: platform would fall through its base (its legs collapse) within the 2 s
ENERGY_TEST_OVERRIDES = {"gough_stewart": dict(gravity_accel=0.0)}


@pytest.mark.parametrize("name", catalogue(slow=SPATIAL_SLOW))
def test_energy_conservation(name):
    """RK4 of the frictionless, torque-free robot: relative drift <= 1e-8 over 2 s."""
    robot = frictionless(robots.get(name, **ENERGY_TEST_OVERRIDES.get(name, {})))
    rng = np.random.default_rng(3)
    q0, qd0, _ = sample_state(robot, rng, speed=0.2)
    tau0 = jnp.zeros(robot.n_actuators)
    # the spatial arms fall under gravity with light wrists: RK4's own drift over 2 s is
    # 8e-7 at 2 ms on ur5, 5e-8 at 1 ms, 4e-9 at 0.5 ms (fourth order); panda 1e-8 at 0.5 ms
    dt, steps = (2.5e-4, 8000) if isinstance(robot, SpatialSerial) else (2e-3, 1000)

    def f(x):
        q, qd = x
        return qd, robot.forward_dynamics(q, qd, tau0)

    a_coef = jnp.array([0.0, 0.5, 0.5, 1.0])
    b_coef = jnp.array([1.0, 2.0, 2.0, 1.0]) / 6.0

    def rk4(x, dt):
        # the four stages as a scan, so forward_dynamics is traced (and compiled) once
        def stage(carry, ab):
            k_prev, acc = carry
            a, b = ab
            k = f(jax.tree_util.tree_map(lambda u, v: u + a * dt * v, x, k_prev))
            return (k, jax.tree_util.tree_map(lambda s_, v: s_ + b * v, acc, k)), None

        zero = jax.tree_util.tree_map(jnp.zeros_like, x)
        (_, incr), _ = jax.lax.scan(stage, (zero, zero), (a_coef, b_coef))
        x = jax.tree_util.tree_map(lambda u, v: u + dt * v, x, incr)
        return x, robot.energy(*x)

    E0 = float(robot.energy(jnp.asarray(q0), jnp.asarray(qd0)))
    scale = max(abs(E0), float(robot.kinetic_energy(jnp.asarray(q0), jnp.asarray(qd0))))
    programs = []  # (kept alive: each run is its own program)

    def drift(step, n_steps):
        programs.append(jax.jit(lambda x, h: jax.lax.scan(lambda c, _: rk4(c, h), x, None, length=n_steps)))
        (qT, _), E = programs[-1]((jnp.asarray(q0), jnp.asarray(qd0)), jnp.asarray(step))
        assert np.all(np.isfinite(np.asarray(E)))
        assert np.abs(np.asarray(qT) - q0).max() > 1e-3  # it did move
        return np.max(np.abs(np.asarray(E) - E0)) / scale

    coarse = drift(dt, steps)
    if coarse >= 1e-8:
        # RK4's own drift falls as dt^4 (16x per halving; kinova: 3.0e-6, 1.6e-7, 9.4e-9 at
        # 0.5, 0.25 and 0.125 ms), a non-conservative model's does not
        fine = drift(dt / 2, 2 * steps)
        assert fine < 1e-7 and coarse / fine > 12, (coarse, fine)


# the closed chains and the spatial arms compile for about a minute each on a slow 2-core
# machine: slow (their dynamics stay in the default suite through the Pinocchio and
# structure tests)
@pytest.mark.parametrize("name", catalogue(slow=("parallel3", "pkm2", "gough_stewart", "ibm7535", "wmr", "serial3_vertical", *SPATIAL)))
def test_transforms_on_every_function(name):
    """jit, vmap and grad (with respect to the state, the torques and the robot's
    parameters) work on every public function and give finite results (one compile)."""
    robot = robots.get(name)
    rng = np.random.default_rng(5)
    states = [sample_state(robot, rng) for _ in range(3)]
    Q, QD, QDD = (jnp.asarray(np.stack(s)) for s in zip(*states))
    TAU = jnp.asarray(rng.uniform(-1, 1, (3, robot.n_actuators)))

    def everything(r, q, qd, qdd, tau):
        out = {"fk": r.forward_kinematics(q), "J": r.jacobian(q), "M": r.mass_matrix(q),
               "bias": r.bias(q, qd), "id": r.inverse_dynamics(q, qd, qdd),
               "fd": r.forward_dynamics(q, qd, tau), "w": r.manipulability(q)}
        return sum(jnp.sum(v) for v in out.values()), out

    fn = jax.value_and_grad(lambda *x: everything(robot, *x), argnums=(0, 1, 2, 3), has_aux=True)
    (_, out), grads = jax.jit(jax.vmap(fn))(Q, QD, QDD, TAU)
    for key, val in out.items():
        assert val.shape[0] == 3 and np.all(np.isfinite(np.asarray(val))), key
    for g in grads:
        assert g.shape[0] == 3 and np.all(np.isfinite(np.asarray(g)))
    # the batched, jitted results are the per-sample ones, and the gradients central
    # differences of the summed outputs (step 1e-5, float64), within their truncation
    # and their rounding error, about eps (sum of the outputs' magnitudes) / step: a light
    # arm's forward dynamics under unit torques reach 1e4 (so100), which puts the rounding
    # near 1e-6 at a step of 1e-6
    scalar = jax.jit(lambda *x: everything(robot, *x)[0])
    single = jax.jit(lambda *x: everything(robot, *x)[1])  # (op by op it compiles each operation)
    for i in range(3):
        args = [np.asarray(a[i]) for a in (Q, QD, QDD, TAU)]
        one = single(*(jnp.asarray(a) for a in args))
        for key in out:
            np.testing.assert_allclose(out[key][i], one[key], rtol=1e-10, atol=1e-12, err_msg=key)
        for a, g in enumerate(grads):
            fd = np.zeros_like(args[a])
            for j in range(fd.size):
                up, dn = [x.copy() for x in args], [x.copy() for x in args]
                up[a][j] += 1e-5
                dn[a][j] -= 1e-5
                fd[j] = (float(scalar(*up)) - float(scalar(*dn))) / 2e-5
            rounding = 10 * np.finfo(float).eps * sum(float(np.abs(v).sum()) for v in one.values()) / 1e-5
            np.testing.assert_allclose(g[i], fd, rtol=1e-5, atol=1e-6 * max(1.0, np.abs(fd).max()) + rounding)
    # gradient with respect to the robot's own parameters (masses, lengths, ...; the way
    # jtraj.sensitivity substitutes them, Python floats included) of the inverse dynamics,
    # against central differences in every entry
    limit_fields = {f.name for f in dataclasses.fields(robots.Limits)}
    names = [k for k in robots.parameter_names(robot) if k not in limit_fields
             and np.size(getattr(robot, k)) and np.all(np.isfinite(np.asarray(getattr(robot, k), float)))]
    theta0 = {k: jnp.asarray(getattr(robot, k), float) for k in names}

    def id_sum(th):
        r = eqx.tree_at(lambda rb: [getattr(rb, k) for k in names], robot, [th[k] for k in names])
        return jnp.sum(r.inverse_dynamics(Q[0], QD[0], QDD[0]))

    value, grad = jax.jit(id_sum), jax.jit(jax.grad(id_sum))(theta0)
    assert max(float(jnp.max(jnp.abs(g))) for g in grad.values()) > 0
    for k in names:
        base = np.asarray(theta0[k])
        for j in range(base.size):
            step = 1e-6 * max(1.0, abs(base.flat[j]))
            up, dn = base.copy(), base.copy()
            up.flat[j] += step
            dn.flat[j] -= step
            fd = (float(value({**theta0, k: jnp.asarray(up)}))
                  - float(value({**theta0, k: jnp.asarray(dn)}))) / (2 * step)
            g = float(np.asarray(grad[k]).flat[j])
            assert abs(g - fd) <= 1e-5 * max(1.0, abs(fd)), (k, j, g, fd)


# ----- pkm2 ---------------------------------------------------------------------------
def pkm2_lagrange_multiplier_forces(q, qd, qdd, mp, ms, ml, R, r, L):
    """Slider forces of pkm2 from a redundant-coordinate model z = (x, y, y1, y2) with a
    constant mass matrix (uniform-rod legs, T = m/6 (vA^2 + vA.vB + vB^2)) and the
    closure constraints enforced by Lagrange multipliers."""
    x, y = q
    xd, yd = qd
    xdd, ydd = qdd
    c = R - r
    Mz = np.array([[mp + 2 * ml / 3, 0, 0, 0],
                   [0, mp + 2 * ml / 3, ml / 6, ml / 6],
                   [0, ml / 6, ms + ml / 3, 0],
                   [0, ml / 6, 0, ms + ml / 3]])
    z_dd, Phi_z = np.zeros(4), np.zeros((2, 4))
    z_dd[:2] = qdd
    for i, s in enumerate((+1.0, -1.0)):
        u, ud, udd = x + s * c, xd, xdd
        w = np.sqrt(L**2 - u**2)
        wd = -u * ud / w
        wdd = -(ud**2 + u * udd + wd**2) / w
        yi = y + w
        z_dd[2 + i] = ydd + wdd
        Phi_z[i, 0] = 2 * u
        Phi_z[i, 1] = 2 * (y - yi)
        Phi_z[i, 2 + i] = -2 * (y - yi)
    B = np.zeros((4, 2))
    B[2, 0] = B[3, 1] = 1.0
    sol = np.linalg.solve(np.concatenate([Phi_z.T, B], axis=1), Mz @ z_dd)
    return sol[2:]


def test_pkm2_closure_and_inverse_dynamics():
    robot = robots.get("pkm2")

    @jax.jit
    def model(q, qd, qdd):
        y_a = robot.actuated_coordinates(q)
        return (robot.closure_residual(q, y_a), robot.leg_endpoints(q), robot.inverse_dynamics(q, qd, qdd),
                robot.generalized_forces(q, qd, qdd), robot.actuator_jacobian(q))

    rng = np.random.default_rng(6)
    for _ in range(5):
        q, qd, qdd = sample_state(robot, rng)
        res, (A, B), tau, Q, Ja = jax.tree_util.tree_map(np.asarray, model(q, qd, qdd))
        assert np.abs(res).max() < 1e-12
        assert np.allclose(np.linalg.norm(B - A, axis=1), 1.9725, atol=1e-12)
        assert np.all(A[:, 1] > q[1])  # branch: platform below sliders
        ref = pkm2_lagrange_multiplier_forces(q, qd, qdd, 200.0, 100.0, 570.5, 1.203, 0.075, 1.9725)
        assert rel_err(tau, ref) < 1e-10
        # virtual work: slider power equals generalised power
        y_ad = Ja @ qd
        assert abs(tau @ y_ad - Q @ qd) < 1e-10 * np.abs(tau).max() * np.abs(y_ad).max()


def test_pkm2_singularities():
    robot = robots.get("pkm2")
    # inside the workspace: no singularity
    s = robot.singularities(jnp.array([0.3, -1.2]))
    assert float(s.type1) > 0.1 and abs(float(s.type2)) > 0.1 and float(s.type3) > 0.1
    # type 1 at |x| = L - (R - r): left leg horizontal
    x1 = 1.9725 - (1.203 - 0.075)
    s = robot.singularities(jnp.array([x1 - 1e-9, -1.2]))
    assert abs(float(s.type1)) < 1e-3 and abs(float(s.type2)) > 0.1
    assert float(robot.manipulability(jnp.array([x1 - 1e-9, -1.2]))) < 1e-3
    assert np.all(np.asarray(robot.path_constraints(jnp.array([0.0, -1.2]))) < 0)


# ----- parallel3 ----------------------------------------------------------------------
def parallel3_leg_joints(q, base, L):
    """Leg joint angles (theta_i, psi_i) (3, 2) by circle intersection, elbow
    counter-clockwise of the base-to-C line; psi is the relative elbow angle."""
    d = q[None, :] - base
    rho = jnp.linalg.norm(d, axis=1)
    perp = jnp.stack([-d[:, 1], d[:, 0]], axis=1) / rho[:, None]
    E = base + d / 2 + jnp.sqrt(L**2 - rho**2 / 4)[:, None] * perp
    theta = jnp.arctan2(E[:, 1] - base[:, 1], E[:, 0] - base[:, 0])
    phi = jnp.arctan2(q[1] - E[:, 1], q[0] - E[:, 0])
    return jnp.stack([theta, phi - theta], axis=1), E


def test_parallel3_closure_and_inverse_dynamics():
    pytest.importorskip("pinocchio")
    robot = robots.get("parallel3")
    base, L = np.asarray(robot.base), 0.6
    model_pin, data_pin, _ = pinocchio_planar((L, L), (10.0, 10.0), (0.1, 0.1), com=(0.3, 0.3))
    legs = lambda q: parallel3_leg_joints(q, jnp.asarray(base), L)[0]  # noqa: E731

    @jax.jit
    def reference_kinematics(q, qd, qdd):
        """Leg joints, rates and accelerations by differentiating the independent leg IK."""
        joints, E = parallel3_leg_joints(q, jnp.asarray(base), L)
        _, jd = jax.jvp(legs, (q,), (qd,))
        Jq = jax.jacfwd(legs)(q)  # (3, 2, 2)
        Jdot_qd = jax.jvp(lambda x: jnp.einsum("ijk,k->ij", jax.jacfwd(legs)(x), qd), (q,), (qd,))[1]
        return joints, E, jd, jnp.einsum("ijk,k->ij", Jq, qdd) + Jdot_qd, Jq

    @jax.jit
    def model(q, qd, qdd):
        theta = robot.actuated_coordinates(q)
        return (robot.elbows(q), robot.closure_residual(q, theta), robot.generalized_forces(q, qd, qdd),
                robot.inverse_dynamics(q, qd, qdd))

    rng = np.random.default_rng(7)
    for _ in range(5):
        q, qd, qdd = sample_state(robot, rng)
        joints, E, jd, jdd, Jq = (np.asarray(x) for x in reference_kinematics(q, qd, qdd))
        E_m, res, Q, tau = (np.asarray(x) for x in model(q, qd, qdd))
        assert np.abs(E_m - E).max() < 1e-12
        assert np.abs(res).max() < 1e-12
        Q_ref = sum(Jq[i].T @ pin_rnea(model_pin, data_pin, joints[i], jd[i], jdd[i]) for i in range(3))
        assert rel_err(Q, Q_ref) < 1e-10
        Ja = Jq[:, 0, :]  # d theta / dq
        tau_ref = Ja @ np.linalg.solve(Ja.T @ Ja, Q_ref)
        assert rel_err(tau, tau_ref) < 1e-10
        assert abs(tau @ (Ja @ qd) - Q @ qd) < 1e-10 * np.abs(tau).max()


def test_plot_path_shades_where_path_constraints_are_violated():
    # the tip-path panel of a robot whose tip is its first two coordinates shades the
    # region of its workspace where a path constraint is violated: for parallel3 the discs
    # around the base points (a leg folded) and the corners (a leg stretched), against
    # NumPy's leg ratios; for wmr its obstacles
    pytest.importorskip("matplotlib")
    import types

    from jtraj import Problem
    from jtraj.plotting import _path_constraint_region, plot_path

    robot = robots.get("parallel3")
    x, y, g = _path_constraint_region(robot)
    s = np.linalg.norm(np.stack([x, y], axis=-1)[..., None, :] - np.asarray(robot.base), axis=-1) / 1.2
    outside = np.any((s < robot.rho_min) | (s > robot.rho_max), axis=-1)
    assert 0.01 < outside.mean() < 0.2
    np.testing.assert_array_equal(g > 0, outside)
    assert _path_constraint_region(robots.get("serial3")) is None  # no path constraints
    # wmr: its obstacles, grown by the body's radius, over its workspace
    wmr = robots.get("wmr")
    x, y, g = _path_constraint_region(wmr)
    ob = np.asarray(wmr.obstacles)
    d = np.linalg.norm(np.stack([x, y], axis=-1)[..., None, :] - ob[:, :2], axis=-1)
    np.testing.assert_array_equal(g > 0, np.any(d < ob[:, 2] + float(wmr.body_radius), axis=-1))
    q0, q1 = np.array([-0.3, 0.2]), np.array([0.3, -0.3])
    q = q0 + np.linspace(0, 1, 6)[:, None] * (q1 - q0)
    sol = types.SimpleNamespace(q=q, qd=np.zeros_like(q), v=np.zeros((5, 2)), tau=np.zeros((5, 3)), h=np.full(5, 0.1))
    ax = plot_path(Problem(robot, q0, q1, N=5, validate=False), sol).axes[0]
    assert "path constraints violated" in [t.get_text() for t in ax.get_legend().get_texts()]


# ----- wmr ----------------------------------------------------------------------------
def test_wmr_reduced_equations():
    robot = robots.get("wmr")
    m, I, rw, b, Jw = 50.0, 2.5, 0.1, 0.25, 0.005
    wmr_model = jax.jit(lambda q, qd, tau: (lambda a: (a, robot.inverse_dynamics(q, qd, a)))(
        robot.forward_dynamics(q, qd, tau)))
    rng = np.random.default_rng(8)
    for _ in range(5):
        th, v, w = rng.uniform(-np.pi, np.pi), rng.uniform(-1, 1), rng.uniform(-1, 1)
        q = jnp.array([5.0, 6.0, th])
        qd = jnp.array([v * np.cos(th), v * np.sin(th), w])
        tau = jnp.asarray(rng.uniform(-1, 1, 2))
        vd = (tau[0] + tau[1]) / rw / (m + 2 * Jw / rw**2)
        wd = b * (tau[0] - tau[1]) / rw / (I + 2 * Jw * b**2 / rw**2)
        ref = np.array([vd * np.cos(th) - v * w * np.sin(th), vd * np.sin(th) + v * w * np.cos(th), wd])
        qdd, tau_back = wmr_model(q, qd, tau)
        assert rel_err(qdd, ref) < 1e-12
        assert rel_err(tau_back, tau) < 1e-12
        assert abs(float(robot.path_equalities(q, qd)[0])) < 1e-15
    assert np.all(np.asarray(robot.path_constraints(jnp.array([8.0, 8.5, 0.0]))) [0] > 0)  # inside an obstacle


# ----- bad input ----------------------------------------------------------------------
@pytest.mark.parametrize("name, overrides, word", [
    ("serial3", {"masses": (10.0, -8.0, 4.0)}, "masses"),
    ("serial3", {"lengths": (1.0, 0.0, 0.45)}, "lengths"),
    ("serial3", {"masses": (10.0, 8.0)}, "masses"),
    ("serial3", {"masses": (10.0, np.nan, 4.0)}, "masses"),
    ("serial3", {"inertias": (np.inf, 1.0, 1.0)}, "inertias"),
    ("pkm2", {"L": -1.0}, "L"),
    ("pkm2", {"platform_mass": 0.0}, "platform_mass"),
    ("pkm2", {"tau_max": (550.0, 700.0, 1.0)}, "tau_max"),
    ("parallel3", {"link_length": 0.0}, "link_length"),
    ("parallel3", {"base": np.zeros((2, 2))}, "base"),
    ("parallel3", {"tau_max": (25.0, 25.0)}, "tau_max"),
    ("wmr", {"mass": -50.0}, "mass"),
    ("wmr", {"wheel_radius": np.nan}, "wheel_radius"),
    ("serial3", {"no_such_param": 1.0}, "no_such_param"),
    ("pkm2", {"masses": (1.0, 2.0)}, "masses"),
])
def test_bad_overrides(name, overrides, word):
    with pytest.raises(ValueError, match=word):
        robots.get(name, **overrides)


def test_bad_names_and_shapes():
    with pytest.raises(ValueError, match="robot"):
        robots.get("no_such_robot")
    with pytest.raises(ValueError, match="lengths"):
        serial_planar((1.0, -1.0), (1.0, 1.0), (0.1, 0.1))
    with pytest.raises(ValueError, match="masses"):
        serial_planar((1.0, 1.0), (1.0,), (0.1, 0.1))
    robot = robots.get("pkm2")
    with pytest.raises(ValueError, match="q"):
        robot.check_q([0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="q"):
        robot.check_q([0.1, np.nan])


def test_overrides_apply():
    r = robots.get("pkm2", platform_mass=300.0, tau_max=(600.0, 700.0))
    assert float(r.platform_mass) == 300.0 and np.allclose(r.limits.tau_max, (600.0, 700.0))
    M0 = robots.get("pkm2").mass_matrix(jnp.array([0.0, -1.2]))
    M1 = r.mass_matrix(jnp.array([0.0, -1.2]))
    assert np.allclose(np.asarray(M1 - M0), 100.0 * np.eye(2))
    p3 = robots.get("parallel3", tau_max=30.0)
    assert p3.limits.tau_max.shape == (3,)
    assert "platform_mass" in robots.parameter_names("pkm2")
    for name in catalogue():
        r = robots.get(name)
        lim = r.limits
        assert lim.tau_max is not None and lim.tau_max.shape == (r.n_actuators,)
        assert 0 < lim.h_min < lim.h_max


@pytest.mark.parametrize("name, param, values", [
    ("serial3_vertical", "gravity_accel", (9.81, 9.5)),
    ("pkm2", "platform_mass", (200.0, 300.0)),
    ("gough_stewart", "platform_mass", (50.0, 55.0)),
])
def test_scalar_overrides_are_traced_not_static(name, param, values):
    """A scalar parameter given as an override is a 0-d array, a leaf that jit traces, so
    a sweep over it reuses one compiled program; its values still reach the dynamics
    (checked against the robot built with the same value as a Python float)."""
    traces = []

    @eqx.filter_jit
    def efforts(robot, q, qd, qdd):
        traces.append(1)
        return robot.inverse_dynamics(q, qd, qdd)

    base = robots.get(name)
    q, qd, qdd = sample_state(base, np.random.default_rng(0))
    got = []
    for value in values:
        robot = robots.get(name, **{param: value})
        assert getattr(robot, param).shape == () and eqx.is_inexact_array(getattr(robot, param))
        tau = efforts(robot, q, qd, qdd)
        ref = dataclasses.replace(base, **{param: float(value)}).inverse_dynamics(q, qd, qdd)
        np.testing.assert_allclose(tau, ref, rtol=1e-12, atol=1e-12)
        got.append(tau)
    assert len(traces) == 1
    assert not np.allclose(got[0], got[1])
