"""Certification of a solver's point: the feasibility polish, multiplier estimates
and the KKT error the verification reads."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from .nlp import NLP, Multipliers, violation
from .options import SolverOptions


def stationarity(nlp: NLP, z, g):
    """The largest entry of the projected gradient at z (``g``: the AL's gradient there)."""
    return jnp.max(jnp.abs(z - jnp.clip(z - g, nlp.layout.z_lo, nlp.layout.z_hi)))


def _residual(nlp: NLP, z, act_tol):
    """Stacked equalities and nearly-active inequalities (g > -act_tol); inactive rows are
    zero. (The polish's holding phase takes the nearly-active rows' max(g, 0): it removes
    violations while keeping satisfied nearly-active rows where they are to first order,
    their Jacobian rows kept, instead of pulling them onto their boundary.)"""
    eq, ineq, glob = nlp.constraints(z)
    rows = [c.ravel() for c in jax.tree.leaves(eq)]
    for g in jax.tree.leaves(ineq) + [glob]:
        rows.append(jnp.where(g.ravel() > -act_tol, g.ravel(), 0.0))
    return jnp.concatenate(rows)


def _ridge_solve(Jf, b, eps, gram=None):
    """``(Jf^T Jf + eps I)^-1 b`` by a Cholesky factorisation (nz x nz): the normal
    equations of the polish's minimum-norm corrections and of the least-squares
    multipliers, each with its own ridge ``eps``. ``gram``: ``Jf^T Jf`` if known."""
    A = (Jf.T @ Jf if gram is None else gram) + eps * jnp.eye(Jf.shape[1], dtype=Jf.dtype)
    return jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(A), True), b)


#: the violation below which the feasibility polish stops (the verification asks 1e-6)
_POLISH_DONE = 1e-12


def _polish(nlp: NLP, z, iterations: int = 4, chord: bool = True, release_above=None, skip=None):
    """Feasibility polish: a few Gauss-Newton projections of z onto the manifold of the
    equalities and nearly-active inequalities (minimum-norm corrections, simple bounds
    held). The AL leaves O((lambda* - lambda)/mu) violations; this removes them without
    changing the optimum to first order. A step is kept only if the violation shrinks;
    the projections stop after ``iterations`` or at the first that does not shrink it.

    With ``chord`` (the finish) the constraints' Jacobian is computed once, at z, and the
    projections also stop once the violation is below ``_POLISH_DONE``: the corrections
    are as small as the AL's violations, so the chord converges about as fast as
    Gauss-Newton at about half the cost. Without it (the restart's starting point, see
    :func:`jtraj.solver.al.restart_state`) the Jacobian is recomputed at every projection, because a restart
    runs on from that point for many iterations and is sensitive to it.

    A satisfied nearly-active inequality is held where it is to first order. With
    ``release_above``, a point that this holding phase leaves violated by more than
    ``release_above`` goes on to a releasing phase over all inequality rows: a satisfied
    inequality is left free unless the correction would take it across its boundary.
    Holding fails where a row is nearly parallel to a violated one
    (``Problem(efforts="intervals")``), whose correction it would cancel (see
    :func:`final_polish`). Both phases are one bounded loop with one body, which halves
    the finish's and the restart's compilation; the normal equations' ``J^T J`` is formed
    once per Jacobian, the fixed variables' rows and columns zeroed in it."""
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi
    window = 1e-3  # the holding phase's act_tol: the rows nearly active within it
    n_eq = sum(x.size for x in jax.tree.leaves(jax.eval_shape(lambda zz: nlp.constraints(zz)[0], z)))
    n_rows = jax.eval_shape(lambda zz: _residual(nlp, zz, window), z).shape[0]
    is_ineq = jnp.arange(n_rows) >= n_eq
    jac = jax.jacfwd(_residual, argnums=1)
    done = _POLISH_DONE if chord else 0.0
    releasing = release_above is not None

    def viol(zz):
        return violation(*nlp.constraints(zz))

    def correction(J, r, fixed, gram=None):
        # normal equations in z (nz x nz, smaller than the row space); the tiny ridge
        # selects the minimum-norm correction when J is rank deficient. ``gram``: J^T J,
        # whose rows and columns of the fixed variables are Jf^T Jf's zeros
        Jf = jnp.where(fixed[None, :], 0.0, J)
        if gram is not None:
            gram = jnp.where(fixed[:, None] | fixed[None, :], 0.0, gram)
        return _ridge_solve(Jf, Jf.T @ r, 1e-10 * (1.0 + jnp.max(jnp.sum(Jf**2, axis=0))), gram)

    def body(c: _Projection) -> _Projection:
        z, v, k, rel, v_start = c.z, c.violation, c.it, c.releasing, c.violation_start
        act_tol = jnp.where(rel, jnp.inf, window)
        if chord:  # the Jacobian at the entry point, of the phase's rows
            J = jnp.where(rel, J_all, J_near) if releasing else J_near
            # J^T J of the holding phase's rows (a releasing lane's first correction
            # below is replaced by its own rounds' in any case)
            gram = G_near
        else:
            J = jac(nlp, z, act_tol)
            gram = J.T @ J
        fixed = (z <= lo + 1e-12) | (z >= hi - 1e-12)
        raw = _residual(nlp, z, act_tol)
        Jr, r = J, jnp.where(is_ineq, jnp.maximum(raw, 0.0), raw)  # holding: violated part only
        dz = correction(Jr, r, fixed, gram)
        if releasing:
            # releasing: equalities and violated inequalities; satisfied rows the
            # correction would take across their boundary join them (four rounds: each
            # correction can cross others)
            def select(c: _Rounds) -> _Rounds:
                dz = correction(jnp.where(c.rows[:, None], J, 0.0), jnp.where(c.rows, raw, 0.0), fixed)
                return _Rounds(c.rows | (is_ineq & (raw - J @ dz > 0)), dz, c.round + 1)

            rows, dz, _ = jax.lax.while_loop(lambda c: rel & (c.round < 4), select,
                                             _Rounds(~is_ineq | (raw > 0), dz, jnp.asarray(0)))
            Jr = jnp.where(rel, jnp.where(rows[:, None], J, 0.0), J)
            r = jnp.where(rel, jnp.where(rows, raw, 0.0), r)
            # the selected rows' J^T J, formed (like the rounds) only while some lane releases
            gram, _ = jax.lax.while_loop(lambda c: rel & ~c[1], lambda c: (Jr.T @ Jr, jnp.asarray(True)),
                                         (gram, jnp.asarray(False)))
        # variables the correction would push through a bound are held there and the
        # correction recomputed (clipping it would undo part of it)
        dz = correction(Jr, r, fixed | (z - dz < lo) | (z - dz > hi), gram)
        z_new = jnp.clip(z - dz, lo, hi)
        v_new = viol(z_new)
        better = jnp.isfinite(v_new) & (v_new < v)
        z, v, k = jnp.where(better, z_new, z), jnp.where(better, v_new, v), k + 1
        going = better & (v_new > done)
        if releasing:  # the holding phase over: the releasing one starts where needed
            switch = ~rel & ~(going & (k < iterations)) & (v > release_above) & (v_start <= window)
            rel, k, going = rel | switch, jnp.where(switch, 0, k), going | switch
        return _Projection(z, v, k, going, rel, v_start)

    v0 = viol(z)
    need = v0 > done if skip is None else (v0 > done) & ~skip
    if chord:
        # every row's Jacobian at z; the holding phase's rows are those nearly active there
        # (the rows of jac(nlp, z, window)), the releasing phase's all rows (a chord from z,
        # not from where the releasing phase starts: a point the holding phase moved by
        # the size of the AL's violations). J^T J once per chord, not twice per projection
        # (each a (rows x nz)^T (rows x nz) product: serial3, N = 20, 241 x 80). Inside a
        # loop of at most one pass, so that under vmap it runs only if some lane polishes
        J_all, J_near, G_near = at_most_once(need, lambda zz: _chord_jacobian(nlp, zz, window, is_ineq), z)
    carry = _Projection(z, v0, jnp.asarray(0), need, jnp.asarray(False), v0)
    # a bounded loop (under vmap it runs while some lane still improves)
    return jax.lax.while_loop(lambda c: c.going & (c.it < iterations), body, carry).z


class _Projection(NamedTuple):
    """The carry of :func:`_polish`'s projections."""

    z: Array
    violation: Array
    #: projections so far (of the current phase)
    it: Array
    #: the last projection shrank the violation (and it is above the target)
    going: Array
    #: in the releasing phase
    releasing: Array
    #: the violation at the polish's start
    violation_start: Array


class _Rounds(NamedTuple):
    """The carry of the releasing phase's row selection."""

    rows: Array
    dz: Array
    round: Array


def at_most_once(pred, fn, x, fill=0.0):
    """``fn(x)`` where ``pred``, else ``fill`` in its shape: a loop of at most one pass, so
    that under vmap (where ``lax.cond`` evaluates both sides) it runs only if some lane
    needs it. The body's argument is x plus zero times the pass count: an argument that
    does not change from pass to pass lets XLA hoist the whole body out of the loop
    (loop-invariant code motion), and it then ran on every call."""
    out = jax.tree.map(lambda a: jnp.full(a.shape, fill, a.dtype), jax.eval_shape(fn, x))

    def body(c):
        return fn(x + 0.0 * c[1]), c[1] + 1

    return jax.lax.while_loop(lambda c: pred & (c[1] < 1), body, (out, jnp.zeros((), x.dtype)))[0]


def _chord_jacobian(nlp: NLP, z, window, is_ineq):
    """Every constraint row's Jacobian at z, the holding phase's rows of it (those nearly
    active within ``window``), and their J^T J (see :func:`_polish`)."""
    J_all = jax.jacfwd(_residual, argnums=1)(nlp, z, jnp.inf)
    J_near = jnp.where((_residual(nlp, z, jnp.inf) > -window)[:, None] | ~is_ineq[:, None], J_all, 0.0)
    return J_all, J_near, J_near.T @ J_near


def final_polish(nlp: NLP, z, opts: SolverOptions, chord: bool = True, skip=None):
    """:func:`_polish` with its releasing phase for a point the holding one leaves violated
    by more than ``verify_tol``. Where the holding polish succeeds its result is kept
    unchanged. ``chord``: chord or Gauss-Newton projections (see :func:`_polish`).

    Measured: on 96 dataset pairs (seed 5, h_max 0.2 s) with ``Problem(efforts="intervals")``
    the holding polish left 4 certified optima violated by 2e-6 to 1.7e-5: nearly parallel
    effort rows cancelled its corrections; the releasing one brought all 4 below 1e-15
    (costs within 2.5e-5). On benchmark pair 16 of seed 21 (``kink_margin=1e-4,
    kink_after=0``) the loop certified a point 6e-6 off the goal whose Gauss-Newton
    correction crossed a torque bound 1e-3 away from its limit, so no step was kept
    (``VERIFICATION_FAILED``); the releasing polish over all rows removed it (cost +5e-5).
    Only for a point the AL brought within the polish's window: a far-off point (an
    infeasible problem's) is beyond its reach. Under vmap the releasing phase runs only
    while some lane needs it (as a ``lax.cond`` whose predicate differs between lanes it
    ran on every lane, and was then 45 % of a batch's finish, 5.7 of 12.6 ms per problem,
    where hardly any lane needed it)."""
    return _polish(nlp, z, chord=chord, release_above=opts.verify_tol, skip=skip)


def init_multipliers(nlp: NLP, z) -> Multipliers:
    eq, ineq, glob = nlp.constraints(z)
    r0 = nlp.pbm_init if nlp.ineq_penalty == "pbm" else 0.0
    return Multipliers(eq=jax.tree.map(jnp.zeros_like, eq), ineq=jax.tree.map(lambda g: jnp.full_like(g, r0), ineq),
                       glob=jnp.full_like(glob, r0))


def ls_multipliers(nlp: NLP, z, act_tol: float = 1e-3):
    """Least-squares multipliers at z: minimise ||grad f + J_A^T lambda|| over the
    equalities and nearly-active inequalities (rows of :func:`_residual`), in the free
    variables; inequality multipliers are clipped to >= 0, inactive ones are 0.
    Returns (lambda flat, J, grad f, number of equality rows)."""
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi
    gf = jax.grad(lambda zz: sum(nlp.cost_terms(zz).values()))(z)
    J = jax.jacfwd(_residual, argnums=1)(nlp, z, act_tol)
    free = ~((z <= lo + 1e-12) | (z >= hi - 1e-12))
    Jf = jnp.where(free[None, :], J, 0.0)
    # the ridge-regularised normal equations (Jf Jf^T + eps I) lam = -Jf gf, solved in
    # the variables' space by the push-through identity (Jf Jf^T + eps I)^-1 Jf =
    # Jf (Jf^T Jf + eps I)^-1: an nz x nz instead of a rows x rows system (serial3,
    # N = 20: 80 against 241; the KKT error at the end of a batch 3.6 -> 0.9 ms per problem)
    eps = 1e-10 * (1.0 + jnp.max(jnp.sum(Jf**2, axis=1)))  # max diag(Jf Jf^T)
    lam = -Jf @ _ridge_solve(Jf, jnp.where(free, gf, 0.0), eps)
    lam = jnp.where(jnp.isfinite(lam), lam, 0.0)
    n_eq = sum(x.size for x in jax.tree.leaves(nlp.constraints(z)[0]))
    lam = jnp.where(jnp.arange(lam.size) < n_eq, lam, jnp.clip(lam, 0.0, 1e10))
    return lam, J, gf, n_eq


def estimate_multipliers(nlp: NLP, z, act_tol: float = 1e-3, ls=None) -> Multipliers:
    """:func:`ls_multipliers` (or ``ls``, its result) in the multipliers' tree
    structure (for warm starts)."""
    lam = (ls_multipliers(nlp, z, act_tol) if ls is None else ls)[0]
    # the rows of _residual are the leaves of (eq, ineq, glob) in this order
    shapes = Multipliers(*nlp.constraints(z))
    leaves, pos = [], 0
    for x in jax.tree.leaves(shapes):
        leaves.append(lam[pos:pos + x.size].reshape(x.shape))
        pos += x.size
    return jax.tree.unflatten(jax.tree.structure(shapes), leaves)


def kkt_error(nlp: NLP, z, act_tol: float = 1e-3, ls=None):
    """First-order optimality error of the original problem at z, independent of the AL
    state: the projected gradient of the Lagrangian with least-squares multipliers
    (signs enforced; ``ls``: :func:`ls_multipliers` at z if already computed), and
    complementarity max lambda_i * |g_i| over the nearly-active inequalities; in the
    units of ``tol_optimality``."""
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi
    lam, J, gf, n_eq = ls_multipliers(nlp, z, act_tol) if ls is None else ls
    r = gf + J.T @ lam
    pg = z - jnp.clip(z - r, lo, hi)
    rows = _residual(nlp, z, act_tol)
    comp = jnp.where(jnp.arange(lam.size) < n_eq, 0.0, lam * jnp.abs(rows))
    return jnp.maximum(jnp.max(jnp.abs(pg)), jnp.max(comp))


def _multiplier_kkt_error(nlp: NLP, z, mult: Multipliers):
    """The KKT error of :func:`kkt_error` with given multipliers (inequality ones >= 0)
    instead of least-squares ones: the projected gradient of the Lagrangian and the
    complementarity ``lambda_i |g_i|``. Any such multipliers bound the KKT error from
    above."""
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi

    def lagrangian(zz):
        eq, ineq, glob = nlp.constraints(zz)
        val = sum(nlp.cost_terms(zz).values()) + jnp.sum(mult.glob * glob)
        for c, l in zip(jax.tree.leaves((eq, ineq)), jax.tree.leaves((mult.eq, mult.ineq))):
            val = val + jnp.sum(l * c)
        return val, (ineq, glob)

    g, (ineq, glob) = jax.grad(lagrangian, has_aux=True)(z)
    pg = jnp.max(jnp.abs(z - jnp.clip(z - g, lo, hi)))
    comp = [jnp.max(r * jnp.abs(c)) for c, r in zip(jax.tree.leaves(ineq) + [glob],
                                                      jax.tree.leaves(mult.ineq) + [mult.glob])]
    return jnp.maximum(pg, jnp.max(jnp.stack(comp)))


def al_kkt_error(nlp: NLP, z, mult: Multipliers, mu):
    """The smaller KKT error of two multiplier vectors the AL loop provides at its final
    z: its current multipliers (updated at the end of the last subproblem) and the ones
    the AL implies at z (``rho + mu c`` and ``max(0, rho + mu g)``: those of a run stopped
    inside a subproblem). Least-squares multipliers (:func:`kkt_error`) fail where
    nearly-active constraints are nearly parallel, as the efforts at an interval's end and
    at the next sample are when the acceleration hardly changes
    (``Problem(efforts="intervals")``): least squares splits the multiplier into large
    ones of both signs, and clipping the negative one leaves a projected gradient of ~1
    at a point the AL certified (34 of 57 such benchmark pairs above ``tol_optimality``)."""
    eq, ineq, glob = nlp.constraints(z)
    implied = Multipliers(eq=jax.tree.map(lambda r, c: r + mu * c, mult.eq, eq),
                          ineq=jax.tree.map(lambda r, g: nlp.ineq_update(g, r, mu), mult.ineq, ineq),
                          glob=nlp.ineq_update(glob, mult.glob, mu))
    # both by one vmapped pass (one copy of the Lagrangian's gradient in the program)
    both = jax.tree.map(lambda a, b: jnp.stack([a, b]), mult, implied)
    return jnp.min(jax.vmap(lambda m: _multiplier_kkt_error(nlp, z, m))(both))
