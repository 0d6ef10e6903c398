"""Stage-wise Newton directions for the decoupled transcription (a Riccati recursion).

The solver's Newton system ``(H_f + s D) d = -g_f`` in the scaled controls z is dense
(every state depends on all earlier controls), and factorising it costs O((N (n+1))^3)
per shift. The same system is the KKT system of a linear-quadratic problem over the
stages, which a backward Riccati recursion solves in O(N n^3)::

    min  sum_k  1/2 [dx_k; du_k]^T [[Q_k, S_k^T], [S_k, R_k]] [dx_k; du_k] + [c_x; c_u]_k . [dx_k; du_k]
    s.t. dx_{k+1} = A_k dx_k + B_k du_k,   dx_0 = 0

with the state ``x_k = (q_k, qd_k, t_k)`` (``t_k``: time elapsed, whose terminal value
carries the bound on T), the controls ``du_k = (dv_k, dh_k)`` in z's scaling, ``A_k, B_k``
the Jacobians of Khoukhi's recursion, the stage gradients ``c`` and Hessians of the
augmented Lagrangian, and the recursion's curvature weighted by the co-states
``lambda_{k+1}`` (the reduced Hessian of the Lagrangian equals the Hessian of the
condensed objective), all from autodiff (:func:`stage_model`). Bounds held active by the
projected Newton method are fixed (``du_i = 0``) and the Levenberg shift is added to the
free controls' diagonal, so the result equals the dense solve (tests compare both to
1e-9). Measured on serial3 (2 cores): about even with the dense solve at N = 20, 4.1x
faster in a batch and 2.1x for one solve at N = 40 (``SolverOptions.linear_solver``).

The small per-stage factorisations are unrolled Cholesky factorisations of
``(n+1) x (n+1)`` matrices written with array operations, which vectorise over the
shifts and a batch (LAPACK would be called once per matrix).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from .transcription import sample_times, recursion_step

__all__ = ["StageModel", "decoupled_step", "newton_directions", "small_cho_solve", "stage_model"]


def small_cho_solve(A: Array, Y: Array) -> tuple[Array, Array]:
    """Solve ``A X = Y`` for a small symmetric A (m, m, *L) and Y (m, r, *L) by an
    unrolled Cholesky factorisation; the trailing *lane* axes L come last so that every
    operation vectorises over them. Returns (X (m, r, *L), ok (*L)) where ``ok`` says
    whether A was numerically positive definite (X is then finite, NaN otherwise)."""
    m = A.shape[0]
    L = [[None] * m for _ in range(m)]
    ok = jnp.ones(A.shape[2:], bool)
    inv_diag = []
    for j in range(m):
        s = A[j, j] - sum(L[j][k] ** 2 for k in range(j)) if j else A[j, j]
        pos = s > 1e-300
        ok = ok & pos
        d = jnp.sqrt(jnp.where(pos, s, jnp.nan))
        inv_diag.append(1.0 / d)
        for i in range(j + 1, m):
            t = A[i, j] - sum(L[i][k] * L[j][k] for k in range(j)) if j else A[i, j]
            L[i][j] = t * inv_diag[j]
    Z = []  # forward substitution L Z = Y, then back substitution L^T X = Z
    for i in range(m):
        acc = Y[i] - sum(L[i][k][None] * Z[k] for k in range(i)) if i else Y[i]
        Z.append(acc * inv_diag[i][None])
    X = [None] * m
    for i in reversed(range(m)):
        acc = Z[i] - sum(L[k][i][None] * X[k] for k in range(i + 1, m)) if i < m - 1 else Z[i]
        X[i] = acc * inv_diag[i][None]
    return jnp.stack(X), ok


class StageModel(NamedTuple):
    """The Newton model of the condensed objective in stage form (see the module doc)."""

    A: Array  # (N, nx, nx) d x_{k+1} / d x_k
    B: Array  # (N, nx, m) d x_{k+1} / d u_k (z's scaling)
    Q: Array  # (N, nx, nx) state blocks, k < N
    S: Array  # (N, m, nx) control-state blocks (z's scaling)
    R: Array  # (N, m, m) control blocks (z's scaling)
    cx: Array  # (N+1, nx) the stage gradients in x_k (row N: terminal, with d phi / dT)
    cu: Array  # (N, m) the stage gradients in u_k (z's scaling)
    PN: Array  # (nx, nx) terminal Hessian (with d2 phi / dT2)
    g: Array  # (N (n+1),) gradient in z of the condensed objective


def decoupled_step(x: Array, u: Array) -> Array:
    """Khoukhi's recursion on the augmented state x = (q, qd, t) with u = (v, h)."""
    n = u.shape[0] - 1
    h = u[-1]
    q, qd = recursion_step(x[:n], x[n:2 * n], u[:n], h)
    return jnp.concatenate([q, qd, (x[-1] + h)[None]])


def stage_model(W: Array, c: Array, Hk: Array, u_scale: Array, h_scale: Array,
                phi_t: tuple[Array, Array] = (0.0, 0.0)) -> StageModel:
    """Stage blocks of the Newton model of ``sum_k l_k(w_k) + phi(T)``.

    Every derivative of the recursion is autodiff of the one-step map
    :func:`decoupled_step`: its Jacobians A_k, B_k (forward mode; :func:`newton_directions`
    relies on their sparsity), the gradient and the co-states (one reverse pass
    through the recursion re-run from the given states, with a zero perturbation added to
    each state, whose cotangent is that state's co-state), and its curvature weighted by
    the co-states (the Hessian of ``lambda_{k+1} . step``). Nothing is hand-derived.

    Args:
        W: (N+1, 3n+1) stage vectors w_k = (q_k, qd_k, v_k, h_k) (physical units).
        c: (N+1, 3n+1) gradients of the stage terms in w_k (autodiff).
        Hk: (N+1, 3n+1, 3n+1) their Hessians in w_k (autodiff).
        u_scale: (n,) and h_scale: () the scaling of z = (v / u_scale, h / h_scale).
        phi_t: first and second derivative of a term of the total time T = t_N (the AL
            term of the bound on T), or zeros.
    """
    step = decoupled_step
    N = W.shape[0] - 1
    n = (W.shape[1] - 1) // 3
    nx = 2 * n + 1
    dt = W.dtype
    sy = jnp.concatenate([u_scale, h_scale[None]]).astype(dt)  # (m,) d(physical)/dz per stage
    t = sample_times(W[:N, -1])
    X = jnp.concatenate([W[:, :2 * n], t[:, None]], axis=1)  # (N+1, nx) states
    U = W[:N, 2 * n:]  # (N, m) physical controls
    dphi, d2phi = (jnp.asarray(x, dt) for x in phi_t)
    cx = jnp.concatenate([c[:, :2 * n], jnp.zeros((N + 1, 1), dt)], axis=1).at[N, -1].set(dphi)
    cu = c[:N, 2 * n:]

    def linearised(U, E):  # sum_k c_k . w_k along the recursion re-run from X_0 + E_0
        def body(x, ue):
            u, e = ue
            return step(x, u) + e, x

        xN, xs = jax.lax.scan(body, X[0] + E[0], (U, E[1:]))
        return jnp.sum(cx[:N] * xs) + cx[N] @ xN + jnp.sum(cu * U)

    g_u, lam = jax.grad(linearised, argnums=(0, 1))(U, jnp.zeros_like(X))  # lam[k]: co-state of x_k
    A, B = jax.vmap(jax.jacfwd(step, argnums=(0, 1)))(X[:N], U)

    def curvature(xk, uk, lam_next):  # Hessian in (x, u) of lam_{k+1} . step(x, u)
        # by forward mode over the gradient one argument at a time: the step is affine in
        # the state, so the state's tangents meet only symbolic zeros (no work)
        def grad(x, u):
            gx, gu = jax.grad(lambda x, u: lam_next @ step(x, u), argnums=(0, 1))(x, u)
            return jnp.concatenate([gx, gu])

        return jnp.concatenate([jax.jacfwd(grad, argnums=i)(xk, uk) for i in (0, 1)], axis=1)

    C = jax.vmap(curvature)(X[:N], U, lam[1:])
    ix = jnp.arange(2 * n)

    def pad(Y, axis):  # the t row / column of the stage Hessians (the stage terms ignore t)
        return jnp.concatenate([Y, jnp.zeros(Y.shape[:axis] + (1,) + Y.shape[axis + 1:], dt)], axis=axis)

    Q = pad(pad(Hk[:N][:, ix[:, None], ix[None, :]], 1), 2) + C[:, :nx, :nx]
    S = (pad(Hk[:N, 2 * n:, :2 * n], 2) + C[:, nx:, :nx]) * sy[None, :, None]
    R = (Hk[:N, 2 * n:, 2 * n:] + C[:, nx:, nx:]) * jnp.outer(sy, sy)[None]
    g_u = g_u * sy[None, :]
    return StageModel(
        A=A, B=B * sy[None, None, :], Q=Q, S=S, R=R, cx=cx, cu=cu * sy[None, :],
        PN=pad(pad(Hk[N][ix[:, None], ix[None, :]], 0), 1).at[-1, -1].set(d2phi),
        g=jnp.concatenate([g_u[:, :n].ravel(), g_u[:, -1]]))


def newton_directions(model: StageModel, free: Array, shifts: Array) -> tuple[Array, Array]:
    """Projected Newton directions ``d = -(H_f + s D_free)^{-1} g_f``, one per shift.

    Args:
        model: :func:`stage_model`.
        free: (N (n+1),) mask of the free variables of z (z's layout: all v, then all h);
            held variables get d = 0.
        shifts: (S,) Levenberg shifts added to the free variables' diagonal.

    Returns (d (S, N (n+1)), ok (S,): whether every stage factorisation was positive
    definite, i.e. whether ``H_f + s D_free`` is).
    """
    N, nx, m = model.B.shape
    n = m - 1
    dt = model.B.dtype
    ff = jnp.concatenate([free[:N * n].reshape(N, n), free[N * n:, None]], axis=1).astype(dt)  # (N, m)
    # held variables: du_i = 0 (rows and columns removed, unit diagonal)
    S = model.S * ff[..., None]
    R = model.R * ff[:, :, None] * ff[:, None, :] + jax.vmap(jnp.diag)(1.0 - ff)
    # the sparsity of Khoukhi's recursion (the values come from the autodiff Jacobians):
    # A = [[I, h I, 0], [0, I, 0], [0, 0, 1]], and B's columns in v are diagonal blocks
    # (h^2/2, h on the q and qd rows, scaled); only B's column in h is dense
    ix = jnp.arange(n)
    h = model.A[:, 0, n]
    bq = model.B[:, ix, ix] * ff[:, :n]
    bqd = model.B[:, n + ix, ix] * ff[:, :n]
    bh = model.B[:, :, n] * ff[:, n:]
    d, ok = _riccati(h, bq, bqd, bh, model.Q, S, R, model.cx, model.cu * ff, model.PN, ff, shifts)
    return jnp.moveaxis(d, -1, 0), ok


def _lead(a, ndim: int):
    """``a`` with leading axes of length 1 up to ``ndim`` axes: the broadcast NumPy's rank
    promotion would make, written out."""
    return jnp.reshape(a, (1,) * (ndim - a.ndim) + a.shape)


def _mm(X, Y):
    """Products of small matrices X (a, b, *L) and Y (b, c, *L) lane by lane, as sums of
    elementwise products (fused by XLA)."""
    return sum(X[:, b, None] * Y[None, b] for b in range(X.shape[1]))


class _Recursion(NamedTuple):
    """The Jacobians of one step of the recursion by their nonzeros (see
    :func:`newton_directions`), lanes trailing: h (1,) the period (A's qd -> q block is
    h I), bq, bqd (n, 1) the diagonals of B's v columns on the q and qd rows, bh (nx, 1)
    B's column in h. Products with A and B cost O(nx^2) instead of O(nx^3). Measured
    against dense products (serial3, N = 20, 32 problems under vmap, one core): the
    stage model, Hessian bounds and Riccati solve 348 -> 234 us per problem, a whole
    Newton iteration 541 -> 410 us."""

    h: Array
    bq: Array
    bqd: Array
    bh: Array

    def right_A(self, X):  # X A, X (r, nx, *L)
        n = self.bq.shape[0]
        return jnp.concatenate([X[:, :n], X[:, n:2 * n] + _lead(self.h, X.ndim) * X[:, :n], X[:, 2 * n:]], axis=1)

    def left_At(self, Y):  # A^T Y, Y (nx, c, *L)
        n = self.bq.shape[0]
        return jnp.concatenate([Y[:n], Y[n:2 * n] + _lead(self.h, Y.ndim) * Y[:n], Y[2 * n:]], axis=0)

    def right_B(self, X):  # X B, X (r, nx, *L) -> (r, m, *L)
        n = self.bq.shape[0]
        xv = X[:, :n] * self.bq[None] + X[:, n:2 * n] * self.bqd[None]
        return jnp.concatenate([xv, jnp.sum(X * self.bh[None], axis=1)[:, None]], axis=1)

    def left_Bt(self, Y):  # B^T Y, Y (nx, c, *L) -> (m, c, *L)
        n = self.bq.shape[0]
        yv = Y[:n] * self.bq[:, None] + Y[n:2 * n] * self.bqd[:, None]
        return jnp.concatenate([yv, jnp.sum(Y * self.bh[:, None], axis=0)[None]], axis=0)

    def step(self, dx, du):  # A dx + B du, dx (nx, *L), du (m, *L)
        n = self.bq.shape[0]
        dq = dx[:n] + _lead(self.h, dx.ndim) * dx[n:2 * n] + self.bq * du[:n]
        dqd = dx[n:2 * n] + self.bqd * du[:n]
        return jnp.concatenate([dq, dqd, dx[2 * n:]], axis=0) + self.bh * _lead(du[n], self.bh.ndim)


def _riccati(h, bq, bqd, bh, Q, S, R, cx, cu, PN, ff, shifts):
    """The Riccati solve for all shifts at once, the shifts as a trailing *lane* axis:
    the recursion's Jacobians by their nonzeros h (N,), bq, bqd (N, n), bh (N, nx) (see
    :class:`_Recursion`), Q (N, nx, nx), S (N, m, nx), R (N, m, m), cx (N+1, nx),
    cu (N, m), PN (nx, nx), ff (N, m), shifts (L,). Returns d (nz, L) and ok (L,).
    (Measured with dense A and B, serial3 N = 20, 32 problems under vmap: 145-196 us per
    problem for 4 shifts, 31-37 for one; a batching rule that made the problems lanes
    too was slower.)"""
    N, m = ff.shape[:2]
    n, nx = m - 1, Q.shape[1]
    h, bq, bqd, bh, Q, S, R, cx, cu, PN, ff = (x[..., None] for x in (h, bq, bqd, bh, Q, S, R, cx, cu, PN, ff))
    eye = jnp.eye(m, dtype=R.dtype)[..., None]

    def back(carry, xs):
        P, p, ok = carry
        rec, Rk, Sk, Qk, rk, cxk, fk = xs
        rec = _Recursion(*rec)
        PA = rec.right_A(P)
        Quu = Rk + rec.left_Bt(rec.right_B(P)) + eye * (shifts[None, :] * fk)[:, None]
        Qux = Sk + rec.left_Bt(PA)
        Qxx = Qk + rec.left_At(PA)
        qu = rk + rec.left_Bt(p[:, None])[:, 0]
        qx = cxk + rec.left_At(p[:, None])[:, 0]
        X, pd = small_cho_solve(Quu, jnp.concatenate([Qux, qu[:, None]], axis=1))
        K, kff = -X[:, :-1], -X[:, -1]
        QuxT = jnp.swapaxes(Qux, 0, 1)
        P_new = Qxx + _mm(QuxT, K)
        return (0.5 * (P_new + jnp.swapaxes(P_new, 0, 1)), qx + _mm(QuxT, kff[:, None])[:, 0], ok & pd), (K, kff)

    lanes = shifts.shape
    init = (jnp.broadcast_to(PN, PN.shape[:2] + lanes), jnp.broadcast_to(cx[N], (nx,) + lanes),
            jnp.ones(lanes, bool))
    recs = (h, bq, bqd, bh)
    (_, _, ok), (K, kff) = jax.lax.scan(back, init, (recs, R, S, Q, cu, cx[:N], ff), reverse=True)

    def fwd(dx, xs):
        Kk, kk, rec = xs
        du = _mm(Kk, dx[:, None])[:, 0] + kk
        return _Recursion(*rec).step(dx, du), du

    _, du = jax.lax.scan(fwd, jnp.zeros((nx,) + lanes, Q.dtype), (K, kff, recs))
    du = du * ff  # (N, m, *lanes)
    return jnp.concatenate([du[:, :n].reshape((N * n,) + lanes), du[:, -1]]), ok


def kkt_directions(model: StageModel, shifts: Array, terminal: Array) -> tuple[Array, Array, Array]:
    """Newton directions for several right-hand sides from one factorisation per shift
    (the interior-point method's KKT solve, :mod:`jtraj.solver.ipm`): column 0 is
    ``-(H + s I)^{-1} g`` for the model's own gradient, column j >= 1 is
    ``-(H + s I)^{-1} J_N^T e_j``, the response to a unit linear term
    ``terminal[:, j - 1]`` on the terminal state (the rows of the terminal equalities'
    Jacobian), whose Schur complement gives their multipliers. All controls are free.

    Args:
        model: :func:`stage_model`.
        shifts: (L,) shifts added to the whole diagonal in z.
        terminal: (nx, r) linear terms on the terminal state x_N.

    Returns (d (nz, 1 + r, L), dX (N+1, nx, 1 + r, L) the state trajectories of the
    directions, ok (L,): whether every stage factorisation was positive definite).
    """
    N, nx, m = model.B.shape
    n = m - 1
    r = terminal.shape[1]
    dt = model.B.dtype
    ix = jnp.arange(n)
    recs = (model.A[:, 0, n], model.B[:, ix, ix], model.B[:, n + ix, ix], model.B[:, :, n])
    cx = jnp.zeros((N + 1, nx, 1 + r), dt).at[:, :, 0].set(model.cx).at[N, :, 1:].set(terminal)
    cu = jnp.zeros((N, m, 1 + r), dt).at[:, :, 0].set(model.cu)
    lane = (x[..., None] for x in (*recs, model.Q, model.S, model.R, cx, cu, model.PN))
    h, bq, bqd, bh, Q, S, R, cx, cu, PN = lane
    eye = jnp.eye(m, dtype=dt)[..., None]

    def back(carry, xs):
        P, p, ok = carry
        rec, Rk, Sk, Qk, rk, cxk = xs
        rec = _Recursion(*rec)
        PA = rec.right_A(P)
        Quu = Rk + rec.left_Bt(rec.right_B(P)) + eye * shifts[None, None]
        Qux = Sk + rec.left_Bt(PA)
        Qxx = Qk + rec.left_At(PA)
        qu = rk + rec.left_Bt(p)  # (m, 1 + r, L)
        qx = cxk + rec.left_At(p)
        X, pd = small_cho_solve(Quu, jnp.concatenate([Qux, qu], axis=1))
        K, kff = -X[:, :nx], -X[:, nx:]
        QuxT = jnp.swapaxes(Qux, 0, 1)
        P_new = Qxx + _mm(QuxT, K)
        return (0.5 * (P_new + jnp.swapaxes(P_new, 0, 1)), qx + _mm(QuxT, kff), ok & pd), (K, kff)

    lanes = shifts.shape
    init = (jnp.broadcast_to(PN, PN.shape[:2] + lanes), jnp.broadcast_to(cx[N], (nx, 1 + r) + lanes),
            jnp.ones(lanes, bool))
    (_, _, ok), (K, kff) = jax.lax.scan(back, init, ((h, bq, bqd, bh), R, S, Q, cu, cx[:N]), reverse=True)

    def fwd(dx, xs):  # dx (nx, 1 + r, L)
        Kk, kk, rec = xs
        du = _mm(Kk, dx) + kk
        rec = _Recursion(*(x[:, None] for x in rec))  # broadcast over the right-hand sides
        return rec.step(dx, du), (dx, du)

    xN, (dX, du) = jax.lax.scan(fwd, jnp.zeros((nx, 1 + r) + lanes, dt), (K, kff, (h, bq, bqd, bh)))
    dX = jnp.concatenate([dX, xN[None]])
    d = jnp.concatenate([du[:, :n].reshape((N * n, 1 + r) + lanes), du[:, -1]])
    return d, dX, ok
