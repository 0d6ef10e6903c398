"""jtraj.anfis: clustering as MATLAB subclust, Jang's public benchmarks, save/load, bad input.

Tolerances (float64, conftest enables x64):
* Mackey-Glass (Jang 1993 set-up, 16 rules, first-order TSK): check RMSE <= 0.003
  (Jang: 0.0016; we measure about 0.0011).
* Two-input sinc (121 grid samples, 16 rules): training RMSE <= 0.02, RMSE on a 41 x 41
  grid of the square <= 0.05 (measured 0.006 / 0.024).
* Mackey-Glass with Tsukamoto consequents, 30 epochs: check RMSE <= 0.004 (measured 0.0021).
"""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtraj import anfis
from jtraj.anfis import datasets
from jtraj.anfis.clustering import potentials, subclust


def rmse(a, b):
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


@pytest.fixture(scope="module")
def mackey_glass():
    return datasets.jang_mackey_glass()


@pytest.fixture(scope="module")
def mg_model(mackey_glass):
    Xtr, ytr, _, _ = mackey_glass
    return anfis.train(Xtr, ytr, n_rules=16)


@pytest.fixture(scope="module")
def sinc():
    return datasets.jang_sinc()


# ----------------------------------------------------------------------------- data
def test_mackey_glass_series_is_converged_in_step():
    _, x1 = datasets.mackey_glass(400.0, dt=0.02)
    _, x2 = datasets.mackey_glass(400.0, dt=0.01)
    assert x1[0] == 1.2
    assert np.max(np.abs(x1 - x2)) < 1e-5
    assert 0.2 < x2[100:].min() and x2[100:].max() < 1.4


def test_mackey_glass_series_against_the_method_of_steps():
    # an independent delay-equation solution: x' = a x(t - tau) / (1 + x(t - tau)^10) - b x
    # with zero history, integrated segment by segment (length tau) by SciPy's DOP853,
    # the delayed term read from the previous segment's dense output
    from scipy.integrate import solve_ivp

    tau, a, b = 17.0, 0.2, 0.1
    segs, x = [], 1.2
    for k in range(24):  # up to 408
        prev = segs[k - 1].sol if k else (lambda s: np.zeros(1))

        def f(t, y, prev=prev):
            d = prev(t - tau)[0]
            return [a * d / (1 + d**10) - b * y[0]]

        segs.append(solve_ivp(f, (k * tau, (k + 1) * tau), [x], method="DOP853", dense_output=True,
                              rtol=1e-12, atol=1e-13))
        x = segs[-1].y[0, -1]
    ref = np.array([segs[min(int(t // tau), 23)].sol(t)[0] for t in range(401)])
    _, series = datasets.mackey_glass(400.0)
    np.testing.assert_allclose(series, ref, rtol=0, atol=1e-5)  # measured 7.4e-7


# ----------------------------------------------------------------------------- clustering
def test_potentials_match_direct_formula_and_chunking():
    rng = np.random.default_rng(1)
    Z = rng.random((300, 3))
    r = np.array([0.3, 0.5, 0.4])
    D = (Z[:, None, :] - Z[None, :, :]) / r
    direct = np.exp(-4 * np.sum(D**2, -1)).sum(1)
    np.testing.assert_allclose(potentials(Z, r), direct, rtol=1e-12)
    np.testing.assert_allclose(potentials(Z, r, chunk_bytes=8 * 300 * 3 * 7), direct, rtol=1e-12)


def _reference_subclust(X, ra, sq, acc, rej):
    """Loop-by-loop transcription of the MATLAB algorithm with MATLAB's complex
    comparison for the first centre (real part of ratio + i compared with 1)."""
    lo, hi = X.min(0), X.max(0)
    Z = (X - lo) / (hi - lo)
    P = len(Z)
    pot = np.array([np.sum(np.exp(-4 * np.sum(((Z[i] - Z) / ra) ** 2, 1))) for i in range(P)])
    i = int(np.argmax(pot))
    ref = best = pot[i]
    C = []
    while best > 0:
        ratio = best / ref
        if ratio > acc:
            take = True
        elif ratio > rej:
            dmin = complex(0, 1) if not C else math.sqrt(min(np.sum(((Z[i] - c) / ra) ** 2) for c in C))
            take = (ratio + dmin).real >= 1
        else:
            break
        if take:
            C.append(Z[i].copy())
            pot = np.maximum(pot - best * np.exp(-4 * np.sum(((Z[i] - Z) / (sq * ra)) ** 2, 1)), 0)
        else:
            pot[i] = 0
        i = int(np.argmax(pot))
        best = pot[i]
    return np.array(C) * (hi - lo) + lo


@pytest.mark.parametrize("settings", [(0.5, 1.25, 0.5, 0.15), (0.3, 1.25, 0.5, 0.15), (0.9, 0.5, 1.0, 0.8)])
def test_subclust_matches_reference_transcription(settings):
    ra, sq, acc, rej = settings
    rng = np.random.default_rng(0)
    X = np.concatenate([rng.normal(m, 0.3, (60, 2)) for m in ((0, 0), (3, 1), (1, 4))]) * [1.0, 10.0]
    cl = subclust(X, ra, squash=sq, accept=acc, reject=rej)
    ref = _reference_subclust(X, ra, sq, acc, rej)
    assert cl.centers.shape[0] >= 1
    np.testing.assert_allclose(cl.centers, ref, rtol=1e-12)
    np.testing.assert_allclose(cl.sigmas, ra * (X.max(0) - X.min(0)) / math.sqrt(8), rtol=1e-12)


def test_first_centre_quirk_thesis_settings_find_rules():
    """Radius 0.9, squash 0.5, accept 1.0, reject 0.8: a literal real-arithmetic port
    finds no rule; MATLAB (and jtraj) accept the first centre."""
    rng = np.random.default_rng(3)
    X = rng.random((200, 3))
    cl = subclust(X, 0.9, squash=0.5, accept=1.0, reject=0.8)
    assert cl.centers.shape[0] >= 1
    pot = potentials((X - X.min(0)) / (X.max(0) - X.min(0)), 0.9)
    np.testing.assert_allclose(cl.centers[0], X[np.argmax(pot)])


def test_radius_for_rules_hits_count(mackey_glass):
    Xtr, ytr, _, _ = mackey_glass
    r, cl = anfis.radius_for_rules(np.c_[Xtr, ytr], 16)
    assert cl.centers.shape[0] == 16 and 0.05 < r < 1.0


# ----------------------------------------------------------------------------- benchmarks
def test_mackey_glass_16_rules(mackey_glass, mg_model):
    _, _, Xck, yck = mackey_glass
    model, hist = mg_model
    assert model.n_rules == 16
    err = rmse(model.predict(Xck), yck)
    assert err <= 0.003, err
    assert hist.val_rmse[hist.best_epoch] < hist.val_rmse[0]  # training improved on genfis2 + LSE


def test_sinc_tsk(sinc):
    Xtr, ytr, Xck, yck = sinc
    model, hist = anfis.train(Xtr, ytr, n_rules=16, validation=0)
    assert rmse(model.predict(Xtr), ytr) <= 0.02
    assert rmse(model.predict(Xck), yck) <= 0.05


def test_mackey_glass_tsukamoto(mackey_glass):
    Xtr, ytr, Xck, yck = mackey_glass
    model = anfis.fit(Xtr, ytr, n_rules=16, kind="tsukamoto", epochs=30)
    assert model.kind == "tsukamoto"
    assert rmse(model.predict(Xck), yck) <= 0.004
    rho, s = model.tsukamoto_parameters()
    assert rho.shape == (16, 1) and s.shape == (16, 1)


def test_multi_output_zero_order_and_shapes():
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (300, 3))
    Y = np.c_[np.sin(2 * X[:, 0]) + X[:, 1], X[:, 2] ** 2 - X[:, 0]]
    model, hist = anfis.train(X, Y, radius=0.6, epochs=15, order=0)
    assert model.predict(X).shape == (300, 2) and model.predict(X[0]).shape == (2,)
    np.testing.assert_allclose(model.predict(X[0]), model.predict(X)[0], rtol=1e-12)
    assert hist.train_rmse[-1] < 0.5 * hist.train_rmse[0]
    assert rmse(model.predict(X), Y) < 0.05


def test_log_space_firing_no_underflow():
    """Eight inputs, every one 15 widths from the nearest centre: w = exp(-900)
    underflows to 0 in float64, the normalised strengths must not be 0/0."""
    d, R = 8, 3
    c = np.linspace(0.2, 0.8, R)[:, None] * np.ones((R, d))
    model = anfis.Model(jnp.asarray(c), jnp.full((R, d), 0.05), jnp.asarray(np.arange(R * (d + 1), dtype=float)
                                                                           .reshape(R, d + 1, 1)),
                        jnp.zeros(d), jnp.ones(d), jnp.zeros(1), jnp.ones(1), scalar_output=True)
    far = np.full((1, d), 0.8 + 15 * 0.05)
    y = np.asarray(model.predict(far))
    beta = np.asarray(model.firing(far))
    assert np.isfinite(y).all() and np.isfinite(beta).all()
    np.testing.assert_allclose(beta.sum(), 1.0, rtol=1e-12)
    np.testing.assert_allclose(beta[0, -1], 1.0, rtol=1e-12)  # the nearest rule takes it all
    assert np.exp(-0.5 * d * 15**2) == 0.0  # the naive product would be 0 / 0


# ----------------------------------------------------------------------------- save / load
def test_save_load_roundtrip(tmp_path, mg_model, mackey_glass):
    model, _ = mg_model
    model = model.with_metadata(mapping="mg")
    path = tmp_path / "mg.anfis"
    model.save(path)
    back = anfis.load(path, mapping="mg")
    _, _, Xck, _ = mackey_glass
    np.testing.assert_array_equal(np.asarray(back.predict(Xck)), np.asarray(model.predict(Xck)))
    assert back.metadata["n_rules"] == 16 and back.kind == model.kind
    with pytest.raises(ValueError, match="mapping"):
        anfis.load(path, mapping="nefotc")


def test_clip_outputs_bounds_predictions_and_survives_save(tmp_path):
    rng = np.random.default_rng(3)
    X = rng.uniform(-1, 1, (300, 2))
    Y = np.c_[np.tanh(4 * X[:, 0]), X[:, 0] * X[:, 1]]
    model = anfis.fit(X, Y, n_rules=6, epochs=5, order=1)
    Xq = rng.uniform(-3, 3, (2000, 2))  # far outside the training box too
    raw = np.asarray(model.predict(Xq))
    clipped = model.with_clip()
    P = np.asarray(clipped.predict(Xq))
    lo, hi = np.asarray(model.y_lo), np.asarray(model.y_lo + model.y_span)
    assert np.all(P >= lo - 1e-12) and np.all(P <= hi + 1e-12)
    np.testing.assert_allclose(P, np.clip(raw, lo, hi), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(jax.jit(clipped.predict_fn())(jnp.asarray(Xq))), P, rtol=1e-12)
    clipped.save(tmp_path / "c.anfis")
    back = anfis.load(tmp_path / "c.anfis")
    assert back.clip_outputs
    np.testing.assert_array_equal(np.asarray(back.predict(Xq)), P)


def test_load_rejects_other_version_and_junk(tmp_path, mg_model):
    model, _ = mg_model
    path = tmp_path / "m.anfis"
    model.save(path)
    raw = path.read_bytes()
    head, rest = raw.split(b"\n", 1)
    h = json.loads(head)
    h["version"] = 999
    (tmp_path / "v.anfis").write_bytes(json.dumps(h).encode() + b"\n" + rest)
    with pytest.raises(ValueError, match="version"):
        anfis.load(tmp_path / "v.anfis")
    # files of format 1 (single models, before ensembles) are still read
    h["version"] = 1
    (tmp_path / "v1.anfis").write_bytes(json.dumps(h).encode() + b"\n" + rest)
    np.testing.assert_array_equal(np.asarray(anfis.load(tmp_path / "v1.anfis").centers), np.asarray(model.centers))
    (tmp_path / "junk.anfis").write_bytes(b"hello\nworld")
    with pytest.raises(ValueError, match="not a jtraj ANFIS model"):
        anfis.load(tmp_path / "junk.anfis")
    (tmp_path / "trunc.anfis").write_bytes(raw[: len(head) + 20])
    with pytest.raises(ValueError, match="corrupted"):
        anfis.load(tmp_path / "trunc.anfis")


# ----------------------------------------------------------------------------- bad input
def test_bad_input():
    rng = np.random.default_rng(0)
    X = rng.random((50, 2))
    y = X.sum(1)
    with pytest.raises(ValueError, match="different numbers of samples"):
        anfis.fit(X, y[:40])
    Xn = X.copy()
    Xn[3, 1] = np.nan
    with pytest.raises(ValueError, match="X contains NaN"):
        anfis.fit(Xn, y)
    with pytest.raises(ValueError, match="Y contains NaN"):
        anfis.fit(X, np.where(np.arange(50) == 7, np.nan, y))
    with pytest.raises(ValueError, match="fewer training samples"):
        anfis.fit(X, y, n_rules=60)
    with pytest.raises(ValueError, match="yields no rule"):
        anfis.fit(X, y, radius=0.5, reject=1.0, accept=1.0)
    with pytest.raises(ValueError, match="radius"):
        anfis.fit(X, y, radius=0.0)
    with pytest.raises(ValueError, match="kind"):
        anfis.fit(X, y, kind="mamdani")
    model = anfis.fit(X, y, radius=0.8, epochs=0)
    with pytest.raises(ValueError, match="shape"):
        model.predict(jnp.zeros((4, 3)))


def test_train_from_given_premises_and_their_bad_shapes():
    """``premises=`` replaces the clustering: the model keeps the given centres (in input
    units) before training, and a wrong shape is refused naming the argument."""
    rng = np.random.default_rng(0)
    X = rng.uniform(-1.0, 2.0, (60, 2))
    Y = np.sin(X[:, :1]) + X[:, 1:] ** 2
    centers = np.array([[-1.0, -1.0], [2.0, -1.0], [-1.0, 2.0], [2.0, 2.0]])
    model, hist = anfis.train(X, Y, premises=(centers, 1.0), epochs=0, validation=0.0)
    assert model.n_rules == 4
    np.testing.assert_allclose(np.asarray(model.centers) * np.asarray(model.x_span) + np.asarray(model.x_lo),
                               centers, atol=1e-12)
    with pytest.raises(ValueError, match="premises' centers"):
        anfis.train(X, Y, premises=(centers[:, :1], 1.0), epochs=0)
    with pytest.raises(ValueError, match="positive sigmas"):
        anfis.train(X, Y, premises=(centers, 0.0), epochs=0)
