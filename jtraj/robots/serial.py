"""Planar serial arms with any number of revolute links.

Geometry: link i has length ``l_i``, its centre of mass at distance ``d_i`` from
joint i along the link, mass ``m_i`` and inertia ``I_i`` about its centre of mass
(around the axis normal to the plane). Joint angles are relative: the absolute angle of
link i is ``phi_i = q_1 + ... + q_i``. The task point is the tip of the last link.
Gravity ``g`` acts along -y (a vertical plane); ``g = 0`` is a horizontal plane.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._checks import as_vector
from .._math import sincos
from ._base import Actuator, Friction, Limits, Robot, Vec


class SerialPlanar(Robot):
    """A planar serial arm of revolute joints; see the module docstring for geometry.

    The mass matrix and Coriolis terms come from the kinetic energy by autodiff (the
    general path); :meth:`rigid_body_forces` uses a planar recursive Newton-Euler
    recursion, about 3x cheaper in the optimiser's hot loop, tested against the
    Lagrangian path and against Pinocchio.
    """

    lengths: Vec
    masses: Vec
    inertias: Vec
    com: Vec
    gravity_accel: float | Array
    label: str = eqx.field(static=True, default="serial_planar")

    @property
    def n(self) -> int:
        return self.lengths.shape[0]

    @property
    def name(self) -> str:
        return self.label

    def _frames(self, q):
        phi = jnp.cumsum(q)
        # the barrier materialises cos and sin once: without it XLA fuses them into each
        # consumer and evaluates every sine and cosine more than once (rigid_body_forces
        # has its own); sincos: see jtraj._math
        sin, cos = sincos(phi)
        e = jax.lax.optimization_barrier(jnp.stack([cos, sin], axis=-1))  # (n, 2) link directions
        joints = jnp.concatenate([jnp.zeros((1, 2)), jnp.cumsum(self.lengths[:, None] * e, axis=0)])
        return phi, e, joints  # joints: (n+1, 2), joint i at row i, tip at row n

    def com_positions(self, q: Vec) -> Array:
        """Centres of mass of the links, (n, 2)."""
        _, e, joints = self._frames(q)
        return joints[:-1] + self.com[:, None] * e

    def joint_positions(self, q: Vec) -> Array:
        """Positions of the joints and the tip, (n+1, 2) (for plots)."""
        return self._frames(q)[2]

    def forward_kinematics(self, q: Vec) -> Array:
        return self._frames(q)[2][-1]

    def kinetic_energy(self, q, qd):
        vc = jax.jvp(self.com_positions, (q,), (qd,))[1]
        omega = jnp.cumsum(qd)
        return 0.5 * jnp.sum(self.masses * jnp.sum(vc**2, axis=-1)) + 0.5 * jnp.sum(self.inertias * omega**2)

    def potential_energy(self, q):
        return self.gravity_accel * jnp.sum(self.masses * self.com_positions(q)[:, 1])

    def rigid_body_forces(self, q, qd, qdd):
        """Planar recursive Newton-Euler: M(q) qdd + c(q, qd) + g(q).

        Written joint by joint on scalars (the links' x and y components apart, no
        (n, 2) arrays): under ``vmap`` every quantity is then one array over the batch,
        which XLA's CPU loops run contiguously, where the vector form's (..., n, 2)
        arrays have a minor axis of two (a batch of serial3 efforts about 6x faster)."""
        n = self.n
        phi = jnp.cumsum(q)
        sin, cos = sincos(phi)
        # the barrier materialises cos and sin once: without it XLA fuses them into each
        # consumer and evaluates every sine and cosine several times (a batch of serial3
        # efforts at 256 x 3 x 20 states: about 0.4 ms with it, 1 ms without); sincos: see
        # jtraj._math
        cs = jax.lax.optimization_barrier(jnp.stack([cos, sin]))
        c, s = [cs[0, i] for i in range(n)], [cs[1, i] for i in range(n)]
        lengths, com, masses, inertias = self.lengths, self.com, self.masses, self.inertias
        # forward: angular velocity w and acceleration a of each link; (ax, ay) the
        # acceleration of joint i, gravity entering as an upward base acceleration
        w = a = 0.0
        ax, ay = 0.0, self.gravity_accel
        fx, fy, alpha = [], [], []
        for i in range(n):
            w, a = w + qd[i], a + qdd[i]
            w2 = w * w
            # acceleration of a point at unit distance along link i relative to joint i:
            # a e_perp - w^2 e, with e = (c, s) the link's direction, e_perp = (-s, c)
            ux, uy = -a * s[i] - w2 * c[i], a * c[i] - w2 * s[i]
            fx.append(masses[i] * (ax + com[i] * ux))  # net force on link i
            fy.append(masses[i] * (ay + com[i] * uy))
            ax, ay = ax + lengths[i] * ux, ay + lengths[i] * uy
            alpha.append(a)
        # backward: (Fx, Fy) the force link i + 1 takes from link i, torque about joint i
        tau = [None] * n
        Fx = Fy = torque = 0.0
        for i in reversed(range(n)):
            gx, gy = fx[i] + Fx, fy[i] + Fy
            torque = (inertias[i] * alpha[i] + torque + com[i] * (c[i] * gy - s[i] * gx)
                      + (lengths[i] - com[i]) * (c[i] * Fy - s[i] * Fx))
            Fx, Fy = gx, gy
            tau[i] = torque
        return jnp.stack(tau)


def serial_planar(lengths, masses, inertias, *, com=None, gravity: float = 0.0,
                  friction: Friction | None = None, actuator: Actuator | None = None,
                  limits: Limits | dict | None = None, name: str = "serial_planar") -> SerialPlanar:
    """Build a planar serial arm with ``len(lengths)`` revolute links.

    Args:
        lengths: link lengths [m], (n,), > 0.
        masses: link masses [kg], (n,), > 0.
        inertias: inertias about each link's centre of mass [kg m^2], (n,), >= 0.
        com: distance of each centre of mass from its joint [m]; default mid-link.
        gravity: gravitational acceleration along -y [m/s^2]; 0 for a horizontal plane.
        friction: optional :class:`Friction`.
        actuator: optional :class:`Actuator` (torque limits are then motor-side).
        limits: a :class:`Limits` or a dict of :meth:`Limits.make` keyword arguments.
        name: label shown in reports.
    """
    lengths = as_vector(lengths, "lengths", positive=True)
    n = lengths.shape[0]
    if n < 1:
        raise ValueError("lengths must have at least one link")
    masses = as_vector(masses, "masses", n, positive=True)
    inertias = as_vector(inertias, "inertias", n, nonnegative=True)
    # (checked on the host: no programs dispatched for a robot's construction)
    com = jnp.asarray(np.asarray(lengths) / 2) if com is None else as_vector(com, "com", n, nonnegative=True)
    if (np.asarray(com) > np.asarray(lengths)).any():
        raise ValueError(f"com must lie on the link (0 <= com <= lengths), got {com}")
    if limits is None:
        limits = Limits.make(n)
    elif isinstance(limits, dict):
        limits = Limits.make(n, **limits)
    return SerialPlanar(limits=limits, friction=friction, actuator=actuator, lengths=lengths,
                        masses=masses, inertias=inertias, com=com,
                        gravity_accel=float(gravity), label=name)


SERIAL3_LIMITS = dict(tau_max=(40.0, 25.0, 20.0), qd_max=2.0, qdd_max=3.0, h_min=0.005, h_max=0.1)


def serial3() -> SerialPlanar:
    """The thesis' planar three-link benchmark arm (Khoukhi, Table 6.1) in a horizontal plane.

    Lengths (1.0, 0.8, 0.45) m, masses (10, 8, 4) kg, inertias about the centres of
    mass (9.23, 7.5, 5.21) kg m^2, centres of mass at mid-link, no gravity, no friction.
    Limits: |tau| <= (40, 25, 20) N m, |qd| <= 2 rad/s, |qdd| <= 3 rad/s^2,
    h in [0.005, 0.1] s; no joint box, no workspace box (the thesis' boxes differ
    between chapters and some are inverted). Benchmarks depend on this definition.
    """
    return serial_planar((1.0, 0.8, 0.45), (10.0, 8.0, 4.0), (9.23, 7.5, 5.21),
                         limits=SERIAL3_LIMITS, name="serial3")


def serial3_vertical() -> SerialPlanar:
    """The serial3 arm in a vertical plane (g = 9.81 m/s^2), driven through gearboxes.

    Holding the arm stretched horizontally takes about 238 N m at joint 1 and 72 N m
    at joint 2, so the published limits (40, 25, 20) N m cannot be joint torques with
    gravity on. We read them as *motor-side* torques behind a rotary gear of ratio 20
    on every joint (motor rotor inertia J_m = 1e-3 kg m^2, i.e. 0.4 kg m^2 reflected;
    motor viscous damping b_m = 1e-3 N m s/rad, i.e. 0.4 N m s/rad reflected; the
    gear's output-side inertia and damping are neglected). With ratio 20, static
    holding needs at most about 12 N m at motor 1, leaving margin for motion.
    Velocity, acceleration and sampling-period limits are those of ``serial3``.
    """
    act = Actuator.rotary(3, gear_ratio=20.0, J_m=1e-3, b_m=1e-3)
    return serial_planar((1.0, 0.8, 0.45), (10.0, 8.0, 4.0), (9.23, 7.5, 5.21), gravity=9.81,
                         actuator=act, limits=SERIAL3_LIMITS, name="serial3_vertical")


def ibm7535() -> SerialPlanar:
    """A planar two-link SCARA-like arm standing in for the IBM 7535 B04 (Chettibi 7.1).

    The IBM 7535's mass and length parameters (Geering et al. 1986) are not in our
    sources and no public copy was found, so these values are *assumed*: horizontal
    plane; lengths (0.4, 0.25) m; masses (15, 6) kg; inertias about the centres of mass
    (1.6, 2.4) kg m^2 (gear-reflected rotor inertia lumped in, which is why they
    exceed the slender-rod values), centres of mass at mid-link. They are chosen so that
    the classic task (0, 0) -> (0, pi/4) rad with |tau| <= (25, 9) N m takes about
    one second, like the published 0.99 s; absolute times therefore differ from the
    literature and only ratios between transcriptions are comparable.
    Limits: |tau| <= (25, 9) N m, |qd| <= 10 rad/s, |qdd| <= 50 rad/s^2 (loose:
    the torque limits decide), h in [0.005, 0.1] s.
    """
    return serial_planar((0.4, 0.25), (15.0, 6.0), (1.6, 2.4),
                         limits=dict(tau_max=(25.0, 9.0), qd_max=10.0, qdd_max=50.0,
                                     h_min=0.005, h_max=0.1),
                         name="ibm7535")
