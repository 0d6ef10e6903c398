"""Deterministic sampling of start/goal pairs.

Pairs are drawn in fixed *sampling blocks* of :data:`BLOCK` consecutive pairs; block
``b`` uses its own generator ``numpy.random.default_rng([seed, b])``. Pair ``i`` is
therefore a function of ``(seed, i)`` and of the distribution only: it does not depend
on the batch size, on the total number of pairs (a run of 96 pairs is the prefix of a
run of 1,000 with the same seed), on the order in which chunks are computed, or on which
process (or Ray worker) computes them.

Distributions (``space``):

``"joint"`` (default)
    ``q_start ~ U(lo, hi)^n`` with ``lo = max(-start_range, q_min)``,
    ``hi = min(start_range, q_max)`` per joint (``start_range`` = 1.2 rad by default;
    robots without a joint box: ``U(-1.2, 1.2)^n``, the benchmark family of
    ``jtraj_peers.pairs.benchmark_pairs``), then
    ``q_goal = q_start + U(-step_range, step_range)^n`` (``step_range`` = 0.8 rad).
    A candidate pair is rejected and redrawn (from the same block generator) when
    ``|q_goal - q_start|_2 < min_separation`` (default 0.05 rad), when the goal leaves
    the joint box, or when its start or goal puts the task point outside the robot's
    workspace box or violates its path constraints (``robot.path_constraints``, e.g.
    the leg-singularity margins of ``parallel3``), which :class:`jtraj.Problem` would
    refuse. So pairs are uniform over the admissible part of (start box) x (step cube).
    With no joint box and no such constraints (``serial3``), rejection only removes a
    ball of radius 0.05 from the step cube, about 1e-4 of its volume. Goals are
    redrawn, not clipped into the joint box: on a small box such as ``parallel3``'s,
    clipping would put about half of them exactly on its boundary. Where
    ``max_move_time`` is set, a pair is also redrawn when its rest-to-rest move needs
    longer than that by the velocity and acceleration bounds
    (:func:`jtraj.problem.minimum_time_bound`): a dataset sets it to ``N h_max``
    (:func:`jtraj.dataset.make_spec`) where a step of the law could need longer, i.e.
    for a joint whose velocity bound is small against ``step_range`` (a telescopic
    torso at 0.035 m/s), whose steps would otherwise be mostly infeasible on their face.

``"task"``
    Task points uniform over the reachable workspace: ``p ~ U(box)`` where ``box`` is
    ``robot.limits.workspace`` when set, otherwise the bounding box of the forward
    kinematics of 4,096 configurations drawn from the joint box (or ``[-pi, pi]^n``),
    and a point is kept only when inverse kinematics
    (:func:`jtraj.robots.ik.ik`, ``method=ik_method``) reaches it (status 0): rejection
    sampling, hence uniform over the reachable part of the box. ``q_start`` is the IK
    solution from a start drawn as in the joint space case; ``q_goal`` is the IK
    solution of the goal point started from ``q_start`` (the nearest branch). Pairs
    with ``|p_goal - p_start|_2 < min_separation`` (task units, default 0.05), or
    whose start or goal configuration violates the robot's path constraints, are
    rejected.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import equinox as eqx
import numpy as np

#: pairs per sampling block (part of the definition of the distribution; do not change)
BLOCK = 64
_MAX_ROUNDS = 1000


@dataclass(frozen=True)
class Distribution:
    """How pairs are drawn (stored in the dataset metadata)."""

    space: str = "joint"
    start_range: float = 1.2
    step_range: float = 0.8
    min_separation: float = 0.05
    ik_method: str = "weighted"
    #: seconds; None: no bound on the move's minimum time (see the module docstring)
    max_move_time: float | None = None

    @classmethod
    def from_record(cls, record: dict) -> "Distribution":
        """The distribution that :meth:`describe` wrote ``record`` of (a dataset's
        ``identity["distribution"]``)."""
        return cls(**{k: record[k] for k in ("space", "start_range", "step_range", "min_separation", "ik_method")},
                   max_move_time=record.get("max_move_time"))

    def __post_init__(self):
        if self.space not in ("joint", "task"):
            raise ValueError(f"space must be 'joint' or 'task', got {self.space!r}")
        for name in ("start_range", "step_range"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
        if not (math.isfinite(self.min_separation) and self.min_separation >= 0):
            raise ValueError(f"min_separation must be a finite number >= 0, got {self.min_separation!r}")
        if self.max_move_time is not None and not (math.isfinite(self.max_move_time) and self.max_move_time > 0):
            raise ValueError(f"max_move_time must be a finite number of seconds > 0 or None, got "
                             f"{self.max_move_time!r}")
        if self.max_move_time is not None and self.space != "joint":
            raise ValueError("max_move_time applies to the joint-space law only")
        if self.space == "joint" and self.min_separation >= self.step_range * math.sqrt(3):
            raise ValueError(f"min_separation {self.min_separation} is too large for step_range {self.step_range}")

    def describe(self) -> dict:
        d = asdict(self)
        if self.max_move_time is None:  # absent, so that the identities of datasets without it stay
            del d["max_move_time"]
        d["block"] = BLOCK
        d["generator"] = "numpy.random.default_rng([seed, block]) (PCG64)"
        if self.space == "joint":
            d["law"] = ("q_start ~ U(max(-start_range, q_min), min(start_range, q_max))^n; "
                        "q_goal = q_start + U(-step_range, step_range)^n; redrawn unless q_goal is in the joint "
                        "box; "
                        "rejected if |q_goal - q_start|_2 < min_separation or if q_start or q_goal violates the "
                        "workspace box or the robot's path constraints"
                        + ("" if self.max_move_time is None else
                           f"; rejected if the rest-to-rest move needs more than max_move_time = "
                           f"{self.max_move_time:.6g} s (N h_max) by the velocity and acceleration bounds "
                           "(max_j max(|dq_j| / qd_max_j, 2 sqrt(|dq_j| / qdd_max_j)))"))
        else:
            d["law"] = ("p_start, p_goal ~ U(workspace box), kept when IK reaches them (uniform over the "
                        "reachable workspace); q_start = ik(p_start, q ~ joint-space start law); "
                        "q_goal = ik(p_goal, q_start); rejected if |p_goal - p_start|_2 < min_separation or if q_start "
                        "or q_goal violates the robot's path constraints")
        return d


def _joint_box(robot):
    n = robot.n
    lim = robot.limits
    q_min = np.full(n, -np.inf) if lim.q_min is None else np.asarray(lim.q_min, float)
    q_max = np.full(n, np.inf) if lim.q_max is None else np.asarray(lim.q_max, float)
    return q_min, q_max


def start_box(robot, dist: Distribution):
    """Per-joint (lo, hi) of the start law; raises if a joint range is empty."""
    q_min, q_max = _joint_box(robot)
    lo = np.maximum(-dist.start_range, q_min)
    hi = np.minimum(dist.start_range, q_max)
    if np.any(lo >= hi):
        raise ValueError(f"the start range [-{dist.start_range}, {dist.start_range}] does not meet the "
                         f"joint box of robot {robot.name!r} (q_min={q_min.tolist()}, q_max={q_max.tolist()})")
    return lo, hi


def check(robot, dist: Distribution) -> None:
    """Raise ``ValueError`` when ``dist`` cannot be sampled for ``robot`` (before any compute)."""
    start_box(robot, dist)
    if dist.space == "task":
        try:
            from jtraj.robots import ik  # noqa: F401
        except ImportError as err:  # pragma: no cover - depends on the tree
            raise ValueError(f"--space task needs jtraj.robots.ik ({err})") from err
        from jtraj.robots.ik import METHODS

        if dist.ik_method not in METHODS:
            raise ValueError(f"ik_method must be one of {METHODS}, got {dist.ik_method!r}")


def admissible(robot, q):
    """(B,) bool: rows of ``q`` (B, n) that :func:`jtraj.problem.admissible_configuration`
    accepts (joint box, workspace box and path constraints)."""
    return np.asarray(_admissible_jit(robot, np.asarray(q, float)))


@eqx.filter_jit  # module level: compiled once per robot and shape, not at every round
def _admissible_jit(robot, q):
    import jax

    from jtraj.problem import admissible_configuration

    return jax.vmap(lambda x: admissible_configuration(robot, x))(q)


def move_time(robot, dq):
    """(B,) :func:`jtraj.problem.minimum_time_bound` of the rest-to-rest moves ``dq`` (B, n),
    in NumPy: float64 whatever JAX's precision setting, so that which pairs a dataset
    keeps does not depend on it."""
    lim = robot.limits
    dq = np.abs(np.asarray(dq, float))
    T = np.zeros(dq.shape[0])
    if lim.qd_max is not None:
        T = np.maximum(T, np.max(dq / np.asarray(lim.qd_max, float), axis=1))
    if lim.qdd_max is not None:
        T = np.maximum(T, np.max(2 * np.sqrt(dq / np.asarray(lim.qdd_max, float)), axis=1))
    return T


def longest_step_time(robot, dist: Distribution) -> float:
    """The longest :func:`move_time` of a step the joint-space law can draw (each joint's
    step up to ``step_range`` and the width of its joint box)."""
    q_min, q_max = _joint_box(robot)
    return float(move_time(robot, np.minimum(dist.step_range, q_max - q_min)[None])[0])


def _block_joint(robot, dist, seed, b):
    rng = np.random.default_rng([seed, b])
    n = robot.n
    lo, hi = start_box(robot, dist)
    qs, qg = [], []
    count = 0
    for _ in range(_MAX_ROUNDS):
        u = rng.random((BLOCK, 2, n))
        a = lo + (hi - lo) * u[:, 0]
        g = a + dist.step_range * (2 * u[:, 1] - 1)
        ok = (np.linalg.norm(g - a, axis=1) >= dist.min_separation) & admissible(robot, a) & admissible(robot, g)
        if dist.max_move_time is not None:
            ok &= move_time(robot, g - a) <= dist.max_move_time
        qs.append(a[ok])
        qg.append(g[ok])
        count += int(ok.sum())
        if count >= BLOCK:
            return np.concatenate(qs)[:BLOCK], np.concatenate(qg)[:BLOCK]
    raise ValueError("could not draw pairs with the requested minimum separation inside the robot's joint box, "
                     "workspace box and path constraints"
                     + ("" if dist.max_move_time is None else f" that move within {dist.max_move_time:g} s"))


_WORKSPACE_CACHE: dict = {}


def workspace_box(robot):
    """(2, d) box from which task points are drawn (see the module docstring)."""
    import jax

    lim = robot.limits
    if lim.workspace is not None:
        return np.asarray(lim.workspace, float)
    key = id(robot)
    if key not in _WORKSPACE_CACHE:
        q_min, q_max = _joint_box(robot)
        lo = np.where(np.isfinite(q_min), q_min, -np.pi)
        hi = np.where(np.isfinite(q_max), q_max, np.pi)
        q = lo + (hi - lo) * np.random.default_rng(0).random((4096, robot.n))
        p = np.asarray(jax.vmap(robot.forward_kinematics)(q))
        _WORKSPACE_CACHE[key] = (robot, np.stack([p.min(0), p.max(0)]))
    return _WORKSPACE_CACHE[key][1]


def _ik_batch(robot, p, q_init, method):
    import jax

    from jtraj.robots.ik import ik

    res = jax.vmap(lambda pp, qq: ik(robot, pp, qq, method=method))(p, q_init)
    return np.asarray(res.q), np.asarray(res.status)


def _block_task(robot, dist, seed, b):
    rng = np.random.default_rng([seed, b])
    n = robot.n
    lo, hi = start_box(robot, dist)
    box = workspace_box(robot)
    d = box.shape[1]
    qs, qg = [], []
    count = 0
    for _ in range(_MAX_ROUNDS):
        u = rng.random((BLOCK, 2 * d + n))
        p0 = box[0] + (box[1] - box[0]) * u[:, :d]
        p1 = box[0] + (box[1] - box[0]) * u[:, d:2 * d]
        q_init = lo + (hi - lo) * u[:, 2 * d:]
        sep = np.linalg.norm(p1 - p0, axis=1) >= dist.min_separation
        a, s0 = _ik_batch(robot, p0, q_init, dist.ik_method)
        g, s1 = _ik_batch(robot, p1, a, dist.ik_method)
        ok = sep & (s0 == 0) & (s1 == 0) & admissible(robot, a) & admissible(robot, g)
        qs.append(a[ok])
        qg.append(g[ok])
        count += int(ok.sum())
        if count >= BLOCK:
            return np.concatenate(qs)[:BLOCK], np.concatenate(qg)[:BLOCK]
    raise ValueError("could not draw reachable task-space pairs (is the workspace box sensible?)")


def sample_pairs(robot, dist: Distribution, seed: int, start: int, stop: int):
    """Pairs ``start .. stop-1`` of the run with ``seed``: ``(q_start, q_goal)``, each (stop-start, n)."""
    if not (0 <= start < stop):
        raise ValueError(f"need 0 <= start < stop, got {start}, {stop}")
    fn = _block_joint if dist.space == "joint" else _block_task
    b0, b1 = start // BLOCK, (stop - 1) // BLOCK
    parts = [fn(robot, dist, seed, b) for b in range(b0, b1 + 1)]
    qs = np.concatenate([p[0] for p in parts])
    qg = np.concatenate([p[1] for p in parts])
    off = start - b0 * BLOCK
    return qs[off:off + stop - start].copy(), qg[off:off + stop - start].copy()
