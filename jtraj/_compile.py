"""Per-function XLA compiler options that apply on the CPU backend only, and the
solver's (used by :mod:`jtraj.solver` and :mod:`jtraj.sensitivity`)."""

from __future__ import annotations

import functools
from typing import Any, Callable

import equinox as eqx
import jax
import numpy as np


@functools.lru_cache(maxsize=None)
def _accepted(name: str, value: Any) -> bool:
    """Whether this jaxlib's XLA CPU compiler takes the option ``name=value``. The CPU
    options below are XLA debug options, some of them experimental: they come and go
    between jaxlib releases, and an unknown one fails every compilation that names it.
    Checked once per process by compiling a scalar addition (a few milliseconds)."""
    try:
        jax.jit(lambda x: x + 1).lower(np.zeros((), np.float32)).compile({name: value})
    except Exception:  # noqa: BLE001 - any refusal means: do not pass this option
        return False
    return True


def supported_options(options: dict[str, Any]) -> dict[str, Any]:
    """The entries of ``options`` this XLA CPU compiler accepts (see :func:`_accepted`)."""
    return {k: v for k, v in options.items() if _accepted(k, v)}


def cpu_jit(options: dict[str, Any], **jit_kwargs) -> Callable[[Callable], Callable]:
    """A decorator like ``eqx.filter_jit`` that compiles with the XLA ``options`` when
    JAX's default backend is the CPU (checked at each call) and without them elsewhere,
    so that an accelerator never sees a CPU-only option (``xla_cpu_*``) or one its
    compiler refuses (XLA GPU requires ``xla_backend_optimization_level >= 2``). Options
    the installed XLA does not know are dropped (:func:`supported_options`).
    ``jit_kwargs`` (e.g. ``donate``) go to ``eqx.filter_jit`` on every backend."""

    def decorate(fn: Callable) -> Callable:
        other = eqx.filter_jit(fn, **jit_kwargs)

        @functools.lru_cache(maxsize=1)
        def on_cpu():
            return eqx.filter_jit(fn, compiler_options=supported_options(options), **jit_kwargs)

        @functools.wraps(fn)
        def call(*args, **kwargs):
            return (on_cpu() if jax.default_backend() == "cpu" else other)(*args, **kwargs)

        return call

    return decorate


# The solver's kernels are small, loop-heavy programs. Two XLA CPU options suit them:
# * the legacy loop emitters compile them a third faster and run them about 10 % faster
#   than the newer fusion emitters (serial3, N = 20, 64 pairs on one core: compile
#   67 -> 45 s, solve 5.4 -> 4.8 s, identical iterates; the CLI's first solve compiles in
#   19 instead of 25 s);
# * no YNNPACK library fusions (``xla_cpu_experimental_ynn_fusion_type`` empty; jaxlib
#   0.10 hands the dots and reductions to YNNPACK by default, whose per-call cost is
#   far above the work of these 3 x 3 to 20 x 20 operations: one Newton iteration of 8
#   serial3 lanes spent about a quarter of its time in 38 such calls; see the documentation's
#   "Performance and compilation" guide).
# XLA's default LLVM optimisation level stays: level 0 compiles the interior-point
# program (serial3, N = 20) in about 0.4x the time but runs it 2.4x slower, which only
# a process's first single solve takes (jtraj._tracecache.tiered); levels 1 to 3 run it
# alike and their compile times differ by less than a shared 2-core machine's noise
# (``benchmarks/bench_opt_level.py``, ``benchmarks/profile_compile.py --staged``).
SOLVER_XLA_OPTIONS = {"xla_cpu_use_fusion_emitters": False, "xla_cpu_experimental_ynn_fusion_type": ""}
solver_jit = cpu_jit(SOLVER_XLA_OPTIONS)



@functools.lru_cache(maxsize=None)
def nested_jit(fn: Callable) -> Callable:
    """A solver entry point decorated by :func:`cpu_jit` (through
    ``jtraj.solver.options.options_jit``) as a plain ``eqx.filter_jit`` of the function it
    wraps, for use inside another trace: XLA compiler options are for top-level programs
    only."""
    return eqx.filter_jit(fn.__wrapped__)
