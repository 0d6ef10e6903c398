"""Shared robot machinery: limits, friction, actuators and Lagrangian dynamics.

Notation (SI units throughout)::

    q, qd, qdd : (n,)   generalised positions [rad or m], velocities, accelerations
    tau        : (n,)   actuator efforts: joint torques [N m] / forces [N], or motor
                        torques when the robot has an :class:`Actuator`
    p          : (d,)   task point returned by ``forward_kinematics``

A robot is an :class:`equinox.Module`. Its parameters are arrays (so they can be
differentiated, e.g. for sensitivities of an optimum with respect to a mass) and its
structure (number of links, name) is static. A concrete robot only writes its
kinematics and its energies; mass matrix, Coriolis/centrifugal and gravity terms come
from the Euler-Lagrange equations by automatic differentiation::

    L(q, qd) = T(q, qd) - V(q)
    M(q)           = d^2 T / d qd^2
    c(q, qd)       = (d/dq (dT/dqd)) qd - dT/dq        (= C(q, qd) qd)
    g(q)           = dV/dq
    M qdd + c + g + friction + actuator terms = generalised force

All methods are pure functions of arrays: jit-, vmap- and grad-able.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .. import _linalg
from .._checks import as_vector, check_state

Vec = Float[Array, "n"]


class Limits(eqx.Module):
    """Box limits of a robot. ``None`` where the robot has no such limit.

    Attributes:
        q_min, q_max: (n,) joint position box [rad or m].
        qd_max: (n,) symmetric velocity bound |qd| <= qd_max.
        qdd_max: (n,) symmetric acceleration bound.
        qddd_max: (n,) symmetric jerk bound (used by the cycloidal initial guess).
        tau_max: (n,) symmetric actuator bound |tau| <= tau_max (motor side when the
            robot has an actuator model).
        h_min, h_max: sampling-period bounds [s].
        workspace: (2, d) task-space box ``[[lo...], [hi...]]`` on the task point.
    """

    q_min: Array | None
    q_max: Array | None
    qd_max: Array | None
    qdd_max: Array | None
    qddd_max: Array | None
    tau_max: Array | None
    h_min: float | Array
    h_max: float | Array
    workspace: Array | None = None

    @staticmethod
    def make(n: int, *, q_min=None, q_max=None, qd_max=None, qdd_max=None, qddd_max=None,
             tau_max=None, h_min=0.005, h_max=0.1, workspace=None,
             n_actuators: int | None = None) -> "Limits":
        """Validated constructor; scalars broadcast to all ``n`` joints.

        ``tau_max`` has one entry per actuator: ``n_actuators`` of them (default ``n``;
        differs for redundantly actuated or under-actuated robots).
        """
        m = n if n_actuators is None else int(n_actuators)

        def vec(x, name, **kw):
            return None if x is None else as_vector(x, name, n, allow_inf=True, **kw)

        lo, hi = vec(q_min, "q_min"), vec(q_max, "q_max")
        concrete = not any(isinstance(x, jax.core.Tracer) for x in (lo, hi, h_min, h_max))
        if concrete and lo is not None and hi is not None and bool(jnp.any(lo >= hi)):
            raise ValueError(f"q_min must be < q_max element-wise, got {lo} and {hi}")
        if concrete and not (0 < float(h_min) < float(h_max)):
            raise ValueError(f"need 0 < h_min < h_max, got h_min={h_min}, h_max={h_max}")
        if workspace is not None:
            workspace = jnp.asarray(workspace, dtype=float)
            if workspace.ndim != 2 or workspace.shape[0] != 2:
                raise ValueError(f"workspace must have shape (2, d), got {workspace.shape}")
            if bool(jnp.any(workspace[0] >= workspace[1])):
                raise ValueError(f"workspace must have lower < upper, got {workspace}")
        return Limits(
            q_min=lo, q_max=hi,
            qd_max=vec(qd_max, "qd_max", positive=True),
            qdd_max=vec(qdd_max, "qdd_max", positive=True),
            qddd_max=vec(qddd_max, "qddd_max", positive=True),
            tau_max=None if tau_max is None else as_vector(tau_max, "tau_max", m, positive=True,
                                                           allow_inf=True),
            # 0-d (weakly typed) arrays, not Python floats: traced under jit, so robots that
            # differ only in their period bounds share one compiled solver
            h_min=h_min if isinstance(h_min, jax.core.Tracer) else jnp.asarray(float(h_min)),
            h_max=h_max if isinstance(h_max, jax.core.Tracer) else jnp.asarray(float(h_max)), workspace=workspace,
        )


class Friction(eqx.Module):
    """Viscous + smoothed Coulomb joint friction.

    ``f(qd) = viscous * qd + coulomb * sgn_c(qd)`` with the smooth sign
    ``sgn_c(x) = (2/pi) arctan(sharpness * x)``. ``sharpness`` [s/rad] sets how fast the
    sign saturates: ``sgn_c`` reaches 0.5 at ``|qd| = 1/sharpness`` and 0.94 at
    ``10/sharpness``. Larger values are closer to the true (discontinuous) Coulomb law
    but make the optimisation stiffer; 50 s/rad is a reasonable default.
    """

    viscous: Vec
    coulomb: Vec
    sharpness: float | Array = 50.0

    def __call__(self, qd: Vec) -> Vec:
        return self.viscous * qd + self.coulomb * (2.0 / jnp.pi) * jnp.arctan(self.sharpness * qd)


class Actuator(eqx.Module):
    """Ballscrew/gear actuator per joint (Khoukhi's model, identical structure per joint).

    For a joint coordinate x driven through a gear of ratio ``gear_ratio`` (n) and a
    ballscrew of pitch ``pitch`` (p, metres per screw turn; use p = 2 pi for a purely
    rotary gearbox, then the "screw" is the gear's output shaft)::

        tau_m = M_a xdd + V_a xd + K_a f
        M_a = 2 pi / (n p) (J_s + n^2 J_m),  V_a = 2 pi / (n p) (b_s + n^2 b_m),
        K_a = p / (2 pi n)

    where f is the joint-side effort and tau_m the motor torque. Dividing by K_a shows
    the actuator adds ``M_a / K_a`` to the diagonal of the mass matrix and
    ``V_a / K_a`` to the viscous damping; torque limits then apply to ``tau_m``.
    """

    gear_ratio: Vec
    pitch: Vec
    J_s: Vec
    J_m: Vec
    b_s: Vec
    b_m: Vec

    @property
    def K_a(self) -> Vec:
        return self.pitch / (2 * jnp.pi * self.gear_ratio)

    @property
    def M_a(self) -> Vec:
        return 2 * jnp.pi / (self.gear_ratio * self.pitch) * (self.J_s + self.gear_ratio**2 * self.J_m)

    @property
    def V_a(self) -> Vec:
        return 2 * jnp.pi / (self.gear_ratio * self.pitch) * (self.b_s + self.gear_ratio**2 * self.b_m)

    @staticmethod
    def rotary(n: int, gear_ratio, J_m, b_m=0.0, J_s=0.0, b_s=0.0) -> "Actuator":
        """A rotary gearbox (no ballscrew) on each of ``n`` joints."""
        v = lambda x, name: as_vector(x, name, n)  # noqa: E731
        return Actuator(gear_ratio=as_vector(gear_ratio, "gear_ratio", n, positive=True),
                        pitch=jnp.full((n,), 2 * jnp.pi), J_s=v(J_s, "J_s"), J_m=v(J_m, "J_m"),
                        b_s=v(b_s, "b_s"), b_m=v(b_m, "b_m"))


def yoshikawa(J: Array) -> Array:
    """Yoshikawa's manipulability of a (d, n) Jacobian: the product of its singular
    values, ``sqrt(det(J J^T))`` where d <= n and ``sqrt(det(J^T J))`` where the arm has
    fewer joints than task coordinates (``J J^T`` is singular everywhere there); 0 at a
    singularity, with a zero gradient there (not the NaN of ``sqrt`` at 0)."""
    G = J @ J.T if J.shape[-2] <= J.shape[-1] else J.T @ J
    det = _linalg.det(G)
    regular = det > 0
    return jnp.where(regular, jnp.sqrt(jnp.where(regular, det, 1.0)), 0.0)


class Robot(eqx.Module):
    """Base class: a robot is its kinematics and its energies.

    Subclasses implement :meth:`forward_kinematics`, :meth:`kinetic_energy` and
    :meth:`potential_energy`, and set the ``limits`` field. They may override
    :meth:`rigid_body_forces` with a faster formulation (e.g. recursive Newton-Euler),
    which must then be tested against the Lagrangian one, and
    :meth:`generalized_to_actuator` for robots whose actuated joints are not the
    generalised coordinates (parallel robots). :meth:`inverse_dynamics` must stay affine
    in the acceleration (``M(q) qdd + b(q, qd)`` mapped linearly to the actuators), as
    every rigid-body model is: the solver's stage Hessians rely on it (tested for every
    built-in robot).
    """

    limits: Limits
    friction: Friction | None
    actuator: Actuator | None

    # ----- what a robot must provide -------------------------------------------------
    @property
    def n(self) -> int:
        """Number of degrees of freedom (length of q)."""
        raise NotImplementedError

    @property
    def n_actuators(self) -> int:
        """Number of actuators (length of tau); ``n`` unless the robot is redundantly
        actuated or under-actuated."""
        return self.n

    @property
    def name(self) -> str:
        return type(self).__name__

    def forward_kinematics(self, q: Vec) -> Array:
        """Task point p(q), shape (d,)."""
        raise NotImplementedError

    def kinetic_energy(self, q: Vec, qd: Vec) -> Array:
        """Kinetic energy T(q, qd) [J] of the mechanism (actuators excluded)."""
        raise NotImplementedError

    def potential_energy(self, q: Vec) -> Array:
        """Potential energy V(q) [J]."""
        raise NotImplementedError

    # ----- kinematics ---------------------------------------------------------------
    def jacobian(self, q: Vec) -> Array:
        """Task Jacobian dp/dq, shape (d, n)."""
        return jax.jacfwd(self.forward_kinematics)(q)

    def manipulability(self, q: Vec) -> Array:
        """Yoshikawa's manipulability of the task Jacobian (:func:`yoshikawa`); 0 at
        singular configurations."""
        return yoshikawa(self.jacobian(q))

    # ----- Lagrangian dynamics ------------------------------------------------------
    def _mass_matrix_mechanism(self, q: Vec) -> Array:
        dT = jax.grad(self.kinetic_energy, argnums=1)
        return jax.jacfwd(dT, argnums=1)(q, jnp.zeros_like(q))

    def coriolis(self, q: Vec, qd: Vec) -> Vec:
        """Coriolis and centrifugal vector c(q, qd) = C(q, qd) qd."""
        dT_dqd = lambda q_: jax.grad(self.kinetic_energy, argnums=1)(q_, qd)  # noqa: E731
        _, Mdot_qd = jax.jvp(dT_dqd, (q,), (qd,))
        return Mdot_qd - jax.grad(self.kinetic_energy, argnums=0)(q, qd)

    def coriolis_matrix(self, q: Vec, qd: Vec) -> Array:
        """A Coriolis matrix C(q, qd) with C qd = c and dM/dt - 2C skew-symmetric
        (Christoffel symbols of the first kind)."""
        dM = jax.jacfwd(self._mass_matrix_mechanism)(q)  # dM[i, j, k] = d M_ij / d q_k
        christoffel = 0.5 * (dM + jnp.swapaxes(dM, 1, 2) - jnp.transpose(dM, (2, 0, 1)))
        # christoffel[i, j, k] = 1/2 (dM_ij/dq_k + dM_ik/dq_j - dM_jk/dq_i)
        return christoffel @ qd

    def gravity(self, q: Vec) -> Vec:
        """Gravity vector g(q) = dV/dq."""
        return jax.grad(self.potential_energy)(q)

    def _drive_damping(self, qd: Vec) -> Vec:
        """Friction and actuator damping, as generalised (joint-side) efforts."""
        f = jnp.zeros_like(qd)
        if self.friction is not None:
            f = f + self.friction(qd)
        if self.actuator is not None:
            f = f + self.actuator.V_a / self.actuator.K_a * qd
        return f

    def _reflected_inertia(self) -> Vec | None:
        if self.actuator is None:
            return None
        return self.actuator.M_a / self.actuator.K_a

    def mass_matrix(self, q: Vec) -> Array:
        """Joint-space inertia matrix M(q), (n, n), actuator inertia included."""
        M = self._mass_matrix_mechanism(q)
        refl = self._reflected_inertia()
        return M if refl is None else M + jnp.diag(refl)

    def bias(self, q: Vec, qd: Vec) -> Vec:
        """Everything but inertia: Coriolis/centrifugal + gravity + friction + actuator
        damping, as generalised efforts (n,)."""
        return self.coriolis(q, qd) + self.gravity(q) + self._drive_damping(qd)

    def rigid_body_forces(self, q: Vec, qd: Vec, qdd: Vec) -> Vec:
        """Mechanism-only generalised forces M(q) qdd + c(q, qd) + g(q)."""
        return self._mass_matrix_mechanism(q) @ qdd + self.coriolis(q, qd) + self.gravity(q)

    def generalized_forces(self, q: Vec, qd: Vec, qdd: Vec) -> Vec:
        """Generalised efforts needed for the motion, drives included (n,)."""
        Q = self.rigid_body_forces(q, qd, qdd) + self._drive_damping(qd)
        refl = self._reflected_inertia()
        return Q if refl is None else Q + refl * qdd

    def generalized_to_actuator(self, q: Vec, Q: Vec) -> Vec:
        """Map generalised efforts to actuator efforts (identity for serial arms; motor
        torques ``K_a * Q`` with an actuator model)."""
        return Q if self.actuator is None else self.actuator.K_a * Q

    def actuator_to_generalized(self, q: Vec, tau: Vec) -> Vec:
        """Inverse of :meth:`generalized_to_actuator`."""
        return tau if self.actuator is None else tau / self.actuator.K_a

    def inverse_dynamics(self, q: Vec, qd: Vec, qdd: Vec) -> Vec:
        """Actuator efforts tau (n,) producing acceleration qdd at state (q, qd).

        A nested jit (:func:`_inverse_dynamics`): traced once per robot type and argument
        shapes, however many places of a program evaluate it (a solver program does at
        dozens, under vmap, jvp and grad). XLA inlines it, so the compiled program is
        the same; serial3's single-solve program traces and lowers in about 5.2 instead
        of 7.7 s (its persistent-cache hits too). Override :meth:`generalized_forces`
        or :meth:`rigid_body_forces` rather than this."""
        return _inverse_dynamics(self, q, qd, qdd)

    def forward_dynamics(self, q: Vec, qd: Vec, tau: Vec) -> Vec:
        """Acceleration qdd (n,) produced by actuator efforts tau at state (q, qd).

        A nested jit like :meth:`inverse_dynamics` (:func:`_forward_dynamics`): serial3's
        coupled single-solve program (N = 10) traces and lowers in about 11 instead of 26 s
        (compiled in 79 s either way)."""
        return _forward_dynamics(self, q, qd, tau)

    def energy(self, q: Vec, qd: Vec) -> Array:
        """Total mechanical energy (mechanism + reflected actuator inertia)."""
        E = self.kinetic_energy(q, qd) + self.potential_energy(q)
        refl = self._reflected_inertia()
        return E if refl is None else E + 0.5 * jnp.sum(refl * qd**2)

    # ----- conveniences -------------------------------------------------------------
    def check_q(self, q: Any, name: str = "q") -> Array:
        """Validate a configuration vector (shape (n,) or (..., n), finite)."""
        return check_state(q, name, self.n)

    def replace(self, **changes) -> "Robot":
        """A copy with some fields replaced (see :func:`jtraj.robots.get` for validated
        parameter overrides)."""
        return dataclasses.replace(self, **changes)


@eqx.filter_jit
def _inverse_dynamics(robot: Robot, q: Vec, qd: Vec, qdd: Vec) -> Vec:
    return robot.generalized_to_actuator(q, robot.generalized_forces(q, qd, qdd))


@eqx.filter_jit
def _forward_dynamics(robot: Robot, q: Vec, qd: Vec, tau: Vec) -> Vec:
    Q = robot.actuator_to_generalized(q, tau)
    return _linalg.solve(robot.mass_matrix(q), Q - robot.bias(q, qd))
