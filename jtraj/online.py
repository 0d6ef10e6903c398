"""Online planning with trained ANFIS models: a whole trajectory per (start, goal) in one
jitted call, its feasibility, and optional exact refinement.

Two kinds of planner:

* **open loop**, one model of the ``plan`` mapping (``jtraj train --mapping plan``):
  ``(q_start, q_goal) -> (v (N n), h (N))``. :meth:`Planner.plan` predicts the
  accelerations and periods, clips the periods into ``[h_min, h_max]`` and rolls the
  decoupled recursion out (``q'' = v``, the recursion of the exact solver) from the start
  at rest;
* **closed loop** (the thesis' NeFOTC with NeFuMOP), a ``nefotc`` model, the torque
  controller ``(q_goal - q, qd, k/N) -> tau``, with ``periods=`` a ``nefumop`` model
  whose last output is ``h``: at each of the N steps the controller's torque (clipped to
  the torque box) drives the robot's forward dynamics for the predicted period. The
  goal offset is fed back, so errors are corrected on the way: on 100 held-out pairs of a
  300-pair serial3 dataset the median goal error was 0.030 rad, against 0.20 rad for the
  open-loop plan model (docs/guides/anfis.md).

The actuator efforts come from the robot's inverse dynamics, and :class:`Plan` reports:

* ``tau_violation``, ``qd_violation``, ``q_violation``: largest relative excess over the
  robot's limits (0 when within; e.g. 0.1 means 10 % over);
* ``h_violation``: largest relative excess of the raw predicted periods (before clipping);
* ``goal_error``: ``||q_N - q_goal||`` [rad], ``goal_velocity``: ``||qd_N||``;
* ``feasible``: every violation <= ``tol`` and goal error <= ``goal_tol``.

The robot is the one named in the model's metadata, with the sampling-period bound of
the training dataset (``h_max`` in the metadata) where recorded. With ``refine=True``
the plan warm-starts the exact solver on
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


def _load(model):
    from jtraj import anfis

    return model if isinstance(model, (anfis.Model, anfis.Ensemble)) else anfis.load(model)


def _excess(x, bound):
    if bound is None:
        return jnp.zeros(())
    return jnp.max(jnp.maximum(jnp.abs(x) / bound - 1.0, 0.0))


def model_inputs(meta: dict, robot, q, qd, q_goal, k, N: int):
    """The inputs of a ``nefotc`` or ``nefumop`` model (as
    :func:`jtraj.anfis.trajectory.view` builds them, from the model's ``goal_inputs`` and
    ``phase_input`` metadata) at the state ``(q, qd)`` of step ``k`` towards ``q_goal``."""
    if meta["mapping"] == "nefotc":
        x, xd, xg = q, qd, q_goal
    else:
        x, xd = jax.jvp(robot.forward_kinematics, (q,), (qd,))
        xg = robot.forward_kinematics(q_goal)
    from jtraj.anfis.trajectory import goal_blocks

    parts = goal_blocks(x, xd, xg, meta.get("goal_inputs"))
    if meta.get("phase_input"):
        parts.append(jnp.full((1,), k / N, x.dtype))
    return jnp.concatenate(parts)


class Planner:
    """``Planner(model)`` (or a model path); ``plan(q_start, q_goal)`` -> :class:`Plan`.

    ``model``: of mapping ``plan`` (open loop), or ``nefotc`` together with ``periods``,
    a ``nefumop`` model (or path) trained on the same dataset (closed loop; see the
    module doc). ``robot`` defaults to the one named in the model's metadata, with the
    dataset's ``h_max`` where the metadata records it.
    """

    def __init__(self, model, robot=None, *, periods=None, tol: float = 1e-6, goal_tol: float = 1e-2):
        from jtraj import robots

        model = _load(model)
        meta = model.metadata
        if meta.get("mapping") not in ("plan", "nefotc"):
            raise ValueError(f"the planner needs a model of mapping 'plan', or 'nefotc' with periods=, got "
                             f"{meta.get('mapping')!r}")
        if meta["mapping"] == "nefotc":
            if periods is None:
                raise ValueError("a nefotc model plans in closed loop: give periods= (jtraj query --periods) a "
                                 "nefumop model of the same dataset (its output h sets the sampling periods)")
            if not meta.get("goal_inputs"):
                raise ValueError("the nefotc model has no goal inputs (trained with --goal-inputs none), so it "
                                 "cannot steer towards a goal: train it with the default inputs")
            periods = _load(periods)
            pm = periods.metadata
            if pm.get("mapping") != "nefumop" or pm.get("outputs", [None])[-1] != "h":
                raise ValueError(f"periods must be a nefumop model (outputs ending with h), got mapping "
                                 f"{pm.get('mapping')!r}")
            if (pm.get("robot"), pm.get("N")) != (meta.get("robot"), meta.get("N")):
                raise ValueError(f"periods was trained for robot {pm.get('robot')!r}, N = {pm.get('N')}; the "
                                 f"model for robot {meta.get('robot')!r}, N = {meta.get('N')}")
        elif periods is not None:
            raise ValueError("periods= is for a nefotc model; a plan model predicts its own periods")
        self.model, self.periods = model, periods
        if robot is None:
            robot = robots.get(meta["robot"], **({"h_max": meta["h_max"]} if meta.get("h_max") else {}))
        self.robot = robot
        self.n = self.robot.n
        self.N = int(meta["N"])
        if meta["mapping"] == "plan":
            if model.n_inputs != 2 * self.n or model.n_outputs != self.N * (self.n + 1):
                raise ValueError(f"model shapes ({model.n_inputs} inputs, {model.n_outputs} outputs) do not "
                                 f"match robot {meta['robot']} (n = {self.n}) with N = {self.N}")
        else:
            z = jnp.zeros(self.n)
            for m in (model, periods):
                d = model_inputs(m.metadata, self.robot, z, z, z, 0, self.N).shape[0]
                if d != m.n_inputs:
                    raise ValueError(f"the {m.metadata['mapping']} model has {m.n_inputs} inputs, its metadata "
                                     f"describes {d}")
        self.tol, self.goal_tol = tol, goal_tol
        self._plan = jax.jit(self._build() if periods is None else self._build_closed_loop())

    def _report(self, q, qd, v, h, h_raw, qg):
        rb = self.robot
        lim = rb.limits
        tau = jax.vmap(rb.inverse_dynamics)(q[:-1], qd[:-1], v)
        hv = jnp.max(jnp.maximum(jnp.maximum(lim.h_min - h_raw, h_raw - lim.h_max) / lim.h_max, 0.0))
        qv = jnp.zeros(())
        if lim.q_min is not None:
            qv = jnp.max(jnp.maximum(jnp.maximum(lim.q_min - q, q - lim.q_max) / (lim.q_max - lim.q_min), 0.0))
        return Plan(q, qd, v, tau, h, jnp.sum(h), _excess(tau, lim.tau_max), _excess(qd, lim.qd_max), qv, hv,
                    jnp.linalg.norm(q[-1] - qg), jnp.linalg.norm(qd[-1]))

    def _build(self):
        f = self.model.predict_fn()
        N, n = self.N, self.n
        lim = self.robot.limits

        def plan(qs, qg):
            y = f(jnp.concatenate([qs, qg])[None, :])[0]
            v = y[: N * n].reshape(N, n)
            h_raw = y[N * n:]
            h = jnp.clip(h_raw, lim.h_min, lim.h_max)
            dqd = h[:, None] * v
            qd = jnp.concatenate([jnp.zeros((1, n), v.dtype), jnp.cumsum(dqd, axis=0)])
            dq = h[:, None] * qd[:-1] + 0.5 * (h**2)[:, None] * v
            q = jnp.concatenate([qs[None], qs + jnp.cumsum(dq, axis=0)])
            return self._report(q, qd, v, h, h_raw, qg)
        return plan

    def _build_closed_loop(self):
        ctl, per = self.model.predict_fn(), self.periods.predict_fn()
        mc, mp = self.model.metadata, self.periods.metadata
        rb, N = self.robot, self.N
        lim = rb.limits
        tau_max = jnp.inf if lim.tau_max is None else lim.tau_max

        def plan(qs, qg):
            def step(state, k):
                q, qd = state
                tau = jnp.clip(ctl(model_inputs(mc, rb, q, qd, qg, k, N)[None])[0], -tau_max, tau_max)
                h_raw = per(model_inputs(mp, rb, q, qd, qg, k, N)[None])[0, -1]
                h = jnp.clip(h_raw, lim.h_min, lim.h_max)
                a = rb.forward_dynamics(q, qd, tau)
                return (q + h * qd + 0.5 * h * h * a, qd + h * a), (q, qd, a, h, h_raw)

            (qN, qdN), (q, qd, v, h, h_raw) = jax.lax.scan(step, (qs, jnp.zeros_like(qs)), jnp.arange(N))
            return self._report(jnp.concatenate([q, qN[None]]), jnp.concatenate([qd, qdN[None]]), v, h, h_raw, qg)
        return plan

    def plan(self, q_start, q_goal) -> Plan:
        """The predicted trajectory and its feasibility (one jitted call). ``ValueError``
        where ``q_start`` or ``q_goal`` is not an (n,) vector of finite numbers."""
        from ._checks import check_state

        qs = jnp.asarray(np.asarray(check_state(q_start, "q_start", self.n), float).reshape(self.n))
        qg = jnp.asarray(np.asarray(check_state(q_goal, "q_goal", self.n), float).reshape(self.n))
        return self._plan(qs, qg)

    def check(self, q_start, q_goal) -> None:
        """``ValueError`` where ``q_start`` or ``q_goal`` is not what ``jtraj.Problem``
        accepts of a start and a goal: an (n,) finite vector inside the robot's joint box,
        workspace box and path constraints (:func:`jtraj.problem.check_configurations`)."""
        from ._checks import check_state
        from .problem import check_configurations

        check_configurations(self.robot, {"q_start": check_state(q_start, "q_start", self.n).reshape(self.n),
                                          "q_goal": check_state(q_goal, "q_goal", self.n).reshape(self.n)})

    __call__ = plan

    def feasible(self, p: Plan) -> bool:
        worst = max(float(p.tau_violation), float(p.qd_violation), float(p.q_violation))
        return worst <= self.tol and float(p.goal_error) <= self.goal_tol

    def query(self, q_start, q_goal, *, refine: bool = False, weights=None, options=None,
              warm: str = "primal", N: int | None = None) -> dict:
        """Plan, report feasibility, and optionally refine with the exact solver.

        ``q_start`` and ``q_goal`` are checked first (:meth:`check`: ``ValueError``).
        ``N``: intervals of the refined problem, by default the model's; another N
        warm-starts from the plan re-sampled onto N equal periods (the plan's acceleration
        at each new interval's midpoint), which keeps the plan's total time.

        ``weights`` default to those of the training dataset (stored in the model's
        metadata as ``"weights"``, e.g. ``"time=1,energy=0.1"``), else ``Weights()``.
        Returns a JSON-able dict; with ``refine`` it adds the solver's status,
        iterations, time, and the same solve from the solver's default initial guess
        (the cycloid, slowed to meet the torque bounds) for comparison
        (``cycloidal_iterations``, ``cycloidal_seconds``).

        ``warm``: ``"primal"`` (default) starts the solver at the plan with the
        multipliers and penalty of a cold start; ``"full"`` is ``jtraj.solve(init=...)``,
        which also estimates multipliers at the plan and starts the penalty at
        ``penalty_max / 100``: right for a guess near an optimum, but the plan is not
        (median goal error ~0.3 rad), and on 60 held-out serial3 pairs
        ``"full"`` converged on 2/60 against 43/60 from the cycloidal start, ``"primal"``
        on 45/60 with 0.85x the iterations (``jtraj.solve(..., warm=)``)."""
        if warm not in ("primal", "full"):
            raise ValueError(f"warm must be 'primal' or 'full', got {warm!r}")
        if N is not None and (isinstance(N, bool) or not isinstance(N, (int, np.integer)) or N < 2):
            raise ValueError(f"N must be an integer >= 2 or None, got {N!r}")
        N = self.N if N is None else int(N)
        self.check(q_start, q_goal)
        t0 = time.perf_counter()
        p = jax.block_until_ready(self.plan(q_start, q_goal))
        out = dict(seconds=time.perf_counter() - t0, T=float(p.T), feasible=self.feasible(p),
                   tau_violation=float(p.tau_violation), qd_violation=float(p.qd_violation),
                   q_violation=float(p.q_violation), h_violation=float(p.h_violation),
                   goal_error=float(p.goal_error), goal_velocity=float(p.goal_velocity),
                   q=np.asarray(p.q).tolist(), h=np.asarray(p.h).tolist())
        if self.robot.limits.tau_max is not None and np.all(np.isfinite(np.asarray(p.q))):
            # the plan holds v_k over each interval too: its efforts between the samples
            from .resample import intersample_effort

            out["effort_between_samples"] = float(intersample_effort(
                {"q": p.q, "qd": p.qd, "v": p.v, "h": p.h}, self.robot))
        if refine:
            import jtraj

            if weights is None and self.model.metadata.get("weights"):
                weights = jtraj.Weights.parse(self.model.metadata["weights"])  # the dataset's cost
            kw = {} if weights is None else {"weights": weights}
            prob = jtraj.Problem(self.robot, np.asarray(q_start, float), np.asarray(q_goal, float), N=N, **kw)
            out["refined_N"] = N
            # cycloidal first: in a fresh process it pays the compilation (shared with the
            # warm solve), so refined_seconds is a compiled solve's time
            for label, init in (("cycloidal", None), ("refined", _resampled(p.v, p.h, N, self.robot.limits))):
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



def _resampled(v, h, N: int, limits):
    """A plan's (v (M, n), h (M,)) on N equal periods of the same total time (within the
    robot's period bounds): the acceleration at each new interval's midpoint (the plan
    itself where N = M)."""
    v, h = np.asarray(v), np.asarray(h)
    if N == h.shape[0]:
        return jnp.asarray(v), jnp.asarray(h)
    T = float(h.sum())
    mid = (np.arange(N) + 0.5) * T / N
    k = np.minimum(np.searchsorted(np.cumsum(h), mid), h.shape[0] - 1)
    return jnp.asarray(v[k]), jnp.full(N, float(np.clip(T / N, limits.h_min, limits.h_max)))
