"""A fast stand-in for ``jtraj.solve_batch`` (tests of storage, resume and scale-out).

:func:`fake_solve_batch` has the signature and output fields of ``solve_batch`` but no
optimisation: a straight-line trajectory with constant period, deterministic in the
inputs, with some pairs flagged as failures (``status`` 1 when ``sum(q_goal) > 1``).
``JTRAJ_FAKE_SOLVER_DELAY`` (seconds per call) makes it slow enough to be killed mid-run;
``JTRAJ_FAKE_SOLVER_PAIR_DELAY`` (seconds per pair) adds a delay per pair, reported through
``progress`` as ``solve_batch`` does.
Use it with ``make_spec(..., solver="jtraj.dataset.testing:fake_solve_batch")`` or the
hidden CLI option ``--solver``.
"""

from __future__ import annotations

import os
import time

import numpy as np


def fake_solve_batch(robot, q_start, q_goal, *, N=20, weights=None, solver=None, progress=None):
    delay = float(os.environ.get("JTRAJ_FAKE_SOLVER_DELAY", "0") or 0)
    if delay:
        time.sleep(delay)
    q0, q1 = np.asarray(q_start, float), np.asarray(q_goal, float)
    B, n = q0.shape
    pair_delay = float(os.environ.get("JTRAJ_FAKE_SOLVER_PAIR_DELAY", "0") or 0)
    for k in range(B):
        time.sleep(pair_delay)
        if progress is not None:
            progress(k + 1, B)
    s = np.linspace(0.0, 1.0, N + 1)
    q = q0[:, None] + (q1 - q0)[:, None] * s[None, :, None]
    h = np.full((B, N), 0.05) + 0.001 * np.abs(q1 - q0).sum(1, keepdims=True)
    qd = np.concatenate([np.zeros((B, 1, n)), np.diff(q, axis=1) / h[..., None]], axis=1)
    v = np.diff(qd, axis=1) / h[..., None]
    tau = np.sin(q[:, :-1]) + 0.1 * v
    bad = q1.sum(1) > 1.0
    status = np.where(bad, 1, 0).astype(np.int32)
    T = h.sum(1)
    energy = (h * (tau ** 2).sum(2)).sum(1)
    return {"q": q, "qd": qd, "v": v, "tau": tau, "h": h, "T": T, "cost": T + 0.1 * energy,
            "cost_terms": {"time": T, "energy": 0.1 * energy}, "energy": energy,
            "max_violation": {"overall": np.where(bad, 0.1, 0.0), "goal": np.zeros(B)},
            "converged": ~bad, "status": status, "iterations": np.full(B, 7, np.int32),
            "outer_iterations": np.full(B, 2, np.int32)}


def fake_solve_batch_cpus(robot, q_start, q_goal, *, N=20, weights=None, solver=None):
    """:func:`fake_solve_batch` whose ``iterations`` is the number of CPUs the solving
    process may run on (tests of where chunks are solved: one, for identical rounding)."""
    out = fake_solve_batch(robot, q_start, q_goal, N=N, weights=weights, solver=solver)
    out["iterations"] = np.full(len(out["T"]), len(os.sched_getaffinity(0)), np.int32)
    return out
