"""A CasADi recursive Newton-Euler algorithm for kinematic trees of one-DOF joints,
with its numbers read from a Pinocchio model (the installed ``pin`` wheels have no
``pinocchio.casadi``).

Independent of :mod:`jtraj`. Pinocchio is used at build time only, to parse a URDF and
to read each joint's placement in its parent, its axis and its body's spatial inertia;
the algorithm below is written out in CasADi (SX by default) from those numbers, so
the resulting :class:`casadi.Function` can sit inside an IPOPT NLP.

Conventions (Featherstone's RNEA, each joint's quantities in its own frame, spatial
vectors ordered (linear, angular) at the frame's origin):

* joint i's frame in its parent's: ``(R_i, p_i) = placement_i * J_i(q_i)``, with
  ``J_i`` a rotation by ``q_i`` about the joint's unit axis ``u_i`` (revolute,
  continuous) or a translation ``q_i u_i`` (prismatic);
* motion subspace ``S_i = (0, u_i)`` (revolute) or ``(u_i, 0)`` (prismatic);
* forward pass: ``v_i = X_i v_parent + S_i qd_i``,
  ``a_i = X_i a_parent + S_i qdd_i + v_i x S_i qd_i``, with the base's acceleration
  ``a_0 = (-g, 0)`` (gravity enters as an upward acceleration of the base);
* body force ``f_i = I_i a_i + v_i x* I_i v_i``; backward pass ``tau_i = S_i . f_i``,
  ``f_parent += X_i^* f_i``.

Continuous joints take their angle as the coordinate (Pinocchio stores
``(cos q, sin q)``; :func:`pinocchio_configuration` converts).

API: :func:`rnea_function`, :func:`panda_model`, :func:`example_robot_urdf`,
:func:`pinocchio_configuration`, :func:`model_limits`.
"""

from __future__ import annotations

import glob
import os
import sys
from dataclasses import dataclass

import casadi as ca
import numpy as np

_AXES = {"X": (1.0, 0.0, 0.0), "Y": (0.0, 1.0, 0.0), "Z": (0.0, 0.0, 1.0)}


@dataclass(frozen=True)
class _Joint:
    name: str
    parent: int  # index into the joint list, -1 for the base
    revolute: bool
    continuous: bool
    axis: np.ndarray  # (3,) unit, in the joint frame
    R: np.ndarray  # (3, 3) placement rotation in the parent's frame
    p: np.ndarray  # (3,) placement translation
    mass: float
    com: np.ndarray  # (3,) centre of mass in the joint frame
    inertia: np.ndarray  # (3, 3) about the centre of mass
    iv: int  # index of its coordinate


def _joint_kind(jm) -> tuple[bool, bool, np.ndarray]:
    """(revolute, continuous, axis) of a one-DOF Pinocchio joint model."""
    short = jm.shortname()
    kinds = {"JointModelR": (True, False), "JointModelRUB": (True, True), "JointModelP": (False, False)}
    for prefix in ("JointModelRUB", "JointModelR", "JointModelP"):
        tail = short[len(prefix):]
        if short.startswith(prefix) and tail in _AXES:
            return (*kinds[prefix], np.array(_AXES[tail]))
    if short in ("JointModelRevoluteUnaligned", "JointModelRevoluteUnboundedUnaligned", "JointModelPrismaticUnaligned"):
        axis = np.asarray(jm.extract().axis, float)
        return short.startswith("JointModelRevolute"), "Unbounded" in short, axis / np.linalg.norm(axis)
    raise ValueError(f"joint type {short} is not supported (revolute, continuous or prismatic joints only)")


def _joints(model) -> list[_Joint]:
    out = []
    for i in range(1, model.njoints):
        jm = model.joints[i]
        if jm.nv != 1:
            raise ValueError(f"joint {model.names[i]!r} has {jm.nv} degrees of freedom; one-DOF joints only")
        revolute, continuous, axis = _joint_kind(jm)
        M, Y = model.jointPlacements[i], model.inertias[i]
        out.append(_Joint(name=model.names[i], parent=int(model.parents[i]) - 1, revolute=revolute,
                          continuous=continuous, axis=axis, R=np.array(M.rotation), p=np.array(M.translation),
                          mass=float(Y.mass), com=np.array(Y.lever), inertia=np.array(Y.inertia), iv=int(jm.idx_v)))
    return out


def _rotation(axis: np.ndarray, angle):
    """Rodrigues: rotation by ``angle`` (symbolic) about the unit ``axis`` (numbers)."""
    K = ca.DM(np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]]))
    return ca.DM.eye(3) + ca.sin(angle) * K + (1 - ca.cos(angle)) * (K @ K)


def rnea_function(model, *, sym=ca.SX, name: str = "rnea") -> ca.Function:
    """``Function(name, [q, qd, qdd], [tau])`` (each (nv,)) of the Pinocchio ``model``:
    joint efforts for the motion, gravity ``model.gravity`` included, by the recursive
    Newton-Euler algorithm written here in CasADi (see the module docstring)."""
    joints = _joints(model)
    nv = model.nv
    q, qd, qdd = sym.sym("q", nv), sym.sym("qd", nv), sym.sym("qdd", nv)
    g = np.asarray(model.gravity.linear, float)
    v, a, f = [], [], []
    for j in joints:
        u = ca.DM(j.axis)
        x, xd, xdd = q[j.iv], qd[j.iv], qdd[j.iv]
        if j.revolute:
            R = ca.DM(j.R) @ _rotation(j.axis, x)
            p = ca.DM(j.p)
            S_lin, S_ang = ca.DM.zeros(3), u
        else:
            R = ca.DM(j.R)
            p = ca.DM(j.p) + ca.DM(j.R) @ u * x
            S_lin, S_ang = u, ca.DM.zeros(3)
        if j.parent < 0:
            v_lin_p, w_p, a_lin_p, dw_p = ca.DM.zeros(3), ca.DM.zeros(3), ca.DM(-g), ca.DM.zeros(3)
        else:
            (v_lin_p, w_p), (a_lin_p, dw_p) = v[j.parent], a[j.parent]
        # parent -> joint frame: w' = R^T w, v' = R^T (v + w x p)
        w = R.T @ w_p + S_ang * xd
        v_lin = R.T @ (v_lin_p + ca.cross(w_p, p)) + S_lin * xd
        vJ_lin, vJ_ang = S_lin * xd, S_ang * xd
        # v x vJ (motion cross product): (w x vJ_lin + v_lin x vJ_ang, w x vJ_ang)
        dw = R.T @ dw_p + S_ang * xdd + ca.cross(w, vJ_ang)
        a_lin = (R.T @ (a_lin_p + ca.cross(dw_p, p)) + S_lin * xdd
                 + ca.cross(w, vJ_lin) + ca.cross(v_lin, vJ_ang))
        v.append((v_lin, w))
        a.append((a_lin, dw))
        c, m, Ic = ca.DM(j.com), j.mass, ca.DM(j.inertia)
        # momentum h = I v and force I a + v x* h about the frame's origin
        l = m * (v_lin + ca.cross(w, c))
        k = Ic @ w + ca.cross(c, l)
        n = m * (a_lin + ca.cross(dw, c))
        mom = Ic @ dw + ca.cross(c, n)
        f.append([n + ca.cross(w, l), mom + ca.cross(w, k) + ca.cross(v_lin, l), R, p])
    tau = [None] * nv
    for idx in range(len(joints) - 1, -1, -1):
        j = joints[idx]
        n, mom, R, p = f[idx]
        u = ca.DM(j.axis)
        tau[j.iv] = ca.dot(u, mom) if j.revolute else ca.dot(u, n)
        if j.parent >= 0:  # joint -> parent frame: n' = R n, m' = R m + p x R n
            Rn = R @ n
            f[j.parent][0] = f[j.parent][0] + Rn
            f[j.parent][1] = f[j.parent][1] + R @ mom + ca.cross(p, Rn)
    return ca.Function(name, [q, qd, qdd], [ca.vertcat(*tau)], ["q", "qd", "qdd"], ["tau"])


def pinocchio_configuration(model, q) -> np.ndarray:
    """Pinocchio's configuration vector (nq,) of coordinates ``q`` (nv,): continuous
    joints' angles become ``(cos, sin)``."""
    q = np.asarray(q, float).reshape(model.nv)
    out = np.zeros(model.nq)
    for i in range(1, model.njoints):
        jm = model.joints[i]
        x = q[jm.idx_v]
        if jm.nq == 2:
            out[jm.idx_q:jm.idx_q + 2] = np.cos(x), np.sin(x)
        else:
            out[jm.idx_q] = x
    return out


def model_limits(model) -> dict:
    """Position, velocity and effort limits of the model's coordinates (nv,) each:
    ``q_min``, ``q_max`` (infinite for continuous joints), ``qd_max``, ``tau_max``."""
    lo, hi = np.full(model.nv, -np.inf), np.full(model.nv, np.inf)
    for i in range(1, model.njoints):
        jm = model.joints[i]
        if jm.nq == 1:
            lo[jm.idx_v] = model.lowerPositionLimit[jm.idx_q]
            hi[jm.idx_v] = model.upperPositionLimit[jm.idx_q]
    return dict(q_min=lo, q_max=hi, qd_max=np.array(model.velocityLimit, float),
                tau_max=np.array(model.effortLimit, float))


def example_robot_urdf(relpath: str) -> str:
    """Path of a URDF shipped by the ``example-robot-data`` package, e.g.
    ``"panda_description/urdf/panda.urdf"``."""
    roots = [os.path.join(p, "cmeel.prefix", "share", "example-robot-data", "robots") for p in sys.path if p]
    roots += glob.glob(os.path.join(sys.prefix, "lib", "python3*", "site-packages", "cmeel.prefix", "share",
                                    "example-robot-data", "robots"))
    for root in roots:
        path = os.path.join(root, relpath)
        if os.path.isfile(path):
            return path
    raise FileNotFoundError(f"{relpath} not found: install example-robot-data (pip install example-robot-data)")


def panda_model():
    """The Franka Panda of example-robot-data as a 7-DOF Pinocchio model: the URDF's two
    finger joints locked at their neutral position (``buildReducedModel``)."""
    import pinocchio as pin

    full = pin.buildModelFromUrdf(example_robot_urdf("panda_description/urdf/panda.urdf"))
    locked = [full.getJointId(n) for n in full.names if "finger" in n]
    return pin.buildReducedModel(full, locked, pin.neutral(full))
