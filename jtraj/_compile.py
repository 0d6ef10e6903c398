"""Per-function XLA compiler options that apply on the CPU backend only."""

from __future__ import annotations

import functools
from typing import Any, Callable

import equinox as eqx
import jax


def cpu_jit(options: dict[str, Any]) -> Callable[[Callable], Callable]:
    """A decorator like ``eqx.filter_jit`` that compiles with the XLA ``options`` when
    JAX's default backend is the CPU (checked at each call) and without them elsewhere,
    so that an accelerator never sees a CPU-only option (``xla_cpu_*``) or one its
    compiler refuses (XLA GPU requires ``xla_backend_optimization_level >= 2``)."""

    def decorate(fn: Callable) -> Callable:
        on_cpu = eqx.filter_jit(fn, compiler_options=options)
        other = eqx.filter_jit(fn)

        @functools.wraps(fn)
        def call(*args, **kwargs):
            return (on_cpu if jax.default_backend() == "cpu" else other)(*args, **kwargs)

        return call

    return decorate
