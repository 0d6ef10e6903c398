"""The iterative methods' protocol and the one bounded driver that runs them.

A method (the augmented-Lagrangian loop :class:`jtraj.solver.al.ALMethod`, the
interior-point method :class:`jtraj.solver.ipm.InteriorPoint`) is an object built inside
a compiled program from the solver's options, with five functions; a driver never
looks inside a state:

* ``init(nlp, z0, ...) -> state``: the starting state (a NamedTuple holding the
  iteration count ``it``) from the scaled unknowns ``z0``;
* ``enter(nlp, state)``: what a run of iterations from ``state`` holds fixed, handed to
  ``step`` and ``terminate`` as their ``nlp`` (the NLP itself, or the AL method's NLP in
  the phase of its run);
* ``step(nlp, state) -> state``: one iteration, branch-free (a finished state comes back
  unchanged or is never stepped);
* ``terminate(nlp, state) -> bool array``: whether the run is over; it includes the
  method's own iteration cap, so that every loop here is bounded. It reads the state
  (and the method's options) only, elementwise, so that the batch driver applies it to
  all its lanes' states at once (``nlp`` None there);
* ``postprocess(nlp, state, start) -> ALState``: the finished state as the
  augmented-Lagrangian state that :func:`jtraj.solver.core.finish` polishes, verifies
  and certifies (``start``: the state the solve began from).

A method that restarts a run that ended uncertified (the AL method) also has
``restarts`` (whether any restart can happen: a static bool), ``needs_restart(nlp,
state) -> bool array`` (elementwise like ``terminate``) and ``restart(nlp, state) ->
state``; :func:`run` then runs the
restarts through the same driver (:class:`Restarting`).

:func:`iterate` is the driver: one ``lax.while_loop`` of ``step`` until ``terminate``
(or, resumable, until ``state.it`` reaches ``limit``). The single solve
(:mod:`jtraj.solver.core`) runs each method with it, and the batch driver
(:mod:`jtraj.solver.lanes`) advances its vmapped lanes with the same ``step`` and
``terminate``, so that a new method is its five functions, not a new loop.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array


def iterate(method, nlp, state, limit=None):
    """``method.step`` from ``state`` until ``method.terminate``, or until ``state.it``
    reaches ``limit`` (a traced bound: a segment of a resumable run). One
    ``lax.while_loop``; under ``vmap`` a finished member waits for the others."""
    nlp = method.enter(nlp, state)

    def cond(s):
        going = ~method.terminate(nlp, s)
        return going if limit is None else going & (s.it < limit)

    return jax.lax.while_loop(cond, lambda s: method.step(nlp, s), state)


def run(method, nlp, state):
    """``method`` from ``state`` to its end, restarts included (:class:`Restarting`)
    where the method has them."""
    if not method.restarts:
        return iterate(method, nlp, state)
    return iterate(Restarting(method), nlp, Runs(state=state, runs=jnp.asarray(0))).state


class Runs(NamedTuple):
    """The state of :class:`Restarting`: the inner method's state and the runs so far."""

    state: Any
    #: runs so far (the first, then the restarts)
    runs: Array


class Restarting:
    """A method whose step is a whole run of ``method`` (:func:`iterate`), restarted
    first (``method.restart``) after the first run; it ends when a run needs no
    restart (``method.needs_restart``, which counts the restarts left: bounded). One
    copy of the inner loop is compiled whatever the number of restarts."""

    def __init__(self, method):
        self.method = method

    def enter(self, nlp, c: Runs):
        return nlp

    def step(self, nlp, c: Runs) -> Runs:
        # a real branch for one problem; under vmap both sides run on the first pass
        # (the restart is a no-op where it is not needed)
        s = jax.lax.cond(c.runs > 0, lambda t: self.method.restart(nlp, t), lambda t: t, c.state)
        return Runs(state=iterate(self.method, nlp, s), runs=c.runs + 1)

    def terminate(self, nlp, c: Runs) -> Array:
        return ~((c.runs == 0) | self.method.needs_restart(nlp, c.state))
