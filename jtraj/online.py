"""Online planning with trained ANFIS models: a whole trajectory per (start, goal) in one
jitted call, feasible by construction, with its cost, its coverage and optional exact
refinement.

Two kinds of prediction:

* **open loop**, one model of the ``plan`` mapping (``jtraj train --mapping plan``):
  ``(q_start, q_goal) -> (v (N n), h (N))``, the accelerations and periods of the whole
  trajectory, run through the decoupled recursion (``q'' = v``, the exact solver's) from
  the start at rest;
* **closed loop** (the thesis' NeFOTC with NeFuMOP), a ``nefotc`` model, the torque
  controller ``(q_goal - q, qd, k/N) -> tau``, with ``periods=`` a ``nefumop`` model
  whose last output is ``h``: at each of the N steps the controller's torque (clipped to
  the torque box) drives the robot's forward dynamics for the predicted period.

Either prediction ``(v, h)`` then goes through the feasibility repair of
:mod:`jtraj.repair` (``correct=True``, the default): a projection of ``v`` onto the goal
state (reached to rounding, at rest) and a time scaling that restores the velocity,
acceleration, effort and jerk bounds at the lowest cost of the scaled plans, compared
with switching profiles on the same periods (the shape of effort-bounded optima) and a
synchronised trapezoidal velocity profile (the shape of velocity- and
acceleration-bounded optima), all inside the same jitted call; where the robot has
path constraints (a parallel robot's leg-singularity margins), each candidate's path is
first bent back inside them and the boxes on positions, which the time scaling leaves
unchanged. ``correct=False`` returns the raw prediction.

The efforts come from the robot's inverse dynamics, and :class:`Plan` reports:

* ``cost``: the cost of the training dataset's weights (:func:`jtraj.repair.cost_of`);
* ``violation``: largest relative excess over the robot's constraints (efforts,
  velocities, accelerations, positions, periods, and the acceleration jumps where the
  robot has a jerk bound, as ``jtraj.Problem`` bounds them; 0 when within, 0.1 means
  10 % over), and each of ``tau_violation``, ``qd_violation`` (the joint velocity box and
  a parallel robot's velocity constraints), ``qdd_violation``, ``q_violation`` (the joint
  and workspace boxes and a parallel robot's path constraints:
  :func:`jtraj.repair.position_excess`), ``h_violation``, ``jerk_violation``;
* ``goal_error``: ``||q_N - q_goal||`` [rad], ``goal_velocity``: ``||qd_N||``, and
  ``predicted_goal_error``, the goal error of the raw prediction;
* ``scale``: the repair's time scaling (1 without it), and ``candidate``, the candidate
  it chose (an index into ``Planner.candidates``, -1 without it);
* ``coverage_distance``, ``coverage_box`` and ``ood``: the query's distance to the
  nearest training pair and outside the training data's box (:mod:`jtraj.coverage`), and
  whether it lies out of distribution (farther than the training data's radius, or
  more than :data:`BOX_MARGIN` outside the box).

A plan is ``feasible`` when ``violation <= tol`` (1e-6) and the goal position and
velocity errors are ``<= goal_tol`` (1e-6). :meth:`Planner.plan` takes one start/goal
pair ``(n,)`` or a batch ``(B, n)`` (one jitted, vmapped call).

The robot is the one named in the model's metadata, with the sampling-period bound of
the training dataset (``h_max`` in the metadata) where recorded. With ``refine=True``
:meth:`Planner.query` warm-starts the exact solver on
``Problem(robot, q_start, q_goal, N=N, weights=<the dataset's>)`` from the plan and
reports the plan's cost gap to the refined optimum.
"""

from __future__ import annotations

import os
import re
import threading
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


#: a query flags out of distribution beyond this scaled distance outside the training box
#: (jtraj.coverage): a new draw of the training law falls a little outside the range of
#: a few hundred training pairs (4 of 40 held-out serial3 pairs at margin 0)
BOX_MARGIN = 0.05
#: :meth:`Planner.plan` splits a larger batch into calls of this many pairs (the last one
#: padded, so that one compiled program serves every batch size above it): on a CPU the
#: batched program's arrays of a few hundred plans stay in cache, and the calls run on
#: :data:`THREADS` threads at once
CHUNK = 256
#: where the repair bends paths (:func:`jtraj.repair.position_step`), :meth:`Planner.plan`
#: runs a batch without the step and the plans it flags again with it, in calls of this
#: many pairs (on parallel3 about 4 % of a batch)
BEND_CHUNK = 16
#: threads :meth:`Planner.plan` runs a chunked batch's calls on (XLA releases the GIL)
THREADS = min(os.cpu_count() or 1, 8)
#: custom calls that one program must not run on two threads at once: jaxlib's CPU LAPACK
#: kernels (``jnp.linalg.solve``, ``det``, ``cholesky``, ... in a robot's dynamics) then
#: hang over large batches (reproduced with jaxlib 0.10.2 by a jitted, vmapped 2 x 2 solve
#: of 65,536 systems called from two threads; two different programs ran side by side).
#: Where a planner's programs hold one, :meth:`Planner.plan` runs a batch's chunks one
#: after the other and calls from several of the user's threads one at a time.
SERIAL_CUSTOM_CALLS = ("lapack_",)
#: the interior-point settings of :meth:`Planner.query`'s refinement from the plan where no
#: solver is given: a shorter barrier schedule (``mu_init``), a start kept near the plan
#: (``bound_push``, 1e-2 in a cold start) and a small first Hessian shift
#: (``first_shift``, 1.0 in a cold start: a plan's Hessians need little). All are traced
#: options, so the refinement runs the cold solve's compiled program. The benchmarks page
#: ("Online planner") has the iterations against a cold start (``benchmarks/bench_online.py``,
#: variant ``plan_warm``); the solver guide's "Warm starts" says why a plan gains little
WARM_IPM = dict(mu_init=1e-4, bound_push=1e-4, first_shift=1e-2)
#: XLA CPU options of the programs :meth:`Planner.plan` runs, for one plan and for a batch:
#: no YNNPACK library fusions (jaxlib hands the small reductions over 2 to 60 numbers per
#: plan to YNNPACK, slower than XLA's own loops for arrays of this shape), and the legacy
#: loop emitters (a batch of plans about 15 % faster than with the newer fusion emitters).
#: One panda plan (N = 40, the efforts of 7-joint chains reduced over 3-vectors) takes
#: 1.25 ms with them against 7.2 ms without; one serial3 plan 94 against 101 us
BATCH_XLA_OPTIONS = {"xla_cpu_use_fusion_emitters": False, "xla_cpu_experimental_ynn_fusion_type": ""}


class Plan(NamedTuple):
    q: jax.Array  # (N+1, n)
    qd: jax.Array  # (N+1, n)
    v: jax.Array  # (N, n)
    tau: jax.Array  # (N, m)
    h: jax.Array  # (N,)
    T: jax.Array
    cost: jax.Array
    violation: jax.Array
    tau_violation: jax.Array
    qd_violation: jax.Array
    qdd_violation: jax.Array
    q_violation: jax.Array
    h_violation: jax.Array
    jerk_violation: jax.Array
    goal_error: jax.Array
    goal_velocity: jax.Array
    predicted_goal_error: jax.Array
    scale: jax.Array
    #: the repair's chosen candidate, an index into ``Planner.candidates`` (-1 without
    #: the repair)
    candidate: jax.Array
    #: whether the repair's position step bent a candidate's path back inside the
    #: position constraints (:func:`jtraj.repair.position_step`)
    bent: jax.Array
    coverage_distance: jax.Array
    coverage_box: jax.Array
    ood: jax.Array


def _holds_custom_call(fn, x, prefixes) -> bool:
    """Whether the jitted ``fn``'s program on ``x`` calls a custom call whose target
    starts with one of ``prefixes`` (read from its lowered text: no compilation)."""
    text = fn.lower(x).as_text()
    return any(re.search("custom_call @" + re.escape(p), text) for p in prefixes)


def _options_jit(fn):
    """``jax.jit(fn)`` with :data:`BATCH_XLA_OPTIONS` where JAX's default backend is the CPU
    (decided once, here: a plain ``jax.jit`` dispatches faster than a wrapper that
    checks the backend at each call)."""
    if jax.default_backend() != "cpu":
        return jax.jit(fn)
    from ._compile import supported_options

    return jax.jit(fn, compiler_options=supported_options(BATCH_XLA_OPTIONS))


def _packed(core, n: int):
    """``(flat, flat_batch, unpack)`` for ``core(q_start, q_goal) -> Plan``: jitted functions
    of the start and goal side by side (``(2n,)``, or ``(B, 2n)`` for a batch) returning
    the plan as one float array, and the host function rebuilding the :class:`Plan` of
    NumPy arrays from it. A jitted call pays for each buffer it takes and returns; a Plan
    has over twenty, which on a CPU cost more than a third of a single plan's time."""
    dtype = jnp.asarray(0.0).dtype
    spec = jax.ShapeDtypeStruct((n,), dtype)
    leaves = jax.tree.leaves(jax.eval_shape(core, spec, spec))
    sizes = [int(np.prod(x.shape, dtype=int)) for x in leaves]
    ends = np.cumsum(sizes)
    # (start, stop, shape, dtype or None where the float value is already the field's)
    fields = [(int(e - k), int(e), tuple(x.shape), None if x.dtype == dtype else x.dtype)
              for x, e, k in zip(leaves, ends, sizes)]

    def flat(x):
        return jnp.concatenate([jnp.ravel(y).astype(dtype) for y in jax.tree.leaves(core(x[:n], x[n:]))])

    def flat_batch(x):
        out = jax.tree.leaves(jax.vmap(core)(x[:, :n], x[:, n:]))
        return jnp.concatenate([y.reshape(y.shape[0], -1).astype(dtype) for y in out], axis=1)

    cast = [(i, d) for i, (_, _, _, d) in enumerate(fields) if d is not None]

    def unpack(values) -> Plan:
        values = np.asarray(values)
        if values.ndim == 1:
            out = [values[a:b].reshape(shape) for a, b, shape, _ in fields]
        else:
            B = values.shape[0]
            out = [values[:, a:b].reshape((B,) + shape) for a, b, shape, _ in fields]
        for i, d in cast:
            out[i] = out[i].astype(d)
        return Plan(*out)

    unpack.columns = {name: (a, b) for name, (a, b, _, _) in zip(Plan._fields, fields)}
    # (the single plan as _plan compiles it, with the same options: the same program, bit for bit)
    return _options_jit(flat), _options_jit(flat_batch), unpack


def _load(model):
    from jtraj import anfis

    return model if isinstance(model, (anfis.Model, anfis.Ensemble)) else anfis.load(model)


def model_inputs(meta: dict, robot, q, qd, q_goal, k, N: int):
    """The inputs of a ``nefotc`` or ``nefumop`` model (as
    :func:`jtraj.mappings.view` builds them, from the model's ``goal_inputs`` and
    ``phase_input`` metadata) at the state ``(q, qd)`` of step ``k`` towards ``q_goal``."""
    if meta["mapping"] == "nefotc":
        x, xd, xg = q, qd, q_goal
    else:
        x, xd = jax.jvp(robot.forward_kinematics, (q,), (qd,))
        xg = robot.forward_kinematics(q_goal)
    from jtraj.mappings import goal_blocks

    parts = goal_blocks(x, xd, xg, meta.get("goal_inputs"))
    if meta.get("phase_input"):
        parts.append(jnp.full((1,), k / N, x.dtype))
    return jnp.concatenate(parts)


class Planner:
    """``Planner(model)`` (or a model path); ``plan(q_start, q_goal)`` -> :class:`Plan`.

    ``model``: of mapping ``plan`` (open loop), or ``nefotc`` together with ``periods``,
    a ``nefumop`` model (or path) trained on the same dataset (closed loop; see the
    module doc). ``robot`` defaults to the one named in the model's metadata, with the
    dataset's ``h_max`` where the metadata records it; a robot of another name or number
    of joints than the model's is refused (the same robot with other limits is taken: the
    repair keeps the plans within them). ``weights`` (a :class:`jtraj.Weights`) default
    to the dataset's (the model's metadata ``"weights"``), else ``Weights()``: the cost
    the plan reports and the repair's time scaling minimises; weights other than the ones
    the model records are refused, since its predictions are optima of those
    (:meth:`query`'s ``weights=`` refines a plan for other weights). ``correct``: apply the
    feasibility repair (default) or return the raw prediction; ``switch``, ``effort``:
    with the repair's switching-profile candidates (default) and its least-effort step
    candidates (off by default: on held-out serial3 pairs they lower no plan's cost once
    the switching candidates run, and cost more than half the batch's time;
    :func:`jtraj.repair.make_repair`); ``projection``: with the candidate of the model's
    own accelerations projected onto the goal (default; ``False`` keeps the switching
    profiles on the model's periods alone, about a fifth less CPU time per plan: on 1000
    fresh serial3 pairs the projection won 5 %, by at most 3 % of the cost). The
    projection on uniform periods is left out (it won 6 of those 1000 pairs, by at most
    0.54 %). ``trapezoid``: with the synchronised trapezoidal velocity profile
    (:func:`jtraj.repair.trapezoid_profile`; default: where the robot has velocity and
    acceleration bounds). It needs no prediction: on 1024 fresh pairs of a panda dataset's
    law (N = 40) it is the cheapest candidate for 978, and the held-out plans' median cost
    gap is 1.3 % with it against 3.1 % without; on serial3 it wins 225 of 4096 and costs
    about a fifth of the batch's throughput (``trapezoid=False`` leaves it out).
    ``positions``: bend the candidates' paths inside the position constraints
    (:func:`jtraj.repair.position_step`; default: where the robot has path constraints,
    as a parallel robot's leg-singularity margins). On 4,096 fresh parallel3 pairs of a
    300-pair dataset's law it raises the feasible plans from 96.3 % to 98.5 %; the rest
    need more time than ``N h_max`` allows along the candidates' paths (half of the 16
    examined are infeasible for the exact solver too). A batch runs the repair without
    the step first and only the plans it flags (:attr:`Plan.bent`) again with it, in
    calls of ``bend_chunk`` pairs (:data:`BEND_CHUNK`).

    Coverage (``coverage_distance``, ``coverage_box``, ``ood``; :mod:`jtraj.coverage`):
    with the training pairs in the model's metadata (models from
    :func:`jtraj.mappings.train_mapping`), the distance to the nearest one against
    ``coverage_radius`` and the distance outside their box; otherwise, for a plan model,
    the distance outside the model's input box (``coverage_kind`` says which); a
    closed-loop model without training pairs has no coverage (``coverage_kind`` None,
    never flagged).
    """

    def __init__(self, model, robot=None, *, periods=None, weights=None, correct: bool = True,
                 effort: bool = False, switch: bool = True, projection: bool = True, trapezoid: bool | None = None,
                 positions: bool | None = None, tol: float = 1e-6, goal_tol: float = 1e-6):
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
        for name, x in (("correct", correct), ("effort", effort), ("switch", switch), ("projection", projection)):
            if not isinstance(x, bool):
                raise ValueError(f"{name} must be True or False, got {x!r}")
        for name, x in (("trapezoid", trapezoid), ("positions", positions)):
            if x is not None and not isinstance(x, bool):
                raise ValueError(f"{name} must be None, True or False, got {x!r}")
        for name, x in (("tol", tol), ("goal_tol", goal_tol)):
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not np.isfinite(x) or x < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {x!r}")
        self.model, self.periods = model, periods
        if robot is None:
            robot = robots.from_metadata(meta)
        self.robot = robot
        self.n = self.robot.n
        self.N = int(meta["N"])
        if meta["mapping"] == "plan":
            if model.n_inputs != 2 * self.n or model.n_outputs != self.N * (self.n + 1):
                raise ValueError(f"model shapes ({model.n_inputs} inputs, {model.n_outputs} outputs) do not "
                                 f"match robot {getattr(robot, 'name', meta['robot'])} (n = {self.n}) with "
                                 f"N = {self.N}")
        else:
            z = jnp.zeros(self.n)
            for m in (model, periods):
                try:
                    d = model_inputs(m.metadata, self.robot, z, z, z, 0, self.N).shape[0]
                except (TypeError, ValueError) as e:
                    raise ValueError(f"the {m.metadata['mapping']} model does not fit the robot: {e}") from None
                if d != m.n_inputs:
                    raise ValueError(f"the {m.metadata['mapping']} model has {m.n_inputs} inputs, the robot's "
                                     f"state gives {d}")
        if meta.get("robot") and getattr(robot, "name", meta["robot"]) != meta["robot"]:
            raise ValueError(f"robot: the model was trained on optima of robot {meta['robot']!r}, got robot "
                             f"{robot.name!r} (a URDF arm is named by jtraj.robots.from_urdf(..., name=...))")
        if correct and getattr(robot, "path_equalities", None) is not None:
            raise ValueError(f"robot: {robot.name!r} has path equalities (a nonholonomic constraint on its "
                             f"velocities), which the repair's time scaling and goal projection do not keep; "
                             f"plan it with jtraj.solve, or with correct=False for the raw prediction")
        import jtraj

        trained = jtraj.Weights.parse(meta["weights"]) if meta.get("weights") else None
        if weights is None:
            weights = jtraj.Weights() if trained is None else trained
        elif trained is not None and not _same_weights(weights, trained):
            raise ValueError(f"weights: the model was trained on optima for weights {meta['weights']!r}, which "
                             f"its plans predict; got other weights. Leave weights=None, or refine a plan for "
                             f"other weights with Planner.query(..., refine=True, weights=...)")
        self.weights = weights
        self.tol, self.goal_tol, self.correct, self.effort = float(tol), float(goal_tol), correct, effort
        self.switch, self.projection, self.trapezoid, self.positions = switch, projection, trapezoid, positions
        if correct and not (projection or switch or effort or trapezoid is not False):
            raise ValueError("projection, switch, effort and trapezoid are all False: the repair has no candidate")
        self._coverage()
        core = self._core()
        # device arrays, for use inside other jitted code
        self._plan = _options_jit(core)
        self._plan_batch = _options_jit(jax.vmap(core))
        # what plan() runs: one output buffer, NumPy arrays on the host
        self._flat, self._flat_batch, self._unpack = _packed(core, self.n)
        # a batch's programs: where the repair bends paths, the first runs it without the
        # position step and flags the plans that need it, the second runs those again with
        # it (under vmap the step's branch is a select, which every plan would pay for)
        self._bend_batch = None
        if core.bends:
            self._bend_batch = self._flat_batch
            self._flat_batch = _packed(self._core("flag"), self.n)[1]
        self.chunk, self.threads, self._pool = CHUNK, THREADS, None
        self.bend_chunk = BEND_CHUNK
        self._serial = None  # whether the programs hold a SERIAL_CUSTOM_CALLS call (_is_serial)
        self._lock = threading.Lock()

    def _coverage(self):
        from . import coverage

        meta = self.model.metadata
        if meta.get("train_pairs"):
            pairs = np.asarray(meta["train_pairs"], float)
            if pairs.ndim != 2 or pairs.shape[1] != 2 * self.n:
                raise ValueError(f"the model's train_pairs have shape {pairs.shape}, expected (P, {2 * self.n})")
            self.coverage_kind = "nearest training pair"
            self.coverage_radius = coverage.radius(pairs)  # (recomputed: milliseconds for 1000s of pairs)
            self._distance = coverage.distance_fn(pairs)
        elif meta["mapping"] == "plan":
            m = self.model.members[0] if hasattr(self.model, "members") else self.model
            self.coverage_kind = "model input box"
            self.coverage_radius = 0.0
            self._distance = coverage.box_distance_fn(m.x_lo, m.x_span)
        else:
            self.coverage_kind, self.coverage_radius = None, 0.0
            self._distance = lambda x: (jnp.zeros((), x.dtype), jnp.zeros((), x.dtype))

    def _predict(self):
        """``(q_start, q_goal) -> (q, qd, v, h)`` of the raw prediction (periods clipped into
        the box); ``q`` and ``qd`` None for a plan model (:meth:`_core` integrates them
        where it needs them)."""
        lim = self.robot.limits
        N, n = self.N, self.n
        if self.periods is None:
            f = self.model.predict_fn()

            def predict(qs, qg):
                y = f(jnp.concatenate([qs, qg])[None, :])[0]
                v = y[: N * n].reshape(N, n)
                h = jnp.clip(y[N * n:], lim.h_min, lim.h_max)
                return None, None, v, h
            return predict
        ctl, per = self.model.predict_fn(), self.periods.predict_fn()
        mc, mp = self.model.metadata, self.periods.metadata
        rb = self.robot
        tau_max = jnp.inf if lim.tau_max is None else lim.tau_max

        def predict(qs, qg):
            def step(state, k):
                q, qd = state
                tau = jnp.clip(ctl(model_inputs(mc, rb, q, qd, qg, k, N)[None])[0], -tau_max, tau_max)
                h = jnp.clip(per(model_inputs(mp, rb, q, qd, qg, k, N)[None])[0, -1], lim.h_min, lim.h_max)
                a = rb.forward_dynamics(q, qd, tau)
                return (q + h * qd + 0.5 * h * h * a, qd + h * a), (q, qd, a, h)

            (qN, qdN), (q, qd, v, h) = jax.lax.scan(step, (qs, jnp.zeros_like(qs)), jnp.arange(N))
            return jnp.concatenate([q, qN[None]]), jnp.concatenate([qd, qdN[None]]), v, h
        return predict

    def _core(self, positions=None):
        """``core(q_start, q_goal) -> Plan``; ``positions`` as :func:`jtraj.repair.make_repair`'s
        (default: the planner's)."""
        from .repair import cost_of, make_repair, rollout, terminal_rows, violation_parts

        # a spatial arm's efforts over the repair's samples in the body-frame Newton-Euler
        # form (the same efforts up to rounding; SpatialSerial.newton_euler): on the panda
        # a single plan about 1.5x and a batch about 1.7x faster than in the world form
        predict, rb = self._predict(), self.robot
        if getattr(rb, "newton_euler", None) == "world":
            rb = rb.replace(newton_euler="bodies")
        repair = (make_repair(rb, self.weights, effort=self.effort, switch=self.switch,
                                  projection=self.projection, uniform_projection=False, trapezoid=self.trapezoid,
                                  positions=self.positions if positions is None else positions)
                  if self.correct else None)
        weights, distance, radius = self.weights, self._distance, self.coverage_radius

        def core(qs, qg):
            q, qd, v, h = predict(qs, qg)
            if q is None and repair is not None:
                # the raw prediction's end from rest: q_N = q_0 + sum_k c_k v_k (jtraj.repair)
                pred_err = jnp.linalg.norm(qs + jnp.sum(terminal_rows(h)[1][:, None] * v, axis=0) - qg)
            else:
                if q is None:
                    q, qd = rollout(qs, jnp.zeros_like(qs), v, h)
                pred_err = jnp.linalg.norm(q[-1] - qg)
            if repair is None:
                tau = jax.vmap(rb.inverse_dynamics)(q[:-1], qd[:-1], v)
                cost, s, pick = cost_of(rb, weights, q, qd, tau, h), jnp.ones(()), jnp.asarray(-1)
                bent = jnp.zeros((), bool)
            else:
                z = jnp.zeros_like(qs)
                r = repair(qs, z, qg, z, v, h)
                q, qd, v, h, tau, cost, s, pick, bent = r.q, r.qd, r.v, r.h, r.tau, r.cost, r.scale, r.candidate, r.bent
            parts = violation_parts(rb, q, qd, v, tau, h)
            d, box = distance(jnp.concatenate([qs, qg]))
            return Plan(q, qd, v, tau, h, jnp.sum(h), cost, jnp.max(jnp.stack(parts)), *parts,
                        jnp.linalg.norm(q[-1] - qg), jnp.linalg.norm(qd[-1]), pred_err, s, pick, bent, d, box,
                        (d > radius) | (box > BOX_MARGIN))
        self.candidates = () if repair is None else repair.candidates
        core.bends = repair is not None and repair.positions is True  # (the step runs in core)
        return core

    def _inputs(self, q_start, q_goal):
        """The start and goal side by side, ``(2n,)`` or ``(B, 2n)`` floats, checked on the
        host (no device round trip): the messages of :func:`jtraj._checks.check_state`."""
        out = []
        for x, name in ((q_start, "q_start"), (q_goal, "q_goal")):
            try:
                arr = np.asarray(x, dtype=float)
            except (TypeError, ValueError) as err:
                raise ValueError(f"{name} must be an array of numbers, got {x!r}") from err
            if arr.ndim == 0 or arr.shape[-1] != self.n:
                raise ValueError(f"{name} must have shape ({self.n},) (or (..., {self.n})), got shape {arr.shape}")
            out.append(arr)
        qs, qg = out
        if qs.ndim > 2 or qs.shape != qg.shape:
            raise ValueError(f"q_start and q_goal must both have shape ({self.n},) or (B, {self.n}), got "
                             f"{qs.shape} and {qg.shape}")
        x = np.concatenate([qs, qg], axis=-1)
        if not np.isfinite(x).all():
            name = "q_start" if not np.isfinite(qs).all() else "q_goal"
            raise ValueError(f"{name} must be finite (no NaN or inf)")
        return x

    def plan(self, q_start, q_goal) -> Plan:
        """The plan and its report, as NumPy arrays. ``q_start``, ``q_goal``: ``(n,)``, or
        ``(B, n)`` for a batch (every field of the Plan then has a leading B axis).
        ``ValueError`` where they are not finite numbers of those shapes. Joint, workspace
        and path limits are not checked here (the fast path, where a batch keeps a result
        per pair): a start or goal outside them gives a plan whose violations show it
        (``q_violation`` > 0, :meth:`feasible` False), usually flagged out of distribution
        too. :meth:`check` and :meth:`query` refuse such a pair.

        One jitted call for one pair or a batch of up to ``self.chunk`` pairs (default
        :data:`CHUNK`); a larger batch runs as calls of ``self.chunk`` pairs on
        ``self.threads`` threads (default :data:`THREADS`), the last call padded with
        copies of the batch's first pair."""
        x = self._inputs(q_start, q_goal)
        return self._unpack(self._call(self._flat, x) if x.ndim == 1 else self._batch(x))

    def _is_serial(self, fn, x) -> bool:
        """Whether the planner's programs hold a :data:`SERIAL_CUSTOM_CALLS` call (read
        once, from ``fn``'s program on ``x``: the single and the batched program run the
        same dynamics)."""
        if self._serial is None:
            self._serial = _holds_custom_call(fn, x, SERIAL_CUSTOM_CALLS)
        return self._serial

    def _call(self, fn, x):
        """``fn(x)`` as a NumPy array; one such call at a time (from any thread) where the
        programs hold a :data:`SERIAL_CUSTOM_CALLS` call."""
        if not self._is_serial(fn, x):
            return np.asarray(fn(x))
        with self._lock:
            return np.asarray(fn(x))

    def _batch(self, x):
        """The packed plans of a (B, 2n) batch of starts and goals side by side (:meth:`plan`)."""
        B, C = x.shape[0], int(self.chunk)
        if B <= C:
            return self._bend(x, self._call(self._flat_batch, x))
        pad = (-B) % C
        if pad:
            x = np.concatenate([x, np.repeat(x[:1], pad, axis=0)])
        parts = [x[i:i + C] for i in range(0, B + pad, C)]
        run = lambda p: self._bend(p, self._call(self._flat_batch, p))  # noqa: E731  (waits for the result)
        if self.threads > 1 and not self._is_serial(self._flat_batch, parts[0]):
            if self._pool is None:
                from concurrent.futures import ThreadPoolExecutor

                self._pool = ThreadPoolExecutor(self.threads)
            out = list(self._pool.map(run, parts))
        else:
            out = [run(p) for p in parts]
        return np.concatenate(out)[:B]

    def _bend(self, x, values):
        """The packed plans ``values`` of the pairs ``x`` (B, 2n), those flagged ``bent``
        planned again with the position step (calls of ``self.bend_chunk`` pairs, the last
        one padded): bit for bit the plans of the batch program that takes the step where
        any candidate crosses a row (under ``vmap`` a select that every plan pays for), as
        the single-plan program does."""
        if self._bend_batch is None:
            return values
        a, _ = self._unpack.columns["bent"]
        rows = np.flatnonzero(values[:, a] != 0)
        if rows.size == 0:
            return values
        S = int(self.bend_chunk)
        sub = x[rows]
        pad = (-rows.size) % S
        if pad:
            sub = np.concatenate([sub, np.repeat(sub[:1], pad, axis=0)])
        values = np.array(values)
        values[rows] = np.concatenate([self._call(self._bend_batch, sub[i:i + S])
                                       for i in range(0, sub.shape[0], S)])[:rows.size]
        return values

    def check(self, q_start, q_goal) -> None:
        """``ValueError`` where ``q_start`` or ``q_goal`` is not what ``jtraj.Problem``
        accepts of a start and a goal: an (n,) finite vector inside the robot's joint box,
        workspace box and path constraints (:func:`jtraj.problem.check_configurations`)."""
        from ._checks import check_state
        from .problem import check_configurations

        check_configurations(self.robot, {"q_start": check_state(q_start, "q_start", self.n).reshape(self.n),
                                          "q_goal": check_state(q_goal, "q_goal", self.n).reshape(self.n)})

    __call__ = plan

    def feasible(self, p: Plan):
        """Whether the plan meets every box within ``tol`` (relative) and the goal position
        and velocity within ``goal_tol``: a bool, or a (B,) bool array for a batch."""
        ok = ((np.asarray(p.violation) <= self.tol) & (np.asarray(p.goal_error) <= self.goal_tol)
              & (np.asarray(p.goal_velocity) <= self.goal_tol))
        return bool(ok) if ok.ndim == 0 else ok

    def report(self, p: Plan) -> dict:
        """A single plan as a JSON-able dict (the trajectory included)."""
        out = dict(T=float(p.T), cost=float(p.cost), feasible=self.feasible(p), corrected=self.correct,
                   violation=float(p.violation))
        for k in ("tau_violation", "qd_violation", "qdd_violation", "q_violation", "h_violation", "jerk_violation",
                  "goal_error", "goal_velocity", "predicted_goal_error", "scale"):
            out[k] = float(getattr(p, k))
        out["candidate"] = self.candidates[int(p.candidate)] if int(p.candidate) >= 0 else None
        out["bent"] = bool(p.bent)
        out["coverage"] = dict(kind=self.coverage_kind, distance=float(p.coverage_distance),
                               radius=self.coverage_radius, outside_box=float(p.coverage_box),
                               out_of_distribution=bool(p.ood))
        out["out_of_distribution"] = bool(p.ood)
        for k in ("q", "qd", "v", "tau", "h"):
            out[k] = np.asarray(getattr(p, k)).tolist()
        return out

    def query(self, q_start, q_goal, *, refine: bool = False, weights=None, solver=None,
              warm: str = "primal", N: int | None = None, options=None, compare: bool = True) -> dict:
        """Plan, report feasibility, cost and coverage, and optionally refine with the exact
        solver.

        ``q_start`` and ``q_goal`` are checked first (:meth:`check`: ``ValueError``).
        ``N``: intervals of the refined problem, by default the model's; another N
        warm-starts from the plan re-sampled onto N equal periods (the plan's acceleration
        at each new interval's midpoint), which keeps the plan's total time.

        ``weights`` of the refined problem default to the planner's (the training
        dataset's); ``solver`` is its solver (:class:`jtraj.IPM` or
        :class:`jtraj.AugmentedLagrangian`, or :class:`jtraj.Auto`; ``options``, a
        :class:`jtraj.SolverOptions`, is deprecated as in :func:`jtraj.solve`). Without
        one, the solve from the plan is ``jtraj.Auto(ipm=jtraj.IPM(**WARM_IPM))``
        (:data:`WARM_IPM`: a short barrier schedule from a start kept near the plan, a small
        first Hessian shift) and
        the comparison's ``jtraj.Auto()``. Returns
        :meth:`report`'s dict with ``seconds`` (the plan's wall time,
        Python included); with ``refine`` it adds the solver's status, iterations, time,
        cost and trajectory (``refined_q``, ``refined_qd``, ``refined_v``, ``refined_tau``,
        ``refined_h``), the plan's ``gap`` to the refined optimum (``(cost - refined_cost) /
        refined_cost``, where the refined solve converged with the plan's weights and N),
        and, unless ``compare=False``, the same solve from the solver's default initial
        guess (the cycloid, slowed to meet the torque bounds) for comparison
        (``cycloidal_iterations``, ``cycloidal_seconds``, ...). That solve runs first: in a
        fresh process it pays the compilation both share, so ``refined_seconds`` is a
        compiled solve's time; with ``compare=False`` the refined solve pays it.

        ``warm``: ``"primal"`` (default) starts the solver at the plan with the
        multipliers and penalty of a cold start; ``"full"`` is ``jtraj.solve(init=...)``,
        which also estimates multipliers at the plan and starts the penalty at
        ``penalty_max / 100`` (``jtraj.solve(..., warm=)``; benchmarks/bench_online.py
        compares them)."""
        from jtraj.solver.api import solver_argument

        solver = solver_argument(solver, options)
        warm_solver = solver
        if solver is None:
            import jtraj

            warm_solver = jtraj.Auto(ipm=jtraj.IPM(**WARM_IPM))
        if warm not in ("primal", "full"):
            raise ValueError(f"warm must be 'primal' or 'full', got {warm!r}")
        if not isinstance(compare, bool):
            raise ValueError(f"compare must be True or False, got {compare!r}")
        if N is not None and (isinstance(N, bool) or not isinstance(N, (int, np.integer)) or N < 2):
            raise ValueError(f"N must be an integer >= 2 or None, got {N!r}")
        N = self.N if N is None else int(N)
        self.check(q_start, q_goal)
        t0 = time.perf_counter()
        p = jax.block_until_ready(self.plan(q_start, q_goal))
        out = dict(seconds=time.perf_counter() - t0, **self.report(p))
        if self.robot.limits.tau_max is not None and np.all(np.isfinite(np.asarray(p.q))):
            # the plan holds v_k over each interval too: its efforts between the samples
            from .resample import intersample_effort

            out["effort_between_samples"] = float(intersample_effort(
                {"q": p.q, "qd": p.qd, "v": p.v, "h": p.h}, self.robot))
        if refine:
            import jtraj

            same_cost = weights is None
            prob = jtraj.Problem(self.robot, np.asarray(q_start, float), np.asarray(q_goal, float), N=N,
                                 weights=self.weights if weights is None else weights)
            out["refined_N"] = N
            # cycloidal first: in a fresh process it pays the compilation (shared with the
            # warm solve), so refined_seconds is a compiled solve's time
            runs = [("cycloidal", None)] if compare else []
            for label, init in runs + [("refined", _resampled(p.v, p.h, N, self.robot.limits))]:
                t1 = time.perf_counter()
                if init is None:
                    sol = jtraj.solve(prob, solver=solver)
                else:
                    sol = jtraj.solve(prob, init=init, solver=warm_solver, warm=warm)
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
            for k in ("q", "qd", "v", "tau", "h"):  # the refined trajectory
                out[f"refined_{k}"] = np.asarray(getattr(sol, k)).tolist()
            if same_cost and N == self.N and out["refined_converged"]:
                out["gap"] = (out["cost"] - out["refined_cost"]) / abs(out["refined_cost"])
        return out


def _same_weights(a, b) -> bool:
    """Whether two :class:`jtraj.Weights` give the same cost."""
    def same(x, y):
        if x is None or y is None:
            return x is None and y is None
        x, y = np.asarray(x, float), np.asarray(y, float)
        return x.shape == y.shape and bool(np.allclose(x, y, rtol=1e-12, atol=0.0))

    return all(same(getattr(a, k), getattr(b, k)) for k in ("time", "energy", "kinetic", "singularity", "U", "Q"))


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
