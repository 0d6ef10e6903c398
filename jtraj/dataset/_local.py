"""Local multi-process backend: chunks solved by JAX worker processes pinned one per core.

A vmapped solver in one JAX process does not use several CPU cores well (XLA parallelises
inside operations, and the solver's are small). One process per core, each pinned to its
core, does: on 2 cores a 256-pair serial3 dataset took 142 s in one process and 93 s in
two workers. Pinning also fixes the rounding: XLA's CPU results depend in the last
bits on how many CPUs the solving process may use (:mod:`jtraj._cpu`), so chunks are
solved only in processes restricted to one CPU (these workers, Ray tasks that claim a
CPU, or this process where it runs on one CPU; see :func:`solves_here`), and a dataset
is the same wherever its chunks were solved. Workers are started with ``spawn`` (no forked JAX
state), die with the driver (``PR_SET_PDEATHSIG`` on Linux: a ``kill -9`` of the driver
leaves no solver running) and return each chunk's numpy arrays; only the driver writes
the store, as with Ray. One chunk per worker is in flight, so a kill loses at most that
(one chunk per worker).
"""

from __future__ import annotations

import os
import signal
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool


def available_cpus() -> int:
    """CPUs this process may run on (affinity-aware)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def default_workers() -> int:
    """One worker per available CPU; 1 (this process) when JAX's default backend is an
    accelerator (a GPU solves a whole chunk at once; workers would compete for it)."""
    import jax

    return available_cpus() if jax.default_backend() == "cpu" else 1


def solves_here() -> bool:
    """Whether this process solves a dataset's chunks as a pinned worker would: where
    JAX's default backend is an accelerator, or where this process may run on one CPU
    only (restricted before JAX started, e.g. under ``taskset -c 0``, for the rounding
    to match). Otherwise :func:`jtraj.dataset.build` hands even a single chunk to a
    worker process."""
    return default_workers() == 1


def init_worker(counter):
    """Process-pool initializer: die with the parent, pin to one CPU (the counter-th)."""
    try:  # die with the driver
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    with counter.get_lock():
        index = counter.value
        counter.value += 1
    from jtraj._cpu import pin_to_one_cpu

    pin_to_one_cpu(index)


def worker_pool(workers: int) -> ProcessPoolExecutor:
    """A pool of ``workers`` spawned processes set up by :func:`init_worker`."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    return ProcessPoolExecutor(workers, mp_context=ctx, initializer=init_worker, initargs=(ctx.Value("i", 0),))


class ProcessBackend:
    """``run(spec, chunks, finish)`` as :class:`jtraj.dataset._ray.RayBackend`: each chunk
    ``c`` is ``task(spec, c, *extra)`` in a worker process, returning ``(c, arrays)``. ``task`` is
    a module-level function (the pool sends it by name; the caller passes
    :func:`jtraj.dataset.build.worker_task`, so this backend imports nothing of the build)."""

    def __init__(self, workers: int, task, *extra):
        self.workers = workers
        self.task = task
        self.extra = extra  # more arguments of every task
        self.pool = worker_pool(workers)

    def run(self, spec, chunks, finish):
        todo = list(chunks)
        pending = set()
        while todo or pending:
            while todo and len(pending) < self.workers:
                pending.add(self.pool.submit(self.task, spec, todo.pop(0), *self.extra))
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in done:
                try:
                    c, arrays = fut.result()
                except BrokenProcessPool as err:
                    raise RuntimeError(
                        "a dataset worker process died before returning its chunk (finished chunks are "
                        "kept; re-run to resume). Workers are started with 'spawn': a script that calls "
                        "jtraj.dataset.build must do so under 'if __name__ == \"__main__\":', or pass "
                        "workers=1") from err
                finish(c, arrays)

    def close(self):
        self.pool.shutdown(wait=True, cancel_futures=True)
