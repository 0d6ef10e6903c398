"""Pinning a JAX process to one CPU core.

XLA's CPU client sizes its thread pool by the CPUs the process may run on. The solver's
operations are small, so handing them between threads costs more than it gains: a
single ``jtraj.solve`` (serial3, N = 20, warm, 2-core machine) took a median 171-198 ms
in a process pinned to one core against 282-406 ms unpinned, with the same iterates.
Batches gain from several cores only through several processes (one per core, see
:mod:`jtraj.dataset._local`).
"""

from __future__ import annotations

import os


def pin_to_one_cpu(index: int | None = None) -> int | None:
    """Restrict this process to one CPU of its current affinity mask and return it.

    Call it before JAX's first computation in the process (the thread pool is made
    then); later it only moves the process. ``index`` picks the CPU among the allowed
    ones (modulo their number); by default the process id does, so that concurrent
    processes spread over the cores. Returns None where affinity is not supported
    (not Linux).
    """
    if not hasattr(os, "sched_setaffinity"):
        return None
    cpus = sorted(os.sched_getaffinity(0))
    cpu = cpus[(os.getpid() if index is None else index) % len(cpus)]
    os.sched_setaffinity(0, {cpu})
    return cpu
