"""The IPOPT peer for arms whose dynamics is a CasADi function (the Panda through the
CasADi RNEA): its solutions re-verified with Pinocchio, its cost the verifier's, and the
optimum against a re-solve from another start."""

import numpy as np
import pytest

pytest.importorskip("casadi")
pin = pytest.importorskip("pinocchio")


from jtraj_peers import casadi_rnea as CR  # noqa: E402
from jtraj_peers import ipopt_arm as A  # noqa: E402
from jtraj_peers import verify_arm as VA  # noqa: E402


@pytest.fixture(scope="module")
def panda():
    try:
        model = CR.panda_model()
    except FileNotFoundError as err:
        pytest.skip(str(err))
    lim = CR.model_limits(model)
    spec = A.ArmSpec.make(CR.rnea_function(model), q_min=lim["q_min"], q_max=lim["q_max"], qd_max=lim["qd_max"],
                          qdd_max=10.0, tau_max=lim["tau_max"], h_min=0.005, h_max=0.1)
    return model, lim, spec


def test_panda_move_verified_by_pinocchio(panda):
    model, lim, spec = panda
    lo, hi = lim["q_min"], lim["q_max"]
    rng = np.random.default_rng(0)
    q0 = (lo + hi) / 2 + 0.3 * (hi - lo) * rng.uniform(-1, 1, 7)
    q1 = np.clip(q0 + rng.uniform(-0.5, 0.5, 7), lo, hi)
    N = 8
    r = A.solve_pair(spec, q0, q1, N=N)
    assert r["strict_success"], r["status"]
    kw = dict(tau_max=lim["tau_max"], qd_max=lim["qd_max"], qdd_max=10.0, q_min=lo, q_max=hi, h_min=0.005, h_max=0.1)
    c = VA.verify(model, q0, q1, r["v"], r["h"], **kw)
    assert c["ok"], c["max_rel_violation"]
    assert c["goal_error"] < 1e-8
    assert abs(c["cost"] - r["cost"]) < 1e-10 * r["cost"]
    np.testing.assert_allclose(r["tau"], c["tau"], rtol=0, atol=1e-9 * np.abs(c["tau"]).max())
    # a re-solve from a slower guess ends at a verified local optimum of nearly the same
    # cost (the NLP is not convex: 1.3e-4 relative apart here)
    v0, h0 = A.cycloidal_init(spec, q0, q1, N)
    r2 = A.solve_pair(spec, q0, q1, N=N, init=(0.25 * v0, 2.0 * h0))
    assert r2["strict_success"] and abs(r2["cost"] - r["cost"]) < 1e-3 * r["cost"]
    assert VA.verify(model, q0, q1, r2["v"], r2["h"], **kw)["ok"]
    # a spec's serialised dynamics is the function it was made from
    fn = spec.function()
    q, qd, qdd = rng.uniform(-1, 1, (3, 7))
    ref = pin.rnea(model, model.createData(), q, qd, qdd)
    np.testing.assert_allclose(np.array(fn(q, qd, qdd)).ravel(), ref, rtol=1e-12, atol=1e-12)


def test_spec_rejects_bad_limits(panda):
    _, lim, spec = panda
    fn = spec.function()
    with pytest.raises(ValueError, match="q_min must be < q_max"):
        A.ArmSpec.make(fn, q_min=lim["q_max"], q_max=lim["q_min"], qd_max=1.0, qdd_max=1.0, tau_max=1.0,
                       h_min=0.005, h_max=0.1)
    with pytest.raises(ValueError, match="tau_max"):
        A.ArmSpec.make(fn, q_min=-1, q_max=1, qd_max=1.0, qdd_max=1.0, tau_max=0.0, h_min=0.005, h_max=0.1)


def test_jerk_bound_is_met_and_active(panda):
    """With a jerk bound tight enough to matter, every change of acceleration between
    consecutive intervals stays within jerk_max times the time between their midpoints,
    the bound is active somewhere, and the move is slower than without it."""
    model, lim, spec = panda
    fn = spec.function()
    jerk = 40.0
    tight = A.ArmSpec.make(fn, q_min=lim["q_min"], q_max=lim["q_max"], qd_max=lim["qd_max"], qdd_max=10.0,
                           tau_max=lim["tau_max"], h_min=0.005, h_max=0.1, jerk_max=jerk)
    lo, hi = lim["q_min"], lim["q_max"]
    q0 = (lo + hi) / 2
    q1 = q0 + 0.4
    N = 8
    free, r = A.solve_pair(spec, q0, q1, N=N), A.solve_pair(tight, q0, q1, N=N)
    assert free["strict_success"] and r["strict_success"]
    dv = np.abs(np.diff(r["v"], axis=0))
    dt = 0.5 * (r["h"][1:] + r["h"][:-1])
    ratio = dv / (jerk * dt[:, None])
    assert ratio.max() <= 1 + 1e-6 and ratio.max() > 0.99
    assert r["T"] > free["T"] * (1 + 1e-3)
