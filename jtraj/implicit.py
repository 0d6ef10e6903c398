"""Derivatives through the solve: implicit differentiation of the KKT conditions.

``jax.grad``, ``jax.vjp``, ``jax.jvp``, ``jax.jacfwd``/``jacrev``, ``jax.vmap`` and
``jax.jit`` work through :func:`jtraj.solve` and :func:`jtraj.solve_batch`: when a
problem's array leaves (start, goal, boundary velocities, via points, ``T_max``, the
weights, the robot's parameters and limits) are traced, the solve goes through a
``jax.custom_jvp`` rule. Its primal is the ordinary solver (never differentiated: the
native KKT kernel and the loops are not traced for derivatives); its tangent is the
derivative of the optimum by the implicit function theorem. Reverse mode follows by
transposition: the tangent is linear in the input tangents and built from transposable
operations only (forward-mode derivatives of the problem's functions and a linear
solve whose operator is computed from primal values).

Mathematics. At the returned optimum ``z*`` (the scaled controls and periods,
:class:`jtraj.transcription.Layout`) the NLP ``min f(z, theta)`` s.t. ``c_E(z, theta) = 0``,
``c_I(z, theta) <= 0``, ``lo(theta) <= z <= hi(theta)`` satisfies the KKT conditions with
multipliers ``lambda``. Its active set is fixed at ``z*``:

* every equality row that is not identically zero (the goal, path equalities);
* every inequality with ``c_i > -ACT_TOL`` whose least-squares multiplier exceeds a
  threshold: ``WEAK * max(1, max lambda)``, or less at an accurate optimum (``NOISE``
  times the stationarity error of the least-squares fit, which bounds the multipliers'
  own error; at least ``WEAK_MIN * max(1, max lambda)``);
* every simple bound ``z*`` touches (within ``BOUND_TOL``) whose bound multiplier (the
  Lagrangian's gradient there) has the right sign and exceeds the same threshold.

The multipliers are the least-squares ones at ``z*`` over the equalities and the nearly
active inequalities, in the free variables (the estimate of the solver's certificate,
:func:`jtraj.solver.certify.ls_multipliers`, recomputed on the variables that stay free): at a
KKT point that satisfies LICQ they are the unique multipliers, so no state of the
solver's run is needed and the primal solve is the unchanged solver (single solves and
the host-driven batch driver alike). With the active set ``A`` and the free variables
``f`` fixed, the optimum is the root of

    F(z, l, theta) = [ grad_z L(z, l, theta)_f ;  z_b - bound_b(theta) ;  c_A(z, theta) ]

with ``L = f + l . c_A``, and ``K = dF/d(z, l)`` (the KKT matrix of an equality
constrained QP, bordered by the bound-fixed variables) gives the tangent
``(dz, dl) = -K^{-1} (dF/dtheta . dtheta)``. Every output (q, qd, v, tau, h, T, cost,
cost_terms, energy) is a function of ``(z*, theta)``: its tangent is the forward-mode
derivative of that map along ``(dz, dtheta)``.

The active rows are compressed into ``r = min(rows, nz)`` slots (at most nz constraints
can be active with linearly independent gradients; more make the point degenerate and
the derivative invalid). The linear system is solved in one of two ways
(:data:`KKT_SOLVE`):

* ``"stagewise"``, the decoupled transcription's: the symmetric form of K (the
  bound-held variables' columns moved to the right-hand side) is an equality-constrained
  linear-quadratic problem over the stages, solved in O(N) by the Riccati recursion of
  the Newton steps inside an iteration on the multipliers (:mod:`jtraj.adjoint`),
  wrapped in ``jax.lax.custom_linear_solve`` so that reverse mode transposes it into the
  same solve; no (nz + r)-square matrix is formed. It is valid where every stage
  factorisation is positive definite and it reproduces a probe solution to
  :data:`PROBE_TOL`;
* ``"dense"``, every other transcription's and the reference the tests compare with: K
  formed by forward-mode derivatives, (nz + r) square, and factorised by LU (160 x 160
  for serial3 at N = 20); valid where the factorisation is regular.

The active set and the least-squares multipliers themselves (:func:`active_set`) are
computed densely in both cases (a Jacobian of all rows in z and an nz-square solve).

Weakly active constraints (on their boundary with a multiplier at or below the
threshold) are treated as inactive: the result is the derivative of the strictly active
set, the one-sided derivative in the directions that keep such a constraint satisfied.
At a point where the active set changes the derivative is one-sided in this sense.

Refinement. The active set is read off the returned point: at the interior-point
method's default tolerances a constraint with a small multiplier lies about
``mu / multiplier`` inside its bound and can be missed (more than ``ACT_TOL`` inside);
the reduced Hessian of the remaining set is then indefinite and the derivative there not
valid. Where a converged solve's derivative is not valid, the rule refines the optimum
(:func:`refine`, warm-started at the returned point, bounded work: where the
interior-point method applies, its iterations with a barrier parameter of 1e-8,
:data:`REFINE_IP`, which stay at the returned point's optimum, then the AL method at
tolerances 1e-10, :data:`REFINE`, from their point) and differentiates at the refined
point, the same optimum to the refinement's tolerance. With concrete primal values (a
derivative outside ``jit``) the check is read on the host and the refinement is one
compiled program run per flagged sample; inside ``jit`` or ``vmap`` it is a
``lax.cond`` on the traced flag (under ``vmap`` both
sides run, the lanes that need no refinement starting finished). The primal outputs stay
those of the returned solve. Where the stage-wise solve still fails its self-check at a
converged point (its iteration on the multipliers not converging in ``MAX_ITER`` steps),
the derivative comes from the dense LU of the same system where that is regular (with
concrete values; inside a trace the derivative stays invalid).

Failures are never silent. A derivative is valid where the solve converged
(``Status.CONVERGED``), the active set fits (``r`` slots) and the KKT system is
regular (as its solve above tests it), at the returned point or at its refinement.
Elsewhere a single solve's tangents and gradients are NaN (``on_failure="nan"``, the
default) or the solve raises at run time when it is differentiated
(``on_failure="raise"``, through ``equinox.error_if``: inside ``jit`` too, as an
``XlaRuntimeError``/``EquinoxRuntimeError``); in a batch each invalid sample's
derivative is zero. The status says why: a solve that did not converge keeps its own
code, and a differentiated solve that converged but whose derivative is not valid
reports ``Status.CONVERGED_NO_DERIVATIVE`` (its primal values are the converged
solve's, ``converged`` stays True); :func:`valid_derivatives` (status ``CONVERGED``)
gives the mask. The code is part of the rule's primal output, so only a solve that is
differentiated (``grad``, ``jvp``, ``vjp``, ...) reports it: an undifferentiated solve
never checks its derivative.

Static structure (N, the transcription, ``efforts``, the robot's type, the options) is
not differentiable; a traced value where a static one is expected raises a ``ValueError``
naming the argument.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg
import numpy as np

from .problem import Problem
from .solver.methods import IPM, AugmentedLagrangian
from .transcription import Transcription

__all__ = ["ACT_TOL", "BOUND_TOL", "NOISE", "REFINE", "REFINE_IP", "REFINE_IP_TIGHT", "WEAK", "WEAK_MIN",
           "implicit_tangent", "interior_point_applies", "refine", "refinement_stage", "valid_derivatives"]

#: inequalities with ``c_i > -ACT_TOL`` (normalised units) are candidates for the active set
ACT_TOL = 1e-3
#: simple bounds within BOUND_TOL (z's scaled units) are candidates for the active set (the
#: interior-point method may end a little inside a bound it could not snap onto)
BOUND_TOL = 1e-3
#: a candidate is active where its multiplier exceeds a threshold: WEAK * max(1, max
#: multiplier) at most, lowered to NOISE times the point's stationarity error in its free
#: variables where the optimum is more accurate (a genuine multiplier of 1e-7 is told from
#: noise at an optimum solved to 1e-12), and not below WEAK_MIN * max(1, max multiplier)
WEAK = 1e-7
NOISE = 1e3
WEAK_MIN = 1e-12
#: steps of iterated regularisation of the least-squares multipliers
LS_STEPS = 3

#: the refinement of a converged optimum whose derivative is not valid as it is (the AL
#: method warm-started at it, tolerances 1e-10; see :func:`refine`): the rule differentiates
#: at the refined point
REFINE = AugmentedLagrangian(tol_feasibility=1e-10, tol_optimality=1e-10, max_iter=2000)
#: the refinement's first stage, where the interior-point method applies: that method
#: warm-started at the returned point with a small barrier parameter and tolerances 1e-9
#: (tens of iterations), whose point :data:`REFINE` then finishes (a few to tens of
#: iterations from there instead of hundreds to thousands from the returned point). The
#: start stays where it is (``bound_push=1e-8``): pushed 1e-2 inside its boxes, as a cold
#: start is, some optima took hundreds of iterations to come back (24 serial3 optima of
#: the dataset family: at most 1,250 + 1,941 iterations, 2.3 s, against 129 + 29 and
#: 0.04 s; the same refined optima to 1e-12 in cost but one, within 2e-5)
REFINE_IP = IPM(tol=1e-9, mu_init=1e-8, bound_push=1e-8, dual_tol=1e-9, compl_tol=1e-9, tol_optimality=1e-9,
                tol_feasibility=1e-10)
#: the refinement's second interior-point stage, from the first's certified point: the
#: same method to tolerances 1e-11. Where it converges, its point is the refined optimum
#: and the AL stage does not run: on a 7-joint arm that stage takes thousands of
#: iterations (the Panda: 1,790 to 2,340, 4 to 6 s) for derivatives no closer to
#: differences of re-solves. Where it does not, its last iterate can have walked to a
#: neighbouring optimum, and the AL stage starts from the first stage's point instead
REFINE_IP_TIGHT = IPM(tol=1e-11, mu_init=1e-10, bound_push=1e-10, dual_tol=1e-11, compl_tol=1e-11,
                      tol_optimality=1e-11, tol_feasibility=1e-11, max_iter=300)

#: the linear solve of the derivatives through jtraj.solve / solve_batch: None (the
#: transcription's default: "stagewise" for the decoupled one, "dense" otherwise),
#: "stagewise" or "dense" (the reference, e.g. to compare in tests)
KKT_SOLVE: str | None = None

#: the differentiable fields of a Solution (the others get zero tangents)
DIFF_FIELDS = ("q", "qd", "v", "tau", "h", "T", "cost", "cost_terms", "energy")
_ON_FAILURE = ("nan", "raise", "zero")


def valid_derivatives(solution) -> jax.Array:
    """The boolean mask of the solutions whose derivatives are valid: those whose status
    is ``Status.CONVERGED``. A differentiated solve reports a converged solution whose
    derivative is not valid (after refinement) ``Status.CONVERGED_NO_DERIVATIVE``, so the
    mask is False there too. A single solution gives a 0-d mask, a batch one entry per
    sample. Derivatives of the other samples are zero in a batch and NaN (or an error,
    see ``on_failure``) for a single solve."""
    return jnp.asarray(solution.status) == 0


# ----------------------------------------------------------------------------------------
# the problem's functions of (z, theta)


def _nlp(problem: Problem, tr: Transcription):
    from .solver.nlp import NLP as _NLP

    return _NLP(problem=problem, tr=tr, layout=tr.layout(problem), sd=tr.stage_data(problem))


def _flat(tree):
    leaves = jax.tree.leaves(tree)
    return jnp.concatenate([jnp.ravel(x) for x in leaves]) if leaves else jnp.zeros(0)


def _rows(nlp, z):
    """(all constraint rows flat (eq, ineq, glob), number of equality rows)."""
    eq, ineq, glob = nlp.constraints(z)
    n_eq = sum(x.size for x in jax.tree.leaves(eq))
    return jnp.concatenate([_flat(eq), _flat(ineq), jnp.ravel(glob)]), n_eq


def _cost(nlp, z):
    return sum(nlp.cost_terms(z).values())


def outputs(problem: Problem, tr: Transcription, z) -> dict:
    """The differentiable fields of a :class:`jtraj.Solution` as functions of z (the
    same formulas as the solver's finish)."""
    nlp = _nlp(problem, tr)
    _, h = nlp.layout.unpack(z)
    W = nlp.W(z)
    q, qd, c, _ = jax.vmap(lambda w: tr.split_stage(problem, w))(W)
    a, tau = jax.vmap(lambda q_, qd_, c_: tr.accel_and_tau(problem, q_, qd_, c_))(q[:-1], qd[:-1], c[:-1])
    terms = nlp.cost_terms(z)
    lim = problem.robot.limits
    scale = 1.0 if lim.tau_max is None else lim.tau_max[None]
    energy = jnp.sum(h * jnp.sum((tau / scale) ** 2, axis=1))
    return dict(q=q, qd=qd, v=a, tau=tau, h=h, T=jnp.sum(h), cost=sum(terms.values()), cost_terms=terms,
                energy=energy)


def z_of(problem: Problem, tr: Transcription, solution):
    """The scaled decision vector of a solution (controls and periods)."""
    return tr.layout(problem).pack(tr.controls_of(solution), solution.h)


# ----------------------------------------------------------------------------------------
# the implicit step


class ActiveSet(eqx.Module):
    """The active set and multipliers at z*, compressed into ``r`` row slots."""

    idx: jax.Array  # (r,) row indices of the active constraints (first `count` slots)
    on: jax.Array  # (r,) slot holds an active row
    mult: jax.Array  # (r,) their multipliers
    at_lo: jax.Array  # (nz,) variables held at their lower bound
    at_hi: jax.Array  # (nz,) at their upper bound
    fits: jax.Array  # () the active rows fit the slots


def active_set(problem: Problem, tr: Transcription, z) -> ActiveSet:
    """The active set at z* and its least-squares multipliers (see the module doc)."""
    nlp = _nlp(problem, tr)
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi
    c, n_eq = _rows(nlp, z)
    J = jax.jacfwd(lambda zz: _rows(nlp, zz)[0])(z)
    gf = jax.grad(lambda zz: _cost(nlp, zz))(z)
    nc, nz = J.shape
    is_eq = jnp.arange(nc) < n_eq
    nonzero = jnp.any(J != 0, axis=1)
    cand = nonzero & (is_eq | (c > -ACT_TOL))
    near_lo, near_hi = z <= lo + BOUND_TOL, z >= hi - BOUND_TOL
    free0 = ~(near_lo | near_hi)

    def ls(free, rows):  # least-squares multipliers over `rows` in the `free` variables
        Jf = jnp.where(rows[:, None] & free[None, :], J, 0.0)
        g = jnp.where(free, gf, 0.0)
        # Tikhonov-regularised normal equations (J_f^T J_f is singular where fewer rows
        # than variables are active), then LS_STEPS steps of iterated regularisation:
        # each divides the regularisation's bias eps / (sigma^2 + eps) by the same factor,
        # so that the multipliers reach the stationarity the point itself has
        eps = 1e-12 * (1.0 + jnp.max(jnp.sum(Jf**2, axis=1)))
        cf = jax.scipy.linalg.cho_factor(Jf.T @ Jf + eps * jnp.eye(nz, dtype=J.dtype))
        lam = jnp.zeros(nc, J.dtype)
        for _ in range(LS_STEPS):
            lam = lam - Jf @ jax.scipy.linalg.cho_solve(cf, g + Jf.T @ lam)
        return jnp.where(rows, lam, 0.0)

    lam = ls(free0, cand)
    scale = jnp.maximum(1.0, jnp.max(jnp.abs(lam)))
    # the multipliers' noise: the stationarity the point has in its free variables
    noise = jnp.max(jnp.where(free0, jnp.abs(gf + J.T @ lam), 0.0))
    weak = jnp.minimum(WEAK * scale, jnp.maximum(NOISE * noise, WEAK_MIN * scale))
    active = cand & (is_eq | (lam > weak))
    lam = ls(free0, active)
    nu = gf + J.T @ lam  # the bound multipliers (lower: nu >= 0, upper: nu <= 0)
    at_lo = near_lo & (nu > weak)
    at_hi = near_hi & ~at_lo & (nu < -weak)
    free = ~(at_lo | at_hi)
    lam = ls(free, active)  # weakly held variables released
    r = min(nc, nz)
    order = jnp.argsort(~active, stable=True)[:r]
    count = jnp.sum(active)
    on = jnp.arange(r) < count
    return ActiveSet(idx=order, on=on, mult=jnp.where(on, lam[order], 0.0), at_lo=at_lo, at_hi=at_hi,
                     fits=count <= r)


def _kkt_residual(dyn, static, tr: Transcription, act: ActiveSet, z, l):
    """F(z, l, theta) of the module doc: (nz + r,)."""
    problem = eqx.combine(dyn, static)
    nlp = _nlp(problem, tr)
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi

    def lagrangian(zz):
        c = _rows(nlp, zz)[0]
        return _cost(nlp, zz) + jnp.sum(jnp.where(act.on, l, 0.0) * c[act.idx])

    free = ~(act.at_lo | act.at_hi)
    Fz = jnp.where(free, jax.grad(lagrangian)(z), z - jnp.where(act.at_lo, lo, hi))
    Fc = jnp.where(act.on, _rows(nlp, z)[0][act.idx], l)
    return jnp.concatenate([Fz, Fc])


def implicit_tangent(problem: Problem, tr: Transcription, solution, tangent, converged, method: str | None = None,
                     at=None):
    """The tangent of the optimum along ``tangent`` (a pytree like ``problem``'s
    inexact-array part, :func:`equinox.partition`): returns ``(dz, outputs' tangents,
    z, valid)``. Linear in ``tangent``; ``valid`` is a traced bool (converged, the active
    set fits, the KKT system regular). ``method``: ``"stagewise"`` (the decoupled
    transcription's default, :mod:`jtraj.adjoint`) or ``"dense"`` (every other
    transcription's, and the reference). ``at``: the point ``(u, h)`` (the
    transcription's controls and the periods) to differentiate at, by default the
    solution's own (a refined optimum of the same problem, see :func:`refine`). Where not
    valid, the tangents are finite values the caller masks (a NaN in ``tangent``, or in a
    cotangent in reverse mode, stays NaN)."""
    method = _method(tr, method)
    dyn, static = eqx.partition(problem, eqx.is_inexact_array)
    z = z_of(problem, tr, solution) if at is None else tr.layout(problem).pack(*at)
    finite = jnp.all(jnp.isfinite(z))
    layout = tr.layout(problem)
    z = jnp.where(finite, z, jnp.clip(jnp.zeros_like(z), layout.z_lo, layout.z_hi))
    act = active_set(problem, tr, z)
    # the held variables on their bounds (the point the active set describes)
    z = jnp.where(act.at_lo, layout.z_lo, jnp.where(act.at_hi, layout.z_hi, z))
    F = functools.partial(_kkt_residual, static=static, tr=tr, act=act)
    _, dF = jax.jvp(lambda d_: F(d_, z=z, l=act.mult), (dyn,), (tangent,))
    if method == "dense":
        dz, regular = _dense_solve(F, dyn, z, act, dF, converged & finite & act.fits)
    else:
        dz, regular = _stagewise_solve(problem, tr, F, dyn, z, act, dF)
    valid = converged & finite & act.fits & regular
    _, dout = jax.jvp(lambda zz, d_: outputs(eqx.combine(d_, static), tr, zz), (z, dyn), (dz, tangent))
    return dz, dout, z, valid


def _method(tr: Transcription, method):
    if method is None:
        return "stagewise" if tr.name == "decoupled" else "dense"
    if method not in ("stagewise", "dense"):
        raise ValueError(f"method must be 'stagewise' or 'dense', got {method!r}")
    if method == "stagewise" and tr.name != "decoupled":
        raise ValueError(f"method='stagewise' needs the decoupled transcription, got {tr.name!r}")
    return method


def _dense_solve(F, dyn, z, act, dF, usable):
    """dz by a dense LU factorisation of K = dF/d(z, l), (nz + r) square."""
    nz, r = z.shape[0], act.idx.shape[0]
    K = jax.jacfwd(lambda w: F(dyn, z=w[:nz], l=w[nz:]))(jnp.concatenate([z, act.mult]))
    lu, piv = jax.scipy.linalg.lu_factor(K)
    d = jnp.abs(jnp.diagonal(lu))
    regular = jnp.all(jnp.isfinite(lu)) & (jnp.min(d) > 1e-13 * jnp.maximum(jnp.max(d), 1e-300))
    keep = usable & regular
    lu = jnp.where(keep, lu, jnp.eye(nz + r, dtype=K.dtype))
    piv = jnp.where(keep, piv, jnp.arange(nz + r, dtype=piv.dtype))
    return jax.scipy.linalg.lu_solve((lu, piv), -dF)[:nz], regular


#: the stage-wise solve is valid where it reproduces a probe solution to this accuracy (root
#: mean square over unit entries): a regular system reproduces it to about 1e-10 (serial3)
#: to 2e-7 (pkm2's path constraints, where the solve still agrees with the dense LU to
#: 1e-14 relative), a singular or indefinite one misses it by O(1) or more
PROBE_TOL = 1e-5


def _stagewise_solve(problem, tr, F, dyn, z, act, dF):
    """dz by the stage-wise solve of the symmetric KKT system (:mod:`jtraj.adjoint`),
    wrapped in ``jax.lax.custom_linear_solve`` (reverse mode: the same solve)."""
    from .adjoint import stagewise_kkt

    nz = z.shape[0]
    nlp = _nlp(problem, tr)
    _, K_mv = jax.linearize(lambda w: F(dyn, z=w[:nz], l=w[nz:]), jnp.concatenate([z, act.mult]))
    sk = stagewise_kkt(problem, tr, nlp, act, z, lambda xz, xl: K_mv(jnp.concatenate([xz, xl])),
                       lambda zz: _rows(nlp, zz)[0])
    fixed = act.at_lo | act.at_hi
    ff, on = (~fixed).astype(z.dtype), act.on.astype(z.dtype)
    # the bound-held variables follow their bounds; their columns move to the right-hand side
    dzb = jnp.where(fixed, -dF[:nz], 0.0)
    Kb = K_mv(jnp.concatenate([dzb, jnp.zeros_like(act.mult)]))
    b = ((-dF[:nz] - Kb[:nz]) * ff, (-dF[nz:] - Kb[nz:]) * on)
    xz, _ = jax.lax.custom_linear_solve(sk.matvec, b, sk.solve, symmetric=True)
    # regularity: the solve reproduces a probe solution (a singular or ill-conditioned
    # system, a reduced Hessian that is not positive definite, or an iteration that does
    # not converge fails it)
    e = (ff, on)
    xe, ok = sk.iterate(sk.matvec(e))
    err = jnp.sqrt(sum(jnp.sum((a - b_) ** 2) for a, b_ in zip(xe, e)) / jnp.maximum(1.0, jnp.sum(ff) + jnp.sum(on)))
    regular = ok & jnp.isfinite(err) & (err < PROBE_TOL)
    return xz * ff + dzb, regular


# ----------------------------------------------------------------------------------------
# the custom_jvp rules around the solve


@dataclasses.dataclass(frozen=True)
class _Config:
    """What the rules close over (never traced): the problem's static part, the
    resolved options, the transcription, the start flags and the failure mode."""

    static: Any
    opts: Any
    transcription: str
    warm: bool
    guess: bool
    on_failure: str
    batch: Any = None  # (slots, segment) for a batch


def _to_float(sol):
    """The Solution with its integer and boolean fields as floats (custom_jvp outputs
    whose tangents are plain zeros); :func:`_from_float` undoes it."""
    return dataclasses.replace(sol, converged=sol.converged.astype(float), status=sol.status.astype(float),
                               iterations=sol.iterations.astype(float),
                               outer_iterations=sol.outer_iterations.astype(float))


def _from_float(sol):
    count = jax.dtypes.canonicalize_dtype(np.int64)  # the solver's iteration counters
    return dataclasses.replace(sol, converged=sol.converged > 0.5, status=sol.status.astype(jnp.int32),
                               iterations=sol.iterations.astype(count),
                               outer_iterations=sol.outer_iterations.astype(count))


@functools.lru_cache(maxsize=None)
def _nested(fn):
    """A solver entry point (decorated by ``jtraj.solver.options.options_jit``) as a plain
    ``eqx.filter_jit`` for use inside another trace: XLA compiler options are for
    top-level programs only."""
    return eqx.filter_jit(fn.__wrapped__)


def _primal_single(cfg: _Config, dyn, init):
    """The solve itself: inside a trace one program (``solve_jit``); with concrete values
    the staged programs of :func:`jtraj.solve` (:mod:`jtraj.solver.staged`), the ones an
    ordinary solve of the problem runs (compiled once for both)."""
    from .solver import staged as _staged
    from .solver.core import solve_jit as _solve_jit

    problem = eqx.combine(dyn, cfg.static)
    if any_traced((dyn, init)):
        return _nested(_solve_jit)(problem, cfg.opts, cfg.transcription, init, np.bool_(cfg.warm),
                                   np.bool_(cfg.guess))
    return _staged.solve(problem, cfg.opts, cfg.transcription, init, np.bool_(cfg.warm), np.bool_(cfg.guess))


def _primal_batch(cfg: _Config, dyn, init):
    from .solver.lanes import solve_batch_jit as _solve_batch_jit, solve_problems as _solve_problems

    problems = eqx.combine(dyn, cfg.static)
    leaves = jax.tree.leaves((dyn, init))
    if any(isinstance(x, jax.core.Tracer) for x in leaves):  # inside jit or vmap: one vmapped program
        return _nested(_solve_batch_jit)(problems, cfg.opts, cfg.transcription, init, jnp.asarray(cfg.warm))
    slots, segment = cfg.batch  # concrete values: the host-driven lane driver
    return _solve_problems(problems, cfg.opts, cfg.transcription, init, cfg.warm, slots, segment)


def _tangent_solution(cfg: _Config, dyn, ddyn, sol, at, method=None):
    """The Solution-shaped tangent of one solve (floats everywhere, see _to_float) at the
    point ``at`` = (u, h), unmasked, and whether it is valid (``method``: default
    KKT_SOLVE). The rules mask it once the final validity is known (:func:`_masked`)."""
    return _tangent_program(cfg.static, cfg.transcription, KKT_SOLVE if method is None else method, dyn, ddyn, sol,
                            at)


def _nan_where_invalid(dout, ddyn, valid):
    """The output tangents ``dout`` where ``valid``, NaN in every entry otherwise, in
    forward and in reverse mode alike.

    A product with the primal factor ``1`` / ``NaN`` makes every output tangent NaN, but
    its transpose reaches only the inputs whose tangent flows into the outputs through
    unmasked operations: an input that enters only masked rows of the KKT system (an
    inactive ``T_max``, a cost term that the failed point does not see) would receive an
    exact zero cotangent. The second term couples every input entry to every output:
    ``(factor - 1) * sum(input tangents)`` is ``0 * s`` where valid (its transpose
    ``0 * cotangent``, zero) and NaN otherwise (its transpose NaN in every input entry).
    """
    factor = jnp.where(valid, 1.0, jnp.nan)
    total = sum((jnp.sum(t) for t in jax.tree.leaves(ddyn)), jnp.zeros((), factor.dtype))
    coupling = (factor - 1.0) * total
    return jax.tree.map(lambda t: t * factor + jnp.broadcast_to(coupling, jnp.shape(t)).astype(t.dtype), dout)


@eqx.filter_jit  # keyed by the problem's structure, not by the solver options
def _tangent_program(static, transcription: str, method, dyn, ddyn, sol, at):
    tr = Transcription(transcription)
    problem = eqx.combine(dyn, static)
    _, dout, _, valid = implicit_tangent(problem, tr, sol, ddyn, sol.status == 0, method=method, at=at)
    zeros = jax.tree.map(jnp.zeros_like, _to_float(sol))
    return dataclasses.replace(zeros, **dout), valid


def _masked(dsol, ddyn, valid, batch: bool):
    """The tangent ``dsol`` where ``valid``; elsewhere zero (a batch, per sample) or NaN
    in every entry (a single solve, :func:`_nan_where_invalid`)."""
    fields = {f: getattr(dsol, f) for f in DIFF_FIELDS}
    if batch:
        expand = lambda t: jnp.reshape(valid, jnp.shape(valid) + (1,) * (jnp.ndim(t) - jnp.ndim(valid)))  # noqa: E731
        fields = jax.tree.map(lambda t: jnp.where(expand(t), t, 0.0), fields)
    else:
        fields = _nan_where_invalid(fields, ddyn, valid)
    return dataclasses.replace(dsol, **fields)


def _with_status(out, valid):
    """The (float) primal output with ``Status.CONVERGED_NO_DERIVATIVE`` where the solve
    converged but its derivative is not valid: the status of a differentiated solve
    tells why its derivative is zero or NaN, and :func:`valid_derivatives` agrees."""
    from .solver.results import Status

    no_derivative = (out.status == float(Status.CONVERGED)) & ~valid
    return dataclasses.replace(out, status=jnp.where(no_derivative, float(Status.CONVERGED_NO_DERIVATIVE), out.status))


# ----------------------------------------------------------------------------------------
# refinement of an optimum whose derivative is not valid as it is


def _point(tr: Transcription, sol):
    """(u, h) of a solution (batched or not): the point the derivative is taken at."""
    return tr.controls_of(sol), sol.h


def interior_point_applies(problem: Problem, transcription: str) -> bool:
    """Whether the interior-point method applies to the problem (the decoupled
    transcription, no path equalities, no jerk rows): the first stage of the refinement."""
    from .solver.core import resolve_method

    return resolve_method(None, transcription, problem.robot, problem.jerk).method == "ip"


def _refine_options(problem: Problem, transcription: str):
    """The resolved options of the refinement's stages: ``(interior point or None, AL)``."""
    from .solver.core import resolve_method
    from .solver.options import to_options

    al = resolve_method(to_options(REFINE), transcription, problem.robot, problem.jerk)
    if not interior_point_applies(problem, transcription):
        return None, None, al
    return tuple(resolve_method(to_options(m), transcription, problem.robot, problem.jerk)
                 for m in (REFINE_IP, REFINE_IP_TIGHT)) + (al,)


def _ip_stage(problem: Problem, tr: Transcription, opts, at, need):
    """The interior-point iterations alone, warm-started at ``at`` where ``need``: ``((u,
    h), solved)``, the point where it is certified (active bounds snapped on), else its
    last iterate, else ``at`` where it did not run or its iterate is not finite."""
    from .solver.core import prepare, run_ip

    nlp, state, _ = prepare(problem, opts, tr, at, True)
    state = state._replace(done=state.done | ~need)
    method, ip = run_ip(nlp, state, opts)
    solved = ip.done & ~ip.failed
    z = jnp.where(solved, method.postprocess(nlp, ip, state).z, ip.z)
    ran = ~state.done & jnp.all(jnp.isfinite(z))
    return nlp.layout.unpack(jnp.where(ran, z, state.z)), ran & solved


def refine(problem: Problem, tr: Transcription, at, need):
    """The optimum refined where the traced bool ``need`` says so, warm-started at
    ``at`` = (u, h). Where the interior-point method applies: :data:`REFINE_IP`, then
    :data:`REFINE_IP_TIGHT` from its point where it is certified; the second stage's
    point is the result where it is certified. Otherwise :data:`REFINE` (the AL loop)
    from the first stage's point (its last iterate where it is not certified: near the
    optimum, the small barrier parameter keeps it there), or from ``at`` where the
    interior-point method does not apply. Returns ``(u, h)``: the refined point, ``at``
    where no stage converged. Where ``need`` is False every stage starts finished (no
    iteration; under ``vmap`` such a lane waits for the others). Bounded work: at most
    ``REFINE_IP.max_iter + REFINE_IP_TIGHT.max_iter`` interior-point iterations,
    ``REFINE.max_iter`` Newton iterations of the AL loop and one restart."""
    from .solver import loop
    from .solver.al import ALMethod
    from .solver.core import finish, prepare

    ip_opts, tight_opts, opts = _refine_options(problem, tr.name)
    start, tight, done = at, at, jnp.zeros((), bool)
    if ip_opts is not None:
        start, solved = _ip_stage(problem, tr, ip_opts, at, need)
        tight, done = _ip_stage(problem, tr, tight_opts, start, need & solved)
    nlp, state, valid = prepare(problem, opts, tr, start, True)
    state = state._replace(done=state.done | ~need | done)
    al = ALMethod(opts)
    ref = finish(nlp, al.postprocess(nlp, loop.run(al, nlp, state), state), opts, valid)
    ok = need & ~done & (ref.status == 0)
    return tuple(jnp.where(done, t, jnp.where(ok, a, b)) for t, a, b in zip(tight, _point(tr, ref), at))


def _concrete(x):
    """``x`` as a NumPy array where it is a concrete value, None where it is traced."""
    return None if isinstance(x, jax.core.Tracer) else np.asarray(x)


def _refined_tangent(cfg: _Config, dyn, ddyn, sol, batch: bool):
    """The Solution-shaped tangent of a solve (``batch``: per sample), unmasked, and its
    validity.

    Where the derivative at the returned optimum is not valid although the solve
    converged (the active set read off a point on the interior-point method's central
    path misses constraints with small multipliers: the reduced Hessian of the rest is
    indefinite, the stage-wise solve's self-check fails), the optimum is refined
    (:func:`refine`) and the derivative taken at the refined point: the derivative of the
    same optimum to the refinement's tolerance. With concrete primal values (a derivative
    outside ``jit``) the decision is taken on the host and the refinement's stages run on
    the samples that need it, one at a time, by the staged solver's programs
    (:func:`_refine_staged`); inside ``jit`` or ``vmap`` the refinement is one program
    that runs with the traced flag, iterating only where it is set."""
    tr = Transcription(cfg.transcription)
    at = _point(tr, sol)

    def tangent(point, method=None):
        if batch:
            return jax.vmap(lambda d, dd, s, a: _tangent_solution(cfg, d, dd, s, a, method))(dyn, ddyn, sol, point)
        return _tangent_solution(cfg, dyn, ddyn, sol, point, method)

    dsol, valid = tangent(at)
    need = (sol.status == 0) & ~valid
    flags = _concrete(need)
    if flags is not None and not np.any(flags):
        return dsol, valid
    if flags is not None and not any_traced((dyn, sol)):  # on the host: re-solve what needs it
        at = _refine_host(cfg, dyn, at, flags, batch)
    else:  # inside a trace: one bounded refinement program whose stages start finished where
        # nothing needs it. Not a lax.cond on any(need): under an outer vmap its predicate is
        # batched, the cond becomes a select over operands all broadcast along the batch, and
        # the constants the interior-point iterations close over reach their custom_vmap rule
        # batched, which JAX refuses
        def run(d, a, n):
            return refine(eqx.combine(d, cfg.static), tr, a, n)

        at = jax.vmap(run)(dyn, at, need) if batch else run(dyn, at, need)
    dsol, valid = tangent(at)
    # a stage-wise solve that still fails its self-check at a converged point (an iteration on
    # the multipliers that does not converge in MAX_ITER steps): with concrete values, the
    # dense LU of the same KKT system where it is regular
    still = _concrete((sol.status == 0) & ~valid)
    if still is None or not np.any(still) or _method(tr, KKT_SOLVE) != "stagewise":
        return dsol, valid
    dense, ok = tangent(at, "dense")
    use = still & np.asarray(ok)
    if not batch:  # (a host choice)
        return (dense, ok) if bool(use) else (dsol, valid)
    # a per-sample selection (the caller masks the invalid samples by selection as well)
    pick = lambda a, b: jnp.where(jnp.reshape(use, use.shape + (1,) * (jnp.ndim(a) - use.ndim)), a, b)  # noqa: E731
    return jax.tree.map(pick, dense, dsol), valid | use


def refinement_stage(problem: Problem, transcription: str, at):
    """The last stage of :func:`refine` for one concrete problem, the stages run by the
    staged solver's programs (those of ordinary solves): ``(solver, start, solution)``.
    Where the interior-point method applies, :data:`REFINE_IP` runs from ``at``, then
    :data:`REFINE_IP_TIGHT` from its point where it converged; where that converges too,
    it is the last stage: ``(REFINE_IP_TIGHT, its start, its Solution)``.
    Otherwise the last stage is :data:`REFINE` from the first stage's point (its last
    iterate where it is finite), else from ``at``, not yet run: ``(REFINE, start, None)``."""
    from .solver import staged
    from .solver.results import Status

    tr = Transcription(transcription)
    ip_opts, tight_opts, _ = _refine_options(problem, tr.name)
    start = at
    if ip_opts is not None:
        first = staged.warm_ip(problem, ip_opts, tr.name, at)
        point = _point(tr, first)
        if all(np.all(np.isfinite(np.asarray(a))) for a in point):
            start = point
        if int(first.status) == Status.CONVERGED:
            tight = staged.warm_ip(problem, tight_opts, tr.name, point)
            if int(tight.status) == Status.CONVERGED:
                return REFINE_IP_TIGHT, point, tight
    return REFINE, start, None


def _refine_staged(problem: Problem, tr: Transcription, at):
    """:func:`refine` of one concrete problem (:func:`refinement_stage`, then the staged AL
    program where that stage is :data:`REFINE`): the refined ``(u, h)``, else ``at``."""
    from .solver import staged
    from .solver.results import Status

    _, start, last = refinement_stage(problem, tr.name, at)
    if last is None:
        last = staged.warm_al(problem, _refine_options(problem, tr.name)[2], tr.name, start)
    return _point(tr, last) if int(last.status) == Status.CONVERGED else at


def _refine_host(cfg: _Config, dyn, at, flags, batch: bool):
    """:func:`refine` with concrete values: each flagged problem by :func:`_refine_staged`."""
    tr = Transcription(cfg.transcription)
    if not batch:
        return _refine_staged(eqx.combine(dyn, cfg.static), tr, at)
    u, h = (np.array(a) for a in at)
    for i in np.flatnonzero(flags):
        one = eqx.combine(jax.tree.map(lambda x: x[i], dyn), cfg.static)
        ui, hi = _refine_staged(one, tr, (jnp.asarray(u[i]), jnp.asarray(h[i])))
        u[i], h[i] = np.asarray(ui), np.asarray(hi)
    return jnp.asarray(u), jnp.asarray(h)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _single(cfg: _Config, dyn, init):
    return _to_float(_primal_single(cfg, dyn, init))


@_single.defjvp
def _single_jvp(cfg: _Config, primals, tangents):
    dyn, init = primals
    ddyn, _ = tangents
    sol = _primal_single(cfg, dyn, init)
    dsol, valid = _refined_tangent(cfg, dyn, ddyn, sol, batch=False)
    dsol = _masked(dsol, ddyn, valid, batch=False)
    out = _with_status(_to_float(sol), valid)
    if cfg.on_failure == "raise":
        out = eqx.error_if(out, ~valid, "jtraj: derivative of a solve that did not converge (or whose KKT "
                                        "system at the optimum is degenerate); see Solution.status")
    return out, dsol


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _batch(cfg: _Config, dyn, init):
    return _to_float(_primal_batch(cfg, dyn, init))


@_batch.defjvp
def _batch_jvp(cfg: _Config, primals, tangents):
    dyn, init = primals
    ddyn, _ = tangents
    sol = _primal_batch(cfg, dyn, init)
    dsol, valid = _refined_tangent(cfg, dyn, ddyn, sol, batch=True)
    return _with_status(_to_float(sol), valid), _masked(dsol, ddyn, valid, batch=True)


def _zero_tangent_safe(x):
    return jax.lax.stop_gradient(x)


def solve_traced(problem: Problem, opts, transcription: str, init, warm: bool, guess: bool, on_failure: str):
    """:func:`jtraj.solve` on a problem whose leaves are traced (called by it)."""
    if on_failure not in ("nan", "raise"):
        raise ValueError(f"on_failure must be 'nan' or 'raise', got {on_failure!r}")
    dyn, static = eqx.partition(problem, eqx.is_inexact_array)
    cfg = _Config(static=static, opts=opts, transcription=transcription, warm=bool(warm), guess=bool(guess),
                  on_failure=on_failure)
    init = jax.tree.map(_zero_tangent_safe, init)
    sol = _single(cfg, dyn, init)
    return _from_float(sol)


def solve_batch_traced(problems, opts, transcription: str, init, warm: bool, slots, segment: int):
    """:func:`jtraj.solve_batch` on problems whose leaves are traced (called by it):
    per-sample derivatives, zero where a sample's derivative is not valid."""
    dyn, static = eqx.partition(problems, eqx.is_inexact_array)
    cfg = _Config(static=static, opts=opts, transcription=transcription, warm=bool(warm), guess=False,
                  on_failure="zero", batch=(slots, segment))
    init = jax.tree.map(_zero_tangent_safe, init)
    return _from_float(_batch(cfg, dyn, init))


def any_traced(tree) -> bool:
    """Whether a leaf of ``tree`` is a JAX tracer (inside jit, vmap or a derivative).
    Outside every transformation no leaf can be one: that case is answered without
    flattening the tree (about 4 against 30-100 us for a problem)."""
    if _trace_state_clean is not None and _trace_state_clean():
        return False
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(tree))


try:  # (a JAX internal; without it every call flattens the tree)
    from jax._src.core import trace_state_clean as _trace_state_clean
except ImportError:  # pragma: no cover
    _trace_state_clean = None


def envelope(problem: Problem, tr: Transcription, solution) -> tuple[Any, dict]:
    """The envelope-theorem gradient of the optimal cost in every inexact-array leaf of
    ``problem`` (a pytree like its :func:`equinox.partition`-ed array part): the
    parameters' partial derivative of the Lagrangian at ``(z*, lambda*)`` with the
    bound-held variables following their bounds. At a KKT point it equals the chain
    rule through the implicit tangent (``d cost``); :func:`jtraj.sensitivity` reports
    both. Also returns the active set's sizes (``kkt_size``, ``n_active``, ``n_bound``)."""
    dyn, static = eqx.partition(problem, eqx.is_inexact_array)
    z = z_of(problem, tr, solution)
    act = active_set(problem, tr, z)
    fixed = act.at_lo | act.at_hi

    def lagrangian(d):
        p = eqx.combine(d, static)
        nlp = _nlp(p, tr)
        zz = jnp.where(act.at_lo, nlp.layout.z_lo, jnp.where(act.at_hi, nlp.layout.z_hi, z))
        zz = jnp.where(fixed, zz, jax.lax.stop_gradient(zz))
        c = _rows(nlp, zz)[0]
        return _cost(nlp, zz) + jnp.sum(jnp.where(act.on, act.mult, 0.0) * c[act.idx])

    counts = {"kkt_size": z.shape[0] + act.idx.shape[0], "n_active": jnp.sum(act.on), "n_bound": jnp.sum(fixed)}
    return jax.grad(lagrangian)(dyn), counts
