"""Inverse kinematics for any robot with ``forward_kinematics`` (redundant arms included).

Two iterative methods, both a fixed-bound ``lax.while_loop`` (jit- and vmap-able; vmap
over ``p`` and ``q_init``)::

    e_k   = p - f(q_k),   clipped to at most ``max_step`` (task units) in norm
    "weighted" (Khoukhi):  J# = M^{-1} J^T (J M^{-1} J^T)^{-1}       (M = mass matrix)
                           dq = J# e_k + (I - J# J) z,   z = -null_gain W (q - q_mid)
    "dls":                 dq = J^T (J J^T + lambda^2 I)^{-1} e_k
    q_{k+1} = q_k + dq,   |dq|_inf clipped to ``max_dq`` rad (or m)

The weighted pseudo-inverse is the inertia-weighted ("dynamically consistent") one of
the thesis. Its null-space term moves the joints towards the middle of their range
without moving the task point. The thesis prints ``W = diag(q_max - q_min)``, which is
dimensionally inconsistent (it would push wide-range joints hardest); we use the
Liegeois weighting ``W = diag(min_j(half_j^2) / half_i^2)``, ``half = (q_max - q_min)/2``,
i.e. the gradient of ``sum ((q_i - q_mid,i) / half_i)^2`` scaled so that the largest
weight is 1 (keeps the iteration stable), so joints close to a limit relative to
their range are pushed hardest. Without a joint
box (``q_min``/``q_max`` None) there is no null-space term.

Iteration stops when ``|e| <= tol`` and q is inside the joint box (or, outside it,
once the null-space step is below ``null_tol``: the self-motion cannot bring q back
in), or after ``max_iter`` iterations.

Status codes (:data:`STATUS`):

* 0 ``SUCCESS``: ``|p - f(q)| <= tol`` and q inside the joint box (if any);
* 1 ``NOT_CONVERGED``: the residual did not reach ``tol`` in ``max_iter`` iterations:
  the target is unreachable (outside the workspace, or the closed chains of a parallel
  robot cannot assemble there: ``assembly_margin(q) <= 0``) or the iteration stalled
  (e.g. at a singularity);
* 2 ``JOINT_LIMITS``: the task point is reached but q lies outside the joint box;
* 3 ``NONFINITE``: NaN/inf appeared (e.g. NaN inputs inside a traced call); q is
  then the last finite iterate.

Bad concrete input (wrong shape, NaN/inf, unknown method) raises ``ValueError`` naming
the argument, before tracing.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._checks import as_array, is_concrete
from ._base import Robot

SUCCESS, NOT_CONVERGED, JOINT_LIMITS, NONFINITE = 0, 1, 2, 3
STATUS = {SUCCESS: "success", NOT_CONVERGED: "unreachable or not converged",
          JOINT_LIMITS: "reached outside the joint limits", NONFINITE: "non-finite values"}
METHODS = ("weighted", "dls")


class IKResult(NamedTuple):
    """Result of :func:`ik`. Under vmap every field gains a leading batch axis.

    q: (n,) joint configuration; status: int code (see :data:`STATUS`);
    error: task-space residual ``|p - f(q)|``; iterations: iterations used.
    """

    q: Array
    status: Array
    error: Array
    iterations: Array


def check_array(x, name: str, shape: tuple[int, ...]):
    if is_concrete(x):
        return jnp.asarray(as_array(x, name, shape))
    x = jnp.asarray(x)
    if x.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got shape {x.shape}")
    return x.astype(jnp.result_type(float))


def check_settings(robot, max_iter, null_gain, **positive) -> None:
    """``ValueError`` naming the argument: ``robot`` not a Robot, ``max_iter`` not a
    positive integer, a concrete ``null_gain`` negative or not finite, or a concrete
    value of ``positive`` not a finite number > 0 (traced values pass)."""
    if not isinstance(robot, Robot):
        raise ValueError(f"robot must be a jtraj.robots.Robot, got {type(robot).__name__}")
    if not isinstance(max_iter, (int, np.integer)) or isinstance(max_iter, bool) or max_iter < 1:
        raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}")
    for name, val in positive.items():
        if is_concrete(val) and not (np.isfinite(val) and float(val) > 0):
            raise ValueError(f"{name} must be a finite number > 0, got {val!r}")
    if is_concrete(null_gain) and not (np.isfinite(null_gain) and float(null_gain) >= 0):
        raise ValueError(f"null_gain must be a finite number >= 0, got {null_gain!r}")


def default_q_init(robot: Robot) -> Array:
    """Middle of the joint box when the robot has one, else 0.5 on every coordinate
    (a bent, non-singular posture for planar serial arms)."""
    lim = robot.limits
    q = jnp.full((robot.n,), 0.5)
    if lim.q_min is not None and lim.q_max is not None:
        mid = 0.5 * (lim.q_min + lim.q_max)
        q = jnp.where(jnp.isfinite(mid), mid, q)
    return q


def ik(robot: Robot, p, q_init=None, *, method: str = "weighted", max_iter: int = 200,
       tol: float = 1e-10, damping: float = 0.05, null_gain: float = 0.5,
       null_tol: float = 1e-8, max_step: float = 0.2, max_dq: float = 0.3) -> IKResult:
    """Joint configuration q with ``robot.forward_kinematics(q) = p``.

    Args:
        robot: any :class:`~jtraj.robots.Robot`.
        p: (d,) target task point.
        q_init: (n,) start of the iteration; default :func:`default_q_init`. Different
            starts reach different solutions of a redundant arm.
        method: ``"weighted"`` (thesis: inertia-weighted pseudo-inverse + joint-limit
            null-space motion) or ``"dls"`` (damped least squares).
        max_iter: iteration bound (static).
        tol: task-space tolerance on ``|p - f(q)|``.
        damping: lambda of the DLS method (task units).
        null_gain: gain of the null-space motion (0 gives the plain weighted
            pseudo-inverse).
        null_tol: the weighted method also waits until the null-space step is this small.
        max_step: largest task-space correction per iteration (norm).
        max_dq: largest joint change per iteration (infinity norm).

    Returns:
        :class:`IKResult`.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    check_settings(robot, max_iter, null_gain, tol=tol, damping=damping, max_step=max_step, max_dq=max_dq,
                   null_tol=null_tol)
    n = robot.n
    q0 = default_q_init(robot) if q_init is None else check_array(q_init, "q_init", (n,))
    d = jax.eval_shape(robot.forward_kinematics, jax.ShapeDtypeStruct((n,), q0.dtype)).shape[0]
    p = check_array(p, "p", (d,))
    hyper = [jnp.asarray(x, dtype=q0.dtype) for x in (tol, damping, null_gain, null_tol, max_step, max_dq)]
    return _ik(robot, p, q0, method, int(max_iter), *hyper)  # traced hyperparameters: one compile


def box_centring(lim):
    """(q_mid, W) of the null-space term ``-null_gain W (q - q_mid)`` that pulls a
    redundant arm towards the middle of its joint box: W_i = min_j half_j^2 / half_i^2
    (the gradient of ``sum ((q_i - q_mid,i) / half_i)^2`` scaled so that the narrowest
    joint's weight is 1, see the module docstring), zero for a joint without finite limits."""
    lo, hi = lim.q_min, lim.q_max
    finite = jnp.isfinite(lo) & jnp.isfinite(hi)
    mid = jnp.where(finite, 0.5 * (lo + hi), 0.0)
    half2 = jnp.where(finite, (0.5 * (hi - lo)) ** 2, 1.0)
    return mid, jnp.where(finite, jnp.min(jnp.where(finite, half2, jnp.inf)) / half2, 0.0)


@eqx.filter_jit
def _ik(robot, p, q0, method, max_iter, tol, damping, null_gain, null_tol, max_step, max_dq):
    lim = robot.limits
    has_box = lim.q_min is not None and lim.q_max is not None
    if has_box:
        mid, w = box_centring(lim)

    def residual(q):
        return p - robot.forward_kinematics(q)

    def step(q):
        e = residual(q)
        en = jnp.linalg.norm(e)
        e_c = e * jnp.minimum(1.0, max_step / jnp.maximum(en, 1e-300))
        J = robot.jacobian(q)
        dd = J.shape[0]
        if method == "dls":
            dq = J.T @ jnp.linalg.solve(J @ J.T + damping**2 * jnp.eye(dd), e_c)
            dq_null = jnp.zeros_like(q)
        else:
            Minv_Jt = jnp.linalg.solve(robot.mass_matrix(q), J.T)
            A = J @ Minv_Jt
            A = A + 1e-12 * jnp.trace(A) / dd * jnp.eye(dd)  # guard exact singularity
            Jsharp = Minv_Jt @ jnp.linalg.inv(A)
            dq = Jsharp @ e_c
            if has_box:
                z = -null_gain * w * (q - mid)
                dq_null = z - Jsharp @ (J @ z)
            else:
                dq_null = jnp.zeros_like(q)
            dq = dq + dq_null
        scale = jnp.minimum(1.0, max_dq / jnp.maximum(jnp.max(jnp.abs(dq)), 1e-300))
        return q + scale * dq, jnp.max(jnp.abs(dq_null))

    def inside_box(q):
        return jnp.all((q >= lim.q_min) & (q <= lim.q_max)) if has_box else jnp.asarray(True)

    def done(q, null_step):
        return (jnp.linalg.norm(residual(q)) <= tol) & (inside_box(q) | (null_step <= null_tol))

    def cond(state):
        q, k, null_step, bad = state
        return (k < max_iter) & ~done(q, null_step) & ~bad

    def body(state):
        q, k, _, _ = state
        q_new, null_step = step(q)
        bad = ~(jnp.all(jnp.isfinite(q_new)) & jnp.isfinite(null_step))
        return jnp.where(bad, q, q_new), k + 1, null_step, bad  # keep the last finite q

    init = (q0, jnp.zeros((), jnp.int32), jnp.asarray(jnp.inf, q0.dtype), ~jnp.all(jnp.isfinite(q0)))
    q, k, _, bad = jax.lax.while_loop(cond, body, init)
    err = jnp.linalg.norm(residual(q))
    reached = err <= tol
    assembled = jnp.asarray(True)
    margin = getattr(robot, "assembly_margin", None)
    if margin is not None:
        assembled = margin(q) > 0
    inside = inside_box(q)
    status = jnp.where(~assembled | (~reached & ~bad), NOT_CONVERGED,
                       jnp.where(bad | ~jnp.isfinite(err), NONFINITE,
                                 jnp.where(inside, SUCCESS, JOINT_LIMITS)))
    return IKResult(q=q, status=status.astype(jnp.int32), error=err, iterations=k)
