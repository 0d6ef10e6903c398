"""``gough_stewart``: the 6-DOF Gough-Stewart platform (Khoukhi ch. 4, general model).

Six prismatic legs join base points ``a_i`` (universal joints, fixed in the world frame)
to platform points ``b_i`` (spherical joints, fixed in the platform frame). SI units.

**Generalised coordinates.** The platform pose ``q = (x, y, z, phi, theta, psi)``:
position ``p = (x, y, z)`` [m] of the platform frame's origin (also its centre of mass
and the task point) and roll-pitch-yaw angles [rad] with

    R(phi, theta, psi) = Rz(psi) Ry(theta) Rx(phi)

(rotations about the fixed x, then y, then z axes). The world angular velocity is
``omega = E(q) (phid, thetad, psid)`` with the columns
``E = [Rz(psi) Ry(theta) e_x, Rz(psi) e_y, e_z]`` and ``det E = cos(theta)``: the
convention is singular at ``theta = +-pi/2`` (gimbal lock). The joint box keeps every
angle within +-0.5 rad, far from it.

**Inverse kinematics** (closed form): leg vectors ``d_i = p + R b_i - a_i``, lengths
``rho_i = |d_i|`` (the actuated coordinates), unit vectors ``u_i = d_i / rho_i``.
**Leg Jacobian** ``J = d rho / d q`` (6 x 6), row i::

    J_i = [ u_i^T ,  ((R b_i) x u_i)^T E(q) ]

so that ``rhod = J qd``. By virtual work the generalised force of the leg forces is
``Q = J^T tau``; inverse dynamics returns ``tau = J^{-T} Q`` [N] (positive: the leg
pushes the platform away from the base).

**Singularities.** ``det J = 0`` (Gosselin-Angeles type 2, the platform gains a motion
that the legs do not see; with these Euler angles it also contains the gimbal lock,
``det J = det J_twist cos(theta)``). The measure is
``manipulability(q) = |det(J(q) D)| / |det(J(q_0) D)|`` with
``D = diag(1, 1, 1, 1/r, 1/r, 1/r)`` (the angle columns in metres of platform rim, so
that every entry is dimensionless) normalised to 1 at the home pose
``q_0 = (0, 0, z_home, 0, 0, 0)``; it is 0 at a singularity, and the solver's
singularity term ``1 / manipulability`` grows there. :meth:`path_constraints` keeps it
above ``det_min`` (0.2). For this layout the nearest known singularity of the
symmetric family is the platform turned by +-90 degrees about z (Fichter), well
outside ``|psi| <= 0.5`` rad.

**Legs.** Each leg is two slender axisymmetric bodies: a cylinder of mass ``cyl_mass``
hinged at ``a_i`` with its centre of mass ``cyl_com`` from ``a_i`` along ``u_i``, and a
piston of mass ``piston_mass`` sliding in it with its centre of mass ``piston_com``
from ``b_i`` (at ``a_i + (rho_i - piston_com) u_i``). Their inertias about the centre of
mass are ``cyl_inertia`` and ``piston_inertia`` for rotations perpendicular to the leg;
the moment about the leg's own axis is neglected (slender legs), so the spin that the
universal joint imposes about the axis carries no energy. The leg's perpendicular
angular velocity is ``u_i x ud_i`` (``|.| = |ud_i|``)::

    T_leg = 1/2 m_c cyl_com^2 |ud|^2 + 1/2 m_p |rhod u + (rho - piston_com) ud|^2
            + 1/2 (I_c + I_p) |ud|^2

**Platform.** Mass ``platform_mass``, inertia tensor ``platform_inertia`` (3 x 3, body
frame, about the centre of mass at ``p``): ``T_p = 1/2 m |pd|^2 + 1/2 w^T I w`` with
the body angular velocity ``w = vee(R^T Rd)``. Gravity ``gravity_accel`` along -z.

**Parameters (our choice; the thesis publishes none for this model).** Base radius
1.0 m, platform radius 0.5 m; base points in pairs at ``120 k +- 15`` degrees,
platform points at ``120 k +- 45`` degrees (k = 0, 1, 2), leg ``2k`` joining
``120 k - 15`` to ``120 k - 45`` and leg ``2k + 1`` joining ``120 k + 15`` to
``120 k + 45`` (the classic crossed layout); home height 1.0 m (legs 1.18 m).
Platform 50 kg, a uniform disc of radius 0.5 m (inertia diag(3.125, 3.125, 6.25)
kg m^2). Legs 5 kg each: cylinder 3 kg, 0.8 m long (centre of mass 0.4 m from the
base joint, 0.16 kg m^2), piston 2 kg, 0.8 m long (centre of mass 0.4 m from the
platform joint, 0.107 kg m^2). g = 9.81 m/s^2.

**Limits.** Platform box x, y in [-0.3, 0.3] m, z in [0.8, 1.3] m, angles in
[-0.5, 0.5] rad (joint box; the workspace box is the position part); leg lengths
``rho_i`` in [0.85, 1.6] m and leg speeds ``|rhod_i| <= 0.5`` m/s as path constraints;
leg forces ``|tau_i| <= 1500`` N (holding the platform at home takes about 120 N per
leg); ``|qd| <= 0.5`` m/s or rad/s and ``|qdd| <= 5`` m/s^2 or rad/s^2 on the pose
coordinates; h in [0.005, 0.1] s.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array

from .. import _linalg
from ._base import Limits, Robot, Vec


def rpy_matrix(angles: Array) -> Array:
    """``R = Rz(psi) Ry(theta) Rx(phi)`` for ``angles = (phi, theta, psi)``, (3, 3)."""
    phi, theta, psi = angles[0], angles[1], angles[2]
    cf, sf = jnp.cos(phi), jnp.sin(phi)
    ct, st = jnp.cos(theta), jnp.sin(theta)
    cp, sp = jnp.cos(psi), jnp.sin(psi)
    return jnp.stack([
        jnp.stack([cp * ct, cp * st * sf - sp * cf, cp * st * cf + sp * sf]),
        jnp.stack([sp * ct, sp * st * sf + cp * cf, sp * st * cf - cp * sf]),
        jnp.stack([-st, ct * sf, ct * cf]),
    ])


def rpy_rate_matrix(angles: Array) -> Array:
    """E with ``omega = E (phid, thetad, psid)`` (world frame), (3, 3); det E = cos(theta)."""
    _, theta, psi = angles[0], angles[1], angles[2]
    ct, st = jnp.cos(theta), jnp.sin(theta)
    cp, sp = jnp.cos(psi), jnp.sin(psi)
    zero, one = jnp.zeros_like(ct), jnp.ones_like(ct)
    return jnp.stack([
        jnp.stack([cp * ct, -sp, zero]),
        jnp.stack([sp * ct, cp, zero]),
        jnp.stack([-st, zero, one]),
    ])


class GoughStewart(Robot):
    """6-DOF Gough-Stewart platform; see the module docstring."""

    base_points: Array  # (6, 3) a_i, world frame [m]
    platform_points: Array  # (6, 3) b_i, platform frame [m]
    platform_mass: float | Array
    platform_inertia: Array  # (3, 3) body frame, about the centre of mass [kg m^2]
    cyl_mass: float | Array
    cyl_com: float | Array
    cyl_inertia: float | Array
    piston_mass: float | Array
    piston_com: float | Array
    piston_inertia: float | Array
    platform_radius: float | Array
    z_home: float | Array
    gravity_accel: float | Array = 9.81
    rho_min: float | Array = 0.85
    rho_max: float | Array = 1.6
    rhod_max: float | Array = 0.5
    det_min: float | Array = 0.2

    #: units of the coordinates (x, y, z, roll, pitch, yaw) and of the efforts (leg forces)
    coordinate_units = ("m", "m", "m", "rad", "rad", "rad")
    effort_units = ("N",) * 6

    @property
    def n(self) -> int:
        return 6

    @property
    def name(self) -> str:
        return "gough_stewart"

    # ----- kinematics -----------------------------------------------------------------
    def rotation(self, q: Vec) -> Array:
        """Platform orientation R(q), (3, 3) (roll-pitch-yaw, see the module docstring)."""
        return rpy_matrix(q[3:6])

    def forward_kinematics(self, q: Vec) -> Array:
        """Task point: the platform position p = (x, y, z) [m]."""
        return jnp.asarray(q)[:3]

    def leg_vectors(self, q: Vec) -> Array:
        """``d_i = p + R b_i - a_i``, (6, 3)."""
        return q[None, :3] + self.platform_points @ self.rotation(q).T - self.base_points

    def leg_lengths(self, q: Vec) -> Array:
        """Closed-form inverse kinematics: leg lengths rho_i [m], (6,)."""
        return jnp.sqrt(jnp.sum(self.leg_vectors(q) ** 2, axis=-1))

    def actuated_coordinates(self, q: Vec) -> Array:
        """The actuated joint positions: the leg lengths (6,) [m]."""
        return self.leg_lengths(q)

    def actuator_jacobian(self, q: Vec) -> Array:
        """Leg Jacobian J = d rho / d q (6, 6): ``rhod = J qd`` (closed form, see the
        module docstring)."""
        d = self.leg_vectors(q)
        u = d / jnp.sqrt(jnp.sum(d**2, axis=-1, keepdims=True))
        Rb = self.platform_points @ self.rotation(q).T
        return jnp.concatenate([u, jnp.cross(Rb, u) @ rpy_rate_matrix(q[3:6])], axis=1)

    def _scaled_det(self, q: Vec) -> Array:
        s = jnp.concatenate([jnp.ones(3), jnp.full(3, 1.0 / self.platform_radius)])
        return _linalg.det(self.actuator_jacobian(q) * s[None, :])

    def manipulability(self, q: Vec) -> Array:
        """``|det(J D)| / |det(J(q_0) D)|``: 1 at home, 0 at a singularity (see the module
        docstring); the solver's singularity term is its inverse."""
        home = jnp.zeros(6).at[2].set(self.z_home)
        return jnp.abs(self._scaled_det(q)) / jnp.abs(self._scaled_det(home))

    def inverse_condition(self, q: Vec) -> Array:
        """Smallest over largest singular value of ``J D`` (a diagnostic in [0, 1])."""
        s = jnp.concatenate([jnp.ones(3), jnp.full(3, 1.0 / self.platform_radius)])
        sv = jnp.linalg.svd(self.actuator_jacobian(q) * s[None, :], compute_uv=False)
        return sv[-1] / sv[0]

    def path_constraints(self, q: Vec) -> Array:
        """Normalised inequalities g <= 0, (13,): leg lengths in [rho_min, rho_max]
        (``1 - rho_i / rho_min``, ``rho_i / rho_max - 1``) and the distance to the
        singularity ``1 - manipulability / det_min``."""
        rho = self.leg_lengths(q)
        return jnp.concatenate([1.0 - rho / self.rho_min, rho / self.rho_max - 1.0,
                                (1.0 - self.manipulability(q) / self.det_min)[None]])

    def velocity_constraints(self, q: Vec, qd: Vec) -> Array:
        """Leg speeds as normalised inequalities g <= 0, (12,): ``+-rhod_i / rhod_max - 1``."""
        rhod = self.actuator_jacobian(q) @ qd
        return jnp.concatenate([rhod / self.rhod_max - 1.0, -rhod / self.rhod_max - 1.0])

    # ----- energies -------------------------------------------------------------------
    def _leg_state(self, q):
        d = self.leg_vectors(q)
        rho = jnp.sqrt(jnp.sum(d**2, axis=-1))
        return rho, d / rho[:, None]

    def _mass_matrix_mechanism(self, q: Vec) -> Array:
        """M(q) (6, 6) in closed form, the Hessian in qd of :meth:`kinetic_energy`:
        the platform's ``blockdiag(m I, E^T R I_b R^T E)`` plus, per leg, ``G_i^T K_i G_i``
        with ``dd_i = G_i qd``, ``G_i = [I, -skew(R b_i) E]`` (velocity of the leg vector),
        ``K_i = m_p u u^T + (m_p (rho - e_p)^2 + m_c e_c^2 + I_c + I_p) / rho^2 (I - u u^T)``
        (the piston's axial and both bodies' transverse motion; ``ud = (I - u u^T) dd / rho``)."""
        R, E = self.rotation(q), rpy_rate_matrix(q[3:6])
        RE = R.T @ E  # body angular velocity per angle rate
        M = jnp.zeros((6, 6))
        M = M.at[:3, :3].set(self.platform_mass * jnp.eye(3))
        M = M.at[3:, 3:].set(RE.T @ self.platform_inertia @ RE)
        rho, u = self._leg_state(q)
        Rb = self.platform_points @ R.T
        skew = jnp.cross(Rb[:, :, None], jnp.eye(3)[None, :, :], axis=1)  # skew(Rb_i) e_j as columns
        G = jnp.concatenate([jnp.broadcast_to(jnp.eye(3), (6, 3, 3)), -skew @ E], axis=2)  # (6, 3, 6)
        uu = u[:, :, None] * u[:, None, :]
        transverse = (self.piston_mass * (rho - self.piston_com) ** 2 + self.cyl_mass * self.cyl_com**2
                      + self.cyl_inertia + self.piston_inertia) / rho**2
        K = self.piston_mass * uu + transverse[:, None, None] * (jnp.eye(3)[None] - uu)
        return M + jnp.einsum("kai,kab,kbj->ij", G, K, G)

    def kinetic_energy(self, q: Vec, qd: Vec) -> Array:
        """``T = 1/2 qd^T M(q) qd`` (bodies and terms in the module docstring)."""
        return 0.5 * qd @ self._mass_matrix_mechanism(q) @ qd

    def potential_energy(self, q: Vec) -> Array:
        rho, u = self._leg_state(q)
        z_cyl = self.base_points[:, 2] + self.cyl_com * u[:, 2]
        z_piston = self.base_points[:, 2] + (rho - self.piston_com) * u[:, 2]
        height = self.platform_mass * q[2] + self.cyl_mass * jnp.sum(z_cyl) + self.piston_mass * jnp.sum(z_piston)
        return self.gravity_accel * height

    # ----- actuation ------------------------------------------------------------------
    def generalized_to_actuator(self, q: Vec, Q: Vec) -> Vec:
        """Leg forces from generalised forces: solve ``J^T tau = Q`` [N]."""
        return _linalg.solve(self.actuator_jacobian(q).T, Q)

    def actuator_to_generalized(self, q: Vec, tau: Vec) -> Vec:
        """Generalised forces of the leg forces by virtual work: ``Q = J^T tau``."""
        return self.actuator_jacobian(q).T @ tau


def _layout(radius, angles_deg):
    a = jnp.deg2rad(jnp.asarray(angles_deg, dtype=float))
    return jnp.stack([radius * jnp.cos(a), radius * jnp.sin(a), jnp.zeros_like(a)], axis=-1)


def gough_stewart() -> GoughStewart:
    """The Gough-Stewart platform: six prismatic legs, the platform's pose as coordinates (Khoukhi ch. 4).

    The parameters are the module docstring's."""
    base = _layout(1.0, [-15, 15, 105, 135, 225, 255])
    plat = _layout(0.5, [-45, 45, 75, 165, 195, 285])
    m_p, r_p = 50.0, 0.5
    inertia = jnp.diag(jnp.array([m_p * r_p**2 / 4, m_p * r_p**2 / 4, m_p * r_p**2 / 2]))
    lim = Limits.make(6, q_min=(-0.3, -0.3, 0.8, -0.5, -0.5, -0.5), q_max=(0.3, 0.3, 1.3, 0.5, 0.5, 0.5),
                      qd_max=0.5, qdd_max=5.0, tau_max=1500.0, h_min=0.005, h_max=0.1,
                      workspace=[[-0.3, -0.3, 0.8], [0.3, 0.3, 1.3]])
    return GoughStewart(limits=lim, friction=None, actuator=None, base_points=base, platform_points=plat,
                        platform_mass=m_p, platform_inertia=inertia,
                        cyl_mass=3.0, cyl_com=0.4, cyl_inertia=3.0 * 0.8**2 / 12,
                        piston_mass=2.0, piston_com=0.4, piston_inertia=2.0 * 0.8**2 / 12,
                        platform_radius=r_p, z_home=1.0)
