"""IPOPT peer for any arm whose inverse dynamics is a CasADi function: the decoupled
(ALD) transcription of :mod:`.ipopt_peer`, generalised from serial3 to n joints with
position bounds (for spatial arms such as the Panda, dynamics from
:mod:`.casadi_rnea`). Independent of :mod:`jtraj`.

Problem (N intervals, decision variables v_k in R^n and h_k, k = 0..N-1; the arm
starts and ends at rest)::

    q_{k+1}  = q_k + h_k qd_k + h_k^2/2 v_k,   qd_{k+1} = qd_k + h_k v_k,   q_0 = q_start
    tau_k = ID(q_k, qd_k, v_k)
    J = sum_k h_k [w_time + tau_k^T U tau_k + w_kin qd_k^T qd_k],  U = w_energy diag(1/tau_max^2)
    |tau_k| <= tau_max, |v_k| <= qdd_max (k < N);  |qd_k| <= qd_max, q_min <= q_k <= q_max
    (k = 1..N);  h_min <= h_k <= h_max;  q_N = q_goal, qd_N = 0

which is jtraj's decoupled NLP for ``Weights(time=w_time, energy=w_energy,
kinetic=w_kin)`` (jtraj's ``U = energy diag(1/tau_max^2)``, ``Q = kinetic I``; the
state bounds apply from sample 1 on, the torque bound at the samples 0..N-1).
Optional ``jerk_max`` adds ``|v_{k+1} - v_k| <= jerk_max (h_k + h_{k+1}) / 2``
(k = 0..N-2): the change of acceleration between consecutive intervals over the time
between their midpoints. The formulation is the planar peer's "lifted" one (states
1..N are variables, the recursion is a set of equalities).

API: :class:`ArmSpec` (the robot: a serialised CasADi function and its limits),
:func:`solve_pair`, :func:`solve_many` (one process per core, NLP built once per
worker), :func:`cycloidal_init`.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .ipopt_peer import IPOPT_OPTIONS, SolveBatch


@dataclass(frozen=True)
class ArmSpec:
    """An arm for the peer: its inverse dynamics ``(q, qd, qdd) -> tau`` as a serialised
    CasADi function (picklable, so worker processes rebuild it) and its limits, tuples
    of n floats (``q_min``/``q_max`` may be infinite; ``jerk_max`` optional)."""

    dynamics: str
    n: int
    q_min: tuple
    q_max: tuple
    qd_max: tuple
    qdd_max: tuple
    tau_max: tuple
    h_min: float
    h_max: float
    jerk_max: tuple | None = None

    @staticmethod
    def make(dynamics: ca.Function, *, q_min, q_max, qd_max, qdd_max, tau_max, h_min, h_max,
             jerk_max=None) -> "ArmSpec":
        n = int(dynamics.size1_in(0))
        if [dynamics.size1_in(i) for i in range(3)] != [n] * 3 or dynamics.size1_out(0) != n:
            raise ValueError(f"dynamics must map (q, qd, qdd), each ({n},), to tau ({n},)")

        def vec(x, name, positive=True):
            arr = np.broadcast_to(np.asarray(x, float), (n,))
            if np.isnan(arr).any() or (positive and not (arr > 0).all()):
                raise ValueError(f"{name} must be {n} numbers{' > 0' if positive else ''}, got {arr.tolist()}")
            return tuple(float(a) for a in arr)

        lo, hi = vec(q_min, "q_min", False), vec(q_max, "q_max", False)
        if any(a >= b for a, b in zip(lo, hi)):
            raise ValueError(f"q_min must be < q_max, got {lo} and {hi}")
        if not 0 < h_min < h_max:
            raise ValueError(f"need 0 < h_min < h_max, got {h_min}, {h_max}")
        return ArmSpec(dynamics=dynamics.serialize(), n=n, q_min=lo, q_max=hi, qd_max=vec(qd_max, "qd_max"),
                       qdd_max=vec(qdd_max, "qdd_max"), tau_max=vec(tau_max, "tau_max"), h_min=float(h_min),
                       h_max=float(h_max), jerk_max=None if jerk_max is None else vec(jerk_max, "jerk_max"))

    def function(self) -> ca.Function:
        return ca.Function.deserialize(self.dynamics)


class _ArmPeer:
    """The built IPOPT solver of one (spec, N, weights)."""

    def __init__(self, spec: ArmSpec, N: int, weights: tuple[float, float, float]):
        self.spec, self.N, self.weights = spec, N, weights
        n = spec.n
        w_time, w_energy, w_kin = weights
        idf = spec.function()
        tau_max = np.asarray(spec.tau_max)
        U = ca.diag(ca.DM(w_energy / tau_max**2))
        v, h = ca.SX.sym("v", n, N), ca.SX.sym("h", N)
        Q, QD = ca.SX.sym("Q", n, N), ca.SX.sym("QD", n, N)  # states 1..N
        p = ca.SX.sym("p", 2 * n)  # [q_start; q_goal]
        q_start, q_goal = p[:n], p[n:]
        q, qd, f, g, lbg, ubg, taus = q_start, ca.SX.zeros(n), 0, [], [], [], []
        for k in range(N):
            tau = idf(q, qd, v[:, k])
            taus.append(tau)
            f += h[k] * (w_time + ca.bilin(U, tau, tau) + w_kin * ca.dot(qd, qd))
            g += [tau, Q[:, k] - (q + h[k] * qd + 0.5 * h[k] ** 2 * v[:, k]), QD[:, k] - (qd + h[k] * v[:, k])]
            lbg += [-tau_max, np.zeros(2 * n)]
            ubg += [tau_max, np.zeros(2 * n)]
            q, qd = Q[:, k], QD[:, k]
        g.append(Q[:, N - 1] - q_goal)
        lbg.append(np.zeros(n))
        ubg.append(np.zeros(n))
        if spec.jerk_max is not None:
            jm = ca.DM(spec.jerk_max)
            for k in range(N - 1):
                dv, dt = v[:, k + 1] - v[:, k], 0.5 * (h[k] + h[k + 1])
                g += [dv - jm * dt, -dv - jm * dt]
                lbg += [np.full(2 * n, -np.inf)]
                ubg += [np.zeros(2 * n)]
        x = ca.vertcat(ca.vec(v), h, ca.vec(Q), ca.vec(QD))
        self.lbg, self.ubg = np.concatenate(lbg), np.concatenate(ubg)
        qdd_max, qd_max = np.asarray(spec.qdd_max), np.asarray(spec.qd_max)
        q_lo, q_hi = np.tile(spec.q_min, N), np.tile(spec.q_max, N)
        qd_hi = np.concatenate([np.tile(qd_max, N - 1), np.zeros(n)])  # qd_N = 0
        self.lbx = np.concatenate([np.tile(-qdd_max, N), np.full(N, spec.h_min), q_lo, -qd_hi])
        self.ubx = np.concatenate([np.tile(qdd_max, N), np.full(N, spec.h_max), q_hi, qd_hi])
        self.solver = ca.nlpsol("S", "ipopt", {"x": x, "p": p, "f": f, "g": ca.vertcat(*g)}, dict(IPOPT_OPTIONS))
        # the trajectory of (v, h), recomputed by the recursion (not read from the lifted states)
        xvh = ca.vertcat(ca.vec(v), h)
        q, qd, qs, qds, taus2, cost = q_start, ca.SX.zeros(n), [q_start], [ca.SX.zeros(n)], [], 0
        for k in range(N):
            tau = idf(q, qd, v[:, k])
            taus2.append(tau)
            cost += h[k] * (w_time + ca.bilin(U, tau, tau) + w_kin * ca.dot(qd, qd))
            q, qd = q + h[k] * qd + 0.5 * h[k] ** 2 * v[:, k], qd + h[k] * v[:, k]
            qs.append(q)
            qds.append(qd)
        self.traj = ca.Function("traj", [xvh, p], [ca.horzcat(*qs).T, ca.horzcat(*qds).T, ca.horzcat(*taus2).T, cost])

    def pack(self, v, h, p) -> np.ndarray:
        """Starting point from (v, h), with the states the recursion gives."""
        n, N = self.spec.n, self.N
        xvh = np.concatenate([np.asarray(v, float).reshape(N, n).reshape(-1), np.asarray(h, float).reshape(N)])
        q, qd, _, _ = self.traj(xvh, p)
        return np.concatenate([xvh, np.asarray(q)[1:].reshape(-1), np.asarray(qd)[1:].reshape(-1)])

    def solve(self, q_start, q_goal, init=None) -> dict:
        n, N = self.spec.n, self.N
        q_start = np.asarray(q_start, float).reshape(n)
        q_goal = np.asarray(q_goal, float).reshape(n)
        v0, h0 = cycloidal_init(self.spec, q_start, q_goal, N) if init is None else init
        p = np.concatenate([q_start, q_goal])
        x0 = self.pack(v0, h0, p)
        t0 = time.perf_counter()
        sol = self.solver(x0=x0, p=p, lbx=self.lbx, ubx=self.ubx, lbg=self.lbg, ubg=self.ubg)
        seconds = time.perf_counter() - t0
        st = self.solver.stats()
        x = np.asarray(sol["x"]).ravel()[:(n + 1) * N]
        q, qd, tau, cost = self.traj(x, p)
        status = str(st.get("return_status", "unknown"))
        h = x[n * N:]
        return dict(v=x[:n * N].reshape(N, n), h=h, q=np.asarray(q), qd=np.asarray(qd), tau=np.asarray(tau),
                    T=float(h.sum()), cost=float(cost),
                    success=status in ("Solve_Succeeded", "Solved_To_Acceptable_Level"),
                    strict_success=status == "Solve_Succeeded", status=status,
                    iterations=int(st.get("iter_count", -1)), seconds=seconds,
                    ipopt_seconds=float(st.get("t_wall_total", float("nan"))), q_start=q_start, q_goal=q_goal)


def cycloidal_init(spec: ArmSpec, q_start, q_goal, N: int) -> tuple[np.ndarray, np.ndarray]:
    """The kinematic cycloid (jtraj's ``"cycloidal"`` guess): ``T = max_j max(2|dq|/qd_max,
    sqrt(2 pi |dq|/qdd_max), (4 pi^2 |dq|/qddd_max)^(1/3))`` clipped to [N h_min, N h_max],
    ``h_k = T/N``, ``v_k`` the cycloid's acceleration at the interval midpoints."""
    dq = np.asarray(q_goal, float) - np.asarray(q_start, float)
    a = np.abs(dq)
    T = np.max(np.maximum(2 * a / np.asarray(spec.qd_max), np.sqrt(2 * math.pi * a / np.asarray(spec.qdd_max))))
    if spec.jerk_max is not None:
        T = max(T, np.max(np.cbrt(4 * math.pi**2 * a / np.asarray(spec.jerk_max))))
    T = float(min(max(T, N * spec.h_min), N * spec.h_max))
    t = (np.arange(N) + 0.5) * T / N
    return dq[None, :] * (2 * math.pi / T**2) * np.sin(2 * math.pi * t / T)[:, None], np.full(N, T / N)


_CACHE: dict[tuple, _ArmPeer] = {}


def _key(spec: ArmSpec, N, weights) -> tuple:
    weights = tuple(float(w) for w in weights)
    if len(weights) != 3 or min(weights) < 0:
        raise ValueError(f"weights must be (w_time, w_energy, w_kin) >= 0, got {weights}")
    if int(N) != N or N < 2:
        raise ValueError(f"N must be an integer >= 2, got {N}")
    return spec, int(N), weights


def get_peer(spec: ArmSpec, N: int = 40, weights=(1.0, 0.1, 0.0)) -> _ArmPeer:
    """The cached built solver for (spec, N, weights) (built on first use in a process)."""
    key = _key(spec, N, weights)
    if key not in _CACHE:
        _CACHE[key] = _ArmPeer(*key)
    return _CACHE[key]


def solve_pair(spec: ArmSpec, q_start, q_goal, N: int = 40, weights=(1.0, 0.1, 0.0), init=None) -> dict:
    """One rest-to-rest move with IPOPT. Returns the dict of :mod:`.ipopt_peer`'s
    ``solve_pair``: v (N, n), h (N,), q/qd (N+1, n), tau (N, n), T, cost, success,
    strict_success, status, iterations, seconds, ipopt_seconds, q_start, q_goal."""
    return get_peer(spec, N, weights).solve(q_start, q_goal, init)


_WORKER: tuple | None = None


def _worker_init(key, barrier):
    global _WORKER
    _WORKER = key
    get_peer(*key)
    if barrier is not None:
        barrier.wait(timeout=900)


def _worker_solve(job):
    q_start, q_goal, init = job
    return get_peer(*_WORKER).solve(q_start, q_goal, init)


def solve_many(spec: ArmSpec, q_starts, q_goals, *, N: int = 40, weights=(1.0, 0.1, 0.0), inits=None,
               processes: int | None = None, start_method: str = "spawn") -> SolveBatch:
    """Solve many pairs on ``processes`` workers (default all cores), each worker
    building the NLP once; ``wall_seconds`` starts after every worker has built it (as
    :func:`.ipopt_peer.solve_many`). One thread per worker."""
    q_starts = np.asarray(q_starts, float).reshape(-1, spec.n)
    q_goals = np.asarray(q_goals, float).reshape(-1, spec.n)
    if q_starts.shape != q_goals.shape:
        raise ValueError(f"q_starts {q_starts.shape} and q_goals {q_goals.shape} differ")
    inits = [None] * len(q_starts) if inits is None else list(inits)
    if len(inits) != len(q_starts):
        raise ValueError(f"inits has {len(inits)} entries for {len(q_starts)} pairs")
    key = _key(spec, N, weights)
    processes = max(1, min(int(processes or os.cpu_count() or 1), max(len(q_starts), 1)))
    jobs = list(zip(q_starts, q_goals, inits))
    batch = SolveBatch()
    batch.processes = processes
    if processes == 1:
        t0 = time.perf_counter()
        peer = get_peer(*key)
        batch.setup_seconds = time.perf_counter() - t0
        t0 = time.perf_counter()
        batch.extend(peer.solve(a, b, i) for a, b, i in jobs)
        batch.wall_seconds = time.perf_counter() - t0
        return batch
    ctx = mp.get_context(start_method)
    env_keys = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    saved = {k: os.environ.get(k) for k in env_keys}
    try:
        os.environ.update({k: "1" for k in env_keys})
        t0 = time.perf_counter()
        barrier = ctx.Barrier(processes + 1)
        with ctx.Pool(processes, initializer=_worker_init, initargs=(key, barrier)) as pool:
            barrier.wait(timeout=900)
            t1 = time.perf_counter()
            batch.extend(pool.map(_worker_solve, jobs, chunksize=1))
            batch.wall_seconds = time.perf_counter() - t1
            batch.setup_seconds = t1 - t0
    finally:
        for k, val in saved.items():
            if val is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = val
    return batch
