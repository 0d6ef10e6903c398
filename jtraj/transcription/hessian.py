"""The decoupled transcription's Hessian in closed form: the recursion's first and second
derivatives assembled with the stage Hessians from autodiff (the solver's fast path), and
the diagonal and row bounds the stage-wise Newton solve needs without forming it."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .base import Layout
from .recursion import prefix_sums, sample_times, suffix_sums, time_differences


def decoupled_hessian(layout: Layout, W, c, Hk):
    """Hessian in z of ``sum_k l_k(W_k(z))`` for the decoupled recursion, from the stage
    co-states ``c = dl_k/dw_k`` (N+1, nw) and stage Hessians ``Hk`` (N+1, nw, nw), both
    from autodiff, using the closed form of the recursion's derivatives (the solver's
    fast path; :meth:`jtraj.solver.nlp.NLP.al_derivatives` falls back to ``jacfwd`` for the
    other transcriptions, and the tests check both against each other).

    With ``t_k = sum_{i<k} h_i`` and ``j < k``, the recursion gives (I: n x n identity)::

        dqd_k/dv_j = h_j I          dq_k/dv_j = h_j (t_k - t_j - h_j / 2) I
        dqd_k/dh_j = v_j            dq_k/dh_j = qd_j + (t_k - t_j) v_j

    and its only second derivatives (i, j < k)::

        d2qd_k/dh_j dv_j = I        d2q_k/dh_j dv_j = (t_k - t_j) I
        d2q_k/dh_i dv_j = h_j I  (j < i)        d2q_k/dh_i dh_j = v_min(i,j)

    so ``H = sum_k J_k^T Hk J_k + sum_k c_k . d2W_k`` is assembled from O(N^2 n) terms
    without differentiating the recursion. The state rows of J (2n per stage) and its
    control rows (v_k, h_k: selectors of z) are treated apart, which halves the work of
    the dense product. Internally z is ordered stage-major, y = (v_0, h_0, v_1, h_1, ...).
    """
    N, n = layout.N, layout.m_u
    ns, ny = 2 * n, N * (n + 1)
    A, sy, Chv, Chh, perm = decoupled_pieces(layout, W, c)
    Hss, Hsc, Hcc = Hk[:, :ns, :ns], Hk[:N, :ns, ns:], Hk[:N, ns:, ns:]
    H = jnp.einsum("kai,kaj->ij", A, jnp.einsum("kab,kbj->kaj", Hss, A))
    X = jnp.einsum("kai,kab->ikb", A[:N], Hsc).reshape(ny, ny) * sy[None]  # state-control rows
    H = H + X + X.T
    H = H + jnp.einsum("kab,kl->kalb", Hcc, jnp.eye(N, dtype=W.dtype)).reshape(ny, ny) * jnp.outer(sy, sy)
    C = jnp.zeros((N, n + 1, N, n + 1), W.dtype).at[:, n, :, :n].set(Chv).reshape(ny, ny)
    C = C + C.T + jnp.zeros((N, n + 1, N, n + 1), W.dtype).at[:, n, :, n].set(Chh).reshape(ny, ny)
    H = H + C * jnp.outer(sy, sy)
    return H[perm][:, perm]


def costate_terms(c, u, dt):
    """The co-state term ``sum_k c_k . d2W_k`` of :func:`decoupled_hessian` by its
    pieces, unscaled, from the co-states c (N+1, nw), the accelerations u (N, n) and
    ``dt`` (N+1, N), t_k - t_j where k > j and 0 elsewhere: Cq (N, n), the suffix sums
    ``sum_{k > i} cq_k`` of the position co-states (which carry d2q_k to every k > j), so
    that [h_i, v_j] = Cq_i h_j for j < i; cv_diag (N, n), the [h_j, v_j] entries; Chh
    (N, N), the [h_i, h_j] block ``Cq_{max(i,j)} . v_min(i,j)``."""
    N, n = u.shape
    cq, cqd = c[:, :n], c[:, n:2 * n]
    Cq = suffix_sums(cq)
    cv_diag = suffix_sums(cqd) + jnp.sum(dt[..., None] * cq[:, None, :], axis=0)
    M = Cq @ u.T  # [i, j] = Cq_i . v_j
    I, J = jnp.arange(N)[:, None], jnp.arange(N)[None, :]
    return Cq, cv_diag, jnp.where(I >= J, M, M.T)


def decoupled_pieces(layout: Layout, W, c):
    """The recursion's derivatives for :func:`decoupled_hessian`, stage-major
    (y = (v_0, h_0, v_1, h_1, ...)): the state rows A (N+1, 2n, ny) of J (scaled to z),
    dy/dz sy (ny,), the co-state terms Chv (N, N, n) [h_i, v_j] and Chh (N, N) [h_i, h_j]
    (unscaled), and the permutation from y to z's order."""
    N, n = layout.N, layout.m_u
    ns, ny = 2 * n, N * (n + 1)
    qd, u, h = W[:, n:ns], W[:N, ns:ns + n], W[:N, -1]
    _, low, dt = time_differences(h)
    eye = jnp.eye(n, dtype=W.dtype)

    def rows(coef, dh):  # (N+1, N) scalar v-coefficients, (N+1, N, n) h-columns
        blk = coef[:, None, :, None] * eye[None, :, None, :]  # (N+1, n, N, n)
        return jnp.concatenate([blk, dh.transpose(0, 2, 1)[..., None]], axis=-1)

    Aq = rows(jnp.where(low, h[None] * (dt - 0.5 * h[None]), 0.0), jnp.where(low[..., None], qd[None, :N] + dt[..., None] * u[None], 0.0))
    Aqd = rows(jnp.where(low, h[None], 0.0), jnp.where(low[..., None], u[None], 0.0))
    sy = jnp.tile(jnp.concatenate([layout.u_scale, layout.h_scale[None]]), N)  # dy/dz
    A = jnp.concatenate([Aq, Aqd], axis=1).reshape(N + 1, ns, ny) * sy[None, None]  # state rows of J
    Cq, cv_diag, Chh = costate_terms(c, u, dt)
    I, J = jnp.arange(N)[:, None], jnp.arange(N)[None, :]
    Chv = jnp.where((J < I)[..., None], Cq[:, None, :] * h[None, :, None], 0.0) + jnp.eye(N)[..., None] * cv_diag[None]
    perm = np.concatenate([(np.arange(N)[:, None] * (n + 1) + np.arange(n)).ravel(), np.arange(N) * (n + 1) + n])
    return A, sy, Chv, Chh, perm


def state_diagonal(layout: Layout, W, Hss):
    """The diagonal of ``sum_k J_k^T Hss_k J_k`` over the states' rows J_k of the
    recursion, unscaled, (N, n + 1) stage-major, in O(N n^2) instead of O(N^2 n^3): every
    column of J_k is a polynomial in ``dt = t_k - t_j`` (j < k):

        h_j:          x_kj = p_j + dt r_j,  p_j = (qd_j, v_j), r_j = (v_j, 0)
        v_j (comp b): h_j (dt - h_j / 2) in q_k[b], h_j in qd_k[b]

    so the sums over k > j need only the suffix sums of Hss_k, t_k Hss_k, t_k^2 Hss_k."""
    N, n = layout.N, layout.m_u
    qd, u, h = W[:N, n:2 * n], W[:N, 2 * n:3 * n], W[:N, -1]
    t = sample_times(h)
    tk, tj = t[:, None, None], t[:N, None, None]
    T0, T1, T2 = suffix_sums(Hss), suffix_sums(tk * Hss), suffix_sums(tk**2 * Hss)
    S0, S1, S2 = T0, T1 - tj * T0, T2 - 2 * tj * T1 + tj**2 * T0  # sums of dt^0, dt^1, dt^2 times Hss_k
    p = jnp.concatenate([qd, u], axis=1)
    r = jnp.concatenate([u, jnp.zeros_like(u)], axis=1)

    def quad(S, a, b):
        return jnp.sum(a[:, :, None] * S * b[:, None, :], axis=(1, 2))

    d_h = quad(S0, p, p) + 2 * quad(S1, p, r) + quad(S2, r, r)
    i = np.arange(n)
    hj = h[:, None]

    def qq(S):
        return S[:, i, i]

    d_v = hj**2 * (qq(S2) - hj * qq(S1) + hj**2 / 4 * qq(S0) + 2 * (S1[:, i, n + i] - hj / 2 * S0[:, i, n + i])
                   + S0[:, n + i, n + i])
    return jnp.concatenate([d_v, d_h[:, None]], axis=1)


def decoupled_hessian_bounds(layout: Layout, W, c, Hk):
    """The diagonal of :func:`decoupled_hessian`'s H and a function ``free -> bound``
    giving upper bounds on the row sums of |H| over the free columns
    (``sum_{j free} |H_ij| <= bound_i``), both in z's order, without forming H or the
    recursion's Jacobian: the diagonal in O(N n^2) (:func:`state_diagonal`), the bound
    in O(N^2 n) (instead of O(N^3 n^2) for H). The bound takes absolute values stage by
    stage (|H| <= sum_k |J_k|^T |Hk| |J_k| + |C|); it feeds the Gershgorin shift of the
    stage-wise Newton solve (:mod:`jtraj.lq`). The diagonal comes first because the
    solver's choice of free variables depends on it.

    With the derivatives of :func:`decoupled_hessian`, |J_k| 1_free and |J_k|^T u need
    no (N+1, 2n, N (n+1)) Jacobian: the v-columns' coefficients ``h_j`` and
    ``h_j (t_k - t_j - h_j / 2)`` are positive polynomials in t_k, so their sums over
    j < k (or k > j) are prefix (suffix) sums; only the h-columns' ``|qd_j + (t_k - t_j)
    v_j|`` need an (N+1, N, n) array. The co-state term's |C| has the same structure
    (``Chv[i, j] = Cq_{>i} h_j`` for j < i). On serial3 at N = 20 this takes the diagonal
    and the row bounds from about 100 to 60 us per problem against the dense Jacobian."""
    N, n = layout.N, layout.m_u
    ns = 2 * n
    qd, u, h = W[:N, n:ns], W[:N, ns:ns + n], W[:N, -1]
    sv, sh = layout.u_scale[None], layout.h_scale  # (1, n): the v-scales by stage rows
    t, low, dt = time_differences(h)
    Hss, Hcc = Hk[:, :ns, :ns], Hk[:N, ns:, ns:]
    Cq, cv_diag, Chh = costate_terms(c, u, dt)
    # diagonal: state part, the control block, the co-state term (on the h diagonal only)
    sd = state_diagonal(layout, W, Hss)  # (N, n + 1), unscaled
    hcc = jnp.diagonal(Hcc, axis1=1, axis2=2)  # (N, n + 1)
    d_v = (sd[:, :n] + hcc[:, :n]) * sv**2
    d_h = (sd[:, n] + hcc[:, n] + jnp.diagonal(Chh)) * sh**2
    diag = jnp.concatenate([d_v.ravel(), d_h])
    # |qd_j + (t_k - t_j) v_j| (k > j), the h-columns of the position rows
    E = jnp.where(low[..., None], jnp.abs(qd[None] + dt[..., None] * u[None]), 0.0)  # (N+1, N, n)
    aV = jnp.abs(u)
    aCq, aCv, aChh = jnp.abs(Cq), jnp.abs(cv_diag), jnp.abs(Chh)
    tj = t[:N, None]
    hj = h[:, None]
    zero = jnp.zeros((1, n), W.dtype)

    def rows(free):
        fv = free[:N * n].reshape(N, n).astype(W.dtype)
        fh = free[N * n:].astype(W.dtype)
        # w = |J_k| 1_free: state rows, then the stage's own controls
        hf = hj * fv * sv
        Ph = prefix_sums(hf)  # (N+1, n)
        w_q = t[:, None] * Ph - prefix_sums((tj + hj / 2) * hf) + sh * jnp.sum(E * fh[None, :, None], axis=1)
        w_qd = Ph + sh * prefix_sums(aV * fh[:, None])
        w_u = jnp.concatenate([jnp.concatenate([fv * sv, fh[:, None] * sh], axis=1), jnp.zeros((1, n + 1), W.dtype)])
        w = jnp.concatenate([w_q, w_qd, w_u], axis=1)  # (N+1, 2n + n + 1)
        U = jnp.sum(jnp.abs(Hk) * w[:, None, :], axis=-1)  # |Hk| w
        uq, uqd = U[:, :n], U[:, n:ns]
        # |J_k|^T U summed over k
        Sq, Stq, Sqd = suffix_sums(uq), suffix_sums(t[:, None] * uq), suffix_sums(uqd)
        r_v = sv * hj * (Stq - (tj + hj / 2) * Sq + Sqd) + U[:N, ns:ns + n] * sv
        r_h = sh * (jnp.sum(E * uq[:, None, :], axis=(0, 2)) + jnp.sum(aV * Sqd, axis=1)) + U[:N, -1] * sh
        # |C| (scaled): [h_i, v_ja] = Cq_{>i,a} h_j (j < i) + cv_diag_ia (j == i), [h_i, h_j] = Chh
        r_h = r_h + sh * jnp.sum(aCq * Ph[:N] + sv * aCv * fv, axis=1) + sh**2 * (aChh @ fh)
        r_v = r_v + sh * sv * (hj * suffix_sums(jnp.concatenate([aCq * fh[:, None], zero])) + aCv * fh[:, None])
        return jnp.concatenate([r_v.ravel(), r_h])

    return diag, rows
