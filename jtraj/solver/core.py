"""One problem's solve as traced programs: the starting point, the NLP and its
starting state, the interior-point run with the AL fallback, and the finish
(polish, verification, :class:`jtraj.Solution`)."""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..problem import Problem, orientation_error
from ..transcription import Transcription
from . import curvature, ipm, loop
from .al import ALMethod, ALState, with_phase
from .certify import al_kkt_error, at_most_once, final_polish, kkt_error
from .nlp import NLP
from .options import SolverOptions, options_jit, static_options
from .results import Solution, Status


def initial_guess(problem: Problem, opts: SolverOptions, tr: Transcription):
    """The default starting point (u (N, m_u), h (N,)) of ``opts.guess``, converted to
    the transcription's controls (:meth:`Transcription.initial_controls`)."""
    from ..initial_guess import GUESSES

    v0, h0 = GUESSES[opts.guess](problem)
    return tr.initial_controls(problem, v0, h0), h0


def stagewise_directions(opts: SolverOptions, tr: Transcription, jerk: bool = False) -> bool:
    """Whether the Newton directions come from the stage-wise solve (see
    ``SolverOptions.linear_solver``; never with jerk rows, which couple stages)."""
    solver = opts.linear_solver
    if solver == "auto":
        solver = "riccati" if jax.default_backend() == "cpu" and not jerk else "dense"
    if solver == "riccati" and jerk:
        raise ValueError("the solver's linear_solver='riccati' does not handle Problem(jerk=True) (its rows couple "
                         "consecutive stages); use linear_solver='auto' or 'dense', or jerk=False")
    return solver == "riccati" and tr.name == "decoupled"


class Start(NamedTuple):
    """One problem's start (:func:`prepare`)."""

    nlp: NLP
    #: the AL state the solve starts from (finished at once where not ``valid``)
    state: ALState
    #: whether the problem is a valid input (finite, not infeasible on its face)
    valid: Array


def prepare(problem: Problem, opts: SolverOptions, tr: Transcription, init, warm=False) -> Start:
    """The NLP, starting state and validity of one problem; invalid samples start from a
    finite placeholder and are flagged at the end."""
    layout = tr.layout(problem)
    nlp = NLP(problem=problem, tr=tr, layout=layout, sd=tr.stage_data(problem),
              stagewise=stagewise_directions(opts, tr, problem.jerk),
              ineq_penalty=opts.inequality_penalty, pbm_init=opts.pbm_init, pbm_ratio=opts.pbm_ratio,
              ip_curvature=curvature.resolve(static_options(opts).ip_curvature, problem.robot))
    u0, h0 = init
    z0 = jnp.clip(layout.pack(u0, h0), layout.z_lo, layout.z_hi)
    # what a single Problem rejects up front (a batch builds its problems unvalidated;
    # non-finite ends included)
    valid = jnp.all(jnp.isfinite(z0)) & ~problem.infeasible_on_its_face()
    z0 = jnp.where(valid, z0, jnp.clip(jnp.zeros_like(z0), layout.z_lo, layout.z_hi))
    # an invalid sample takes no iteration (its lane is free at once in a batch)
    state = ALMethod(opts).init(nlp, z0, warm)
    return Start(nlp=nlp, state=state._replace(done=state.done | ~valid), valid=valid)


def solve_core(problem: Problem, opts: SolverOptions, tr: Transcription, init, warm=False) -> Solution:
    """One problem's solve as one traced program: the interior-point method where the
    options' method is "ip", the AL loop (with its restarts) where it leaves the problem
    undecided or alone otherwise, then :func:`finish`; each method run by the driver of
    :mod:`jtraj.solver.loop`."""
    nlp, state, valid = prepare(problem, opts, tr, init, warm)
    al = ALMethod(opts)
    if static_options(opts).method == "ip":
        # one problem: a real branch (vmapped, both sides would run; solve_batch does not
        # come here with "ip")
        method, ip = run_ip(nlp, state, opts)
        solved = ipm.decided(state, ip)
        state = jax.lax.cond(solved, lambda: method.postprocess(nlp, ip, state),
                             lambda: loop.run(al, nlp, state))
        sol = finish(nlp, state, opts, valid, light=solved)
        return dataclasses.replace(sol, iterations=sol.iterations + jnp.where(solved, 0, ip.it))
    return finish(nlp, al.postprocess(nlp, loop.run(al, nlp, state), state), opts, valid)


def ip_method(opts, max_iter=None) -> ipm.InteriorPoint:
    """The interior-point method of the options: at most ``max_iter`` iterations (default
    ``ip_max_iter``; a solve passes 0 for a state the AL loop would not run, a warm start
    already optimal), its tolerances :func:`ip_tolerances`."""
    max_iter = static_options(opts).ip_max_iter if max_iter is None else max_iter
    return ipm.InteriorPoint(max_iter=max_iter, tol=ip_tolerances(opts))


def run_ip(nlp, state, opts):
    """``(method, final state)`` of the interior-point method run from the AL start
    ``state`` as a solve runs it: no iteration where ``state`` is done, the run started
    with the options' ``ip_mu_init``, ``ip_bound_push`` and ``ip_first_shift``."""
    method = ip_method(opts, jnp.where(state.done, 0, static_options(opts).ip_max_iter))
    start = method.init(nlp, state.z, opts.ip_mu_init, opts.ip_bound_push, opts.ip_first_shift)
    return method, loop.iterate(method, nlp, start)


def ip_tolerances(opts) -> ipm.Tolerances:
    """When the interior-point method's run ends as solved (see ``SolverOptions.method``):
    the residual of every constraint within half ``verify_tol``, so that the strict
    verification passes without a polish. The parts' test is never looser than the AL
    loop's own targets: with ``tol_feasibility`` / ``tol_optimality`` set below them (a
    user asking for a tight solve) it ends only at the overall ``ip_tol``."""
    return ipm.Tolerances(static_options(opts).ip_tol, jnp.minimum(opts.ip_dual_tol, opts.tol_optimality),
                          jnp.minimum(0.5 * opts.verify_tol, opts.tol_feasibility),
                          jnp.minimum(opts.ip_compl_tol, opts.tol_optimality), opts.ip_project_tol,
                          opts.ip_damping)


def finish(nlp: NLP, s: ALState, opts: SolverOptions, valid, light=False) -> Solution:
    """The solution of a finished run: polished (:func:`jtraj.solver.certify.final_polish`), verified and
    certified. ``light``: a point the interior-point method decided (converged to
    ``ip_tol``, feasible to ~1e-7, or stalled far from feasible) is verified as it is,
    without the polish, and its KKT error is that of its own multipliers (``s.mult``), not
    of least-squares ones: both cost a Jacobian of every constraint row (serial3, N = 20,
    8 lanes, one core: the finish 1.48 ms per problem, of which the polish about 0.8 and
    the least-squares KKT error about 0.7). Under vmap either runs only while some lane
    needs it, so :func:`jtraj.solver.lanes._finish_lanes` groups the light problems together."""
    nlp = with_phase(nlp, s)
    problem, tr = nlp.problem, nlp.tr
    # a Python True (one interior-point result, :mod:`jtraj.solver.staged`): neither the polish
    # nor the least-squares KKT error is in the program
    static_light = light is True
    light = jnp.asarray(light)
    if not static_light:
        s = s._replace(z=final_polish(nlp, s.z, opts, skip=light))
    _, h = nlp.layout.unpack(s.z)
    W = nlp.W(s.z)
    q, qd, c, _ = jax.vmap(lambda w: tr.split_stage(problem, w))(W)
    a, tau = jax.vmap(lambda q_, qd_, c_: tr.accel_and_tau(problem, q_, qd_, c_))(q[:-1], qd[:-1], c[:-1])
    eq, ineq, glob = nlp.constraints(s.z)
    viol = {k: jnp.max(jnp.maximum(g, 0.0)) for k, g in ineq.items()}
    # bounds kept by projection, reported for completeness (relative)
    lim = problem.robot.limits
    if lim.qdd_max is not None:
        viol["qdd"] = jnp.maximum(viol.get("qdd", 0.0), jnp.max(jnp.maximum(jnp.abs(a) / lim.qdd_max[None] - 1, 0)))
    if lim.tau_max is not None:
        viol["tau"] = jnp.maximum(viol.get("tau", 0.0), jnp.max(jnp.maximum(jnp.abs(tau) / lim.tau_max[None] - 1, 0)))
    viol["h"] = jnp.max(jnp.maximum(jnp.maximum(lim.h_min - h, h - lim.h_max) / lim.h_max, 0.0))
    viol["T"] = jnp.maximum(glob[0], 0.0)
    if problem.jerk:  # the jerk rows (normalised, see jtraj.transcription.jerk_inequalities)
        viol["jerk"] = jnp.max(jnp.maximum(glob[1:], 0.0))
    viol["goal"] = jnp.maximum(jnp.max(jnp.abs(q[-1] - problem.q_goal)), jnp.max(jnp.abs(qd[-1] - problem.qd_goal)))
    if problem.via_points:
        # the Euclidean distance beyond each via point's own tol, absolute (task units)
        # like the goal's: the AL and the polish meet the imposed box to ~1e-7, which a
        # check relative to a tight tol (1e-6 m) could never accept
        sd = nlp.sd
        dist = jnp.linalg.norm(jax.vmap(problem.robot.forward_kinematics)(q) - sd.via_target, axis=-1)
        viol["via"] = jnp.max(jnp.where(sd.is_via > 0, jnp.maximum(dist - sd.via_tol, 0.0), 0.0))
        if sd.via_rotation is not None:  # ||vect(R^T R_l)|| beyond rot_tol, absolute likewise
            rot = jax.vmap(lambda q_, R_l: jnp.linalg.norm(orientation_error(problem.robot.rotation(q_), R_l)))
            err = rot(q, sd.via_rotation)
            viol["via_rotation"] = jnp.max(jnp.where(sd.is_via_rot > 0, jnp.maximum(err - sd.via_rot_tol, 0.0), 0.0))
    for k, c in eq.items():
        if k != "goal":
            viol[k] = jnp.max(jnp.abs(c))
    overall = jnp.max(jnp.stack(list(viol.values())))
    viol["overall"] = overall
    terms = nlp.cost_terms(s.z)
    cost = sum(terms.values())
    finite = jnp.all(jnp.isfinite(s.z)) & jnp.isfinite(cost) & jnp.all(jnp.isfinite(tau))
    verified = overall <= opts.verify_tol
    # the loop certifies optimality on the AL's own measure at the end of a subproblem;
    # a point it left uncertified (iteration limit) may still be a KKT point of the
    # original problem: the KKT error with the best of three multiplier estimates decides
    kkt = al_kkt_error(nlp, s.z, s.mult, s.mu)
    if not static_light:
        kkt = jnp.minimum(at_most_once(~light, lambda zz: kkt_error(nlp, zz), s.z, fill=jnp.inf), kkt)
    # a certified point reports at most its certifying test's value (Solution.kkt_error)
    kkt = jnp.minimum(kkt, jnp.where(s.done & ~s.failed, s.stationarity, jnp.inf))
    certified = s.done | (kkt <= opts.tol_optimality)
    unfinished = jnp.where(s.stalled, Status.LIKELY_INFEASIBLE, Status.MAX_ITERATIONS)
    status = jnp.where(
        ~valid, Status.INVALID_INPUT,
        jnp.where(~finite | s.failed, Status.NUMERICAL_ERROR,
                  jnp.where(certified & verified, Status.CONVERGED,
                            jnp.where(s.done, Status.VERIFICATION_FAILED,
                                      jnp.where(verified, Status.FEASIBLE_NOT_OPTIMAL, unfinished)))))
    scale = 1.0 if lim.tau_max is None else lim.tau_max[None]
    energy = jnp.sum(h * jnp.sum((tau / scale) ** 2, axis=1))
    return Solution(q=q, qd=qd, v=a, tau=tau, h=h, T=jnp.sum(h), cost=cost, cost_terms=terms, energy=energy,
                    max_violation=viol, converged=status == Status.CONVERGED, status=status.astype(jnp.int32),
                    iterations=s.it, outer_iterations=s.outer, history=s.history, kkt_error=kkt)


@options_jit()  # jtraj._compile.solver_jit (the solver's XLA CPU options), options split
def solve_jit(problem, opts, transcription, init, warm, guess):
    # init is always arrays, replaced by the default guess where the traced bool ``guess``
    # says so (one program for cold and warm starts, and the guess without a program
    # call of its own: 0.36 ms of a ~6 ms warm single solve), and warm a traced bool
    tr = Transcription(transcription)
    init = jax.lax.cond(guess, lambda: initial_guess(problem, opts, tr), lambda: init)
    return solve_core(problem, opts, tr, init, warm)


@functools.lru_cache(maxsize=16)
def placeholder_init(N: int, m_u: int):
    return np.zeros((N, m_u)), np.zeros(N)


def resolve_method(opts: SolverOptions | None, transcription: str, robot, jerk: bool = False) -> SolverOptions:
    """The options (the defaults for None) with ``method="auto"`` resolved (see
    :class:`jtraj.SolverOptions`) and an explicit "ip" checked. Cached: building a
    SolverOptions and checking it costs about 0.15 ms, which one warm solve (about 5 ms)
    paid twice."""
    if opts is not None and not isinstance(opts, SolverOptions):
        raise ValueError(f"options must be a jtraj.SolverOptions, got {type(opts).__name__}")
    return _resolved(opts, transcription, getattr(robot, "path_equalities", None) is not None, bool(jerk))


@functools.lru_cache(maxsize=64)
def _resolved(opts: SolverOptions | None, transcription: str, path_equalities: bool,
              jerk: bool = False) -> SolverOptions:
    opts = SolverOptions() if opts is None else opts
    if opts.method == "auto":
        ip = transcription == "decoupled" and not path_equalities and not jerk and opts.inequality_penalty == "phr"
        return dataclasses.replace(opts, method="ip" if ip else "al")
    _check_method(opts, transcription, path_equalities, jerk)
    return opts


def _check_method(opts: SolverOptions, transcription: str, path_equalities: bool, jerk: bool = False):
    """``method="ip"`` needs the decoupled transcription, no equalities but the goal and
    no jerk rows (its global rows are functions of T alone)."""
    if opts.method != "ip":
        return
    if transcription != "decoupled":
        raise ValueError(f"solver jtraj.IPM: method='ip' needs transcription='decoupled', got {transcription!r}; "
                         f"use jtraj.Auto or jtraj.AugmentedLagrangian")
    if path_equalities:
        raise ValueError("solver jtraj.IPM: method='ip' does not handle a robot's path_equalities; use jtraj.Auto "
                         "or jtraj.AugmentedLagrangian")
    if jerk:
        raise ValueError("solver jtraj.IPM: method='ip' does not handle Problem(jerk=True) (its rows couple "
                         "consecutive stages); use jtraj.Auto or jtraj.AugmentedLagrangian, or jerk=False")
