"""Linear solves and determinants of small matrices by unrolled Gaussian elimination.

The robot models solve small systems in their dynamics (a parallel robot's leg forces
``J^T tau = Q``, 6 x 6 for the Gough-Stewart platform; the constraint forces of a wheeled
robot) and take small determinants (manipulability). ``jnp.linalg.solve`` and ``det``
lower each of them to a call of jaxlib's CPU LAPACK kernels, and the solver's programs
hold dozens of such calls once the dynamics are differentiated twice. With jaxlib 0.10.2
a program that holds many of them can stop for good on a CPU: its result never becomes
ready while every thread waits (reproduced: one vmapped interior-point iteration of
``gough_stewart`` on 16 lanes, whose stage Hessians hold 31 LAPACK calls, stopped in
about four runs in five; on 12 lanes it finished). :meth:`Planner.plan
<jtraj.online.Planner.plan>` guards its calls against the same kernels run on two threads
at once (``jtraj.online.SERIAL_CUSTOM_CALLS``).

Here the eliminations are written out in ``jnp`` operations for a static order ``n <=``
:data:`SMALL_MAX`, with LAPACK's partial pivoting (``getrf``'s pivots) and row exchanges
as selects rather than gathers, so that they fuse with their neighbours into XLA loops. No custom call remains.

- A solve is Gauss-Jordan elimination of ``[A | b | I]``: the solution and the inverse
  from one pass of n rank-one updates (about half the operations that an LU
  factorisation and its two substitutions put in the program), then one step of
  iterative refinement with that inverse, ``x + A^-1 (b - A x)``, which brings the
  residual to an LU solve's (Gauss-Jordan's alone can be larger by up to the condition
  number). Its derivatives are
  products with that inverse, by a custom JVP (``d x = A^-1 (d b - d A x)``, ``d A^-1 =
  -A^-1 d A A^-1``) that applies again at every order, so no derivative of the
  elimination is ever formed.
- A determinant is the product of the pivots of an LU factorisation, and its
  derivatives go through the elimination (the pivot choice is piecewise constant),
  which keeps them finite at a singular matrix.

Larger orders fall back to ``jnp.linalg``. A singular matrix gives a zero determinant
and, as LAPACK's solve does, non-finite solutions.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

#: the largest order eliminated here; beyond it ``jnp.linalg`` (LAPACK on a CPU)
SMALL_MAX = 8


def _swap_rows(M, k, p):
    """M with rows k and p (traced) exchanged, by selects (exact, and fusible)."""
    rows = jnp.arange(M.shape[0])
    is_p, is_k = (rows == p)[:, None], (rows == k)[:, None]
    return jnp.where(is_k, jnp.sum(jnp.where(is_p, M, 0), axis=0), jnp.where(is_p, M[k], M))


def _lu(A):
    """(packed factors (n, n): unit-lower L below the diagonal and U on and above it,
    the sign of the row permutation) of one square matrix."""
    n = A.shape[-1]
    sign = jnp.ones((), A.dtype)
    for k in range(n - 1):
        p = k + jnp.argmax(jnp.abs(A[k:, k]))
        A = _swap_rows(A, k, p)
        sign = jnp.where(p != k, -sign, sign)
        pivot = A[k, k]
        # (a zero pivot: the column below it is zero too, and so are the multipliers)
        f = A[k + 1:, k] / jnp.where(pivot == 0, 1, pivot)
        A = A.at[k + 1:, k + 1:].add(-f[:, None] * A[k, k + 1:][None, :]).at[k + 1:, k].set(f)
    return A, sign


def _mm(a, b):
    # full precision on every backend (float32 products may round their operands, as
    # TF32 on GPUs does), so that derivatives are as accurate as the elimination
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)


def _gauss_jordan(A, B):
    """``A^-1 B`` for B (n, k), by Gauss-Jordan elimination of ``[A | B]`` with partial
    pivoting (the pivots of :func:`_lu`): per column, the row exchange, then one rank-one
    update of every other row."""
    n = A.shape[-1]
    rows = jnp.arange(n)
    M = jnp.concatenate([A, B], axis=1)
    for k in range(n):
        M = _swap_rows(M, k, k + jnp.argmax(jnp.abs(M[k:, k])))
        pivot_row = M[k] / M[k, k]
        M = jnp.where((rows == k)[:, None], pivot_row[None, :],
                      M - jnp.where(rows == k, 0, M[:, k])[:, None] * pivot_row[None, :])
    return M[:, n:]


def _check(A):
    if A.ndim < 2 or A.shape[-1] != A.shape[-2]:
        raise ValueError(f"A must be square in its last two axes, got shape {A.shape}")


@jax.custom_jvp
def _solve_inv(A, B):
    """(A^-1 B, A^-1) for B (n, k), from one elimination of ``[A | B | I]``."""
    n, k = B.shape
    X = _gauss_jordan(A, jnp.concatenate([B, jnp.eye(n, dtype=A.dtype)], axis=1))
    x, inv = X[:, :k], X[:, k:]
    # one step of iterative refinement: Gauss-Jordan elimination is forward stable but not
    # backward stable (its residual can exceed an LU solve's by up to the condition number),
    # and the solver's stopping tests at 1e-11 read the efforts' residual-level noise
    return x + _mm(inv, B - _mm(A, x)), inv


@_solve_inv.defjvp
def _solve_inv_jvp(primals, tangents):
    # d (A^-1 B) = A^-1 (d B - d A A^-1 B), d A^-1 = -A^-1 d A A^-1: the tangents are
    # products with A^-1, and so, by this rule again, are the derivatives of every order
    (A, B), (dA, dB) = primals, tangents
    x, X = _solve_inv(A, B)
    return (x, X), (_mm(X, dB - _mm(dA, x)), -_mm(_mm(X, dA), X))


def _solve_one(A, b):
    if b.ndim == 1:
        return _solve_inv(A, b[:, None])[0][:, 0]
    return _solve_inv(A, b)[0]


def solve(A, b):
    """The solution x of ``A x = b`` by Gauss-Jordan elimination with partial pivoting in
    ``jnp`` operations: no LAPACK call for orders n <= 8 (``jnp.linalg.solve`` beyond).
    A: (..., n, n); b: (..., n) or (..., n, k) with the same leading axes. Derivatives:
    products with the inverse of A. A singular A gives non-finite entries, as LAPACK's
    solve does."""
    A, b = jnp.asarray(A), jnp.asarray(b)
    _check(A)
    signature = "(n,n),(n)->(n)" if b.ndim == A.ndim - 1 else "(n,n),(n,k)->(n,k)"
    dtype = jnp.result_type(A, b)

    def one(A, b):
        if A.shape[-1] > SMALL_MAX:
            return jnp.linalg.solve(A, b)
        return _solve_one(A.astype(dtype), b.astype(dtype))

    return jnp.vectorize(one, signature=signature)(A, b)


def det(A):
    """The determinant of A (..., n, n) by LU with partial pivoting in ``jnp`` operations:
    no LAPACK call for orders n <= 8 (``jnp.linalg.det`` beyond). Derivatives through the
    elimination, finite at a singular matrix (where the determinant is 0)."""
    A = jnp.asarray(A)
    _check(A)
    if A.shape[-1] > SMALL_MAX:
        return jnp.linalg.det(A)

    def one(A):
        LU, sign = _lu(A)
        return sign * jnp.prod(jnp.diagonal(LU))

    return jnp.vectorize(one, signature="(n,n)->()")(A)
