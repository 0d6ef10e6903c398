"""Independent verifier for arm trajectories given as ``(v, h)``: the states re-simulated
by the transcription's recursion in NumPy (:func:`.verify.simulate`), efforts from
Pinocchio's RNEA on a Pinocchio model (e.g. :func:`.casadi_rnea.panda_model`). Shares
no code with :mod:`jtraj` nor with the CasADi peers' dynamics.

``verify(model, q_start, q_goal, v, h, *, tau_max, qd_max, qdd_max, q_min, q_max,
h_min, h_max, weights, tol, jerk_max=None)`` -> dict(ok, goal_error, max_rel_violation
{tau, v, qd, q, h, and jerk with a jerk bound}, cost, T, q, qd, tau).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from .verify import _box, simulate


def _configuration(model, q):
    from .casadi_rnea import pinocchio_configuration

    return pinocchio_configuration(model, q)


def verify(model, q_start, q_goal, v, h, *, tau_max, qd_max, qdd_max, q_min, q_max, h_min, h_max,
           weights=(1.0, 0.1, 0.0), tol=1e-6, jerk_max=None) -> dict:
    """Re-simulate ``(v (N, n), h (N,))`` from ``q_start`` at rest and check it: efforts
    ``|tau_k| <= tau_max`` (k < N), ``|v_k| <= qdd_max``, ``|qd_k| <= qd_max`` and
    ``q_min <= q_k <= q_max`` (k = 1..N), relative to the bound (the position box
    relative to its half-width), ``h_min <= h_k <= h_max`` relative to h_max, and with
    ``jerk_max`` each acceleration jump ``|v_{k+1} - v_k| <= jerk_max (h_k + h_{k+1}) / 2``
    relative to its bound; goal ``|q_N - q_goal|`` and ``|qd_N|`` absolute; all within
    ``tol``. ``cost`` is
    ``sum_k h_k [w_time + w_energy sum (tau_k / tau_max)^2 + w_kin |qd_k|^2]``."""
    v = np.asarray(v, np.float64)
    h = np.asarray(h, np.float64).reshape(-1)
    if v.ndim != 2 or v.shape != (h.shape[0], model.nv):
        raise ValueError(f"v must be (N, {model.nv}) and h (N,), got {v.shape} and {h.shape}")
    q, qd = simulate(q_start, v, h)
    data = model.createData()
    tau = np.stack([np.array(pin.rnea(model, data, _configuration(model, q[k]), qd[k], v[k])) for k in range(len(h))])
    n = model.nv
    tau_max = np.broadcast_to(np.asarray(tau_max, float), (n,))
    lo, hi = (np.broadcast_to(np.asarray(b, float), (n,)) for b in (q_min, q_max))
    finite = np.isfinite(lo) & np.isfinite(hi)
    lo_f, hi_f = np.where(finite, lo, 0.0), np.where(finite, hi, 0.0)  # (no inf - inf: continuous joints)
    mid, half = (lo_f + hi_f) / 2, np.where(finite, (hi_f - lo_f) / 2, np.inf)
    goal_error = float(max(np.max(np.abs(q[-1] - np.asarray(q_goal, float))), np.max(np.abs(qd[-1]))))
    rel = dict(tau=_box(tau, tau_max), v=_box(v, qdd_max), qd=_box(qd[1:], qd_max),
               q=_box(q[1:] - mid, half),
               h=float(np.max(np.maximum(np.maximum(h_min - h, h - h_max), 0.0)) / h_max))
    if jerk_max is not None:
        bound = np.broadcast_to(np.asarray(jerk_max, float), (n,)) * (h[1:] + h[:-1])[:, None] / 2
        rel["jerk"] = float(np.max(np.maximum(np.abs(np.diff(v, axis=0)) / bound - 1.0, 0.0)))
    w_time, w_energy, w_kin = weights
    stage = w_time + w_energy * np.sum((tau / tau_max) ** 2, axis=1) + w_kin * np.sum(qd[:-1] ** 2, axis=1)
    ok = bool(goal_error <= tol and all(r <= tol for r in rel.values()) and np.all(np.isfinite(v))
              and np.all(np.isfinite(h)))
    return dict(ok=ok, goal_error=goal_error, max_rel_violation=rel, cost=float(np.sum(h * stage)),
                T=float(np.sum(h)), q=q, qd=qd, tau=tau)
