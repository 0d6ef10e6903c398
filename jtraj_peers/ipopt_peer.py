"""IPOPT peer: the canonical ``serial3`` decoupled (ALD) transcription in CasADi + IPOPT.

This is an *independent* reference implementation of the problem jtraj solves in JAX;
it imports nothing from :mod:`jtraj`. The inverse dynamics are written here in CasADi
SX from the Lagrangian (kinetic energy -> mass matrix by ``hessian``, Coriolis terms by
``jacobian``), not from the JAX code.

Problem (N intervals, decision variables v_k in R^3 and h_k, k = 0..N-1)::

    q_{k+1}  = q_k + h_k qd_k + h_k^2/2 v_k,   qd_{k+1} = qd_k + h_k v_k,
    q_0 = q_start, qd_0 = 0,   tau_k = ID(q_k, qd_k, v_k)
    J = sum_k h_k [w_time + tau_k^T U tau_k + w_kin qd_k^T qd_k],  U = w_energy diag(1/tau_max^2)
    |tau_k| <= tau_max, |v_k| <= qdd_max (k < N), |qd_k| <= qd_max (k = 1..N),
    h_min <= h_k <= h_max,  q_N = q_goal,  qd_N = 0.

Two CasADi formulations of this same transcription (same unknowns v, h, same optimum):

* ``"lifted"`` (default): the states q_k, qd_k (k = 1..N) are extra NLP variables and
  the recursion enters as equality constraints (multiple-shooting style), so IPOPT sees
  sparse Jacobians and Hessians of short expressions. This is how CasADi users build
  such problems, and the fair peer: on 16 benchmark pairs it took a median 0.22 s
  (67 iterations, 3.4 ms each) against 0.97 s for the condensed form.
* ``"condensed"``: the states are eliminated (single shooting): 4N variables, but dense
  derivatives of deep SX graphs (about 15 ms per IPOPT iteration at N = 20).

The NLP is built **once** per settings ``(N, weights, masses, h_max, formulation)`` with
the start and goal as CasADi parameters and cached per process (:data:`_CACHE`).

API
---
``solve_pair(q_start, q_goal, N=20, weights=(1, 0.1, 0), init=None, masses=None)``
    -> dict(v (N,3), h (N,), q (N+1,3), qd (N+1,3), tau (N,3), T, cost, success,
    strict_success, status, iterations, seconds, ipopt_seconds)

``success`` is True when IPOPT's ``return_status`` is ``Solve_Succeeded`` **or**
``Solved_To_Acceptable_Level``; ``strict_success`` only for ``Solve_Succeeded``.
``seconds`` is the wall time of the solver call alone (not the build, not the initial
guess, not the post-processing); ``ipopt_seconds`` is IPOPT's own ``t_wall_total``.

``solve_many(q_starts, q_goals, *, processes=None, **kw)`` -> :class:`SolveBatch`
(a ``list`` of the per-pair dicts with ``wall_seconds`` for the whole set on all
workers, ``setup_seconds`` for starting the pool and building the NLP in every
worker, and ``processes``).
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import time
from typing import Sequence

import casadi as ca
import numpy as np

from .pairs import benchmark_pairs  # noqa: F401  (re-exported: the family IPOPT is run on)

# ---------------------------------------------------------------- the serial3 robot
LENGTHS = (1.0, 0.8, 0.45)  # m
MASSES = (10.0, 8.0, 4.0)  # kg
INERTIAS = (9.23, 7.5, 5.21)  # kg m^2, about each link's centre of mass
COM = tuple(l / 2 for l in LENGTHS)  # centre of mass at mid-link
TAU_MAX = (40.0, 25.0, 20.0)  # N m
QD_MAX = 2.0  # rad/s
QDD_MAX = 3.0  # rad/s^2
H_MIN, H_MAX = 0.005, 0.1  # s
CANONICAL_WEIGHTS = (1.0, 0.1, 0.0)  # (w_time, w_energy, w_kin)
NDOF = 3

IPOPT_OPTIONS = {
    "ipopt.print_level": 0,
    "print_time": False,
    "ipopt.sb": "yes",  # no banner
    "ipopt.tol": 1e-8,
    "ipopt.constr_viol_tol": 1e-8,
    "ipopt.max_iter": 3000,
    "ipopt.linear_solver": "mumps",
    "ipopt.hessian_approximation": "exact",
}


def inverse_dynamics_function(masses: Sequence[float] = MASSES) -> ca.Function:
    """CasADi ``Function('id', [q, qd, qdd], [tau])`` for serial3 (horizontal plane).

    Lagrangian: T = 1/2 sum m_i |v_ci|^2 + 1/2 sum I_i omega_i^2 with omega_i = qd_1+..+qd_i;
    tau = M(q) qdd + (d/dq dT/dqd) qd - dT/dq, M = d^2T/dqd^2. No gravity, no friction.
    """
    q, qd, qdd = ca.SX.sym("q", NDOF), ca.SX.sym("qd", NDOF), ca.SX.sym("qdd", NDOF)
    phi = ca.cumsum(q)
    joint = ca.SX.zeros(2)  # position of joint i
    coms = []
    for i in range(NDOF):
        e = ca.vertcat(ca.cos(phi[i]), ca.sin(phi[i]))
        coms.append(joint + COM[i] * e)
        joint = joint + LENGTHS[i] * e
    omega = ca.cumsum(qd)
    kin = 0
    for i in range(NDOF):
        vc = ca.jtimes(coms[i], q, qd)  # d/dt of the centre of mass
        kin += 0.5 * masses[i] * ca.dot(vc, vc) + 0.5 * INERTIAS[i] * omega[i] ** 2
    M, dT_dqd = ca.hessian(kin, qd)
    tau = M @ qdd + ca.jacobian(dT_dqd, q) @ qd - ca.gradient(kin, q)
    return ca.Function("id", [q, qd, qdd], [ca.simplify(tau)], ["q", "qd", "qdd"], ["tau"])


# ---------------------------------------------------------------- NLP construction
class _Peer:
    """The built solver and helpers for one setting (N, weights, masses, h_max, formulation)."""

    def __init__(self, N: int, weights: tuple[float, float, float], masses: tuple[float, ...],
                 h_max: float = H_MAX, formulation: str = "lifted"):
        self.N, self.weights, self.masses, self.h_max = N, weights, masses, h_max
        self.formulation = formulation
        w_time, w_energy, w_kin = weights
        idf = inverse_dynamics_function(masses)
        v = ca.SX.sym("v", NDOF, N)  # column k = v_k
        h = ca.SX.sym("h", N)
        p = ca.SX.sym("p", 2 * NDOF)  # [q_start; q_goal]
        q_start, q_goal = p[:NDOF], p[NDOF:]
        U = ca.diag(ca.DM([w_energy / t**2 for t in TAU_MAX]))

        def stage(q, qd, vk, hk):
            """One sample: its effort, its cost term and the next state (both forms)."""
            tau = idf(q, qd, vk)
            cost_k = hk * (w_time + ca.bilin(U, tau, tau) + w_kin * ca.dot(qd, qd))
            return tau, cost_k, q + hk * qd + 0.5 * hk**2 * vk, qd + hk * vk

        # the condensed recursion: states as expressions of (v, h); the trajectory read-out
        # of both forms, and the condensed NLP itself
        q, qd = q_start, ca.SX.zeros(NDOF)
        qs, qds, taus, cost = [q], [qd], [], 0
        for k in range(N):
            tau, cost_k, q, qd = stage(q, qd, v[:, k], h[k])
            taus.append(tau)
            cost += cost_k
            qs.append(q)
            qds.append(qd)
        xvh = ca.vertcat(ca.vec(v), h)  # v column-major: v_0, v_1, ... then h
        tmax = np.tile(TAU_MAX, N)
        lbx_vh = np.concatenate([np.full(NDOF * N, -QDD_MAX), np.full(N, H_MIN)])
        ubx_vh = np.concatenate([np.full(NDOF * N, QDD_MAX), np.full(N, h_max)])
        if formulation == "condensed":
            x, f = xvh, cost
            # constraints: tau_k (3N), qd_k k=1..N-1 (3(N-1)), qd_N (3), q_N - q_goal (3)
            g = ca.vertcat(*taus, *qds[1:N], qds[N], qs[N] - q_goal)
            self.lbg = np.concatenate([-tmax, np.full(NDOF * (N - 1), -QD_MAX), np.zeros(2 * NDOF)])
            self.ubg = np.concatenate([tmax, np.full(NDOF * (N - 1), QD_MAX), np.zeros(2 * NDOF)])
            self.lbx, self.ubx = lbx_vh, ubx_vh
        else:  # lifted: states 1..N are variables, the recursion is a set of equalities
            Q, QD = ca.SX.sym("Q", NDOF, N), ca.SX.sym("QD", NDOF, N)
            q, qd, f, g, lbg, ubg = q_start, ca.SX.zeros(NDOF), 0, [], [], []
            for k in range(N):
                tau, cost_k, q_next, qd_next = stage(q, qd, v[:, k], h[k])
                f += cost_k
                g += [tau, Q[:, k] - q_next, QD[:, k] - qd_next]
                lbg += [-np.asarray(TAU_MAX), np.zeros(2 * NDOF)]
                ubg += [np.asarray(TAU_MAX), np.zeros(2 * NDOF)]
                q, qd = Q[:, k], QD[:, k]
            g.append(Q[:, N - 1] - q_goal)
            lbg.append(np.zeros(NDOF))
            ubg.append(np.zeros(NDOF))
            x, g = ca.vertcat(xvh, ca.vec(Q), ca.vec(QD)), ca.vertcat(*g)
            self.lbg, self.ubg = np.concatenate(lbg), np.concatenate(ubg)
            # |qd_k| <= qd_max for k = 1..N-1 and qd_N = 0 as simple bounds
            qd_lo = np.concatenate([np.full(NDOF * (N - 1), -QD_MAX), np.zeros(NDOF)])
            self.lbx = np.concatenate([lbx_vh, np.full(NDOF * N, -np.inf), qd_lo])
            self.ubx = np.concatenate([ubx_vh, np.full(NDOF * N, np.inf), -qd_lo])
            self.states = ca.Function("states", [xvh, p], [ca.horzcat(*qs[1:]), ca.horzcat(*qds[1:])])
        self.solver = ca.nlpsol("S", "ipopt", {"x": x, "p": p, "f": f, "g": g}, dict(IPOPT_OPTIONS))
        self.traj = ca.Function("traj", [xvh, p],
                                [ca.horzcat(*qs).T, ca.horzcat(*qds).T, ca.horzcat(*taus).T, cost],
                                ["x", "p"], ["q", "qd", "tau", "cost"])

    def pack(self, v, h, p=None) -> np.ndarray:
        """The NLP's starting point from (v, h); the lifted form adds the states that
        the recursion gives from v and h (p = [q_start; q_goal])."""
        v = np.asarray(v, float).reshape(self.N, NDOF)
        xvh = np.concatenate([v.reshape(-1), np.asarray(h, float).reshape(self.N)])
        if self.formulation == "condensed":
            return xvh
        Q, QD = self.states(xvh, p)
        return np.concatenate([xvh, np.asarray(Q).T.reshape(-1), np.asarray(QD).T.reshape(-1)])

    def solve(self, q_start, q_goal, init=None) -> dict:
        q_start = np.asarray(q_start, float).reshape(NDOF)
        q_goal = np.asarray(q_goal, float).reshape(NDOF)
        v0, h0 = cycloidal_init(q_start, q_goal, self.N, self.h_max) if init is None else init
        p = np.concatenate([q_start, q_goal])
        x0 = self.pack(v0, h0, p)
        t0 = time.perf_counter()
        sol = self.solver(x0=x0, p=p, lbx=self.lbx, ubx=self.ubx, lbg=self.lbg, ubg=self.ubg)
        seconds = time.perf_counter() - t0
        st = self.solver.stats()
        x = np.asarray(sol["x"]).ravel()[:(NDOF + 1) * self.N]  # (v, h); the lifted states follow
        out = self.traj(x, p)
        status = str(st.get("return_status", "unknown"))
        h = x[NDOF * self.N:]
        return dict(
            v=x[:NDOF * self.N].reshape(self.N, NDOF), h=h,
            q=np.asarray(out[0]), qd=np.asarray(out[1]), tau=np.asarray(out[2]),
            T=float(h.sum()), cost=float(out[3]),
            success=status in ("Solve_Succeeded", "Solved_To_Acceptable_Level"),
            strict_success=status == "Solve_Succeeded",
            status=status, iterations=int(st.get("iter_count", -1)),
            seconds=seconds, ipopt_seconds=float(st.get("t_wall_total", float("nan"))),
            q_start=q_start, q_goal=q_goal)


_CACHE: dict[tuple, _Peer] = {}


FORMULATIONS = ("lifted", "condensed")


def _key(N, weights, masses, h_max=H_MAX, formulation="lifted") -> tuple:
    weights = tuple(float(w) for w in weights)
    if len(weights) != 3:
        raise ValueError(f"weights must be (w_time, w_energy, w_kin), got {weights}")
    masses = MASSES if masses is None else tuple(float(m) for m in masses)
    if len(masses) != NDOF or min(masses) <= 0:
        raise ValueError(f"masses must be {NDOF} positive numbers, got {masses}")
    if int(N) != N or N < 1:
        raise ValueError(f"N must be a positive integer, got {N}")
    h_max = float(h_max)
    if not (math.isfinite(h_max) and h_max > H_MIN):
        raise ValueError(f"h_max must be a number above h_min = {H_MIN}, got {h_max}")
    if formulation not in FORMULATIONS:
        raise ValueError(f"formulation must be one of {FORMULATIONS}, got {formulation!r}")
    return int(N), weights, masses, h_max, formulation


def get_peer(N: int = 20, weights=CANONICAL_WEIGHTS, masses=None, h_max=H_MAX, formulation="lifted") -> _Peer:
    """The cached built solver for these settings (built on first use in this process)."""
    key = _key(N, weights, masses, h_max, formulation)
    if key not in _CACHE:
        _CACHE[key] = _Peer(*key)
    return _CACHE[key]


def cycloidal_init(q_start, q_goal, N: int = 20, h_max: float = H_MAX) -> tuple[np.ndarray, np.ndarray]:
    """The canonical cycloidal initial guess ``(v (N,3), h (N,))``.

    T_j = max(2|dq_j|/qd_max, sqrt(2 pi |dq_j|/qdd_max)), T = max_j T_j clipped to
    [N h_min, N h_max] (N h_min when start == goal); h_k = T/N and v_k = the cycloid's
    acceleration dq (2 pi/T^2) sin(2 pi t_k/T) at t_k = k T/N.
    """
    dq = np.asarray(q_goal, float).reshape(NDOF) - np.asarray(q_start, float).reshape(NDOF)
    a = np.abs(dq)
    T = float(np.max(np.maximum(2 * a / QD_MAX, np.sqrt(2 * math.pi * a / QDD_MAX))))
    T = N * H_MIN if T == 0 else min(max(T, N * H_MIN), N * h_max)
    t = np.arange(N) * T / N
    v = dq[None, :] * (2 * math.pi / T**2) * np.sin(2 * math.pi * t / T)[:, None]
    return v, np.full(N, T / N)


def solve_pair(q_start, q_goal, N: int = 20, weights=CANONICAL_WEIGHTS, init=None,
               masses=None, h_max=H_MAX, formulation="lifted") -> dict:
    """Solve one start -> goal problem with IPOPT (solver built once per process/settings).

    Args:
        q_start, q_goal: (3,) joint angles [rad]; the arm starts and ends at rest.
        N: number of intervals.
        weights: (w_time, w_energy, w_kin).
        init: optional starting point ``(v (N,3), h (N,))``; default :func:`cycloidal_init`.
        masses: optional override of the link masses (3,) [kg].
        h_max: upper bound of the periods [s] (default the robot's 0.1; jtraj datasets
            use twice that by default).
        formulation: "lifted" (default, the fast peer) or "condensed" (see the module
            docstring).

    Returns a dict: v (N,3), h (N,), q (N+1,3), qd (N+1,3), tau (N,3), T (= sum h),
    cost, success (Solve_Succeeded or Solved_To_Acceptable_Level), strict_success
    (Solve_Succeeded only), status (IPOPT's return_status), iterations, seconds (wall
    time of the solver call), ipopt_seconds (IPOPT's t_wall_total), q_start, q_goal.
    """
    return get_peer(N, weights, masses, h_max, formulation).solve(q_start, q_goal, init)


# ---------------------------------------------------------------- multiprocessing
class SolveBatch(list):
    """A list of :func:`solve_pair` dicts with ``wall_seconds`` (solving the whole set
    once every worker had built its NLP), ``setup_seconds`` (pool start + builds) and
    ``processes``."""

    wall_seconds: float = float("nan")
    setup_seconds: float = 0.0
    processes: int = 1


_WORKER_SETTINGS: tuple | None = None


def _worker_init(settings, barrier):
    global _WORKER_SETTINGS
    _WORKER_SETTINGS = settings
    get_peer(*settings)  # build the NLP once per worker
    if barrier is not None:
        barrier.wait(timeout=600)


def _worker_solve(job):
    q_start, q_goal, init = job
    N, weights, masses, h_max, formulation = _WORKER_SETTINGS
    return solve_pair(q_start, q_goal, N=N, weights=weights, init=init, masses=masses, h_max=h_max,
                      formulation=formulation)


def solve_many(q_starts, q_goals, *, processes: int | None = None, N: int = 20,
               weights=CANONICAL_WEIGHTS, masses=None, inits=None, h_max=H_MAX, formulation="lifted",
               start_method: str = "spawn", single_thread: bool = True) -> SolveBatch:
    """Solve many pairs on ``processes`` worker processes (default ``os.cpu_count()``).

    Each worker builds the NLP once in a Pool initializer; the clock for
    ``wall_seconds`` starts only after every worker has finished building (a barrier),
    so ``len(result) / result.wall_seconds`` is the solve throughput on all cores.
    ``processes=1`` solves serially in this process (no pool). ``inits`` is an optional
    list of ``(v, h)`` starting points, one per pair. The ``spawn`` start method is the
    default because the caller may have imported JAX, which is not fork-safe.
    ``single_thread`` sets OMP/OPENBLAS/MKL_NUM_THREADS=1 in the workers (one solve per
    core; restored in the parent afterwards).
    """
    q_starts = np.asarray(q_starts, float).reshape(-1, NDOF)
    q_goals = np.asarray(q_goals, float).reshape(-1, NDOF)
    if q_starts.shape != q_goals.shape:
        raise ValueError(f"q_starts {q_starts.shape} and q_goals {q_goals.shape} differ")
    n = len(q_starts)
    inits = [None] * n if inits is None else list(inits)
    if len(inits) != n:
        raise ValueError(f"inits has {len(inits)} entries for {n} pairs")
    settings = _key(N, weights, masses, h_max, formulation)
    processes = max(1, min(int(processes or os.cpu_count() or 1), max(n, 1)))
    jobs = list(zip(q_starts, q_goals, inits))
    batch = SolveBatch()
    batch.processes = processes
    if processes == 1:
        t0 = time.perf_counter()
        get_peer(*settings)
        batch.setup_seconds = time.perf_counter() - t0
        t0 = time.perf_counter()
        batch.extend(solve_pair(a, b, *settings[:2], init=i, masses=settings[2], h_max=settings[3],
                                formulation=settings[4]) for a, b, i in jobs)
        batch.wall_seconds = time.perf_counter() - t0
        return batch
    ctx = mp.get_context(start_method)
    env_keys = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    saved = {k: os.environ.get(k) for k in env_keys}
    try:
        if single_thread:  # inherited by spawned workers, restored below
            os.environ.update({k: "1" for k in env_keys})
        t0 = time.perf_counter()
        barrier = ctx.Barrier(processes + 1)
        with ctx.Pool(processes, initializer=_worker_init, initargs=(settings, barrier)) as pool:
            barrier.wait(timeout=600)  # every worker has built its NLP
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
