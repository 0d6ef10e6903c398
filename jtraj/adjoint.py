"""The stage-wise solve of the implicit-differentiation KKT system (decoupled transcription).

:mod:`jtraj.implicit` differentiates the optimum through the KKT system of the active
set at ``z*``::

    [ H_ff   J_Af^T ] [ dz_f ]   [ r_z ]
    [ J_Af   0      ] [ dl   ] = [ r_l ]          (dz_b given: the bound-held variables)

with ``H`` the Hessian of the Lagrangian in z and ``J_A`` the active constraints'
Jacobian. For the decoupled transcription every active row is a function of one stage
vector ``w_k`` (the stage inequalities and path equalities), of the terminal state (the
goal) or of the total time (the bound on T), and H is the Hessian of a sum of stage
terms along Khoukhi's recursion: the system is a linear-quadratic problem over the
stages with stage-wise equality constraints. Here it is solved in O(N) by the Riccati
recursion of the Newton steps (:func:`jtraj.lq.newton_directions`) inside an iteration
on the multipliers (the method of multipliers for a linear system, Uzawa's iteration
with an augmented Hessian)::

    M = H_ff + rho J_Af^T J_Af                      (stage-wise: rho J_k^T J_k per stage)
    x <- x + P(b - K x),   P(r) = ( M^{-1}(r_z + rho J^T r_l),  rho (J M^{-1}(...) - r_l) )

``M`` keeps the stage structure (the penalty adds ``rho J_k^T J_k`` to stage k's
Hessian, ``rho E^T E`` to the terminal one and ``rho (dg_T/dT)^2`` to the time term), so
each application of P is one Riccati factorisation and sweep; ``K x`` is exact (forward-
mode derivatives of the KKT residual of :mod:`jtraj.implicit`). One step of P zeroes the
first block row's residual and divides the second's by ``1 + rho sigma`` for each
eigenvalue sigma of ``J M^{-1} J^T``; the iteration stops where the residual is
``REL_TOL`` of the right-hand side (at most ``MAX_ITER`` steps). M is positive definite
where the reduced Hessian is (second-order sufficiency) and rho is large enough:
``RHO`` times the largest diagonal entry of the stage control blocks.

The active-set KKT system is kept (rather than the interior-point method's barrier KKT
system at its final iterate, ``Sigma = Z / S``): it is what the dense reference solves,
it exists for every primal method (the AL solver ends without slacks), and its solution
is the derivative of the returned optimum itself, not of a barrier problem's central
path at the final barrier parameter.

The solve is wrapped in ``jax.lax.custom_linear_solve`` with the symmetric operator
(bound-held rows and unused multiplier slots as identity rows), so reverse mode
transposes it into the same solve: a gradient costs one structured solve per problem.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from . import lq

__all__ = ["MAX_ITER", "REL_TOL", "RHO", "StagewiseKKT", "stagewise_kkt"]

#: the penalty of the augmented Hessian, relative to the largest stage control curvature
RHO = 1e6
#: the iteration stops where the residual is within REL_TOL of the right-hand side
REL_TOL = 1e-13
#: at most this many multiplier steps (each one Riccati sweep)
MAX_ITER = 12


def _unflatten(flat, like):
    """A flat vector in the order of ``jtraj.implicit._rows`` -> a pytree like ``like``
    (leaves ravelled one after another)."""
    leaves, tdef = jax.tree.flatten(like)
    out, pos = [], 0
    for x in leaves:
        size = int(np.prod(x.shape))
        out.append(flat[pos:pos + size].reshape(x.shape))
        pos += size
    return jax.tree.unflatten(tdef, out)


@dataclasses.dataclass(frozen=True)
class StagewiseKKT:
    """The linear operators of the symmetric KKT system at z* (closures over primal
    values, never differentiated) and its stage-wise solve."""

    matvec: object  # (xz, xl) -> K (xz, xl), the symmetric operator
    iterate: object  # b -> (x, ok): the stage-wise solve; ok: every factorisation positive definite

    def solve(self, matvec, b):
        """For ``jax.lax.custom_linear_solve`` (``matvec`` is this operator)."""
        return self.iterate(b)[0]


def stagewise_kkt(problem, tr, nlp, act, z, kkt_jvp, rows_of) -> StagewiseKKT:
    """The stage-wise solver of :mod:`jtraj.implicit`'s KKT system at z*.

    Args:
        problem, tr, nlp: the problem, its (decoupled) transcription and ``_NLP``.
        act: the :class:`jtraj.implicit.ActiveSet`.
        z: z* (bound-held variables on their bounds).
        kkt_jvp: ``(dz, dl) -> dF`` the forward-mode derivative of the KKT residual in
            (z, l) at (z*, multipliers): the unsymmetric K of the module doc.
        rows_of: ``z -> all constraint rows`` (flat, the order of the active set's
            indices).
    """
    from .solver.ipm import z_to_stages
    from .solver.nlp import Multipliers

    layout = nlp.layout
    N, n = layout.N, problem.robot.n
    nz = z.shape[0]
    dt = z.dtype
    free = ~(act.at_lo | act.at_hi)
    ff = free.astype(dt)
    on = act.on.astype(dt)

    # ---- the multipliers and the active mask in the solver's structure --------------
    eq_like, ineq_like, glob_like = jax.eval_shape(nlp.constraints, z)
    n_eq = sum(int(np.prod(x.shape)) for x in jax.tree.leaves(eq_like))
    n_in = sum(int(np.prod(x.shape)) for x in jax.tree.leaves(ineq_like))
    nc = n_eq + n_in + int(np.prod(glob_like.shape))
    lam = jnp.zeros(nc, dt).at[act.idx].add(jnp.where(act.on, act.mult, 0.0))
    mask = jnp.zeros(nc, dt).at[act.idx].add(on)
    eq_m, ineq_m = _unflatten(lam[:n_eq], eq_like), _unflatten(lam[n_eq:n_eq + n_in], ineq_like)
    glob_m = lam[n_eq + n_in:].reshape(glob_like.shape)
    mult = Multipliers(eq=eq_m, ineq=ineq_m, glob=glob_m)
    eq_a, ineq_a = _unflatten(mask[:n_eq], eq_like), _unflatten(mask[n_eq:n_eq + n_in], ineq_like)
    glob_a = mask[n_eq + n_in:].reshape(glob_like.shape)
    stage_mask = jnp.concatenate([x.reshape(N + 1, -1) for x in jax.tree.leaves(eq_a) + jax.tree.leaves(ineq_a)],
                                 axis=1)  # (N+1, rows per stage)

    # ---- the stage model of the Lagrangian's Hessian --------------------------------
    W = nlp.W(z)
    lag = dataclasses.replace(nlp, ineq_penalty="lagrangian")
    _, c, Hk = lag.stage_derivatives(W, mult, jnp.asarray(0.0, dt))

    def stage_rows(w, sdk):
        eq, ineq = tr.stage_constraints(problem, w, sdk)
        return jnp.concatenate([jnp.ravel(x) for x in jax.tree.leaves(eq) + jax.tree.leaves(ineq)])

    Jw = jax.vmap(jax.jacfwd(stage_rows))(W, nlp.sd)  # (N+1, rows, nw)
    # the penalty's scale: the stage control blocks of the Lagrangian's Hessian in z
    sy = jnp.concatenate([layout.u_scale, layout.h_scale[None]]).astype(dt)
    ctrl = jnp.abs(jnp.diagonal(Hk[:N, 2 * n:, 2 * n:], axis1=1, axis2=2)) * sy[None] ** 2
    rho = RHO * jnp.maximum(1.0, jnp.max(ctrl))
    Hk = Hk + rho * jnp.einsum("kri,kr,krj->kij", Jw, stage_mask, Jw)

    T = jnp.sum(W[:N, -1])
    gT_of = lambda t: jnp.ravel(tr.time_inequalities(problem, t))  # noqa: E731
    dgT = jax.jacfwd(gT_of)(T)
    d2gT = jax.jacfwd(jax.jacfwd(gT_of))(T)
    gm, ga = jnp.ravel(glob_m), jnp.ravel(glob_a)
    dphi = jnp.sum(gm * dgT)
    d2phi = jnp.sum(gm * d2gT) + rho * jnp.sum(ga * dgT**2)
    model = lq.stage_model(W, c, Hk, layout.u_scale, layout.h_scale, (dphi, d2phi))
    zeros_x = jnp.zeros_like(model.cx)

    def m_solve(g):  # M_f^{-1} g_f (held entries 0): one Riccati factorisation and sweep
        d, ok = lq.newton_directions(model._replace(cx=zeros_x, cu=-z_to_stages(g, N, n)), free,
                                     jnp.zeros((1,), dt))
        return jnp.where(ok[0], d[0], 0.0), ok[0]

    # ---- the symmetric operator and the active rows' Jacobian -----------------------
    def rows_on(zz):
        return jnp.where(act.on, rows_of(zz)[act.idx], 0.0)

    _, J_mv = jax.linearize(rows_on, z)  # J_A x
    J_tv = jax.linear_transpose(J_mv, z)  # J_A^T y

    def matvec(x):
        xz, xl = x
        dF = kkt_jvp(xz * ff, xl * on)
        return dF[:nz] * ff + xz * (1.0 - ff), dF[nz:] * on + xl * (1.0 - on)

    def iterate(b):
        """(x, ok): the iteration of the module doc from x = 0, and whether every
        factorisation was positive definite."""
        bnorm = jnp.sqrt(sum(jnp.sum(v**2) for v in b))

        def cond(s):
            it, _, res, _ = s
            rn = jnp.sqrt(sum(jnp.sum(v**2) for v in res))
            return (it < MAX_ITER) & (rn > REL_TOL * bnorm)

        def body(s):
            it, (xz, xl), (rz, rl), ok = s
            dz, ok_k = m_solve(rz * ff + rho * ff * J_tv(rl * on)[0])
            dl = rho * (J_mv(dz) - rl) * on + rl * (1.0 - on)
            x = (xz + dz + rz * (1.0 - ff), xl + dl)
            kx = matvec(x)
            return it + 1, x, tuple(bi - ki for bi, ki in zip(b, kx)), ok & ok_k

        zero = tuple(jnp.zeros_like(v) for v in b)
        _, x, _, ok = jax.lax.while_loop(cond, body, (jnp.asarray(0), zero, b, jnp.asarray(True)))
        # finite for a finite b (a failed factorisation is reported by `ok`): a transposed
        # solve of an invalid sample must not turn its zero cotangent into NaN; a NaN in b
        # (the NaN cotangent of on_failure="nan") stays NaN
        x = tuple(jnp.where(jnp.isfinite(v), v, 0.0) for v in x)
        return tuple(jnp.where(jnp.isfinite(bnorm), v, jnp.nan) for v in x), ok

    return StagewiseKKT(matvec=matvec, iterate=iterate)
