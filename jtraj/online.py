"""Online planning with a trained ANFIS: a whole trajectory per (start, goal) in one
jitted call, its feasibility, and optional exact refinement.

The model must be of the ``plan`` mapping (``jtraj train --mapping plan``):
``(q_start, q_goal) -> (v (N n), h (N))``. :meth:`Planner.plan` predicts the
accelerations and periods, clips the periods into ``[h_min, h_max]``, rolls the
decoupled dynamics out (``q'' = v``, the recursion of the exact solver) from the start
at rest, computes the actuator efforts by the robot's inverse dynamics, and reports:

* ``tau_violation``, ``qd_violation``, ``q_violation``: largest relative excess over the
  robot's limits (0 when within; e.g. 0.1 means 10 % over);
* ``h_violation``: largest relative excess of the raw predicted periods (before clipping);
* ``goal_error``: ``||q_N - q_goal||`` [rad], ``goal_velocity``: ``||qd_N||``;
* ``feasible``: every violation <= ``tol`` and goal error <= ``goal_tol``.

With ``refine=True`` the plan warm-starts the exact solver on
``Problem(robot, q_start, q_goal, N=N, weights=<the dataset's>)`` from ``(v, h)``
(primal point only by default, see :meth:`Planner.query`).
"""

from __future__ import annotations

import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class Plan(NamedTuple):
    q: jax.Array  # (N+1, n)
    qd: jax.Array  # (N+1, n)
    v: jax.Array  # (N, n)
    tau: jax.Array  # (N, m)
    h: jax.Array  # (N,)
    T: jax.Array
    tau_violation: jax.Array
    qd_violation: jax.Array
    q_violation: jax.Array
    h_violation: jax.Array
    goal_error: jax.Array
    goal_velocity: jax.Array


def _excess(x, bound):
    if bound is None:
        return jnp.zeros(())
    return jnp.max(jnp.maximum(jnp.abs(x) / bound - 1.0, 0.0))


class Planner:
    """``Planner(model)`` (or a model path); ``plan(q_start, q_goal)`` -> :class:`Plan`.

    ``robot`` defaults to the one named in the model's metadata.
    """

    def __init__(self, model, robot=None, *, tol: float = 1e-6, goal_tol: float = 1e-2):
        from jtraj import anfis, robots

        if not isinstance(model, (anfis.Model, anfis.Ensemble)):
            model = anfis.load(model, mapping="plan")
        meta = model.metadata
        if meta.get("mapping") != "plan":
            raise ValueError(f"the planner needs a model of mapping 'plan', got {meta.get('mapping')!r}")
        self.model = model
        self.robot = robot if robot is not None else robots.get(meta["robot"])
        self.n = self.robot.n
        self.N = int(meta["N"])
        if model.n_inputs != 2 * self.n or model.n_outputs != self.N * (self.n + 1):
            raise ValueError(f"model shapes ({model.n_inputs} inputs, {model.n_outputs} outputs) do not match "
                             f"robot {meta['robot']} (n = {self.n}) with N = {self.N}")
        self.tol, self.goal_tol = tol, goal_tol
        self._plan = jax.jit(self._build())

    def _build(self):
        f = self.model.predict_fn()
        rb, N, n = self.robot, self.N, self.n
        lim = rb.limits

        def plan(qs, qg):
            y = f(jnp.concatenate([qs, qg])[None, :])[0]
            v = y[: N * n].reshape(N, n)
            h_raw = y[N * n:]
            h = jnp.clip(h_raw, lim.h_min, lim.h_max)
            dqd = h[:, None] * v
            qd = jnp.concatenate([jnp.zeros((1, n), v.dtype), jnp.cumsum(dqd, axis=0)])
            dq = h[:, None] * qd[:-1] + 0.5 * (h**2)[:, None] * v
            q = jnp.concatenate([qs[None], qs + jnp.cumsum(dq, axis=0)])
            tau = jax.vmap(rb.inverse_dynamics)(q[:-1], qd[:-1], v)
            hv = jnp.max(jnp.maximum(jnp.maximum(lim.h_min - h_raw, h_raw - lim.h_max) / lim.h_max, 0.0))
            qv = jnp.zeros(())
            if lim.q_min is not None:
                qv = jnp.max(jnp.maximum(jnp.maximum(lim.q_min - q, q - lim.q_max) / (lim.q_max - lim.q_min), 0.0))
            return Plan(q, qd, v, tau, h, jnp.sum(h), _excess(tau, lim.tau_max), _excess(qd, lim.qd_max), qv, hv,
                        jnp.linalg.norm(q[-1] - qg), jnp.linalg.norm(qd[-1]))
        return plan

    def plan(self, q_start, q_goal) -> Plan:
        """The predicted trajectory and its feasibility (one jitted call)."""
        qs = jnp.asarray(np.asarray(q_start, float).reshape(self.n))
        qg = jnp.asarray(np.asarray(q_goal, float).reshape(self.n))
        return self._plan(qs, qg)

    __call__ = plan

    def feasible(self, p: Plan) -> bool:
        worst = max(float(p.tau_violation), float(p.qd_violation), float(p.q_violation))
        return worst <= self.tol and float(p.goal_error) <= self.goal_tol

    def query(self, q_start, q_goal, *, refine: bool = False, weights=None, options=None,
              warm: str = "primal") -> dict:
        """Plan, report feasibility, and optionally refine with the exact solver.

        ``weights`` default to those of the training dataset (stored in the model's
        metadata as ``"weights"``, e.g. ``"time=1,energy=0.1"``), else ``Weights()``.
        Returns a JSON-able dict; with ``refine`` it adds the solver's status,
        iterations, time, and the same solve from the cycloidal initial guess for
        comparison (``cycloidal_iterations``, ``cycloidal_seconds``).

        ``warm``: ``"primal"`` (default) starts the solver at the plan with the
        multipliers and penalty of a cold start; ``"full"`` is ``jtraj.solve(init=...)``,
        which also estimates multipliers at the plan and starts the penalty at
        ``penalty_max / 100``: right for a guess near an optimum, but the plan is not
        (median goal error ~0.3 rad), and on 60 held-out serial3 pairs (README, ANFIS)
        ``"full"`` converged on 2/60 against 43/60 from the cycloidal start, ``"primal"``
        on 45/60 with 0.85x the iterations (``jtraj.solve(..., warm=)``)."""
        if warm not in ("primal", "full"):
            raise ValueError(f"warm must be 'primal' or 'full', got {warm!r}")
        t0 = time.perf_counter()
        p = jax.block_until_ready(self.plan(q_start, q_goal))
        out = dict(seconds=time.perf_counter() - t0, T=float(p.T), feasible=self.feasible(p),
                   tau_violation=float(p.tau_violation), qd_violation=float(p.qd_violation),
                   q_violation=float(p.q_violation), h_violation=float(p.h_violation),
                   goal_error=float(p.goal_error), goal_velocity=float(p.goal_velocity),
                   q=np.asarray(p.q).tolist(), h=np.asarray(p.h).tolist())
        if refine:
            import jtraj

            if weights is None and self.model.metadata.get("weights"):
                weights = jtraj.Weights.parse(self.model.metadata["weights"])  # the dataset's cost
            kw = {} if weights is None else {"weights": weights}
            prob = jtraj.Problem(self.robot, np.asarray(q_start, float), np.asarray(q_goal, float), N=self.N, **kw)
            # cycloidal first: in a fresh process it pays the compilation (shared with the
            # warm solve), so refined_seconds is a compiled solve's time
            for label, init in (("cycloidal", None), ("refined", (p.v, p.h))):
                t1 = time.perf_counter()
                if init is None:
                    sol = jtraj.solve(prob, options=options)
                else:
                    sol = jtraj.solve(prob, init=init, options=options, warm=warm)
                    out["refined_warm"] = warm
                jax.block_until_ready(sol)
                dt = time.perf_counter() - t1
                out[f"{label}_status"] = sol.status_message
                out[f"{label}_status_code"] = int(np.asarray(sol.status))
                out[f"{label}_cost"] = float(np.asarray(sol.cost))
                out[f"{label}_iterations"] = int(np.asarray(sol.iterations))
                out[f"{label}_seconds"] = dt
                out[f"{label}_T"] = float(np.asarray(sol.T))
                out[f"{label}_converged"] = bool(np.asarray(sol.converged))
        return out

