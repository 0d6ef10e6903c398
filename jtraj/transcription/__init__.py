"""Transcriptions: from a :class:`~jtraj.Problem` to a finite-dimensional NLP.

Notation and shapes (N intervals, n joints, m actuators)::

    z      : (N * (m_u + 1),)  scaled decision vector [u_0 .. u_{N-1}, h_0 .. h_{N-1}]
    u_k    : (m_u,)  controls: accelerations v_k (decoupled), efforts tau_k (coupled,
                     shooting), see :class:`Transcription` for the others
    h_k    : ()      sampling periods [s], T = sum_k h_k
    q, qd  : (N+1, n)  states, q_0 = q_start, qd_0 = qd_start
    a_k    : (n,)    accelerations: a_k = v_k (decoupled) or forward dynamics (coupled)

The decoupled and coupled transcriptions share the state recursion of Khoukhi's
discrete model::

    q_{k+1}  = q_k + h_k qd_k + h_k^2 / 2 a_k
    qd_{k+1} = qd_k + h_k a_k

**Decoupled (ALD, the thesis method):** u_k = v_k and tau_k = ID(q_k, qd_k, v_k). The
state recursion is linear in v for fixed h; all nonlinearity sits in the cost and the
torque constraints. **Coupled:** u_k = tau_k and a_k = FD(q_k, qd_k, tau_k).
Chettibi's three transcriptions (**collocation**, **shooting**, **spline**) are
described in :class:`Transcription`.

The objective and every constraint are written *once per sample* as a function of the
stage vector ``w_k = (q_k, qd_k, u_k, h_k)``: the NLP is a sum of stage terms composed
with the (cheap, polynomial) state recursion ``W(z)``. The solver exploits this to
build exact Hessians from small per-stage Hessians (see :mod:`jtraj.solver`).
Constraints are *normalised* (``g <= 0`` with O(1) scale): boxes are divided by their
bound, so a tolerance on ``g`` is a relative tolerance on the box.
The box on the controls (v, tau, knot positions, collocation states) and on h is kept
exactly by the solver (projection); all other constraints enter the augmented Lagrangian
(or the interior-point barrier).

Modules: :mod:`.base` (the stage data, the layout of z and the abstract
:class:`Transcription` with the shared objective and constraints), :mod:`.methods` (one
class per transcription), :mod:`.recursion` (Khoukhi's recursion and the sums over
samples), :mod:`.hessian` (the decoupled transcription's Hessian in closed form).
"""

from .base import BIG, H_SCALE, TRANSCRIPTIONS, Layout, StageData, Transcription, box_rows, sd_mask
from .hessian import decoupled_hessian, decoupled_hessian_bounds
from .methods import Collocation, Coupled, Decoupled, Shooting, Spline, clamped_spline
from .recursion import integrate, jerk_inequalities, prefix_sums, recursion_step, sample_times, suffix_sums

__all__ = ["BIG", "H_SCALE", "TRANSCRIPTIONS", "Collocation", "Coupled", "Decoupled", "Layout", "Shooting",
           "Spline", "StageData", "Transcription", "box_rows", "clamped_spline", "decoupled_hessian",
           "decoupled_hessian_bounds", "integrate", "jerk_inequalities", "prefix_sums", "recursion_step",
           "sample_times", "sd_mask", "suffix_sums"]
