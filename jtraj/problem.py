"""What to achieve: :class:`Problem`, :class:`Weights` and :class:`ViaPoint`.

Units: positions in rad (or m for prismatic/task coordinates), velocities per second,
times in seconds, torques in N m (or N). Build robots and problems with
``jax_enable_x64`` on: their arrays take JAX's float width of that moment, and
:func:`jtraj.solve` refuses float32 (see :mod:`jtraj._setup`). A :class:`Problem` is an equinox Module: its
arrays are leaves (so problems can be batched with ``vmap`` and differentiated), its
sizes (``N``, number of via points) are static.
"""

from __future__ import annotations

import math
from typing import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from . import _kkt_native
from ._checks import as_vector, check_state, is_concrete
from .robots import Robot


class Weights(eqx.Module):
    """Weights of the multi-objective cost

    ``J = sum_k h_k [ time + tau_k^T U tau_k + qd_k^T Q qd_k + singularity * w(q_k) ]``

    with ``w(q) = 1 / sqrt(det(J J^T))`` the inverse manipulability. By default
    ``U = energy * diag(1 / tau_max^2)`` (torques normalised by their limits, so the
    energy term is dimensionless per second) and ``Q = kinetic * I``. Pass ``U`` or
    ``Q`` (square matrices, or vectors for diagonals) to override.

    "Energy" in reports is ``sum_k h_k tau_k^T U_1 tau_k`` with ``U_1 = diag(1/tau_max^2)``,
    i.e. the h-weighted (time-integral) form, independent of the weight ``energy``.

    The weights are array leaves: a compiled solver serves any values (a sweep over
    weights compiles once). Which optional terms exist is static and fixed here: a
    ``kinetic`` or ``singularity`` weight that is a concrete 0 when the Weights is built
    drops its term from the compiled cost, derivatives included (with the singularity
    term, even at a weight of 1e-12, 128 serial3 benchmark pairs took 1.47x as long: 6.30
    against 4.29 s on one core); a traced weight keeps it. Build a new Weights (not
    ``eqx.tree_at``) to switch a term on.
    """

    time: Array
    energy: Array
    kinetic: Array
    singularity: Array
    U: Array | None
    Q: Array | None
    #: static: whether the kinetic and the singularity terms are part of the cost
    has_kinetic: bool = eqx.field(static=True)
    has_singularity: bool = eqx.field(static=True)

    def __init__(self, time=1.0, energy=1.0, kinetic=0.0, singularity=0.0, U=None, Q=None):
        zero = {}
        for name, value in (("time", time), ("energy", energy), ("kinetic", kinetic), ("singularity", singularity)):
            if is_concrete(value):
                try:
                    arr = np.asarray(value, dtype=float)
                except (TypeError, ValueError):
                    raise ValueError(f"Weights.{name} must be a number, got {value!r}") from None
                if not np.all(np.isfinite(arr)) or np.any(arr < 0):
                    raise ValueError(f"Weights.{name} must be a finite number >= 0, got {value!r}")
                value, zero[name] = arr, not np.any(arr)
            setattr(self, name, value)
        self.U, self.Q = U, Q
        self.has_kinetic = Q is not None or not zero.get("kinetic", False)
        self.has_singularity = not zero.get("singularity", False)

    def invalid(self) -> Array:
        """A traced bool: what the constructor rejects where the values are concrete (a
        weight negative or not finite; ``U`` or ``Q`` not finite, not symmetric or with an
        eigenvalue below -1e-12), for weights traced past it (checked by the
        solve, :meth:`Problem.infeasible_on_its_face`)."""
        bad = jnp.zeros((), bool)
        for w in (self.time, self.energy, self.kinetic, self.singularity):
            w = jnp.asarray(w)
            bad |= jnp.any(~jnp.isfinite(w) | (w < 0))
        for M in (self.U, self.Q):
            if M is not None:
                M = jnp.asarray(M)
                M = jnp.diag(M) if M.ndim == 1 else M
                finite = jnp.all(jnp.isfinite(M))
                Ms = jnp.where(finite, M, 0.0)
                bad |= ~finite | jnp.any(jnp.abs(Ms - Ms.T) > 1e-8 + 1e-5 * jnp.abs(Ms.T))  # (np.allclose's)
                bad |= jnp.min(jnp.linalg.eigvalsh(0.5 * (Ms + Ms.T))) < -1e-12
        return bad

    def matrices(self, robot: Robot) -> tuple[Array, Array]:
        """(U, Q) for ``robot``: U is (m, m) over actuator efforts, Q (n, n)."""
        tau_max = robot.limits.tau_max
        m = robot.n if tau_max is None else tau_max.shape[0]
        if self.U is None:
            scale = jnp.ones(m) if tau_max is None else 1.0 / tau_max**2
            U = self.energy * jnp.diag(scale)
        else:
            U = _square(self.U, m, "Weights.U")
        Q = self.kinetic * jnp.eye(robot.n) if self.Q is None else _square(self.Q, robot.n, "Weights.Q")
        return U, Q

    @staticmethod
    def parse(text: str) -> "Weights":
        """Parse ``"time=1,energy=0.1"`` (CLI form)."""
        kw = {}
        for item in filter(None, (s.strip() for s in text.split(","))):
            key, sep, value = item.partition("=")
            if not sep or key.strip() not in ("time", "energy", "kinetic", "singularity"):
                raise ValueError(f"weights must look like 'time=1,energy=0.1' with keys time, "
                                 f"energy, kinetic, singularity; got {item!r}")
            try:
                kw[key.strip()] = float(value)
            except ValueError as err:
                raise ValueError(f"weights: {key.strip()} must be a number, got {value!r}") from err
        return Weights(**kw)


def _square(M, m, name):
    M = jnp.asarray(M, dtype=float)
    if M.ndim == 1:
        M = jnp.diag(M)
    if M.shape != (m, m):
        raise ValueError(f"{name} must have shape ({m}, {m}) or ({m},), got {M.shape}")
    if is_concrete(M):
        Mn = np.asarray(M)
        if not np.isfinite(Mn).all() or not np.allclose(Mn, Mn.T) or np.linalg.eigvalsh(Mn).min() < -1e-12:
            raise ValueError(f"{name} must be finite, symmetric and positive semidefinite")
    return M


class ViaPoint(eqx.Module):
    """An imposed passage of the task point: ``||p(q_k) - point|| <= tol``, and with a
    ``rotation`` R_l (3, 3) also of the orientation (the thesis' form):
    ``||vect(R(q_k)^T R_l)|| <= rot_tol``, where ``R(q)`` is the robot's ``rotation``
    and ``vect`` the axial vector of a rotation's skew part (norm = sin of the angle
    between the two orientations, so ``rot_tol`` is about an angle in rad).

    The passing sample is fixed before solving (fixed shapes, smooth constraints):
    ``sample`` if given, else via point l of L is assigned ``k = round((l+1) N/(L+1))``,
    i.e. the via points split the samples evenly. Because the sampling periods are free,
    the optimiser still chooses *when* the passage happens.
    """

    point: Array
    tol: float | Array = 1e-6
    sample: int | None = eqx.field(static=True, default=None)
    rotation: Array | None = None
    rot_tol: float | Array = 1e-3


def orientation_error(R, R_target) -> Array:
    """``vect(R^T R_target)`` (3,), with ``vect(A) = (A_32 - A_23, A_13 - A_31,
    A_21 - A_12) / 2``: ``sin(angle) * axis`` of the rotation between the two
    orientations; its norm is the thesis' orientation distance of a passage."""
    A = R.T @ R_target
    return 0.5 * jnp.stack([A[2, 1] - A[1, 2], A[0, 2] - A[2, 0], A[1, 0] - A[0, 1]])


#: slack of the checks of a problem's start and goal against its boxes and path
#: constraints (absolute, in the constraints' units; path constraints are normalised)
FACE_TOL = 1e-9


def configuration_checks(robot: Robot, q) -> dict:
    """Traced bools, one per family the robot has: ``"joint"`` (``q`` in the joint box),
    ``"workspace"`` (the task point in the workspace box) and ``"path"`` (the robot's
    path constraints met), each within ``FACE_TOL``."""
    lim = robot.limits
    checks = {}
    if lim.q_min is not None:
        checks["joint"] = jnp.all((q >= lim.q_min - FACE_TOL) & (q <= lim.q_max + FACE_TOL))
    if lim.workspace is not None:
        p = robot.forward_kinematics(q)
        checks["workspace"] = jnp.all((p >= lim.workspace[0] - FACE_TOL) & (p <= lim.workspace[1] + FACE_TOL))
    path = getattr(robot, "path_constraints", None)
    if path is not None:
        checks["path"] = jnp.all(path(q) <= FACE_TOL)
    return checks


def admissible_configuration(robot: Robot, q) -> Array:
    """A traced bool: ``q`` is finite and passes every :func:`configuration_checks`. What
    :class:`Problem` demands of a start and a goal (see
    :meth:`Problem.infeasible_on_its_face`), and what dataset sampling keeps."""
    ok = jnp.all(jnp.isfinite(q))
    for c in configuration_checks(robot, q).values():
        ok &= c
    return ok


def check_configurations(robot: Robot, configurations: dict, velocities: dict | None = None) -> None:
    """``ValueError`` naming the first of ``configurations`` (name -> (n,) concrete
    array) outside the joint box, the workspace box or the robot's path constraints, or
    of ``velocities`` beyond ``qd_max``: the checks :class:`Problem` makes of its start and
    goal (the joint box of every configuration first), shared with the CLI and
    :class:`jtraj.online.Planner`. Shapes and finiteness: :func:`jtraj._checks.check_state`."""
    lim = robot.limits
    ends = list(configurations.items())
    failed = {name: {k for k, c in configuration_checks(robot, q).items() if not bool(c)} for name, q in ends}
    for name, q in ends:
        if "joint" in failed[name]:
            qa, lo, hi = (np.broadcast_to(np.asarray(x, float), np.shape(q)) for x in (q, lim.q_min, lim.q_max))
            i = int(np.argmax((qa < lo - FACE_TOL) | (qa > hi + FACE_TOL)))
            names = getattr(robot, "joint_names", None)
            joint = f"joint {names[i]!r} (index {i})" if names else f"joint {i}"
            raise ValueError(f"{name} = {np.asarray(q).tolist()} is outside the joint limits: {joint} at "
                             f"{qa[i]:.6g}, outside [{lo[i]:.6g}, {hi[i]:.6g}] (q_min = {lo.tolist()}, "
                             f"q_max = {hi.tolist()})")
    for name, qd in (velocities or {}).items():
        if lim.qd_max is not None and bool(jnp.any(jnp.abs(qd) > lim.qd_max * (1 + FACE_TOL))):
            raise ValueError(f"{name} exceeds the velocity limits qd_max = {np.asarray(lim.qd_max).tolist()}")
    for name, q in ends:
        if "workspace" in failed[name]:
            p = np.asarray(robot.forward_kinematics(q)).tolist()
            raise ValueError(f"{name} puts the task point at {p}, outside "
                             f"the workspace box {np.asarray(lim.workspace).tolist()}")
    for name, q in ends:
        if "path" in failed[name]:
            g = np.asarray(robot.path_constraints(q))
            raise ValueError(f"{name} = {np.asarray(q).tolist()} violates the path constraints of robot "
                             f"{robot.name!r} (largest normalised value {g.max():.3g} > 0: e.g. too "
                             f"close to a singularity)")


#: where the torque bound is imposed (see :class:`Problem`)
EFFORTS = ("samples", "intervals")


def _per_sample(x, name: str, n: int, shape: tuple) -> Array:
    """A boundary velocity broadcast to ``shape`` ((n,) or (B, n)): a scalar, (n,) or ``shape``."""
    if jnp.ndim(x) == 0:
        return check_state(jnp.broadcast_to(jnp.asarray(x, float), shape), name, n)
    x = check_state(x, name, n)
    if x.shape not in ((n,), shape):
        raise ValueError(f"{name} must be a scalar, ({n},) or {shape}, got shape {x.shape}")
    return x if x.shape == shape else jnp.broadcast_to(x, shape)


def default_jerk(robot) -> bool:
    """Whether a problem of ``robot`` gets jerk rows by default: where its limits include a
    jerk bound ``qddd_max`` that the acceleration bound and the shortest period do not
    already imply. With ``|v_k| <= qdd_max``, every row holds when
    ``2 qdd_max <= qddd_max h_min`` (then ``|v_{k+1} - v_k| <= 2 qdd_max <= qddd_max
    (h_k + h_{k+1}) / 2``): such rows never bind, and leaving them out keeps the
    interior-point method with its stage-wise Newton steps. The ``panda``'s published
    limits are such a case (``2 qdd_max / qddd_max`` = 4 ms against ``h_min`` = 5 ms).
    Traced limits (a derivative with respect to them) keep the rows."""
    lim = robot.limits
    if lim.qddd_max is None:
        return False
    if lim.qdd_max is None:
        return True
    try:
        qdd, qddd, h_min = (np.asarray(x, float) for x in (lim.qdd_max, lim.qddd_max, lim.h_min))
    except (TypeError, jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return True
    return not bool(np.all(2.0 * qdd <= qddd * h_min))


class Problem(eqx.Module):
    """A point-to-point trajectory problem for the decoupled transcription.

    Args:
        robot: a :class:`jtraj.robots.Robot`.
        q_start, q_goal: (n,) start and goal configurations; (B, n) for a batch of B
            problems (:func:`jtraj.solve_batch`), whose boundary velocities and ``T_max``
            are then broadcast to (B, n) and (B,). A batch's shapes and values are checked
            here; a sample infeasible on its face is flagged ``INVALID_INPUT`` by the solve.
        N: number of sampling intervals (>= 2).
        weights: :class:`Weights` of the cost.
        qd_start, qd_goal: (n,) start and goal velocities (default 0); a batch also takes (B, n).
        via_points: sequence of :class:`ViaPoint` (or (d,) points).
        T_max: optional upper bound on the total time T = sum h_k [s]; a batch also takes (B,).
        efforts: where the torque bound is imposed. "samples" (default, the thesis):
            ``|tau_k| <= tau_max`` at the sampling instants, ``tau_k = ID(q_k, qd_k,
            v_k)``. Between the samples the executed constant-acceleration motion asks
            for ``ID(q(t), qd(t), v_k)``, which exceeds the bound at the end of an
            interval (where the state has moved on and the acceleration is still
            ``v_k``): on serial3 datasets (h_max 0.2 s) by a median 1.1-1.5 %, at most 21 %
            (:func:`jtraj.resample.intersample_effort`). "intervals" also bounds
            ``ID(q_{k+1}, qd_{k+1}, v_k)``, the effort at each interval's end, so the
            bound holds at both ends of every interval (and between them within 2.4e-4
            relative on 64 benchmark pairs, 1.7e-3 on 96 dataset pairs with h_max 0.2 s),
            for 1.56-1.77x the solve time. Decoupled transcription only.
        jerk: bound the change of acceleration between consecutive intervals by the
            robot's ``limits.qddd_max`` (``|v_{k+1} - v_k| <= qddd_max (h_k + h_{k+1}) / 2``,
            see :func:`jtraj.transcription.jerk_inequalities`). None (default): on where
            the robot's limits include a jerk bound that they do not already imply
            (:func:`default_jerk`), off elsewhere (``serial3`` and the thesis' other robots
            have none; the ``panda``'s acceleration bounds and shortest period imply its
            published jerk bounds). True: on wherever the limits include one. The rows couple consecutive stages:
            such problems are solved by the augmented-Lagrangian method with dense Newton
            systems (``method="auto"`` picks it; "ip" and the Riccati solve refuse them).
    """

    robot: Robot
    q_start: Array
    q_goal: Array
    qd_start: Array
    qd_goal: Array
    weights: Weights
    via_points: tuple[ViaPoint, ...]
    T_max: Array
    N: int = eqx.field(static=True)
    efforts: str = eqx.field(static=True, default="samples")
    jerk: bool = eqx.field(static=True, default=False)

    def __init__(self, robot: Robot, q_start, q_goal, *, N: int = 20, weights: Weights | None = None,
                 qd_start=0.0, qd_goal=0.0, via_points: Sequence = (), T_max: float | None = None,
                 efforts: str = "samples", jerk: bool | None = None, validate: bool = True):
        if not isinstance(robot, Robot):
            raise ValueError(f"robot must be a jtraj.robots.Robot, got {type(robot).__name__}")
        if isinstance(N, jax.core.Tracer):
            raise ValueError("N (the number of intervals) is static: it cannot be traced or differentiated")
        if not isinstance(N, (int, np.integer)) or isinstance(N, bool) or N < 2:
            raise ValueError(f"N must be an integer >= 2, got {N!r}")
        if not isinstance(efforts, str) or efforts not in EFFORTS:
            raise ValueError(f"efforts must be one of {EFFORTS}, got {efforts!r}")
        # the native KKT kernel's build (once per machine) starts now, in a background
        # thread, so that it is ready or nearly so when the solve needs it
        _kkt_native.prefetch(robot.n)
        has_jerk = robot.limits.qddd_max is not None
        if jerk is None:
            jerk = default_jerk(robot)
        elif not isinstance(jerk, (bool, np.bool_)):
            raise ValueError(f"jerk must be True, False or None, got {jerk!r}")
        elif jerk and not has_jerk:
            raise ValueError(f"jerk=True needs a jerk bound in the robot's limits (limits.qddd_max); robot "
                             f"{robot.name!r} has none")
        n = robot.n
        self.robot = robot
        self.N = int(N)
        self.efforts = efforts
        self.jerk = bool(jerk)
        self.q_start = check_state(q_start, "q_start", n)
        if self.q_start.ndim > 2:
            raise ValueError(f"q_start must have shape ({n},) or (B, {n}) (a batch), got shape {self.q_start.shape}")
        shape = self.q_start.shape  # (n,), or (B, n) for a batch
        self.q_goal = check_state(q_goal, "q_goal", n)
        if self.q_goal.shape != shape:
            raise ValueError(f"q_goal must have shape {shape} like q_start, got shape {self.q_goal.shape}")
        self.qd_start = _per_sample(qd_start, "qd_start", n, shape)
        self.qd_goal = _per_sample(qd_goal, "qd_goal", n, shape)
        self.weights = Weights() if weights is None else weights
        if not isinstance(self.weights, Weights):
            raise ValueError(f"weights must be a jtraj.Weights, got {type(weights).__name__}")
        if via_points:  # (the task space's dimension, by tracing the kinematics: ~3 ms)
            q = jax.ShapeDtypeStruct((n,), self.q_start.dtype)
            d = jax.eval_shape(robot.forward_kinematics, q).shape[0]
            self.via_points = tuple(_as_via(p, i, d, robot) for i, p in enumerate(via_points))
        else:
            self.via_points = ()
        if T_max is None:
            self.T_max = jnp.asarray(jnp.inf) if len(shape) == 1 else jnp.full(shape[:-1], jnp.inf)
        else:
            if jnp.shape(T_max) not in ((), shape[:-1]):
                raise ValueError(f"T_max must be a scalar{' or have shape ' + str(shape[:-1]) if shape[:-1] else ''}"
                                 f", got shape {jnp.shape(T_max)}")
            if is_concrete(T_max) and not np.all(np.asarray(T_max, dtype=float) > 0):
                raise ValueError(f"T_max must be > 0 or None, got {T_max!r}")
            self.T_max = jnp.asarray(T_max, dtype=float)
            if self.T_max.shape != shape[:-1]:
                self.T_max = jnp.broadcast_to(self.T_max, shape[:-1])
        # the host-side checks need concrete values: skipped where any is traced (a
        # solve then flags such a problem INVALID_INPUT instead, see infeasible_on_its_face),
        # and for a batch (jtraj.solve_batch flags its samples the same way)
        if validate and len(shape) == 1 and all(is_concrete(x) for x in jax.tree.leaves(
                (robot, self.q_start, self.q_goal, self.qd_start, self.qd_goal, self.T_max))):
            self._check_feasible()

    @property
    def batch_size(self) -> int | None:
        """B for a batch of problems (``q_start`` of shape (B, n), :func:`jtraj.solve_batch`),
        None for one problem."""
        return None if self.q_start.ndim == 1 else int(self.q_start.shape[0])

    def via_samples(self) -> tuple[int, ...]:
        """The sample index k at which each via point must be passed."""
        L = len(self.via_points)
        out = []
        for l, vp in enumerate(self.via_points):
            k = vp.sample if vp.sample is not None else int(round((l + 1) * self.N / (L + 1)))
            if not 1 <= k <= self.N - 1:
                raise ValueError(f"via_points[{l}].sample must be in [1, N-1] = [1, {self.N - 1}], got {k}")
            out.append(k)
        return tuple(out)

    def _check_feasible(self):
        """Reject problems that are infeasible on their face (before any solve)."""
        lim = self.robot.limits
        N = self.N
        check_configurations(self.robot, {"q_start": self.q_start, "q_goal": self.q_goal},
                             {"qd_start": self.qd_start, "qd_goal": self.qd_goal})
        rest = not (bool(jnp.any(self.qd_start != 0)) or bool(jnp.any(self.qd_goal != 0)))
        T_need = float(minimum_time_bound(self)) if rest else 0.0
        if T_need > N * lim.h_max * (1 + 1e-9):
            raise ValueError(f"N = {N} is too small: the move needs at least {T_need:.3g} s but "
                             f"N * h_max = {N * lim.h_max:.3g} s; increase N")
        if float(self.T_max) < max(T_need, N * lim.h_min):
            raise ValueError(f"T_max = {float(self.T_max):.4g} s is below the minimum time of this "
                             f"move ({max(T_need, N * lim.h_min):.4g} s: velocity/acceleration bound "
                             f"or N * h_min)")
        if N * lim.h_min > float(self.T_max):
            raise ValueError("T_max is below N * h_min; reduce N")

    def infeasible_on_its_face(self) -> Array:
        """A traced bool: what :meth:`_check_feasible` rejects with a ``ValueError``
        (start or goal outside the joint box, the workspace box or the robot's path
        constraints, boundary velocities beyond ``qd_max``, a move longer than N h_max or
        T_max allow) or :class:`Weights` rejects (a weight negative or not finite, ``U``
        or ``Q`` not finite or with a negative eigenvalue). A batch gives such samples the
        status ``INVALID_INPUT`` instead of solving them."""
        lim = self.robot.limits
        bad = ~admissible_configuration(self.robot, self.q_start) | ~admissible_configuration(self.robot, self.q_goal)
        bad |= self.weights.invalid()
        if lim.qd_max is not None:
            bound = lim.qd_max * (1 + FACE_TOL)
            bad |= jnp.any(jnp.abs(self.qd_start) > bound) | jnp.any(jnp.abs(self.qd_goal) > bound)
        rest = jnp.all(self.qd_start == 0) & jnp.all(self.qd_goal == 0)
        T_need = jnp.where(rest, minimum_time_bound(self), 0.0)
        bad |= T_need > self.N * lim.h_max * (1 + 1e-9)
        bad |= self.T_max < jnp.maximum(T_need, self.N * lim.h_min)
        return bad

    @staticmethod
    def from_task(robot: Robot, p_start, p_goal, *, R_start=None, R_goal=None, q_init=None,
                  ik_method: str = "weighted", ik_starts: int = 8, **kwargs) -> "Problem":
        """Build a problem from task-space start and goal points using inverse kinematics.

        Planar robots: :func:`jtraj.robots.ik.ik` (``ik_method``). Spatial robots (a 3-D
        task point and a ``rotation(q)``: URDF arms, ``gough_stewart``): positions, and
        with ``R_start`` / ``R_goal`` (3, 3) full poses, by
        :func:`jtraj.robots.spatial_ik.solve_pose` (damped least squares in the joint
        box, a null-space term for redundant arms) from ``q_init`` (default the middle
        of the joint box) and ``ik_starts - 1`` seeded starts; the goal's search starts
        at the start's solution. ``kwargs`` go to :class:`Problem`.

        Raises ``ValueError`` when a point or pose is unreachable, with the IK status and
        its residuals in the message.
        """
        spatial = callable(getattr(robot, "rotation", None)) and jax.eval_shape(
            robot.forward_kinematics, jax.ShapeDtypeStruct((robot.n,), jnp.result_type(float))).shape == (3,)
        if not spatial:
            for name, R in (("R_start", R_start), ("R_goal", R_goal)):
                if R is not None:
                    raise ValueError(f"{name} needs a spatial robot (a 3-D task point and a rotation(q) method); "
                                     f"robot {robot.name!r} is not one")
            q_start = ik_or_raise(robot, p_start, q_init, "p_start", ik_method)
            q_goal = ik_or_raise(robot, p_goal, q_start, "p_goal", ik_method)
        else:
            q_start = pose_or_raise(robot, p_start, R_start, q_init, "p_start", ik_starts)
            q_goal = pose_or_raise(robot, p_goal, R_goal, q_start, "p_goal", ik_starts)
        return Problem(robot, q_start, q_goal, **kwargs)


def ik_or_raise(robot, p, q_init, name, method="weighted"):
    """Inverse kinematics for a single point, raising ``ValueError`` naming ``name``."""
    from .robots.ik import ik

    res = ik(robot, p, q_init, method=method)
    if int(res.status) != 0:
        raise ValueError(f"{name} = {np.asarray(p).tolist()} is unreachable for robot "
                         f"{robot.name!r} (IK status {int(res.status)}, residual {float(res.error):.3g} m)")
    return res.q


def pose_or_raise(robot, p, R, q_init, name, starts=8):
    """Spatial inverse kinematics of a position (``R`` None) or a pose, raising
    ``ValueError`` naming ``name`` with the IK status and residuals."""
    from .robots.ik import STATUS
    from .robots.spatial_ik import solve_pose

    res = solve_pose(robot, p, R, q_init, starts=starts)
    status = int(res.status)
    if status != 0:
        what = "position" if R is None else "pose (position and rotation)"
        rot = "" if R is None else f", orientation residual {float(res.rot_error):.3g} rad"
        raise ValueError(f"{name} = {np.asarray(p).tolist()}: this {what} is unreachable for robot {robot.name!r} "
                         f"within its joint limits (IK status {status}: {STATUS.get(status, '?')}; position "
                         f"residual {float(res.error):.3g} m{rot}; {starts} starts tried)")
    return res.q


def _as_via(p, i, d, robot) -> ViaPoint:
    """Validate via point ``i`` of ``robot``, whose task space has dimension ``d``."""
    vp = p if isinstance(p, ViaPoint) else ViaPoint(point=p)
    name = f"via_points[{i}]" + (".point" if isinstance(p, ViaPoint) else "")
    if jnp.shape(vp.point) != (d,):
        raise ValueError(f"{name} must have shape ({d},) (the robot's task space), got shape {jnp.shape(vp.point)}")
    point = as_vector(vp.point, name, d)
    if jnp.ndim(vp.tol) != 0:
        raise ValueError(f"via_points[{i}].tol must be a scalar, got shape {jnp.shape(vp.tol)}")
    if is_concrete(vp.tol) and not (math.isfinite(float(vp.tol)) and float(vp.tol) > 0):
        raise ValueError(f"via_points[{i}].tol must be a finite distance > 0 [m], got {vp.tol!r}")
    rotation = None
    if vp.rotation is not None:
        if not callable(getattr(robot, "rotation", None)):
            raise ValueError(f"via_points[{i}].rotation needs a robot with an orientation (a rotation(q) "
                             f"method); robot {robot.name!r} has none")
        if jnp.shape(vp.rotation) != (3, 3):
            raise ValueError(f"via_points[{i}].rotation must be a (3, 3) rotation matrix, "
                             f"got shape {jnp.shape(vp.rotation)}")
        rotation = jnp.asarray(vp.rotation, dtype=float)
        if is_concrete(rotation):
            Rn = np.asarray(rotation)
            if not (np.all(np.isfinite(Rn)) and np.allclose(Rn.T @ Rn, np.eye(3), atol=1e-9)
                    and np.linalg.det(Rn) > 0):
                raise ValueError(f"via_points[{i}].rotation must be a rotation matrix (R^T R = I, "
                                 f"det R = +1), got {Rn.tolist()}")
        if jnp.ndim(vp.rot_tol) != 0:
            raise ValueError(f"via_points[{i}].rot_tol must be a scalar, got shape {jnp.shape(vp.rot_tol)}")
        if is_concrete(vp.rot_tol) and not (math.isfinite(float(vp.rot_tol)) and 0 < float(vp.rot_tol) < 1):
            raise ValueError(f"via_points[{i}].rot_tol must be in (0, 1) (sin of an angle), got {vp.rot_tol!r}")
    return ViaPoint(point=point, tol=vp.tol, sample=vp.sample, rotation=rotation, rot_tol=vp.rot_tol)


def minimum_time_bound(problem: Problem) -> Array:
    """A lower bound on T from the velocity and acceleration boxes, per joint, for a
    rest-to-rest move: ``T >= max_j max(|dq|/qd_max, 2 sqrt(|dq|/qdd_max))``."""
    lim = problem.robot.limits
    dq = jnp.abs(problem.q_goal - problem.q_start)
    T = jnp.zeros(())
    if lim.qd_max is not None:
        T = jnp.maximum(T, jnp.max(dq / lim.qd_max))
    if lim.qdd_max is not None:
        T = jnp.maximum(T, jnp.max(2 * jnp.sqrt(dq / lim.qdd_max)))
    return T
