"""Gradient checks: jax.grad vs the hand-written discrete adjoint and central FD.

Each robot costs one compilation (~10 s on 2 cores), so the points are few and N small.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtraj import gradcheck as gc
from jtraj import Weights, robots
from jtraj.robots.serial import SerialPlanar, serial_planar
from jtraj import _testing


# The serial arms compile in ~10 s; the closed-chain and mobile models take about a
# minute each on 2 cores, so they run with -m slow (and in `jtraj gradcheck --robot all`).
FAST = ("serial3",)


def _robot_params():
    out = []
    for name in robots.names():
        marks = [] if name in FAST else [pytest.mark.slow]
        out.append(pytest.param(name, marks=marks, id=name))
    return out


@pytest.mark.parametrize("name", _robot_params())
def test_adjoint_and_fd_agree_with_autodiff(name):
    report = gc.gradcheck(name, N=5, points=2, seed=1)
    print(gc.format_table(report))
    (r,) = report.results
    if r.status == "skipped":
        assert name not in FAST and "not available" in r.note
        pytest.skip(r.note)
    assert r.status == "ok", (r.robot, r.note)
    assert r.cost_adjoint <= 1e-8 and r.al_adjoint <= 1e-8, r
    assert r.cost_fd <= 1e-6 and r.al_fd <= 1e-6, r
    for p in r.per_point:  # non-trivial gradients were compared
        assert p["cost_grad_norm"] > 1e-3 and p["al_grad_norm"] > 1e-3
    assert report.passed and name in gc.format_table(report)


def _small_arm():
    """A cheap 2-link arm in a vertical plane with torque, velocity, acceleration and joint boxes."""
    return serial_planar((0.6, 0.4), (3.0, 2.0), (0.2, 0.1), gravity=9.81, name="arm2",
                         limits=dict(tau_max=(30.0, 15.0), qd_max=2.0, qdd_max=4.0,
                                     q_min=(-3.0, -3.0), q_max=(3.0, 3.0)))


def _wrong_adjoint(v, h, q, qd, dl):
    """The classic slip: p_qd,k forgets the h_k p_q,k+1 coupling of q_{k+1} on qd_k."""
    lq, lqd, lv, lh = dl
    N = h.shape[0]
    p_q, p_qd = lq[N], lqd[N]
    gv, gh = [None] * N, [None] * N
    for k in range(N - 1, -1, -1):
        gv[k] = lv[k] + 0.5 * h[k] ** 2 * p_q + h[k] * p_qd
        gh[k] = lh[k] + jnp.dot(qd[k] + h[k] * v[k], p_q) + jnp.dot(v[k], p_qd)
        p_q, p_qd = lq[k] + p_q, lqd[k] + p_qd
    return jnp.stack(gv), jnp.stack(gh)


# the negative test uses a cheap arm and no singularity term (faster compilation)
_W = Weights(time=1.0, energy=1.0, kinetic=0.1)


@jax.custom_jvp
def _id_forces(robot, q, qd, qdd):
    return SerialPlanar.rigid_body_forces(robot, q, qd, qdd)


@_id_forces.defjvp
def _id_forces_jvp(primals, tangents):
    # a derivative rule that is 1 % off: autodiff (and the adjoint, which uses local
    # autodiff) inherit it; only finite differences can see it
    out, dout = jax.jvp(lambda *a: SerialPlanar.rigid_body_forces(*a), primals, tangents)
    return out, 1.01 * dout


class _BadDerivativeArm(SerialPlanar):
    def rigid_body_forces(self, q, qd, qdd):
        return _id_forces(self, q, qd, qdd)


@pytest.mark.slow  # the checker's own test (the default suite checks serial3 passes)
def test_checker_can_fail():
    """Two faults injected at once, each visible to one comparison only (one compile):

    * the adjoint recursion forgets the ``h_k p_q,k+1`` term of ``p_qd,k``: only the
      autodiff-vs-adjoint comparison can see it;
    * the arm's inverse dynamics carries a derivative rule 1 % off (custom_jvp): autodiff
      *and* the adjoint's local partials inherit it, so they still agree with each
      other; only finite differences can see it.
    """
    arm = _small_arm()
    bad_arm = _BadDerivativeArm(**{f: getattr(arm, f) for f in
                                   ("limits", "friction", "actuator", "lengths", "masses", "inertias", "com",
                                    "gravity_accel", "label")})
    res = gc.gradcheck_robot(bad_arm, N=4, points=1, seed=3, weights=_W, adjoint=_wrong_adjoint)
    assert res.status == "FAIL" and not res.passed
    assert res.cost_adjoint > 1e-4 and res.al_adjoint > 1e-4
    assert res.cost_fd > 1e-4 and max(res.cost_fd, res.al_fd) > gc.TOL_FD
    report = gc.Report(results=[res])
    assert not report.passed and "FAILED" in gc.format_table(report)


def test_missing_model_is_skipped(monkeypatch):
    monkeypatch.setitem(robots._REGISTRY, "not_yet", "jtraj.robots.not_yet_written:factory")
    res = gc.gradcheck_robot("not_yet", N=3, points=1)
    assert res.status == "skipped" and res.passed and "not available" in res.note
    with pytest.raises(ValueError, match="robot"):
        gc.gradcheck_robot("no_such_robot")


def test_fd_step_and_error_measure():
    assert _testing.gradcheck_rel((np.zeros(3), np.ones(2)), (np.zeros(3), np.ones(2))) == 0.0
    assert math.isclose(_testing.gradcheck_rel((np.array([1.0, 2.0]),), (np.array([1.0, 2.2]),)), 0.2 / 2.2)
    assert _testing.gradcheck_rel((np.array([np.nan]),), (np.array([1.0]),)) == math.inf
