"""Independent verifier for serial3 trajectories: NumPy float64 + Pinocchio RNEA.

Shares no code with :mod:`jtraj` nor with the CasADi peer (:mod:`.ipopt_peer`): the
robot is rebuilt with Pinocchio's API (revolute-Z joints, each placed along x by the
previous link's length; ``pin.Inertia(m, [d, 0, 0], I_com)`` with the inertia about the
centre of mass; zero gravity), states are re-simulated from ``(v, h)`` with the
transcription's recursion in plain NumPy, torques come from ``pin.rnea``.

``verify(q_start, q_goal, v, h, ...)`` -> dict(ok, goal_error, max_rel_violation
{tau, v, qd, h}, cost, T, q, qd, tau); ``verify_batch`` loops over many.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pinocchio as pin

# serial3, restated here on purpose (a test checks it agrees with the peer's)
LENGTHS = (1.0, 0.8, 0.45)
MASSES = (10.0, 8.0, 4.0)
INERTIAS = (9.23, 7.5, 5.21)  # about the centres of mass
TAU_MAX = (40.0, 25.0, 20.0)
QD_MAX = 2.0
QDD_MAX = 3.0
H_MIN, H_MAX = 0.005, 0.1
WEIGHTS = (1.0, 0.1, 0.0)  # (w_time, w_energy, w_kin)


@lru_cache(maxsize=32)
def _model(masses: tuple[float, ...]) -> tuple[pin.Model, pin.Data]:
    model = pin.Model()
    parent, offset = 0, 0.0
    for i, (l, m, I) in enumerate(zip(LENGTHS, masses, INERTIAS)):
        placement = pin.SE3(np.eye(3), np.array([offset, 0.0, 0.0]))
        jid = model.addJoint(parent, pin.JointModelRZ(), placement, f"joint{i + 1}")
        # inertia about the centre of mass; only the z entry matters for planar motion
        model.appendBodyToJoint(jid, pin.Inertia(m, np.array([l / 2, 0.0, 0.0]), np.diag([I, I, I])),
                                pin.SE3.Identity())
        parent, offset = jid, l
    model.gravity = pin.Motion.Zero()
    return model, model.createData()


def serial3_model(masses=None) -> pin.Model:
    """The Pinocchio model of serial3 (horizontal plane, no gravity)."""
    return _model(_masses(masses))[0]


def _masses(masses) -> tuple[float, ...]:
    return MASSES if masses is None else tuple(float(m) for m in masses)


def rnea(q, qd, qdd, masses=None) -> np.ndarray:
    """Joint torques tau = M(q) qdd + C(q, qd) qd by Pinocchio's RNEA."""
    model, data = _model(_masses(masses))
    return np.array(pin.rnea(model, data, np.asarray(q, float), np.asarray(qd, float),
                             np.asarray(qdd, float)))


def simulate(q_start, v, h, qd_start=0.0) -> tuple[np.ndarray, np.ndarray]:
    """States (q (N+1,n), qd (N+1,n)) from the recursion q' = q + h qd + h^2/2 v, qd' = qd + h v."""
    v = np.asarray(v, np.float64)
    h = np.asarray(h, np.float64).reshape(-1)
    N, n = v.shape
    q = np.empty((N + 1, n))
    qd = np.empty((N + 1, n))
    q[0] = np.asarray(q_start, np.float64)
    qd[0] = np.broadcast_to(np.asarray(qd_start, np.float64), (n,))
    for k in range(N):
        q[k + 1] = q[k] + h[k] * qd[k] + 0.5 * h[k] ** 2 * v[k]
        qd[k + 1] = qd[k] + h[k] * v[k]
    return q, qd


def _box(x, bound) -> float:
    """Largest relative violation of |x| <= bound (0 when satisfied)."""
    bound = np.broadcast_to(np.asarray(bound, float), np.shape(x)[-1:])
    if np.size(x) == 0:
        return 0.0
    return float(np.max(np.maximum(np.abs(x) - bound, 0.0) / bound))


def verify(q_start, q_goal, v, h, *, qd_start=0.0, tau_max=TAU_MAX, qd_max=QD_MAX,
           qdd_max=QDD_MAX, h_min=H_MIN, h_max=H_MAX, masses=None, weights=WEIGHTS,
           tol=1e-6) -> dict:
    """Re-simulate ``(v (N,3), h (N,))`` from ``q_start`` and check it.

    Checks (``ok`` when all hold): |tau_k| <= tau_max (k = 0..N-1, Pinocchio RNEA),
    |v_k| <= qdd_max, |qd_k| <= qd_max (k = 1..N), h_min <= h_k <= h_max, each to a
    *relative* tolerance (violation / bound <= tol), and the goal |q_N - q_goal| and
    |qd_N| to ``tol`` absolute.

    Returns dict(ok, goal_error (max abs of q_N - q_goal and qd_N), max_rel_violation
    (dict tau, v, qd, h), cost (sum h_k [w_time + w_energy sum (tau_k/tau_max)^2 +
    w_kin |qd_k|^2] with ``weights``), T (sum h), q (N+1,3), qd (N+1,3), tau (N,3)).
    """
    v = np.asarray(v, np.float64)
    h = np.asarray(h, np.float64).reshape(-1)
    if v.ndim != 2 or v.shape[0] != h.shape[0]:
        raise ValueError(f"v must be (N, n) and h (N,), got {v.shape} and {h.shape}")
    masses = _masses(masses)
    q, qd = simulate(q_start, v, h, qd_start)
    tau = np.stack([rnea(q[k], qd[k], v[k], masses) for k in range(len(h))]) if len(h) else \
        np.zeros((0, v.shape[1]))
    tau_max = np.broadcast_to(np.asarray(tau_max, float), (v.shape[1],))
    goal_error = float(max(np.max(np.abs(q[-1] - np.asarray(q_goal, float))), np.max(np.abs(qd[-1]))))
    rel = dict(
        tau=_box(tau, tau_max),
        v=_box(v, qdd_max),
        qd=_box(qd[1:], qd_max),
        # relative to h_max on both sides, as jtraj reports it (h_min may be 0)
        h=float(np.max(np.maximum(np.maximum(h_min - h, h - h_max), 0.0)) / h_max) if len(h) else 0.0,
    )
    w_time, w_energy, w_kin = weights
    stage = w_time + w_energy * np.sum((tau / tau_max) ** 2, axis=1) + w_kin * np.sum(qd[:-1] ** 2, axis=1)
    ok = bool(goal_error <= tol and all(r <= tol for r in rel.values())
              and np.all(np.isfinite(v)) and np.all(np.isfinite(h)))
    return dict(ok=ok, goal_error=goal_error, max_rel_violation=rel, cost=float(np.sum(h * stage)),
                T=float(np.sum(h)), q=q, qd=qd, tau=tau)


def verify_batch(q_starts, q_goals, vs, hs, **kw) -> dict:
    """:func:`verify` over many trajectories (a loop). ``vs`` (B,N,3) or a list of (N_i,3),
    ``hs`` (B,N) or a list. Returns dict of arrays: ok (B,), goal_error (B,), cost (B,),
    T (B,), max_rel_violation {tau, v, qd, h: (B,)}, and ``results`` (the per-trajectory dicts).
    """
    if not len(q_starts) == len(q_goals) == len(vs) == len(hs):
        raise ValueError("q_starts, q_goals, vs and hs must have the same length")
    res = [verify(a, b, v, h, **kw) for a, b, v, h in zip(q_starts, q_goals, vs, hs)]
    return dict(
        ok=np.array([r["ok"] for r in res], bool),
        goal_error=np.array([r["goal_error"] for r in res]),
        cost=np.array([r["cost"] for r in res]),
        T=np.array([r["T"] for r in res]),
        max_rel_violation={k: np.array([r["max_rel_violation"][k] for r in res])
                           for k in ("tau", "v", "qd", "h")},
        results=res,
    )
