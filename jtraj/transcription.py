"""Transcriptions: from a :class:`~jtraj.Problem` to a finite-dimensional NLP.

Notation and shapes (N intervals, n joints, m actuators)::

    z      : (N * (m_u + 1),)  scaled decision vector [u_0 .. u_{N-1}, h_0 .. h_{N-1}]
    u_k    : (m_u,)  controls: accelerations v_k (decoupled) or efforts tau_k (coupled)
    h_k    : ()      sampling periods [s], T = sum_k h_k
    q, qd  : (N+1, n)  states, q_0 = q_start, qd_0 = qd_start
    a_k    : (n,)    accelerations: a_k = v_k (decoupled) or forward dynamics (coupled)

Both transcriptions share the state recursion of Khoukhi's discrete model::

    q_{k+1}  = q_k + h_k qd_k + h_k^2 / 2 a_k
    qd_{k+1} = qd_k + h_k a_k

**Decoupled (ALD, the thesis method):** u_k = v_k and tau_k = ID(q_k, qd_k, v_k). The
state recursion is linear in v for fixed h; all nonlinearity sits in the cost and the
torque constraints. **Coupled:** u_k = tau_k and a_k = FD(q_k, qd_k, tau_k).

The objective and every constraint are written *once per sample* as a function of the
stage vector ``w_k = (q_k, qd_k, u_k, h_k)``: the NLP is a sum of stage terms composed
with the (cheap, polynomial) state recursion ``W(z)``. The solver exploits this to
build exact Hessians from small per-stage Hessians (see :mod:`jtraj.solver`).
Constraints are *normalised* (``g <= 0`` with O(1) scale): boxes are divided by their
bound, so a tolerance on ``g`` is a relative tolerance on the box.
The box on the controls (v or tau) and on h is kept exactly by the solver (projection);
all other constraints enter the augmented Lagrangian.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .problem import Problem

_BIG = 1e6  # "no bound" stand-in for scaling when a box is absent

TRANSCRIPTIONS = ("decoupled", "coupled")


class StageData(NamedTuple):
    """Per-sample constant data, arrays with a leading (N+1) axis."""

    is_interval: Array  # (N+1,) 1 for k < N (controls, torques and cost exist)
    is_inner: Array  # (N+1,) 1 for k >= 1 (state boxes apply; q_0, qd_0 are given)
    is_final: Array  # (N+1,) 1 for k == N
    via_target: Array  # (N+1, d) task point to pass at this sample
    via_halfwidth: Array  # (N+1,) half-width of the via box (0 where none)
    is_via: Array  # (N+1,) 1 where a via point is imposed


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
    """A transcription: the meaning of the controls. ``name`` in TRANSCRIPTIONS."""

    name: str = "decoupled"

    def __post_init__(self):
        if self.name not in TRANSCRIPTIONS:
            raise ValueError(f"transcription must be one of {TRANSCRIPTIONS}, got {self.name!r}")

    # -- controls ------------------------------------------------------------------------
    def control_dim(self, problem: Problem) -> int:
        if self.name == "decoupled":
            return problem.robot.n
        tau_max = problem.robot.limits.tau_max
        return problem.robot.n if tau_max is None else tau_max.shape[0]

    def layout(self, problem: Problem) -> Layout:
        lim = problem.robot.limits
        N, m_u = problem.N, self.control_dim(problem)
        bound = lim.qdd_max if self.name == "decoupled" else lim.tau_max
        u_scale = jnp.full((m_u,), 1.0) if bound is None else bound
        u_lo, u_hi = (-_BIG * jnp.ones(m_u), _BIG * jnp.ones(m_u)) if bound is None else (-jnp.ones(m_u), jnp.ones(m_u))
        h_scale = jnp.asarray(lim.h_max, dtype=float)
        z_lo = jnp.concatenate([jnp.tile(u_lo, N), jnp.full((N,), lim.h_min / lim.h_max)])
        z_hi = jnp.concatenate([jnp.tile(u_hi, N), jnp.ones(N)])
        return Layout(N=N, m_u=m_u, u_scale=u_scale, h_scale=h_scale, z_lo=z_lo, z_hi=z_hi)

    def accel_and_tau(self, problem: Problem, q, qd, u):
        """(a, tau) at one sample from the control u."""
        robot = problem.robot
        if self.name == "decoupled":
            return u, robot.inverse_dynamics(q, qd, u)
        return robot.forward_dynamics(q, qd, u), u

    # -- states ----------------------------------------------------------------------------
    def states(self, problem: Problem, u, h):
        """(q, qd), each (N+1, n), from controls u (N, m_u) and periods h (N,)."""
        if self.name == "decoupled":
            return integrate(problem.q_start, problem.qd_start, u, h)

        def step(carry, uh):
            q, qd = carry
            uk, hk = uh
            a, _ = self.accel_and_tau(problem, q, qd, uk)
            nxt = (q + hk * qd + 0.5 * hk**2 * a, qd + hk * a)
            return nxt, nxt

        _, (qs, qds) = jax.lax.scan(step, (problem.q_start, problem.qd_start), (u, h))
        return (jnp.concatenate([problem.q_start[None], qs]),
                jnp.concatenate([problem.qd_start[None], qds]))

    def stage_vectors(self, problem: Problem, layout: Layout, z):
        """W(z): the stage vectors w_k = (q_k, qd_k, u_k, h_k), shape (N+1, 2n + m_u + 1).
        Row N carries zero control and period (only terminal terms apply there)."""
        u, h = layout.unpack(z)
        q, qd = self.states(problem, u, h)
        u_ext = jnp.concatenate([u, jnp.zeros((1, u.shape[1]))])
        h_ext = jnp.concatenate([h, jnp.zeros(1)])
        return jnp.concatenate([q, qd, u_ext, h_ext[:, None]], axis=1)

    def split_stage(self, problem: Problem, w):
        n = problem.robot.n
        return w[:n], w[n:2 * n], w[2 * n:-1], w[-1]

    # -- per-sample objective and constraints -------------------------------------------
    def stage_cost_terms(self, problem: Problem, w, sd: StageData):
        """The four cost terms of one interval (zero at k = N): dict of scalars."""
        q, qd, u, h = self.split_stage(problem, w)
        _, tau = self.accel_and_tau(problem, q, qd, u)
        U, Q = problem.weights.matrices(problem.robot)
        wt = problem.weights
        terms = {
            "time": wt.time * h,
            "energy": h * tau @ U @ tau,
            "kinetic": h * qd @ Q @ qd,
            "singularity": wt.singularity * h / jnp.maximum(problem.robot.manipulability(q), 1e-9)
            if _nonzero(wt.singularity) else jnp.zeros(()),
        }
        return {k: sd_mask(sd.is_interval, v) for k, v in terms.items()}

    def stage_constraints(self, problem: Problem, w, sd: StageData):
        """Normalised constraints of one sample: (equalities, inequalities), dicts of
        arrays; masked-out entries are 0 (equalities) or -1 (inequalities)."""
        robot, lim = problem.robot, problem.robot.limits
        q, qd, u, h = self.split_stage(problem, w)
        a, tau = self.accel_and_tau(problem, q, qd, u)
        ineq, eq = {}, {}

        def box(x, bound, mask):
            g = jnp.stack([x / bound - 1.0, -x / bound - 1.0], axis=-1)
            return jnp.where(mask > 0, g, -1.0)

        if self.name == "decoupled":
            if lim.tau_max is not None:
                ineq["tau"] = box(tau, lim.tau_max, sd.is_interval)
        elif lim.qdd_max is not None:
            ineq["qdd"] = box(a, lim.qdd_max, sd.is_interval)
        if lim.qd_max is not None:
            ineq["qd"] = box(qd, lim.qd_max, sd.is_inner)
        if lim.q_min is not None:
            mid, half = (lim.q_max + lim.q_min) / 2, (lim.q_max - lim.q_min) / 2
            ineq["q"] = box(q - mid, half, sd.is_inner)
        needs_p = lim.workspace is not None or len(problem.via_points) > 0
        p = robot.forward_kinematics(q) if needs_p else None
        if lim.workspace is not None:
            lo, hi = lim.workspace
            ineq["workspace"] = box(p - (lo + hi) / 2, (hi - lo) / 2, sd.is_inner)
        if len(problem.via_points) > 0:
            width = jnp.maximum(sd.via_halfwidth, 1e-12)
            # scale: a via box of half-width tol is normalised by 1 m + tol so that a
            # tight tolerance does not blow up the conditioning
            g = jnp.stack([(p - sd.via_target - width) / (1.0 + width),
                           (sd.via_target - p - width) / (1.0 + width)], axis=-1)
            ineq["via"] = jnp.where(sd.is_via > 0, g, -1.0)
        extra = getattr(robot, "path_constraints", None)
        if extra is not None:
            ineq["path"] = jnp.where(sd.is_inner > 0, extra(q), -1.0)
        qd_scale = 1.0 if lim.qd_max is None else lim.qd_max
        eq["goal"] = sd.is_final * jnp.concatenate([q - problem.q_goal, (qd - problem.qd_goal) / qd_scale])
        extra_eq = getattr(robot, "path_equalities", None)
        if extra_eq is not None:
            eq["path"] = sd.is_inner * extra_eq(q, qd)
        return eq, ineq

    def global_inequalities(self, problem: Problem, layout: Layout, z):
        """Constraints that couple all samples (normalised): the bound on T."""
        _, h = layout.unpack(z)
        T_max = jnp.where(jnp.isfinite(problem.T_max), problem.T_max, 1.0)
        g = jnp.where(jnp.isfinite(problem.T_max), jnp.sum(h) / T_max - 1.0, -1.0)
        return g[None]

    def stage_data(self, problem: Problem) -> StageData:
        N = problem.N
        d = problem.robot.forward_kinematics(problem.q_start).shape[0]
        k = jnp.arange(N + 1)
        target = jnp.zeros((N + 1, d))
        width = jnp.zeros(N + 1)
        is_via = jnp.zeros(N + 1)
        for vp, kk in zip(problem.via_points, problem.via_samples()):
            target = target.at[kk].set(vp.point)
            width = width.at[kk].set(jnp.asarray(vp.tol) / jnp.sqrt(d))
            is_via = is_via.at[kk].set(1.0)
        return StageData(is_interval=(k < N).astype(float), is_inner=(k >= 1).astype(float),
                         is_final=(k == N).astype(float), via_target=target,
                         via_halfwidth=width, is_via=is_via)


def sd_mask(mask, x):
    return mask * x


def _nonzero(x) -> bool:
    try:
        return float(x) != 0.0
    except (TypeError, jax.errors.ConcretizationTypeError):
        return True  # traced weight: keep the term


def integrate(q0, qd0, v, h):
    """Closed form of the decoupled recursion: (q, qd), each (N+1, n).

    Prefix sums are products with a lower-triangular matrix of ones rather than
    ``cumsum``: under ``jacfwd``/``vmap`` on a CPU this is about 3x faster (measured)."""
    N = h.shape[0]
    S = jnp.tril(jnp.ones((N + 1, N), dtype=v.dtype), k=-1)  # row k sums intervals j < k
    qd = qd0 + S @ (h[:, None] * v)
    dq = h[:, None] * qd[:-1] + 0.5 * (h**2)[:, None] * v
    q = q0 + S @ dq
    return q, qd
