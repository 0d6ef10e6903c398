"""Initial guesses: cycloidal (serial arms) and trapezoidal (PKM) profiles.

Both return ``(v, h)`` with v (N, n) accelerations at the samples and h (N,) equal
periods, for a rest-to-rest move ``q_start -> q_goal``.

Cycloidal profile (Khoukhi): ``q(t) = q0 + dq (t/T - sin(2 pi t/T) / (2 pi))`` with
the per-joint minimum time
``T_j = max(2|dq_j|/qd_max_j, sqrt(2 pi |dq_j| / qdd_max_j), (4 pi^2 |dq_j| / qddd_max_j)^(1/3))``
and ``T = max_j T_j`` (limits that a robot does not have are skipped), then clipped to
``[N h_min, N h_max]`` and to ``T_max``.

Torque-scaled cycloid (``"cycloidal_torque"``, the solver's default): the same path,
slowed until it also meets the torque bounds. Along a path traversed c times slower the
efforts are ``tau = D / c^2 + G(q)`` (D: the inertial and Coriolis part at duration T,
G: gravity), so the smallest c that keeps ``|tau| <= tau_max`` at 2N + 1 points of the
path is ``c^2 = max |D| / (tau_max - sign(D) G)`` (friction, which does not scale so, is
counted in D). On the serial3 benchmark family the kinematic cycloid asks a median 2.4x
the torque bound; the torque-scaled one is within 0.78-0.98x of the optimal T, and the
interior-point method takes about 10 % fewer Newton iterations from it than from the
kinematic cycloid (and more from one run slower or faster than it).

Trapezoidal profile: accelerate at ``a`` up to ``v_c``, cruise, decelerate, every joint
synchronised to the slowest one.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .problem import Problem


def _clip_T(problem: Problem, T):
    lim = problem.robot.limits
    N = problem.N
    T = jnp.clip(T, N * lim.h_min, N * lim.h_max)
    return jnp.minimum(T, jnp.where(jnp.isfinite(problem.T_max), problem.T_max, jnp.inf))


def cycloidal_time(problem: Problem):
    """Minimum cycloidal time T = max_j T_j (before clipping)."""
    lim = problem.robot.limits
    dq = jnp.abs(problem.q_goal - problem.q_start)
    T = jnp.zeros(())
    if lim.qd_max is not None:
        T = jnp.maximum(T, jnp.max(2 * dq / lim.qd_max))
    if lim.qdd_max is not None:
        T = jnp.maximum(T, jnp.max(jnp.sqrt(2 * jnp.pi * dq / lim.qdd_max)))
    if lim.qddd_max is not None:
        T = jnp.maximum(T, jnp.max(jnp.cbrt(4 * jnp.pi**2 * dq / lim.qddd_max)))
    return T


def torque_scaled_time(problem: Problem, T):
    """The duration >= T at which the cycloid meets the torque bounds (see the module
    doc); T itself where the robot has none or its efforts are not per joint."""
    robot = problem.robot
    tau_max = robot.limits.tau_max
    if tau_max is None:
        return T
    T0 = jnp.maximum(T, 1e-3)  # T = 0 when start == goal (D = 0 then)
    s = jnp.arange(2 * problem.N + 1) / (2 * problem.N)
    q, qd = cycloid_path(problem, T0, s * T0)
    qdd = cycloid_acceleration(problem, T0, s * T0)
    tau = jax.vmap(robot.inverse_dynamics)(q, qd, qdd)
    if tau.shape[-1] != tau_max.shape[-1]:
        return T
    G = jax.vmap(robot.inverse_dynamics)(q, jnp.zeros_like(qd), jnp.zeros_like(qdd))
    D = tau - G
    room = jnp.maximum(tau_max[None, :] - jnp.sign(D) * G, 1e-3 * tau_max[None, :])  # gravity alone over the bound: slowest
    c2 = jnp.max(jnp.abs(D) / room)
    return jnp.where(c2 > 1.0, T0 * jnp.sqrt(c2), T)


def cycloidal(problem: Problem, torque: bool = False):
    """(v, h) sampled from the minimum-time cycloidal profile (Khoukhi's: kinematic
    bounds only; with ``torque``, slowed until it meets the torque bounds too)."""
    T = cycloidal_time(problem)
    T = _clip_T(problem, torque_scaled_time(problem, T) if torque else T)
    N = problem.N
    h = jnp.full((N,), T / N)
    t = jnp.arange(N) * T / N + 0.5 * T / N  # mid-interval acceleration
    return cycloid_acceleration(problem, T, t), h


def cycloid_acceleration(problem: Problem, T, t):
    """qdd(t) of the cycloid of duration T at times t."""
    dq = problem.q_goal - problem.q_start
    return dq[None, :] * (2 * jnp.pi / T**2 * jnp.sin(2 * jnp.pi * t / T))[:, None]


def cycloid_path(problem: Problem, T, t):
    """q(t), qd(t) of the cycloid of duration T at times t (for plots)."""
    dq = problem.q_goal - problem.q_start
    s = t / T
    q = problem.q_start[None, :] + dq[None, :] * (s - jnp.sin(2 * jnp.pi * s) / (2 * jnp.pi))[:, None]
    qd = dq[None, :] * ((1 - jnp.cos(2 * jnp.pi * s)) / T)[:, None]
    return q, qd


def trapezoidal(problem: Problem, accel_fraction: float = 0.25):
    """(v, h) of a synchronised trapezoidal velocity profile.

    Each joint accelerates for ``accel_fraction * T``, cruises, and decelerates for the
    same time; T is the smallest time meeting every joint's velocity and acceleration
    bound with that shape.
    """
    lim = problem.robot.limits
    dq = problem.q_goal - problem.q_start
    f = accel_fraction
    # cruise speed dq / ((1 - f) T), acceleration dq / (f (1 - f) T^2)
    T = jnp.zeros(())
    if lim.qd_max is not None:
        T = jnp.maximum(T, jnp.max(jnp.abs(dq) / ((1 - f) * lim.qd_max)))
    if lim.qdd_max is not None:
        T = jnp.maximum(T, jnp.max(jnp.sqrt(jnp.abs(dq) / (f * (1 - f) * lim.qdd_max))))
    T = _clip_T(problem, T)
    N = problem.N
    h = jnp.full((N,), T / N)
    t = (jnp.arange(N) + 0.5) * T / N
    a = dq / (f * (1 - f) * T**2)
    sign = jnp.where(t < f * T, 1.0, jnp.where(t > (1 - f) * T, -1.0, 0.0))
    return sign[:, None] * a[None, :], h


def cycloidal_torque(problem: Problem):
    """:func:`cycloidal` slowed until it meets the torque bounds."""
    return cycloidal(problem, torque=True)


GUESSES = {"cycloidal_torque": cycloidal_torque, "cycloidal": cycloidal, "trapezoidal": trapezoidal}
