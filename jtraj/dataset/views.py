"""Learning views of a dataset: (inputs, targets, trajectory index) per sample.

Each view returns a :class:`View` ``(X, Y, traj)``: one row per time sample, and
``traj[i]`` the pair index of row ``i``'s trajectory, so that train/test splits can be
made by trajectory (never splitting one trajectory across sets)::

    X, Y, traj = views.nefotc(data)
    test = np.isin(traj, rng.choice(np.unique(traj), 100, replace=False))

Only converged trajectories are used unless ``converged_only=False``.

* :func:`nefotc` (neuro-fuzzy optimal trajectory controller): ``X = (q_k, qd_k)``
  (2n columns), ``Y = tau_k`` (m columns), k = 0..N-1.
* :func:`nefumop` (neuro-fuzzy motion planner): ``X = (p_k, pd_k)`` with the task
  point ``p = f(q)`` and its velocity ``pd = J(q) qd`` (for planar arms
  ``(x, y, xd, yd)``), ``Y = (tau_k, h_k)``, k = 0..N-1.
* :func:`nefik` (neuro-fuzzy inverse kinematics): ``X = p_k``, ``Y = q_k``, k = 0..N.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import numpy as np


class View(NamedTuple):
    X: np.ndarray
    Y: np.ndarray
    traj: np.ndarray


def _select(data, converged_only):
    conv = np.asarray(data["converged"], bool)
    sel = conv if converged_only else np.ones_like(conv)
    return sel, np.asarray(data["index"])[sel]


def _rows(a):
    """(P', K, c) -> (P' K, c)."""
    a = np.asarray(a)
    return a.reshape(a.shape[0] * a.shape[1], *a.shape[2:])


def _traj(index, K):
    return np.repeat(index, K)


def robot_of(data):
    """The robot a dataset was made with (:func:`jtraj.robots.from_metadata`: the built-in
    robot it names, or the URDF arm it stores; with its sampling-period bound)."""
    from jtraj import robots

    return robots.from_metadata(data["metadata"])


def nefotc(data, *, converged_only: bool = True) -> View:
    """``(q, qd) -> tau`` per time sample k = 0..N-1."""
    sel, idx = _select(data, converged_only)
    q, qd, tau = data["q"][sel][:, :-1], data["qd"][sel][:, :-1], data["tau"][sel]
    N = tau.shape[1]
    X = np.concatenate([_rows(q), _rows(qd)], axis=1)
    return View(X, _rows(tau), _traj(idx, N))


def task_state(robot, q, qd):
    """Task point ``p = f(q)`` and its velocity ``pd = J(q) qd`` for rows of ``q``, ``qd``."""
    p, pd = _task_state_jit(robot, np.asarray(q, float), np.asarray(qd, float))
    return np.asarray(p), np.asarray(pd)


@eqx.filter_jit  # module level: compiled once per robot and shape, not at every call
def _task_state_jit(robot, q, qd):
    import jax

    return jax.vmap(lambda q_, qd_: jax.jvp(robot.forward_kinematics, (q_,), (qd_,)))(q, qd)


def nefumop(data, *, converged_only: bool = True, robot=None) -> View:
    """``(p, pd) -> (tau, h)`` per time sample k = 0..N-1 (``p = f(q)``, ``pd = J(q) qd``)."""
    sel, idx = _select(data, converged_only)
    robot = robot or robot_of(data)
    tau, h = data["tau"][sel], data["h"][sel]
    N = tau.shape[1]
    q, qd = _rows(data["q"][sel][:, :-1]), _rows(data["qd"][sel][:, :-1])
    if len(q) == 0:
        d = 0
        p = pd = np.zeros((0, d))
    else:
        p, pd = task_state(robot, q, qd)
    X = np.concatenate([p, pd], axis=1)
    Y = np.concatenate([_rows(tau), _rows(h[..., None])], axis=1)
    return View(X, Y, _traj(idx, N))


def nefik(data, *, converged_only: bool = True, robot=None) -> View:
    """``p -> q`` per time sample k = 0..N."""
    sel, idx = _select(data, converged_only)
    robot = robot or robot_of(data)
    q = data["q"][sel]
    K = q.shape[1]
    qr = _rows(q)
    p = task_state(robot, qr, np.zeros_like(qr))[0] if len(qr) else np.zeros((0, 0))
    return View(p, qr, _traj(idx, K))
