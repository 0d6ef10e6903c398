"""A solved trajectory on a dense time grid: what a joint controller executes.

The decoupled and coupled transcriptions hold the acceleration constant over each
interval (``q_{k+1} = q_k + h_k qd_k + h_k^2/2 v_k``), so between the samples the motion
is known exactly::

    q(t_k + s) = q_k + s qd_k + s^2/2 v_k,   qd(t_k + s) = qd_k + s v_k,   qdd = v_k

and the efforts that realise it are ``tau(t) = ID(q(t), qd(t), v_k)``. By default
(``Problem(efforts="samples")``, the thesis) the solver bounds the efforts at the
samples only; between them they vary with the state and exceed ``tau_max`` at the end of
an interval (``efforts="intervals"`` bounds those too). :func:`resample` returns them,
and :func:`intersample_effort` measures the excess (docs/guides/problems.md,
"Efforts between the samples").

The other transcriptions are not constant-acceleration trajectories (the spline's
acceleration is linear between knots, shooting and collocation integrate the forward
dynamics); :func:`resample` recognises that from the solution itself (its states do not
follow the recursion from its ``v`` and ``h``) and refuses it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .robots import Robot
from .transcription import integrate, recursion_step

__all__ = ["Samples", "intersample_effort", "interval_times", "resample"]


class Samples(NamedTuple):
    """A trajectory on a time grid (a leading batch axis for a batch of solutions).

    Attributes:
        t: (M,) times [s] from 0 to T (the last grid step may be shorter, see
            :func:`resample`); q, qd, qdd: (M, n); tau: (M, m) efforts by inverse dynamics;
        interval: (M,) index k of the interval each time lies in.
    """

    t: Array
    q: Array
    qd: Array
    qdd: Array
    tau: Array
    interval: Array


@eqx.filter_jit
def _evaluate(robot, q, qd, v, h, t):
    """Samples at times t (M,) of one trajectory (q (N+1, n), qd, v (N, n), h (N,))."""
    N = h.shape[0]
    starts = jnp.concatenate([jnp.zeros(1, h.dtype), jnp.cumsum(h)[:-1]])
    k = jnp.clip(jnp.searchsorted(starts, t, side="right") - 1, 0, N - 1)
    vk = v[k]
    qt, qdt = recursion_step(q[k], qd[k], vk, (t - starts[k])[:, None])
    tau = jax.vmap(robot.inverse_dynamics)(qt, qdt, vk)
    return Samples(t=t, q=qt, qd=qdt, qdd=vk, tau=tau, interval=k)


def _arrays(solution, robot):
    """(q, qd, v, h) as float64/float NumPy arrays with a batch axis, checked."""
    if isinstance(solution, Mapping) and all(k in solution for k in ("q", "qd", "v", "h")):
        fields = tuple(solution[k] for k in ("q", "qd", "v", "h"))  # jtraj.dataset.load(path), say
    elif all(hasattr(solution, k) for k in ("q", "qd", "v", "h")):
        fields = (solution.q, solution.qd, solution.v, solution.h)  # a Solution, a jtraj.online.Plan
    else:
        raise ValueError(f"solution must be a jtraj.Solution, a jtraj.online.Plan or a mapping with q, qd, v, h "
                         f"(a loaded dataset), got {type(solution).__name__}")
    if not isinstance(robot, Robot):
        raise ValueError(f"robot must be a jtraj.robots.Robot, got {type(robot).__name__}")
    q, qd, v, h = (np.asarray(x, dtype=float) for x in fields)
    if q.ndim not in (2, 3) or qd.shape != q.shape or v.shape != q.shape[:-2] + (q.shape[-2] - 1, q.shape[-1]) \
            or h.shape != v.shape[:-1]:
        raise ValueError(f"solution: q, qd (..., N+1, n), v (..., N, n), h (..., N) expected, got {q.shape}, "
                         f"{qd.shape}, {v.shape}, {h.shape}")
    single = q.ndim == 2
    if single:
        q, qd, v, h = q[None], qd[None], v[None], h[None]
    if q.shape[-1] != robot.n:
        raise ValueError(f"robot has n = {robot.n} joints, the solution {q.shape[-1]}")
    bad = ~(np.isfinite(q).all(axis=(1, 2)) & np.isfinite(qd).all(axis=(1, 2)) & np.isfinite(v).all(axis=(1, 2))
            & np.isfinite(h).all(axis=1) & (h > 0).all(axis=1))
    if bad.any():
        which = "" if single else f" (samples {np.flatnonzero(bad)[:10].tolist()})"
        raise ValueError(f"solution holds non-finite values or non-positive periods{which}; "
                         "resample only solutions whose status says they hold a trajectory")
    # the constant-acceleration recursion from (q_0, qd_0, v, h) must reproduce the states
    qs, qds = (np.asarray(x) for x in jax.vmap(integrate)(q[:, 0], qd[:, 0], v, h))
    worst = np.max(np.maximum(np.abs(qs - q), np.abs(qds - qd)) / (1.0 + np.abs(q) + np.abs(qd)), axis=(1, 2))
    tol = max(1e-6, 100 * float(np.finfo(qs.dtype).eps))  # float32 without x64
    if (worst > tol).any():
        which = "" if single else f" (samples {np.flatnonzero(worst > tol)[:10].tolist()})"
        raise ValueError(f"solution: its states do not follow the constant-acceleration recursion from its "
                         f"(v, h){which} (largest relative mismatch {worst.max():.2g}); resample supports "
                         "the decoupled and coupled transcriptions")
    return single, q, qd, v, h


def resample(solution, robot, *, dt: float | None = None, num: int | None = None, times=None) -> Samples:
    """The trajectory of ``solution`` on a time grid, with its efforts by inverse dynamics.

    Args:
        solution: a :class:`jtraj.Solution` of the decoupled or coupled transcription,
            single or batched; or anything with its arrays ``q``, ``qd``, ``v``, ``h``
            (a :class:`jtraj.online.Plan`, a mapping such as a loaded dataset).
        robot: the robot it was solved for.
        dt: grid step [s] (single solutions): t = 0, dt, 2 dt, ... below T, then T itself,
            so the last step may be shorter than dt.
        num: number of grid points, t = linspace(0, T, num) per trajectory.
        times: explicit times [s] within [0, T]: (M,), or (B, M) for a batch. At a sample
            time t_k the motion of interval k is used (the efforts jump there with the
            acceleration).

    Returns :class:`Samples` (a leading batch axis for a batched solution). Give exactly
    one of ``dt``, ``num`` and ``times``; bad input raises ``ValueError`` naming the
    argument.
    """
    if sum(x is not None for x in (dt, num, times)) != 1:
        raise ValueError("give exactly one of dt (grid step, s), num (number of grid points) and times")
    return _resample(robot, *_arrays(solution, robot), dt=dt, num=num, times=times)


def _resample(robot, single, q, qd, v, h, *, dt=None, num=None, times=None) -> Samples:
    """:func:`resample` on the arrays :func:`_arrays` checked."""
    B, T = q.shape[0], h.sum(axis=1)
    if dt is not None:
        try:
            dt = float(dt)
        except (TypeError, ValueError):
            raise ValueError(f"dt must be a number of seconds, got {dt!r}") from None
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a finite number of seconds > 0, got {dt!r}")
        if not single:
            raise ValueError("dt gives each trajectory of a batch its own grid length; use num for a batch")
        M = int(np.floor(T[0] / dt * (1 - 1e-12))) + 1  # grid points strictly below T
        if M > 10_000_000:
            raise ValueError(f"dt = {dt!r} s gives {M} points for T = {T[0]:.4g} s; use a larger dt")
        grids = np.concatenate([np.arange(M) * dt, T[:1]])[None]
    elif num is not None:
        if not isinstance(num, (int, np.integer)) or isinstance(num, bool) or num < 2:
            raise ValueError(f"num must be an integer >= 2, got {num!r}")
        grids = np.linspace(0.0, 1.0, int(num))[None] * T[:, None]
    else:
        grids = np.asarray(times, dtype=float)
        if single and grids.ndim != 1:
            raise ValueError(f"times must have shape (M,) for a single solution, got {grids.shape}")
        if grids.ndim == 1:
            grids = np.broadcast_to(grids, (B,) + grids.shape)
        if grids.ndim != 2 or grids.shape[0] != B or grids.shape[1] < 1:
            raise ValueError(f"times must have shape (M,){'' if single else f' or ({B}, M)'}, got "
                             f"{np.shape(times)}")
        outside = ~np.isfinite(grids) | (grids < 0) | (grids > T[:, None] * (1 + 1e-12))
        if outside.any():
            raise ValueError(f"times must lie within [0, T] (T = {T.max():.6g} s at most); "
                             f"{int(outside.sum())} do not")
    args = [jnp.asarray(x) for x in (q, qd, v, h, grids)]
    samples = eqx.filter_vmap(_evaluate, in_axes=(None, 0, 0, 0, 0, 0))(robot, *args)
    return jax.tree.map(lambda x: x[0], samples) if single else samples


def interval_times(h, per_interval: int) -> np.ndarray:
    """``per_interval`` evenly spaced times in every interval, both ends included (the
    right end nudged by 1e-9 h_k so that it still belongs to interval k): (..., N *
    per_interval) for periods h (..., N)."""
    if not isinstance(per_interval, (int, np.integer)) or isinstance(per_interval, bool) or per_interval < 2:
        raise ValueError(f"per_interval must be an integer >= 2, got {per_interval!r}")
    h = np.asarray(h, dtype=float)
    starts = np.cumsum(h, axis=-1) - h
    frac = np.minimum(np.linspace(0.0, 1.0, int(per_interval)), 1 - 1e-9)
    return (starts[..., None] + h[..., None] * frac).reshape(h.shape[:-1] + (-1,))


def intersample_effort(solution, robot, *, per_interval: int = 16) -> Array:
    """max_t |tau_i(t)| / tau_max_i over the whole motion, evaluated at ``per_interval``
    evenly spaced points of every interval (both ends included, :func:`interval_times`),
    per trajectory.

    By default the solver bounds the ratio by 1 at the samples only; this is what the
    executed motion asks of the actuators in between. Raises ValueError for a robot
    without ``tau_max``.
    """
    single, q, qd, v, h = _arrays(solution, robot)
    if robot.limits.tau_max is None:
        raise ValueError("robot has no tau_max: the effort ratio is undefined")
    samples = _resample(robot, single, q, qd, v, h, times=interval_times(h[0] if single else h, per_interval))
    tau_max = jnp.reshape(robot.limits.tau_max, (1,) * (samples.tau.ndim - 1) + (-1,))
    return jnp.max(jnp.abs(samples.tau) / tau_max, axis=(-2, -1))
