"""``pkm2``: planar 2-DOF translational parallel manipulator (Khoukhi ch. 4, annex B;
after Liu, Wang & Wang 2004).

Geometry (all in one plane, SI units)::

      slider 1 (y1)                               slider 2 (y2)
      guide x = -R  |                             |  guide x = +R
                    A1 = (-R, y1)     A2 = (+R, y2)
                      \\   leg 1 (length L)    /  leg 2
                       \\                     /
                        B1 ---- P=(x,y) ---- B2      platform, half-width r,
                        (x - r, y)     (x + r, y)    constant orientation

Two sliders move along vertical guides at ``x = -R`` and ``x = +R`` (the actuated
prismatic joints, efforts ``tau = (f1, f2)`` [N]). Each slider carries a parallelogram
leg of length L whose far end is pinned to the platform at ``B_i``. The parallelograms
keep the platform's orientation constant, so the platform only translates. Loop
closure of leg i::

    (x -+ (R - r))^2 + (y - y_i)^2 = L^2        (- for leg 1, + for leg 2 written as
                                                 (x + (R - r)) and (x - (R - r)))

**Generalised coordinates.** ``q = (x, y)``, the position of the platform's reference
point P (midway between the leg pins) [m]. Given q the slider positions follow in
closed form (one branch, see below), so q is a set of independent coordinates of the
closed chain; the Lagrangian machinery of :class:`~jtraj.robots.Robot` applies
unchanged and :meth:`generalized_to_actuator` maps generalised forces to slider forces
by virtual work (``Q = J_a^T tau``, ``J_a = d(y1, y2)/dq``). The task point is P, so
``forward_kinematics(q) = q`` and the joint box coincides with the workspace box.

**Branch (assumption).** The platform hangs *below* both sliders::

    y_i = y + sqrt(L^2 - (x -+ (R - r))^2)

This is consistent with the thesis' workspace (y in [-1.72, -0.72] m puts the sliders
near y in [-0.1, 0.9] m). On this branch the two legs are never parallel, so there is
no type-2 (direct kinematic) singularity anywhere; the type-1 singularity (a leg
perpendicular to its guide, ``y_i = y``) lies at ``|x| = L - (R - r) = 0.8445`` m,
just outside the workspace box ``|x| <= 0.8`` m.

**Dynamics from energies** (the printed eq. 70 of the thesis is garbled):

* platform: ``T_p = m_p/2 (xd^2 + yd^2)``;
* sliders: ``T_s = m_s/2 (y1d^2 + y2d^2)``;
* legs: each parallelogram is modelled as a uniform bar of the total leg mass ``m_l``
  from ``A_i`` to ``B_i`` (the two parallel bars move identically, so their combined
  kinetic energy is that of one bar with the total mass):
  ``T_l = m_l/2 |v_centre|^2 + (m_l L^2 / 12)/2 omega^2``;
* potential: gravity ``g`` along -y (default 0, see below).

**Parameters (assumptions marked).** Chapter 4 values: platform 200 kg, each leg
570.5 kg, each slider 100 kg (annex B prints 575 kg and 60 kg; override with
``get("pkm2", leg_mass=575.0, slider_mass=60.0)``); r = 0.075 m, R = 1.203 m,
L = 1.9725 m. *Assumed*: the mechanism works in a horizontal plane (g = 0): with
gravity along the guides each slider would need about 2.8 kN just to hold the
machine, five times the published force limits. No friction, no actuator model.

**Limits** (Table 4.1): x in [-0.8, 0.8] m, y in [-1.72, -0.72] m (joint box and
workspace box); |f1| <= 550 N, |f2| <= 700 N; |qd| <= 0.2 m/s and |qdd| <= 2 m/s^2 on
each platform coordinate (our reading of "v_max, a_max"); h in [0.005, 0.7] s.

**Singularities** (:meth:`singularities`), Gosselin-Angeles classification of
``A qd + B y_ad = 0`` with ``A = dPhi/dq``, ``B = dPhi/dy_a``:

* type 1 (inverse kinematic, ``det B = 0``): a leg perpendicular to its guide;
* type 2 (direct kinematic, ``det A = 0``): the two legs parallel;
* type 3 (combined): both at once (only for special geometries, ``R - r = L``).

:meth:`path_constraints` adds the thesis' singularity distances
``|(y - y1)(y - y2)| >= eps1`` and ``|x + sgn(x)(r - R)| >= eps2`` (eps1 = 0.05 m^2,
eps2 = 0.05 m: *assumed*, unpublished; both inactive inside the workspace box).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from .. import _linalg
from ._base import Limits, Robot, Vec


class PKMSingularities(NamedTuple):
    """Singularity measures of ``pkm2``, each dimensionless and zero at the singularity.

    type1: ``(y1 - y)(y2 - y) / L^2`` = product of the sines of the legs' angles with
        the horizontal (det B up to a factor); 0 when a leg is perpendicular to its guide.
    type2: ``sin`` of the angle between the two legs (det A / (4 L^2)); 0 when the legs
        are parallel.
    type3: ``max(|type1|, |type2|)``; 0 only where both vanish together.
    """

    type1: Array
    type2: Array
    type3: Array


class PKM2(Robot):
    """Planar 2-DOF translational parallel manipulator; see the module docstring."""

    platform_mass: float | Array
    slider_mass: float | Array
    leg_mass: float | Array
    R: float | Array
    r: float | Array
    L: float | Array
    gravity_accel: float | Array = 0.0
    eps1: float | Array = 0.05
    eps2: float | Array = 0.05

    #: units of the coordinates and of the actuator efforts (plots)
    coordinate_units = ("m", "m")
    effort_units = ("N", "N")

    @property
    def n(self) -> int:
        return 2

    @property
    def name(self) -> str:
        return "pkm2"

    # ----- kinematics -----------------------------------------------------------------
    def _leg_dx(self, q):
        """Horizontal offsets of the legs, (x + (R - r), x - (R - r))."""
        off = self.R - self.r
        return jnp.stack([q[0] + off, q[0] - off])

    def actuated_coordinates(self, q: Vec) -> Array:
        """Slider positions (y1, y2) [m] on the chosen branch (platform below sliders)."""
        dx = self._leg_dx(q)
        return q[1] + jnp.sqrt(self.L**2 - dx**2)

    def actuator_jacobian(self, q: Vec) -> Array:
        """J_a = d(y1, y2)/d(x, y), (2, 2): slider velocities = J_a qd."""
        return jax.jacfwd(self.actuated_coordinates)(q)

    def closure_residual(self, q: Vec, y_a: Vec) -> Array:
        """Loop-closure equations ``(x -+ (R - r))^2 + (y - y_i)^2 - L^2``, (2,)."""
        return self._leg_dx(q) ** 2 + (q[1] - y_a) ** 2 - self.L**2

    def leg_endpoints(self, q: Vec) -> tuple[Array, Array]:
        """(A, B): slider pins A_i and platform pins B_i, each (2, 2) with row i = leg i."""
        y_a = self.actuated_coordinates(q)
        A = jnp.stack([jnp.stack([-self.R, y_a[0]]), jnp.stack([self.R, y_a[1]])])
        B = jnp.stack([jnp.stack([q[0] - self.r, q[1]]), jnp.stack([q[0] + self.r, q[1]])])
        return A, B

    def forward_kinematics(self, q: Vec) -> Array:
        """Platform reference point P = (x, y) (the generalised coordinates)."""
        return jnp.asarray(q)

    def assembly_margin(self, q: Vec) -> Array:
        """``min_i (L^2 - (x -+ (R - r))^2) / L^2``: > 0 where both legs can close."""
        return jnp.min(self.L**2 - self._leg_dx(q) ** 2) / self.L**2

    def manipulability(self, q: Vec) -> Array:
        """Manipulability of the actuator-to-platform map ``qd = J_a^{-1} y_ad``:
        ``sqrt(det(J_a^{-1} J_a^{-T})) = 1 / |det J_a|``; tends to 0 at type-1
        singularities (the task Jacobian dp/dq is the identity, so the base-class
        measure would carry no information)."""
        return 1.0 / jnp.abs(_linalg.det(self.actuator_jacobian(q)))

    def singularities(self, q: Vec) -> PKMSingularities:
        """Type-1/2/3 singularity measures at q (see :class:`PKMSingularities`)."""
        A, B = self.leg_endpoints(q)
        u = (B - A) / self.L  # unit leg vectors, slider -> platform
        t1 = u[0, 1] * u[1, 1]
        t2 = u[0, 0] * u[1, 1] - u[0, 1] * u[1, 0]
        return PKMSingularities(type1=t1, type2=t2, type3=jnp.maximum(jnp.abs(t1), jnp.abs(t2)))

    def path_constraints(self, q: Vec) -> Array:
        """Thesis singularity distances as normalised inequalities g <= 0, (2,):
        ``1 - |(y - y1)(y - y2)| / eps1`` and ``1 - ||x| - (R - r)| / eps2``."""
        y_a = self.actuated_coordinates(q)
        d1 = jnp.abs((q[1] - y_a[0]) * (q[1] - y_a[1]))
        d2 = jnp.abs(jnp.abs(q[0]) - (self.R - self.r))
        return jnp.stack([1.0 - d1 / self.eps1, 1.0 - d2 / self.eps2])

    # ----- energies -------------------------------------------------------------------
    def kinetic_energy(self, q: Vec, qd: Vec) -> Array:
        (A, B), (Ad, Bd) = jax.jvp(self.leg_endpoints, (q,), (qd,))
        vc = 0.5 * (Ad + Bd)  # leg centres
        rel, reld = B - A, Bd - Ad
        omega = (rel[:, 0] * reld[:, 1] - rel[:, 1] * reld[:, 0]) / self.L**2
        T_legs = 0.5 * self.leg_mass * jnp.sum(vc**2) + 0.5 * (self.leg_mass * self.L**2 / 12) * jnp.sum(omega**2)
        T_platform = 0.5 * self.platform_mass * jnp.sum(qd**2)
        T_sliders = 0.5 * self.slider_mass * jnp.sum(Ad[:, 1] ** 2)
        return T_platform + T_sliders + T_legs

    def potential_energy(self, q: Vec) -> Array:
        A, B = self.leg_endpoints(q)
        h = (self.platform_mass * q[1] + self.slider_mass * jnp.sum(A[:, 1])
             + self.leg_mass * 0.5 * jnp.sum(A[:, 1] + B[:, 1]))
        return self.gravity_accel * h

    # ----- actuation ------------------------------------------------------------------
    def generalized_to_actuator(self, q: Vec, Q: Vec) -> Vec:
        """Slider forces from generalised forces: solve ``J_a^T tau = Q``."""
        return _linalg.solve(self.actuator_jacobian(q).T, Q)

    def actuator_to_generalized(self, q: Vec, tau: Vec) -> Vec:
        """Generalised forces of slider forces by virtual work: ``Q = J_a^T tau``."""
        return self.actuator_jacobian(q).T @ tau


def pkm2() -> PKM2:
    """The thesis' planar translational parallel manipulator on two sliders (Khoukhi ch. 4).

    Chapter 4's parameters; the module docstring describes the model."""
    lim = Limits.make(2, q_min=(-0.8, -1.72), q_max=(0.8, -0.72), qd_max=0.2, qdd_max=2.0,
                      tau_max=(550.0, 700.0), h_min=0.005, h_max=0.7,
                      workspace=[[-0.8, -1.72], [0.8, -0.72]])
    return PKM2(limits=lim, friction=None, actuator=None, platform_mass=200.0, slider_mass=100.0,
                leg_mass=570.5, R=1.203, r=0.075, L=1.9725)
