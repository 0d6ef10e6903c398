"""One concrete problem solved in stages: the programs a problem needs, compiled when it
needs them.

:func:`jtraj.solve` on concrete arrays comes here; under an outer ``jit``, ``vmap`` or
``grad`` it stays one traced program (:func:`jtraj.solver.core.solve_jit`, whose
``lax.cond`` between the interior-point result and the augmented-Lagrangian loop
compiles both sides). Here the decision is taken on the host, on the concrete result:

* :func:`_solve_ip_jit`: the default guess, the interior-point method
  (:mod:`jtraj.solver.ipm`) and the light finish of a point it decided (verified as it is, its
  KKT error that of its own multipliers): the program every default solve runs;
* :func:`_solve_al_jit`: the augmented-Lagrangian loop with its restarts, the final
  polish and the least-squares KKT error, from the same start: for a problem the
  interior-point method leaves undecided, a warm start that is already optimal, an
  invalid sample, or ``method="al"``.

The interior-point program is about a third of the single program's size and the
compiler's time grows faster than its size, so the first solution of a problem that
needs only the first program comes several times sooner. Both give the results of the
single program (the same operations, compiled apart). Both compile quickly for a
process's first call and optimised from its second (:func:`jtraj._tracecache.tiered`).
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from ..transcription import Transcription
from . import ipm, loop
from .al import ALMethod
from .core import finish, initial_guess, prepare, run_ip
from .options import options_jit, static_options
from .results import Solution


def _start(problem, opts, transcription, init, warm, guess):
    tr = Transcription(transcription)
    init = jax.lax.cond(guess, lambda: initial_guess(problem, opts, tr), lambda: init)
    return prepare(problem, opts, tr, init, warm)


@options_jit(quick_first=True)
def _solve_ip_jit(problem, opts, transcription, init, warm, guess):
    """(Solution, decided, interior-point iterations): the solution is the one to return
    where ``decided`` (see :func:`jtraj.solver.ipm.decided`)."""
    nlp, state, valid = _start(problem, opts, transcription, init, warm, guess)
    method, ip = run_ip(nlp, state, opts)
    sol = finish(nlp, method.postprocess(nlp, ip, state), opts, valid, light=True)
    return sol, ipm.decided(state, ip), ip.it


@options_jit(quick_first=True)
def _solve_al_jit(problem, opts, transcription, init, warm, guess, ip_iterations):
    """The augmented-Lagrangian solve from the start, its iterations counted after
    ``ip_iterations`` (an interior-point run's that left the problem undecided; None:
    ``method="al"``)."""
    nlp, state, valid = _start(problem, opts, transcription, init, warm, guess)
    al = ALMethod(opts)
    sol = finish(nlp, al.postprocess(nlp, loop.run(al, nlp, state), state), opts, valid)
    if ip_iterations is None:
        return sol
    return dataclasses.replace(sol, iterations=sol.iterations + ip_iterations)


def solve(problem, opts, transcription: str, init, warm, guess) -> Solution:
    """:func:`jtraj.solve` past its checks, for concrete arguments."""
    ip_iterations = None
    if static_options(opts).method == "ip":
        sol, decided, ip_iterations = _solve_ip_jit(problem, opts, transcription, init, warm, guess)
        if bool(decided):
            return sol
    return _solve_al_jit(problem, opts, transcription, init, warm, guess, ip_iterations)


def warm_ip(problem, opts, transcription: str, init) -> Solution:
    """The interior-point program alone (no AL finish), warm-started at ``init`` = (u, h):
    its Solution, CONVERGED where it decided an optimum (a refinement's stage, see
    :func:`jtraj.implicit.refine`)."""
    return _solve_ip_jit(problem, opts, transcription, init, np.bool_(True), np.bool_(False))[0]


def warm_al(problem, opts, transcription: str, init) -> Solution:
    """The augmented-Lagrangian program warm-started at ``init`` = (u, h): its Solution."""
    return _solve_al_jit(problem, opts, transcription, init, np.bool_(True), np.bool_(False), None)
