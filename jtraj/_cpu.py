"""Pinning a JAX process to one CPU core.

XLA's CPU client sizes its thread pool by the CPUs the process may run on. The solver's
operations are small, so handing them between threads costs more than it gains: a
single ``jtraj.solve`` (serial3, N = 20, warm, 2-core machine) took a median 171-198 ms
in a process pinned to one core against 282-406 ms unpinned, with the same iterates.
Batches gain from several cores only through several processes (one per core, see
:mod:`jtraj.dataset._local`).

The same iterates, but not the same last bits: at N = 20 XLA splits some of the
solver's larger products over its threads, which changes their rounding (serial3
dataset pairs: trajectories 1e-12 apart, relative, between a pinned process and one on 2
cores). Every process that solves dataset chunks therefore runs on one CPU
(:mod:`jtraj.dataset.build`), so that a dataset's values do not depend on where its
chunks were solved.
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


#: lock files of the CPUs this process claimed (held open, hence locked, until it exits)
_claimed: list[int] = []


def claim_one_cpu() -> int | None:
    """Pin this process to a CPU that no other live process has claimed on this machine,
    and return it.

    For worker processes that no one hands an index (Ray's): each takes an exclusive
    ``flock`` on a lock file per CPU in the temporary directory and keeps the first it
    gets until it exits (the kernel releases the lock then, also after a ``kill -9``), so
    that concurrent workers on one machine spread over its cores. Where every CPU is
    claimed it falls back to :func:`pin_to_one_cpu` by process id. A process already
    restricted to one CPU keeps it (a local worker, or a second call). Returns None where
    affinity is not supported (not Linux).
    """
    if not hasattr(os, "sched_setaffinity"):
        return None
    cpus = os.sched_getaffinity(0)
    if len(cpus) == 1:
        return next(iter(cpus))
    import fcntl
    import tempfile

    folder = os.path.join(tempfile.gettempdir(), f"jtraj-cpus-{os.getuid()}")
    os.makedirs(folder, exist_ok=True)
    for cpu in sorted(cpus):
        fd = os.open(os.path.join(folder, f"cpu-{cpu}.lock"), os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        _claimed.append(fd)
        os.sched_setaffinity(0, {cpu})
        return cpu
    return pin_to_one_cpu()
