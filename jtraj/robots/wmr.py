"""``wmr``: two-wheel differential-drive mobile robot (Chettibi example 3; Yamamoto 1999).

**Generalised coordinates.** ``q = (x, y, theta)``: the position of the midpoint of
the wheel axle [m] and the heading [rad]. The task point is the chassis position
``forward_kinematics(q) = (x, y)``. Actuators: the two wheel torques
``tau = (tau_R, tau_L)`` [N m] (``n_actuators = 2 < n = 3``).

**Nonholonomic constraint** (no lateral slip)::

    A(q) qd = -xd sin(theta) + yd cos(theta) = 0

It cannot be integrated into the coordinates (the pose is not a function of the wheel
angles), so it is handled by a Lagrange multiplier (Lagrange-d'Alembert):

* kinetic energy ``T = m/2 (xd^2 + yd^2) + I/2 thetad^2 + J_w/2 (phid_R^2 + phid_L^2)``
  with the wheel spin rates written through the rolling constraints
  ``phid_R,L = (v +- b thetad) / r_w``, ``v = xd cos(theta) + yd sin(theta)``,
  ``b = track / 2``. M, C, G then come from the Robot base by autodiff;
* wheel torques act through ``Q = E(q) tau``,
  ``E = [[c, c], [s, s], [b, -b]] / r_w`` (virtual work of the wheel rotations);
* :meth:`forward_dynamics` solves ``M qdd + bias = E tau + A^T lambda``,
  ``A qdd = thetad v`` (the time derivative of the constraint), so trajectories that
  start admissible stay admissible;
* :meth:`inverse_dynamics` returns the wheel torques of the unique split
  ``Q = E tau + A^T lambda`` of the required generalised force (the lateral part is
  carried by the ground);
* :meth:`path_equalities` returns the normalised lateral velocity, which the
  transcriptions impose at every sample (the discrete recursion does not preserve
  the constraint exactly between samples).

On admissible states these equations coincide with the reduced (quasi-velocity)
equations ``(m + 2 J_w / r_w^2) vd = (tau_R + tau_L) / r_w`` and
``(I + 2 J_w b^2 / r_w^2) omegad = b (tau_R - tau_L) / r_w`` (tested).

**Assumptions (parameters are not published).** Centre of mass on the axle midpoint;
chassis mass 50 kg (wheels included), yaw inertia 2.5 kg m^2, wheel radius 0.1 m,
track 0.5 m, wheel spin inertia 0.005 kg m^2; no friction. With |tau| <= 1 N m the
straight 28 m diagonal then takes about 17 s bang-bang, the order of the published
17.8-18.9 s; absolute times are not comparable with the literature.
Floor 24 m x 24 m (workspace box ``[0, 24]^2`` on (x, y)). Three circular obstacles
(layout not published, *assumed*) as ``(cx, cy, radius)`` rows of ``obstacles``:
(8, 8.5, 2.0), (14, 13, 2.0), (18.5, 19.5, 1.5), all crossing or touching the straight
line (3, 3) -> (23, 23); the chassis is a disc of radius ``body_radius`` = 0.3 m.
:meth:`path_constraints` keeps it clear of them. Other limits (*assumed*): |qd| <=
(2 m/s, 2 m/s, 2 rad/s), |qdd| <= (0.5 m/s^2, 0.5 m/s^2, 2.5 rad/s^2) (slightly looser
than the torque limits allow), h in [0.05, 2.0] s.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array

from .. import _linalg
from ._base import Limits, Robot, Vec


class WMR(Robot):
    """Differential-drive mobile robot; see the module docstring."""

    mass: float | Array
    inertia: float | Array
    wheel_radius: float | Array
    track: float | Array
    wheel_inertia: float | Array
    body_radius: float | Array
    obstacles: Array  # (k, 3): cx, cy, radius

    #: units of the coordinates and of the actuator efforts (plots)
    coordinate_units = ("m", "m", "rad")
    effort_units = ("N m", "N m")

    @property
    def n(self) -> int:
        return 3

    @property
    def n_actuators(self) -> int:
        return 2

    @property
    def name(self) -> str:
        return "wmr"

    # ----- kinematics -----------------------------------------------------------------
    def forward_kinematics(self, q: Vec) -> Array:
        """Chassis position (x, y) [m]."""
        return q[:2]

    def constraint_matrix(self, q: Vec) -> Array:
        """A(q) (1, 3) of the no-slip constraint ``A qd = 0``."""
        return jnp.stack([-jnp.sin(q[2]), jnp.cos(q[2]), jnp.zeros(())])[None, :]

    def input_matrix(self, q: Vec) -> Array:
        """E(q) (3, 2): generalised force of the wheel torques, ``Q = E tau``."""
        c, s, b = jnp.cos(q[2]), jnp.sin(q[2]), 0.5 * self.track
        return jnp.stack([jnp.stack([c, c]), jnp.stack([s, s]), jnp.stack([b, -b])]) / self.wheel_radius

    def admissible_velocity(self, q: Vec, nu: Vec) -> Array:
        """qd (3,) of forward speed and yaw rate ``nu = (v, omega)``; satisfies A qd = 0."""
        return jnp.stack([nu[0] * jnp.cos(q[2]), nu[0] * jnp.sin(q[2]), nu[1]])

    def wheel_rates(self, q: Vec, qd: Vec) -> Array:
        """Wheel spin rates (phid_R, phid_L) [rad/s] from the rolling constraints."""
        v = qd[0] * jnp.cos(q[2]) + qd[1] * jnp.sin(q[2])
        b = 0.5 * self.track
        return jnp.stack([v + b * qd[2], v - b * qd[2]]) / self.wheel_radius

    def path_equalities(self, q: Vec, qd: Vec) -> Array:
        """Lateral velocity over the speed limit (1,): zero when the wheels do not slip."""
        scale = 1.0 if self.limits.qd_max is None else self.limits.qd_max[0]
        return (self.constraint_matrix(q) @ qd) / scale

    def path_constraints(self, q: Vec) -> Array:
        """Obstacle clearance, normalised g <= 0 (k,): ``1 - |p - c_j| / (R_j + body)``."""
        d = jnp.sqrt(jnp.sum((q[None, :2] - self.obstacles[:, :2]) ** 2, axis=-1))
        return 1.0 - d / (self.obstacles[:, 2] + self.body_radius)

    # ----- energies -------------------------------------------------------------------
    def kinetic_energy(self, q: Vec, qd: Vec) -> Array:
        w = self.wheel_rates(q, qd)
        return (0.5 * self.mass * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * self.inertia * qd[2] ** 2
                + 0.5 * self.wheel_inertia * jnp.sum(w**2))

    def potential_energy(self, q: Vec) -> Array:
        return jnp.zeros((), dtype=jnp.result_type(q))

    # ----- actuation and constrained dynamics -----------------------------------------
    def generalized_to_actuator(self, q: Vec, Q: Vec) -> Vec:
        """Wheel torques of the split ``Q = E tau + A^T lambda`` (2,)."""
        EA = jnp.concatenate([self.input_matrix(q), self.constraint_matrix(q).T], axis=1)
        return _linalg.solve(EA, Q)[:2]

    def actuator_to_generalized(self, q: Vec, tau: Vec) -> Vec:
        """``E(q) tau`` (the constraint force is added in :meth:`forward_dynamics`)."""
        return self.input_matrix(q) @ tau

    def constraint_force(self, q: Vec, qd: Vec, tau: Vec) -> Array:
        """Multiplier lambda (1,) [N] of the lateral ground force during forward dynamics."""
        return self._constrained(q, qd, tau)[1]

    def _constrained(self, q, qd, tau):
        M = self.mass_matrix(q)
        A = self.constraint_matrix(q)
        v = qd[0] * jnp.cos(q[2]) + qd[1] * jnp.sin(q[2])
        rhs = jnp.concatenate([self.actuator_to_generalized(q, tau) - self.bias(q, qd),
                               (qd[2] * v)[None]])
        K = jnp.block([[M, -A.T], [A, jnp.zeros((1, 1))]])
        sol = _linalg.solve(K, rhs)
        return sol[:3], sol[3:]

    def forward_dynamics(self, q: Vec, qd: Vec, tau: Vec) -> Vec:
        """qdd (3,) under wheel torques tau (2,) with the no-slip constraint enforced."""
        return self._constrained(q, qd, tau)[0]


def wmr() -> WMR:
    """A differential-drive mobile robot among three circular obstacles (Chettibi, example 3).

    Its mass, inertias, wheel geometry and obstacles are assumed."""
    lim = Limits.make(3, qd_max=(2.0, 2.0, 2.0), qdd_max=(0.5, 0.5, 2.5), tau_max=(1.0, 1.0),
                      h_min=0.05, h_max=2.0, workspace=[[0.0, 0.0], [24.0, 24.0]], n_actuators=2)
    obstacles = jnp.array([[8.0, 8.5, 2.0], [14.0, 13.0, 2.0], [18.5, 19.5, 1.5]])
    return WMR(limits=lim, friction=None, actuator=None, mass=50.0, inertia=2.5, wheel_radius=0.1,
               track=0.5, wheel_inertia=0.005, body_radius=0.3, obstacles=obstacles)
