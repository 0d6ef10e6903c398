"""Independent verifier for parallel3 trajectories: NumPy float64 + Pinocchio RNEA.

Shares no code with :mod:`jtraj`: the robot's data are restated here, each leg's
kinematics is that of a planar 2R arm from its base point ``B_i`` to the common point
C = q, solved in closed form by the law of cosines, and each leg's joint torques come
from ``pin.rnea`` on a planar 2R Pinocchio model (revolute-Z joints, the second placed
along x by the link length; ``pin.Inertia(m, [c, 0, 0], I_com)`` with the inertia about
the centre of mass; zero gravity). The legs' joint torques are mapped to the
generalised force of q by virtual work, and the three actuator torques are the
minimum-norm ones that produce it. States are re-simulated from ``(v, h)`` at rest by
:func:`.verify.simulate`.

**Leg kinematics.** Leg i has the joint angles ``theta_i`` (absolute angle of its first
link, the actuated joint) and ``psi_i`` (relative angle of its second link, so that the
second link's absolute angle is ``phi_i = theta_i + psi_i``); with ``d_i = C - B_i``,
``rho_i = |d_i|``::

    cos psi_i = (rho_i^2 - 2 L^2) / (2 L^2),   psi_i <= 0 (each elbow counter-clockwise
                                                 of the line from B_i to C)
    theta_i   = atan2(d_i) - atan2(sin psi_i, 1 + cos psi_i)

and the leg's 2x2 Jacobian ``J_i = dC / d(theta_i, psi_i)`` gives the joint rates
``J_i^-1 qd`` and accelerations ``J_i^-1 (qdd - Jd_i (theta_d_i, psi_d_i))`` (``Jd_i`` its
time derivative, in closed form).

**Dynamics.** With ``r_i`` the leg's RNEA torques at those joint states, the generalised
force is ``Q = sum_i (J_i^-1)^T r_i`` (the passive elbows' and the common joint's torques
vanish in the closed chain; no mass at C), and the actuator torques are
``tau = J_a (J_a^T J_a)^-1 Q`` with the rows of ``J_a`` (3, 2) the ``d theta_i / dq`` (the
first rows of the ``J_i^-1``).

``verify(q_start, q_goal, v, h, ...)`` -> dict(ok, goal_error, max_rel_violation
{tau, v, qd, q, legs, h}, cost, T, q, qd, tau).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pinocchio as pin

from .verify import _box, simulate

# parallel3, restated here on purpose (a test checks it agrees with jtraj's robot)
LINK_LENGTH = 0.6  # L, both links of every leg
LINK_MASS = 10.0
LINK_COM = 0.3  # centre of mass from the link's proximal joint
LINK_INERTIA = 0.1  # about the centre of mass
BASE_RADIUS = 0.5
BASE_ANGLES = (0.0, 120.0, 240.0)  # degrees
BASE = BASE_RADIUS * np.stack([np.cos(np.deg2rad(BASE_ANGLES)), np.sin(np.deg2rad(BASE_ANGLES))], axis=-1)
TAU_MAX = (25.0, 25.0, 25.0)
QD_MAX = 1.0
QDD_MAX = 10.0
Q_MIN, Q_MAX = (-0.5, -0.5), (0.5, 0.5)
H_MIN, H_MAX = 0.005, 0.1
RHO_MIN, RHO_MAX = 0.05, 0.98  # bounds on rho_i / (2 L)
WEIGHTS = (1.0, 0.1, 0.0)  # (w_time, w_energy, w_kin)


@lru_cache(maxsize=1)
def _model() -> tuple[pin.Model, pin.Data]:
    model = pin.Model()
    parent, offset = 0, 0.0
    for i in range(2):
        placement = pin.SE3(np.eye(3), np.array([offset, 0.0, 0.0]))
        jid = model.addJoint(parent, pin.JointModelRZ(), placement, f"joint{i + 1}")
        # inertia about the centre of mass; only the z entry matters for planar motion
        model.appendBodyToJoint(jid, pin.Inertia(LINK_MASS, np.array([LINK_COM, 0.0, 0.0]),
                                                 np.diag([LINK_INERTIA] * 3)), pin.SE3.Identity())
        parent, offset = jid, LINK_LENGTH
    model.gravity = pin.Motion.Zero()
    return model, model.createData()


def leg_model() -> pin.Model:
    """The Pinocchio model of one leg: a planar 2R arm (horizontal plane, no gravity).
    Its base sits at the origin; without gravity a translation of the base to ``B_i``
    changes none of its joint torques."""
    return _model()[0]


def leg_ratios(q) -> np.ndarray:
    """``rho_i / (2 L)`` (3,): 0 folded (C on B_i), 1 stretched."""
    return np.linalg.norm(np.asarray(q, float)[None, :] - BASE, axis=-1) / (2 * LINK_LENGTH)


def leg_joints(q) -> np.ndarray:
    """Joint angles (3, 2): ``(theta_i, psi_i)`` of each leg reaching C = q (NaN where a
    leg cannot reach it)."""
    d = np.asarray(q, float)[None, :] - BASE
    L = LINK_LENGTH
    with np.errstate(invalid="ignore"):
        psi = -np.arccos((np.sum(d**2, axis=-1) - 2 * L**2) / (2 * L**2))
    theta = np.arctan2(d[:, 1], d[:, 0]) - np.arctan2(np.sin(psi), 1.0 + np.cos(psi))
    return np.stack([theta, psi], axis=-1)


def leg_jacobians(joints) -> np.ndarray:
    """``J_i = dC / d(theta_i, psi_i)`` (3, 2, 2) at the joint angles (3, 2)."""
    theta, phi = joints[:, 0], joints[:, 0] + joints[:, 1]
    L = LINK_LENGTH
    s1, c1, s12, c12 = np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi)
    return L * np.stack([np.stack([-s1 - s12, -s12], axis=-1), np.stack([c1 + c12, c12], axis=-1)], axis=-2)


def _leg_jacobian_rates(joints, rates) -> np.ndarray:
    """``d J_i / dt`` (3, 2, 2) at the joint angles and rates (3, 2)."""
    theta, phi = joints[:, 0], joints[:, 0] + joints[:, 1]
    w1, w12 = rates[:, 0], rates[:, 0] + rates[:, 1]
    L = LINK_LENGTH
    s1, c1, s12, c12 = np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi)
    return L * np.stack([np.stack([-c1 * w1 - c12 * w12, -c12 * w12], axis=-1),
                         np.stack([-s1 * w1 - s12 * w12, -s12 * w12], axis=-1)], axis=-2)


def _inv2(A) -> np.ndarray:
    """Inverses of a stack of 2x2 matrices (..., 2, 2) in closed form (inf or NaN where singular)."""
    det = A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
    adj = np.stack([np.stack([A[..., 1, 1], -A[..., 0, 1]], axis=-1),
                    np.stack([-A[..., 1, 0], A[..., 0, 0]], axis=-1)], axis=-2)
    with np.errstate(divide="ignore", invalid="ignore"):
        return adj / det[..., None, None]


def leg_states(q, qd, qdd) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(joints, rates, accelerations, J_inv)``: each leg's joint angles, rates and
    accelerations (3, 2) at the state ``(q, qd, qdd)`` of C, and ``J_i^-1 = d joints_i / dq``
    (3, 2, 2)."""
    qd, qdd = np.asarray(qd, float), np.asarray(qdd, float)
    joints = leg_joints(q)
    J_inv = _inv2(leg_jacobians(joints))
    with np.errstate(invalid="ignore", over="ignore"):
        rates = J_inv @ qd  # (3, 2)
        acc = np.einsum("lij,lj->li", J_inv,
                        qdd[None, :] - np.einsum("lij,lj->li", _leg_jacobian_rates(joints, rates), rates))
    return joints, rates, acc, J_inv


def actuator_jacobian(q) -> np.ndarray:
    """``J_a = d theta / dq`` (3, 2): the first rows of the legs' ``J_i^-1``."""
    return _inv2(leg_jacobians(leg_joints(q)))[:, 0, :]


def _rnea(joints, rates, acc) -> np.ndarray:
    model, data = _model()
    return np.stack([np.array(pin.rnea(model, data, joints[i], rates[i], acc[i])) for i in range(3)])


def leg_torques(q, qd, qdd) -> np.ndarray:
    """Each leg's joint torques (3, 2) by Pinocchio's RNEA at its joint states."""
    return _rnea(*leg_states(q, qd, qdd)[:3])


def generalized_force(q, qd, qdd) -> np.ndarray:
    """``Q = sum_i (d joints_i / dq)^T r_i`` (2,) with ``r_i`` the legs' RNEA torques."""
    joints, rates, acc, J_inv = leg_states(q, qd, qdd)
    return np.einsum("lij,li->j", J_inv, _rnea(joints, rates, acc))


def inverse_dynamics(q, qd, qdd) -> np.ndarray:
    """Minimum-norm actuator torques ``tau = J_a (J_a^T J_a)^-1 Q`` (3,) for the motion
    ``(q, qd, qdd)`` of C."""
    Ja = actuator_jacobian(q)
    with np.errstate(invalid="ignore", over="ignore"):
        return Ja @ (_inv2(Ja.T @ Ja) @ generalized_force(q, qd, qdd))


def _reaches(q) -> bool:
    """Whether every leg reaches C = q away from its singularities (0 < rho_i < 2 L with a
    regular Jacobian)."""
    if not np.all(np.isfinite(q)):
        return False
    s = leg_ratios(q)
    if not np.all((s > 0) & (s < 1)):
        return False
    J = leg_jacobians(leg_joints(q))
    return bool(np.all(np.abs(J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]) > 0))


def verify(q_start, q_goal, v, h, *, tau_max=TAU_MAX, qd_max=QD_MAX, qdd_max=QDD_MAX, q_min=Q_MIN,
           q_max=Q_MAX, rho_min=RHO_MIN, rho_max=RHO_MAX, h_min=H_MIN, h_max=H_MAX, weights=WEIGHTS,
           tol=1e-6) -> dict:
    """Re-simulate ``(v (N, 2), h (N,))`` from ``q_start`` at rest and check it.

    Checks (``ok`` when all hold): actuator torques ``|tau_k| <= tau_max`` (k = 0..N-1),
    ``|v_k| <= qdd_max``, ``|qd_k| <= qd_max`` and ``q_min <= q_k <= q_max`` (k = 1..N),
    each relative to its bound (the position box relative to its half-width), the legs'
    margins ``rho_min <= rho_ki / (2 L) <= rho_max`` (k = 0..N) as the rows
    ``1 - s / rho_min`` and ``s / rho_max - 1`` (``s = rho / (2 L)``),
    ``h_min <= h_k <= h_max`` relative to h_max, each within ``tol``; every leg reaches
    every sample; the goal ``|q_N - q_goal|`` and ``|qd_N|`` within ``tol`` absolute.
    Non-finite input or a leg that cannot reach C fails the check.

    Returns dict(ok, goal_error (max abs of q_N - q_goal and qd_N), max_rel_violation
    (dict tau, v, qd, q, legs, h), cost (sum h_k [w_time + w_energy sum (tau_k/tau_max)^2 +
    w_kin |qd_k|^2] with ``weights``, k < N), T (sum h), q (N+1, 2), qd (N+1, 2),
    tau (N, 3); NaN rows of tau where a leg cannot reach C).
    """
    v = np.asarray(v, np.float64)
    h = np.asarray(h, np.float64).reshape(-1)
    if v.ndim != 2 or v.shape != (h.shape[0], 2):
        raise ValueError(f"v must be (N, 2) and h (N,), got {v.shape} and {h.shape}")
    q_start, q_goal = (np.broadcast_to(np.asarray(x, np.float64), (2,)) for x in (q_start, q_goal))
    with np.errstate(invalid="ignore", over="ignore"):
        q, qd = simulate(q_start, v, h)
    reach = [_reaches(x) for x in q]
    tau = np.full((len(h), 3), np.nan)
    for k in range(len(h)):
        if reach[k] and np.all(np.isfinite(qd[k])) and np.all(np.isfinite(v[k])):
            tau[k] = inverse_dynamics(q[k], qd[k], v[k])
    tau_max = np.broadcast_to(np.asarray(tau_max, float), (3,))
    lo, hi = (np.broadcast_to(np.asarray(b, float), (2,)) for b in (q_min, q_max))
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        goal_error = float(max(np.max(np.abs(q[-1] - q_goal)), np.max(np.abs(qd[-1]))))
        s = np.stack([leg_ratios(x) for x in q])  # (N+1, 3)
        legs = np.concatenate([1.0 - s / rho_min, s / rho_max - 1.0], axis=1)
        rel = dict(
            tau=_box(tau, tau_max),
            v=_box(v, qdd_max),
            qd=_box(qd[1:], qd_max),
            q=_box(q[1:] - mid, half),
            legs=float(np.max(np.maximum(legs, 0.0))),
            # relative to h_max on both sides, as jtraj reports it (h_min may be 0)
            h=float(np.max(np.maximum(np.maximum(h_min - h, h - h_max), 0.0)) / h_max) if len(h) else 0.0,
        )
        w_time, w_energy, w_kin = weights
        stage = w_time + w_energy * np.sum((tau / tau_max) ** 2, axis=1) + w_kin * np.sum(qd[:-1] ** 2, axis=1)
        cost = float(np.sum(h * stage))
    finite = all(np.all(np.isfinite(x)) for x in (q_start, q_goal, v, h, tau))
    ok = bool(finite and all(reach) and goal_error <= tol and all(r <= tol for r in rel.values()))
    return dict(ok=ok, goal_error=goal_error, max_rel_violation=rel, cost=cost, T=float(np.sum(h)),
                q=q, qd=qd, tau=tau)
