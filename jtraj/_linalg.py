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

Here the factorisation is written out in ``jnp`` operations for a static order ``n <=``
:data:`SMALL_MAX`: LU with partial pivoting (LAPACK's ``getrf`` without blocking: the
same pivots and, up to rounding, the same factors), row exchanges as selects rather
than gathers, so that the elimination fuses with its neighbours into XLA loops. No
custom call remains. A solve's derivatives are solves with the same matrix (a custom
JVP, as ``jnp.linalg.solve`` has); a determinant's go through the elimination (the
pivot choice is piecewise constant), which keeps them finite at a singular matrix.
Larger orders fall back to ``jnp.linalg``. A singular matrix gives a zero determinant
and, as LAPACK's solve does, non-finite solutions.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

#: the largest order eliminated here; beyond it ``jnp.linalg`` (LAPACK on a CPU)
SMALL_MAX = 8


def _lu(A):
    """(packed factors (n, n): unit-lower L below the diagonal and U on and above it,
    the row permutation (n,), its sign) of one square matrix."""
    n = A.shape[-1]
    rows = jnp.arange(n)
    perm = rows
    sign = jnp.ones((), A.dtype)
    for k in range(n - 1):
        p = k + jnp.argmax(jnp.abs(A[k:, k]))
        is_p, is_k = (rows == p)[:, None], (rows == k)[:, None]
        row_k, row_p = A[k], jnp.sum(jnp.where(is_p, A, 0), axis=0)
        A = jnp.where(is_k, row_p, jnp.where(is_p, row_k, A))
        perm = jnp.where(rows == k, perm[p], jnp.where(rows == p, perm[k], perm))
        sign = jnp.where(p != k, -sign, sign)
        pivot = A[k, k]
        # (a zero pivot: the column below it is zero too, and so are the multipliers)
        f = A[k + 1:, k] / jnp.where(pivot == 0, 1, pivot)
        A = A.at[k + 1:, k + 1:].add(-f[:, None] * A[k, k + 1:][None, :]).at[k + 1:, k].set(f)
    return A, perm, sign


def _solve_lu(LU, perm, b):
    """The solution of ``A x = b`` (b: (n,) or (n, k)) from :func:`_lu` of A, by
    column-oriented substitutions (one vector update per column)."""
    n = LU.shape[-1]
    rows = jnp.arange(n)
    col = lambda k, keep: jnp.where(keep, LU[:, k], 0).reshape((n,) + (1,) * (b.ndim - 1))  # noqa: E731
    y = jnp.sum(jnp.where((perm[:, None] == rows[None, :]).reshape((n, n) + (1,) * (b.ndim - 1)), b[None], 0),
                axis=1)  # P b
    for k in range(n - 1):  # L y = P b (L unit lower)
        y = y - col(k, rows > k) * y[k:k + 1]
    for k in reversed(range(n)):  # U x = y, x overwriting y
        xk = y[k:k + 1] / LU[k, k]
        y = jnp.where((rows == k).reshape(col(k, True).shape), xk, y - col(k, rows < k) * xk)
    return y


def _check(A):
    if A.ndim < 2 or A.shape[-1] != A.shape[-2]:
        raise ValueError(f"A must be square in its last two axes, got shape {A.shape}")


@jax.custom_jvp
def _solve_one(A, b):
    LU, perm, _ = _lu(A)
    return _solve_lu(LU, perm, b)


@_solve_one.defjvp
def _solve_one_jvp(primals, tangents):
    # d x = A^-1 (d b - d A x): a solve with the same matrix, whose factorisation XLA
    # computes once (the same operations on the same operands), rather than the
    # derivative of the elimination (n^3 per tangent instead of n^2)
    (A, b), (dA, db) = primals, tangents
    x = _solve_one(A, b)
    return x, _solve_one(A, db - dA @ x)


def solve(A, b):
    """The solution x of ``A x = b`` by LU with partial pivoting in ``jnp`` operations: no
    LAPACK call for orders n <= 8 (``jnp.linalg.solve`` beyond). A: (..., n, n); b:
    (..., n) or (..., n, k) with the same leading axes. Derivatives: solves with the same
    matrix. A singular A gives non-finite entries, as LAPACK's solve does."""
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
        LU, _, sign = _lu(A)
        return sign * jnp.prod(jnp.diagonal(LU))

    return jnp.vectorize(one, signature="(n,n)->()")(A)
