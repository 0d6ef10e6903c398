"""The augmented-Lagrangian solver (ALD): outer multiplier/penalty loop around a
projected, damped Newton method on the stage-structured NLP.

Design (why it is fast under ``vmap`` on a CPU):

* **One flat, bounded loop.** Outer (multiplier) and inner (Newton) iterations share
  one ``lax.while_loop``: an outer update is a branch-free ``jnp.where`` taken when
  the inner subproblem is solved to its tolerance. Under ``vmap`` a nested loop would
  run every inner loop to the batch's worst case; the flat one does not.
* **Exact Hessians from small pieces.** The objective is a sum of per-sample terms
  ``l_k(w_k)`` of the stage vector ``w_k = (q_k, qd_k, u_k, h_k)``, composed with the
  polynomial state recursion ``W(z)``. The Hessian is
  ``sum_k J_k^T (d2 l_k) J_k + sum_k (dl_k/dw_k) . d2 W_k``: per-sample (2n+m+1)^2
  Hessians of the inverse dynamics, plus the co-state term of the recursion. The
  co-states ``dl_k/dw_k`` are reverse-mode autodiff, never hand-derived adjoints. In a
  subproblem that stalls, the model adds the penalty curvature of the inequalities just
  short of their PHR kink, which the exact Hessian of a C1 penalty does not see
  (``SolverOptions.kink_margin``).
* **Newton directions stage by stage.** For the decoupled transcription the Hessian in z
  is never formed: the Newton system is the KKT system of a linear-quadratic problem
  over the stages, solved by a Riccati recursion whose cost grows linearly with N
  (:mod:`jtraj.lq`; ``SolverOptions(linear_solver="dense")`` assembles H and factorises
  it instead, O(N^3), as the other transcriptions always do).
* **Bounds kept exactly.** Boxes on the controls and on h are simple bounds on z,
  handled by Bertsekas' projected Newton (no penalty, never violated); all other
  constraints enter the augmented Lagrangian (PHR for inequalities; opt-in, the
  twice-differentiable penalty-barrier multiplier term of ``SolverOptions.pbm()``).
* **Branch-free globalisation (a parallel trust region).** A geometric ladder of
  Levenberg shifts, up to a Gershgorin bound that is always positive definite, is
  factorised at once; every positive-definite shift gives a direction, tried at a few
  step lengths in one vectorised evaluation of the augmented Lagrangian. No iteration
  is spent only on raising the damping after a failed line search.
* **Feasibility polish.** After the loop, a few Gauss-Newton projections onto the
  equalities and nearly-active inequalities remove the O(1/mu) violations the AL
  leaves; the strict verification is made after it.

Shapes follow :mod:`jtraj.transcription`.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .. import lq
from .certify import estimate_multipliers, final_polish, init_multipliers, kkt_error, ls_multipliers, stationarity
from .nlp import NLP, PBM_FLOOR, Multipliers, violation
from . import loop
from .options import SolverOptions, TracedOptions, static_options


# ----------------------------------------------------------------------------------------
# the loop


class ALState(NamedTuple):
    z: Array
    mult: Multipliers
    mu: Array
    damping: Array
    omega: Array  # current inner tolerance
    eta: Array  # current feasibility tolerance (thesis schedule)
    viol_prev: Array
    inner: Array
    outer: Array
    it: Array
    done: Array
    failed: Array
    stalled: Array  # stopped as likely infeasible
    stationarity: Array
    history: Array  # (max_outer, 3): cost, violation, penalty
    it_max: Array  # iteration budget of this run (max_iter; raised by a restart)
    mu_max: Array  # penalty cap of this run (penalty_max; restart_penalty_max after a restart)
    restarts: Array  # restarts taken so far (see restart_state)
    z_start: Array  # the first run's starting point (a PBM run's PHR fallback starts there)
    val_ref: Array  # the AL's value at the last stall checkpoint of this subproblem


# NumPy, not jnp: a jnp constant made at import takes the dtype of that moment (float32
# when x64 is enabled after ``import jtraj``), which changed the iterates between processes
# that enabled x64 before and after the import (Ray workers against the CLI)
# 4 shifts x 4 step lengths. The trial points are about a third of a Newton iteration's
# cost; against 4 shifts x 6 step lengths (down to 0.01) this is about 1.1x faster on the
# benchmark family with the same pairs converged, and 3 shifts cost 13 % more iterations.
_LADDER = np.linspace(0.0, 1.0, 4)  # exponents of the geometric shift ladder
_STEPS = np.array([1.0, 0.5, 0.25, 0.1])
#: the trial points (index into the ladder, step length), shift-major: every step on every shift but
#: the top (Gershgorin) one, which takes only the full step: the top shift rarely wins
#: with a shorter step (0.5 % of the iterations), so 13 trials cost the same iterations
#: as 16 and run a few per cent faster.
_TRIAL_SHIFT = np.concatenate([np.repeat(np.arange(len(_LADDER) - 1), len(_STEPS)), [len(_LADDER) - 1]])
_TRIAL_STEP = np.concatenate([np.tile(_STEPS, len(_LADDER) - 1), _STEPS[:1]])


def held_bounds(z, g, lo, hi, hdiag, eps):
    """The variables the projected Newton step holds at their bounds: Bertsekas'
    eps-active set, narrowed by the diagonal curvature. A variable within ``eps`` of a
    bound is held only if the gradient pushes it there harder than its curvature holds it
    (the diagonal Newton step ``-g / hdiag`` would reach the bound; always where
    ``hdiag <= 0``). Holding a stiff variable that was merely near a bound froze it while
    the free variables, coupled to it, could not become stationary: the projected
    gradient then cycled about eps until the iteration limit (benchmark pairs stopped at a
    KKT error of ~1e-3; 2 of the 3 such pairs of bench_solver converged with this rule)."""
    curv = jnp.maximum(hdiag, 0.0)
    return (((z <= lo + eps) & (g > 0) & (g >= curv * (z - lo)))
            | ((z >= hi - eps) & (g < 0) & (-g >= curv * (hi - z))))


class NewtonStep(NamedTuple):
    """One projected Newton step of the AL loop (:func:`_newton_step`)."""

    z: Array  # the new point (z itself where no trial point was accepted)
    damping: Array  # the next Levenberg damping
    pg: Array  # the largest projected-gradient residual at the old point
    value: Array  # the augmented Lagrangian at the old point
    moved: Array  # whether a trial point was accepted


def _newton_step(nlp: NLP, z, mult, mu, damping, kink=None) -> NewtonStep:
    # the barrier materialises the derivatives once, so that XLA cannot fuse their
    # assembly into each of the shifted factorisations below (a guard: on serial3 the
    # timings with and without it were within the machine's noise)
    if nlp.stagewise:
        val, model, pieces = jax.lax.optimization_barrier(nlp.stage_newton_model(z, mult, mu, kink))
        g = model.g
    else:
        val, g, H = jax.lax.optimization_barrier(nlp.al_derivatives(z, mult, mu, kink))
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi
    pg = z - jnp.clip(z - g, lo, hi)  # projected-gradient residual
    eps = jnp.minimum(1e-3, jnp.max(jnp.abs(pg)))
    if nlp.stagewise:
        hdiag, rows = nlp.hessian_bounds(pieces)
    else:
        hdiag = jnp.diag(H)
    free = ~held_bounds(z, g, lo, hi, hdiag, eps)
    # Globalisation without serialising control flow (a parallel trust region): the
    # Hessian is factorised with a ladder of Levenberg shifts at once (the last, from
    # Gershgorin's theorem, is always positive definite); every positive-definite shift
    # gives a direction, each is tried at a few step lengths in one vectorised
    # evaluation (Armijo's test); see below for which wins. The next damping is the
    # shift that won, relaxed after a full step.
    if nlp.stagewise:
        # rows bounds the free row sums of |H|: the same Gershgorin test, on a bound
        excess = jnp.where(free, rows(free) - jnp.abs(hdiag) - hdiag, -1.0)
    else:
        Hf = jnp.where(free[:, None] & free[None, :], H, 0.0)
        Hf = Hf + jnp.diag(jnp.where(free, 0.0, 1.0))
        excess = jnp.sum(jnp.abs(Hf), axis=1) - jnp.abs(jnp.diag(Hf)) - jnp.diag(Hf)
    gersh = jnp.maximum(0.0, jnp.max(excess)) + damping
    # geometric ladder from damping / 8 to the Gershgorin bound (always PD)
    low = damping / 8.0
    ladder = jnp.asarray(_LADDER, z.dtype)
    trial_shift, steps = _TRIAL_SHIFT, jnp.asarray(_TRIAL_STEP, z.dtype)
    shifts = low * (jnp.maximum(gersh, 8.0 * low) / low) ** ladder
    if nlp.stagewise:
        d_free, good = lq.newton_directions(model, free, shifts)
    else:
        gf = jnp.where(free, g, 0.0)
        eye = jnp.eye(Hf.shape[0], dtype=Hf.dtype)
        shift_free = jnp.where(free, 1.0, 0.0)
        Ls = jax.vmap(lambda sh: jnp.linalg.cholesky(Hf + sh * jnp.diag(shift_free)))(shifts)
        good = jax.vmap(lambda L: jnp.all(jnp.isfinite(L)))(Ls)
        Ls = jnp.where(good[:, None, None], Ls, eye)
        d_free = -jax.vmap(lambda L: jax.scipy.linalg.cho_solve((L, True), gf))(Ls)
    # variables held at (or within eps of) a bound take a diagonally scaled gradient
    # step under the same shift, so that the ladder also shortens their step (an
    # unscaled -g there overshoots a stiff AL and no step length passes)
    d_held = -g[None, :] / (jnp.abs(hdiag)[None, :] + shifts[:, None])
    d = jnp.where(free[None, :], d_free, d_held)  # (S, nz)
    d = jnp.where(jnp.all(jnp.isfinite(d), axis=1, keepdims=True), d, -g[None, :])
    candidates = jnp.clip(z[None, :] + steps[:, None] * d[trial_shift], lo[None, :], hi[None, :])
    values = jax.vmap(nlp.al_value, in_axes=(0, None, None))(candidates, mult, mu)
    decrease = jnp.einsum("i,ki->k", g, candidates - z[None, :])
    ok = (values <= val + 1e-4 * decrease) & jnp.isfinite(values) & good[trial_shift]
    # far from a stationary point the lowest value found wins (fewest iterations on the
    # benchmark); close to one (projected gradient < 1e-3) the least-damped direction
    # that takes a long step (>= 1/4) does, which keeps Newton's fast local convergence
    # (the lowest value is then decided by rounding)
    long_ok = ok & (steps >= 0.25) & (jnp.max(jnp.abs(pg)) < 1e-3)
    best = jnp.where(jnp.any(long_ok), jnp.argmax(long_ok), jnp.argmin(jnp.where(ok, values, jnp.inf)))
    any_ok = jnp.any(ok)
    z_new = jnp.where(any_ok, candidates[best], z)
    step = steps[best]
    used = shifts[jnp.asarray(trial_shift)[best]]
    damping = jnp.where(any_ok, jnp.where(step == 1.0, used * 0.5, used * 2.0), shifts[-1])
    damping = jnp.clip(jnp.where(jnp.isfinite(damping), damping, 1e10), 1e-12, 1e10)
    return NewtonStep(z=z_new, damping=damping, pg=jnp.max(jnp.abs(pg)), value=val, moved=any_ok)


def with_phase(nlp: NLP, s: "ALState") -> NLP:
    """``nlp`` with its inequality term for the run ``s`` is in: PBM in the first run,
    PHR after a restart (``SolverOptions.inequality_penalty == "pbm"``; else ``nlp``)."""
    if nlp.ineq_penalty != "pbm":
        return nlp
    return eqx.tree_at(lambda n: n.pbm_on, nlp, s.restarts == 0)


def run_al(nlp: NLP, z0, opts: SolverOptions, warm=False):
    """The AL loop from z0 to the end (see :func:`init_state` and :func:`al_loop`)."""
    return run_with_restart(nlp, init_state(nlp, z0, opts, warm), opts)


def init_state(nlp: NLP, z0, opts: SolverOptions, warm=False) -> ALState:
    """The loop's starting state. With ``warm`` (a traced bool), multipliers start from
    their least-squares estimate at z0 and the penalty at its cap / 1e2 instead of zero
    and ``penalty_init``: a warm start near an optimum then stays there. A warm start
    that already meets both tolerances (the KKT error of the original problem and the
    violation) is finished before the first iteration."""
    cold = init_multipliers(nlp, z0)

    def estimate(_):
        ls = ls_multipliers(nlp, z0)
        return estimate_multipliers(nlp, z0, ls=ls), kkt_error(nlp, z0, ls=ls)

    warm = jnp.asarray(warm)
    # a real branch (warm is one flag for a whole batch): a cold start skips the estimate
    est, kkt0 = jax.lax.cond(warm, estimate, lambda _: (cold, jnp.asarray(jnp.inf, z0.dtype)), None)
    done0 = warm & (kkt0 <= opts.tol_optimality) & (violation(*nlp.constraints(z0)) <= opts.tol_feasibility)
    if nlp.ineq_penalty == "pbm":
        est = est._replace(ineq=jax.tree.map(lambda r: jnp.maximum(r, PBM_FLOOR), est.ineq),
                           glob=jnp.maximum(est.glob, PBM_FLOOR))
    mult0 = jax.tree.map(lambda a, b: jnp.where(warm, a, b), est, cold)
    mu0 = jnp.where(warm, jnp.maximum(opts.penalty_init, opts.penalty_max * 1e-2), opts.penalty_init).astype(z0.dtype)
    return ALState(
        z=z0, mult=mult0, mu=mu0, damping=jnp.asarray(opts.damping_init, dtype=z0.dtype),
        omega=jnp.asarray(1e-2, dtype=z0.dtype), eta=jnp.asarray(1e-2, dtype=z0.dtype),
        viol_prev=jnp.asarray(jnp.inf, dtype=z0.dtype), inner=jnp.asarray(0), outer=jnp.asarray(0),
        it=jnp.asarray(0), done=done0, failed=jnp.asarray(False), stalled=jnp.asarray(False),
        stationarity=jnp.where(done0, kkt0, jnp.inf).astype(z0.dtype),
        history=jnp.full((opts.max_outer, 3), jnp.nan, dtype=z0.dtype),
        it_max=jnp.asarray(_first_run_iter(opts)), mu_max=jnp.asarray(opts.penalty_max, dtype=z0.dtype),
        restarts=jnp.asarray(0), z_start=z0, val_ref=jnp.asarray(jnp.inf, dtype=z0.dtype))


def al_finished(s: ALState, opts: SolverOptions):
    return s.done | s.stalled | (s.it >= s.it_max) | (s.outer >= opts.max_outer)


def _fallback(opts: SolverOptions) -> bool:
    """Whether an uncertified PBM run falls back to a cold PHR run (``pbm_fallback_iter``)."""
    return static_options(opts).inequality_penalty == "pbm" and static_options(opts).pbm_fallback_iter > 0


def _first_run_iter(opts: SolverOptions):
    return jnp.minimum(opts.max_iter, opts.pbm_fallback_iter) if _fallback(opts) else opts.max_iter


def _max_restarts(opts: SolverOptions):
    """1 or 2 restarts (see :func:`restart_state`), or none with ``restart_iter = 0`` and no PBM
    fallback; a traced count inside a compiled program."""
    return int(_fallback(opts)) + (opts.restart_iter > 0)


def needs_restart(s: ALState, opts: SolverOptions):
    """A run that ended uncertified (iteration or outer limit), not as likely infeasible
    nor failed, with a restart left (one; two for a PBM run, see :func:`restart_state`)."""
    return ~s.done & ~s.failed & ~s.stalled & (s.restarts < _max_restarts(opts))


def restart_state(nlp: NLP, s: ALState, opts: SolverOptions) -> ALState:
    """Restart an uncertified run once (where :func:`needs_restart`; elsewhere ``s``
    unchanged): from its final point after the feasibility polish, with least-squares
    multipliers there, the penalty at ``restart_penalty_max / 100`` and capped at
    ``restart_penalty_max``, for ``restart_iter`` more iterations.

    Why: on problems whose feasible set is thin (minimum time close to N h_max, the
    torques saturated at most samples) the first-order multiplier updates converge
    slowly, the penalty then grows to its cap, and the Newton subproblems with their PHR
    kinks at mu ~ 1e5-1e6 stall at a feasible point with a KKT error of 1e-3..1e-1. From
    that point, with multipliers estimated there and a moderate penalty, the loop
    converges (benchmark family, seeds 1, 2, 11: all 6 pairs that IPOPT solves and the
    first run left uncertified, about 60 to 590 iterations after the restart, cost within
    0.04 % of IPOPT's). A point the polish
    leaves certified (KKT error and violation within tolerance) is not restarted:
    :func:`jtraj.solver.core.finish` certifies it.

    A PBM run (``SolverOptions.pbm_fallback_iter``) has two restarts: the first is PHR's
    own cold run from the first run's starting point, the second the warm one above."""
    # a warm start at the polished point: least-squares multipliers, fresh schedules, and
    # finished at once where that point is already certified
    fresh = init_state(nlp, final_polish(nlp, s.z, opts, chord=False), opts, warm=True)
    need = needs_restart(s, opts) & ~fresh.done
    dt = s.z.dtype
    new = fresh._replace(mu=jnp.asarray(opts.restart_penalty_max * 1e-2, dt),
                         mu_max=jnp.asarray(opts.restart_penalty_max, dt), it=s.it,
                         it_max=s.it + opts.restart_iter, restarts=s.restarts + 1, z_start=s.z_start)
    if _fallback(opts):
        # the first restart of a PBM run is PHR's own cold run from the first run's start
        # (zero multipliers, PHR's default penalty_init, max_iter iterations); the warm one
        # above follows it if that too ends uncertified
        cold = init_state(nlp, s.z_start, opts)
        cold = cold._replace(mult=jax.tree.map(jnp.zeros_like, cold.mult),
                             mu=jnp.asarray(SolverOptions.penalty_init, dt),
                             it=s.it, it_max=s.it + opts.max_iter, restarts=s.restarts + 1)
        new = jax.tree.map(lambda a, b: jnp.where(s.restarts == 0, a, b), cold, new)
    return jax.tree.map(lambda a, b: jnp.where(need, a, b), new, s)


def run_with_restart(nlp: NLP, state: ALState, opts: SolverOptions) -> ALState:
    """The AL loop from ``state`` to its end, restarted where needed (see
    :func:`restart_state`): :func:`jtraj.solver.loop.run` of :class:`ALMethod`."""
    return loop.run(ALMethod(opts), nlp, state)


def next_inner_tol(opts: SolverOptions, omega, viol, pbm_on=False):
    """The next AL subproblem's stationarity tolerance (see ``SolverOptions.inner_tol_ratio``;
    ``pbm_on``: a traced flag, the PBM phase of a PBM run, which takes ``pbm_inner_tol_ratio``)."""

    def tol(name):
        if getattr(static_options(opts), name) > 0:
            return jnp.maximum(jnp.minimum(1e-2, getattr(opts, name) * viol), opts.tol_optimality)
        return jnp.maximum(omega * 0.1, opts.tol_optimality)

    if opts.inequality_penalty == "pbm":
        return jnp.where(pbm_on, tol("pbm_inner_tol_ratio"), tol("inner_tol_ratio"))
    return tol("inner_tol_ratio")


class ALRun(NamedTuple):
    """What a run of the AL loop holds fixed (:meth:`ALMethod.enter`)."""

    #: the NLP with the run's inequality term (:func:`with_phase`)
    nlp: NLP
    #: whether that term is PBM's (a traced bool; False for PHR)
    pbm_on: Array


def al_loop(nlp: NLP, state: ALState, opts: SolverOptions, limit=None) -> ALState:
    """The AL loop from ``state`` until finished or until ``state.it`` reaches ``limit``
    (resumable, so a batch can be run in segments): :func:`jtraj.solver.loop.iterate`
    of :class:`ALMethod`, without restarts."""
    return loop.iterate(ALMethod(opts), nlp, state, limit)


class ALMethod:
    """The augmented-Lagrangian method in the protocol of :mod:`jtraj.solver.loop`: one
    flat loop of Newton iterations whose outer (multiplier and penalty) updates are
    branch-free, and restarts of runs that end uncertified. ``opts``: the options inside
    the compiled program (a ``SolverOptions`` or its traced form)."""

    def __init__(self, opts):
        self.opts = opts

    @property
    def restarts(self) -> bool:
        """Whether a run can be restarted (static; inside a compiled program the count of
        restarts is traced, so always)."""
        return isinstance(self.opts, TracedOptions) or _max_restarts(self.opts) > 0

    def init(self, nlp: NLP, z0, warm=False) -> ALState:
        """:func:`init_state`."""
        return init_state(nlp, z0, self.opts, warm)

    def enter(self, nlp: NLP, state: ALState) -> ALRun:
        """The NLP in the phase of the run ``state`` is in (PBM's first run, PHR after)."""
        nlp = with_phase(nlp, state)
        return ALRun(nlp=nlp, pbm_on=nlp.pbm_active)

    def terminate(self, run: ALRun, s: ALState):
        """:func:`al_finished`."""
        return al_finished(s, self.opts)

    def needs_restart(self, nlp: NLP, s: ALState):
        """:func:`needs_restart`."""
        return needs_restart(s, self.opts)

    def restart(self, nlp: NLP, s: ALState) -> ALState:
        """:func:`restart_state`."""
        return restart_state(nlp, s, self.opts)

    def postprocess(self, nlp: NLP, s: ALState, start: ALState) -> ALState:
        """The state itself: it is the AL state :func:`jtraj.solver.core.finish` takes."""
        return s

    def step(self, run: ALRun, s: ALState) -> ALState:
        """One Newton iteration of the current subproblem and, where it ends the
        subproblem, the outer update (computed always, applied by ``jnp.where``)."""
        opts, nlp, pbm_on = self.opts, run.nlp, run.pbm_on
        # the kink curvature's margin, zero until the subproblem has run kink_after iterations
        kink = (None if static_options(opts).kink_margin == 0
                else jnp.where((s.inner >= opts.kink_after) & ~pbm_on, opts.kink_margin, 0.0).astype(s.z.dtype))
        newton = _newton_step(nlp, s.z, s.mult, s.mu, s.damping, kink)
        z, damping, val, moved = newton.z, newton.damping, newton.value, newton.moved
        failed = ~jnp.all(jnp.isfinite(z))
        inner = s.inner + 1
        g, ((eq, ineq, glob), cost) = nlp.al_grad_and_parts(z, s.mult, s.mu)
        stat = stationarity(nlp, z, g)
        subproblem_done = (stat <= s.omega) | (inner >= opts.max_inner) | (~moved & (damping >= 1e9))
        # ---- outer update (computed always, applied where subproblem_done) ----
        viol = violation(eq, ineq, glob, s.mult, s.mu)
        # the stall exit (off with stall_window = 0, a traced value like the others)
        stall_on = opts.stall_window > 0
        window = jnp.maximum(opts.stall_window, 1)
        checkpoint = stall_on & (s.inner % window == 0)
        stalled_sub = (checkpoint & (s.inner >= 2 * window) & (s.it >= opts.stall_after)
                       & (viol > opts.stall_min_viol)
                       & (s.val_ref - val < opts.stall_ratio * s.mu * viol**2))
        subproblem_done = subproblem_done | stalled_sub
        val_ref = jnp.where(checkpoint, val, s.val_ref)
        new_eq = jax.tree.map(lambda l, c: jnp.clip(l + s.mu * c, -1e10, 1e10), s.mult.eq, eq)
        new_ineq = jax.tree.map(lambda r, g: nlp.ineq_update(g, r, s.mu), s.mult.ineq, ineq)
        new_glob = nlp.ineq_update(glob, s.mult.glob, s.mu)
        updated = Multipliers(new_eq, new_ineq, new_glob)
        if opts.schedule == "default":
            take_mult = jnp.asarray(True)
            # grow the penalty only while infeasible and not shrinking fast enough
            grow = (viol > opts.feasibility_ratio * s.viol_prev) & (viol > opts.tol_feasibility)
            eta = s.eta
        else:  # Conn-Gould-Toint as in the thesis (alpha = beta = 0.4 family)
            take_mult = viol <= s.eta
            grow = ~take_mult
            mu_next = jnp.where(grow, jnp.minimum(s.mu * opts.penalty_growth, s.mu_max), s.mu)
            eta = jnp.where(take_mult, s.eta * mu_next ** -0.4, 1e-2 * mu_next ** -0.4)
            eta = jnp.maximum(eta, opts.tol_feasibility)
        mult = jax.tree.map(lambda new, old: jnp.where(take_mult, new, old), updated, s.mult)
        mu = jnp.where(grow, jnp.minimum(s.mu * opts.penalty_growth, s.mu_max), s.mu)
        omega = next_inner_tol(opts, s.omega, viol, pbm_on)
        plain_viol = violation(eq, ineq, glob)
        converged = (plain_viol <= opts.tol_feasibility) & (stat <= opts.tol_optimality)
        hist = s.history.at[jnp.minimum(s.outer, opts.max_outer - 1)].set(jnp.stack([cost, plain_viol, s.mu]))
        # likely infeasible: two outer iterations ago the violation was hardly larger
        # although the penalty has grown 16x since (history rows: cost, violation, mu),
        # or has sat at its cap since (see SolverOptions.detect_infeasible)
        back = s.history[jnp.maximum(s.outer - 2, 0)]
        hardly_less = plain_viol > 0.95 * back[1]
        prev = s.history[jnp.maximum(s.outer - 1, 0)]
        grown = ((plain_viol > 1e-3) & (s.mu >= 16.0 * back[2])
                 & ((jnp.minimum(prev[1], back[1]) > opts.detect_min_viol) | ~pbm_on))
        capped = (plain_viol > 1e-4) & (back[2] >= s.mu_max)
        stalled = (subproblem_done & (s.outer >= 2) & hardly_less & (grown | capped) & opts.detect_infeasible
                   & (nlp.tr.name == "decoupled"))

        def pick(new, old):
            return jax.tree.map(lambda a, b: jnp.where(subproblem_done, a, b), new, old)

        return ALState(
            z=z, mult=pick(mult, s.mult), mu=pick(mu, s.mu), damping=damping,
            omega=pick(omega, s.omega), eta=pick(eta, s.eta), viol_prev=pick(viol, s.viol_prev),
            inner=jnp.where(subproblem_done, 0, inner), outer=s.outer + subproblem_done.astype(int),
            it=s.it + 1, done=(subproblem_done & converged) | failed, failed=failed, stalled=stalled,
            stationarity=stat, history=jnp.where(subproblem_done, hist, s.history),
            it_max=s.it_max, mu_max=s.mu_max, restarts=s.restarts, z_start=s.z_start, val_ref=val_ref)
