"""jtraj._linalg.solve and det against NumPy (LAPACK), their derivatives against
jnp.linalg's and central differences, and the programs of the robots that use them: no
LAPACK custom call left in the stage Hessians of the Gough-Stewart platform."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtraj import _linalg
from jtraj.robots import small_det, small_solve
from jtraj.robots import get as get_robot


@pytest.mark.parametrize("n", [1, 2, 3, 6, 8, 10])
def test_solve_and_det_match_numpy(n):
    """Random (well conditioned in the mean) batches of every order up to SMALL_MAX and
    one above it (the jnp.linalg fallback): solutions within 1e-11 relative to the
    condition-scaled norm, determinants within 1e-12 relative."""
    rng = np.random.default_rng(n)
    A = rng.normal(size=(7, n, n)) + 2 * np.eye(n)
    b, B = rng.normal(size=(7, n)), rng.normal(size=(7, n, 3))
    x = np.linalg.solve(A, b[..., None])[..., 0]
    scale = np.linalg.cond(A)[:, None] * np.abs(x).max(-1, keepdims=True)
    assert np.all(np.abs(np.asarray(jax.jit(_linalg.solve)(A, b)) - x) <= 1e-14 * scale * n)
    X = np.linalg.solve(A, B)
    assert np.allclose(np.asarray(jax.jit(_linalg.solve)(A, B)), X, rtol=1e-11, atol=1e-11 * np.abs(X).max())
    np.testing.assert_allclose(np.asarray(jax.jit(_linalg.det)(A)), np.linalg.det(A), rtol=1e-12)


@pytest.mark.parametrize("n", [2, 3, 6])
def test_solve_residual_is_an_lu_solves_on_ill_conditioned_matrices(n):
    """Matrices of condition number 1e10 (random orthogonal factors around graded singular
    values): the normwise backward error ||b - A x|| / (||A|| ||x|| + ||b||) within 4 n eps,
    an LU solve's level (NumPy's, reported beside it on failure)."""
    rng = np.random.default_rng(10 + n)
    eps = np.finfo(float).eps
    worst = lapack = 0.0
    for _ in range(50):
        U, _r = np.linalg.qr(rng.normal(size=(n, n)))
        V, _r = np.linalg.qr(rng.normal(size=(n, n)))
        A = U @ np.diag(np.logspace(0, -10, n)) @ V.T
        b = rng.normal(size=n)
        x = np.asarray(jax.jit(_linalg.solve)(A, b))
        err = lambda x: np.linalg.norm(b - A @ x) / (np.linalg.norm(A, 2) * np.linalg.norm(x) + np.linalg.norm(b))  # noqa: E731
        worst, lapack = max(worst, err(x)), max(lapack, err(np.linalg.solve(A, b)))
    assert worst <= 4 * n * eps, (worst, lapack)


def test_pivoting_reorders_rows():
    """A matrix whose leading entry is zero (elimination without row exchanges divides by
    it) and a permutation matrix of sign -1: exact results."""
    solve, det = jax.jit(_linalg.solve), jax.jit(_linalg.det)
    A = np.array([[0.0, 2.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 3.0]])
    np.testing.assert_allclose(np.asarray(solve(A, np.array([3.0, 1.0, 3.0]))), [1.0, 1.0, 1.0], rtol=1e-15)
    assert float(det(A)) == pytest.approx(-6.0, rel=1e-15)
    P = np.eye(4)[[2, 0, 3, 1]]
    assert float(det(P)) == np.linalg.det(P)


def test_singular_matrix():
    """A zero determinant (no NaN from the zero pivot) and, as LAPACK's solve, a
    non-finite solution."""
    S = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [1.0, 0.0, 1.0]])
    assert float(jax.jit(_linalg.det)(S)) == 0.0
    assert not np.all(np.isfinite(np.asarray(jax.jit(_linalg.solve)(S, np.ones(3)))))


def test_derivatives_match_jnp_linalg_and_differences():
    """First and second derivatives in A and b equal those of jnp.linalg (its custom JVP
    rules) to 1e-10 relative, and the gradient of det its central differences to 1e-7."""
    rng = np.random.default_rng(1)
    A, b = rng.normal(size=(5, 5)) + 3 * np.eye(5), rng.normal(size=5)

    def pair(fn_solve, fn_det):
        return lambda A, b: jnp.sum(jnp.sin(fn_solve(A, b))) + fn_det(A) ** 2

    ours, ref = pair(_linalg.solve, _linalg.det), pair(jnp.linalg.solve, jnp.linalg.det)
    for d in (jax.grad, jax.hessian):
        for arg in (0, 1):  # (jitted: op by op, each derivative of the unrolled elimination takes tens of seconds)
            got, want = jax.jit(d(ours, argnums=arg))(A, b), jax.jit(d(ref, argnums=arg))(A, b)
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-10, atol=1e-10 * np.abs(want).max())
    g = np.asarray(jax.grad(lambda A: _linalg.det(A))(A))
    eps, fd = 1e-6, np.zeros_like(A)
    for i in range(5):
        for j in range(5):
            E = np.zeros_like(A)
            E[i, j] = eps
            fd[i, j] = (np.linalg.det(A + E) - np.linalg.det(A - E)) / (2 * eps)
    np.testing.assert_allclose(g, fd, rtol=1e-7, atol=1e-7 * np.abs(fd).max())


def test_higher_and_mixed_derivatives_of_solve_match_jnp_linalg():
    """The solve's rule applies again at every order and in both modes: third derivatives
    (forward over reverse over reverse) in b and mixed in (A, b), and the gradient in a
    right-hand side with several columns, equal jnp.linalg's to 1e-9 relative."""
    rng = np.random.default_rng(2)
    A, b, B = rng.normal(size=(3, 3)) + 2 * np.eye(3), rng.normal(size=3), rng.normal(size=(3, 2))

    def f(solve):
        return lambda A, b: jnp.sum(jnp.sin(solve(A, b)) * jnp.arange(1.0, 1.0 + b.size).reshape(b.shape))

    for d in (lambda g: jax.jacfwd(jax.jacrev(jax.grad(g, 1), 1), 1),
              lambda g: jax.jacfwd(jax.hessian(g, 1), 0),
              lambda g: jax.grad(g, (0, 1))):
        got, want = jax.jit(d(f(_linalg.solve)))(A, b), jax.jit(d(f(jnp.linalg.solve)))(A, b)
        for x, y in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-9, atol=1e-9 * np.abs(y).max())
    got, want = (jax.jit(jax.grad(f(solve), (0, 1)))(A, B) for solve in (_linalg.solve, jnp.linalg.solve))
    for x, y in zip(got, want):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-9, atol=1e-9 * np.abs(y).max())


def test_public_names():
    """jtraj.robots exports the two functions for robots of a user's own."""
    assert small_solve is _linalg.solve and small_det is _linalg.det


def test_bad_shapes_are_rejected():
    with pytest.raises(ValueError, match="square"):
        _linalg.solve(np.ones((2, 3)), np.ones(2))
    with pytest.raises(ValueError, match="square"):
        _linalg.det(np.ones(3))


def test_gough_stewart_stage_hessian_has_no_lapack_call():
    """The second derivatives of the platform's leg forces and manipulability (what the
    interior-point method's stage Hessians differentiate), vmapped over lanes and samples
    as in a batch solve, compile to a program without LAPACK custom calls (jaxlib's CPU
    kernels are what can stop such a program for good, see jtraj._linalg), and equal
    those through jnp.linalg."""
    robot = get_robot("gough_stewart")
    home = np.array([0.0, 0.0, robot.z_home, 0.0, 0.0, 0.0])
    rng = np.random.default_rng(2)
    q = home + 0.05 * rng.normal(size=(4, 3, 6))

    def term(q):
        Q = jnp.arange(1.0, 7.0) + q
        return jnp.sum(robot.generalized_to_actuator(q, Q) ** 2) + robot.manipulability(q)

    def reference(q):
        Q = jnp.arange(1.0, 7.0) + q
        J = robot.actuator_jacobian(q)
        s = jnp.concatenate([jnp.ones(3), jnp.full(3, 1.0 / robot.platform_radius)])
        scaled = lambda q: jnp.linalg.det(robot.actuator_jacobian(q) * s[None, :])  # noqa: E731
        return jnp.sum(jnp.linalg.solve(J.T, Q) ** 2) + jnp.abs(scaled(q)) / jnp.abs(scaled(jnp.asarray(home)))

    H = jax.jit(jax.vmap(jax.vmap(jax.hessian(term))))
    assert "lapack" not in H.lower(q).as_text()
    ref = jax.jit(jax.vmap(jax.vmap(jax.hessian(reference))))(q)
    np.testing.assert_allclose(np.asarray(H(q)), np.asarray(ref), rtol=1e-9, atol=1e-9 * float(jnp.abs(ref).max()))
