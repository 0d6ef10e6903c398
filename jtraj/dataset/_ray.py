"""Ray backend: chunks are solved by Ray tasks, written by the driver.

Each task runs :func:`jtraj.dataset.build.compute_chunk` (a pure function of the spec and
the chunk index) in a Ray worker process and returns the chunk's numpy arrays; only the
driver touches the store, so the cluster needs no shared file system. At most
``2 x CPUs`` chunks are in flight, which bounds the driver's memory. Results are written
as they arrive; a chunk's file name fixes its place, so arrival order does not matter and
the dataset equals a single-process run's on machines of the same kind.

Workers must be able to import ``jtraj`` (same environment, or a Ray ``runtime_env``).
"""

from __future__ import annotations

import os
import socket


def _probe(address: str, timeout: float = 5.0) -> None:
    target = address.split("://", 1)[-1]
    host, sep, port = target.rpartition(":")
    if not sep or not port.isdigit():
        raise ValueError(f"--ray must be 'auto', 'local', 'local:K' or HOST:PORT (or ray://HOST:PORT), "
                         f"got {address!r}")
    try:
        with socket.create_connection((host or "127.0.0.1", int(port)), timeout=timeout):
            pass
    except OSError as err:
        raise ValueError(f"the Ray cluster at {address!r} does not answer ({err}); "
                         f"start it with 'ray start --head' or check the address") from None


class RayBackend:
    """``run(spec, chunks, finish)``: each chunk ``c`` is ``task(spec, c)`` in a Ray task
    (one CPU, retried), returning ``(c, arrays)``; ``task`` is given by the caller
    (:func:`jtraj.dataset.build.worker_task`)."""

    def __init__(self, started_here: bool, task):
        import ray

        self.ray = ray
        self.started_here = started_here
        self.cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        self.remote = ray.remote(num_cpus=1, max_retries=3)(task)

    def run(self, spec, chunks, finish):
        ray = self.ray
        spec_ref = ray.put(spec)
        todo = list(chunks)
        limit = 2 * self.cpus
        pending = []
        while todo or pending:
            while todo and len(pending) < limit:
                pending.append(self.remote.remote(spec_ref, todo.pop(0)))
            ready, pending = ray.wait(pending, num_returns=1)
            c, arrays = ray.get(ready[0])
            finish(c, arrays)

    def close(self):
        if self.started_here:
            self.ray.shutdown()


def connect(address: str, task) -> RayBackend:
    """Connect to (or start) Ray, for chunks solved by ``task`` (see :class:`RayBackend`); a
    clear ``ValueError`` when that is impossible."""
    try:
        import ray
    except ImportError:
        raise ValueError("--ray needs the 'ray' package: pip install 'jtraj[ray]' (or pip install ray)") from None
    address = str(address).strip()
    kwargs = dict(ignore_reinit_error=True, log_to_driver=False, include_dashboard=False)
    env = {"env_vars": {"JAX_ENABLE_X64": "1"}}
    if ray.is_initialized():
        return RayBackend(started_here=False, task=task)
    if address.startswith("local"):
        _, _, k = address.partition(":")
        if k and not k.isdigit():
            raise ValueError(f"--ray local:K needs an integer K, got {address!r}")
        num = int(k) if k else (os.cpu_count() or 1)
        ray.init(num_cpus=num, runtime_env=env, **kwargs)
        return RayBackend(started_here=True, task=task)
    if address != "auto":
        _probe(address)
    try:
        if address.startswith("ray://"):
            ray.init(address=address, runtime_env=env, ignore_reinit_error=True, log_to_driver=False)
        else:
            ray.init(address=address, runtime_env=env, **kwargs)
    except (ConnectionError, RuntimeError, ValueError) as err:
        raise ValueError(f"cannot connect to the Ray cluster at {address!r}: {err}") from None
    return RayBackend(started_here=True, task=task)
