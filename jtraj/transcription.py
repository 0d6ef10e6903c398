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
exactly by the solver (projection);
all other constraints enter the augmented Lagrangian.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .problem import Problem, orientation_error

_BIG = 1e6  # "no bound" stand-in for scaling when a box is absent
#: periods enter z as h / (_H_SCALE h_max). The Levenberg shifts and the stationarity
#: test are not scale invariant; measured on 96 default serial3 dataset pairs (solver
#: defaults), h_max = 0.1 s / 0.2 s: factor 1 -> 82 of 88 feasible / 83 of 96 converged,
#: mean 220 / 268 iterations; 0.5 -> 87 / 91, 171 / 210; 0.25 -> 86 / 95, 152 / 178;
#: 0.125 -> 86 / 93, 149 / 166. Cost gaps to IPOPT stayed <= 0.1 %.
_H_SCALE = 0.25

TRANSCRIPTIONS = ("decoupled", "coupled", "collocation", "shooting", "spline")


class StageData(NamedTuple):
    """Per-sample constant data, arrays with a leading (N+1) axis."""

    is_interval: Array  # (N+1,) 1 for k < N (controls, torques and cost exist)
    is_inner: Array  # (N+1,) 1 for k >= 1 (state boxes apply; q_0, qd_0 are given)
    is_final: Array  # (N+1,) 1 for k == N
    via_target: Array  # (N+1, d) task point to pass at this sample
    via_tol: Array  # (N+1,) Euclidean tolerance of the passage (0 where none)
    is_via: Array  # (N+1,) 1 where a via point is imposed
    # orientation passages (None unless a via point has a rotation)
    via_rotation: Array | None = None  # (N+1, 3, 3) orientation R_l to pass at this sample
    via_rot_tol: Array | None = None  # (N+1,) tolerance on ||vect(R^T R_l)|| (0 where none)
    is_via_rot: Array | None = None  # (N+1,) 1 where an orientation passage is imposed


class Layout(eqx.Module):
    """How the scaled decision vector z maps to physical controls and periods."""

    N: int = eqx.field(static=True)
    m_u: int = eqx.field(static=True)
    u_scale: Array  # (m_u,)
    h_scale: Array  # ()
    z_lo: Array  # (nz,)
    z_hi: Array  # (nz,)

    @property
    def nz(self) -> int:
        return self.N * (self.m_u + 1)

    def unpack(self, z):
        u = z[: self.N * self.m_u].reshape(self.N, self.m_u) * self.u_scale
        h = z[self.N * self.m_u:] * self.h_scale
        return u, h

    def pack(self, u, h):
        return jnp.concatenate([(u / self.u_scale).ravel(), h / self.h_scale])


@dataclasses.dataclass(frozen=True)
class Transcription:
    """A transcription: what the controls ``u_k`` mean. ``name`` in TRANSCRIPTIONS.

    ========== ================================ ======================================
    name       u_k (scaled in z)                states / accelerations
    ========== ================================ ======================================
    decoupled  v_k (accelerations)              Khoukhi's recursion; tau = ID(q, qd, v)
    coupled    tau_k                            Khoukhi's recursion with a = FD(q, qd, tau)
    collocation (tau_k, q_{k+1}, qd_{k+1})     unknowns; midpoint-rule defects are
                                                equalities (Chettibi's method 1)
    shooting   tau_k (held over the interval)   one RK4 step of the continuous dynamics
                                                per interval (Chettibi's method 2)
    spline     q_{k+1} (knot positions)         clamped cubic spline through the knots
                                                (C2); tau = ID at the knots (method 3)
    ========== ================================ ======================================

    Every transcription fills the same stage vector ``w_k = (q_k, qd_k, c_k, h_k)``
    whose control slot ``c_k`` is ``u_k``, except the spline's, which holds the knot
    acceleration ``qdd_k`` (all N+1 knots: the spline's acceleration is piecewise
    linear, so its bound and the torque bound are checked where they peak, at knots,
    up to the torque's variation between knots). The collocation's states are decision
    variables: its "re-simulation" check is that the defects vanish (within the
    verification tolerance), not a replay of the recursion.
    """

    name: str = "decoupled"

    def __post_init__(self):
        if self.name not in TRANSCRIPTIONS:
            raise ValueError(f"transcription must be one of {TRANSCRIPTIONS}, got {self.name!r}")

    @property
    def linear_stage_map(self) -> bool:
        """Whether W(z) is linear (its second derivative, a Hessian term, vanishes)."""
        return self.name == "collocation"

    @property
    def controls_are_accelerations(self) -> bool:
        """Whether the control slot of a stage vector is the joint acceleration and the
        efforts are its inverse dynamics (decoupled, spline; the others take efforts)."""
        return self.name in ("decoupled", "spline")

    @property
    def linear_in_controls(self) -> bool:
        """Whether W(z) is linear in the controls for fixed periods (the recursion and the
        spline are; forward dynamics are not): the Hessian's co-state term then has no
        control-control block."""
        return self.name in ("decoupled", "spline", "collocation")

    # -- controls ------------------------------------------------------------------------
    def control_dim(self, problem: Problem) -> int:
        n = problem.robot.n
        tau_max = problem.robot.limits.tau_max
        m = n if tau_max is None else tau_max.shape[0]
        return {"decoupled": n, "spline": n, "coupled": m, "shooting": m, "collocation": m + 2 * n}[self.name]

    def _control_box(self, problem: Problem):
        """(scale, lo, hi) of one u_k in physical units / scale."""
        robot, lim = problem.robot, problem.robot.limits
        n = robot.n
        m = n if lim.tau_max is None else lim.tau_max.shape[0]

        def sym(bound, size):
            if bound is None:
                return jnp.ones(size), -_BIG * jnp.ones(size), _BIG * jnp.ones(size)
            return jnp.asarray(bound, float), -jnp.ones(size), jnp.ones(size)

        def joints(scale=1.0):
            scale = jnp.broadcast_to(jnp.asarray(scale, float), (n,))
            if lim.q_min is None:
                return scale, -_BIG * jnp.ones(n), _BIG * jnp.ones(n)
            return scale, jnp.asarray(lim.q_min, float) / scale, jnp.asarray(lim.q_max, float) / scale

        if self.name == "decoupled":
            return sym(lim.qdd_max, n)
        if self.name in ("coupled", "shooting"):
            return sym(lim.tau_max, m)
        if self.name == "spline":
            # knots scaled by the displacement that saturates the acceleration over one
            # period: the Newton system is then O(1) in every direction
            return joints(1.0 if lim.qdd_max is None else lim.qdd_max * lim.h_max**2)
        parts = [sym(lim.tau_max, m), joints(), sym(lim.qd_max, n)]
        return tuple(jnp.concatenate([p[i] for p in parts]) for i in range(3))

    def layout(self, problem: Problem) -> Layout:
        """Variables z = (u / u_scale, h / h_scale) with bounds; h_scale = h_max / 4
        (:data:`_H_SCALE`)."""
        lim = problem.robot.limits
        N, m_u = problem.N, self.control_dim(problem)
        u_scale, u_lo, u_hi = self._control_box(problem)
        lo, hi = jnp.tile(u_lo, (N, 1)), jnp.tile(u_hi, (N, 1))
        if self.name == "spline":  # the last knot is the goal: a fixed variable
            lo, hi = lo.at[-1].set(problem.q_goal / u_scale), hi.at[-1].set(problem.q_goal / u_scale)
        hs = _H_SCALE * lim.h_max
        h_scale = jnp.asarray(hs, dtype=float)
        z_lo = jnp.concatenate([lo.ravel(), jnp.full((N,), lim.h_min / hs)])
        z_hi = jnp.concatenate([hi.ravel(), jnp.full((N,), lim.h_max / hs)])
        return Layout(N=N, m_u=m_u, u_scale=u_scale, h_scale=h_scale, z_lo=z_lo, z_hi=z_hi)

    def accel_and_tau(self, problem: Problem, q, qd, c):
        """(a, tau) at one sample from its control slot c (see the class docstring)."""
        robot = problem.robot
        if self.controls_are_accelerations:
            return c, robot.inverse_dynamics(q, qd, c)
        if self.name == "collocation":
            n = robot.n
            m = c.shape[0] - 2 * n
            tau, q1, qd1 = c[:m], c[m:m + n], c[m + n:]
            return robot.forward_dynamics((q + q1) / 2, (qd + qd1) / 2, tau), tau
        return robot.forward_dynamics(q, qd, c), c

    def initial_controls(self, problem: Problem, v, h):
        """u (N, m_u) of this transcription from an acceleration profile (v, h) run
        through the decoupled recursion (how the default guesses are made)."""
        if self.name == "decoupled":
            return v
        q, qd = integrate(problem.q_start, problem.qd_start, v, h)
        if self.name == "spline":
            return q[1:]
        tau = jax.vmap(problem.robot.inverse_dynamics)(q[:-1], qd[:-1], v)
        if self.name == "collocation":
            return jnp.concatenate([tau, q[1:], qd[1:]], axis=1)
        return tau

    def controls_of(self, solution):
        """u (N, m_u) of a :class:`jtraj.Solution` of this transcription (warm starts)."""
        if self.name == "decoupled":
            return solution.v
        if self.name == "spline":
            return solution.q[1:]
        if self.name == "collocation":
            return jnp.concatenate([solution.tau, solution.q[1:], solution.qd[1:]], axis=1)
        return solution.tau

    # -- states ----------------------------------------------------------------------------
    def states(self, problem: Problem, u, h):
        """(q, qd), each (N+1, n), from controls u (N, m_u) and periods h (N,)."""
        return self._states_and_slot(problem, u, h)[:2]

    def _states_and_slot(self, problem: Problem, u, h):
        """(q, qd, c): states (N+1, n) and the control slot of the stage vectors
        (N+1, m_u'); row N of c is zero except for the spline (the last knot's qdd)."""
        q0, qd0 = problem.q_start, problem.qd_start
        u_ext = jnp.concatenate([u, jnp.zeros((1, u.shape[1]))])
        if self.name == "decoupled":
            return (*integrate(q0, qd0, u, h), u_ext)
        if self.name == "spline":
            return clamped_spline(q0, qd0, problem.qd_goal, u, h)
        if self.name == "collocation":
            n = problem.robot.n
            m = u.shape[1] - 2 * n
            q = jnp.concatenate([q0[None], u[:, m:m + n]])
            qd = jnp.concatenate([qd0[None], u[:, m + n:]])
            return q, qd, u_ext
        fd = problem.robot.forward_dynamics

        def step(carry, uh):
            q, qd = carry
            uk, hk = uh
            if self.name == "coupled":
                nxt = recursion_step(q, qd, fd(q, qd, uk), hk)
            else:  # shooting: classical RK4 on (q, qd)' = (qd, FD(q, qd, tau))
                k1q, k1v = qd, fd(q, qd, uk)
                k2q, k2v = qd + 0.5 * hk * k1v, fd(q + 0.5 * hk * k1q, qd + 0.5 * hk * k1v, uk)
                k3q, k3v = qd + 0.5 * hk * k2v, fd(q + 0.5 * hk * k2q, qd + 0.5 * hk * k2v, uk)
                k4q, k4v = qd + hk * k3v, fd(q + hk * k3q, qd + hk * k3v, uk)
                nxt = (q + hk / 6 * (k1q + 2 * k2q + 2 * k3q + k4q), qd + hk / 6 * (k1v + 2 * k2v + 2 * k3v + k4v))
            return nxt, nxt

        _, (qs, qds) = jax.lax.scan(step, (q0, qd0), (u, h))
        return jnp.concatenate([q0[None], qs]), jnp.concatenate([qd0[None], qds]), u_ext

    def stage_vectors(self, problem: Problem, layout: Layout, z):
        """W(z): the stage vectors w_k = (q_k, qd_k, c_k, h_k), shape (N+1, 2n + m_u + 1).
        Row N carries a zero period (only terminal terms apply there)."""
        u, h = layout.unpack(z)
        q, qd, c = self._states_and_slot(problem, u, h)
        h_ext = jnp.concatenate([h, jnp.zeros(1)])
        return jnp.concatenate([q, qd, c, h_ext[:, None]], axis=1)

    def split_stage(self, problem: Problem, w):
        n = problem.robot.n
        return w[:n], w[n:2 * n], w[2 * n:-1], w[-1]

    # -- per-sample objective and constraints -------------------------------------------
    def stage_cost_terms(self, problem: Problem, w, sd: StageData, a_tau=None):
        """The four cost terms of one interval (zero at k = N): dict of scalars.
        ``a_tau``: (a, tau) of this sample if already computed (see :meth:`stage_terms`)."""
        q, qd, u, h = self.split_stage(problem, w)
        _, tau = self.accel_and_tau(problem, q, qd, u) if a_tau is None else a_tau
        U, Q = problem.weights.matrices(problem.robot)
        wt = problem.weights
        terms = {
            "time": wt.time * h,
            "energy": h * tau @ U @ tau,
            "kinetic": h * qd @ Q @ qd if wt.has_kinetic else jnp.zeros(()),
            "singularity": wt.singularity * h / jnp.maximum(problem.robot.manipulability(q), 1e-9)
            if wt.has_singularity else jnp.zeros(()),
        }
        return {k: sd_mask(sd.is_interval, v) for k, v in terms.items()}

    def stage_constraints(self, problem: Problem, w, sd: StageData, a_tau=None):
        """Normalised constraints of one sample: (equalities, inequalities), dicts of
        arrays; masked-out entries are 0 (equalities) or -1 (inequalities)."""
        robot, lim = problem.robot, problem.robot.limits
        q, qd, u, h = self.split_stage(problem, w)
        a, tau = self.accel_and_tau(problem, q, qd, u) if a_tau is None else a_tau
        ineq, eq = {}, {}

        def box(x, bound, mask):
            g = jnp.stack([x / bound - 1.0, -x / bound - 1.0], axis=-1)
            return jnp.where(mask > 0, g, -1.0)

        # the spline's knot accelerations and torques exist at all N+1 knots
        at = jnp.ones_like(sd.is_interval) if self.name == "spline" else sd.is_interval
        if self.controls_are_accelerations:
            if lim.tau_max is not None:  # otherwise tau is a control, boxed exactly
                ineq["tau"] = box(tau, lim.tau_max, at)
        if self.name == "decoupled" and problem.efforts == "intervals" and lim.tau_max is not None:
            # the effort at the interval's end: the state has moved on, the acceleration is still a
            q1, qd1 = recursion_step(q, qd, a, h)
            ineq["tau_end"] = box(robot.inverse_dynamics(q1, qd1, a), lim.tau_max, sd.is_interval)
        if self.name != "decoupled" and lim.qdd_max is not None:
            ineq["qdd"] = box(a, lim.qdd_max, at)
        if lim.qd_max is not None:
            ineq["qd"] = box(qd, lim.qd_max, sd.is_inner)
        if lim.q_min is not None:
            # a joint with an infinite box (a continuous joint of a URDF arm) has no row
            bounded = jnp.isfinite(lim.q_min) & jnp.isfinite(lim.q_max)
            mid = jnp.where(bounded, (lim.q_max + lim.q_min) / 2, 0.0)
            half = jnp.where(bounded, (lim.q_max - lim.q_min) / 2, 1.0)
            ineq["q"] = jnp.where(bounded[:, None], box(q - mid, half, sd.is_inner), -1.0)
        needs_p = lim.workspace is not None or len(problem.via_points) > 0
        p = robot.forward_kinematics(q) if needs_p else None
        if lim.workspace is not None:
            lo, hi = lim.workspace
            ineq["workspace"] = box(p - (lo + hi) / 2, (hi - lo) / 2, sd.is_inner)
        if len(problem.via_points) > 0:
            # the box inscribed in the ball of radius tol (smooth, unlike the distance at
            # a tight tol); the verification checks the distance itself (solver._finish)
            width = jnp.maximum(sd.via_tol, 1e-12) / jnp.sqrt(p.shape[-1])
            # scale: a via box of half-width tol is normalised by 1 m + tol so that a
            # tight tolerance does not blow up the conditioning
            g = jnp.stack([(p - sd.via_target - width) / (1.0 + width),
                           (sd.via_target - p - width) / (1.0 + width)], axis=-1)
            ineq["via"] = jnp.where(sd.is_via > 0, g, -1.0)
        if sd.via_rotation is not None:
            # the same inscribed box on vect(R^T R_l) (the thesis' orientation distance)
            e = orientation_error(robot.rotation(q), sd.via_rotation)
            width = jnp.maximum(sd.via_rot_tol, 1e-12) / jnp.sqrt(3.0)
            g = jnp.stack([(e - width) / (1.0 + width), (-e - width) / (1.0 + width)], axis=-1)
            ineq["via_rotation"] = jnp.where(sd.is_via_rot > 0, g, -1.0)
        extra = getattr(robot, "path_constraints", None)
        if extra is not None:
            ineq["path"] = jnp.where(sd.is_inner > 0, extra(q), -1.0)
        extra_qd = getattr(robot, "velocity_constraints", None)
        if extra_qd is not None:  # state-dependent bounds, e.g. a parallel robot's leg speeds
            ineq["path_qd"] = jnp.where(sd.is_inner > 0, extra_qd(q, qd), -1.0)
        qd_scale = 1.0 if lim.qd_max is None else lim.qd_max
        if self.name == "collocation":  # midpoint-rule defects of interval k
            n = robot.n
            q1, qd1 = u[-2 * n:-n], u[-n:]
            eq["defect"] = sd.is_interval * jnp.concatenate(
                [q1 - q - h * (qd + qd1) / 2, (qd1 - qd - h * a) / qd_scale])
        eq["goal"] = sd.is_final * jnp.concatenate([q - problem.q_goal, (qd - problem.qd_goal) / qd_scale])
        extra_eq = getattr(robot, "path_equalities", None)
        if extra_eq is not None:
            eq["path"] = sd.is_inner * extra_eq(q, qd)
        return eq, ineq

    def global_inequalities(self, problem: Problem, layout: Layout, z):
        """Constraints that couple samples (normalised): the bound on T (row 0) and, with
        ``problem.jerk``, the jerk rows of :func:`jerk_inequalities` (rows 1..)."""
        u, h = layout.unpack(z)
        g = self.time_inequalities(problem, jnp.sum(h))
        if not problem.jerk:
            return g
        return jnp.concatenate([g, self.jerk_inequalities(problem, u, h)])

    #: the transcriptions whose accelerations the jerk bound applies to (see
    #: :meth:`jerk_inequalities`)
    JERK = ("decoupled", "coupled", "collocation", "spline")

    def check_jerk(self, problem: Problem) -> None:
        """``ValueError`` where ``problem.jerk`` is on and this transcription has no jerk rows."""
        if problem.jerk and self.name not in self.JERK:
            raise ValueError(f"Problem(jerk=True) needs a transcription in {self.JERK} (piecewise-constant or "
                             f"piecewise-linear accelerations); transcription {self.name!r} has none: pass jerk=False")

    def jerk_inequalities(self, problem: Problem, u, h):
        """The jerk rows of this transcription, normalised (see :func:`jerk_inequalities`).

        decoupled: on the controls v_k (linear in z). coupled, collocation: on the
        interval accelerations a_k (forward dynamics at the interval's start or midpoint,
        constant over the interval, as in the decoupled case). spline: the cubic's
        acceleration is continuous and piecewise linear, its jerk on interval k is
        ``(qdd_{k+1} - qdd_k) / h_k`` exactly, so the rows are
        ``|qdd_{k+1} - qdd_k| <= qddd_max h_k`` for k = 0..N-1 (the first and last
        intervals included: the spline's own jerk is bounded everywhere)."""
        lim = problem.robot.limits
        if self.name == "decoupled":
            return jerk_inequalities(u, h, lim)
        q, qd, c = self._states_and_slot(problem, u, h)
        if self.name == "spline":
            return _jump_rows(c[1:] - c[:-1], h, lim)
        a = jax.vmap(lambda q_, qd_, c_: self.accel_and_tau(problem, q_, qd_, c_)[0])(q[:-1], qd[:-1], c[:-1])
        return jerk_inequalities(a, h, lim)

    def time_inequalities(self, problem: Problem, T):
        """The global inequalities as a function of the total time T (all of them depend
        on z through T only, which the stage-wise Newton solve relies on)."""
        T_max = jnp.where(jnp.isfinite(problem.T_max), problem.T_max, 1.0)
        g = jnp.where(jnp.isfinite(problem.T_max), T / T_max - 1.0, -1.0)
        return g[None]

    def stage_data(self, problem: Problem) -> StageData:
        N = problem.N
        d = problem.robot.forward_kinematics(problem.q_start).shape[0]
        k = jnp.arange(N + 1)
        target = jnp.zeros((N + 1, d))
        tol = jnp.zeros(N + 1)
        is_via = jnp.zeros(N + 1)
        for vp, kk in zip(problem.via_points, problem.via_samples()):
            target = target.at[kk].set(vp.point)
            tol = tol.at[kk].set(vp.tol)
            is_via = is_via.at[kk].set(1.0)
        rot = {}
        if any(vp.rotation is not None for vp in problem.via_points):
            R_l, rot_tol, is_rot = jnp.tile(jnp.eye(3), (N + 1, 1, 1)), jnp.zeros(N + 1), jnp.zeros(N + 1)
            for vp, kk in zip(problem.via_points, problem.via_samples()):
                if vp.rotation is not None:
                    R_l = R_l.at[kk].set(vp.rotation)
                    rot_tol = rot_tol.at[kk].set(vp.rot_tol)
                    is_rot = is_rot.at[kk].set(1.0)
            rot = dict(via_rotation=R_l, via_rot_tol=rot_tol, is_via_rot=is_rot)
        return StageData(is_interval=(k < N).astype(float), is_inner=(k >= 1).astype(float),
                         is_final=(k == N).astype(float), via_target=target,
                         via_tol=tol, is_via=is_via, **rot)


def jerk_inequalities(v, h, limits):
    """The jerk bound between consecutive intervals, normalised, (2 (N-1) n,)::

        |v_{k+1} - v_k| <= qddd_max (h_k + h_{k+1}) / 2,   k = 0..N-2, per joint

    The accelerations are constant over each interval, so the motion's jerk is a train
    of impulses at the inner samples; the bound limits each impulse's weight, the jump
    of acceleration, to what a jerk of ``qddd_max`` achieves over the time between the
    two intervals' midpoints (the finite-difference jerk at sample k+1 is then within
    ``qddd_max``). Written this way, and not as ``|v_{k+1} - v_k| / dt <= qddd_max``, the
    rows are *linear* in (v, h): a polyhedron in z, with a constant Jacobian and no
    curvature of its own. Each row is divided by ``qddd_max h_max`` (the bound at the
    longest periods), so ``g <= tol`` lets the jump exceed its bound by at most
    ``tol qddd_max h_max``. The jumps from rest into the first interval and out of the
    last are not bounded (the boundary accelerations are not part of the problem).

    ``v`` (N, n) accelerations, ``h`` (N,) periods; rows ordered (k, joint, sign)."""
    return _jump_rows(v[1:] - v[:-1], 0.5 * (h[1:] + h[:-1]), limits)


def _jump_rows(dv, dt, limits):
    """``|dv| <= qddd_max dt`` row by row as ``(+-dv - qddd_max dt) / (qddd_max h_max) <= 0``:
    dv (K, n) jumps of acceleration, dt (K,) the times they may take; (2 K n,)."""
    J = jnp.asarray(limits.qddd_max, dv.dtype)
    reach = dt[:, None] * J
    scale = J * limits.h_max
    return jnp.stack([(dv - reach) / scale, (-dv - reach) / scale], axis=-1).ravel()


def sd_mask(mask, x):
    return mask * x


def recursion_step(q, qd, a, h):
    """One step of Khoukhi's recursion: ``(q + h qd + h^2/2 a, qd + h a)``
    (:func:`integrate` is its closed form over all steps)."""
    return q + h * qd + 0.5 * h**2 * a, qd + h * a


def integrate(q0, qd0, v, h):
    """Closed form of the decoupled recursion: (q, qd), each (N+1, n), by prefix sums
    (:func:`_prefix_sums`; under ``jacfwd``/``vmap`` on a CPU about 3x faster than
    ``cumsum``, measured)."""
    qd = qd0 + _prefix_sums(h[:, None] * v)
    dq = h[:, None] * qd[:-1] + 0.5 * (h**2)[:, None] * v
    return q0 + _prefix_sums(dq), qd


def decoupled_hessian(layout: Layout, W, c, Hk):
    """Hessian in z of ``sum_k l_k(W_k(z))`` for the decoupled recursion, from the stage
    co-states ``c = dl_k/dw_k`` (N+1, nw) and stage Hessians ``Hk`` (N+1, nw, nw), both
    from autodiff, using the closed form of the recursion's derivatives (the solver's
    fast path; :meth:`jtraj.solver.nlp.NLP.al_derivatives` falls back to ``jacfwd`` for the
    other transcriptions, and the tests check both against each other).

    With ``t_k = sum_{i<k} h_i`` and ``j < k``, the recursion gives (I: n x n identity)::

        dqd_k/dv_j = h_j I          dq_k/dv_j = h_j (t_k - t_j - h_j / 2) I
        dqd_k/dh_j = v_j            dq_k/dh_j = qd_j + (t_k - t_j) v_j

    and its only second derivatives (i, j < k)::

        d2qd_k/dh_j dv_j = I        d2q_k/dh_j dv_j = (t_k - t_j) I
        d2q_k/dh_i dv_j = h_j I  (j < i)        d2q_k/dh_i dh_j = v_min(i,j)

    so ``H = sum_k J_k^T Hk J_k + sum_k c_k . d2W_k`` is assembled from O(N^2 n) terms
    without differentiating the recursion. The state rows of J (2n per stage) and its
    control rows (v_k, h_k: selectors of z) are treated apart, which halves the work of
    the dense product. Internally z is ordered stage-major, y = (v_0, h_0, v_1, h_1, ...).
    """
    N, n = layout.N, layout.m_u
    ns, ny = 2 * n, N * (n + 1)
    A, sy, Chv, Chh, perm = _decoupled_pieces(layout, W, c)
    Hss, Hsc, Hcc = Hk[:, :ns, :ns], Hk[:N, :ns, ns:], Hk[:N, ns:, ns:]
    H = jnp.einsum("kai,kaj->ij", A, jnp.einsum("kab,kbj->kaj", Hss, A))
    X = jnp.einsum("kai,kab->ikb", A[:N], Hsc).reshape(ny, ny) * sy  # state-control rows
    H = H + X + X.T
    H = H + jnp.einsum("kab,kl->kalb", Hcc, jnp.eye(N, dtype=W.dtype)).reshape(ny, ny) * jnp.outer(sy, sy)
    C = jnp.zeros((N, n + 1, N, n + 1), W.dtype).at[:, n, :, :n].set(Chv).reshape(ny, ny)
    C = C + C.T + jnp.zeros((N, n + 1, N, n + 1), W.dtype).at[:, n, :, n].set(Chh).reshape(ny, ny)
    H = H + C * jnp.outer(sy, sy)
    return H[perm][:, perm]


def sample_times(h):
    """t_k = sum_{i<k} h_i, (N+1,), from the periods h (N,)."""
    return _prefix_sums(h)


def _time_differences(h):
    """(t (N+1,), low (N+1, N): k > j, dt (N+1, N): t_k - t_j where k > j, else 0)."""
    N = h.shape[0]
    t = sample_times(h)
    low = jnp.arange(N + 1)[:, None] > jnp.arange(N)[None, :]
    return t, low, jnp.where(low, t[:, None] - t[None, :N], 0.0)


# Prefix and suffix sums over the samples are products with a triangular matrix of ones,
# not ``cumsum``: XLA's CPU lowering of a cumsum is a blocked reduce-window (pads,
# transposes and copies, several kernels each), and these arrays are short (N + 1 rows).
# The products are elementwise and summed, not a dot: XLA fuses them into one loop, where
# a dot of these small shapes is an Eigen contraction that packs its operands into freshly
# allocated buffers (about 3-4 % fewer instructions for a serial3 solve at N = 20).
def _tri_product(tri, X):
    """``tensordot(tri, X, axes=1)`` for a constant 0/1 matrix ``tri``, elementwise."""
    tri = jnp.asarray(tri, X.dtype)
    return jnp.sum(tri.reshape(tri.shape + (1,) * (X.ndim - 1)) * X[None], axis=1)


#: Beyond this many stages the prefix and suffix sums are ``cumsum``: the triangular
#: product's (N + 1, N, ...) intermediate grows as N^2, and under ``jacfwd`` (the
#: polish's and the least-squares multipliers' Jacobians: one tangent per variable) as
#: N^3 (serial3 at N = 1,000: about 100 GB).
_TRI_MAX = 64


def _prefix_sums(X):
    """sum_{j < k} X_j for k = 0..N, from X (N, ...) over the stages."""
    N = X.shape[0]
    if N > _TRI_MAX:
        return jnp.concatenate([jnp.zeros_like(X[:1]), jnp.cumsum(X, axis=0)])
    return _tri_product(np.tri(N + 1, N, -1), X)


def _suffix_sums(X):
    """sum_{k > j} X_k for j = 0..N-1, from X (N+1, ...) over the samples."""
    N = X.shape[0] - 1
    if N > _TRI_MAX:
        return jnp.cumsum(X[::-1], axis=0)[::-1][1:]
    return _tri_product(np.triu(np.ones((N, N + 1)), 1), X)


def _costate_terms(c, u, dt):
    """The co-state term ``sum_k c_k . d2W_k`` of :func:`decoupled_hessian` by its
    pieces, unscaled, from the co-states c (N+1, nw), the accelerations u (N, n) and
    ``dt`` (N+1, N), t_k - t_j where k > j and 0 elsewhere: Cq (N, n), the suffix sums
    ``sum_{k > i} cq_k`` of the position co-states (which carry d2q_k to every k > j), so
    that [h_i, v_j] = Cq_i h_j for j < i; cv_diag (N, n), the [h_j, v_j] entries; Chh
    (N, N), the [h_i, h_j] block ``Cq_{max(i,j)} . v_min(i,j)``."""
    N, n = u.shape
    cq, cqd = c[:, :n], c[:, n:2 * n]
    Cq = _suffix_sums(cq)
    cv_diag = _suffix_sums(cqd) + jnp.sum(dt[..., None] * cq[:, None, :], axis=0)
    M = Cq @ u.T  # [i, j] = Cq_i . v_j
    I, J = jnp.arange(N)[:, None], jnp.arange(N)[None, :]
    return Cq, cv_diag, jnp.where(I >= J, M, M.T)


def _decoupled_pieces(layout: Layout, W, c):
    """The recursion's derivatives for :func:`decoupled_hessian`, stage-major
    (y = (v_0, h_0, v_1, h_1, ...)): the state rows A (N+1, 2n, ny) of J (scaled to z),
    dy/dz sy (ny,), the co-state terms Chv (N, N, n) [h_i, v_j] and Chh (N, N) [h_i, h_j]
    (unscaled), and the permutation from y to z's order."""
    N, n = layout.N, layout.m_u
    ns, ny = 2 * n, N * (n + 1)
    qd, u, h = W[:, n:ns], W[:N, ns:ns + n], W[:N, -1]
    _, low, dt = _time_differences(h)
    eye = jnp.eye(n, dtype=W.dtype)

    def rows(coef, dh):  # (N+1, N) scalar v-coefficients, (N+1, N, n) h-columns
        blk = coef[:, None, :, None] * eye[None, :, None, :]  # (N+1, n, N, n)
        return jnp.concatenate([blk, dh.transpose(0, 2, 1)[..., None]], axis=-1)

    Aq = rows(jnp.where(low, h * (dt - 0.5 * h), 0.0), jnp.where(low[..., None], qd[None, :N] + dt[..., None] * u, 0.0))
    Aqd = rows(jnp.where(low, h, 0.0), jnp.where(low[..., None], u[None], 0.0))
    sy = jnp.tile(jnp.concatenate([layout.u_scale, layout.h_scale[None]]), N)  # dy/dz
    A = jnp.concatenate([Aq, Aqd], axis=1).reshape(N + 1, ns, ny) * sy  # state rows of J
    Cq, cv_diag, Chh = _costate_terms(c, u, dt)
    I, J = jnp.arange(N)[:, None], jnp.arange(N)[None, :]
    Chv = jnp.where((J < I)[..., None], Cq[:, None, :] * h[None, :, None], 0.0) + jnp.eye(N)[..., None] * cv_diag
    perm = np.concatenate([(np.arange(N)[:, None] * (n + 1) + np.arange(n)).ravel(), np.arange(N) * (n + 1) + n])
    return A, sy, Chv, Chh, perm


def _state_diagonal(layout: Layout, W, Hss):
    """The diagonal of ``sum_k J_k^T Hss_k J_k`` over the states' rows J_k of the
    recursion, unscaled, (N, n + 1) stage-major, in O(N n^2) instead of O(N^2 n^3): every
    column of J_k is a polynomial in ``dt = t_k - t_j`` (j < k):

        h_j:          x_kj = p_j + dt r_j,  p_j = (qd_j, v_j), r_j = (v_j, 0)
        v_j (comp b): h_j (dt - h_j / 2) in q_k[b], h_j in qd_k[b]

    so the sums over k > j need only the suffix sums of Hss_k, t_k Hss_k, t_k^2 Hss_k."""
    N, n = layout.N, layout.m_u
    qd, u, h = W[:N, n:2 * n], W[:N, 2 * n:3 * n], W[:N, -1]
    t = sample_times(h)
    tk, tj = t[:, None, None], t[:N, None, None]
    T0, T1, T2 = _suffix_sums(Hss), _suffix_sums(tk * Hss), _suffix_sums(tk**2 * Hss)
    S0, S1, S2 = T0, T1 - tj * T0, T2 - 2 * tj * T1 + tj**2 * T0  # sums of dt^0, dt^1, dt^2 times Hss_k
    p = jnp.concatenate([qd, u], axis=1)
    r = jnp.concatenate([u, jnp.zeros_like(u)], axis=1)

    def quad(S, a, b):
        return jnp.sum(a[:, :, None] * S * b[:, None, :], axis=(1, 2))

    d_h = quad(S0, p, p) + 2 * quad(S1, p, r) + quad(S2, r, r)
    i = np.arange(n)
    hj = h[:, None]

    def qq(S):
        return S[:, i, i]

    d_v = hj**2 * (qq(S2) - hj * qq(S1) + hj**2 / 4 * qq(S0) + 2 * (S1[:, i, n + i] - hj / 2 * S0[:, i, n + i])
                   + S0[:, n + i, n + i])
    return jnp.concatenate([d_v, d_h[:, None]], axis=1)


def decoupled_hessian_bounds(layout: Layout, W, c, Hk):
    """The diagonal of :func:`decoupled_hessian`'s H and a function ``free -> bound``
    giving upper bounds on the row sums of |H| over the free columns
    (``sum_{j free} |H_ij| <= bound_i``), both in z's order, without forming H or the
    recursion's Jacobian: the diagonal in O(N n^2) (:func:`_state_diagonal`), the bound
    in O(N^2 n) (instead of O(N^3 n^2) for H). The bound takes absolute values stage by
    stage (|H| <= sum_k |J_k|^T |Hk| |J_k| + |C|); it feeds the Gershgorin shift of the
    stage-wise Newton solve (:mod:`jtraj.lq`). The diagonal comes first because the
    solver's choice of free variables depends on it.

    With the derivatives of :func:`decoupled_hessian`, |J_k| 1_free and |J_k|^T u need
    no (N+1, 2n, N (n+1)) Jacobian: the v-columns' coefficients ``h_j`` and
    ``h_j (t_k - t_j - h_j / 2)`` are positive polynomials in t_k, so their sums over
    j < k (or k > j) are prefix (suffix) sums; only the h-columns' ``|qd_j + (t_k - t_j)
    v_j|`` need an (N+1, N, n) array. The co-state term's |C| has the same structure
    (``Chv[i, j] = Cq_{>i} h_j`` for j < i). On serial3 at N = 20 this takes the diagonal
    and the row bounds from about 100 to 60 us per problem against the dense Jacobian."""
    N, n = layout.N, layout.m_u
    ns = 2 * n
    qd, u, h = W[:N, n:ns], W[:N, ns:ns + n], W[:N, -1]
    sv, sh = layout.u_scale, layout.h_scale
    t, low, dt = _time_differences(h)
    Hss, Hcc = Hk[:, :ns, :ns], Hk[:N, ns:, ns:]
    Cq, cv_diag, Chh = _costate_terms(c, u, dt)
    # diagonal: state part, the control block, the co-state term (on the h diagonal only)
    sd = _state_diagonal(layout, W, Hss)  # (N, n + 1), unscaled
    hcc = jnp.diagonal(Hcc, axis1=1, axis2=2)  # (N, n + 1)
    d_v = (sd[:, :n] + hcc[:, :n]) * sv**2
    d_h = (sd[:, n] + hcc[:, n] + jnp.diagonal(Chh)) * sh**2
    diag = jnp.concatenate([d_v.ravel(), d_h])
    # |qd_j + (t_k - t_j) v_j| (k > j), the h-columns of the position rows
    E = jnp.where(low[..., None], jnp.abs(qd[None] + dt[..., None] * u[None]), 0.0)  # (N+1, N, n)
    aV = jnp.abs(u)
    aCq, aCv, aChh = jnp.abs(Cq), jnp.abs(cv_diag), jnp.abs(Chh)
    tj = t[:N, None]
    hj = h[:, None]
    zero = jnp.zeros((1, n), W.dtype)

    def rows(free):
        fv = free[:N * n].reshape(N, n).astype(W.dtype)
        fh = free[N * n:].astype(W.dtype)
        # w = |J_k| 1_free: state rows, then the stage's own controls
        hf = hj * fv * sv
        Ph = _prefix_sums(hf)  # (N+1, n)
        w_q = t[:, None] * Ph - _prefix_sums((tj + hj / 2) * hf) + sh * jnp.sum(E * fh[None, :, None], axis=1)
        w_qd = Ph + sh * _prefix_sums(aV * fh[:, None])
        w_u = jnp.concatenate([jnp.concatenate([fv * sv, fh[:, None] * sh], axis=1), jnp.zeros((1, n + 1), W.dtype)])
        w = jnp.concatenate([w_q, w_qd, w_u], axis=1)  # (N+1, 2n + n + 1)
        U = jnp.sum(jnp.abs(Hk) * w[:, None, :], axis=-1)  # |Hk| w
        uq, uqd = U[:, :n], U[:, n:ns]
        # |J_k|^T U summed over k
        Sq, Stq, Sqd = _suffix_sums(uq), _suffix_sums(t[:, None] * uq), _suffix_sums(uqd)
        r_v = sv * hj * (Stq - (tj + hj / 2) * Sq + Sqd) + U[:N, ns:ns + n] * sv
        r_h = sh * (jnp.sum(E * uq[:, None, :], axis=(0, 2)) + jnp.sum(aV * Sqd, axis=1)) + U[:N, -1] * sh
        # |C| (scaled): [h_i, v_ja] = Cq_{>i,a} h_j (j < i) + cv_diag_ia (j == i), [h_i, h_j] = Chh
        r_h = r_h + sh * jnp.sum(aCq * Ph[:N] + sv * aCv * fv, axis=1) + sh**2 * (aChh @ fh)
        r_v = r_v + sh * sv * (hj * _suffix_sums(jnp.concatenate([aCq * fh[:, None], zero])) + aCv * fh[:, None])
        return jnp.concatenate([r_v.ravel(), r_h])

    return diag, rows


def clamped_spline(q0, qd0, qdN, knots, h):
    """Clamped cubic spline through ``q0, knots[0], ..., knots[-1]`` with end velocities
    ``qd0, qdN`` and interval lengths ``h``: (q, qd, qdd) at the N+1 knots.

    The knot velocities solve the C2 continuity conditions (tridiagonal, diagonally
    dominant; solved densely, N is small), for interior knots i::

        h_i qd_{i-1} + 2 (h_{i-1} + h_i) qd_i + h_{i-1} qd_{i+1}
            = 3 (h_i d_{i-1} + h_{i-1} d_i),   d_k = (q_{k+1} - q_k) / h_k

    and the acceleration at the start of interval k is
    ``6 d_k / h_k - (4 qd_k + 2 qd_{k+1}) / h_k`` (at its end
    ``-6 d_k / h_k + (2 qd_k + 4 qd_{k+1}) / h_k``; equal at interior knots)."""
    q = jnp.concatenate([q0[None], knots])
    N = h.shape[0]
    d = (q[1:] - q[:-1]) / h[:, None]
    if N == 1:
        qd = jnp.stack([qd0, qdN])
    else:
        hl, hr = h[:-1], h[1:]  # h_{i-1}, h_i for i = 1..N-1
        rhs = 3 * (hr[:, None] * d[:-1] + hl[:, None] * d[1:])
        rhs = rhs.at[0].add(-hr[0] * qd0).at[-1].add(-hl[-1] * qdN)
        A = jnp.diag(2 * (hl + hr)) + jnp.diag(hr[1:], -1) + jnp.diag(hl[:-1], 1)
        qd = jnp.concatenate([qd0[None], jnp.linalg.solve(A, rhs), qdN[None]])
    a_start = 6 * d / h[:, None] - (4 * qd[:-1] + 2 * qd[1:]) / h[:, None]
    a_end = -6 * d[-1] / h[-1] + (2 * qd[-2] + 4 * qd[-1]) / h[-1]
    return q, qd, jnp.concatenate([a_start, a_end[None]])
