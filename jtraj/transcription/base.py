"""The shared part of every transcription: the stage data, the decision vector's layout,
and :class:`Transcription`, the abstract base whose subclasses (:mod:`.methods`) say what
the controls mean. The objective and the constraints are written here once per sample as
functions of the stage vector; a subclass supplies the controls' box, the states they
produce and the few rows only it has."""

from __future__ import annotations

from typing import ClassVar, NamedTuple

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from ..problem import Problem, orientation_error

#: "no bound" stand-in for scaling when a box is absent
BIG = 1e6
#: periods enter z as h / (H_SCALE h_max). The Levenberg shifts and the stationarity
#: test are not scale invariant; on 96 default serial3 dataset pairs (solver defaults,
#: h_max = 0.1 s / 0.2 s) factor 1 gave 82 of 88 feasible / 83 of 96 converged, mean
#: 220 / 268 iterations; 0.5: 87 / 91, 171 / 210; 0.25: 86 / 95, 152 / 178; 0.125: 86 /
#: 93, 149 / 166, with cost gaps to IPOPT <= 0.1 % throughout.
H_SCALE = 0.25

#: the transcriptions' names, in the order the documentation lists them
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
        u = z[: self.N * self.m_u].reshape(self.N, self.m_u) * self.u_scale[None]
        h = z[self.N * self.m_u:] * self.h_scale
        return u, h

    def pack(self, u, h):
        return jnp.concatenate([(u / self.u_scale[None]).ravel(), h / self.h_scale])


def sd_mask(mask, x):
    return mask * x


def box_rows(x, bound, mask):
    """``|x| <= bound`` as the normalised rows ``(+-x / bound - 1)`` (last axis: the
    sign), -1 (inactive) where ``mask`` is 0."""
    g = jnp.stack([x / bound - 1.0, -x / bound - 1.0], axis=-1)
    return jnp.where(mask > 0, g, -1.0)


class Transcription:
    """A transcription: what the controls ``u_k`` mean. ``Transcription(name)``, ``name``
    in :data:`TRANSCRIPTIONS`, returns the subclass of that name
    (:mod:`jtraj.transcription.methods`).

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

    A subclass sets :attr:`name` and the structural flags and implements
    :meth:`control_dim`, :meth:`control_box`, :meth:`accel_and_tau`,
    :meth:`initial_controls`, :meth:`controls_of` and :meth:`states_and_slot` (and
    :meth:`jerk_inequalities` where it has jerk rows); the hooks
    :meth:`control_bounds`, :meth:`effort_samples`, :meth:`acceleration_rows` and
    :meth:`defect_rows` add what only it has. Instances hold no data: two of the same
    name are equal.
    """

    name: ClassVar[str] = ""
    #: whether W(z) is linear (its second derivative, a Hessian term, vanishes)
    linear_stage_map: ClassVar[bool] = False
    #: whether the control slot of a stage vector is the joint acceleration and the
    #: efforts are its inverse dynamics (the others take efforts as controls)
    controls_are_accelerations: ClassVar[bool] = False
    #: whether W(z) is linear in the controls for fixed periods (the recursion and the
    #: spline are; forward dynamics are not): the Hessian's co-state term then has no
    #: control-control block
    linear_in_controls: ClassVar[bool] = False
    #: the transcriptions whose accelerations the jerk bound applies to (see
    #: :meth:`jerk_inequalities`)
    JERK: ClassVar[tuple[str, ...]] = ("decoupled", "coupled", "collocation", "spline")
    _by_name: ClassVar[dict[str, type]] = {}

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if cls.name:
            Transcription._by_name[cls.name] = cls

    def __new__(cls, name: str | Transcription | None = None):
        if isinstance(name, Transcription):
            name = name.name
        if cls is Transcription:
            name = "decoupled" if name is None else name
            if not isinstance(name, str) or name not in TRANSCRIPTIONS:
                raise ValueError(f"transcription must be one of {TRANSCRIPTIONS}, got {name!r}")
            cls = Transcription._by_name[name]
        elif name is not None and name != cls.name:
            raise ValueError(f"{cls.__name__} is the {cls.name!r} transcription, not {name!r}")
        return object.__new__(cls)

    def __init__(self, name: str | Transcription | None = None):
        del name  # checked by __new__

    def __eq__(self, other):
        return type(self) is type(other)

    def __hash__(self):
        return hash((Transcription, self.name))

    def __repr__(self):
        return f"Transcription({self.name!r})"

    # -- what a subclass supplies ----------------------------------------------------------
    def control_dim(self, problem: Problem) -> int:
        """m_u, the size of one u_k."""
        raise NotImplementedError

    def control_box(self, problem: Problem):
        """(scale, lo, hi) of one u_k in physical units / scale."""
        raise NotImplementedError

    def control_bounds(self, problem: Problem, lo, hi, u_scale):
        """The (N, m_u) bounds of the scaled controls from the tiled box (a subclass fixes
        variables here)."""
        return lo, hi

    def accel_and_tau(self, problem: Problem, q, qd, c):
        """(a, tau) at one sample from its control slot c (see the class docstring)."""
        raise NotImplementedError

    def initial_controls(self, problem: Problem, v, h):
        """u (N, m_u) of this transcription from an acceleration profile (v, h) run
        through the decoupled recursion (how the default guesses are made)."""
        raise NotImplementedError

    def controls_of(self, solution):
        """u (N, m_u) of a :class:`jtraj.Solution` of this transcription (warm starts)."""
        raise NotImplementedError

    def states_and_slot(self, problem: Problem, u, h):
        """(q, qd, c): states (N+1, n) and the control slot of the stage vectors
        (N+1, m_u'); row N of c is zero except for the spline (the last knot's qdd)."""
        raise NotImplementedError

    def jerk_inequalities(self, problem: Problem, u, h):
        """The jerk rows of this transcription, normalised (see
        :func:`jtraj.transcription.jerk_inequalities`)."""
        raise ValueError(f"transcription {self.name!r} has no jerk rows")

    def effort_samples(self, sd: StageData):
        """Where the effort bound (and the acceleration box) apply: the intervals' starts."""
        return sd.is_interval

    def acceleration_rows(self, problem: Problem, q, qd, a, h, sd: StageData, at) -> dict:
        """Inequality rows on the accelerations of one sample: the box on ``a`` (where it
        is not a control box already)."""
        qdd_max = problem.robot.limits.qdd_max
        return {} if qdd_max is None else {"qdd": box_rows(a, qdd_max, at)}

    def defect_rows(self, problem: Problem, q, qd, u, h, a, sd: StageData) -> dict:
        """Equality rows that tie the states to the controls (where states are unknowns)."""
        return {}

    # -- shared ----------------------------------------------------------------------------
    def layout(self, problem: Problem) -> Layout:
        """Variables z = (u / u_scale, h / h_scale) with bounds; h_scale = h_max / 4
        (:data:`H_SCALE`)."""
        lim = problem.robot.limits
        N, m_u = problem.N, self.control_dim(problem)
        u_scale, u_lo, u_hi = self.control_box(problem)
        lo, hi = self.control_bounds(problem, jnp.tile(u_lo, (N, 1)), jnp.tile(u_hi, (N, 1)), u_scale)
        hs = H_SCALE * lim.h_max
        h_scale = jnp.asarray(hs, dtype=float)
        z_lo = jnp.concatenate([lo.ravel(), jnp.full((N,), lim.h_min / hs)])
        z_hi = jnp.concatenate([hi.ravel(), jnp.full((N,), lim.h_max / hs)])
        return Layout(N=N, m_u=m_u, u_scale=u_scale, h_scale=h_scale, z_lo=z_lo, z_hi=z_hi)

    def states(self, problem: Problem, u, h):
        """(q, qd), each (N+1, n), from controls u (N, m_u) and periods h (N,)."""
        return self.states_and_slot(problem, u, h)[:2]

    def stage_vectors(self, problem: Problem, layout: Layout, z):
        """W(z): the stage vectors w_k = (q_k, qd_k, c_k, h_k), shape (N+1, 2n + m_u + 1).
        Row N carries a zero period (only terminal terms apply there)."""
        u, h = layout.unpack(z)
        q, qd, c = self.states_and_slot(problem, u, h)
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
        box = box_rows
        at = self.effort_samples(sd)
        if self.controls_are_accelerations:
            if lim.tau_max is not None:  # otherwise tau is a control, boxed exactly
                ineq["tau"] = box(tau, lim.tau_max, at)
        ineq.update(self.acceleration_rows(problem, q, qd, a, h, sd, at))
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
            # a tight tol); the solver's verification checks the distance itself
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
        eq.update(self.defect_rows(problem, q, qd, u, h, a, sd))
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

    def check_jerk(self, problem: Problem) -> None:
        """``ValueError`` where ``problem.jerk`` is on and this transcription has no jerk rows."""
        if problem.jerk and self.name not in self.JERK:
            raise ValueError(f"Problem(jerk=True) needs a transcription in {self.JERK} (piecewise-constant or "
                             f"piecewise-linear accelerations); transcription {self.name!r} has none: pass jerk=False")

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
