"""Reduced runs of examples/mackey_glass.py and examples/neurofuzzy.py.

* Mackey-Glass (Jang 1993 set-up), Jang's grid structure (2 memberships per input, 16
  rules), 5 Levenberg-Marquardt epochs: check RMSE <= 0.003 (measured 0.0019; Jang
  publishes 0.0015-0.0016 after 500 epochs), at least 20x below the linear AR map fitted
  by least squares on the same inputs (measured 0.096), and the premise epochs lower the
  check RMSE of the least-squares start (measured 0.0023).
* NeFIK (task point -> joint angles, 6 rules, 10 epochs) on serial3 joint-space lines
  with the third angle tied to the second (no optimisation; the tip then determines the
  angles): on held-out lines its relative RMSE is below 0.2x the affine least-squares
  map's (measured 0.0033 against 0.069), and the forward kinematics of its prediction
  lands within 5 mm (median) of the test tip points (measured 1.4 mm).
"""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))


def test_mackey_glass_grid_anfis_beats_linear_ar():
    import mackey_glass as ex

    res = ex.run(epochs=5, gradient_epochs=0)
    g, ar = res["grid"], res["ar"]
    assert g["model"].n_rules == 16
    assert g["check"] <= 0.003, g["check"]
    assert g["check"] * 20 <= ar["check"], (g["check"], ar["check"])
    assert g["check"] < g["initial_check"]
    # the AR baseline is the least-squares optimum: no affine map does better on the training pairs
    Xtr, ytr, _, _ = res["data"]
    w = np.linalg.lstsq(np.c_[Xtr, np.ones(len(Xtr))], ytr, rcond=None)[0] * (1 + 1e-3)
    assert ar["train"] <= float(np.sqrt(np.mean((np.c_[Xtr, np.ones(len(Xtr))] @ w - ytr) ** 2)))


@pytest.fixture(scope="module")
def nefik_lines():
    """40 joint-space straight lines of 21 samples in the thesis' region, with q3 tied to
    q2 (q3 = 0.6 q2), so that the tip point determines the joint angles: (robot, X, Y,
    train rows, test rows), the test rows the last 4 lines."""
    from jtraj import robots
    from jtraj.mappings import split

    robot = robots.get("serial3")
    rng = np.random.default_rng(3)
    ends = rng.uniform([-0.3, 0.3], [0.5, 1.2], (40, 2, 2))
    s = np.linspace(0.0, 1.0, 21)[None, :, None]
    q12 = (ends[:, :1] + s * (ends[:, 1:] - ends[:, :1])).reshape(-1, 2)
    Y = np.c_[q12, 0.6 * q12[:, 1]]
    X = np.asarray(jax.vmap(robot.forward_kinematics)(jnp.asarray(Y)))
    tr, te = split(np.repeat(np.arange(40), 21), 0.1)
    return robot, X, Y, tr, te


def test_nefik_on_held_out_trajectories(nefik_lines):
    import neurofuzzy as ex

    robot, X, Y, tr, te = nefik_lines
    r = ex.fit_eval(X, Y, tr, te, n_rules=6, epochs=10)
    assert r["rules"] == 6
    assert ex.relative(r["test"], r["range"]) < 0.2 * ex.relative(r["linear"], r["range"])
    tip = np.asarray(jax.vmap(robot.forward_kinematics)(jnp.asarray(r["pred_test"])))
    err = np.linalg.norm(tip - X[te], axis=1)
    assert np.median(err) < 0.005, np.median(err)
    # without noise the "noisy" test inputs are the clean ones
    np.testing.assert_allclose(r["test"], r["test_noisy"], rtol=1e-12)


def test_input_noise_disturbs_inputs_only(nefik_lines):
    import neurofuzzy as ex

    _, X, Y, tr, te = nefik_lines
    r = ex.fit_eval(X, Y, tr, te, n_rules=6, epochs=2, noise=0.05, seed=1)
    # the clean and the disturbed test inputs give different errors; the targets are untouched
    assert not np.allclose(r["test"], r["test_noisy"])
    np.testing.assert_allclose(r["range"], Y.max(0) - Y.min(0))
