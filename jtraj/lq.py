"""Stage-wise Newton directions for the decoupled transcription (a Riccati recursion).

The solver's Newton system ``(H_f + s D) d = -g_f`` in the scaled controls z is dense
(every state depends on all earlier controls), and factorising it costs O((N (n+1))^3)
per shift. The same system is the KKT system of a linear-quadratic problem over the
stages, which a backward Riccati recursion solves in O(N (n+1)^3)::

    min  sum_k  1/2 [dx_k; du_k]^T [[Q_k, S_k^T], [S_k, R_k]] [dx_k; du_k] + [c_x; c_u]_k . [dx_k; du_k]
    s.t. dx_{k+1} = A_k dx_k + B_k du_k,   dx_0 = 0

with the state ``x_k = (q_k, qd_k, t_k)`` (``t_k``: time elapsed, whose terminal value
carries the bound on T), the controls ``du_k = (dv_k, dh_k)`` in z's scaling, ``A_k, B_k``
the Jacobians of Khoukhi's recursion, the stage gradients ``c`` and Hessians of the
augmented Lagrangian from autodiff, and the recursion's curvature weighted by the co-states
``lambda_{k+1}`` (the reduced Hessian of the Lagrangian equals the Hessian of the
condensed objective). Bounds held active by the projected Newton method are fixed
(``du_i = 0``) and the Levenberg shift is added to the free controls' diagonal, so the
result equals the dense solve (tests compare both to 1e-8).

The small per-stage factorisations are unrolled Cholesky factorisations of
``(n+1) x (n+1)`` matrices written with array operations, which vectorise over the
shifts and a batch (LAPACK would be called once per matrix).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

__all__ = ["StageModel", "newton_directions", "small_cho_solve", "stage_model"]


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

    h: Array  # (N,) periods (A_k depends on them only)
    Q: Array  # (N, nx, nx) state blocks, k < N
    S: Array  # (N, m, nx) control-state blocks (z's scaling)
    R: Array  # (N, m, m) control blocks (z's scaling)
    B: Array  # (N, nx, m) d x_{k+1} / d u_k (z's scaling)
    cx: Array  # (N+1, nx) the stage gradients in x_k (row N: terminal, with d phi / dT)
    cu: Array  # (N, m) the stage gradients in u_k (z's scaling)
    PN: Array  # (nx, nx) terminal Hessian (with d2 phi / dT2)
    g: Array  # (N (n+1),) gradient in z of the condensed objective (co-state pass)


def stage_model(W: Array, c: Array, Hk: Array, u_scale: Array, h_scale: Array,
                phi_t: tuple[Array, Array] = (0.0, 0.0)) -> StageModel:
    """Stage blocks of the Newton model of ``sum_k l_k(w_k) + phi(T)``.

    Args:
        W: (N+1, 3n+1) stage vectors w_k = (q_k, qd_k, v_k, h_k) (physical units).
        c: (N+1, 3n+1) gradients of the stage terms in w_k (autodiff).
        Hk: (N+1, 3n+1, 3n+1) their Hessians in w_k (autodiff).
        u_scale: (n,) and h_scale: () the scaling of z = (v / u_scale, h / h_scale).
        phi_t: first and second derivative of a term of the total time T = t_N (the AL
            term of the bound on T), or zeros.
    """
    N = W.shape[0] - 1
    n = (W.shape[1] - 1) // 3
    m = n + 1
    dt = W.dtype
    qd, v, h = W[:N, n:2 * n], W[:N, 2 * n:3 * n], W[:N, -1]
    sy = jnp.concatenate([u_scale, h_scale[None]]).astype(dt)  # (m,) d(physical)/dz per stage
    eye = jnp.eye(n, dtype=dt)

    # co-states of x_k = (q, qd, t): lam_N = c_N, lam_k = c_k + A_k^T lam_{k+1}
    dphi, d2phi = (jnp.asarray(x, dt) for x in phi_t)
    cx = jnp.concatenate([c[:, :2 * n], jnp.zeros((N + 1, 1), dt)], axis=1).at[N, -1].set(dphi)

    def costate(lam_next, k):
        lq, lqd, lt = lam_next[:n], lam_next[n:2 * n], lam_next[-1]
        lam = cx[k] + jnp.concatenate([lq, h[k] * lq + lqd, lt[None]])
        return lam, lam_next

    _, lam_next = jax.lax.scan(costate, cx[N], jnp.arange(N), reverse=True)  # lam_next[k] = lam_{k+1}
    lq, lqd = lam_next[:, :n], lam_next[:, n:2 * n]

    # B_k = d x_{k+1} / d(v_k, h_k) in z's scaling (A_k is applied in closed form)
    Bq = jnp.concatenate([0.5 * (h**2)[:, None, None] * eye, (qd + h[:, None] * v)[..., None]], axis=2)
    Bqd = jnp.concatenate([h[:, None, None] * eye, v[..., None]], axis=2)
    Bt = jnp.zeros((N, 1, m), dt).at[:, 0, -1].set(1.0)
    B = jnp.concatenate([Bq, Bqd, Bt], axis=1) * sy  # (N, nx, m)
    cu = c[:N, 2 * n:] * sy
    g_u = cu + jnp.einsum("kxm,kx->km", B, lam_next)  # (N, m)

    # the recursion's curvature weighted by lam_{k+1} (only h enters nonlinearly:
    # d2 q+/dh dqd = I, d2 q+/dh dv = h I, d2 qd+/dh dv = I, d2 q+/dh2 = v)
    ix = jnp.arange(2 * n)
    Hxx = Hk[:N][:, ix[:, None], ix[None, :]]
    Hux = Hk[:N, 2 * n:, :2 * n].at[:, -1, n:2 * n].add(lq)
    cross = h[:, None] * lq + lqd
    Huu = Hk[:N, 2 * n:, 2 * n:].at[:, -1, :n].add(cross).at[:, :n, -1].add(cross)
    Huu = Huu.at[:, -1, -1].add(jnp.sum(lq * v, axis=1))

    def pad(X, axis):  # the t row / column: no curvature
        return jnp.concatenate([X, jnp.zeros(X.shape[:axis] + (1,) + X.shape[axis + 1:], dt)], axis=axis)

    return StageModel(
        h=h, Q=pad(pad(Hxx, 1), 2), S=pad(Hux, 2) * sy[:, None], R=Huu * jnp.outer(sy, sy), B=B, cx=cx, cu=cu,
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
    B = model.B * ff[:, None, :]
    d, ok = _riccati(model.h, model.Q, S, R, B, model.cx, model.cu * ff, model.PN, ff, shifts)
    return jnp.moveaxis(d, -1, 0), ok


def _mm(X, Y):
    """Products of small matrices X (a, b, *L) and Y (b, c, *L) lane by lane, as sums of
    elementwise products (fused by XLA)."""
    return sum(X[:, b, None] * Y[None, b] for b in range(X.shape[1]))


def _riccati(h, Q, S, R, B, cx, cu, PN, ff, shifts):
    """The Riccati solve for all shifts at once, the shifts as a trailing *lane* axis:
    h (N,), Q (N, nx, nx), S (N, m, nx), R (N, m, m), B (N, nx, m), cx (N+1, nx), cu (N, m),
    PN (nx, nx), ff (N, m), shifts (L,). Returns d (nz, L) and ok (L,).
    (Measured, serial3 N = 20, 32 problems under vmap: 145 us per problem for 4 shifts,
    31 for one; a batching rule that made the problems lanes too was slower, 163-184.)"""
    N, m = ff.shape[:2]
    n, nx = m - 1, Q.shape[1]
    h, Q, S, R, B, cx, cu, PN, ff = (x[..., None] for x in (h, Q, S, R, B, cx, cu, PN, ff))
    eye = jnp.eye(m, dtype=R.dtype)[..., None]

    def A_T(M, hk):  # A_k^T M for A_k = [[I, h I, 0], [0, I, 0], [0, 0, 1]]
        return M.at[n:2 * n].add(hk[None, None] * M[:n])

    def back(carry, xs):
        P, p, ok = carry
        Bk, Rk, Sk, Qk, rk, cxk, hk, fk = xs
        Bt = jnp.swapaxes(Bk, 0, 1)
        PA = jnp.swapaxes(A_T(P, hk), 0, 1)  # P A_k (P symmetric)
        Quu = Rk + _mm(Bt, _mm(P, Bk)) + eye * (shifts * fk)[:, None]
        Qux = Sk + _mm(Bt, PA)
        Qxx = Qk + A_T(PA, hk)
        qu = rk + _mm(Bt, p[:, None])[:, 0]
        qx = cxk + A_T(p[:, None], hk)[:, 0]
        X, pd = small_cho_solve(Quu, jnp.concatenate([Qux, qu[:, None]], axis=1))
        K, kff = -X[:, :-1], -X[:, -1]
        QuxT = jnp.swapaxes(Qux, 0, 1)
        P_new = Qxx + _mm(QuxT, K)
        return (0.5 * (P_new + jnp.swapaxes(P_new, 0, 1)), qx + _mm(QuxT, kff[:, None])[:, 0], ok & pd), (K, kff)

    lanes = shifts.shape
    init = (jnp.broadcast_to(PN, PN.shape[:2] + lanes), jnp.broadcast_to(cx[N], (nx,) + lanes),
            jnp.ones(lanes, bool))
    (_, _, ok), (K, kff) = jax.lax.scan(back, init, (B, R, S, Q, cu, cx[:N], h, ff), reverse=True)

    def fwd(dx, xs):
        Kk, kk, Bk, hk = xs
        du = _mm(Kk, dx[:, None])[:, 0] + kk
        return dx.at[:n].add(hk[None] * dx[n:2 * n]) + _mm(Bk, du[:, None])[:, 0], du

    _, du = jax.lax.scan(fwd, jnp.zeros((nx,) + lanes, Q.dtype), (K, kff, B, h))
    du = du * ff  # (N, m, *lanes)
    return jnp.concatenate([du[:, :n].reshape((N * n,) + lanes), du[:, -1]]), ok
