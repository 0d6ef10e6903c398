"""The five transcriptions, one class each (see :class:`~jtraj.transcription.Transcription`
for what their controls mean): the decoupled one of Khoukhi's thesis, the coupled one
(forward dynamics in the same recursion) and Chettibi's collocation, shooting and spline."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..problem import Problem
from .base import BIG, StageData, Transcription, box_rows
from .recursion import integrate, jerk_inequalities, jump_rows, recursion_step


#: the decoupled transcription scales a joint's accelerations by at most
#: ``ACCEL_SCALE_SWEEPS * qd_max / h_max``: 2, the acceleration that crosses the velocity
#: box ``[-qd_max, qd_max]`` in one longest period (see :meth:`Decoupled.control_box`)
ACCEL_SCALE_SWEEPS = 2.0


def _symmetric_box(bound, size):
    """(scale, lo, hi) of ``|x| <= bound``, scaled by the bound (BIG where absent)."""
    if bound is None:
        return jnp.ones(size), -BIG * jnp.ones(size), BIG * jnp.ones(size)
    return jnp.asarray(bound, float), -jnp.ones(size), jnp.ones(size)


def _joint_box(problem: Problem, scale=1.0):
    """(scale, lo, hi) of the joint positions' box divided by ``scale``."""
    lim, n = problem.robot.limits, problem.robot.n
    scale = jnp.broadcast_to(jnp.asarray(scale, float), (n,))
    if lim.q_min is None:
        return scale, -BIG * jnp.ones(n), BIG * jnp.ones(n)
    return scale, jnp.asarray(lim.q_min, float) / scale, jnp.asarray(lim.q_max, float) / scale


def _n_efforts(problem: Problem) -> int:
    tau_max = problem.robot.limits.tau_max
    return problem.robot.n if tau_max is None else tau_max.shape[0]


def _forward_accelerations(tr: Transcription, problem: Problem, q, qd, c):
    """The interval accelerations a_k (N, n) of an effort-driven transcription."""
    return jax.vmap(lambda q_, qd_, c_: tr.accel_and_tau(problem, q_, qd_, c_)[0])(q[:-1], qd[:-1], c[:-1])


class _AccelerationDriven(Transcription):
    """A control slot holding the joint accelerations, the efforts their inverse dynamics."""

    controls_are_accelerations = True
    linear_in_controls = True

    def control_dim(self, problem):
        return problem.robot.n

    def accel_and_tau(self, problem, q, qd, c):
        return c, problem.robot.inverse_dynamics(q, qd, c)


class Decoupled(_AccelerationDriven):
    """u_k = v_k, the accelerations; tau_k = ID(q_k, qd_k, v_k) (the thesis' method)."""

    name = "decoupled"

    def control_box(self, problem):
        """The accelerations' box ``|v| <= qdd_max``, each joint's accelerations scaled by
        ``min(qdd_max, 2 qd_max / h_max)``: an acceleration of ``2 qd_max / h_max`` crosses
        the whole velocity box in one longest period, so that where ``qdd_max`` is larger
        the velocity bound, not the acceleration bound, sets the scale of the joint's
        motion. Scaled by ``qdd_max`` alone, such a joint (a slow prismatic torso: 0.035
        m/s against the default 10 m/s^2 of a URDF arm) moves through unknowns an order
        of magnitude smaller than the other joints', and the solver stalls away from
        feasible points of problems IPOPT solves (TIAGo Pro's arm in
        ``benchmarks/bench_urdf_arms.py``; serial3 with a slow joint in
        ``tests/test_solver.py``)."""
        lim, n = problem.robot.limits, problem.robot.n
        if lim.qdd_max is None or lim.qd_max is None:
            return _symmetric_box(lim.qdd_max, n)
        qdd_max = jnp.broadcast_to(jnp.asarray(lim.qdd_max, float), (n,))
        scale = jnp.minimum(qdd_max, ACCEL_SCALE_SWEEPS * jnp.asarray(lim.qd_max, float) / lim.h_max)
        return scale, -qdd_max / scale, qdd_max / scale

    def initial_controls(self, problem, v, h):
        return v

    def controls_of(self, solution):
        return solution.v

    def states_and_slot(self, problem, u, h):
        u_ext = jnp.concatenate([u, jnp.zeros((1, u.shape[1]))])
        return (*integrate(problem.q_start, problem.qd_start, u, h), u_ext)

    def acceleration_rows(self, problem, q, qd, a, h, sd: StageData, at):
        # the accelerations are the controls, boxed exactly; with efforts="intervals" the
        # effort at the interval's end too: the state has moved on, the acceleration is still a
        lim = problem.robot.limits
        if problem.efforts != "intervals" or lim.tau_max is None:
            return {}
        q1, qd1 = recursion_step(q, qd, a, h)
        return {"tau_end": box_rows(problem.robot.inverse_dynamics(q1, qd1, a), lim.tau_max, sd.is_interval)}

    def jerk_inequalities(self, problem, u, h):
        return jerk_inequalities(u, h, problem.robot.limits)


class _EffortDriven(Transcription):
    """The recursion or an integrator driven by the efforts through forward dynamics."""

    def control_dim(self, problem):
        return _n_efforts(problem)

    def control_box(self, problem):
        return _symmetric_box(problem.robot.limits.tau_max, _n_efforts(problem))

    def accel_and_tau(self, problem, q, qd, c):
        return problem.robot.forward_dynamics(q, qd, c), c

    def initial_controls(self, problem, v, h):
        q, qd = integrate(problem.q_start, problem.qd_start, v, h)
        return jax.vmap(problem.robot.inverse_dynamics)(q[:-1], qd[:-1], v)

    def controls_of(self, solution):
        return solution.tau

    def step(self, problem, q, qd, u, h):
        """(q, qd) at the end of one interval."""
        raise NotImplementedError

    def states_and_slot(self, problem, u, h):
        q0, qd0 = problem.q_start, problem.qd_start
        u_ext = jnp.concatenate([u, jnp.zeros((1, u.shape[1]))])

        def step(carry, uh):
            nxt = self.step(problem, *carry, *uh)
            return nxt, nxt

        _, (qs, qds) = jax.lax.scan(step, (q0, qd0), (u, h))
        return jnp.concatenate([q0[None], qs]), jnp.concatenate([qd0[None], qds]), u_ext


class Coupled(_EffortDriven):
    """u_k = tau_k; Khoukhi's recursion with a_k = FD(q_k, qd_k, tau_k)."""

    name = "coupled"

    def step(self, problem, q, qd, u, h):
        return recursion_step(q, qd, problem.robot.forward_dynamics(q, qd, u), h)

    def jerk_inequalities(self, problem, u, h):
        q, qd, c = self.states_and_slot(problem, u, h)
        return jerk_inequalities(_forward_accelerations(self, problem, q, qd, c), h, problem.robot.limits)


class Shooting(_EffortDriven):
    """u_k = tau_k held over the interval; one classical RK4 step of the continuous
    dynamics per interval (Chettibi's method 2). No jerk rows: its acceleration varies
    within an interval."""

    name = "shooting"

    def step(self, problem, q, qd, u, h):
        fd = problem.robot.forward_dynamics
        k1q, k1v = qd, fd(q, qd, u)
        k2q, k2v = qd + 0.5 * h * k1v, fd(q + 0.5 * h * k1q, qd + 0.5 * h * k1v, u)
        k3q, k3v = qd + 0.5 * h * k2v, fd(q + 0.5 * h * k2q, qd + 0.5 * h * k2v, u)
        k4q, k4v = qd + h * k3v, fd(q + h * k3q, qd + h * k3v, u)
        return (q + h / 6 * (k1q + 2 * k2q + 2 * k3q + k4q), qd + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v))


class Collocation(Transcription):
    """u_k = (tau_k, q_{k+1}, qd_{k+1}): the states are unknowns and the midpoint-rule
    defects of every interval are equalities (Chettibi's method 1)."""

    name = "collocation"
    linear_stage_map = True
    linear_in_controls = True

    def control_dim(self, problem):
        return _n_efforts(problem) + 2 * problem.robot.n

    def control_box(self, problem):
        lim = problem.robot.limits
        parts = [_symmetric_box(lim.tau_max, _n_efforts(problem)), _joint_box(problem),
                 _symmetric_box(lim.qd_max, problem.robot.n)]
        return tuple(jnp.concatenate([p[i] for p in parts]) for i in range(3))

    def accel_and_tau(self, problem, q, qd, c):
        n = problem.robot.n
        m = c.shape[0] - 2 * n
        tau, q1, qd1 = c[:m], c[m:m + n], c[m + n:]
        return problem.robot.forward_dynamics((q + q1) / 2, (qd + qd1) / 2, tau), tau

    def initial_controls(self, problem, v, h):
        q, qd = integrate(problem.q_start, problem.qd_start, v, h)
        tau = jax.vmap(problem.robot.inverse_dynamics)(q[:-1], qd[:-1], v)
        return jnp.concatenate([tau, q[1:], qd[1:]], axis=1)

    def controls_of(self, solution):
        return jnp.concatenate([solution.tau, solution.q[1:], solution.qd[1:]], axis=1)

    def states_and_slot(self, problem, u, h):
        u_ext = jnp.concatenate([u, jnp.zeros((1, u.shape[1]))])
        n = problem.robot.n
        m = u.shape[1] - 2 * n
        q = jnp.concatenate([problem.q_start[None], u[:, m:m + n]])
        qd = jnp.concatenate([problem.qd_start[None], u[:, m + n:]])
        return q, qd, u_ext

    def defect_rows(self, problem, q, qd, u, h, a, sd: StageData):
        # midpoint-rule defects of interval k
        n, qd_max = problem.robot.n, problem.robot.limits.qd_max
        qd_scale = 1.0 if qd_max is None else qd_max
        q1, qd1 = u[-2 * n:-n], u[-n:]
        return {"defect": sd.is_interval * jnp.concatenate([q1 - q - h * (qd + qd1) / 2, (qd1 - qd - h * a) / qd_scale])}

    def jerk_inequalities(self, problem, u, h):
        q, qd, c = self.states_and_slot(problem, u, h)
        return jerk_inequalities(_forward_accelerations(self, problem, q, qd, c), h, problem.robot.limits)


class Spline(_AccelerationDriven):
    """u_k = q_{k+1}, the knot positions of a clamped cubic spline (C2) through the start
    and the knots; tau = ID at the knots (Chettibi's method 3). The last knot is the goal,
    a fixed variable; the knot accelerations and efforts are bounded at all N+1 knots."""

    name = "spline"

    def control_box(self, problem):
        # knots scaled by the displacement that saturates the acceleration over one
        # period: the Newton system is then O(1) in every direction
        lim = problem.robot.limits
        return _joint_box(problem, 1.0 if lim.qdd_max is None else lim.qdd_max * lim.h_max**2)

    def control_bounds(self, problem, lo, hi, u_scale):
        goal = problem.q_goal / u_scale
        return lo.at[-1].set(goal), hi.at[-1].set(goal)

    def initial_controls(self, problem, v, h):
        return integrate(problem.q_start, problem.qd_start, v, h)[0][1:]

    def controls_of(self, solution):
        return solution.q[1:]

    def states_and_slot(self, problem, u, h):
        return clamped_spline(problem.q_start, problem.qd_start, problem.qd_goal, u, h)

    def effort_samples(self, sd: StageData):
        return jnp.ones_like(sd.is_interval)

    def jerk_inequalities(self, problem, u, h):
        """The cubic's acceleration is continuous and piecewise linear, its jerk on
        interval k is ``(qdd_{k+1} - qdd_k) / h_k`` exactly: the rows are
        ``|qdd_{k+1} - qdd_k| <= qddd_max h_k`` for k = 0..N-1 (the first and last
        intervals included: the spline's own jerk is bounded everywhere)."""
        c = self.states_and_slot(problem, u, h)[2]
        return jump_rows(c[1:] - c[:-1], h, problem.robot.limits)


def clamped_spline(q0, qd0, qdN, knots, h):
    """Clamped cubic spline through ``q0, knots[0], ..., knots[-1]`` with end velocities
    ``qd0, qdN`` and interval lengths ``h``: (q, qd, qdd) at the N+1 knots.

    The knot velocities solve the C2 continuity conditions (tridiagonal, diagonally
    dominant; solved densely, N is small), for interior knots i::

        h_i qd_{i-1} + 2 (h_{i-1} + h_i) qd_i + h_{i-1} qd_{i+1}
            = 3 (h_i d_{i-1} + h_{i-1} d_i),   d_k = (q_{k+1} - q_k) / h_k

    and the acceleration at the start of interval k is
    ``6 d_k / h_k - (4 qd_k + 2 qd_{k+1}) / h_k`` (at its end
    ``-6 d_k / h_k + (2 qd_k + 4 qd_{k+1}) / h_k``; equal at interior knots)."""
    q = jnp.concatenate([q0[None], knots])
    N = h.shape[0]
    d = (q[1:] - q[:-1]) / h[:, None]
    if N == 1:
        qd = jnp.stack([qd0, qdN])
    else:
        hl, hr = h[:-1], h[1:]  # h_{i-1}, h_i for i = 1..N-1
        rhs = 3 * (hr[:, None] * d[:-1] + hl[:, None] * d[1:])
        rhs = rhs.at[0].add(-hr[0] * qd0).at[-1].add(-hl[-1] * qdN)
        A = jnp.diag(2 * (hl + hr)) + jnp.diag(hr[1:], -1) + jnp.diag(hl[:-1], 1)
        qd = jnp.concatenate([qd0[None], jnp.linalg.solve(A, rhs), qdN[None]])
    a_start = 6 * d / h[:, None] - (4 * qd[:-1] + 2 * qd[1:]) / h[:, None]
    a_end = -6 * d[-1] / h[-1] + (2 * qd[-2] + 4 * qd[-1]) / h[-1]
    return q, qd, jnp.concatenate([a_start, a_end[None]])
