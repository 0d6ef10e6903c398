"""``parallel3``: planar 2-DOF parallel robot with three two-link legs (Chettibi 7.2).

Three identical legs join at a common point C = (x, y). Leg i has its actuated
revolute joint at the base point ``B_i``, a first link of length L from ``B_i`` to the
elbow ``E_i``, a passive elbow, and a second link of length L from ``E_i`` to C, where
all three legs share a passive revolute joint. Two degrees of freedom, three actuators:
the robot is *redundantly actuated*.

**Generalised coordinates.** ``q = (x, y)``, the position of C [m]; it is also the task
point (``forward_kinematics(q) = q``). Each leg's configuration is a closed-form
function of C on the chosen branch, so q are independent coordinates of the closed
chain and the Lagrangian machinery of :class:`~jtraj.robots.Robot` applies:
with ``d_i = C - B_i``, ``rho_i = |d_i|``, ``alpha_i = atan2(d_i)``,
``beta_i = arccos(rho_i / (2 L))``::

    theta_i = alpha_i + s_i beta_i     (actuated joint = absolute angle of link 1)
    phi_i   = alpha_i - s_i beta_i     (absolute angle of link 2, isosceles triangle)

**Actuation.** ``J_a = d theta / dq`` (3, 2) and, by virtual work, the generalised
force of the actuator torques is ``Q = J_a^T tau``. Inverse dynamics returns the
minimum-norm torques ``tau = J_a (J_a^T J_a)^{-1} Q`` (with the three identical torque
limits this also minimises ``sum (tau_i / tau_max)^2``, the integrand of Chettibi's
cost); any internal preload ``tau + null(J_a^T)`` would produce the same motion.
``forward_dynamics`` accepts any tau of length 3.

**Assumptions (the base layout is not published).**

* Base points on a circle of radius 0.5 m centred at the origin, at angles 0, 120 and
  240 degrees. With it every point of the box [-0.5, 0.5]^2 is reachable by all three
  legs (largest ``rho / 2L`` = 0.998, at a corner) and the straight task
  (-0.3, 0.2) -> (0.3, -0.3) keeps ``rho / 2L`` in [0.20, 0.76].
* Branch: ``s_i = +1`` for all legs (each elbow lies counter-clockwise of the line
  from its base to C), kept fixed; it cannot change without passing a singularity.
* Horizontal plane (g = 0): with gravity each leg would need about 90 N m at its base
  joint to hold itself, far above the 25 N m limit.
* No mass at C (no payload), no friction, no actuator model.
* Link data (published): L = 0.6 m, m = 10 kg, centre of mass 0.3 m from the link's
  proximal joint, inertia 0.1 kg m^2 about the centre of mass.

**Singularities.** A leg is singular when stretched (``rho_i = 2L``, the actuator loses
control of C) or folded (``rho_i = 0``, C on the base point: the branch formula is not
differentiable there). The folded points lie inside the box (at the base points), so
:meth:`path_constraints` keeps ``rho_i / (2L)`` in ``[rho_min, rho_max]`` =
[0.05, 0.98] (assumed margins).

Limits: |tau_i| <= 25 N m; x, y in [-0.5, 0.5] m (joint box and workspace box);
|qd| <= 1 m/s, |qdd| <= 10 m/s^2 (loose, *assumed*: the torques decide);
h in [0.005, 0.1] s.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array

from .. import _linalg
from ._base import Limits, Robot, Vec


class Parallel3(Robot):
    """Redundantly actuated planar 3-leg parallel robot; see the module docstring."""

    link_length: float | Array
    link_mass: float | Array
    link_com: float | Array
    link_inertia: float | Array
    base: Array  # (3, 2) base points B_i
    gravity_accel: float | Array = 0.0
    rho_min: float | Array = 0.05
    rho_max: float | Array = 0.98

    #: units of the coordinates and of the actuator efforts (plots)
    coordinate_units = ("m", "m")
    effort_units = ("N m",) * 3

    @property
    def n(self) -> int:
        return 2

    @property
    def n_actuators(self) -> int:
        return 3

    @property
    def name(self) -> str:
        return "parallel3"

    # ----- kinematics -----------------------------------------------------------------
    def leg_angles(self, q: Vec) -> tuple[Array, Array]:
        """(theta, phi): absolute angles of the first and second links, each (3,)."""
        d = q[None, :] - self.base
        rho = jnp.sqrt(jnp.sum(d**2, axis=-1))
        alpha = jnp.arctan2(d[:, 1], d[:, 0])
        beta = jnp.arccos(rho / (2 * self.link_length))
        return alpha + beta, alpha - beta

    def actuated_coordinates(self, q: Vec) -> Array:
        """Actuated joint angles theta (3,) [rad]."""
        return self.leg_angles(q)[0]

    def actuator_jacobian(self, q: Vec) -> Array:
        """J_a = d theta / dq, (3, 2)."""
        return jax.jacfwd(self.actuated_coordinates)(q)

    def elbows(self, q: Vec) -> Array:
        """Elbow positions E_i, (3, 2)."""
        theta = self.actuated_coordinates(q)
        return self.base + self.link_length * jnp.stack([jnp.cos(theta), jnp.sin(theta)], axis=-1)

    def closure_residual(self, q: Vec, theta: Vec) -> Array:
        """``|C - E_i(theta_i)|^2 - L^2`` for each leg, (3,): zero when the legs close."""
        E = self.base + self.link_length * jnp.stack([jnp.cos(theta), jnp.sin(theta)], axis=-1)
        return jnp.sum((q[None, :] - E) ** 2, axis=-1) - self.link_length**2

    def leg_ratios(self, q: Vec) -> Array:
        """``rho_i / (2 L)`` (3,): 0 folded, 1 stretched."""
        return jnp.sqrt(jnp.sum((q[None, :] - self.base) ** 2, axis=-1)) / (2 * self.link_length)

    def assembly_margin(self, q: Vec) -> Array:
        """``min_i (1 - rho_i / 2L)``: > 0 where every leg reaches C."""
        return jnp.min(1.0 - self.leg_ratios(q))

    def forward_kinematics(self, q: Vec) -> Array:
        """The common point C = (x, y) (the generalised coordinates)."""
        return jnp.asarray(q)

    def manipulability(self, q: Vec) -> Array:
        """Manipulability of the actuator-to-C map ``qd = pinv(J_a) theta_d``:
        ``1 / sqrt(det(J_a^T J_a))`` (dp/dq is the identity here)."""
        Ja = self.actuator_jacobian(q)
        return 1.0 / jnp.sqrt(_linalg.det(Ja.T @ Ja))

    def path_constraints(self, q: Vec) -> Array:
        """Leg-singularity margins as normalised inequalities g <= 0, (6,):
        ``1 - rho_i/(2L rho_min)`` and ``rho_i/(2L rho_max) - 1``."""
        s = self.leg_ratios(q)
        return jnp.concatenate([1.0 - s / self.rho_min, s / self.rho_max - 1.0])

    # ----- energies -------------------------------------------------------------------
    def _link_state(self, q):
        theta, phi = self.leg_angles(q)
        E = self.base + self.link_length * jnp.stack([jnp.cos(theta), jnp.sin(theta)], axis=-1)
        G1 = self.base + self.link_com * jnp.stack([jnp.cos(theta), jnp.sin(theta)], axis=-1)
        G2 = E + self.link_com * jnp.stack([jnp.cos(phi), jnp.sin(phi)], axis=-1)
        return theta, phi, G1, G2

    def kinetic_energy(self, q: Vec, qd: Vec) -> Array:
        _, (w1, w2, v1, v2) = jax.jvp(self._link_state, (q,), (qd,))
        m, I = self.link_mass, self.link_inertia
        return 0.5 * m * (jnp.sum(v1**2) + jnp.sum(v2**2)) + 0.5 * I * (jnp.sum(w1**2) + jnp.sum(w2**2))

    def potential_energy(self, q: Vec) -> Array:
        _, _, G1, G2 = self._link_state(q)
        return self.gravity_accel * self.link_mass * (jnp.sum(G1[:, 1]) + jnp.sum(G2[:, 1]))

    # ----- actuation ------------------------------------------------------------------
    def generalized_to_actuator(self, q: Vec, Q: Vec) -> Vec:
        """Minimum-norm actuator torques (3,) with ``J_a^T tau = Q``."""
        Ja = self.actuator_jacobian(q)
        return Ja @ _linalg.solve(Ja.T @ Ja, Q)

    def actuator_to_generalized(self, q: Vec, tau: Vec) -> Vec:
        """Generalised force of actuator torques by virtual work: ``J_a^T tau``."""
        return self.actuator_jacobian(q).T @ tau


def parallel3() -> Parallel3:
    """Chettibi's planar parallel robot with three two-link legs, redundantly actuated (Chettibi 7.2).

    The base layout (an equilateral triangle of circumradius 0.5 m) is assumed."""
    ang = jnp.deg2rad(jnp.array([0.0, 120.0, 240.0]))
    base = 0.5 * jnp.stack([jnp.cos(ang), jnp.sin(ang)], axis=-1)
    lim = Limits.make(2, q_min=(-0.5, -0.5), q_max=(0.5, 0.5), qd_max=1.0, qdd_max=10.0,
                      tau_max=(25.0, 25.0, 25.0), h_min=0.005, h_max=0.1,
                      workspace=[[-0.5, -0.5], [0.5, 0.5]], n_actuators=3)
    return Parallel3(limits=lim, friction=None, actuator=None, link_length=0.6, link_mass=10.0,
                     link_com=0.3, link_inertia=0.1, base=base)
