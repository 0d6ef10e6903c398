"""Derivatives through jtraj.solve / solve_batch (jtraj.implicit) against central finite
differences of warm re-solves, and the stage-wise KKT solve (jtraj.adjoint) against the
dense reference.

The re-solves use the AL method at tight tolerances (1e-10): the interior-point method
ends at its own ``ip_tol`` (a barrier parameter of 1e-8, variables up to 1e-4 inside a
bound they press on), which limits central differences of T to about 1e-3 relative.
The default tests solve serial3 at N = 10 with the same options and share one compiled
solver and one reverse-mode program: the module fixture ``grads`` holds the gradients of
T and of the cost in every array leaf of the problem from one ``jax.vjp``, and the
tests compare its entries with finite differences. Agreement: 1e-5 relative (plus a
small absolute floor for entries near zero) where the re-solves' noise allows it.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj
from jtraj import implicit
from jtraj.implicit import valid_derivatives

START, GOAL = np.array((0.2, -0.3, 0.4)), np.array((0.3, -0.2, 0.3))
WEIGHTS = dict(time=1.0, energy=0.1)
TIGHT = jtraj.SolverOptions(tol_feasibility=1e-10, tol_optimality=1e-10, max_iter=1000, method="al")
ROBOT = jtraj.robots.get("serial3")
N = 10


def _problem(robot=ROBOT, q_start=START, q_goal=GOAL, weights=None, **kw):
    w = jtraj.Weights(**WEIGHTS) if weights is None else weights
    return jtraj.Problem(robot, q_start, q_goal, N=N, weights=w, **kw)


@pytest.fixture(scope="module")
def base():
    sol = jtraj.solve(_problem(), options=TIGHT)
    assert bool(sol.converged), sol.status_message
    return sol


def _reverse(problem, options=TIGHT):
    """Gradients of (T, cost) in every inexact-array leaf of ``problem`` (one vjp, two
    cotangents): {"T": tree, "cost": tree} shaped like the problem's array part."""
    dyn, static = eqx.partition(problem, eqx.is_inexact_array)

    def f(d):
        s = jtraj.solve(eqx.combine(d, static), options=options)
        return jnp.stack([s.T, s.cost])

    _, vjp = jax.vjp(f, dyn)
    return {"T": vjp(jnp.array([1.0, 0.0]))[0], "cost": vjp(jnp.array([0.0, 1.0]))[0]}


@pytest.fixture(scope="module")
def grads():
    return _reverse(_problem())


def _fd(make, x0, out, base, rel=1e-5, absolute=None, options=TIGHT):
    """Central differences of out(solve(make(x))) in each entry of x0 (warm re-solves)."""
    x0 = np.asarray(x0, float)
    cols = []
    for i in range(x0.size):
        step = absolute if absolute is not None else rel * max(abs(x0.flat[i]), 1e-3)
        vals = []
        for sign in (1.0, -1.0):
            x = x0.copy()
            x.flat[i] += sign * step
            s = jtraj.solve(make(x), options=options, init=(base.v, base.h))
            assert bool(s.converged), s.status_message
            vals.append(np.asarray(out(s)))
        cols.append((vals[0] - vals[1]) / (2 * step))
    return np.stack(cols, axis=-1).reshape(np.shape(out(base)) + x0.shape)


def _close(a, b, rtol=1e-5, floor=1e-7):
    a, b = np.asarray(a), np.asarray(b)
    scale = np.max(np.abs(b))
    np.testing.assert_allclose(a, b, rtol=rtol, atol=floor + rtol * 1e-2 * scale)


def _tree_close(a, b, rtol):
    """Every leaf of a within rtol of b, relative to the largest entry of b's leaf (or,
    for a leaf that is zero up to rounding, 1e-6 of the largest entry of all of b)."""
    ys = [np.asarray(y) for y in jax.tree.leaves(b)]
    top = max(np.max(np.abs(y), initial=0.0) for y in ys)
    for x, y in zip(jax.tree.leaves(a), ys, strict=True):
        scale = max(np.max(np.abs(y), initial=0.0), 1e-6 * top)
        np.testing.assert_allclose(np.asarray(x), y, rtol=0, atol=rtol * scale)


def _T_and_cost(s):
    return np.array([s.T, s.cost])


def test_grad_wrt_goal_and_start(grads, base):
    fd = _fd(lambda g: _problem(q_goal=g), GOAL, _T_and_cost, base, absolute=1e-5)
    _close(grads["T"].q_goal, fd[0])
    _close(grads["cost"].q_goal, fd[1])
    fd = _fd(lambda q0: _problem(q_start=q0), START, _T_and_cost, base, absolute=1e-5)
    _close(grads["T"].q_start, fd[0])
    _close(grads["cost"].q_start, fd[1])


def test_grad_wrt_weights_and_torque_limit(grads, base):
    w0 = np.array([WEIGHTS["time"], WEIGHTS["energy"]])
    # T is not stationary in the weights: the re-solves' noise (~1e-9) needs a longer step
    fd = _fd(lambda w: _problem(weights=jtraj.Weights(time=w[0], energy=w[1])), w0, _T_and_cost, base, rel=1e-4)
    g = grads["T"].weights, grads["cost"].weights
    _close([g[0].time, g[0].energy], fd[0], rtol=1e-4)
    _close([g[1].time, g[1].energy], fd[1])
    tau0 = np.asarray(ROBOT.limits.tau_max)
    fd = _fd(lambda t: _problem(robot=jtraj.robots.get("serial3", tau_max=t)), tau0, _T_and_cost, base, rel=1e-4)
    _close(grads["T"].robot.limits.tau_max, fd[0], rtol=1e-4)
    _close(grads["cost"].robot.limits.tau_max, fd[1], rtol=1e-4)


def test_grad_wrt_masses(grads, base):
    m0 = np.asarray(ROBOT.masses)
    fd = _fd(lambda m: _problem(robot=jtraj.robots.get("serial3", masses=m)), m0, _T_and_cost, base, rel=1e-4)
    _close(grads["cost"].robot.masses, fd[1])
    _close(grads["T"].robot.masses, fd[0], rtol=1e-4)


@pytest.mark.slow  # differentiating another set of leaves is a reverse program of its own
def test_grad_wrt_masses_through_robots_get(grads):
    """The masses traced through ``robots.get(..., masses=m)`` (host checks skipped): the
    same gradient as the problem's leaf."""
    m0 = np.asarray(ROBOT.masses)

    def cost(m):
        return jtraj.solve(_problem(robot=jtraj.robots.get("serial3", masses=m)), options=TIGHT).cost

    g = jax.grad(cost)(jnp.asarray(m0))
    np.testing.assert_allclose(g, grads["cost"].robot.masses, rtol=1e-10, atol=1e-14)


@pytest.mark.slow  # the dense reference is a reverse program of its own
def test_stagewise_solve_equals_dense_reference(grads, monkeypatch):
    """The stage-wise KKT solve (jtraj.adjoint, the decoupled default) against the dense LU
    of the same system: every input's gradient of T and cost to 1e-8."""
    monkeypatch.setattr(implicit, "KKT_SOLVE", "dense")
    dense = _reverse(_problem())
    _tree_close(grads, dense, 1e-8)


def test_unconverged_single_solve_gives_nan_or_raises(grads):
    """(The same program as ``grads``: the options differ only in traced numbers.)"""
    short = jtraj.SolverOptions(tol_feasibility=1e-10, tol_optimality=1e-10, max_iter=2, method="al",
                                restart_iter=0)
    g = _reverse(_problem(), options=short)
    for out in ("T", "cost"):
        for leaf in (g[out].q_goal, g[out].q_start, g[out].weights.time, g[out].robot.masses):
            assert np.all(np.isnan(leaf))
    dyn, static = eqx.partition(_problem(), eqx.is_inexact_array)
    with pytest.raises(Exception, match="did not converge"):
        jax.block_until_ready(jax.grad(lambda d: jtraj.solve(eqx.combine(d, static), options=short,
                                                             on_failure="raise").T)(dyn))


def _force_invalid_derivatives(monkeypatch):
    """Every derivative reported not valid (the tangent program's flag forced False) and
    the refinement keeping the point: the case of a converged solve whose derivative
    stays invalid after refinement and the dense fallback. Returns the list of the
    refinement's calls."""
    program = implicit._tangent_program

    def invalid(static, transcription, method, *args):
        # (the dense fallback's program is the stage-wise one here: not compiled for this test)
        dsol, valid = program(static, transcription, None, *args)
        return dsol, jnp.zeros_like(valid)

    calls = []

    def keep(cfg, dyn, at, flags, batch):
        calls.append(np.asarray(flags))
        return at

    monkeypatch.setattr(implicit, "_tangent_program", invalid)
    monkeypatch.setattr(implicit, "_refine_host", keep)
    return calls


@pytest.mark.slow  # 14 s of its own programs; the default suite keeps the unconverged solve's NaN
def test_converged_solve_with_invalid_derivative_says_so(grads, monkeypatch):
    """A converged solve whose derivative is not valid after refinement reports
    ``Status.CONVERGED_NO_DERIVATIVE`` when differentiated (``converged`` stays True, its
    values are the solve's), ``valid_derivatives`` is False, every gradient entry is NaN,
    and ``on_failure="raise"`` raises; the undifferentiated solve reports CONVERGED. (The
    programs are ``grads``'.)"""
    calls = _force_invalid_derivatives(monkeypatch)
    p = _problem()
    plain = jtraj.solve(p, options=TIGHT)
    assert int(plain.status) == jtraj.Status.CONVERGED
    dyn, static = eqx.partition(p, eqx.is_inexact_array)

    def f(d, on_failure="nan"):
        s = jtraj.solve(eqx.combine(d, static), options=TIGHT, on_failure=on_failure)
        return s.T, s

    T, vjp, sol = jax.vjp(f, dyn, has_aux=True)
    (g,) = vjp(jnp.ones(()))
    assert len(calls) == 1 and bool(calls[0])  # the refinement was tried
    assert int(sol.status) == jtraj.Status.CONVERGED_NO_DERIVATIVE
    assert "derivative" in sol.status_message
    assert bool(sol.converged) and not bool(valid_derivatives(sol))
    np.testing.assert_allclose(float(T), float(plain.T), rtol=1e-12)
    for leaf in jax.tree.leaves(g):
        assert np.all(np.isnan(np.asarray(leaf)))
    with pytest.raises(Exception, match="degenerate"):
        jax.block_until_ready(jax.grad(lambda d: f(d, "raise")[0])(dyn))


def test_static_inputs_are_refused_when_traced():
    with pytest.raises(ValueError, match="N"):
        jax.grad(lambda n: jtraj.Problem(ROBOT, START, GOAL, N=n).T_max)(3.0)
    with pytest.raises(ValueError, match="on_failure"):
        jtraj.solve(_problem(), on_failure="zero")
    with pytest.raises(ValueError, match="method"):
        implicit._method(jtraj.transcription.Transcription("decoupled"), "lu")


# SolverOptions(method=tracer) makes equinox warn of a static array before jtraj refuses it
@pytest.mark.filterwarnings("ignore:A JAX array is being set as static:UserWarning")
def test_static_arguments_refused_before_tracing():
    """Differentiating with respect to the transcription or a string option raises a
    ValueError naming it, before any solver is traced (no compilation here)."""
    p = _problem()
    cases = {
        "transcription": lambda x: jtraj.solve(p, transcription=x).T,
        "on_failure": lambda x: jtraj.solve(p, on_failure=x).T,
        "warm": lambda x: jtraj.solve(p, warm=x).T,
        "efforts": lambda x: jtraj.Problem(ROBOT, START, GOAL, N=N, efforts=x).T_max,
        "method": lambda x: jtraj.solve(p, options=jtraj.SolverOptions(method=x)).T,
    }
    for name, f in cases.items():
        with pytest.raises(ValueError, match=name):
            jax.grad(f)(1.0)
    with pytest.raises(ValueError, match="transcription"):
        jax.grad(lambda x: jtraj.solve_batch(ROBOT, START[None], GOAL[None], N=N, transcription=x).T.sum())(1.0)


def _face_invalid_gradient():
    """T and the gradient of T in every array leaf of a problem whose host-side checks
    cannot run (its leaves traced) and that the checks would refuse (T_max below the
    move's minimum time), with the solve's status."""
    with pytest.raises(ValueError, match="T_max"):
        _problem(T_max=0.05)
    dyn, static = eqx.partition(_problem(T_max=0.05, validate=False), eqx.is_inexact_array)

    def f(d):
        s = jtraj.solve(eqx.combine(d, static), options=TIGHT)
        return s.T, s.status

    T, vjp, status = jax.vjp(f, dyn, has_aux=True)
    (g,) = vjp(jnp.ones(()))
    return status, g


@pytest.mark.slow  # a reverse program with the status as an auxiliary output: minutes
def test_traced_problem_infeasible_on_its_face_gives_nan():
    """The solve flags such a problem INVALID_INPUT: its derivatives are NaN, never a
    plausible number."""
    status, g = _face_invalid_gradient()
    assert int(status) == jtraj.Status.INVALID_INPUT
    for leaf in (g.q_goal, g.q_start):
        assert np.all(np.isnan(leaf))


def test_traced_problem_infeasible_on_its_face_every_gradient_is_nan(grads, base):
    """Every entry of every gradient of such a problem is NaN, including those of the
    leaves that enter only rows the failed point leaves inactive (T_max, the time
    weight). (The problem differs from ``grads``' and ``base``'s in leaf values only:
    their programs.)"""
    # (T_max put in place keeps the weak type of the default T_max: the same programs)
    p = eqx.tree_at(lambda q: q.T_max, _problem(), jnp.full_like(_problem().T_max, 0.05))
    assert int(jtraj.solve(p, options=TIGHT).status) == jtraj.Status.INVALID_INPUT
    g = _reverse(p)
    for out in ("T", "cost"):
        for leaf in jax.tree.leaves(g[out]):
            assert np.all(np.isnan(np.asarray(leaf)))


@pytest.mark.slow  # the forward-mode tangent program is a compilation of its own
def test_jvp_wrt_weights_and_mass(base):
    """Forward mode along a direction that moves the weights and a link mass at once; a
    solve that did not converge gives a NaN tangent."""
    p0 = _problem()

    def out(p):
        s = jtraj.solve(p, options=TIGHT)
        return jnp.stack([s.T, s.cost, s.energy])

    direction = jax.tree.map(jnp.zeros_like, eqx.filter(p0, eqx.is_inexact_array))
    direction = eqx.tree_at(lambda p: (p.weights.time, p.weights.energy, p.robot.masses), direction,
                            (jnp.asarray(0.5), jnp.asarray(0.02), jnp.array([0.0, 1.0, 0.0])))
    dyn, static = eqx.partition(p0, eqx.is_inexact_array)
    _, tangent = jax.jvp(lambda d: out(eqx.combine(d, static)), (dyn,), (direction,))

    def make(t):
        t = float(t[0])
        robot = jtraj.robots.get("serial3", masses=np.asarray(ROBOT.masses) + t * np.array([0.0, 1.0, 0.0]))
        return _problem(robot=robot, weights=jtraj.Weights(time=1.0 + 0.5 * t, energy=0.1 + 0.02 * t))

    # T and the energy are not stationary at the optimum: re-solve noise (~1e-9) needs a
    # longer step than the cost's
    fd = _fd(make, [0.0], lambda s: np.array([s.T, s.cost, s.energy]), base, absolute=1e-3)[:, 0]
    _close(tangent, fd, rtol=1e-4)

    short = jtraj.SolverOptions(tol_feasibility=1e-10, tol_optimality=1e-10, max_iter=2, method="al",
                                restart_iter=0)
    _, t = jax.jvp(lambda d: jtraj.solve(eqx.combine(d, static), options=short).T, (dyn,), (direction,))
    assert np.isnan(t)


@pytest.mark.slow  # jacfwd batches the tangent program: one more compilation
def test_jacobian_of_q_and_h_wrt_start_forward_and_reverse(base):
    def f(q0):
        s = jtraj.solve(_problem(q_start=q0), options=TIGHT)
        return s.q, s.h

    Jq_f, Jh_f = jax.jacfwd(f)(jnp.asarray(START))
    Jq_r, Jh_r = jax.jacrev(f)(jnp.asarray(START))
    np.testing.assert_allclose(Jq_f, Jq_r, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(Jh_f, Jh_r, rtol=1e-9, atol=1e-11)
    # the periods of re-solves carry ~5e-9 of noise at these tolerances: a step of 1e-4
    fd_h = _fd(lambda q0: _problem(q_start=q0), START, lambda s: s.h, base, absolute=1e-4)
    _close(Jh_f, fd_h, rtol=1e-4, floor=5e-5)
    fd_q = _fd(lambda q0: _problem(q_start=q0), START, lambda s: s.q, base, absolute=1e-4)
    _close(Jq_f, fd_q, rtol=1e-4, floor=5e-5)


@pytest.mark.slow  # a binding T_max gives another active set: its own tangent program (about 2 min)
def test_grad_wrt_torque_limit_and_binding_T_max(base, monkeypatch):
    T_max = 0.998 * float(base.T)
    opts = jtraj.SolverOptions(tol_feasibility=1e-10, tol_optimality=1e-8, max_iter=3000, method="al")

    def f(tau_max, t_max):
        robot = eqx.tree_at(lambda r: r.limits.tau_max, ROBOT, tau_max)
        s = jtraj.solve(_problem(robot=robot, T_max=t_max), options=opts)
        return s.cost

    tau0 = np.asarray(ROBOT.limits.tau_max)
    g_tau, g_T = jax.grad(f, argnums=(0, 1))(jnp.asarray(tau0), jnp.asarray(T_max))
    ref = jtraj.solve(_problem(T_max=T_max), options=opts)
    assert bool(ref.converged), ref.status_message
    assert abs(float(ref.T) - T_max) < 1e-8  # the bound is binding
    fd_tau = _fd(lambda t: _problem(robot=jtraj.robots.get("serial3", tau_max=t), T_max=T_max), tau0,
                 lambda s: s.cost, ref, options=opts)
    fd_T = _fd(lambda t: _problem(T_max=float(t[0])), [T_max], lambda s: s.cost, ref, options=opts)[0]
    _close(g_tau, fd_tau)
    _close(g_T, fd_T)
    # the bound on T active: the stage-wise solve's time term against the dense reference
    monkeypatch.setattr(implicit, "KKT_SOLVE", "dense")
    dense = jax.grad(f, argnums=(0, 1))(jnp.asarray(tau0), jnp.asarray(T_max))
    _tree_close((g_tau, g_T), dense, 1e-8)


@pytest.mark.slow  # the whole solver compiled inside an outer jit: minutes
def test_jit_of_the_whole_equals_eager(base):
    def f(g):
        return jtraj.solve(_problem(q_goal=g), options=TIGHT).T

    g = jnp.asarray(GOAL)
    np.testing.assert_allclose(jax.jit(jax.grad(f))(g), jax.grad(f)(g), rtol=1e-7)
    np.testing.assert_allclose(jax.jit(f)(g), base.T, rtol=1e-9)


@pytest.mark.slow  # a vmapped solver and a vmapped tangent program: minutes of compilation
def test_batch_derivatives_equal_per_sample_and_flag_failures(base):
    goals = np.stack([GOAL, GOAL + np.array([0.05, -0.02, 0.01]), GOAL])
    short_T = np.array([np.inf, np.inf, 0.2])  # the last one cannot make it: infeasible

    def total_T(g):
        s = jtraj.solve_batch(ROBOT, np.broadcast_to(START, g.shape), g, N=N, weights=jtraj.Weights(**WEIGHTS),
                              T_max=short_T, options=TIGHT, slots=None)
        return jnp.sum(jnp.where(valid_derivatives(s), s.T, 0.0)), s

    (_, sol), grads = jax.value_and_grad(total_T, has_aux=True)(jnp.asarray(goals))
    mask = np.asarray(valid_derivatives(sol))
    assert mask.tolist() == [True, True, False]
    assert int(sol.status[2]) != 0 and not bool(sol.converged[2])  # the status says why
    assert np.all(grads[2] == 0) and np.all(np.isfinite(grads))

    def one(g):
        return jtraj.solve(_problem(q_goal=g), options=TIGHT).T

    per = np.stack([jax.grad(one)(jnp.asarray(g)) for g in goals[:2]])
    np.testing.assert_allclose(grads[:2], per, rtol=1e-6, atol=1e-9)
    fd = _fd(lambda g: _problem(q_goal=g), goals[1], lambda s: s.T, base, absolute=1e-5)
    _close(grads[1], fd)


@pytest.mark.slow  # the programs of test_batch_derivatives_equal_per_sample_and_flag_failures
def test_batch_sample_with_invalid_derivative_says_so(monkeypatch):
    """In a batch, a converged sample whose derivative is not valid after refinement gets
    a zero gradient and ``Status.CONVERGED_NO_DERIVATIVE``; a sample that did not converge
    keeps its own status; ``valid_derivatives`` is False for both."""
    calls = _force_invalid_derivatives(monkeypatch)
    goals = np.stack([GOAL, GOAL + np.array([0.05, -0.02, 0.01]), GOAL])
    short_T = np.array([np.inf, np.inf, 0.2])

    def total_T(g):
        s = jtraj.solve_batch(ROBOT, np.broadcast_to(START, g.shape), g, N=N, weights=jtraj.Weights(**WEIGHTS),
                              T_max=short_T, options=TIGHT, slots=None)
        return jnp.sum(s.T), s

    (_, sol), g = jax.value_and_grad(total_T, has_aux=True)(jnp.asarray(goals))
    assert calls and calls[0].tolist() == [True, True, False]  # the converged samples were to be refined
    status = np.asarray(sol.status).tolist()
    assert status[:2] == [jtraj.Status.CONVERGED_NO_DERIVATIVE] * 2
    assert status[2] not in (jtraj.Status.CONVERGED, jtraj.Status.CONVERGED_NO_DERIVATIVE)
    assert np.asarray(sol.converged).tolist() == [True, True, False]
    assert not np.any(np.asarray(valid_derivatives(sol)))
    assert np.all(np.asarray(g) == 0)


@pytest.mark.slow  # the whole solver vmapped inside the derivative's trace: minutes
def test_vmap_of_grad_equals_per_sample_grad():
    goals = np.stack([GOAL, GOAL + np.array([0.05, -0.02, 0.01])])

    def one(g):
        return jtraj.solve(_problem(q_goal=g), options=TIGHT).T

    per = np.stack([jax.grad(one)(jnp.asarray(g)) for g in goals])
    vm = jax.vmap(jax.grad(one))(jnp.asarray(goals))
    np.testing.assert_allclose(vm, per, rtol=1e-6, atol=1e-9)


@pytest.mark.slow
def test_via_point_position_and_tolerance(monkeypatch):
    p_mid = np.asarray(ROBOT.forward_kinematics(jnp.asarray((START + GOAL) / 2))) + np.array([0.01, 0.0])

    def make(x):
        x = np.asarray(x, float)
        return _problem(via_points=[jtraj.ViaPoint(point=x[:2], tol=x[2])])

    x0 = np.r_[p_mid, 1e-3]
    # (the AL method needs more than TIGHT's 1000 iterations on some of the re-solves; the
    # iteration limit is a traced number: the same programs)
    VIA = jtraj.SolverOptions(tol_feasibility=1e-10, tol_optimality=1e-10, max_iter=4000, method="al")
    base = jtraj.solve(make(x0), options=VIA)
    assert bool(base.converged), base.status_message

    def f(x):
        return jtraj.solve(_problem(via_points=[jtraj.ViaPoint(point=x[:2], tol=x[2])]), options=VIA,
                           init=(base.v, base.h)).T

    g = jax.grad(f)(jnp.asarray(x0))
    # steps of 1e-6 m in the point and in the tolerance (0.1 % of it): the via constraint
    # stays active, the re-solves' noise (about 1e-11 in T) stays below 1e-5 of the slope
    fd = _fd(make, x0, lambda s: s.T, base, absolute=1e-6, options=VIA)
    _close(g, fd, rtol=1e-4)
    monkeypatch.setattr(implicit, "KKT_SOLVE", "dense")
    _tree_close(g, jax.grad(f)(jnp.asarray(x0)), 1e-8)


@pytest.mark.slow
def test_path_constrained_robot_pkm2(monkeypatch):
    robot = jtraj.robots.get("pkm2")
    # the AL method needs more than TIGHT's 1000 iterations on pkm2 (about 1,600 at N = 20)
    PKM2 = jtraj.SolverOptions(tol_feasibility=1e-10, tol_optimality=1e-10, max_iter=4000, method="al")
    q0 = np.asarray(robot.limits.q_min) * 0.5 + np.asarray(robot.limits.q_max) * 0.5
    lo, hi = np.asarray(robot.limits.q_min), np.asarray(robot.limits.q_max)
    qs, qg = q0 - 0.1 * (hi - lo), q0 + 0.1 * (hi - lo)

    def make(g):
        return jtraj.Problem(robot, qs, jnp.asarray(g), N=N, weights=jtraj.Weights(**WEIGHTS))

    # the base in two stages (tolerances 1e-8, then 1e-10 warm): the cold AL run at 1e-10 can
    # stop feasible but not certified within its iterations (the tolerances are traced
    # numbers: the same programs)
    ROUGH = jtraj.SolverOptions(tol_feasibility=1e-8, tol_optimality=1e-8, max_iter=4000, method="al")
    rough = jtraj.solve(make(qg), options=ROUGH)
    base = jtraj.solve(make(qg), options=PKM2, init=(rough.v, rough.h))
    assert bool(base.converged), base.status_message
    g = jax.grad(lambda x: jtraj.solve(make(x), options=PKM2, init=(base.v, base.h)).cost)(jnp.asarray(qg))
    fd = _fd(make, qg, lambda s: s.cost, base, absolute=1e-6, options=PKM2)
    _close(g, fd, rtol=1e-4)
    monkeypatch.setattr(implicit, "KKT_SOLVE", "dense")
    _tree_close(g, jax.grad(lambda x: jtraj.solve(make(x), options=PKM2, init=(base.v, base.h)).cost)(jnp.asarray(qg)), 1e-8)


@pytest.mark.slow  # pkm2 at N = 20 solved to 1e-11, its forward-mode program and four re-solves (minutes)
def test_weakly_held_bound_with_a_genuine_multiplier_stays_held():
    """A period on its upper bound with a bound multiplier of about 3e-7, below the
    default threshold WEAK * max multiplier (3.1e-7), at an optimum solved to 1e-11: the
    threshold follows the optimum's accuracy, so the bound is held and the derivative
    equals the Richardson extrapolation of central differences of re-solves (releasing
    the bound gives a derivative of T 3.9e-5 off). pkm2, the start and goal of
    bench_grad's path kind, pair 36."""
    from jtraj.transcription import Transcription

    robot = jtraj.robots.get("pkm2")
    lo, hi = np.asarray(robot.limits.q_min), np.asarray(robot.limits.q_max)
    u = np.random.default_rng([1, 36]).uniform(0.2, 0.8, (2, 2))
    problem = jtraj.Problem(robot, lo + u[0] * (hi - lo), lo + u[1] * (hi - lo), N=20,
                            weights=jtraj.Weights(**WEIGHTS))
    al = jtraj.AugmentedLagrangian(tol_feasibility=1e-10, tol_optimality=1e-10, max_iter=8000)
    rough = jtraj.solve(problem, solver=al)
    assert bool(rough.converged), rough.status_message

    def resolve(p, init, *stages):
        """``stages`` run in turn, each from the point of the one before (the AL method
        at 1e-12 is not reached from every start at XLA's optimisation level 0, the
        tests' level)."""
        for opts in stages:
            s = jtraj.solve(p, solver=opts, init=init)
            assert bool(s.converged), s.status_message
            init = (s.v, s.h)
        return s

    # the refinement's two interior-point stages: tolerances 1e-9, then 1e-11
    base = resolve(problem, (rough.v, rough.h), implicit.REFINE_IP, implicit.REFINE_IP_TIGHT)
    assert float(base.kkt_error) <= 1e-11
    tr = Transcription("decoupled")
    z = implicit.z_of(problem, tr, base)
    act = implicit.active_set(problem, tr, z)
    scale = max(1.0, float(jnp.max(jnp.abs(act.mult))))
    nlp = implicit._nlp(problem, tr)
    held = np.asarray(act.at_hi)
    # the interior-point method's point lies within its barrier's reach of the bound
    assert held.sum() == 1 and 0 <= float(nlp.layout.z_hi[held][0] - z[held][0]) < 1e-5
    gf = jax.grad(lambda zz: implicit._cost(nlp, zz))(z)
    J = jax.jacfwd(lambda zz: implicit._rows(nlp, zz)[0])(z)
    lam = jnp.zeros(J.shape[0]).at[act.idx].add(jnp.where(act.on, act.mult, 0.0))
    nu = float((gf + J.T @ lam)[held][0])
    assert -implicit.WEAK * scale < nu < -1e3 * implicit.WEAK_MIN * scale  # genuinely small, not noise

    dyn, static = eqx.partition(problem, eqx.is_inexact_array)
    tau1 = float(robot.limits.tau_max[1])
    get = lambda d: d.robot.limits.tau_max  # noqa: E731
    e = jnp.array([0.0, tau1])  # a relative step in the second actuator's force bound
    T_of = lambda d, *stages: resolve(eqx.combine(d, static), (base.v, base.h), *stages).T  # noqa: E731
    dT = float(jax.jvp(lambda d: T_of(d, implicit.REFINE_IP_TIGHT), (dyn,),
                       (eqx.tree_at(get, jax.tree.map(jnp.zeros_like, dyn), e),))[1])
    # re-solves warm-started at the base optimum, finished by the AL method at 1e-10 (the
    # first interior-point stage's T lies up to 6e-9 off, its barrier's bias): the
    # reference's error is then about 2e-6 relative, against the 3.9e-5 of the derivative
    # with the bound released
    D = []
    for h in (1e-3, 2.5e-4):
        Ts = [float(T_of(eqx.tree_at(get, dyn, get(dyn) + sg * h * e), implicit.REFINE_IP, al))
              for sg in (1.0, -1.0)]
        D.append((Ts[0] - Ts[1]) / (2 * h))
    ref = (16 * D[1] - D[0]) / 15
    assert abs(dT - ref) <= 5e-6 * abs(ref), (dT, ref)


@pytest.mark.parametrize("name, value", [
    ("time", -1.0), ("energy", -0.1), ("kinetic", np.inf), ("singularity", np.nan),
    ("U", np.array([0.1, -0.2, 0.3])), ("Q", np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])),
])
def test_weights_traced_past_their_check_are_flagged_on_the_device(name, value):
    """What ``Weights`` refuses on the host (a negative or non-finite weight, a U or Q that
    is not positive semidefinite) the device's face check flags when the value is traced
    past the constructor; valid weights are not flagged."""
    if name not in ("U", "Q"):
        with pytest.raises(ValueError, match=name):
            jtraj.Weights(**{**WEIGHTS, name: value})
    p = _problem(weights=jtraj.Weights(**WEIGHTS, U=np.full(3, 0.1), Q=np.eye(3)))
    bad = eqx.tree_at(lambda q: getattr(q.weights, name), p, jnp.asarray(value, float))
    face = jax.jit(lambda q: q.infeasible_on_its_face())
    assert not bool(face(p))
    assert bool(face(bad))


def test_traced_negative_weight_gives_invalid_input_and_nan_gradients(grads, base):
    """A negative time weight traced past ``Weights`` (its host check cannot see it): the
    solve flags INVALID_INPUT and every gradient is NaN. (The problem differs from
    ``grads``' in leaf values only: the same programs.)"""
    # (a float64 array like the constructor's: not weakly typed, the same programs)
    p = eqx.tree_at(lambda q: q.weights.time, _problem(), jnp.full_like(_problem().weights.time, -1.0))
    assert int(jtraj.solve(p, options=TIGHT).status) == jtraj.Status.INVALID_INPUT
    g = _reverse(p)
    for out in ("T", "cost"):
        for leaf in jax.tree.leaves(g[out]):
            assert np.all(np.isnan(np.asarray(leaf)))


# a pair whose default solve (the interior-point method at its default tolerances) converges
# on the barrier's central path at a point whose active set misses constraints with small
# multipliers: the derivative there is not valid, the rule refines the optimum
DEFAULT_START, DEFAULT_GOAL = np.array((-0.9944, -0.6317, 0.7231)), np.array((-0.9287, -0.9564, 0.6696))


@pytest.mark.slow  # (about 40 s: it compiles the default interior-point programs at N = 10)
def test_converged_default_solve_gets_the_refined_optimums_derivative(monkeypatch, base):
    """``jax.grad`` through a converged default solve whose returned point does not give a
    valid derivative (the rule refines it: counted here) gives finite gradients equal to
    central differences of tight re-solves. (serial3, N = 10: the tangent program is
    ``grads``', the refinement's and the re-solves' AL program ``base``'s.)"""
    p = _problem(q_start=DEFAULT_START, q_goal=DEFAULT_GOAL)
    refined = []
    host = implicit._refine_host

    def spy(*args):
        refined.append(np.asarray(args[3]))
        return host(*args)

    monkeypatch.setattr(implicit, "_refine_host", spy)
    dyn, static = eqx.partition(p, eqx.is_inexact_array)

    def f(d):
        s = jtraj.solve(eqx.combine(d, static))
        return jnp.stack([s.T, s.cost]), s

    _, vjp, sol = jax.vjp(f, dyn, has_aux=True)
    g = {"T": vjp(jnp.array([1.0, 0.0]))[0], "cost": vjp(jnp.array([0.0, 1.0]))[0]}
    assert bool(sol.converged), sol.status_message
    assert len(refined) == 1 and bool(refined[0])  # the returned point's derivative was not valid
    tight = jtraj.solve(p, options=TIGHT, init=(sol.v, sol.h))
    assert bool(tight.converged), tight.status_message
    m0 = np.asarray(ROBOT.masses)
    fd = _fd(lambda m: _problem(robot=jtraj.robots.get("serial3", masses=m), q_start=DEFAULT_START,
                                q_goal=DEFAULT_GOAL), m0, _T_and_cost, tight, rel=1e-4)
    for i, out in enumerate(("T", "cost")):
        assert np.all(np.isfinite(np.asarray(g[out].robot.masses)))
        _close(g[out].robot.masses, fd[i], rtol=1e-4)
    for leaf in jax.tree.leaves(g):
        assert np.all(np.isfinite(np.asarray(leaf)))


# serial3 at N = 20 between a start and a goal whose default optimum gives no valid
# derivative where it is returned, and where the AL method at 1e-10 warm-started there walks
# to a neighbouring local optimum (T 0.6647459 against 0.6647232): the refinement's first
# interior-point stage keeps the returned point's optimum
REFINE_START = np.array([0.40686395101237993, -0.08337037687187787, -1.044073050788108])
REFINE_GOAL = np.array([0.6024830699415404, -0.29660584323654327, -1.2339307421466343])


@pytest.mark.slow  # the default solver, the refinement and a tangent program at N = 20 (minutes)
def test_refinement_of_a_default_optimum_matches_tight_re_solves(monkeypatch):
    """``jax.grad`` of T in the goal through a converged default solve whose returned point
    needs the refinement equals Richardson-extrapolated central differences of re-solves
    by the AL method at 1e-12 warm-started at the refined optimum (feasible, their optimality
    certified or not in 8,000 iterations), to 1e-6 relative; the
    refined optimum is the returned one's (T within the interior-point tolerance)."""
    problem = lambda g: jtraj.Problem(ROBOT, REFINE_START, g, N=20, weights=jtraj.Weights(**WEIGHTS))  # noqa: E731
    refined = []
    host = implicit._refine_host

    def spy(*args):
        out = host(*args)
        refined.append(out)
        return out

    monkeypatch.setattr(implicit, "_refine_host", spy)
    T, g = jax.value_and_grad(lambda q: jtraj.solve(problem(q)).T)(jnp.asarray(REFINE_GOAL))
    assert len(refined) == 1  # the returned point's derivative was not valid
    u, h = refined[0]
    assert np.all(np.isfinite(np.asarray(g)))
    assert abs(float(jnp.sum(h)) - float(T)) < 1e-3 * float(T)
    tight = jtraj.AugmentedLagrangian(tol_feasibility=1e-12, tol_optimality=1e-12, max_iter=8000)

    def accurate(s):  # certified at 1e-12, or feasible (the AL method at 1e-12 may stop short of certifying
        # optimality in 8,000 iterations; the agreement below is the test of the re-solves' precision)
        return int(s.status) in (jtraj.Status.CONVERGED, jtraj.Status.FEASIBLE_NOT_OPTIMAL)

    at = jtraj.solve(problem(REFINE_GOAL), solver=tight, init=(u, h))
    assert accurate(at), (at.status_message, float(at.kkt_error))
    np.testing.assert_allclose(float(at.T), float(jnp.sum(h)), rtol=1e-8)
    fd = []
    for i in range(3):
        d = []
        for step in (1e-4, 2.5e-5):
            vals = []
            for sign in (1.0, -1.0):
                q = REFINE_GOAL.copy()
                q[i] += sign * step
                s = jtraj.solve(problem(q), solver=tight, init=(at.v, at.h))
                assert accurate(s), (s.status_message, float(s.kkt_error))
                vals.append(float(s.T))
            d.append((vals[0] - vals[1]) / (2 * step))
        fd.append((16 * d[1] - d[0]) / 15)
    np.testing.assert_allclose(np.asarray(g), fd, rtol=1e-6, atol=1e-9 * max(abs(x) for x in fd))


@pytest.mark.slow  # the traced refinement's program (about a minute) besides the default solver's
def test_refinement_on_the_host_equals_the_traced_refinement():
    """The refinement with concrete values (its stages run by the staged solver's
    programs, ``_refine_staged``) reaches the point the traced refinement (``refine``, one
    program: what a derivative inside ``jit`` runs) reaches from the same returned
    optimum, to 1e-8 of the largest entry."""
    from jtraj.transcription import Transcription

    tr = Transcription("decoupled")
    p = jtraj.Problem(ROBOT, REFINE_START, REFINE_GOAL, N=20, weights=jtraj.Weights(**WEIGHTS))
    sol = jtraj.solve(p)
    assert bool(sol.converged), sol.status_message
    at = (tr.controls_of(sol), sol.h)
    host = implicit._refine_staged(p, tr, at)
    traced = eqx.filter_jit(lambda q, a: implicit.refine(q, tr, a, jnp.bool_(True)))(p, at)
    for a, b, start in zip(host, traced, at):
        a, b = np.asarray(a), np.asarray(b)
        assert np.all(np.isfinite(a)) and np.max(np.abs(a - np.asarray(start))) > 1e-9  # it moved
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8 * np.max(np.abs(b)))
