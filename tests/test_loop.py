"""The methods' protocol and its one driver (:mod:`jtraj.solver.loop`), on a small method
of the test's own (Newton's iteration for a square root, with an iteration cap and
restarts), against the same iteration written as a plain Python loop:

* ``iterate`` stops where ``terminate`` says, at the cap at the latest;
* a run in segments (``limit``) ends where one run ends, to the last bit;
* under ``vmap`` each member takes its own iterations;
* ``run`` restarts a run that ended uncertified, at most as often as the method allows.

The solver's own methods run through the same driver in every solve (test_solver.py,
test_ipm.py); the lowered programs are those of the loops the driver replaced
(``benchmarks/lowered_programs.py``).
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtraj.solver import loop


class State(NamedTuple):
    x: jax.Array
    it: jax.Array
    cap: jax.Array  # this run's iteration budget (raised by a restart)
    restarts: jax.Array


class Sqrt:
    """x <- (x + a / x) / 2 until |x^2 - a| <= tol a or ``cap`` iterations; a restart
    (at most ``max_restarts``) starts again from x = a with ``more`` iterations."""

    def __init__(self, a, tol, max_restarts=0, more=3):
        self.a, self.tol, self.max_restarts, self.more = a, tol, max_restarts, more

    restarts = True

    def init(self, nlp, x0, cap):
        return State(x=jnp.asarray(x0, float), it=jnp.asarray(0), cap=jnp.asarray(cap), restarts=jnp.asarray(0))

    def enter(self, nlp, s):
        return nlp

    def converged(self, s):
        return jnp.abs(s.x * s.x - self.a) <= self.tol * self.a

    def step(self, nlp, s):
        return s._replace(x=0.5 * (s.x + self.a / s.x), it=s.it + 1)

    def terminate(self, nlp, s):
        return self.converged(s) | (s.it >= s.cap)

    def needs_restart(self, nlp, s):
        return ~self.converged(s) & (s.restarts < self.max_restarts)

    def restart(self, nlp, s):
        return s._replace(x=jnp.asarray(self.a, float) * 1.0, cap=s.it + self.more, restarts=s.restarts + 1)


def reference(a, x0, tol, cap, max_restarts=0, more=3):
    """The same iteration as a Python loop: (x, iterations, restarts)."""
    x, it, restarts = float(x0), 0, 0
    while True:
        while not abs(x * x - a) <= tol * a and it < cap:
            x, it = 0.5 * (x + a / x), it + 1
        if abs(x * x - a) <= tol * a or restarts >= max_restarts:
            return x, it, restarts
        x, cap, restarts = float(a), it + more, restarts + 1


@pytest.mark.parametrize("a, x0, cap", [(2.0, 1.0, 50), (1e6, 1.0, 50), (1e6, 1.0, 4), (9.0, 3.0, 50)])
def test_iterate_stops_where_terminate_says(a, x0, cap):
    method = Sqrt(a, 1e-14)
    out = jax.jit(lambda x: loop.iterate(method, None, method.init(None, x, cap)))(x0)
    x, it, _ = reference(a, x0, 1e-14, cap)
    assert int(out.it) == it <= cap
    assert float(out.x) == pytest.approx(x, rel=1e-15)
    if it < cap:
        assert abs(float(out.x) ** 2 - a) <= 1e-14 * a
    if x0 * x0 == a:  # a converged start takes no iteration
        assert int(out.it) == 0


def test_segments_end_where_one_run_ends():
    method = Sqrt(1e6, 1e-14)
    start = method.init(None, 1.0, 50)
    whole = jax.jit(lambda s: loop.iterate(method, None, s))(start)
    segment = jax.jit(lambda s, limit: loop.iterate(method, None, s, limit))
    s, segments = start, 0
    while not bool(method.terminate(None, s)):
        s = segment(s, s.it + 3)
        segments += 1
        assert int(s.it) <= 3 * segments
    assert segments == -(-int(whole.it) // 3)
    assert int(s.it) == int(whole.it) and float(s.x) == float(whole.x)


def test_vmapped_members_take_their_own_iterations():
    a = jnp.asarray([2.0, 1e6, 9.0, 1e-4])
    out = jax.jit(jax.vmap(lambda a_: loop.iterate(Sqrt(a_, 1e-14), None, Sqrt(a_, 1e-14).init(None, 1.0, 60))))(a)
    for i, ai in enumerate(np.asarray(a)):
        x, it, _ = reference(float(ai), 1.0, 1e-14, 60)
        assert int(out.it[i]) == it
        assert float(out.x[i]) == pytest.approx(x, rel=1e-15)
    assert len(set(np.asarray(out.it).tolist())) > 1


@pytest.mark.parametrize("max_restarts, cap", [(0, 3), (1, 3), (2, 3), (5, 3), (2, 50)])
def test_run_restarts_an_uncertified_run_a_bounded_number_of_times(max_restarts, cap):
    a = 1e6  # from x0 = 1 about 14 iterations; each restart adds 3 from x = a
    method = Sqrt(a, 1e-14, max_restarts=max_restarts)
    out = jax.jit(lambda x: loop.run(method, None, method.init(None, x, cap)))(1.0)
    x, it, restarts = reference(a, 1.0, 1e-14, cap, max_restarts)
    assert int(out.restarts) == restarts <= max_restarts
    assert int(out.it) == it
    assert float(out.x) == pytest.approx(x, rel=1e-15)
    # one loop over runs: as many runs as restarts + 1, each through iterate
    runs = jax.jit(lambda s: loop.iterate(loop.Restarting(method), None, loop.Runs(state=s, runs=jnp.asarray(0))))(
        method.init(None, 1.0, cap))
    assert int(runs.runs) == restarts + 1


def test_run_without_restarts_is_one_iterate():
    class NoRestarts(Sqrt):
        restarts = False

    method = NoRestarts(2.0, 1e-14)
    start = method.init(None, 1.0, 50)
    assert jax.make_jaxpr(lambda s: loop.run(method, None, s))(start).eqns[0].primitive.name == "while"
    assert len(jax.make_jaxpr(lambda s: loop.run(method, None, s))(start).eqns) == 1
