"""Independent reference models, state samplers and the small solver problems for the tests.

The references call nothing of jtraj's dynamics: the Pinocchio models are built from the
link data alone, and the closed forms are written out by hand.
"""

from __future__ import annotations

import numpy as np

import jtraj
import jtraj.robots as robots


# ----- Pinocchio planar chains --------------------------------------------------------
def pinocchio_planar(lengths, masses, inertias, com=None, gravity=0.0):
    """A Pinocchio model of a planar serial arm: revolute-z joints, joint i+1 at
    (l_i, 0, 0) in link i's frame, link i's centre of mass at (d_i, 0, 0) with inertia
    I_i about z. Gravity ``gravity`` along -y. Returns (model, data, tip_frame_id)."""
    import pinocchio as pin

    lengths = np.asarray(lengths, float)
    com = lengths / 2 if com is None else np.asarray(com, float)
    model = pin.Model()
    parent = 0
    for i, (l_prev, m, d, I) in enumerate(zip(np.r_[0.0, lengths[:-1]], masses, com, inertias)):
        placement = pin.SE3(np.eye(3), np.array([l_prev, 0.0, 0.0]))
        parent = model.addJoint(parent, pin.JointModelRZ(), placement, f"j{i}")
        model.appendBodyToJoint(parent, pin.Inertia(float(m), np.array([d, 0.0, 0.0]),
                                                    np.diag([1e-3, 1e-3, float(I)])), pin.SE3.Identity())
    tip = model.addFrame(pin.Frame("tip", parent, 0, pin.SE3(np.eye(3), np.array([lengths[-1], 0.0, 0.0])),
                                   pin.FrameType.OP_FRAME))
    model.gravity = pin.Motion(np.array([0.0, -gravity, 0.0]), np.zeros(3))
    return model, model.createData(), tip


def pin_mass(model, data, q):
    import pinocchio as pin

    M = pin.crba(model, data, np.asarray(q, float))
    return np.triu(M) + np.triu(M, 1).T


def pin_rnea(model, data, q, qd, qdd):
    import pinocchio as pin

    return np.array(pin.rnea(model, data, *(np.asarray(x, float) for x in (q, qd, qdd))))


def pin_tip(model, data, frame, q):
    import pinocchio as pin

    pin.framesForwardKinematics(model, data, np.asarray(q, float))
    return np.array(data.oMf[frame].translation[:2])


# ----- textbook 2-link arm ------------------------------------------------------------
def two_link_closed_form(q, qd, l1, m1, m2, d1, d2, I1, I2, g):
    """M, c (= C qd) and G of a planar 2R arm (Spong, Hutchinson & Vidyasagar)."""
    c2, s2 = np.cos(q[1]), np.sin(q[1])
    M11 = m1 * d1**2 + m2 * (l1**2 + d2**2 + 2 * l1 * d2 * c2) + I1 + I2
    M12 = m2 * (d2**2 + l1 * d2 * c2) + I2
    M22 = m2 * d2**2 + I2
    M = np.array([[M11, M12], [M12, M22]])
    h = -m2 * l1 * d2 * s2
    C = np.array([[h * qd[1], h * (qd[0] + qd[1])], [-h * qd[0], 0.0]])
    G = np.array([(m1 * d1 + m2 * l1) * g * np.cos(q[0]) + m2 * d2 * g * np.cos(q[0] + q[1]),
                  m2 * d2 * g * np.cos(q[0] + q[1])])
    return M, C @ qd, G


# ----- catalogue and admissible states ------------------------------------------------
def catalogue(slow=()):
    """The built-in robots' names as pytest parameters, those in ``slow`` marked slow."""
    import pytest

    return [pytest.param(n, marks=pytest.mark.slow) if n in slow else n for n in robots.names()]


def arm_urdf(name="arm3"):
    """A small URDF arm: a shoulder (about z) and an elbow (about y) carrying a tool
    0.25 m out (a fixed joint), and a revolute 'gripper' joint beside it at the end of
    the only branch of movable joints (the default tip: three joints; ``tip_link="tool"``:
    two)."""
    def link(n):
        return (f'<link name="{n}"><inertial><origin xyz="0.1 0 0.1"/><mass value="1"/><inertia ixx="0.01" '
                f'ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>')

    def joint(j, parent, child, axis, xyz, kind="revolute"):
        limit = '<limit lower="-1.5" upper="1.5" effort="40" velocity="2"/>' if kind == "revolute" else ""
        return (f'<joint name="{j}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
                f'<origin xyz="{xyz}"/><axis xyz="{axis}"/>{limit}</joint>')

    return (f'<robot name="{name}"><link name="base"/>{link("l1")}{link("l2")}{link("finger")}<link name="tool"/>'
            f'{joint("shoulder", "base", "l1", "0 0 1", "0 0 0.1")}{joint("elbow", "l1", "l2", "0 1 0", "0 0 0.3")}'
            f'{joint("mount", "l2", "tool", "0 0 1", "0.25 0 0", "fixed")}'
            f'{joint("gripper", "l2", "finger", "0 1 0", "0.2 0 0")}</robot>')


def sample_state(robot, rng, speed=0.5):
    """(q, qd, qdd) at a random admissible state of ``robot`` (NumPy arrays)."""
    n = robot.n
    lim = robot.limits
    while True:
        if lim.q_min is not None:
            lo, hi = np.asarray(lim.q_min), np.asarray(lim.q_max)
            lo, hi = np.where(np.isfinite(lo), lo, -np.pi), np.where(np.isfinite(hi), hi, np.pi)  # continuous joints
            mid, half = (lo + hi) / 2, (hi - lo) / 2
            q = mid + 0.8 * half * rng.uniform(-1, 1, n)
        elif robot.name == "wmr":
            q = np.r_[rng.uniform(2, 22, 2), rng.uniform(-np.pi, np.pi)]
        else:
            q = rng.uniform(-np.pi, np.pi, n)
        if robot.name == "parallel3":
            ratio = np.asarray(robot.leg_ratios(q))
            if ratio.min() < 0.15 or ratio.max() > 0.9:
                continue
        break
    scale = speed * (np.ones(n) if lim.qd_max is None else np.minimum(np.asarray(lim.qd_max), 1.0))
    qd = scale * rng.uniform(-1, 1, n)
    if robot.name == "wmr":
        qd = np.asarray(robot.admissible_velocity(q, scale[:2] * rng.uniform(-1, 1, 2)))
    qdd = rng.uniform(-1, 1, n)
    return q, qd, qdd


def verified_ipopt_cost(sol, i, q_start, q_goal, N):
    """Lane ``i`` of a batch Solution re-simulated from its own (v, h) by the independent
    NumPy + Pinocchio verifier (bounds and goal within 1e-6, its cost equal to the
    Solution's), and IPOPT's cost on the same problem, which must succeed (skips where
    Pinocchio or CasADi is missing; jtraj_peers must be importable)."""
    import pytest

    V = pytest.importorskip("jtraj_peers.verify")
    P = pytest.importorskip("jtraj_peers.ipopt_peer")
    chk = V.verify(q_start, q_goal, np.asarray(sol.v[i]), np.asarray(sol.h[i]), tol=1e-6)
    assert chk["ok"] and chk["goal_error"] <= 1e-6, (chk["max_rel_violation"], chk["goal_error"])
    assert chk["cost"] == pytest.approx(float(sol.cost[i]), rel=1e-9)
    ref = P.solve_pair(q_start, q_goal, N=N)
    assert ref["success"]
    return ref["cost"]


# ----- the small solver problems shared by test_pbm.py and test_ipm.py ---------------------
N_SMALL = 10
W_SMALL = jtraj.Weights(time=1.0, energy=0.1)
Q0 = np.array([1.077, -0.096, 0.619])
Q1 = np.array([1.2, -0.049, 0.9])  # feasible with N = 10 (T <= 1 s), as in test_solver.py
QI = np.array([0.0, 0.3, -0.3])  # + 0.7 rad per joint: not within N h_max = 1 s under the torque limits


def three_sample_batch(options):
    """(q_start, q_goal, Solution) of one batch on 2 lanes: Q0 -> Q1 (feasible), QI -> QI + 0.7
    (infeasible) and a non-finite goal. 2 lanes throughout: one segment program (the default 8
    would step down to 2: two)."""
    q0 = np.stack([Q0, QI, Q0])
    q1 = np.stack([Q1, QI + 0.7, np.full(3, np.nan)])
    return q0, q1, jtraj.solve_batch(robots.get("serial3"), q0, q1, N=N_SMALL, weights=W_SMALL, options=options,
                                     slots=2)
