"""Inverse kinematics of a position or a full pose (position and orientation) for
spatial robots (URDF arms, the Gough-Stewart platform): damped least squares inside
the joint box, with a null-space term for redundant arms.

One iteration, task error ``e = (p - f(q), log(R_target R(q)^T))`` (the orientation part
only with a target rotation; ``log`` the rotation vector, in the world frame like the
angular rows of the Jacobian)::

    e_c  = e clipped to ``max_step`` (m) and ``max_rot_step`` (rad) in norm
    J    = [J_p; J_w]  (3 x n or 6 x n): J_p = d f / dq, J_w the angular velocity
           Jacobian, omega_i = vee(dR/dq_i R^T) (autodiff of ``robot.rotation``)
    dq   = J^T (J J^T + lambda^2 I)^{-1} e_c  +  (I - J^+ J) z,   z = -null_gain W (q - q_mid)
    lambda^2 = damping^2 min(1, |e_c|^2 / max_step^2)
    q   <- clip(q + s dq, q_min, q_max),   s: |s dq|_inf <= max_dq

The damped step is well defined at and near singularities (where the plain
pseudo-inverse blows up); its damping fades with the error, so that the last steps are
Gauss-Newton steps, which converge quadratically where the Jacobian has full row rank; the null-space term (redundant arms only: n greater than the
task's dimension, 3 or 6) moves the joints towards the middle of their range along
the exact null space of J (J^+ by SVD), so it does not disturb the task at first order;
W is :mod:`jtraj.robots.ik`'s Liegeois weighting. The projection onto the joint box
keeps every iterate admissible (continuous joints: infinite bounds, no projection).

A fixed-bound ``lax.while_loop``: jit- and vmap-able over the target and ``q_init``.
It stops when the position residual is within ``tol`` (m) and the orientation residual
within ``rot_tol`` (rad), or after ``max_iter`` iterations. Status codes are
:mod:`jtraj.robots.ik`'s: 0 success, 1 unreachable or not converged (the target is
outside the reach of the arm within its joint box, or the iteration stalled in a local
minimum: try another ``q_init``; :func:`solve_pose` tries several), 3 non-finite
values. (2, reached outside the joint box, cannot occur: every iterate is in the box.)
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._checks import is_concrete
from ._base import Robot
from .ik import NONFINITE, NOT_CONVERGED, STATUS, SUCCESS, box_centring, check_array, check_settings, default_q_init


class PoseIKResult(NamedTuple):
    """Result of :func:`pose_ik`. Under vmap every field gains a leading batch axis.

    q: (n,) joint configuration; status: int code (:data:`jtraj.robots.ik.STATUS`);
    error: position residual ``|p - f(q)|`` [m]; rot_error: orientation residual, the
    angle of ``R_target R(q)^T`` [rad] (0 without a target rotation); iterations."""

    q: Array
    status: Array
    error: Array
    rot_error: Array
    iterations: Array


def _vee(S):
    """The axial vector of the skew part of a 3 x 3 matrix."""
    return 0.5 * jnp.stack([S[2, 1] - S[1, 2], S[0, 2] - S[2, 0], S[1, 0] - S[0, 1]])


def rotation_log(R) -> Array:
    """The rotation vector ``theta * axis`` (3,) of a rotation matrix, theta in [0, pi]:
    from the skew part where theta is away from pi, from the symmetric part
    ``(R + I) / 2 = axis axis^T`` (at theta = pi) near pi; differentiable away from
    theta = 0 and pi, finite everywhere."""
    c = jnp.clip((jnp.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = jnp.arccos(c)
    v = _vee(R)  # sin(theta) axis
    s = jnp.linalg.norm(v)
    small = s < 1e-6
    # away from pi: theta / sin(theta) * v (-> v as theta -> 0)
    factor = jnp.where(theta < 1e-6, 1.0, theta / jnp.where(small, 1.0, s))
    near_pi = small & (c < 0)
    B = 0.5 * (R + jnp.eye(3, dtype=R.dtype))
    i = jnp.argmax(jnp.diagonal(B))
    axis = B[:, i] / jnp.sqrt(jnp.maximum(B[i, i], 1e-300))
    axis = axis * jnp.where(axis @ v < 0, -1.0, 1.0)  # the skew part's sign, where it has one
    return jnp.where(near_pi, theta * axis / jnp.maximum(jnp.linalg.norm(axis), 1e-300), factor * v)


def angular_jacobian(robot: Robot, q) -> Array:
    """The angular velocity Jacobian (3, n) of ``robot.rotation`` in the world frame:
    column i is ``vee(dR/dq_i R^T)`` (autodiff), as the rows 3-5 of a geometric Jacobian."""
    R = robot.rotation(q)
    dR = jax.jacfwd(robot.rotation)(q)  # (3, 3, n)
    return jax.vmap(lambda D: _vee(D @ R.T), in_axes=2, out_axes=1)(dR)


def pose_ik(robot: Robot, p, rotation=None, q_init=None, *, max_iter: int = 300, tol: float = 1e-10,
            rot_tol: float = 1e-10, damping: float = 0.05, null_gain: float = 0.5, max_step: float = 0.2,
            max_rot_step: float = 0.5, max_dq: float = 0.3) -> PoseIKResult:
    """Joint configuration q with ``robot.forward_kinematics(q) = p`` and, with a
    ``rotation``, ``robot.rotation(q) = rotation`` (see the module docstring).

    Args:
        robot: a robot with a 3-D task point; with ``rotation``, one with a
            ``rotation(q)`` method (:class:`~jtraj.robots.spatial.SpatialSerial`,
            :class:`~jtraj.robots.gough_stewart.GoughStewart`).
        p: (3,) target position [m]; rotation: (3, 3) target rotation or None.
        q_init: (n,) start; default :func:`jtraj.robots.ik.default_q_init`.
        max_iter: iteration bound (static); tol, rot_tol: residuals to reach [m], [rad].
        damping: the damped least squares' lambda at a correction of ``max_step`` (it
            fades with the error); null_gain: the null-space term's gain
            (redundant arms; 0 switches it off); max_step, max_rot_step: the largest
            task correction per iteration [m], [rad]; max_dq: the largest joint change
            per iteration (infinity norm).
    """
    check_settings(robot, max_iter, null_gain, tol=tol, rot_tol=rot_tol, damping=damping, max_step=max_step,
                   max_rot_step=max_rot_step, max_dq=max_dq)
    n = robot.n
    q0 = default_q_init(robot) if q_init is None else check_array(q_init, "q_init", (n,))
    d = jax.eval_shape(robot.forward_kinematics, jax.ShapeDtypeStruct((n,), q0.dtype)).shape[0]
    if d != 3:
        raise ValueError(f"pose_ik needs a robot with a 3-D task point; robot {robot.name!r} has d = {d} "
                         f"(use jtraj.robots.ik.ik)")
    p = check_array(p, "p", (3,))
    if rotation is not None:
        if not callable(getattr(robot, "rotation", None)):
            raise ValueError(f"rotation needs a robot with an orientation (a rotation(q) method); "
                             f"robot {robot.name!r} has none")
        rotation = check_array(rotation, "rotation", (3, 3))
        if is_concrete(rotation):
            Rn = np.asarray(rotation)
            if not (np.allclose(Rn.T @ Rn, np.eye(3), atol=1e-9) and np.linalg.det(Rn) > 0):
                raise ValueError(f"rotation must be a rotation matrix (R^T R = I, det R = +1), got {Rn.tolist()}")
    hyper = [jnp.asarray(x, dtype=q0.dtype) for x in (tol, rot_tol, damping, null_gain, max_step, max_rot_step, max_dq)]
    return _pose_ik(robot, p, rotation, q0, int(max_iter), *hyper)


@eqx.filter_jit
def _pose_ik(robot, p, R_t, q0, max_iter, tol, rot_tol, damping, null_gain, max_step, max_rot_step, max_dq):
    lim = robot.limits
    n = robot.n
    pose = R_t is not None
    dim = 6 if pose else 3
    redundant = n > dim
    has_box = lim.q_min is not None and lim.q_max is not None
    if has_box:
        mid, w = box_centring(lim)

    def errors(q):
        e_p = p - robot.forward_kinematics(q)
        if not pose:
            return e_p, jnp.zeros(3, q.dtype)
        return e_p, rotation_log(R_t @ robot.rotation(q).T)

    def jac(q):
        Jp = robot.jacobian(q)
        return jnp.concatenate([Jp, angular_jacobian(robot, q)]) if pose else Jp

    def clip(x, bound):
        return x * jnp.minimum(1.0, bound / jnp.maximum(jnp.linalg.norm(x), 1e-300))

    def step(q):
        e_p, e_o = errors(q)
        e = jnp.concatenate([clip(e_p, max_step), clip(e_o, max_rot_step)]) if pose else clip(e_p, max_step)
        J = jac(q)
        # the damping fades with the error (full at a correction of max_step), so that the
        # last iterations are Gauss-Newton steps (quadratic convergence near a solution)
        lam2 = damping**2 * jnp.minimum(1.0, jnp.sum(e**2) / max_step**2)
        dq = J.T @ jnp.linalg.solve(J @ J.T + lam2 * jnp.eye(dim, dtype=q.dtype), e)
        if redundant and has_box:
            z = -null_gain * w * (q - mid)
            dq = dq + z - jnp.linalg.pinv(J) @ (J @ z)
        scale = jnp.minimum(1.0, max_dq / jnp.maximum(jnp.max(jnp.abs(dq)), 1e-300))
        q_new = q + scale * dq
        return jnp.clip(q_new, lim.q_min, lim.q_max) if has_box else q_new

    def reached(q):
        e_p, e_o = errors(q)
        return (jnp.linalg.norm(e_p) <= tol) & (jnp.linalg.norm(e_o) <= rot_tol)

    def cond(state):
        q, k, bad = state
        return (k < max_iter) & ~reached(q) & ~bad

    def body(state):
        q, k, _ = state
        q_new = step(q)
        bad = ~jnp.all(jnp.isfinite(q_new))
        return jnp.where(bad, q, q_new), k + 1, bad  # keep the last finite q

    init = (q0, jnp.zeros((), jnp.int32), ~jnp.all(jnp.isfinite(q0)))
    q, k, bad = jax.lax.while_loop(cond, body, init)
    e_p, e_o = errors(q)
    err, rerr = jnp.linalg.norm(e_p), jnp.linalg.norm(e_o)
    ok = (err <= tol) & (rerr <= rot_tol)
    status = jnp.where(bad | ~jnp.isfinite(err) | ~jnp.isfinite(rerr), NONFINITE,
                       jnp.where(ok, SUCCESS, NOT_CONVERGED))
    return PoseIKResult(q=q, status=status.astype(jnp.int32), error=err, rot_error=rerr, iterations=k)


def solve_pose(robot: Robot, p, rotation=None, q_init=None, *, starts: int = 8, seed: int = 0,
               **kwargs) -> PoseIKResult:
    """:func:`pose_ik` from ``q_init`` (or the middle of the box) and from ``starts - 1``
    seeded uniform starts in the joint box (finite bounds; +-pi on continuous joints),
    all at once (vmapped); the result of the first start that succeeds, else the one
    with the smallest residual. For start and goal configurations of a problem
    (:meth:`jtraj.Problem.from_task`), where one start can stall in a local minimum."""
    if not isinstance(starts, (int, np.integer)) or isinstance(starts, bool) or starts < 1:
        raise ValueError(f"starts must be a positive integer, got {starts!r}")
    n = robot.n
    first = default_q_init(robot) if q_init is None else check_array(q_init, "q_init", (n,))
    lim = robot.limits
    lo = np.full(n, -np.pi) if lim.q_min is None else np.where(np.isfinite(lim.q_min), lim.q_min, -np.pi)
    hi = np.full(n, np.pi) if lim.q_max is None else np.where(np.isfinite(lim.q_max), lim.q_max, np.pi)
    rng = np.random.default_rng(seed)
    Q = jnp.concatenate([first[None], jnp.asarray(rng.uniform(lo, hi, (starts - 1, n)), first.dtype)])
    res = jax.vmap(lambda q: pose_ik(robot, p, rotation, q, **kwargs))(Q)
    status = np.asarray(res.status)
    resid = np.asarray(res.error) + np.asarray(res.rot_error)
    ok = np.flatnonzero(status == SUCCESS)
    i = int(ok[0]) if ok.size else int(np.nanargmin(np.where(np.isfinite(resid), resid, np.inf)))
    return jax.tree.map(lambda x: x[i], res)


__all__ = ["PoseIKResult", "STATUS", "angular_jacobian", "pose_ik", "rotation_log", "solve_pose"]
