"""Initial guesses: cycloidal (serial arms) and trapezoidal (PKM) profiles.

Both return ``(v, h)`` with v (N, n) accelerations at the samples and h (N,) equal
periods, for a rest-to-rest move ``q_start -> q_goal``.

Cycloidal profile (Khoukhi): ``q(t) = q0 + dq (t/T - sin(2 pi t/T) / (2 pi))`` with
the per-joint minimum time
``T_j = max(2|dq_j|/qd_max_j, sqrt(2 pi |dq_j| / qdd_max_j), (4 pi^2 |dq_j| / qddd_max_j)^(1/3))``
and ``T = max_j T_j`` (limits that a robot does not have are skipped), then clipped to
``[N h_min, N h_max]`` and to ``T_max``.

Trapezoidal profile: accelerate at ``a`` up to ``v_c``, cruise, decelerate, every joint
synchronised to the slowest one.
"""

from __future__ import annotations

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


def cycloidal(problem: Problem):
    """(v, h) sampled from the minimum-time cycloidal profile."""
    T = _clip_T(problem, cycloidal_time(problem))
    N = problem.N
    h = jnp.full((N,), T / N)
    t = jnp.arange(N) * T / N + 0.5 * T / N  # mid-interval acceleration
    dq = problem.q_goal - problem.q_start
    v = dq[None, :] * (2 * jnp.pi / T**2) * jnp.sin(2 * jnp.pi * t / T)[:, None]
    return v, h


def cycloid_path(problem: Problem, T, t):
    """q(t), qd(t) of the cycloid of duration T at times t (for plots)."""
    dq = problem.q_goal - problem.q_start
    s = t / T
    q = problem.q_start + dq * (s - jnp.sin(2 * jnp.pi * s) / (2 * jnp.pi))[:, None]
    qd = dq * ((1 - jnp.cos(2 * jnp.pi * s)) / T)[:, None]
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


GUESSES = {"cycloidal": cycloidal, "trapezoidal": trapezoidal}
