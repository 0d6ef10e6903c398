"""Feasibility repair of a predicted decoupled trajectory ``(v, h)``: a fixed, jitted
correction that lands exactly on the goal state and restores the velocity,
acceleration and effort bounds.

The decoupled recursion (``q'' = v`` held over each period) is linear in ``v`` for
fixed periods ``h``; its terminal state is

    qd_N = qd_0 + sum_k h_k v_k,
    q_N  = q_0 + T qd_0 + sum_k c_k v_k,   c_k = h_k (T - t_{k+1}) + h_k^2 / 2,

two linear equations per joint (``t_{k+1} = h_0 + ... + h_k``). :func:`goal_projection`
moves ``v`` onto them by the smallest change in ``sum_k h_k |dv_k|^2`` (the time
integral of the squared acceleration change): one 2x2 solve shared by all joints.

A uniform time scaling ``h -> s h``, ``v -> v / s^2`` keeps every sample ``q_k`` (so the
goal stays reached) and divides ``qd`` by ``s``. For a robot whose efforts are homogeneous
of degree two in the time derivatives (no gravity, friction or drive damping:
``tau(q, qd / s, v / s^2) = tau(q, qd, v) / s^2``, :func:`is_homogeneous`) the bounds
then read ``s >= |qd| / qd_max``, ``s^2 >= |v| / qdd_max``, ``s^2 >= |tau| / tau_max``
and the cost of the scaled plan is

    J(s) = (time T + singularity sum_k h_k w(q_k)) s + (sum_k h_k qd_k^T Q qd_k) / s
           + (sum_k h_k tau_k^T U tau_k) / s^3,

convex in ``s``, minimised in closed form (a quadratic in ``s^2``): :func:`make_repair`
takes the smallest ``s`` of the feasible ones that is at least that minimiser, within the
period box ``h_min <= s h_k <= h_max``. For other robots it takes the cheapest feasible
``s`` of a fixed log-spaced grid over the period box, refined on a second grid between
the neighbours of the first one's choice. Where the efforts are a polynomial
in ``u = 1 / s`` (gravity and viscous friction: :func:`is_quadratic_in_rate`) the
polynomials of all candidates come from one inverse-dynamics pass over their samples at
three rates, the cost at every grid point from a polynomial of degree four in ``u`` and
the velocity and acceleration ratios from one reduction each, and the chosen plan's
efforts from its polynomial; otherwise the efforts are evaluated at every grid point.

Up to seven candidates are repaired side by side (:func:`make_repair` leaves out any of
them; :class:`jtraj.online.Planner` repairs four by default): the predicted periods (clipped into the
box) and uniform periods of the same total time (which leave the time scaling the
widest period box), each with the projected accelerations, with one
:func:`effort_step` from them (a Gauss-Newton step towards less effort on the goal,
kept near the prediction) and with the projected :func:`switch_profile` (accelerations
held at opposite constants before and after a linear switch, the shape of
effort-bounded optima), and the projected :func:`trapezoid_profile` on its own uniform
periods (the synchronised trapezoidal velocity profile, the shape of velocity- and
acceleration-bounded optima, which needs no prediction); the feasible one of lowest
cost is returned, else the one of smallest violation. Where the robot has a jerk bound
(``limits.qddd_max``), the acceleration jumps, which scale as ``1 / s^3``, enter the
time scaling's bounds as ``jtraj.Problem`` bounds them (:func:`jerk_ratio`). The
returned plan's states come from the recursion and its efforts from the robot's inverse
dynamics, the time scaling applied by its exact relations (``q`` unchanged, ``qd / s``,
the efforts' ``1 / s^2`` or their polynomial in ``1 / s``): its reported violations are
computed on those arrays, and the tests re-verify them independently (NumPy recursion,
Pinocchio).
Constraints on positions alone (the joint and workspace boxes, a parallel robot's path
constraints: :func:`position_rows`) do not change under a time scaling. Where the robot
has path constraints, :func:`position_step` bends every candidate's path back inside
them (and inside the boxes) before the time scaling, keeping its goal; elsewhere they
are measured (:func:`position_excess`), in the choice among the candidates too, not
repaired.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._math import small_matmul
from .lq import small_cho_solve


#: longest axis summed under a triangle of ones (:func:`_cumsum`)
UNROLL = 32
#: points of the time-scaling grid for robots whose efforts are not homogeneous
GRID = 32
#: width of the switch of :func:`switch_profile`, a fraction of the motion's time (the
#: lowest median and 90th-percentile cost gaps of 0.1 to 0.4 on the training pairs of a
#: 300-pair serial3 dataset)
SWITCH = 0.3
#: the values of the acceleration phase's share of the time tried by :func:`trapezoid_profile`
FRACTIONS = 32
#: weight of the distance to the prediction in :func:`effort_step`, relative to the
#: effort term's mean curvature
RHO = 1.0
#: Gauss-Newton steps of :func:`position_step`, the margin it keeps inside the position
#: constraints (in their normalised units), and the weight of its targets relative to
#: the acceleration change (on 4,096 parallel3 pairs of the dataset law drawn with seed 2,
#: the straight-line trapezoids of the 3.9 % whose straight line crosses a leg's
#: singularity margin: 96 % of them repaired with these, 90 % with a step to each row's
#: own target rather than the least-norm one)
POSITION_STEPS, POSITION_MARGIN, POSITION_WEIGHT = 6, 1e-2, 1e4


class Repaired(NamedTuple):
    v: jax.Array  # (N, n)
    h: jax.Array  # (N,)
    q: jax.Array  # (N+1, n)
    qd: jax.Array  # (N+1, n)
    tau: jax.Array  # (N, m)
    cost: jax.Array
    scale: jax.Array  # the time scaling s of the chosen candidate
    uniform: jax.Array  # whether the chosen candidate has uniform periods
    candidate: jax.Array  # the chosen candidate's index (make_repair's order)
    #: whether a candidate's path left the position rows, so that :func:`position_step`
    #: bent it (with ``positions="flag"``: would have bent it); False without the step
    bent: jax.Array


def _cumsum(x):
    """Cumulative sums along axis 0. Up to :data:`UNROLL` rows, the rows summed under the
    lower triangle of ones: one fused loop, which for a single serial3 plan (N = 20)
    costs less than XLA's cumulative sum (a reduce-window) on a CPU. Beyond, a parallel
    prefix sum (``jax.lax.associative_scan``): the triangle's work grows as the square of
    the rows, the prefix sum's as the rows times their logarithm (the rollouts' sums of
    256 panda plans, N = 40, n = 7, three candidates each: 35 ms against 0.7 ms)."""
    if x.shape[0] > UNROLL:
        return jax.lax.associative_scan(jnp.add, x, axis=0)
    N = x.shape[0]
    L = jnp.asarray(np.tril(np.ones((N, N), bool)))
    return jnp.sum(jnp.where(L.reshape((N, N) + (1,) * (x.ndim - 1)), x[None], 0), axis=1)


def rollout(q0, qd0, v, h):
    """(q, qd), each (N+1, n): the decoupled recursion by cumulative sums (on a CPU
    several times faster under ``vmap`` than :func:`jtraj.transcription.integrate`'s
    prefix sums, which suit the solver's derivatives)."""
    qd = jnp.concatenate([qd0[None], qd0[None] + _cumsum(h[:, None] * v)])
    dq = h[:, None] * qd[:-1] + 0.5 * (h**2)[:, None] * v
    return jnp.concatenate([q0[None], q0[None] + _cumsum(dq)]), qd


def _quad(x, M):
    """``x_k^T M x_k`` for each row of x."""
    M = jnp.reshape(M, (1,) * (x.ndim - 1) + M.shape[-2:]) if M.ndim == 2 else M
    return jnp.sum(x[..., :, None] * M * x[..., None, :], axis=(-2, -1))


def terminal_rows(h):
    """(2, N): rows ``h_k`` and ``c_k`` of the terminal map (module doc)."""
    t_next = _cumsum(h)
    T = t_next[-1]
    return jnp.stack([h, h * (T - t_next) + 0.5 * h**2])


def goal_projection(q0, qd0, q_goal, qd_goal, v, h):
    """``v`` (N, n) moved onto ``q_N = q_goal``, ``qd_N = qd_goal`` by the smallest change
    in ``sum_k h_k |dv_k|^2`` (module doc), for periods ``h`` (N,) > 0."""
    A = terminal_rows(h)
    T = jnp.sum(h)
    target = jnp.stack([qd_goal - qd0, q_goal - q0 - T * qd0])  # (2, n)
    r = target - small_matmul(A, v)
    Winv_At = (A / h[None]).T  # (N, 2): W^{-1} A^T with W = diag(h)
    G = small_matmul(A, Winv_At)  # symmetric positive definite 2x2: inverted in closed form
    return v + small_matmul(Winv_At, small_matmul(_inv2(G), r))


def switch_profile(q0, qd0, q_goal, h, width=None):
    """``v`` (N, n): the accelerations of a rest-to-rest motion that holds each joint's
    acceleration at a constant for the first part of the motion and its opposite for the
    last, switching linearly over the middle ``width`` (a fraction of the total time,
    default :data:`SWITCH`), scaled per joint to end at ``q_goal`` (from ``qd0 = 0``;
    :func:`goal_projection` corrects the rest). The shape of the optima of effort-bounded
    time-energy problems (the efforts on their bounds but for the switch), which a
    learned prediction smooths into a ramp."""
    width = SWITCH if width is None else width
    t = _cumsum(h) - 0.5 * h  # the intervals' midpoints
    T = jnp.sum(h)
    shape = -jnp.clip((t - 0.5 * T) / (0.5 * width * T), -1.0, 1.0)
    c = terminal_rows(h)[1]
    den = jnp.sum(c * shape)  # > 0 but for periods far from uniform: then a zero profile
    safe = jnp.abs(den) > 1e-12 * jnp.sum(c)
    return shape[:, None] * jnp.where(safe, (q_goal - q0 - T * qd0) / jnp.where(safe, den, 1.0), 0.0)[None]


def trapezoid_profile(q0, q_goal, N: int, qd_max, qdd_max, fractions: int = FRACTIONS):
    """``(v, h)``: the synchronised trapezoidal velocity profile of a rest-to-rest motion
    on ``N`` equal periods. Every joint accelerates at a constant for the same first
    fraction ``f`` of the time ``T``, coasts, and decelerates for the last fraction ``f``;
    joint ``j`` then peaks at the speed ``D_j / ((1 - f) T)`` and accelerates at ``D_j /
    (f (1 - f) T^2)`` (``D = q_goal - q0``), and ``T`` is the least time that keeps both
    within every joint's bounds: ``T(f) = max_j max(|D_j| / ((1 - f) qd_max_j), sqrt(|D_j|
    / (f (1 - f) qdd_max_j)))``, minimised over ``fractions`` values of ``f`` in (0, 1/2]
    (``f = 1/2``: a triangle). The time-optimal motion of the kinematic bounds alone when
    all joints move together, the shape of velocity- and acceleration-bounded optima (a
    Panda's); the accelerations are the profile's averages over the periods, so that
    :func:`goal_projection` moves them onto the goal by little."""
    D = q_goal - q0
    dist = jnp.abs(D)
    f = (jnp.arange(fractions, dtype=D.dtype) + 1) * (0.5 / fractions)
    vmax, amax = jnp.broadcast_to(qd_max, D.shape)[None], jnp.broadcast_to(qdd_max, D.shape)[None]
    t_speed = dist[None] / ((1 - f)[:, None] * vmax)  # (fractions, n): the time each bound needs
    t_accel = jnp.sqrt(dist[None] / ((f * (1 - f))[:, None] * amax))
    T_f = jnp.max(jnp.maximum(t_speed, t_accel), axis=1)
    k = jnp.argmin(T_f)
    best = jnp.arange(fractions) == k  # (the minimiser by a mask: fused loops, no gather)
    f, T = jnp.sum(jnp.where(best, f, 0.0)), jnp.sum(jnp.where(best, T_f, 0.0))
    T = jnp.where(T > 0, T, 1.0)  # (no motion: any time; the profile is zero)
    edges = jnp.arange(N + 1, dtype=D.dtype) * (T / N)

    def share(a, b):  # of each period inside [a, b]
        return jnp.clip(jnp.minimum(edges[1:], b) - jnp.maximum(edges[:-1], a), 0.0, None) * (N / T)

    shape = share(0.0, f * T) - share((1 - f) * T, T)
    return shape[:, None] * (D / (f * (1 - f) * T**2))[None], jnp.full((N,), T / N, D.dtype)


def linearise(robot, q0, qd0, v, h):
    """``(q, qd, tau, J)`` of the plan ``v``: its states (N+1, n), efforts (N, m) and
    ``J_k = dtau_k / dv_k`` (N, m, n) at its own states (forward mode; the efforts come
    with the derivatives at no extra cost)."""
    q, qd = rollout(q0, qd0, v, h)

    def one(a, b, c):
        f = lambda c_: (robot.inverse_dynamics(a, b, c_),) * 2  # noqa: E731
        J, tau = jax.jacfwd(f, has_aux=True)(c)
        return tau, J

    tau, J = jax.vmap(one)(q[:-1], qd[:-1], v)
    return q, qd, tau, J


def effort_step_at(U, q0, qd0, q_goal, qd_goal, v, h, tau, J, rho):
    """:func:`effort_step` from the efforts ``tau`` and their derivatives ``J`` at ``v``'s
    states (:func:`linearise`)."""
    n = v.shape[1]
    A = terminal_rows(h)
    target = jnp.stack([qd_goal - qd0, q_goal - q0 - jnp.sum(h) * qd0])  # (2, n)
    c = tau - jnp.einsum("kij,kj->ki", J, v)
    U = jnp.broadcast_to(U, (v.shape[0],) + U.shape[-2:])  # one weight matrix, or one per sample
    H = h[:, None, None] * (jnp.einsum("kji,kjl,klm->kim", J, U, J) + rho * jnp.eye(n)[None])  # halved Hessian
    g = h[:, None] * (jnp.einsum("kji,kjl,kl->ki", J, U, c) - rho * v)
    # the samples as trailing lane axes of small_cho_solve: Hinv (N, n, n)
    eye = jnp.broadcast_to(jnp.eye(n, dtype=H.dtype)[:, :, None], (n, n, H.shape[0]))
    Hinv = jnp.moveaxis(small_cho_solve(jnp.moveaxis(H, 0, -1), eye)[0], -1, 0)
    # v_k = -Hinv_k (g_k + sum_r A[r, k] lam_r); A v = target gives S lam = -A Hinv g - target
    Hg = jnp.einsum("kij,kj->ki", Hinv, g)
    S = jnp.einsum("rk,sk,kij->risj", A, A, Hinv).reshape(2 * n, 2 * n)
    lam = small_cho_solve(S, (-(A @ Hg) - target).reshape(2 * n, 1))[0].reshape(2, n)
    return -Hg - jnp.einsum("kij,kj->ki", Hinv, A.T @ lam)


def effort_step(robot, U, q0, qd0, q_goal, qd_goal, v, h, rho):
    """One Gauss-Newton step from ``v`` (on the goal) towards the accelerations of least
    effort ``sum_k h_k tau_k^T U tau_k + rho sum_k h_k |v_k - v_k^0|^2`` on the goal state:
    the efforts linearised in ``v`` at the states of ``v`` (``tau_k ~ J_k v_k + c_k``,
    ``J_k = dtau/dv``), the goal's 2n linear equations kept exactly. The KKT system is
    block diagonal in the samples but for the 2n multipliers: N n x n solves and one
    2n x 2n solve, by unrolled Cholesky factorisations (both matrices are positive
    definite: ``rho > 0``; on a CPU LAPACK's per-matrix calls cost several times more
    for matrices this small)."""
    _, _, tau, J = linearise(robot, q0, qd0, v, h)
    return effort_step_at(U, q0, qd0, q_goal, qd_goal, v, h, tau, J, rho)


def _trial_states(robot, trials: int, seed: int):
    """``trials`` random states ``(q, qd, v)`` at which ``robot``'s efforts are finite:
    positions in the middle half of the joint box (where it is finite; else in [-1, 1]),
    velocities and accelerations in [-1, 1]. A closed chain's efforts are not defined
    everywhere (parallel3's legs do not reach C outside its box), so a state whose
    efforts are not finite is drawn again (up to 20 times each)."""
    rng = np.random.default_rng(seed)
    lim, n = robot.limits, robot.n
    lo = np.full(n, -1.0) if lim.q_min is None else np.asarray(lim.q_min, float) * np.ones(n)
    hi = np.full(n, 1.0) if lim.q_max is None else np.asarray(lim.q_max, float) * np.ones(n)
    finite = np.isfinite(lo) & np.isfinite(hi)
    lo, hi = np.where(finite, lo, -1.0), np.where(finite, hi, 1.0)
    states = []
    for _ in range(trials):
        for _ in range(20):
            q = lo + (hi - lo) * rng.uniform(0.25, 0.75, n)
            qd, v = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
            if np.all(np.isfinite(np.asarray(robot.inverse_dynamics(*(jnp.asarray(x) for x in (q, qd, v)))))):
                break
        states.append(tuple(jnp.asarray(x) for x in (q, qd, v)))
    return states


def is_homogeneous(robot, trials: int = 3, seed: int = 0) -> bool:
    """Whether ``robot``'s efforts satisfy ``tau(q, qd / s, v / s^2) = tau(q, qd, v) / s^2``
    (tested at random states, :func:`_trial_states`, s = 2, relative tolerance 1e-9):
    rigid bodies without gravity, friction or drive damping."""
    for q, qd, v in _trial_states(robot, trials, seed):
        t1 = np.asarray(robot.inverse_dynamics(q, qd, v))
        t2 = np.asarray(robot.inverse_dynamics(q, qd / 2, v / 4)) * 4
        if not np.all(np.abs(t1 - t2) <= 1e-9 * (1 + np.abs(t1))):
            return False
    return True


def is_quadratic_in_rate(robot, trials: int = 3, seed: int = 0) -> bool:
    """Whether ``robot``'s efforts under the time scaling, ``tau(q, qd / s, v / s^2)``, are a
    polynomial of degree two in ``u = 1 / s``: ``tau_0(q) + u tau_1(q, qd) + u^2
    tau_2(q, qd, v)`` (rigid bodies with gravity, viscous friction or drive damping; not
    a smoothed Coulomb friction). Tested at random states (:func:`_trial_states`): the
    efforts at ``u = 3`` against the polynomial through ``u = 1/2, 1, 2``
    (:func:`_rate_polynomial`), relative tolerance 1e-9."""
    ID = robot.inverse_dynamics
    for q, qd, v in _trial_states(robot, trials, seed):
        a, b, c = _rate_polynomial(ID(q, qd / 2, v / 4), ID(q, qd, v), ID(q, 2 * qd, 4 * v))
        t3 = np.asarray(ID(q, 3 * qd, 9 * v))
        fit = np.asarray(a + 3 * b + 9 * c)
        if not np.all(np.abs(t3 - fit) <= 1e-9 * (1 + np.abs(t3))):
            return False
    return True


def _rate_polynomial(t_half, t_one, t_two):
    """``(a, b, c)`` of ``tau(u) = a + b u + c u^2`` through the efforts at ``u = 1/2, 1, 2``."""
    c = (2.0 / 3.0) * (t_two - 3.0 * t_one + 2.0 * t_half)
    b = t_two - t_one - 3.0 * c
    return t_one - b - c, b, c


def _ratio(x, bound):
    """Largest |x| / bound (0 without a bound)."""
    if bound is None:
        return jnp.zeros(())
    return jnp.max(jnp.abs(x) / jnp.broadcast_to(bound, x.shape))


def cost_of(robot, weights, q, qd, tau, h):
    """The cost of :class:`jtraj.Weights` (``sum_k h_k [time + tau_k^T U tau_k +
    qd_k^T Q qd_k + singularity w(q_k)]``, k < N) of a trajectory."""
    U, Q = weights.matrices(robot)
    c = weights.time * h + h * _quad(tau, U)
    if weights.has_kinetic:
        c = c + h * _quad(qd[:-1], Q)
    if weights.has_singularity:
        w = jax.vmap(robot.manipulability)(q[:-1])
        c = c + weights.singularity * h / jnp.maximum(w, 1e-9)
    return jnp.sum(c)


def jerk_ratio(v, h, qddd_max):
    """Largest ratio of an acceleration jump to the problem's jerk bound on it,
    ``|v_{k+1} - v_k| / (qddd_max (h_k + h_{k+1}) / 2)`` (``jtraj.Problem``'s jerk rows;
    0 without a bound, ``qddd_max`` None). Under the time scaling ``h -> s h``, ``v -> v /
    s^2`` it scales as ``1 / s^3``."""
    if qddd_max is None or v.shape[0] < 2:
        return jnp.zeros((), v.dtype)
    bound = jnp.broadcast_to(qddd_max, v.shape[1:])[None] * (0.5 * (h[1:] + h[:-1]))[:, None]
    return jnp.max(jnp.abs(v[1:] - v[:-1]) / bound)


def violation_parts(robot, q, qd, v, tau, h):
    """The largest relative excesses over the robot's boxes (0 when within), in this
    order: efforts, velocities (samples 1..N, :func:`velocity_excess`), accelerations, positions
    (:func:`position_excess`; 0 without position constraints), periods (relative to h_max) and
    acceleration jumps (relative to their jerk bounds, :func:`jerk_ratio`; 0 without
    one). Each is the largest ratio less one (the same number as the largest excess,
    with a batch's reductions about twice as fast)."""
    lim = robot.limits
    return (jnp.maximum(_ratio(tau, lim.tau_max) - 1, 0.0), velocity_excess(robot, q, qd),
            jnp.maximum(_ratio(v, lim.qdd_max) - 1, 0.0),
            _or_zero(position_excess(robot, q), h.dtype),
            jnp.max(jnp.maximum(jnp.maximum(lim.h_min - h, h - lim.h_max) / lim.h_max, 0.0)),
            jnp.maximum(jerk_ratio(v, h, lim.qddd_max) - 1, 0.0))


def violation(robot, q, qd, v, tau, h):
    """Largest relative excess over the robot's boxes (0 when within): the largest of
    :func:`violation_parts`."""
    return jnp.max(jnp.stack(violation_parts(robot, q, qd, v, tau, h)))


def position_rows(robot, q):
    """The constraints on the positions alone at one sample q (n,), as normalised rows
    ``r(q) <= 0`` (R,), or None where the robot has none: the joint box and the
    workspace box, each relative to its width (1 where the box is infinite), and the
    robot's path constraints ``g(q) <= 0`` (normalised, as ``jtraj.Problem`` takes
    them). None of them changes under a time scaling."""
    lim, parts = robot.limits, []
    if lim.q_min is not None:
        parts += _box_rows(q, lim.q_min, lim.q_max)
    if lim.workspace is not None:
        parts += _box_rows(robot.forward_kinematics(q), lim.workspace[0], lim.workspace[1])
    path = getattr(robot, "path_constraints", None)
    if path is not None:
        parts.append(path(q))
    return jnp.concatenate(parts) if parts else None


def _box_rows(x, lo, hi):
    lo, hi = jnp.broadcast_to(lo, x.shape), jnp.broadcast_to(hi, x.shape)
    width = jnp.where(jnp.isfinite(hi - lo), hi - lo, 1.0)
    return [(lo - x) / width, (x - hi) / width]


def position_excess(robot, q):
    """Largest excess of the positions q (N+1, n) over :func:`position_rows` (0 when
    within), or None where the robot has no constraints on positions."""
    lim = robot.limits
    if lim.q_min is None and lim.workspace is None and getattr(robot, "path_constraints", None) is None:
        return None
    return jnp.maximum(jnp.max(jax.vmap(lambda x: position_rows(robot, x))(q)), 0.0)


def position_step(robot, q0, qd0, q_goal, qd_goal, v, h, steps: int = POSITION_STEPS,
                  margin: float = POSITION_MARGIN, weight: float = POSITION_WEIGHT):
    """``v`` (N, n) changed so that the positions of the decoupled recursion meet
    :func:`position_rows` at the samples 1..N-1, with the goal state kept (to rounding).

    Each of ``steps`` Gauss-Newton steps linearises the rows at the current samples;
    at every sample where one comes within ``margin`` of its bound, the least-norm
    displacement that puts the linearised rows ``margin`` inside becomes a target, and
    the step is the change ``dv`` of least ``sum_k h_k |dv_k|^2 + rho sum_k |dq_k -
    d_k|^2`` (over the samples with a target) that keeps the terminal state, ``dq`` being
    linear in ``dv`` for fixed periods (module doc): one (N + 2)-square system shared by
    the joints. ``rho`` is ``weight`` relative to the two terms' mean curvatures. The
    ends are left alone (a problem's start and goal meet the constraints), and so is a
    plan whose samples all meet the rows already. A plan's positions stay put under the
    time scaling, so the step comes before it; where the constraints cannot be met near
    the path (or the steps do not suffice), the plan's reported violation says so."""
    N = h.shape[0]
    rows = jax.vmap(lambda x: position_rows(robot, x))
    jac = jax.vmap(jax.jacfwd(lambda x: position_rows(robot, x)))
    t_next = _cumsum(h)
    t = jnp.concatenate([jnp.zeros(1, h.dtype), t_next])
    # q_k = q0 + t_k qd0 + sum_{j<k} C_kj v_j (the recursion's positions, linear in v)
    C = jnp.where(jnp.arange(N)[None] < jnp.arange(N + 1)[:, None],
                  h[None] * (t[:, None] - t_next[None]) + 0.5 * h[None] ** 2, 0.0)
    rho = weight * jnp.sum(h) / jnp.sum(C**2)
    A = terminal_rows(h)
    inner = (jnp.arange(N + 1) > 0) & (jnp.arange(N + 1) < N)
    v_in, outside = v, jnp.any(rows(rollout(q0, qd0, v, h)[0]) > 0)
    def step(_, v):  # (a loop, not unrolled: a robot's rows and their Jacobians compiled once)
        q = rollout(q0, qd0, v, h)[0]
        r, G = rows(q) + margin, jac(q)  # (N+1, R), (N+1, R, n)
        active = r > 0
        Ga = jnp.where(active[..., None], G, 0.0)  # (a select: an inactive row's non-finite gradient stays out)
        # least-norm d with G_a d = -r_a, as -(e I + G_a^T G_a)^-1 G_a^T r_a: an n x n system per
        # sample whatever the number of rows (the small shift e keeps dependent rows, or fewer
        # active rows than joints, solvable)
        P = jnp.swapaxes(Ga, 1, 2) @ Ga
        n = P.shape[-1]
        P = P + (1e-9 * (1 + jnp.trace(P, axis1=1, axis2=2)))[:, None, None] * jnp.eye(n, dtype=h.dtype)[None]
        d = -jax.vmap(_spd_solve)(P, jnp.einsum("krn,kr->kn", Ga, jnp.where(active, r, 0.0))[..., None])[..., 0]
        w = jnp.where(inner & jnp.any(active, axis=1), rho, 0.0)
        # min sum_k h_k |dv_k|^2 + w_k |C_k dv - d_k|^2 subject to A dv = 0: with H = diag(h) + C^T W C,
        # dv = X - Y (A Y)^-1 A X for X = H^-1 C^T W d, Y = H^-1 A^T
        XY = _spd_solve(jnp.diag(h) + (C.T * w[None]) @ C, jnp.concatenate([(C.T * w[None]) @ d, A.T], axis=1))
        X, Y = XY[:, :-2], XY[:, -2:]
        return v + X - Y @ _inv2(A @ Y) @ (A @ X)
    return jnp.where(outside, jax.lax.fori_loop(0, steps, step, v), v_in)


def _spd_solve(A, B):
    """``A^-1 B`` for a symmetric positive definite A (m, m) and B (m, k), by Gauss-Jordan
    elimination without pivoting (stable for such matrices), unrolled: one rank-one
    update per column, no custom call."""
    M = jnp.concatenate([A, B], axis=1)
    rows = jnp.arange(A.shape[0])
    for k in range(A.shape[0]):
        pivot_row = M[k] / M[k, k]
        M = jnp.where((rows == k)[:, None], pivot_row[None], M - M[:, k:k + 1] * pivot_row[None])
    return M[:, A.shape[0]:]


def _inv2(G):
    """The inverse of a 2 x 2 matrix in closed form."""
    return jnp.stack([jnp.stack([G[1, 1], -G[0, 1]]), jnp.stack([-G[1, 0], G[0, 0]])]) / (
        G[0, 0] * G[1, 1] - G[0, 1] * G[1, 0])


def velocity_excess(robot, q, qd):
    """Largest excess of the velocities of samples 1..N over the joint velocity box
    (relative) and the robot's state-dependent velocity constraints ``g(q, qd) <= 0`` (a
    parallel robot's leg speeds, normalised). The repair's time scaling accounts for the
    box only; the constraints are measured on the plan it returns."""
    ex = jnp.maximum(_ratio(qd[1:], robot.limits.qd_max) - 1, 0.0)
    vel = getattr(robot, "velocity_constraints", None)
    if vel is not None:
        ex = jnp.maximum(ex, jnp.max(jax.vmap(vel)(q[1:], qd[1:])))
    return ex


def _or_zero(x, dtype):
    return jnp.zeros((), dtype) if x is None else x


def make_repair(robot, weights, *, homogeneous: bool | None = None, quadratic: bool | None = None,
                grid: int = GRID, rho: float | None = None, effort: bool = True, switch: bool = True,
                projection: bool = True, uniform_projection: bool = True, trapezoid: bool | None = None,
                positions: bool | None = None):
    """``repair(q0, qd0, q_goal, qd_goal, v, h) -> Repaired``: a jit-, vmap-able pure function
    (see the module doc). ``homogeneous`` defaults to :func:`is_homogeneous` (tested here,
    on the host). For a robot that is not, ``quadratic`` (default
    :func:`is_quadratic_in_rate`, tested on the host) takes the efforts at the time
    scaling's grid points, and the chosen plan's, from their polynomial in ``1 / s``
    through three scalings (``s = 2, 1, 1/2``: one inverse-dynamics pass over all the
    candidates' samples) instead of one inverse-dynamics pass per grid point.
    ``effort=False`` leaves out the two :func:`effort_step` candidates, ``switch=False``
    the two :func:`switch_profile` candidates, ``projection=False`` and
    ``uniform_projection=False`` the projected prediction on its own and on uniform periods,
    ``trapezoid=False`` the projected :func:`trapezoid_profile` (default: where the robot
    has velocity and acceleration bounds; ``True`` without them raises). The
    trapezoidal profile needs no prediction: it is the planner's answer where the model
    is poor as well (``repair.candidates`` names the candidates, in the order of
    :attr:`Repaired.candidate`). Without the projected prediction, the prediction's
    accelerations serve only the effort steps (the switching profiles use its periods
    alone). ``positions`` (default: where the robot has path constraints; the value in
    effect is ``repair.positions``) runs
    :func:`position_step` on every candidate before its time scaling, where a
    candidate's path leaves the position rows (:attr:`Repaired.bent`);
    ``positions="flag"`` only reports whether it would have run: the repair is then
    the one without the step, and equals the one with it wherever ``bent`` is False
    (:class:`jtraj.online.Planner` runs a batch that way, and only the flagged plans
    again with the step)."""
    lim = robot.limits
    if positions is None:
        positions = getattr(robot, "path_constraints", None) is not None
    if not (positions is True or positions is False or (isinstance(positions, str) and positions == "flag")):
        raise ValueError(f"make_repair: positions must be None, True, False or 'flag', got {positions!r}")
    if homogeneous is None:
        homogeneous = is_homogeneous(robot)
    if quadratic is None:
        quadratic = not homogeneous and is_quadratic_in_rate(robot)
    ID = jax.vmap(robot.inverse_dynamics)
    h_min, h_max = lim.h_min, lim.h_max
    jerk = lim.qddd_max is not None  # (the scaling then keeps the acceleration jumps within their bounds)

    def states(q0, qd0, v, h):
        q, qd = rollout(q0, qd0, v, h)
        return q, qd, ID(q[:-1], qd[:-1], v)

    def scaled(q0, qd0, v, h, s):
        q, qd, tau = states(q0, qd0, v / s**2, h * s)
        return q, qd, tau, v / s**2, h * s

    def s_range(h):
        return jnp.max(h_min / h), jnp.min(h_max / h)

    def scale_homogeneous(q, qd, tau, v, h):
        """(s, cost, violation of the scaled plan) from the unscaled plan's reductions
        (the scaled plan has the same q, qd / s, tau / s^2, v / s^2, h s: module doc)."""
        r_qd, r_v, r_tau = _ratio(qd, lim.qd_max), _ratio(v, lim.qdd_max), _ratio(tau, lim.tau_max)
        s_f = jnp.maximum(jnp.maximum(r_qd, jnp.sqrt(r_v)), jnp.sqrt(r_tau))
        if jerk:
            r_j = jerk_ratio(v, h, lim.qddd_max)
            s_f = jnp.maximum(s_f, jnp.cbrt(r_j))
        s_f = s_f * (1 + 1e-12)
        U, Q = weights.matrices(robot)
        B = jnp.sum(h * _quad(tau, U))
        C = jnp.sum(h * _quad(qd[:-1], Q)) if weights.has_kinetic else 0.0
        A = weights.time * jnp.sum(h)
        if weights.has_singularity:
            A = A + weights.singularity * jnp.sum(h / jnp.maximum(jax.vmap(robot.manipulability)(q[:-1]), 1e-9))
        # J'(s) = A - C / s^2 - 3 B / s^4 = 0: A x^2 - C x - 3 B = 0 in x = s^2
        safe_A = jnp.where(A > 0, A, 1.0)
        x = (C + jnp.sqrt(C**2 + 12 * A * B)) / (2 * safe_A)
        s_lo, s_hi = s_range(h)
        s_opt = jnp.where(A > 0, jnp.sqrt(x), s_hi)
        s = jnp.minimum(jnp.maximum(jnp.maximum(s_opt, s_f), s_lo), s_hi)
        # violation() of the scaled plan, term by term
        hs = h * s
        ex = [jnp.maximum(r_tau / s**2 - 1, 0.0), jnp.maximum(_ratio(qd[1:], lim.qd_max) / s - 1, 0.0),
              jnp.maximum(r_v / s**2 - 1, 0.0),
              jnp.max(jnp.maximum(jnp.maximum(lim.h_min - hs, hs - lim.h_max) / lim.h_max, 0.0))]
        pos = position_excess(robot, q)
        if pos is not None:
            ex.append(pos)
        if jerk:
            ex.append(jnp.maximum(r_j / s**3 - 1, 0.0))
        return s, A * s + C / s + B / s**3, jnp.max(jnp.stack(ex))

    def cheapest_scaling(h, evaluate):
        """``(s, cost, violation)`` of the cheapest feasible scaling, else the least
        infeasible, where ``evaluate(ss) -> (cost, violation)`` gives them for a (G,) array
        of scalings: on the log-spaced grid over the period box, then on a second grid as
        fine between the first's neighbours of its choice (the choice itself among its
        points, so that it never does worse). The first grid's step is (s_hi /
        s_lo)^(1 / (grid - 1)), about 19 % in ``s`` for a period box of 200: a scaling
        chosen on it alone can stop that far short of the bound that sets the motion's
        time (on 400 panda plans of N = 40 without the trapezoid, the second grid's choice
        costs 2.4 % less than the first's at the median, 7 % at most). The scalings lie
        inside the period box by construction, so that ``evaluate`` leaves out the
        periods' violation (rounding, which would flip the feasibility of the box's
        ends)."""

        def choose(cost, viol):
            ok = viol <= 0
            return jnp.where(jnp.any(ok), jnp.argmin(jnp.where(ok, cost, jnp.inf)), jnp.argmin(viol))

        def log_grid(lo, hi):
            return jnp.clip(jnp.exp(jnp.linspace(jnp.log(lo), jnp.log(hi), grid)), lo, hi)

        s_lo, s_hi = s_range(h)
        ss = log_grid(s_lo, s_hi)
        k = choose(*evaluate(ss))
        ss = jnp.concatenate([ss[k][None], log_grid(ss[jnp.maximum(k - 1, 0)], ss[jnp.minimum(k + 1, grid - 1)])])
        cost, viol = evaluate(ss)
        k = choose(cost, viol)
        return ss[k], cost[k], viol[k]

    def scale_grid(q0, qd0, v, h):
        """The scaling of :func:`cheapest_scaling`, each scaled plan's efforts by the
        inverse dynamics."""
        def one(s):
            q, qd, tau, vs, hs = scaled(q0, qd0, v, h, s)
            parts = violation_parts(robot, q, qd, vs, tau, hs)
            parts = parts[:4] + parts[5:]  # (the periods' left out)
            return cost_of(robot, weights, q, qd, tau, hs), jnp.max(jnp.stack(parts))
        return cheapest_scaling(h, jax.vmap(one))[0]

    def rate_polynomials(q, qd, v):
        """``(a, b, c)``, each (C, N, m), of the C candidates' efforts under the time
        scaling (:func:`_rate_polynomial`): one inverse-dynamics pass over all their
        samples at ``u = 1/2, 1, 2`` (on a CPU one pass over 3 C N samples costs little
        more than one over N: for so few samples its cost is mostly per operation)."""
        C, N, n = v.shape
        qs, qds, vs = q[None, :, :-1], qd[None, :, :-1], v[None]  # (1, C, N, n)
        rates = jnp.asarray([0.5, 1.0, 2.0], v.dtype).reshape(3, 1, 1, 1)
        tau = ID(jnp.broadcast_to(qs, (3, C, N, n)).reshape(-1, n), (rates * qds).reshape(-1, n),
                 (rates**2 * vs).reshape(-1, n))
        return _rate_polynomial(*tau.reshape((3, C, N, -1)))

    def at_rate(q, qd, v, h, a, b, c, s):
        """The plan scaled by ``s`` from its efforts' polynomial in ``u = 1 / s`` (the
        positions do not change with ``s``): ``(q, qd, v, tau, h)``."""
        u = 1 / s
        return q, qd * u, v * (u * u), a + u * (b + u * c), h * s

    def candidate_quadratic(q_goal, qd_goal, v, h, q, qd, a, b, c):
        """``(s, cost, violation)`` of :func:`cheapest_scaling`, the goal error included. At
        each scaling the efforts are their polynomial in ``u``; every other term of
        :func:`violation` and :func:`cost_of` is a power of ``u`` times one reduction of
        the unscaled plan, so that only the efforts' ratio is evaluated point by point."""
        U, Q = weights.matrices(robot)

        def inner(x, y):  # sum_k h_k x_k^T U y_k
            return jnp.sum(h * jnp.sum(x[:, :, None] * U[None] * y[:, None, :], axis=(1, 2)))

        # sum_k h_k tau_k^T U tau_k = sum_i e_i u^i with tau = a + u b + u^2 c
        e = (inner(a, a), inner(a, b) + inner(b, a), inner(b, b) + inner(a, c) + inner(c, a),
             inner(b, c) + inner(c, b), inner(c, c))
        rate = weights.time * jnp.sum(h)  # the terms of cost_of proportional to s
        if weights.has_singularity:
            rate = rate + weights.singularity * jnp.sum(h / jnp.maximum(jax.vmap(robot.manipulability)(q[:-1]), 1e-9))
        kinetic = jnp.sum(h * _quad(qd[:-1], Q)) if weights.has_kinetic else None
        r_qd, r_v = _ratio(qd[1:], lim.qd_max), _ratio(v, lim.qdd_max)
        r_j = jerk_ratio(v, h, lim.qddd_max) if jerk else None
        q_ex = position_excess(robot, q)

        def evaluate(ss):
            u = 1 / ss
            cost = ss * (rate + e[0] + u * (e[1] + u * (e[2] + u * (e[3] + u * e[4]))))
            if kinetic is not None:
                cost = cost + u * kinetic
            if lim.tau_max is None:
                r_tau = jnp.zeros_like(u)
            else:  # (N, m, G): the scalings' axis minor, reduced over the leading ones
                t_max = jnp.broadcast_to(lim.tau_max, a.shape)[..., None]
                ug = u[None, None]
                r_tau = jnp.max(jnp.abs(a[..., None] + ug * (b[..., None] + ug * c[..., None])) / t_max, axis=(0, 1))
            ex = [r_tau - 1, r_qd * u - 1, r_v * u * u - 1] + ([r_j * u**3 - 1] if jerk else [])
            viol = jnp.maximum(jnp.max(jnp.stack(ex), axis=0), 0.0)
            return cost, viol if q_ex is None else jnp.maximum(viol, q_ex)

        s, cost, viol = cheapest_scaling(h, evaluate)
        err = jnp.maximum(jnp.linalg.norm(q[-1] - q_goal), jnp.linalg.norm(qd[-1] / s - qd_goal))
        return s, cost, jnp.maximum(viol, err)

    rho = RHO if rho is None else rho
    U = weights.matrices(robot)[0]
    # the effort term's curvature scale: rho relative to it keeps the step's Hessian
    # positive definite whatever the energy weight
    u_scale = jnp.maximum(jnp.trace(U) / U.shape[0], 1e-12)

    def candidate(q0, qd0, q_goal, qd_goal, v, h, q, qd, tau):
        # (q, qd, tau): the states and efforts of (v, h); the scaled plan, its cost and its
        # violation (the goal error included)
        s = scale_grid(q0, qd0, v, h)
        q, qd, tau, vs, hs = scaled(q0, qd0, v, h, s)
        err = jnp.maximum(jnp.linalg.norm(q[-1] - q_goal), jnp.linalg.norm(qd[-1] - qd_goal))
        return (vs, hs, q, qd, tau, cost_of(robot, weights, q, qd, tau, hs), s,
                jnp.maximum(violation(robot, q, qd, vs, tau, hs), err))

    def candidate_homogeneous(q_goal, qd_goal, v, h, q, qd, tau):
        # the scaled plan's cost and violation (the goal error included) from the unscaled
        # plan's reductions: the candidates' scaled arrays are never formed, only the
        # chosen one's (repair)
        s, cost, viol = scale_homogeneous(q, qd, tau, v, h)
        err = jnp.maximum(jnp.linalg.norm(q[-1] - q_goal), jnp.linalg.norm(qd[-1] / s - qd_goal))
        return s, cost, jnp.maximum(viol, err)

    # over the candidates
    lin = jax.vmap(linearise, in_axes=(None, None, None, 0, 0))
    step = jax.vmap(effort_step_at, in_axes=(None, None, None, None, None, 0, 0, 0, 0, None))

    # the periods are the predicted ones and uniform ones of the same total time; the
    # projections kept as candidates are a slice of the two
    keep = slice(0 if projection else 1, 2 if uniform_projection else 1)
    names = ["projected", "projected_uniform"][keep]
    if effort:
        names += ["effort", "effort_uniform"]
    if switch:
        names += ["switch", "switch_uniform"]
    bounded = lim.qd_max is not None and lim.qdd_max is not None
    if trapezoid is None:
        trapezoid = bounded
    elif trapezoid and not bounded:
        raise ValueError("make_repair: trapezoid=True needs the robot's qd_max and qdd_max")
    if trapezoid:
        names += ["trapezoid"]
    if not names:
        raise ValueError("make_repair: no candidates (projection, uniform_projection, effort, switch and trapezoid "
                         "all off)")
    uniform_flags = np.array([n.endswith("_uniform") or n == "trapezoid" for n in names])

    def repair(q0, qd0, q_goal, qd_goal, v, h):
        h = jnp.clip(h, h_min, h_max)
        h2 = jnp.stack([h, jnp.full_like(h, jnp.mean(h))])
        proj = jax.vmap(goal_projection, in_axes=(None, None, None, None, None, 0))
        v2 = proj(q0, qd0, q_goal, qd_goal, v, h2)
        vs, hs = v2[keep], h2[keep]
        known = None  # the states and efforts of the candidates so far, where computed
        if effort:  # an effort step from each projection
            # the projections' states and efforts serve both their own candidates and the
            # linearisation of the steps
            q, qd, tau, J = lin(robot, q0, qd0, v2, h2)
            w = step(U, q0, qd0, q_goal, qd_goal, v2, h2, tau, J, rho * u_scale)
            known = (q[keep], qd[keep], tau[keep])
            q1, qd1, tau1 = jax.vmap(states, in_axes=(None, None, 0, 0))(q0, qd0, w, h2)
            vs, hs = jnp.concatenate([vs, w]), jnp.concatenate([hs, h2])
            known = tuple(jnp.concatenate([x, y]) for x, y in zip(known, (q1, qd1, tau1)))
        if switch:  # the switching profile on both periods
            w = jax.vmap(goal_projection, in_axes=(None, None, None, None, 0, 0))(
                q0, qd0, q_goal, qd_goal, jax.vmap(switch_profile, in_axes=(None, None, None, 0))(q0, qd0, q_goal, h2), h2)
            vs, hs = jnp.concatenate([vs, w]), jnp.concatenate([hs, h2])
        if trapezoid:  # the synchronised trapezoid on its own periods
            w, ht = trapezoid_profile(q0, q_goal, h.shape[0], lim.qd_max, lim.qdd_max)
            ht = jnp.clip(ht, h_min, h_max)
            w = goal_projection(q0, qd0, q_goal, qd_goal, w, ht)
            vs, hs = jnp.concatenate([vs, w[None]]), jnp.concatenate([hs, ht[None]])
        outside = jnp.zeros((), bool)
        if positions:  # every candidate's path bent inside the position constraints (its states anew)
            # (skipped where every candidate is inside: for a single plan a branch, under vmap a select)
            rows = jax.vmap(jax.vmap(lambda x: position_rows(robot, x)))
            outside = jnp.any(rows(jax.vmap(rollout, in_axes=(None, None, 0, 0))(q0, qd0, vs, hs)[0]) > 0)
            known = None  # (with "flag" too: the same arithmetic as the step's where it does not run)
            if positions is True:
                step_all = jax.vmap(lambda w, hk: position_step(robot, q0, qd0, q_goal, qd_goal, w, hk))
                vs = jax.lax.cond(outside, step_all, lambda w, hk: w, vs, hs)
        done = 0 if known is None else known[0].shape[0]
        if quadratic:
            # every candidate's states; their efforts at any scaling from one polynomial each
            q, qd = jax.vmap(rollout, in_axes=(None, None, 0, 0))(q0, qd0, vs[done:], hs[done:])
            if known is not None:
                q, qd = jnp.concatenate([known[0], q]), jnp.concatenate([known[1], qd])
            abc = rate_polynomials(q, qd, vs)
            s, cost, viol = jax.vmap(candidate_quadratic, in_axes=(None, None, 0, 0, 0, 0, 0, 0, 0))(
                q_goal, qd_goal, vs, hs, q, qd, *abc)
            arrays = (vs, hs, q, qd) + abc
        else:
            # the states and efforts of every candidate not yet known, in one batch
            if done == vs.shape[0]:
                q, qd, tau = known
            else:
                new = jax.vmap(states, in_axes=(None, None, 0, 0))(q0, qd0, vs[done:], hs[done:])
                q, qd, tau = new if known is None else tuple(jnp.concatenate([x, y]) for x, y in zip(known, new))
            if homogeneous:
                s, cost, viol = jax.vmap(candidate_homogeneous, in_axes=(None, None, 0, 0, 0, 0, 0))(
                    q_goal, qd_goal, vs, hs, q, qd, tau)
                arrays = (vs, hs, q, qd, tau)
            else:
                out = jax.vmap(candidate, in_axes=(None, None, None, None, 0, 0, 0, 0, 0))(
                    q0, qd0, q_goal, qd_goal, vs, hs, q, qd, tau)
                arrays, cost, s, viol = out[:5], out[5], out[6], out[7]
        viol = jnp.where(jnp.isnan(viol), jnp.inf, viol)
        ok = viol <= 1e-9
        i = jnp.where(jnp.any(ok), jnp.argmin(jnp.where(ok, cost, jnp.inf)), jnp.argmin(viol))
        # the chosen candidate by a mask and a sum (fused loops) rather than gathers
        pick = jnp.arange(len(names)) == i
        chosen = lambda a: jnp.sum(jnp.where(pick.reshape((-1,) + (1,) * (a.ndim - 1)), a, 0), axis=0)  # noqa: E731
        if quadratic:
            # the chosen plan scaled, its efforts from their polynomial, its cost measured on
            # the scaled arrays
            s = chosen(s)
            v, h, q, qd, a, b, c3 = (chosen(x) for x in arrays)
            q, qd, v, tau, h = at_rate(q, qd, v, h, a, b, c3, s)
            c = cost_of(robot, weights, q, qd, tau, h)
        else:
            v, h, q, qd, tau = (chosen(a) for a in arrays)
            s, c = chosen(s), chosen(cost)
        if homogeneous:
            # the chosen plan scaled: the same q, qd / s, tau / s^2 (exact, up to rounding; the
            # tests re-verify them), its cost measured on the scaled arrays
            qd, tau, v, h = qd / s, tau / s**2, v / s**2, h * s
            c = cost_of(robot, weights, q, qd, tau, h)
        return Repaired(v, h, q, qd, tau, c, s, jnp.any(pick & uniform_flags), i, outside)

    repair.candidates, repair.positions = tuple(names), positions
    return repair
