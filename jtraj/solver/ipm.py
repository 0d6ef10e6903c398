"""A primal-dual interior-point inner method on the stage-wise Riccati recursion
(``SolverOptions(method="ip")``).

The same NLP as the augmented-Lagrangian solver (:mod:`jtraj.solver`): unknowns z (the
scaled accelerations and periods), the stage inequalities g_k(w_k) <= 0 and the bound on
T, the terminal equalities e(z) = 0 (the goal state), and the boxes on z. Here, as in
IPOPT (Waechter and Biegler 2006):

* every inequality gets a slack s > 0 and a multiplier y > 0 (``g + s = 0``, ``s y = mu``),
  every finite bound of z a multiplier, and the barrier parameter mu falls by IPOPT's
  monotone rule (``mu <- max(tol / 10, min(mu / 5, mu^1.5))`` once the barrier problem's
  error is below ``10 mu``);
* the Newton step of the primal-dual system, with slacks and multipliers eliminated, is
  an equality-constrained linear-quadratic problem over the stages: the Hessian of the
  Lagrangian (exact, from the same per-stage autodiff pieces as the AL solver, with the
  Lagrangian's multipliers in place of the AL's terms) plus ``J_k^T (y / s) J_k`` per
  stage and the bounds' ``z_L / (z - lo) + z_U / (hi - z)``. The terminal equalities are
  kept exactly: one Riccati factorisation solves the gradient's right-hand side and one
  per goal row (:func:`jtraj.lq.kkt_directions`), and a 2n x 2n Schur complement gives
  their multipliers. ``rho_e |e|^2 / 2`` is added to the Hessian (it changes no solution
  of the KKT system) so that it is positive definite whenever the reduced Hessian is;
  otherwise the smallest of a few shifts that is (all factorised at once) is taken;
  after steps the line search cut short, a damping shift stays on the diagonal, as a
  trust region's (:data:`_DAMP_FLOOR`);
* a filter line search (IPOPT's, with its constants) over a few step lengths after the
  fraction-to-the-boundary rule: the full step first, the shorter ones (at once) only
  where it is rejected (:func:`_shorter_trials`).

A run ends as solved where the overall scaled error is within the tolerance, or where
its dual, primal and complementarity parts are each within their own (:class:`Tolerances`:
the solver stops at the barrier parameter ~2e-6 instead of going on to tol / 10; see
``SolverOptions.ip_dual_tol``). Where only the residuals are still above theirs (within
``Tolerances.project``), a closing step, unlike IPOPT, goes for feasibility at once
(:data:`_PROJECT_SHIFT`).

Everything is branch-free with fixed shapes: the loop is a bounded ``while_loop`` and a
problem's iterations end with a status, so it vmaps. No restoration phase: a problem the
method does not solve within ``ip_max_iter`` iterations, whose violation stops
shrinking (:data:`_STALL_WINDOW`), or whose Hessian no shift makes positive definite
(:data:`_DELTA_RANGE`), is handed to the AL solver's cold run by the caller
(:func:`jtraj.solver.solve`), except where it stalled far from feasible with the barrier
parameter never lowered: that run is reported likely infeasible.

:class:`InteriorPoint` is the method in the protocol of :mod:`jtraj.solver.loop`, whose
driver runs it.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .. import _kkt_native, lq
from .._math import small_matmul
from .nlp import Multipliers, violation

#: the line search's step lengths (fractions of the largest step the fraction-to-the-boundary
#: rule allows): the first alone, the others at once where it is rejected (_shorter_trials)
_ALPHAS = np.array([1.0, 0.5, 0.25, 0.1, 0.03, 0.01])
#: the share of a batch's lanes whose shorter step lengths are evaluated alone (see
#: _shorter_trials)
_TRIAL_SHARE = 0.25
_FILTER = 16  # filter entries kept (the oldest is overwritten)
#: the shifts tried at once, x the reference shift (which follows the one taken); the first is 0
_SHIFT_LADDER = np.array([0.0, 0.25, 2.0, 16.0])
#: the reference shift's range. A run whose ladder finds no positive definite shift with
#: the reference at the top is stuck (it would never move again) and stops as stalled: on
#: bench_solver's 256 pairs of seed 1, 25 of the 30 pairs IPOPT reports infeasible got
#: there (slacks near 1e-8 with multipliers near 1e10, so y / s near 1e18 in the Hessian,
#: whose factorisation then fails at every shift) from about iteration 12 and idled until
#: the stall test at iteration 40: 527 of 8,986 lane-iterations
_DELTA_RANGE = (1e-6, 1e8)
_TAU_MIN = 0.99  # fraction to the boundary
_KAPPA_EPS = 10.0  # mu falls when the barrier problem's error is below this x mu
_KAPPA_MU, _THETA_MU = 0.2, 1.5  # ... to max(tol / 10, min(_KAPPA_MU mu, mu^_THETA_MU)) (IPOPT's)
_RHO_E = 1e3  # the terminal equalities' term added to the Hessian (see the module doc)
#: a run stops as stalled when theta (the l1 violation) fell by less than 1 % over the last
#: window (checked every window from the second on). On bench_solver's 256 pairs of seed
#: 1 the 30 pairs IPOPT reports infeasible froze theta at 0.5..12 to two digits from
#: about iteration 20 on with mu still at its start (0.1); the feasible pairs kept
#: lowering it (one feasible pair froze at 0.087 with mu at 2e-6 and went to the AL loop)
_STALL_WINDOW = 20
_MU0 = 0.1
#: the default least distance of a start inside its boxes (``SolverOptions.ip_bound_push``)
_PUSH = 1e-2
#: the default reference shift a run starts with (``SolverOptions.ip_first_shift``; see
#: _SHIFT_LADDER). Runs from a plan of the online planner (``jtraj.online.WARM_IPM``),
#: whose Hessians need small shifts, take fewer iterations from 1e-2
_SHIFT0 = 1.0
_STALL_THETA = 1.0  # the stall test applies above this violation (or above _INFEASIBLE_THETA at mu0)
#: with the Gauss-Newton model (spatial arms, see :mod:`jtraj.solver.curvature`) the test
#: above _STALL_THETA is off, the one at mu0 kept: runs whose violation is above 1 and
#: falls by less than 1 % over a window still finish there. On 16 pairs of the panda
#: dataset's family (``jtraj dataset --robot panda``, N = 40) 7 stopped so at iteration
#: 40 (violation above 1, mu at its floor) and went to the AL loop (52 to 225 of its far
#: dearer iterations); without the test all 16 finish solved in 40 to 81 iterations
_STALL_THETA_GAUSS_NEWTON = np.inf
#: a stalled run with mu never lowered and theta above this is reported likely infeasible
_INFEASIBLE_THETA = 0.1
#: the closing step. Where the dual and complementarity errors are within their
#: tolerances and the residuals within ``Tolerances.project`` (but not the strict
#: ``primal``), the run is optimal to its tolerances but not yet feasible enough, and
#: the normal iterations often wandered on for many more along the nearly flat cost (the
#: barrier parameter falling, the reduced Hessian indefinite, the filter accepting
#: steps that raised the violation 100x for a cost 1e-4 lower). A closing step instead
#: keeps the barrier parameter, adds this shift to the Hessian's diagonal and takes the
#: largest step the fraction-to-the-boundary rule allows, without the filter (multipliers
#: as usual); the next iteration's test decides, at most _PROJECT_MAX per run, normal
#: iterations otherwise. Shifts tried (96 benchmark pairs of seed 1, Newton iterations
#: in all against 2,491 without; the same pairs solved): 0 2,291, 0.01 1,885, 0.1 1,699,
#: 0.3 1,784, 1 1,859; 1 and 100 with the multipliers kept: 2,138 and more (the dual
#: error rose 100x: they no longer match the moved point)
_PROJECT_SHIFT = 0.1
_PROJECT_MAX = 2
#: the damping shift. After a step the line search cut to at most _ALPHAS[_DAMP_CUT] of
#: its largest length, a shift of at least the floor (``Tolerances.damping``, from
#: ``SolverOptions.ip_damping``, default _DAMP_FLOOR; x _DAMP_UP after each further such
#: step) stays on the Hessian's diagonal, as a trust region's; a full step divides it by
#: _DAMP_DOWN, and below half the floor it is off. Late in a run on a flat cost
#: the reduced Hessian can be positive definite with a tiny eigenvalue: its Newton step
#: is long along that direction (|dz| about 1 in scaled units), the violation at the
#: full step rose 10x from the constraints' curvature, and the search took 3 % of it for
#: tens of iterations. With the floor 1e-2 the dataset family (serial3, h_max 0.2 s)
#: takes about 10 % fewer Newton iterations and the benchmark family 2.5 % fewer, with
#: none left unsolved; a second-order correction (IPOPT's) took more
_DAMP_FLOOR, _DAMP_UP, _DAMP_DOWN, _DAMP_CUT = 1e-2, 10.0, 10.0, 2


class Tolerances(NamedTuple):
    """When a run ends as solved: IPOPT's overall scaled optimality error at most
    ``overall`` (which also sets the barrier parameter's floor, ``overall / 10``), or each
    of its parts within its own tolerance: the scaled dual infeasibility within ``dual``,
    the largest constraint residual (normalised units) within ``primal``, the scaled
    complementarity within ``compl``. The defaults leave the second test off."""

    overall: float
    dual: float = 0.0
    primal: float = 0.0
    compl: float = 0.0
    project: float = 0.0  # see _PROJECT_SHIFT
    damping: float = _DAMP_FLOOR  # the damping shift's floor (see _DAMP_FLOOR; 0: off)


class IPState(NamedTuple):
    z: Array  # (nz,)
    s: Array  # (N+1, mi) slacks of the stage inequalities
    y: Array  # (N+1, mi) their multipliers
    sT: Array  # (1,) slack of the bound on T
    yT: Array  # (1,)
    lam: Array  # (2n,) multipliers of the goal equalities
    zl: Array  # (nz,) bound multipliers
    zu: Array  # (nz,)
    mu: Array
    filt: Array  # (_FILTER, 2): (theta, phi) pairs
    fi: Array  # next filter slot
    th_min: Array
    th_max: Array
    delta: Array  # reference shift (see _SHIFT_LADDER)
    th_ref: Array  # theta at the last stall checkpoint
    it: Array
    done: Array
    failed: Array
    stalled: Array  # the violation stopped shrinking (see _STALL_WINDOW)
    infeasible: Array  # ... at the first barrier parameter, far from feasible
    projections: Array  # closing steps taken (see _PROJECT_SHIFT)
    damping: Array  # the damping shift (see _DAMP_FLOOR)
    #: where done: the scaled dual infeasibility and complementarity (:func:`_errors`'
    #: larger one) of the iterate the convergence test certified; inf before
    certified: Array


def _flat(tree):
    """Stage-structured dict of (N+1, ...) arrays -> (N+1, total)."""
    leaves = jax.tree.leaves(tree)
    return jnp.concatenate([x.reshape(x.shape[0], -1) for x in leaves], axis=1)


def _unflat(flat, like):
    leaves, treedef = jax.tree.flatten(like)
    out, start = [], 0
    for x in leaves:
        size = int(np.prod(x.shape[1:]))
        out.append(flat[:, start:start + size].reshape(x.shape))
        start += size
    return jax.tree.unflatten(treedef, out)


class _Pieces(NamedTuple):
    G: Array  # (N+1, mi) stage inequalities
    gT: Array  # (1,)
    e: Array  # (2n,) goal equalities
    f: Array  # cost


def _parts(nlp, z):
    """(stage inequalities, T's, goal equalities, cost) at z, one pass through the dynamics."""
    zero = _zero_mult(nlp, z)
    _, ((eq, ineq, glob), cost) = nlp.al_and_parts(z, zero, jnp.asarray(1.0, z.dtype))
    N = nlp.layout.N
    return _Pieces(_flat(ineq), glob, eq["goal"][N], cost)


def _zero_mult(nlp, z):
    eq, ineq, glob = jax.eval_shape(nlp.constraints, z)
    zeros = lambda t: jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), t)  # noqa: E731
    return Multipliers(zeros(eq), zeros(ineq), zeros(glob))


def _bounds(nlp, z):
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi
    has_lo, has_hi = jnp.isfinite(lo), jnp.isfinite(hi)
    dl = jnp.where(has_lo, z - jnp.where(has_lo, lo, 0.0), 1.0)
    du = jnp.where(has_hi, jnp.where(has_hi, hi, 0.0) - z, 1.0)
    return dl, du, has_lo, has_hi


def _barrier_phi(nlp, z, s, sT, f, mu):
    dl, du, has_lo, has_hi = _bounds(nlp, z)
    logs = (jnp.sum(jnp.log(s)) + jnp.sum(jnp.log(sT)) + jnp.sum(jnp.where(has_lo, jnp.log(dl), 0.0))
            + jnp.sum(jnp.where(has_hi, jnp.log(du), 0.0)))
    return f - mu * logs


def _theta(p: _Pieces, s, sT):
    return jnp.sum(jnp.abs(p.e)) + jnp.sum(jnp.abs(p.G + s)) + jnp.sum(jnp.abs(p.gT + sT))


def init(nlp, z0, mu0=_MU0, push=_PUSH, shift0=_SHIFT0) -> IPState:
    """The state at z0 moved at least ``push`` inside its boxes (relative to
    ``max(1, |bound|)``, at most 0.49 of the box), slacks at least ``push``, the
    inequalities' multipliers ``mu0 / s`` and the bounds' 1 (IPOPT's constant rule), the
    reference shift ``shift0``."""
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi
    rng = jnp.where(jnp.isfinite(hi - lo), hi - lo, jnp.inf)
    push_lo = jnp.minimum(push * jnp.maximum(1.0, jnp.abs(lo)), 0.49 * rng)
    push_hi = jnp.minimum(push * jnp.maximum(1.0, jnp.abs(hi)), 0.49 * rng)
    z = jnp.clip(z0, jnp.where(jnp.isfinite(lo), lo + push_lo, -jnp.inf), jnp.where(jnp.isfinite(hi), hi - push_hi, jnp.inf))
    p = _parts(nlp, z)
    dt = z.dtype
    mu = jnp.asarray(mu0, dt)
    s = jnp.maximum(-p.G, push)
    sT = jnp.maximum(-p.gT, push)
    th0 = _theta(p, s, sT)
    _, _, has_lo, has_hi = _bounds(nlp, z)
    return IPState(
        z=z, s=s, y=mu / s, sT=sT, yT=mu / sT, lam=jnp.zeros_like(p.e),
        zl=jnp.where(has_lo, 1.0, 0.0).astype(dt), zu=jnp.where(has_hi, 1.0, 0.0).astype(dt), mu=mu,
        filt=jnp.full((_FILTER, 2), jnp.inf, dt), fi=jnp.asarray(0),
        th_min=1e-4 * jnp.maximum(1.0, th0), th_max=1e4 * jnp.maximum(1.0, th0),
        delta=jnp.asarray(shift0, dt), th_ref=jnp.asarray(jnp.inf, dt), it=jnp.asarray(0), done=jnp.asarray(False),
        failed=jnp.asarray(False), stalled=jnp.asarray(False), infeasible=jnp.asarray(False),
        projections=jnp.asarray(0), damping=jnp.asarray(0.0, dt), certified=jnp.asarray(jnp.inf, dt))


def z_to_stages(v, N, n):
    """A vector in z's layout (all v, then all h) -> (N, n+1) stage controls."""
    return jnp.concatenate([v[:N * n].reshape(N, n), v[N * n:, None]], axis=1)


def multipliers(nlp, st: IPState):
    """The state's multipliers in the AL solver's structure (``jtraj.solver.Multipliers``:
    the goal rows' at the last sample, the stage inequalities', T's), with the same sign
    convention (the Lagrangian ``f + lam . e + y . g``)."""
    eq_like, ineq_like, _ = jax.eval_shape(nlp.constraints, st.z)
    lam_full = jnp.zeros(eq_like["goal"].shape, st.z.dtype).at[nlp.layout.N].set(st.lam)
    return Multipliers(eq={"goal": lam_full}, ineq=_unflat(st.y, ineq_like), glob=st.yT)


def snap_to_bounds(nlp, st: IPState) -> Array:
    """z with the variables whose bound is active moved onto it. The method keeps z
    strictly inside its boxes (``(z - lo) zl`` near mu, about 1e-8 at the end); a bound
    counts as active where its multiplier exceeds the distance to it (``zl^2 > mu``
    there). The AL solver's projections leave such variables exactly on the bound, and
    its certificate (least-squares multipliers over the free variables) and warm start
    read them so: unsnapped, the least-squares KKT error of a test problem's optimum
    was 0.016 instead of 4e-5 and a warm start from it took 5 iterations instead of 0."""
    dl, du, has_lo, has_hi = _bounds(nlp, st.z)
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi
    z = jnp.where(has_lo & (st.zl > dl), lo, st.z)
    return jnp.where(has_hi & (st.zu > du), hi, z)


def _model(nlp, st: IPState):
    """The primal-dual Newton model at st without its barrier right-hand side (see
    :func:`_with_rhs`; ``model.g`` is the Lagrangian's gradient in z): (model, stage
    Jacobians of the inequalities, dg_T/dT, pieces, goal Jacobian in the terminal state)."""
    layout, problem, tr = nlp.layout, nlp.problem, nlp.tr
    N, n = layout.N, problem.robot.n
    z = st.z
    W = nlp.W(z)
    lag = dataclasses.replace(nlp, ineq_penalty="lagrangian")
    # the inequalities' Jacobians by the chain rule through the efforts, whose values and
    # Jacobians the stage derivatives computed (the inverse dynamics' derivatives once per
    # iteration instead of twice; the decoupled transcription's derivatives are split)
    val, c, Hk, tau, Jtau = lag.stage_derivatives(W, multipliers(nlp, st), jnp.asarray(0.0, z.dtype), efforts=True)

    def stage_ineq(w, t, sdk):
        a = tr.split_stage(problem, w)[2]
        return _flat(jax.tree.map(lambda x: x[None], tr.stage_constraints(problem, w, sdk, (a, t))[1]))[0]

    def value_and_jac(w, t, sdk, J):
        (Jw, Jt), g = jax.jacfwd(lambda w_, t_: (stage_ineq(w_, t_, sdk),) * 2, argnums=(0, 1), has_aux=True)(w, t)
        return g, Jw + (small_matmul(Jt, J) if Jt.size * J.shape[-1] <= _GRAM_ELEMENTWISE_MAX else Jt @ J)

    G, Jg = jax.vmap(value_and_jac)(W, tau, nlp.sd, Jtau)
    Sig = st.y / st.s
    Hk = Hk + _gram(Jg, Sig)  # J^T Sig J per stage
    T = jnp.sum(W[:-1, -1])
    gT_of = lambda t: tr.time_inequalities(problem, t)  # noqa: E731
    gT = gT_of(T)
    dgT = jax.jacfwd(gT_of)(T)
    SigT = st.yT / st.sT
    dphi = jnp.sum(st.yT * dgT)
    d2phi = jnp.sum(SigT * dgT**2)
    model = lq.stage_model(W, c, Hk, layout.u_scale, layout.h_scale, (dphi, d2phi))
    dl, du, has_lo, has_hi = _bounds(nlp, z)
    bound_h = jnp.where(has_lo, st.zl / dl, 0.0) + jnp.where(has_hi, st.zu / du, 0.0)
    model = model._replace(R=model.R + jax.vmap(jnp.diag)(z_to_stages(bound_h, N, n)))
    goal = lambda x: tr.stage_constraints(problem, jnp.concatenate([x, W[N, 2 * n:]]), jax.tree.map(  # noqa: E731
        lambda a: a[N], nlp.sd))[0]["goal"]
    Ex = jax.jacfwd(goal)(W[N, :2 * n])  # (2n, 2n)
    Ex = jnp.concatenate([Ex, jnp.zeros((Ex.shape[0], 1), z.dtype)], axis=1)  # the t column
    e = goal(W[N, :2 * n])
    # rho_e E^T E on the terminal state, and its gradient rho_e E^T e (the goal rows are
    # linear in x_N): the exact Newton step of the KKT system is unchanged
    model = model._replace(PN=model.PN + _RHO_E * Ex.T @ Ex, cx=model.cx.at[N].add(_RHO_E * Ex.T @ e))
    # the cost: the stage terms' Lagrangian values less their constraint terms
    f = jnp.sum(val) - jnp.sum(st.y * G) - jnp.sum(st.lam * e)
    return model, Jg, dgT, _Pieces(G, gT, e, f), Ex


#: per-stage products with the inequality Jacobians Jg (N+1, mi, nw) are formed
#: elementwise (:func:`jtraj._math.small_matmul`, fused with their neighbours) up to this
#: many (mi nw^2: serial3's 18 x 10 blocks), as batched dots above (XLA's elementwise loops
#: run far slower than its dot kernel there: the panda's 42 x 22 blocks over 41 stages,
#: J^T Sig J in 0.4 instead of 2.6 ms)
_GRAM_ELEMENTWISE_MAX = 4096


def _gram(Jg, Sig):
    """``J_k^T diag(Sig_k) J_k`` per stage (see :data:`_GRAM_ELEMENTWISE_MAX`)."""
    A = jnp.swapaxes(Sig[..., None] * Jg, -1, -2)
    return small_matmul(A, Jg) if Jg.shape[-2] * Jg.shape[-1] ** 2 <= _GRAM_ELEMENTWISE_MAX else A @ Jg


def _rows_times(Jg, r):
    """``r_k^T J_k`` per stage (N+1, nw); :func:`_times_columns`: ``J_k x_k`` (N+1, mi)."""
    if Jg.shape[-2] * Jg.shape[-1] ** 2 <= _GRAM_ELEMENTWISE_MAX:
        return jnp.sum(Jg * r[..., None], axis=1)
    return (r[:, None, :] @ Jg)[:, 0]


def _times_columns(Jg, x):
    if Jg.shape[-2] * Jg.shape[-1] ** 2 <= _GRAM_ELEMENTWISE_MAX:
        return jnp.sum(Jg * x[:, None, :], axis=-1)
    return (Jg @ x[..., None])[..., 0]


def _with_rhs(nlp, st: IPState, model, Jg, dgT, p: _Pieces, mu):
    """The model's linear terms for barrier parameter mu: the correction
    J^T (mu / s + Sigma (g + s) - y) and the bounds' barrier gradient enter the gradients
    only (the co-states of the curvature are the Lagrangian's, ``model.g``)."""
    layout = nlp.layout
    N, n = layout.N, nlp.problem.robot.n
    corr = _rows_times(Jg, mu / st.s + (st.y / st.s) * (p.G + st.s) - st.y)
    corrT = jnp.sum((mu / st.sT + (st.yT / st.sT) * (p.gT + st.sT) - st.yT) * dgT)
    sy = jnp.concatenate([layout.u_scale, layout.h_scale[None]])
    dl, du, has_lo, has_hi = _bounds(nlp, st.z)
    bound_g = jnp.where(has_lo, -mu / dl, 0.0) + jnp.where(has_hi, mu / du, 0.0)
    cx = model.cx.at[:, :2 * n].add(corr[:, :2 * n]).at[N, -1].add(corrT)
    cu = model.cu + corr[:N, 2 * n:] * sy[None, :] + z_to_stages(bound_g, N, n)
    return model._replace(cx=cx, cu=cu)


class _Direction(NamedTuple):
    dz: Array
    dlam: Array
    ds: Array
    dsT: Array
    dy: Array
    dyT: Array
    dzl: Array
    dzu: Array
    #: the slope along dz of the constraint terms of the Lagrangian,
    #: ``y . dG + yT dg_T + lam . de`` (see :func:`step`'s cost slope)
    dcon: Array


def _direction(nlp, st: IPState, p: _Pieces, Jg, dgT, Ex, d, dX, mu, any_pd) -> _Direction:
    """The full primal-dual step from the KKT solve's columns d (nz, 1 + 2n) and their
    state trajectories dX (N+1, nx, 1 + 2n): the goal multipliers' step from the Schur
    complement (E dz = -e), then the slacks' and multipliers' for barrier parameter mu."""
    layout = nlp.layout
    N, n = layout.N, nlp.problem.robot.n
    dt = st.z.dtype
    ED = small_matmul(Ex, dX[N])  # (2n, 1 + 2n)
    dlam = -jnp.linalg.solve(jnp.where(any_pd, ED[:, 1:], -jnp.eye(ED.shape[0], dtype=dt)), p.e + ED[:, 0])
    # (the small products as elementwise sums: fewer, fused kernels than XLA's dots)
    dz = d[:, 0] + jnp.sum(d[:, 1:] * dlam[None, :], axis=-1)
    dXz = dX[..., 0] + jnp.sum(dX[..., 1:] * dlam[None, None, :], axis=-1)  # (N+1, nx)
    sy = jnp.concatenate([layout.u_scale, layout.h_scale[None]])
    du_st = z_to_stages(dz, N, n) * sy[None, :]
    dW = jnp.concatenate([dXz[:, :2 * n], jnp.concatenate([du_st, jnp.zeros((1, n + 1), dt)])], axis=1)
    Jdz = _times_columns(Jg, dW)
    dT = jnp.sum(du_st[:, -1])
    ds = -(p.G + st.s) - Jdz
    dsT = -(p.gT + st.sT) - dgT * dT
    dy = mu / st.s - st.y - (st.y / st.s) * ds
    dyT = mu / st.sT - st.yT - (st.yT / st.sT) * dsT
    dl, du, has_lo, has_hi = _bounds(nlp, st.z)
    dzl = jnp.where(has_lo, mu / dl - st.zl - (st.zl / dl) * dz, 0.0)
    dzu = jnp.where(has_hi, mu / du - st.zu + (st.zu / du) * dz, 0.0)
    dcon = jnp.sum(st.y * Jdz) + jnp.sum(st.yT * dgT) * dT + jnp.sum(st.lam * jnp.sum(Ex * dXz[N][None, :], axis=-1))
    return _Direction(dz, dlam, ds, dsT, dy, dyT, dzl, dzu, dcon)


def _errors(nlp, st: IPState, g_lag, p: _Pieces, mu, parts=False):
    """IPOPT's scaled optimality error of the barrier problem with parameter mu
    (``parts``: its dual, primal and complementarity parts apart)."""
    rd = g_lag - st.zl + st.zu
    nd = st.y.size + st.yT.size + st.lam.size + 2 * st.z.size
    s_d = jnp.maximum(100.0, (jnp.sum(jnp.abs(st.lam)) + jnp.sum(st.y) + jnp.sum(st.yT) + jnp.sum(st.zl)
                              + jnp.sum(st.zu)) / nd) / 100.0
    prim = jnp.maximum(jnp.max(jnp.abs(p.e)), jnp.maximum(jnp.max(jnp.abs(p.G + st.s)), jnp.max(jnp.abs(p.gT + st.sT))))
    dl, du, has_lo, has_hi = _bounds(nlp, st.z)
    comp = jnp.maximum(jnp.max(jnp.abs(st.s * st.y - mu)), jnp.max(jnp.abs(st.sT * st.yT - mu)))
    comp = jnp.maximum(comp, jnp.max(jnp.where(has_lo, jnp.abs(dl * st.zl - mu), 0.0)))
    comp = jnp.maximum(comp, jnp.max(jnp.where(has_hi, jnp.abs(du * st.zu - mu), 0.0)))
    if parts:
        # the parts' test stands in for the verification, which reads the goal velocity
        # unscaled: its rows (divided by qd_max) count max(1, qd_max / 2) times, so that
        # ``primal = verify_tol / 2`` keeps |qd_N - qd_goal| within verify_tol whatever
        # qd_max (a panda joint's 2.61 rad/s let 1.005e-6 through); 1 up to 2 rad/s
        qd_max = nlp.problem.robot.limits.qd_max
        if qd_max is not None:
            n = p.e.shape[0] // 2
            factor = jnp.concatenate([jnp.ones(n, p.e.dtype), jnp.maximum(1.0, jnp.broadcast_to(qd_max, (n,)) / 2)])
            prim = jnp.maximum(prim, jnp.max(jnp.abs(p.e) * factor))
        return jnp.max(jnp.abs(rd)) / s_d, prim, comp / s_d
    return jnp.maximum(jnp.maximum(jnp.max(jnp.abs(rd)) / s_d, prim), comp / s_d)


def _ladder_directions(model, shifts, terminal):
    """:func:`jtraj.lq.kkt_directions` for the shift ladder, of which the caller takes the
    least shifted positive definite one: by the native kernel where it is available
    (:mod:`jtraj._kkt_native` in its ladder mode, the shifted systems only where the
    unshifted one is not positive definite; one call for a batch), else by XLA
    (:func:`_ladder_directions_xla`): the same choice, the same numbers up to rounding."""
    if _kkt_native.active(model.B.dtype, model.B.shape[-1] - 1, terminal.shape[-1]):
        return _kkt_native.kkt_directions(model, shifts, terminal, ladder=True)
    return _ladder_directions_xla(model, shifts, terminal)


@jax.custom_batching.custom_vmap
def _ladder_directions_xla(model, shifts, terminal):
    """:func:`jtraj.lq.kkt_directions` for the shift ladder in XLA. For one problem the
    unshifted factorisation comes first and the shifted ones only where it fails (a ``lax.cond``; their slots are
    zeros and not positive definite otherwise): the same choice and the same numbers.
    Under vmap a ``cond`` would run both branches, so there all shifts are factorised at
    once (:func:`_ladder_directions_vmap`). Shift 0 is positive definite in about half
    of the iterations; 8 single solves of seed 1, interleaved in one process, best of
    15: 72.5 instead of 76.8 ms in all."""
    first = lq.kkt_directions(model, shifts[:1], terminal)

    def alone(_):
        d, dX, ok = first
        pad = shifts.shape[0] - 1
        return (jnp.concatenate([d, jnp.zeros(d.shape[:-1] + (pad,), d.dtype)], -1),
                jnp.concatenate([dX, jnp.zeros(dX.shape[:-1] + (pad,), dX.dtype)], -1),
                jnp.concatenate([ok, jnp.zeros((pad,), bool)]))

    def ladder(_):
        rest = lq.kkt_directions(model, shifts[1:], terminal)
        return tuple(jnp.concatenate([a, b], -1) for a, b in zip(first, rest))

    return jax.lax.cond(first[2][0], alone, ladder, None)


@_ladder_directions_xla.def_vmap
def _ladder_directions_vmap(axis_size, in_batched, model, shifts, terminal):
    axes = jax.tree.map(lambda b: 0 if b else None, tuple(in_batched))
    out = jax.vmap(lq.kkt_directions, in_axes=axes, axis_size=axis_size)(model, shifts, terminal)
    return out, (True, True, True)


def _trial(nlp, point, a):
    """(theta, barrier phi) at step length a along the direction; ``point``: (z, s, sT,
    dz, ds, dsT, mu)."""
    z, s, sT, dz, ds, dsT, mu = point
    zt, st_, sTt = z + a * dz, s + a * ds, sT + a * dsT
    pt = _parts(nlp, zt)
    return _theta(pt, st_, sTt), _barrier_phi(nlp, zt, st_, sTt, pt.f, mu)


def _shorter_trials(nlp, point, alphas, need):
    """:func:`_trial` at each of ``alphas`` where ``need`` (the full step was rejected),
    else inf (not evaluated). For one problem a ``lax.cond``. Under vmap (a batch's lanes,
    where a ``cond`` would run both sides) the lanes that need them are gathered, up to a
    quarter of the lanes (:data:`_TRIAL_SHARE`), and evaluated alone; all lanes are
    evaluated where more need them, none where none does. About 4 lane-iterations in 5
    take the full step: 128 pairs of each family, 16 lanes, 84 % (benchmark) and 78 %
    (dataset) of 2,271 and 3,471 lane-iterations."""
    dyn, static = eqx.partition(nlp, eqx.is_array)

    def evaluate(dyn, point, alphas):
        nl = eqx.combine(dyn, static)
        return jax.vmap(lambda a: _trial(nl, point, a))(alphas)

    def skipped(shape, dtype):
        inf = jnp.full(shape, jnp.inf, dtype)
        return inf, inf

    @jax.custom_batching.custom_vmap
    def trials(dyn, point, alphas, need):
        return jax.lax.cond(need, lambda: evaluate(dyn, point, alphas), lambda: skipped(alphas.shape, alphas.dtype))

    @trials.def_vmap
    def trials_batched(lanes, in_batched, dyn, point, alphas, need):
        args, batched = (dyn, point, alphas), tuple(in_batched[:3])
        axes = jax.tree.map(lambda b: 0 if b else None, batched)
        need = jnp.broadcast_to(need, (lanes,))
        shape, dtype = (lanes, alphas.shape[-1]), alphas.dtype
        share = max(1, int(lanes * _TRIAL_SHARE))
        idx = jnp.argsort(~need, stable=True)[:share]  # the lanes that need them first

        def masked(th, ph, keep):
            return jnp.where(keep[:, None], th, jnp.inf), jnp.where(keep[:, None], ph, jnp.inf)

        def some():
            sub = jax.tree.map(lambda x, b: x[idx] if b else x, args, batched)
            th, ph = masked(*jax.vmap(evaluate, in_axes=axes)(*sub), need[idx])
            inf = jnp.full(shape, jnp.inf, dtype)
            return inf.at[idx].set(th), inf.at[idx].set(ph)

        def every():
            return masked(*jax.vmap(evaluate, in_axes=axes)(*args), need)

        count = jnp.sum(need)
        which = jnp.where(count == 0, 0, jnp.where(count <= share, 1, 2))
        return jax.lax.switch(which, [lambda: skipped(shape, dtype), some, every]), (True, True)

    return trials(dyn, point, alphas, need)


def step(nlp, st: IPState, tol) -> IPState:
    """One interior-point iteration (or, where converged, the state marked done).
    ``tol``: :class:`Tolerances`, or a number (the overall tolerance alone)."""
    dt = st.z.dtype
    model, Jg, dgT, p, Ex = _model(nlp, st)
    g_lag = model.g
    tols = tol if isinstance(tol, Tolerances) else Tolerances(tol)
    tol = tols.overall
    e_d, e_p, e_c = _errors(nlp, st, g_lag, p, 0.0, parts=True)  # g_lag: the Lagrangian's gradient
    converged = (jnp.maximum(jnp.maximum(e_d, e_p), e_c) <= tol) | (
        (e_d <= tols.dual) & (e_p <= tols.primal) & (e_c <= tols.compl))
    project = ((e_d <= tols.dual) & (e_p <= tols.project) & (e_c <= tols.compl) & ~converged
               & (st.projections < _PROJECT_MAX))
    # barrier update (up to two decreases per iteration), the filter reset with it
    mu, reset = st.mu, jnp.asarray(False)
    for _ in range(2):
        fall = (_errors(nlp, st, g_lag, p, mu) <= _KAPPA_EPS * mu) & (mu > tol / 10)
        mu = jnp.where(fall, jnp.maximum(tol / 10, jnp.minimum(_KAPPA_MU * mu, mu**_THETA_MU)), mu)
        reset = reset | fall
    mu, reset = jnp.where(project, st.mu, mu), reset & ~project
    model = _with_rhs(nlp, st, model, Jg, dgT, p, mu)
    filt = jnp.where(reset, jnp.inf, st.filt)
    fi = jnp.where(reset, 0, st.fi)
    # Newton directions for a few shifts (at once in a batch); the least shifted positive
    # definite one
    shifts = st.delta * jnp.asarray(_SHIFT_LADDER, dt) + jnp.where(project, _PROJECT_SHIFT, st.damping)
    d, dX, ok = _ladder_directions(model, shifts, Ex.T)
    k = jnp.argmax(ok)
    any_pd = jnp.any(ok)
    # the next reference shift: the one taken (kept after an unshifted step), x 128 after none
    delta = jnp.clip(jnp.where(any_pd, jnp.where(k == 0, st.delta, shifts[k]), 128.0 * st.delta), *_DELTA_RANGE)
    delta = jnp.where(project & any_pd, st.delta, delta)
    stuck = ~any_pd & (st.delta >= _DELTA_RANGE[1])
    d, dX = jnp.where(any_pd, d[..., k], 0.0), jnp.where(any_pd, dX[..., k], 0.0)  # (nz, 1 + 2n), (N+1, nx, 1 + 2n)
    dz, dlam, ds, dsT, dy, dyT, dzl, dzu, dcon = _direction(nlp, st, p, Jg, dgT, Ex, d, dX, mu, any_pd)
    dl, du, has_lo, has_hi = _bounds(nlp, st.z)
    tau = jnp.maximum(_TAU_MIN, 1.0 - mu)

    def amax(x, dx, mask=True):
        neg = (dx < 0) & mask
        return jnp.min(jnp.where(neg, -tau * x / jnp.where(neg, dx, -1.0), 1.0), initial=1.0)

    ap = jnp.minimum(jnp.minimum(amax(st.s, ds), amax(st.sT, dsT)),
                     jnp.minimum(amax(dl, dz, has_lo), amax(du, -dz, has_hi)))
    ad = jnp.minimum(jnp.minimum(amax(st.y, dy), amax(st.yT, dyT)),
                     jnp.minimum(amax(st.zl, dzl, has_lo), amax(st.zu, dzu, has_hi)))
    # filter line search over a few step lengths at once
    # the cost's slope along dz from the Lagrangian's gradient less its constraint terms'
    # (all computed already) instead of a pass through the dynamics with tangents
    df = jnp.sum(g_lag * dz) - dcon
    th0 = _theta(p, st.s, st.sT)
    ph0 = _barrier_phi(nlp, st.z, st.s, st.sT, p.f, mu)
    dlog = (jnp.sum(ds / st.s) + jnp.sum(dsT / st.sT) + jnp.sum(jnp.where(has_lo, dz / dl, 0.0))
            - jnp.sum(jnp.where(has_hi, dz / du, 0.0)))
    gphi = df - mu * dlog
    alphas = ap * jnp.asarray(_ALPHAS, dt)

    def acceptance(alphas, ths, phs):
        finite = jnp.isfinite(ths) & jnp.isfinite(phs)
        m = alphas * gphi
        switch = (m < 0) & ((-m) ** 2.3 * alphas ** (1 - 2.3) > th0 ** 1.1)
        armijo = phs <= ph0 + 1e-8 * m
        f_type = (th0 <= st.th_min) & switch
        suff = (ths <= (1 - 1e-5) * th0) | (phs <= ph0 - 1e-8 * th0)
        blocked = jnp.any((ths[:, None] >= filt[None, :, 0]) & (phs[:, None] >= filt[None, :, 1]), axis=1)
        accept = finite & (ths <= st.th_max) & ~blocked & jnp.where(f_type, armijo, suff) & any_pd
        return accept, finite, armijo, f_type

    # the full step first; the shorter ones only where it is rejected (the first accepted
    # step is taken, so this is the choice of trying all at once)
    point = (st.z, st.s, st.sT, dz, ds, dsT, mu)
    th1, ph1 = _trial(nlp, point, alphas[0])
    first_ok = acceptance(alphas[:1], th1[None], ph1[None])[0][0]
    stop = converged | st.done | st.failed | st.stalled  # (its step is discarded)
    thr, phr = _shorter_trials(nlp, point, alphas[1:], ~first_ok & any_pd & ~stop)
    ths, phs = jnp.concatenate([th1[None], thr]), jnp.concatenate([ph1[None], phr])
    accept, finite, armijo, f_type = acceptance(alphas, ths, phs)
    j = jnp.argmax(accept)
    leap = project & any_pd & finite[0]  # the closing step (alphas[0] is ap)
    moved = jnp.where(project, leap, jnp.any(accept))
    a = jnp.where(project, jnp.where(leap, ap, 0.0), jnp.where(moved, alphas[j], 0.0))
    add = moved & ~(f_type[j] & armijo[j]) & ~project
    filt = jnp.where(add, filt.at[fi].set(jnp.stack([(1 - 1e-5) * th0, ph0 - 1e-8 * th0])), filt)
    fi = jnp.where(add, (fi + 1) % _FILTER, fi)
    ad = jnp.where(moved, ad, 0.0)
    # the damping shift (_DAMP_FLOOR): up after a short step, down after a full one
    cut_short, full = moved & ~project & (j >= _DAMP_CUT), moved & (j == 0)
    damping = jnp.where(cut_short, jnp.maximum(_DAMP_UP * st.damping, tols.damping),
                        jnp.where(full, st.damping / _DAMP_DOWN, st.damping))
    damping = jnp.where(damping < tols.damping / 2, 0.0, jnp.minimum(damping, _DELTA_RANGE[1]))
    z1, s1, sT1 = st.z + a * dz, st.s + a * ds, st.sT + a * dsT
    # IPOPT's safeguard keeps each bound multiplier within a factor 1e10 of mu / slack
    k_sig = 1e10

    def guard(v, slack):
        return jnp.clip(v, mu / (k_sig * slack), k_sig * mu / slack)

    dl1, du1, _, _ = _bounds(nlp, z1)
    new = IPState(
        z=z1, s=s1, y=guard(st.y + ad * dy, s1), sT=sT1, yT=guard(st.yT + ad * dyT, sT1),
        lam=st.lam + a * dlam, zl=jnp.where(has_lo, guard(st.zl + ad * dzl, dl1), 0.0),
        zu=jnp.where(has_hi, guard(st.zu + ad * dzu, du1), 0.0), mu=mu, filt=filt, fi=fi,
        th_min=st.th_min, th_max=st.th_max, delta=delta, th_ref=st.th_ref,
        it=st.it + 1, done=st.done, failed=st.failed, stalled=st.stalled, infeasible=st.infeasible,
        projections=st.projections + project, damping=damping, certified=st.certified)
    failed = ~(jnp.all(jnp.isfinite(new.z)) & jnp.all(jnp.isfinite(new.y)) & jnp.all(jnp.isfinite(new.lam)))
    new = new._replace(failed=failed)
    checkpoint = (st.it % _STALL_WINDOW == 0) & (st.it > 0)
    stall_theta = _STALL_THETA_GAUSS_NEWTON if nlp.ip_curvature == "gauss_newton" else _STALL_THETA
    far = (th0 > stall_theta) | ((st.mu >= _MU0) & (th0 > _INFEASIBLE_THETA))
    stalled = (stuck | (checkpoint & (st.it >= 2 * _STALL_WINDOW) & (th0 > 0.99 * st.th_ref) & far)) & ~converged
    new = new._replace(th_ref=jnp.where(checkpoint, th0, st.th_ref), stalled=stalled,
                       infeasible=stalled & (st.mu >= _MU0) & (th0 > _INFEASIBLE_THETA))
    certified = jnp.where(converged & ~st.done, jnp.maximum(e_d, e_c), st.certified)
    return jax.tree.map(lambda old, nw: jnp.where(stop, old, nw),
                        st._replace(done=st.done | converged, certified=certified), new)


def finished(st: IPState, max_iter) -> Array:
    return st.done | st.failed | st.stalled | (st.it >= max_iter)


class InteriorPoint(NamedTuple):
    """The interior-point method in the protocol of :mod:`jtraj.solver.loop`: at most
    ``max_iter`` iterations (a traced count) of :func:`step` with the tolerances
    ``tol`` (:class:`Tolerances`, or a number: the overall tolerance alone)."""

    #: (None where only :meth:`init` or :meth:`postprocess` is called, which read no option)
    max_iter: Any = None
    tol: Any = None

    def init(self, nlp, z0, mu0=_MU0, push=_PUSH, shift0=_SHIFT0) -> IPState:
        """:func:`init`: the state at z0 (pushed at least ``push`` inside its boxes), first
        barrier parameter ``mu0``, first reference shift ``shift0``."""
        return init(nlp, z0, mu0, push, shift0)

    def enter(self, nlp, st: IPState):
        return nlp

    def step(self, nlp, st: IPState) -> IPState:
        """:func:`step`."""
        return step(nlp, st, self.tol)

    def terminate(self, nlp, st: IPState) -> Array:
        """:func:`finished`."""
        return finished(st, self.max_iter)

    def postprocess(self, nlp, st: IPState, start):
        """The AL state ``start`` (the solve's starting state) holding the result of a run
        the method decided (certified, or stalled: see :func:`decided`): its point with
        its active bounds snapped on (:func:`snap_to_bounds`, unless that costs
        feasibility) and its multipliers; ``jtraj.solver.core.finish(..., light=True)``
        verifies it and reports their KKT error."""
        solved = st.done & ~st.failed
        snapped = snap_to_bounds(nlp, st)
        keep = violation(*nlp.constraints(snapped)) <= jnp.maximum(1e-7, violation(*nlp.constraints(st.z)))
        return start._replace(z=jnp.where(keep, snapped, st.z), mult=multipliers(nlp, st), done=solved,
                              stalled=~solved, it=st.it,
                              stationarity=jnp.where(solved, st.certified, jnp.inf).astype(start.stationarity.dtype))


def decided(start, st: IPState) -> Array:
    """Where the method decided a problem that started from the AL state ``start``
    (solved, or stalled as likely infeasible); elsewhere the AL loop takes over."""
    return ~start.done & ((st.done & ~st.failed) | st.infeasible)
