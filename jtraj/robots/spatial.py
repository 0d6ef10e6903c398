"""Spatial serial chains of revolute and prismatic joints (arms from URDF files).

Geometry. Body 0 is the fixed base, placed in the world by ``(base_rotation,
base_translation)``. Joint i (0-based) sits in the frame of its parent body (the base for
i = 0, body i-1 otherwise) at the fixed placement ``(joint_rotation[i],
joint_translation[i])``; its axis ``axes[i]`` (unit) is expressed in that joint frame.
Moving the joint by ``q_i`` gives the frame of body i: a rotation by ``q_i`` about the
axis (revolute) or a translation by ``q_i`` along it (prismatic). Body i carries mass
``masses[i]`` with its centre of mass at ``com[i]`` and rotational inertia
``inertias[i]`` about the centre of mass, both in the body's frame. The tip frame is
fixed in the last body at ``(tip_rotation, tip_translation)``; its origin is the task
point. Gravity is the acceleration vector ``gravity_vector`` in the world frame
(default ``(0, 0, -9.81)`` m/s^2).

Dynamics, two independent paths:

* the Lagrangian one of :class:`~jtraj.robots.Robot`, from the energies
  ``T = sum_i 1/2 m_i |v_ci|^2 + 1/2 w_i^T R_i I_i R_i^T w_i`` (body velocities from the
  tangent of the body poses, ``[w_i]_x = dR_i/dt R_i^T``) and ``V = -sum_i m_i g . c_i``;
* a recursive Newton-Euler pass (:meth:`rigid_body_forces`), in one of two
  formulations (:attr:`SpatialSerial.newton_euler`, static):

  - ``"world"`` (the default): in the world frame, the body velocities and
    accelerations as prefix sums over the chain and the joint efforts as suffix sums of
    the body wrenches, so that after the chain of body rotations everything is
    elementwise over the bodies, on (n, 3) arrays. The solver's programs (a few dozen
    samples under ``vmap``, differentiated twice) compile and run fastest with it.
  - ``"bodies"``: in the body frames, joint by joint on the scalar components of the
    vectors and rotations (one forward and one backward ``lax.scan`` step per joint).
    Under ``vmap`` every quantity is one array over the batch, which XLA's CPU loops
    run contiguously, where the world form's arrays have a minor axis of three: on
    the panda, under ``vmap`` over 480 to 4096 samples, the efforts about 20x, their
    reverse-mode Jacobian over 10x and their forward-over-reverse Hessian about 10x
    faster. In the solver's programs it compiles slower and runs no faster (the panda's
    interior-point program of N = 40: 2.7x the HLO instructions, up to 2x the compile
    time; a dataset worker's chunk of 16 solves: compiled in 1.5x the time, run in the
    same).

  The mass matrix comes from the body Jacobians,
  ``M = sum_i m_i Jv_i^T Jv_i + Jw_i^T R_i I_i R_i^T Jw_i``.

The paths are tested against each other and against Pinocchio models of the same URDF
files.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._checks import as_array
from .._math import sincos, small_matmul
from ._base import Actuator, Friction, Limits, Robot, Vec, yoshikawa

JOINT_TYPES = ("revolute", "prismatic")
#: the formulations of the recursive Newton-Euler pass (:attr:`SpatialSerial.newton_euler`)
NEWTON_EULER = ("world", "bodies")


def _skew(v):
    """[v]_x for a batch of vectors (..., 3) -> (..., 3, 3)."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1),
                      jnp.stack([-y, x, o], -1)], -2)


def _mv(A, v):
    """A @ v over leading batch axes, elementwise (no dot kernel for 3-vectors)."""
    return jnp.sum(A * v[..., None, :], axis=-1)


#: A @ B for 3 x 3 matrices over leading batch axes, elementwise
_mm = small_matmul


#: the linear map a -> [a]_x: [a]_x[i, j] = sum_k _SKEW_OF[i, j, k] a_k (minus Levi-Civita)
_SKEW_OF = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _SKEW_OF[_i, _j, _k], _SKEW_OF[_i, _k, _j] = -1.0, 1.0


def _cross(a, b):
    """a x b = [a]_x b over (broadcast) leading batch axes, with [a]_x one constant
    linear map of a, elementwise like :func:`_mv`. ``jnp.cross`` slices and stacks the
    components: a recursive Newton-Euler pass and its reverse-mode derivative then hold
    many more small operations (each a fixed cost on a CPU): the efforts' Jacobian of
    the Panda's 41 samples has about 2,000 HLO instructions instead of 3,500 and runs
    about a third faster (``benchmarks/profile_spatial.py --pieces``)."""
    E = jnp.asarray(_SKEW_OF, a.dtype).reshape((1,) * (a.ndim - 1) + (3, 3, 3))
    A = jnp.sum(E * a[..., None, None, :], axis=-1)
    return _mv(A, b)


def _prefix(X, reverse=False):
    """Inclusive prefix sums over the bodies (axis 0) of X (n, 3), or suffix sums with
    ``reverse``, as a constant 0/1 triangle times X, elementwise (the form of
    :func:`jtraj.transcription.prefix_sums`)."""
    n = X.shape[0]
    tri = np.tri(n) if not reverse else np.tri(n).T
    return jnp.sum(jnp.asarray(tri, X.dtype)[:, :, None] * X[None], axis=1)


# 3-vectors and 3 x 3 matrices as tuples of their scalar components (the recursive
# Newton-Euler pass in the body frames, SpatialSerial._newton_euler_bodies)
def _c3(v):
    return (v[0], v[1], v[2])


def _c33(A):
    return tuple((A[i, 0], A[i, 1], A[i, 2]) for i in range(3))


def _c_add(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def _c_scale(s, a):
    return (s * a[0], s * a[1], s * a[2])


def _c_dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _c_cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _c_rot(A, v):
    """A v."""
    return tuple(_c_dot(row, v) for row in A)


def _c_rot_t(A, v):
    """A^T v."""
    return tuple(A[0][k] * v[0] + A[1][k] * v[1] + A[2][k] * v[2] for k in range(3))


class SpatialSerial(Robot):
    """A spatial serial chain; see the module docstring for the conventions.

    Build one with :func:`jtraj.robots.from_urdf` (or :func:`spatial_serial`). All
    array fields are parameters (differentiable, overridable with
    :func:`jtraj.robots.with_params`, e.g. ``masses`` for a payload); the joint types
    and names are static, and so is ``newton_euler``, the formulation of the recursive
    Newton-Euler pass (``"world"`` or ``"bodies"``, see the module docstring): a batch
    of many samples evaluates faster on ``robot.replace(newton_euler="bodies")``.
    """

    joint_rotation: Array  # (n, 3, 3) placement of joint i in its parent body
    joint_translation: Array  # (n, 3)
    axes: Array  # (n, 3) unit joint axes in the joint frames
    masses: Array  # (n,)
    com: Array  # (n, 3) centres of mass in the body frames
    inertias: Array  # (n, 3, 3) rotational inertia about the centre of mass, body frame
    base_rotation: Array  # (3, 3)
    base_translation: Array  # (3,)
    tip_rotation: Array  # (3, 3)
    tip_translation: Array  # (3,)
    gravity_vector: Array  # (3,) [m/s^2], world frame
    joint_types: tuple = eqx.field(static=True)
    joint_names: tuple = eqx.field(static=True)
    label: str = eqx.field(static=True, default="spatial_serial")
    newton_euler: str = eqx.field(static=True, default="world")

    def __check_init__(self):
        if self.newton_euler not in NEWTON_EULER:
            raise ValueError(f"newton_euler must be one of {NEWTON_EULER}, got {self.newton_euler!r}")

    @property
    def n(self) -> int:
        return len(self.joint_types)

    @property
    def name(self) -> str:
        return self.label

    # ----- kinematics ---------------------------------------------------------------
    def _revolute_mask(self):
        return jnp.asarray([t == "revolute" for t in self.joint_types], dtype=self.masses.dtype)

    @property
    def _all_revolute(self) -> bool:
        """Whether every joint is revolute (static): the prismatic terms are then left
        out of the traced programs rather than multiplied by a zero mask."""
        return all(t == "revolute" for t in self.joint_types)

    def body_poses(self, q: Vec):
        """World poses of the bodies and joint axes: ``(R, p, z)`` with ``R`` (n, 3, 3)
        the body rotations, ``p`` (n, 3) the body origins (on the joint axes) and ``z``
        (n, 3) the unit joint axes, all in the world frame."""
        sin, cos = sincos(q)
        K = _skew(self.axes)
        rev = self._revolute_mask()
        revolute = self._all_revolute

        # one joint per step of a scan: the solver differentiates this chain twice (forward
        # over reverse) inside vmap, and a rolled loop gives XLA less to compile than the
        # unrolled one (panda, the stage derivatives of 41 samples: 30-38 s against 37-48 s)
        # and runs faster (the efforts' Jacobian of the 41 samples by reverse mode, one
        # core: unrolled about 1.6 times slower)
        def joint(carry, xs):
            R, p = carry
            R0, t0, axis, Ki, s, c, qi, r = xs
            Rj = _mm(R, R0)
            pj = p + _mv(R, t0)
            z = _mv(Rj, axis)
            RK = _mm(Rj, Ki)  # Rodrigues: Rot = I + sin K + (1 - cos) K^2
            turn = s * RK + (1.0 - c) * _mm(RK, Ki)
            if revolute:  # (static: no prismatic terms)
                return (Rj + turn, pj), (Rj + turn, pj, z)
            R_new = Rj + r * turn
            p_new = pj + (1.0 - r) * z * qi
            return (R_new, p_new), (R_new, p_new, z)

        xs = (self.joint_rotation, self.joint_translation, self.axes, K, sin, cos, q, rev)
        _, out = jax.lax.scan(joint, (self.base_rotation, self.base_translation), xs)
        return out

    def tip_pose(self, q: Vec):
        """Tip frame in the world: position (3,) and rotation (3, 3)."""
        R, p, _ = self.body_poses(q)
        return p[-1] + _mv(R[-1], self.tip_translation), _mm(R[-1], self.tip_rotation)

    def rotation(self, q: Vec) -> Array:
        """The tip frame's rotation (3, 3) in the world (orientation passages of
        :class:`jtraj.ViaPoint` use it)."""
        return self.tip_pose(q)[1]

    def forward_kinematics(self, q: Vec) -> Array:
        """The task point: the tip frame's origin (3,) [m]."""
        return self.tip_pose(q)[0]

    def com_positions(self, q: Vec) -> Array:
        """World positions of the bodies' centres of mass, (n, 3)."""
        R, p, _ = self.body_poses(q)
        return p + _mv(R, self.com)

    def joint_positions(self, q: Vec) -> Array:
        """Base, body origins and tip, (n + 2, 3) [m] (for plots)."""
        R, p, _ = self.body_poses(q)
        tip = p[-1] + _mv(R[-1], self.tip_translation)
        return jnp.concatenate([self.base_translation[None], p, tip[None]])

    def _point_jacobians(self, p, z, points):
        """Linear and angular Jacobians (m, 3, n) of points (m, 3), point k moving with
        body ``k`` (m = n) or with the last body (m = 1)."""
        rev = self._revolute_mask()
        n = self.n
        lin = rev[None, :, None] * _cross(z[None], points[:, None] - p[None]) + (1 - rev)[None, :, None] * z[None]
        ang = rev[None, :, None] * jnp.broadcast_to(z[None], lin.shape)
        if points.shape[0] == n:  # body k moves with joints 0..k only
            lower = (jnp.arange(n)[:, None] >= jnp.arange(n)[None, :]).astype(lin.dtype)[..., None]
            lin, ang = lin * lower, ang * lower
        return jnp.swapaxes(lin, 1, 2), jnp.swapaxes(ang, 1, 2)

    def geometric_jacobian(self, q: Vec) -> Array:
        """The tip's geometric Jacobian (6, n) in the world frame: rows 0-2 the linear
        velocity of the tip point, rows 3-5 the angular velocity (Pinocchio's
        LOCAL_WORLD_ALIGNED frame Jacobian)."""
        R, p, z = self.body_poses(q)
        tip = p[-1] + _mv(R[-1], self.tip_translation)
        lin, ang = self._point_jacobians(p, z, tip[None])
        return jnp.concatenate([lin[0], ang[0]])

    def jacobian(self, q: Vec) -> Array:
        """Positional Jacobian dp/dq (3, n) of the task point."""
        return self.geometric_jacobian(q)[:3]

    def manipulability(self, q: Vec) -> Array:
        """Yoshikawa's ``sqrt(det(J J^T))`` of the tip's geometric Jacobian (6 x n) on an
        arm of 6 or more joints, so that wrist singularities count, of the positional
        Jacobian (3 x n) on a shorter arm (whose 6 x n Jacobian never has full row rank;
        ``sqrt(det(J^T J))`` below 3 joints: :func:`jtraj.robots._base.yoshikawa`); 0 at
        a singularity. The solver's singularity term (``Weights(singularity=...)``) is its
        inverse."""
        return yoshikawa(self.geometric_jacobian(q) if self.n >= 6 else self.jacobian(q))

    # ----- energies (the Lagrangian path) -------------------------------------------
    def kinetic_energy(self, q, qd):
        def poses(q_):
            R, p, _ = self.body_poses(q_)
            return R, p + _mv(R, self.com)

        (R, _), (Rd, vc) = jax.jvp(poses, (q,), (qd,))
        W = jnp.einsum("nij,nkj->nik", Rd, R)  # [w]_x = dR/dt R^T
        w = jnp.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=-1)
        wb = _mv(jnp.swapaxes(R, 1, 2), w)  # body-frame angular velocity
        rot = jnp.sum(wb * _mv(self.inertias, wb))
        return 0.5 * jnp.sum(self.masses * jnp.sum(vc**2, axis=-1)) + 0.5 * rot

    def potential_energy(self, q):
        return -jnp.sum(self.masses * (self.com_positions(q) @ self.gravity_vector))

    # ----- recursive Newton-Euler (the fast path) -----------------------------------
    def _joint_constants(self):
        """Per joint, the parent-to-child rotation ``E_i`` as ``P_i + cos(q_i) Q_i +
        sin(q_i) S_i`` (n, 3, 3 each): for a revolute joint ``E_i = R0_i Rot(a_i, q_i)``,
        by Rodrigues ``Rot = a a^T + cos (I - a a^T) + sin [a]_x``, so ``P = R0 a a^T``,
        ``Q = R0 - P``, ``S = R0 [a]_x``; for a prismatic one ``E_i = R0_i`` (``P = R0``,
        ``Q = S = 0``). Also ``R0_i a_i`` (n, 3), the axis in the parent body's frame."""
        R0, a = self.joint_rotation, self.axes
        R0a = _mv(R0, a)
        P = R0a[:, :, None] * a[:, None, :]
        Q, S = R0 - P, _mm(R0, _skew(a))
        if not self._all_revolute:
            rev = self._revolute_mask()[:, None, None]
            P, Q, S = rev * P + (1.0 - rev) * R0, rev * Q, rev * S
        return P, Q, S, R0a

    def _newton_euler_bodies(self, q, qd, qdd, g):
        """Recursive Newton-Euler in the body frames (``newton_euler="bodies"``), on the
        scalar components of the 3-vectors and rotations (tuples, see ``_c3``), one
        joint per step of a forward and a backward ``lax.scan``. Under ``vmap`` every
        quantity is then one array over the batch, which XLA's CPU loops run
        contiguously, where arrays of (..., n, 3) or (..., 3, 3) have a minor axis of
        three. In the body frames the joint axes, centres of mass and inertias are
        constants and the only rotations are the joints' own ``E_i``. Gravity enters as
        an upward acceleration of the base. The scans keep each fused loop to one joint:
        unrolled over the joints (a Python loop), XLA fuses the whole pass into one loop
        whose code evaluates shared terms many times over (the panda's efforts of one
        sample took about 40 ms, of 480 samples minutes)."""
        revolute = self._all_revolute
        P, Q, S, R0a = self._joint_constants()
        sin, cos = sincos(q)
        rev = self._revolute_mask()
        slide = jnp.zeros_like(q) if revolute else (1.0 - rev) * q

        def forward(carry, xs):
            w, wd, acc = carry
            P, Q, S, R0a, t, a, com, inertia, mass, s, c, x, v, vd, rv = xs
            E = tuple(tuple(P[j, k] + c * Q[j, k] + s * S[j, k] for k in range(3)) for j in range(3))
            r = _c3(t) if revolute else _c_add(_c3(t), _c_scale(x, _c3(R0a)))  # child origin
            a, com, inertia = _c3(a), _c3(com), _c33(inertia)
            acc = _c_add(acc, _c_add(_c_cross(wd, r), _c_cross(w, _c_cross(w, r))))
            acc, w, wd = _c_rot_t(E, acc), _c_rot_t(E, w), _c_rot_t(E, wd)
            vel = _c_scale(v, a)  # joint velocity along the axis
            dwd = _c_add(_c_cross(w, vel), _c_scale(vd, a))
            if revolute:
                wd, w = _c_add(wd, dwd), _c_add(w, vel)
            else:  # a prismatic joint moves the origin, a revolute one turns the body
                wd, w = _c_add(wd, _c_scale(rv, dwd)), _c_add(w, _c_scale(rv, vel))
                slid = _c_add(_c_scale(2.0, _c_cross(w, vel)), _c_scale(vd, a))
                acc = _c_add(acc, _c_scale(1.0 - rv, slid))
            ac = _c_add(acc, _c_add(_c_cross(wd, com), _c_cross(w, _c_cross(w, com))))
            F = _c_scale(mass, ac)  # net force; moment about the body origin:
            M = _c_add(_c_add(_c_rot(inertia, wd), _c_cross(w, _c_rot(inertia, w))), _c_cross(com, F))
            return (w, wd, acc), (E, r, F, M)

        zero = jnp.zeros((), q.dtype)
        acc0 = _c_scale(-1.0, _c_rot_t(_c33(self.base_rotation), _c3(g)))
        xs = (P, Q, S, R0a, self.joint_translation, self.axes, self.com, self.inertias, self.masses,
              sin, cos, slide, qd, qdd, rev)
        _, (E, r, F, M) = jax.lax.scan(forward, ((zero,) * 3, (zero,) * 3, acc0), xs)

        def backward(carry, xs):
            # carry: the force and moment (about its origin) body i takes from its
            # child, in body i's frame
            f, m = carry
            E, r, F, M, a, rv = xs
            f, m, a = _c_add(F, f), _c_add(M, m), _c3(a)
            tau = _c_dot(a, m) if revolute else rv * _c_dot(a, m) + (1.0 - rv) * _c_dot(a, f)
            f_parent = _c_rot(E, f)  # what the parent transmits, in the parent's frame
            m_parent = _c_add(_c_rot(E, m), _c_cross(r, f_parent))
            return (f_parent, m_parent), tau

        _, tau = jax.lax.scan(backward, ((zero,) * 3, (zero,) * 3), (E, r, F, M, self.axes, rev), reverse=True)
        return tau

    def _newton_euler_world(self, q, qd, qdd, g):
        """Recursive Newton-Euler in the world frame (``newton_euler="world"``): the body
        velocities and accelerations as prefix sums over the chain and the efforts as
        suffix sums of the body wrenches, elementwise over (n, 3) arrays after the chain
        of body rotations (:meth:`body_poses`)."""
        R, p, z = self.body_poses(q)
        revolute = self._all_revolute
        rev = self._revolute_mask()[:, None]
        pri = 1.0 - rev
        zqd, zqdd = z * qd[:, None], z * qdd[:, None]
        # angular velocity and acceleration: prefix sums over the chain
        dw = zqd if revolute else rev * zqd
        w = _prefix(dw)
        w_prev = w - dw
        dwd = zqdd + _cross(w_prev, zqd)
        dwd = dwd if revolute else rev * dwd
        wd = _prefix(dwd)
        wd_prev = wd - dwd
        # acceleration of the body origins (gravity as an upward base acceleration)
        r = p - jnp.concatenate([self.base_translation[None], p[:-1]])
        da = _cross(wd_prev, r) + _cross(w_prev, _cross(w_prev, r))
        if not revolute:
            da = da + pri * (2.0 * _cross(w_prev, zqd) + zqdd)
        a = _prefix(da) - g[None]
        rc = _mv(R, self.com)  # body origin -> centre of mass
        ac = a + _cross(wd, rc) + _cross(w, _cross(w, rc))
        # body wrenches; moments about the world origin, accumulated from the tip
        F = self.masses[:, None] * ac
        Rt = jnp.swapaxes(R, 1, 2)
        wb, wdb = _mv(Rt, w), _mv(Rt, wd)
        Iw = _mv(self.inertias, wb)
        Nb = _mv(self.inertias, wdb) + _cross(wb, Iw)
        c = p + rc
        moment = _mv(R, Nb) + _cross(c, F)
        f = _prefix(F, reverse=True)
        n_o = _prefix(moment, reverse=True)
        n_j = n_o - _cross(p, f)  # about each joint's origin
        return jnp.sum(z * (n_j if revolute else rev * n_j + pri * f), axis=-1)

    def _newton_euler(self, q, qd, qdd, g):
        if self.newton_euler == "bodies":
            return self._newton_euler_bodies(q, qd, qdd, g)
        return self._newton_euler_world(q, qd, qdd, g)

    def rigid_body_forces(self, q, qd, qdd):
        """Recursive Newton-Euler: M(q) qdd + c(q, qd) + g(q)."""
        return self._newton_euler(q, qd, qdd, self.gravity_vector)

    def coriolis(self, q, qd):
        return self._newton_euler(q, qd, jnp.zeros_like(qd), jnp.zeros(3, qd.dtype))

    def gravity(self, q):
        zero = jnp.zeros_like(q)
        return self._newton_euler(q, zero, zero, self.gravity_vector)

    def _mass_matrix_mechanism(self, q):
        R, p, z = self.body_poses(q)
        c = p + _mv(R, self.com)
        Jv, Jw = self._point_jacobians(p, z, c)  # (n, 3, n)
        Iw = _mm(_mm(R, self.inertias), jnp.swapaxes(R, 1, 2))
        M = jnp.einsum("b,bki,bkj->ij", self.masses, Jv, Jv) + jnp.einsum("bki,bkl,blj->ij", Jw, Iw, Jw)
        return 0.5 * (M + M.T)


def spatial_serial(joint_rotation, joint_translation, axes, joint_types, masses, com, inertias, *,
                   tip_rotation=None, tip_translation=None, base_rotation=None, base_translation=None,
                   gravity=(0.0, 0.0, -9.81), joint_names=None, limits: Limits | dict | None = None,
                   friction: Friction | None = None, actuator: Actuator | None = None,
                   name: str = "spatial_serial", newton_euler: str = "world") -> SpatialSerial:
    """A validated :class:`SpatialSerial` from its arrays (see the module docstring).

    ``joint_types``: sequence of "revolute" / "prismatic". Axes are normalised.
    ``newton_euler``: the formulation of the recursive Newton-Euler pass, ``"world"`` or
    ``"bodies"`` (see the module docstring).
    Raises ``ValueError`` naming the argument on wrong shapes, non-finite values, a
    zero axis, a non-positive mass or a rotational inertia that is not symmetric
    positive definite.
    """
    if newton_euler not in NEWTON_EULER:
        raise ValueError(f"newton_euler must be one of {NEWTON_EULER}, got {newton_euler!r}")
    joint_types = tuple(joint_types)
    n = len(joint_types)
    if n < 1:
        raise ValueError("joint_types must name at least one joint")
    for i, t in enumerate(joint_types):
        if t not in JOINT_TYPES:
            raise ValueError(f"joint_types[{i}] must be one of {JOINT_TYPES}, got {t!r}")

    def arr(x, name, shape, default=None):
        return as_array(default if x is None else x, name, shape)

    Rj = arr(joint_rotation, "joint_rotation", (n, 3, 3))
    tj = arr(joint_translation, "joint_translation", (n, 3))
    ax = arr(axes, "axes", (n, 3))
    norms = np.linalg.norm(ax, axis=1)
    if (norms < 1e-12).any():
        raise ValueError(f"axes must be non-zero, got {ax.tolist()}")
    ax = ax / norms[:, None]
    m = arr(masses, "masses", (n,))
    if (m <= 0).any():
        raise ValueError(f"masses must be > 0, got {m.tolist()}")
    c = arr(com, "com", (n, 3))
    inertia = arr(inertias, "inertias", (n, 3, 3))
    for i in range(n):
        if not np.allclose(inertia[i], inertia[i].T, rtol=0, atol=1e-12 * max(np.abs(inertia[i]).max(), 1e-300)):
            raise ValueError(f"inertias[{i}] must be symmetric, got {inertia[i].tolist()}")
        if np.linalg.eigvalsh(inertia[i]).min() <= 0:
            raise ValueError(f"inertias[{i}] must be positive definite, got {inertia[i].tolist()}")
    eye = np.eye(3)
    err = np.abs(np.einsum("nij,nkj->nik", Rj, Rj) - eye).max()
    if err > 1e-9:
        raise ValueError(f"joint_rotation must hold rotation matrices (R R^T = I), off by {err:.2e}")
    Rt = arr(tip_rotation, "tip_rotation", (3, 3), eye)
    tt = arr(tip_translation, "tip_translation", (3,), np.zeros(3))
    Rb = arr(base_rotation, "base_rotation", (3, 3), eye)
    tb = arr(base_translation, "base_translation", (3,), np.zeros(3))
    for nm, R in (("tip_rotation", Rt), ("base_rotation", Rb)):
        if np.abs(R @ R.T - eye).max() > 1e-9:
            raise ValueError(f"{nm} must be a rotation matrix (R R^T = I)")
    g = arr(gravity, "gravity", (3,))
    names = tuple(f"joint{i + 1}" for i in range(n)) if joint_names is None else tuple(map(str, joint_names))
    if len(names) != n:
        raise ValueError(f"joint_names must have {n} entries, got {len(names)}")
    if limits is None:
        limits = Limits.make(n)
    elif isinstance(limits, dict):
        limits = Limits.make(n, **limits)
    j = jnp.asarray
    return SpatialSerial(limits=limits, friction=friction, actuator=actuator, joint_rotation=j(Rj),
                         joint_translation=j(tj), axes=j(ax), masses=j(m), com=j(c), inertias=j(inertia),
                         base_rotation=j(Rb), base_translation=j(tb), tip_rotation=j(Rt),
                         tip_translation=j(tt), gravity_vector=j(g), joint_types=joint_types,
                         joint_names=names, label=str(name), newton_euler=newton_euler)
