"""Gradient checking: autodiff against a hand-written discrete adjoint and finite differences.

The solver gets every derivative from JAX. This module checks those derivatives the
way the thesis obtained them: by the backward co-state (adjoint) recursion of the
decoupled discrete model, written out explicitly, and by central finite differences.

Functions checked, both as functions of the physical unknowns ``(v, h)``
(accelerations ``v`` (N, n) and sampling periods ``h`` (N,)):

* the cost ``J(v, h) = sum_k l_k(w_k)``, ``l_k`` the stage cost of
  :meth:`jtraj.transcription.Transcription.stage_cost_terms`;
* the augmented Lagrangian ``L(v, h; lambda, rho, mu)`` of the solver
  (:meth:`jtraj.solver.nlp.NLP.al_value`, the very function the solver minimises), with
  multipliers ``lambda`` (any sign) on the equalities and ``rho >= 0`` on the
  inequalities of :meth:`~jtraj.transcription.Transcription.stage_constraints`, and the
  global bound on ``T = sum h``.

Discrete adjoint (derivation)
-----------------------------
Stage vectors ``w_k = (q_k, qd_k, v_k, h_k)`` for ``k = 0..N`` (``v_N = 0, h_N = 0``: row
N only carries terminal terms), the decoupled model

    q_{k+1}  = q_k + h_k qd_k + h_k^2/2 v_k            (1)
    qd_{k+1} = qd_k + h_k v_k                           (2)

with ``q_0, qd_0`` given, and an objective ``F = sum_{k=0}^{N} l_k(w_k) + G(h)``
(``G`` the term that couples samples: the PHR terms of ``T <= T_max`` and of the jerk
rows of a ``Problem(jerk=True)``, which depend on (v, h) directly). Adjoin the
model with co-states ``p_{k+1} = (p_q,k+1, p_qd,k+1)``:

    F = sum_k l_k + G + sum_{k<N} p_q,k+1 . (q_k + h_k qd_k + h_k^2/2 v_k - q_{k+1})
                      + sum_{k<N} p_qd,k+1 . (qd_k + h_k v_k - qd_{k+1}).

Choosing the co-states so that the (implicit) derivatives with respect to the states
vanish, ``dF/dq_k = dF/dqd_k = 0`` for ``k = 1..N``, gives the terminal condition and
the backward recursion (transposed Jacobian ``[[I, h_k I], [0, I]]^T`` of (1)-(2)):

    p_q,N  = dl_N/dq_N,      p_qd,N = dl_N/dqd_N
    p_q,k  = dl_k/dq_k  + p_q,k+1                              k = N-1 .. 1
    p_qd,k = dl_k/dqd_k + h_k p_q,k+1 + p_qd,k+1

``p_k`` is the total derivative of the cost-to-go ``sum_{j>=k} l_j`` with respect to
the state ``x_k``. The gradient is then the partial derivative of the adjoined
function with respect to the controls and periods:

    dF/dv_k = dl_k/dv_k + h_k^2/2 p_q,k+1 + h_k p_qd,k+1
    dF/dh_k = dl_k/dh_k + (qd_k + h_k v_k) . p_q,k+1 + v_k . p_qd,k+1 + dG/dh_k

for ``k = 0..N-1`` (``p_0`` is not needed: the start state is fixed). The recursion is
written by hand below (:func:`discrete_adjoint`), and so is the forward pass
(:func:`forward_states`, not the transcription's closed form); the per-stage partial derivatives
``dl_k/dw_k`` come from local (per-sample) autodiff of a stage function, and for the
augmented Lagrangian the stage function is rebuilt here from the constraints of
:meth:`~jtraj.transcription.Transcription.stage_constraints` with the textbook
formulas (docs/science.md, the augmented Lagrangian)

    equalities c:    lambda . c + mu/2 ||c||^2
    inequalities g:  (||max(0, rho + mu g)||^2 - ||rho||^2) / (2 mu)    (PHR)

so the check also covers the solver's own AL formula. (As in the solver, these terms
are *not* multiplied by h_k; the thesis weights them by h_k.)

Finite differences: central differences of the same functions in the *scaled*
decision vector ``z`` of :class:`~jtraj.transcription.Layout` (``v / qdd_max``,
``h / h_max``, all O(1)), step ``fd_step`` (default ``1e-6``) in z, i.e. a step of
``1e-6 qdd_max`` on v and ``1e-6 h_max`` on h, converted back to ``(v, h)``. Truncation
error ~ step^2, round-off ~ 1e-16 |F| / step: both far below the 1e-6 tolerance.

Error measure: for each block (v and h separately, so that the small block cannot hide
behind the large one) ``||a - b||_inf / max(||a||_inf, ||b||_inf)`` (0 when both are
0); the reported figure is the larger of the two blocks and the maximum over points.

Use :func:`gradcheck` per robot (or ``jtraj gradcheck --robot NAME|all``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from ._compile import cpu_jit

TOL_ADJOINT = 1e-8
TOL_FD = 1e-6
DEFAULT_FD_STEP = 1e-6


def default_weights():
    """Weights that switch on every cost term (time, energy, kinetic, singularity)."""
    from .problem import Weights

    return Weights(time=1.0, energy=1.0, kinetic=0.1, singularity=0.01)


# ----------------------------------------------------------------------------------------
# the functions and their gradients


def _nlp(problem):
    from .solver.nlp import NLP as _NLP
    from .transcription import Transcription

    tr = Transcription("decoupled")
    return _NLP(problem=problem, tr=tr, layout=tr.layout(problem), sd=tr.stage_data(problem))


def cost_value(problem, v, h):
    """J(v, h): the solver's cost, summed over samples."""
    nlp = _nlp(problem)
    return sum(nlp.cost_terms(nlp.layout.pack(v, h)).values())


def al_value(problem, v, h, mult, mu):
    """L(v, h; mult, mu): the solver's augmented Lagrangian (``_NLP.al_value``)."""
    nlp = _nlp(problem)
    return nlp.al_value(nlp.layout.pack(v, h), mult, mu)


def _stage_cost(problem, tr, w, sdk):
    return sum(tr.stage_cost_terms(problem, w, sdk).values())


def _stage_pair(problem, tr, w, sdk, eq_k, ineq_k, mu):
    """(stage cost, stage AL): the AL rebuilt from the constraints and the textbook
    formulas."""
    cost = _stage_cost(problem, tr, w, sdk)
    val = cost
    eq, ineq = tr.stage_constraints(problem, w, sdk)
    for key, c in eq.items():
        val = val + jnp.vdot(eq_k[key], c) + 0.5 * mu * jnp.vdot(c, c)
    for key, g in ineq.items():
        r = ineq_k[key]
        val = val + (jnp.sum(jnp.maximum(0.0, r + mu * g) ** 2) - jnp.sum(r**2)) / (2 * mu)
    return jnp.stack([cost, val])


def _global_al(problem, v, h, rho_glob, mu):
    """G(v, h): PHR term of the bound T = sum h <= T_max and, with ``problem.jerk``, of
    the jerk rows ``(+-(v_{k+1} - v_k) - J (h_k + h_{k+1}) / 2) / (J h_max) <= 0``, per
    joint j and k = 0..N-2 in the order (k, j, sign) (normalised like the solver)."""
    finite = jnp.isfinite(problem.T_max)
    T_max = jnp.where(finite, problem.T_max, 1.0)
    rows = [jnp.where(finite, jnp.sum(h) / T_max - 1.0, -1.0)]
    if problem.jerk:
        lim = problem.robot.limits
        N, n = v.shape
        for k in range(N - 1):
            for j in range(n):
                J = lim.qddd_max[j]
                reach = J * (h[k] + h[k + 1]) / 2
                rows += [(v[k + 1, j] - v[k, j] - reach) / (J * lim.h_max),
                         (v[k, j] - v[k + 1, j] - reach) / (J * lim.h_max)]
    g = jnp.stack(rows)
    return (jnp.sum(jnp.maximum(0.0, rho_glob + mu * g) ** 2) - jnp.sum(rho_glob**2)) / (2 * mu)


def discrete_adjoint(v, h, q, qd, dl):
    """The hand-written backward co-state recursion of the decoupled model.

    Args:
        v: (N, n) accelerations; h: (N,) periods.
        q, qd: (N+1, n) states of the forward recursion.
        dl: per-sample partials ``(dl/dq, dl/dqd, dl/dv, dl/dh)`` with shapes
            (N+1, n), (N+1, n), (N+1, n), (N+1,) (row N: terminal terms; its v and h
            entries are ignored).

    Returns ``(dF/dv (N, n), dF/dh (N,))`` without any global term. See the module
    docstring for the derivation.
    """
    lq, lqd, lv, lh = dl
    N = h.shape[0]
    p_q, p_qd = lq[N], lqd[N]  # terminal co-states
    gv = [None] * N
    gh = [None] * N
    for k in range(N - 1, -1, -1):  # backward in time; p_q, p_qd hold p_{k+1}
        gv[k] = lv[k] + 0.5 * h[k] ** 2 * p_q + h[k] * p_qd
        gh[k] = lh[k] + jnp.dot(qd[k] + h[k] * v[k], p_q) + jnp.dot(v[k], p_qd)
        p_q, p_qd = lq[k] + p_q, lqd[k] + h[k] * p_q + p_qd  # p_k from p_{k+1}
    return jnp.stack(gv), jnp.stack(gh)


def forward_states(q0, qd0, v, h):
    """The decoupled model (1)-(2) stepped explicitly: (q, qd), each (N+1, n). Written
    here rather than taken from :func:`jtraj.transcription.integrate`, so that a slip
    in the transcription's recursion shows up as a disagreement."""
    q, qd = [q0], [qd0]
    for k in range(h.shape[0]):
        q.append(q[k] + h[k] * qd[k] + 0.5 * h[k] ** 2 * v[k])
        qd.append(qd[k] + h[k] * v[k])
    return jnp.stack(q), jnp.stack(qd)


AdjointFn = Callable[..., tuple]


def adjoint_gradients(problem, v, h, mult, mu, *, adjoint: AdjointFn = discrete_adjoint):
    """(dJ/dv, dJ/dh), (dL/dv, dL/dh) from the discrete adjoint; ``adjoint`` replaceable
    (tests pass a deliberately wrong one)."""
    from .transcription import Transcription

    tr = Transcription("decoupled")
    sd = tr.stage_data(problem)
    n = problem.robot.n
    q, qd = forward_states(problem.q_start, problem.qd_start, v, h)  # forward pass
    # stage vectors w_k = (q_k, qd_k, v_k, h_k); row N carries v_N = 0, h_N = 0
    W = jnp.concatenate([q, qd, jnp.concatenate([v, jnp.zeros((1, v.shape[1]))]),
                         jnp.concatenate([h, jnp.zeros(1)])[:, None]], axis=1)

    def split(g):
        return g[:, :n], g[:, n:2 * n], g[:, 2 * n:-1], g[:, -1]

    # per-sample partials of both stage functions in one local reverse pass: (N+1, 2, nw)
    dl = jax.vmap(jax.jacrev(lambda w, s, e, i: _stage_pair(problem, tr, w, s, e, i, mu)))(
        W, sd, mult.eq, mult.ineq)
    cost = adjoint(v, h, q, qd, split(dl[:, 0]))
    gv, gh = adjoint(v, h, q, qd, split(dl[:, 1]))
    gv_glob, gh_glob = jax.grad(_global_al, argnums=(1, 2))(problem, v, h, mult.glob, mu)
    gv, gh = gv + gv_glob, gh + gh_glob
    return cost, (gv, gh)


def autodiff_gradients(problem, v, h, mult, mu):
    """jax.grad of the solver's cost and augmented Lagrangian with respect to (v, h)."""
    gc = jax.grad(cost_value, argnums=(1, 2))(problem, v, h)
    ga = jax.grad(al_value, argnums=(1, 2))(problem, v, h, mult, mu)
    return gc, ga


def fd_gradients(problem, v, h, mult, mu, step=DEFAULT_FD_STEP):
    """Central finite differences in the scaled z, converted to (v, h) gradients."""
    nlp = _nlp(problem)
    layout = nlp.layout
    z = layout.pack(v, h)
    nz = z.shape[0]
    E = step * jnp.eye(nz, dtype=z.dtype)

    def both(zz):
        return jnp.stack([sum(nlp.cost_terms(zz).values()), nlp.al_value(zz, mult, mu)])

    F = jax.vmap(both)(jnp.concatenate([z[None, :] + E, z[None, :] - E]))  # (2 nz, 2)
    gz = (F[:nz] - F[nz:]) / (2 * step)  # (nz, 2): dF/dz

    def to_vh(g):
        gv, gh = layout.unpack(g)  # unpack multiplies by the scale; a gradient divides
        return gv / layout.u_scale[None] ** 2, gh / layout.h_scale**2

    return to_vh(gz[:, 0]), to_vh(gz[:, 1])


def _rel(a, b):
    """Block-wise normwise relative error (see the module docstring)."""
    out = 0.0
    for x, y in zip(a, b):
        x, y = np.asarray(x, float), np.asarray(y, float)
        den = max(np.max(np.abs(x)), np.max(np.abs(y)))
        err = np.max(np.abs(x - y))
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            return math.inf
        out = max(out, 0.0 if den == 0 else err / den)
    return out


# The check is compiled once per robot and shape; XLA's backend optimisations buy
# nothing for a handful of evaluations and cost half the compile time on a CPU (other
# backends compile with their defaults: XLA GPU refuses optimisation level 0).
_FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


@cpu_jit(_FAST_COMPILE)
def _all_gradients(problem, v, h, mult, mu, step, adjoint):
    ad = autodiff_gradients(problem, v, h, mult, mu)
    adj = adjoint_gradients(problem, v, h, mult, mu, adjoint=adjoint)
    fd = fd_gradients(problem, v, h, mult, mu, step)
    return ad, adj, fd


def check_point(problem, v, h, mult, mu, *, fd_step=DEFAULT_FD_STEP,
                adjoint: AdjointFn = discrete_adjoint) -> dict:
    """Relative errors at one point: ``cost_adjoint``, ``cost_fd``, ``al_adjoint``,
    ``al_fd`` (autodiff against adjoint / finite differences), and gradient norms."""
    mu = jnp.asarray(mu, dtype=jnp.result_type(float))  # traced, so one compilation serves all mu
    (ad_c, ad_a), (adj_c, adj_a), (fd_c, fd_a) = _all_gradients(problem, v, h, mult, mu, fd_step, adjoint)
    return {
        "cost_adjoint": _rel(ad_c, adj_c), "cost_fd": _rel(ad_c, fd_c),
        "al_adjoint": _rel(ad_a, adj_a), "al_fd": _rel(ad_a, fd_a),
        "cost_grad_norm": float(max(np.max(np.abs(np.asarray(x))) for x in ad_c)),
        "al_grad_norm": float(max(np.max(np.abs(np.asarray(x))) for x in ad_a)),
    }


# ----------------------------------------------------------------------------------------
# random points


def _box(robot):
    """Sampling box for q: the joint box shrunk to 80 %; without one, the workspace box
    (shrunk likewise) on the coordinates that the task point copies (mobile robots,
    p = q[:d]) and +-1.2 elsewhere."""
    lim = robot.limits
    n = robot.n
    lo, hi = -1.2 * np.ones(n), 1.2 * np.ones(n)
    if lim.q_min is not None:
        qlo, qhi = np.asarray(lim.q_min, float), np.asarray(lim.q_max, float)
        lo, hi = np.where(np.isfinite(qlo), qlo, lo), np.where(np.isfinite(qhi), qhi, hi)
    elif lim.workspace is not None:
        ws = np.asarray(lim.workspace, float)
        d = ws.shape[1]
        probe = np.linspace(0.3, 0.7, n)
        try:
            copies = d <= n and np.allclose(np.asarray(robot.forward_kinematics(jnp.asarray(probe))), probe[:d])
        except Exception:
            copies = False
        if copies:
            lo[:d], hi[:d] = ws[0], ws[1]
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    return mid - 0.8 * half, mid + 0.8 * half


def _point_ok(robot, q0, qd0, v, h) -> bool:
    """States inside the joint box (where the model is assembled, for closed chains)
    and finite efforts along the trajectory."""
    from .transcription import integrate

    q, qd = integrate(jnp.asarray(q0), jnp.asarray(qd0), jnp.asarray(v), jnp.asarray(h))
    lim = robot.limits
    if lim.q_min is not None and not bool(jnp.all((q >= lim.q_min[None]) & (q <= lim.q_max[None]))):
        return False
    tau = jax.vmap(robot.inverse_dynamics)(q[:-1], qd[:-1], jnp.asarray(v))
    p = jax.vmap(robot.forward_kinematics)(q)
    return bool(jnp.all(jnp.isfinite(tau)) & jnp.all(jnp.isfinite(p)) & jnp.all(jnp.isfinite(q)))


def _nominal(robot):
    for attr in ("q_home", "q_nominal", "home"):
        q = getattr(robot, attr, None)
        if q is not None:
            q = q() if callable(q) else q
            return np.asarray(q, float)
    return None


def random_point(robot, rng: np.random.Generator, *, N: int, weights, mu=None, via: bool = True,
                 tries: int = 50):
    """A random problem and a random point (v, h, multipliers, mu) for ``robot``.

    q_start and q_goal are drawn in the joint box (or around the robot's nominal
    configuration when it has one) until :class:`~jtraj.Problem` accepts them (joint,
    velocity and workspace boxes checked); one via point at the midpoint of the start
    and goal task points and a bound ``T_max = 0.9 sum h`` (active, so its PHR term is
    exercised) are added. v is uniform in the acceleration box, h in [h_min, h_max],
    inequality multipliers uniform in [0, 2], equality multipliers standard normal, mu
    log-uniform in [1, 100] unless given. Where a fully random (v, h) drives the
    states out of the joint box or makes the efforts non-finite (closed chains out of
    assembly), the point is contracted towards the cycloidal guess,
    ``(v, h) = guess + s (random - guess)`` with ``s = 1, 1/2, 1/4, ...``.
    Returns (problem, v, h, mult, mu, info) with info = {validated, spread s, note}.
    """
    from .problem import Problem
    from .solver.certify import init_multipliers as _init_multipliers
    from .solver.nlp import Multipliers

    lim = robot.limits
    n = robot.n
    lo, hi = _box(robot)
    nominal = _nominal(robot)
    note = ""
    q0 = q1 = None
    for _ in range(tries):
        if nominal is not None:
            a = np.clip(nominal + rng.uniform(-0.1, 0.1, n) * (hi - lo), lo, hi)
            b = np.clip(nominal + rng.uniform(-0.1, 0.1, n) * (hi - lo), lo, hi)
        else:
            a, b = rng.uniform(lo, hi), rng.uniform(lo, hi)
        try:
            # joint, velocity and workspace boxes of start and goal (N large: the
            # duration does not matter at a gradient-check point)
            Problem(robot, a, b, N=100_000, weights=weights)
            extra = getattr(robot, "path_constraints", None)
            if extra is not None and not (np.all(np.asarray(extra(jnp.asarray(a))) <= 0)
                                          and np.all(np.asarray(extra(jnp.asarray(b))) <= 0)):
                continue
        except ValueError:
            continue
        q0, q1 = a, b
        break
    if q0 is None:  # keep going at an unvalidated point: derivatives are still defined
        q0, q1 = rng.uniform(lo, hi), rng.uniform(lo, hi)
        note = "no feasible start/goal found; unvalidated point"
    qdd = np.ones(n) if lim.qdd_max is None else np.asarray(lim.qdd_max, float)
    v_rand = rng.uniform(-1, 1, (N, n)) * qdd
    h_rand = rng.uniform(float(lim.h_min), float(lim.h_max), N)
    # fully random (v, h) first; where that leaves the region the model is defined on
    # (closed chains out of assembly), contract towards the cycloidal guess
    from .initial_guess import cycloidal

    v_c, h_c = (np.asarray(x) for x in cycloidal(Problem(robot, q0, q1, N=N, validate=False)))
    v_c = np.clip(v_c, -qdd, qdd)
    for i in range(12):
        s = 0.5**i
        v, h = v_c + s * (v_rand - v_c), h_c + s * (h_rand - h_c)
        if _point_ok(robot, q0, np.zeros(n), v, h):
            break
    else:
        note = (note + "; " if note else "") + "no in-box trajectory found"
    info = {"validated": not note, "spread": s, "note": note}
    vias = ()
    if via:
        p = 0.5 * (np.asarray(robot.forward_kinematics(jnp.asarray(q0)))
                   + np.asarray(robot.forward_kinematics(jnp.asarray(q1))))
        vias = (p,)
    problem = Problem(robot, q0, q1, N=N, weights=weights, via_points=vias, T_max=0.9 * float(h.sum()),
                      validate=False)
    nlp = _nlp(problem)
    z = nlp.layout.pack(jnp.asarray(v), jnp.asarray(h))
    m0 = _init_multipliers(nlp, z)
    eq = jax.tree.map(lambda x: jnp.asarray(rng.standard_normal(x.shape)), m0.eq)
    ineq = jax.tree.map(lambda x: jnp.asarray(rng.uniform(0.0, 2.0, x.shape)), m0.ineq)
    glob = jnp.asarray(rng.uniform(0.0, 2.0, m0.glob.shape))
    mult = Multipliers(eq=eq, ineq=ineq, glob=glob)
    mu = float(10 ** rng.uniform(0, 2)) if mu is None else float(mu)
    return problem, jnp.asarray(v), jnp.asarray(h), mult, mu, info


# ----------------------------------------------------------------------------------------
# the report


@dataclasses.dataclass
class RobotResult:
    """Worst relative errors over the points for one robot (NaN when skipped)."""

    robot: str
    status: str  # "ok", "FAIL", "skipped", "error"
    note: str = ""
    N: int = 0
    points: int = 0
    cost_adjoint: float = math.nan
    cost_fd: float = math.nan
    al_adjoint: float = math.nan
    al_fd: float = math.nan
    fd_step: float = DEFAULT_FD_STEP
    seconds: float = 0.0
    per_point: list = dataclasses.field(default_factory=list)

    @property
    def passed(self) -> bool:
        return self.status in ("ok", "skipped")


@dataclasses.dataclass
class Report:
    results: list
    tol_adjoint: float = TOL_ADJOINT
    tol_fd: float = TOL_FD

    @property
    def passed(self) -> bool:
        return all(r.passed for r in self.results)

    def to_dict(self) -> dict:
        return {"tol_adjoint": self.tol_adjoint, "tol_fd": self.tol_fd, "passed": self.passed,
                "robots": [dataclasses.asdict(r) for r in self.results]}


def _missing_module(exc: BaseException) -> str | None:
    if isinstance(exc, ModuleNotFoundError) and (exc.name or "").startswith("jtraj.robots."):
        return exc.name
    return None


def gradcheck_robot(robot_or_name, *, N: int = 10, seed: int = 0, points: int = 3, weights=None,
                    fd_step: float = DEFAULT_FD_STEP, mu=None, adjoint: AdjointFn = discrete_adjoint,
                    tol_adjoint: float = TOL_ADJOINT, tol_fd: float = TOL_FD) -> RobotResult:
    """Check one robot at ``points`` random points; see :func:`gradcheck`."""
    import time

    from .robots import Robot
    from . import robots as _robots

    jax.config.update("jax_enable_x64", True)
    if not isinstance(N, (int, np.integer)) or N < 2:
        raise ValueError(f"N must be an integer >= 2, got {N!r}")
    if not isinstance(points, (int, np.integer)) or points < 1:
        raise ValueError(f"points must be an integer >= 1, got {points!r}")
    if isinstance(robot_or_name, Robot):
        robot, name = robot_or_name, robot_or_name.name
    else:
        name = robot_or_name
        if name not in _robots.names():
            raise ValueError(f"robot must be one of {_robots.names()}, got {name!r}")
        try:
            robot = _robots.get(name)
        except (ImportError, AttributeError) as exc:
            missing = _missing_module(exc)
            note = f"model not available yet ({missing or exc})"
            return RobotResult(robot=name, status="skipped", note=note, N=N)
    weights = default_weights() if weights is None else weights
    rng = np.random.default_rng(seed)
    res = RobotResult(robot=name, status="ok", N=int(N), points=int(points), fd_step=fd_step)
    t0 = time.perf_counter()
    worst = dict(cost_adjoint=0.0, cost_fd=0.0, al_adjoint=0.0, al_fd=0.0)
    notes = set()
    try:
        for _ in range(points):
            problem, v, h, mult, mu_k, info = random_point(robot, rng, N=int(N), weights=weights, mu=mu)
            if info["note"]:
                notes.add(info["note"])
            errs = check_point(problem, v, h, mult, mu_k, fd_step=fd_step, adjoint=adjoint)
            errs["mu"] = mu_k
            errs["spread"] = info["spread"]
            res.per_point.append(errs)
            for key in worst:
                worst[key] = max(worst[key], errs[key]) if math.isfinite(errs[key]) else math.inf
    except Exception as exc:  # a model that fails to evaluate is reported, not fatal
        res.status, res.note = "error", f"{type(exc).__name__}: {exc}"
        res.seconds = time.perf_counter() - t0
        return res
    for key, val in worst.items():
        setattr(res, key, val)
    ok = (worst["cost_adjoint"] <= tol_adjoint and worst["al_adjoint"] <= tol_adjoint
          and worst["cost_fd"] <= tol_fd and worst["al_fd"] <= tol_fd)
    res.status = "ok" if ok else "FAIL"
    spread = min(p["spread"] for p in res.per_point)
    if spread < 1:
        notes.add(f"random (v, h) contracted towards the cycloid, s >= {spread:g}")
    res.note = "; ".join(sorted(notes))
    res.seconds = time.perf_counter() - t0
    return res


def gradcheck(robot_or_name="all", *, N: int = 10, seed: int = 0, points: int = 3, weights=None,
              fd_step: float = DEFAULT_FD_STEP, mu=None, adjoint: AdjointFn = discrete_adjoint,
              tol_adjoint: float = TOL_ADJOINT, tol_fd: float = TOL_FD) -> Report:
    """Compare jax.grad of the cost and of the augmented Lagrangian with the discrete
    adjoint and with central finite differences (float64), at ``points`` random
    points per robot.

    Args:
        robot_or_name: a :class:`~jtraj.robots.Robot`, a built-in name, a list of
            those, or ``"all"`` (every name in :func:`jtraj.robots.names`; models whose
            module does not exist yet are reported as skipped).
        N: number of intervals; seed: RNG seed; points: random points per robot.
        weights: :class:`~jtraj.Weights` (default: :func:`default_weights`, all
            terms on).
        fd_step: central-difference step in the scaled z (see module docstring).
        mu: penalty (default: random log-uniform in [1, 100] per point).
        adjoint: the adjoint recursion (replaceable for tests).
        tol_adjoint, tol_fd: pass/fail thresholds on the relative errors.

    Returns a :class:`Report` (``.passed``, ``.results``, ``.to_dict()``); print it
    with :func:`format_table`. Switches JAX to float64.
    """
    from . import robots as _robots

    if isinstance(robot_or_name, str) and robot_or_name == "all":
        items: list[Any] = _robots.names()
    elif isinstance(robot_or_name, (list, tuple)):
        items = list(robot_or_name)
    else:
        items = [robot_or_name]
    results = [gradcheck_robot(r, N=N, seed=seed, points=points, weights=weights, fd_step=fd_step, mu=mu,
                               adjoint=adjoint, tol_adjoint=tol_adjoint, tol_fd=tol_fd) for r in items]
    return Report(results=results, tol_adjoint=tol_adjoint, tol_fd=tol_fd)


def format_table(report: Report) -> str:
    """The report as a text table: worst relative error per robot and check."""

    def num(x):
        return "-" if not math.isfinite(x) and math.isnan(x) else f"{x:.1e}"

    head = (f"{'robot':18s} {'status':8s} {'N':>3s} {'pts':>3s}  {'cost:adj':>9s} {'cost:FD':>9s}  "
            f"{'AL:adj':>9s} {'AL:FD':>9s} {'time':>6s}  note")
    lines = [f"gradient check: jax.grad vs discrete adjoint (tol {report.tol_adjoint:.0e}) and "
             f"central FD (tol {report.tol_fd:.0e}), float64, max relative error over points",
             head, "-" * len(head)]
    for r in report.results:
        lines.append(f"{r.robot:18s} {r.status:8s} {r.N:3d} {r.points:3d}  {num(r.cost_adjoint):>9s} "
                     f"{num(r.cost_fd):>9s}  {num(r.al_adjoint):>9s} {num(r.al_fd):>9s} "
                     f"{r.seconds:5.1f}s  {r.note}")
    steps = sorted({r.fd_step for r in report.results})
    lines.append(f"FD step {', '.join(f'{s:g}' for s in steps)} in scaled z (v/qdd_max, h/h_max); "
                 f"{'PASSED' if report.passed else 'FAILED'}")
    return "\n".join(lines)
