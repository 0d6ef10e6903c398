"""Implicit rank promotion (an (n,) array meeting an (N, n) one without a named axis) in
the solver's program: traced, not compiled, under ``jax_numpy_rank_promotion="warn"``,
every jtraj function where a promotion happens is collected; there must be none. The
whole suite runs with promotions raising (conftest.py); this test names every place at
once, where a raising test stops at the first."""

import os
import traceback
import warnings

import jax
import numpy as np

import jtraj
from jtraj import _testing
from jtraj.transcription import Transcription

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(jtraj.__file__)))

def _promotions(fn, *args):
    """The (file, function) of every jtraj frame where tracing ``fn(*args)`` promotes a
    rank."""
    found = set()

    def show(message, category, filename, lineno, file=None, line=None):
        if "rank promotion" not in str(message):
            return
        own = [f for f in traceback.extract_stack()
               if f.filename.startswith(os.path.join(ROOT, "jtraj")) and "_testing" not in f.filename]
        if own:
            found.add((os.path.relpath(own[-1].filename, ROOT), own[-1].name))

    with warnings.catch_warnings(), jax.numpy_rank_promotion("warn"):
        warnings.simplefilter("always")
        warnings.showwarning = show
        jax.eval_shape(fn, *args)
    return found


def test_the_solvers_program_promotes_no_new_rank():
    robot = jtraj.robots.get("serial3")
    problem = jtraj.Problem(robot, np.array([0.2, -0.3, 0.4]), np.array([0.5, -0.1, 0.2]), N=8,
                            weights=jtraj.Weights(time=1.0, energy=0.1))
    opts = _testing.resolve_method(None, "decoupled", robot)
    init = _testing.placeholder_init(problem.N, Transcription("decoupled").control_dim(problem))
    found = _promotions(lambda p, i: _testing.solve_jit.__wrapped__(p, opts, "decoupled", i, np.bool_(False),
                                                                    np.bool_(True)), problem, init)
    assert sorted(found) == [], "write the broadcast out (x[None, :], ...)"
