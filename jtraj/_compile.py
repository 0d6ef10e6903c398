"""Per-function XLA compiler options that apply on the CPU backend only, and the
solver's (used by :mod:`jtraj.solver` and :mod:`jtraj.sensitivity`)."""

from __future__ import annotations

import functools
from typing import Any, Callable

import equinox as eqx
import jax


def cpu_jit(options: dict[str, Any], **jit_kwargs) -> Callable[[Callable], Callable]:
    """A decorator like ``eqx.filter_jit`` that compiles with the XLA ``options`` when
    JAX's default backend is the CPU (checked at each call) and without them elsewhere,
    so that an accelerator never sees a CPU-only option (``xla_cpu_*``) or one its
    compiler refuses (XLA GPU requires ``xla_backend_optimization_level >= 2``).
    ``jit_kwargs`` (e.g. ``donate``) go to ``eqx.filter_jit`` on every backend."""

    def decorate(fn: Callable) -> Callable:
        on_cpu = eqx.filter_jit(fn, compiler_options=options, **jit_kwargs)
        other = eqx.filter_jit(fn, **jit_kwargs)

        @functools.wraps(fn)
        def call(*args, **kwargs):
            return (on_cpu if jax.default_backend() == "cpu" else other)(*args, **kwargs)

        return call

    return decorate


# The solver's kernels are small, loop-heavy programs; XLA CPU's legacy loop emitters
# compile them a third faster and run them about 10 % faster than its newer fusion
# emitters (serial3, N = 20, 64 pairs on one core: compile 67 -> 45 s, solve 5.4 -> 4.8 s,
# identical iterates; the CLI's first solve compiles in 19 instead of 25 s).
SOLVER_XLA_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
solver_jit = cpu_jit(SOLVER_XLA_OPTIONS)
