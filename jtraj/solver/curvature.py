"""The interior-point method's curvature of the dynamics (``SolverOptions.ip_curvature``).

The Newton model of :mod:`jtraj.solver.ipm` needs, per sample k, the Hessian in w_k of the
Lagrangian's stage term phi(w_k, tau_k), with the efforts tau_k = ID(q_k, qd_k, a_k)
given by the inverse dynamics. By the chain rule (see
:meth:`jtraj.solver.nlp.NLP._stage_derivatives_split`), with lam = d phi / d tau and
J = d tau / dw,

    H = phi_ww + phi_wt J + J^T phi_tw + J^T phi_tt J + sum_i lam_i d2 tau_i / dw2.

``"exact"`` keeps every term: the last one is a forward-over-reverse pass through the
inverse dynamics per sample, the dearest part of an iteration on a spatial arm (a
recursive Newton-Euler pass over a chain of 3-D rotations, differentiated twice inside
the loop). ``"gauss_newton"`` drops that term only: the effort multipliers' second
derivatives of the dynamics. What stays is exact: the curvature of the cost and
boxes in w and tau (the energy's ``J^T phi_tt J`` among it), the barrier's
``J^T (y / s) J`` that the method adds, and every gradient, so the method converges to the
same points (its optimality test reads the exact gradient of the Lagrangian); only the
Newton model is approximate, and the method's shifts and line search treat it as they
treat an indefinite exact model. J comes from one reverse-mode pass through the
dynamics per effort (:func:`effort_jacobian`).

``"auto"`` picks ``"gauss_newton"`` for spatial arms (:class:`jtraj.robots.SpatialSerial`)
and ``"exact"`` elsewhere (the planar robots' dynamics are cheap to differentiate twice
and their iteration counts were tuned on the exact model).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

CURVATURES = ("auto", "exact", "gauss_newton")


def resolve(option: str, robot) -> str:
    """The curvature a solve of ``robot`` uses for ``SolverOptions.ip_curvature`` =
    ``option`` ("exact" or "gauss_newton")."""
    if option not in CURVATURES:
        raise ValueError(f"ip_curvature must be one of {CURVATURES}, got {option!r}")
    if option != "auto":
        return option
    from ..robots.spatial import SpatialSerial

    return "gauss_newton" if isinstance(robot, SpatialSerial) else "exact"


def effort_jacobian(tau_of, x, a):
    """(tau, J): the efforts ``tau_of(x, a)`` (m,) and their Jacobian (m, nx + na) in the
    state x and the acceleration a, by reverse mode: one pass through the dynamics and
    one reverse pass per effort, all rows at once (the Panda's 41 samples: about a
    quarter faster to run and a tenth faster to compile than forward mode's 2n + n
    tangents, ``benchmarks/profile_spatial.py --pieces``)."""
    tau, vjp = jax.vjp(tau_of, x, a)
    Jx, Ja = jax.vmap(vjp)(jnp.eye(tau.shape[0], dtype=tau.dtype))
    return tau, jnp.concatenate([Jx, Ja], axis=1)


def stage_derivatives_gauss_newton(nlp, w, sdk, mk, mu, kink, efforts=False):
    """(value, gradient, Hessian[, tau, J]) of one sample's Lagrangian term in w, the
    Hessian without the multipliers' second derivatives of the dynamics (see the
    module docstring); the signature and results of
    :meth:`jtraj.solver.nlp.NLP._stage_derivatives_split`."""
    problem, tr = nlp.problem, nlp.tr
    n, nw = problem.robot.n, w.shape[0]
    nx, na = 2 * n, nw - 2 * n - 1
    x, a = w[:nx], w[nx:nx + na]

    def tau_of(s, acc):
        return tr.accel_and_tau(problem, s[:n], s[n:], acc)[1]

    tau, Jxa = effort_jacobian(tau_of, x, a)
    J = jnp.concatenate([Jxa, jnp.zeros((tau.shape[0], nw - nx - na), w.dtype)], axis=1)
    Hy, val, gy = nlp.phi_hessian(w, tau, sdk, mk, mu, kink)
    lam = gy[nw:]
    A = Hy[:nw, nw:] @ J
    H = Hy[:nw, :nw] + A + A.T + J.T @ Hy[nw:, nw:] @ J
    if efforts:
        return val, gy[:nw] + J.T @ lam, H, tau, J
    return val, gy[:nw] + J.T @ lam, H
