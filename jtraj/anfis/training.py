"""Hybrid learning for :class:`~jtraj.anfis.model.Model` and the public :func:`fit`.

Initialisation is MATLAB ``genfis2``: subtractive clustering of the joint data
``[X, Y]`` (training part only), the input part of each centre becomes a rule, the
premise widths are ``r_a / sqrt(8)`` in unit-hypercube units.

Every epoch (Jang's hybrid rule):

* **consequents by least squares**, given the premises: the output is linear in the
  consequent coefficients, so they are the exact minimiser of the mean squared error
  plus a ridge term ``lambda ||theta||^2`` with
  ``lambda = ridge * trace(Phi^T Phi) / n_coef`` (relative, hence scale-free);
  solved by a Cholesky factorisation of the normal equations (``jnp.linalg``);
* **premises** (centres, widths) by one of

  * ``method="lm"`` (default): a Levenberg-Marquardt step on the residuals with the
    consequents held at their least-squares value (the Jacobian of the residuals is
    taken at fixed consequents, the objective of the trial step re-solves them:
    a variable-projection flavour of the hybrid rule); damping multiplied by 4 on a
    rejected trial (up to 10 trials an epoch), divided by 3 on success;
  * ``method="gradient"``: MATLAB ``anfis``'s rule, a step of length ``ss`` along the
    normalised negative gradient, ``ss`` starting at ``step_size`` (0.01), times 1.1
    after four consecutive decreases of the error, times 0.9 after two consecutive
    up-down oscillations;

  widths are kept above ``sigma_floor`` times their initial value ``r_a / sqrt(8)``
  (0.4 by default: narrower Gaussians interpolate badly between samples; on Jang's
  sinc grid a floor of 0.25 raises the off-grid error sevenfold).

Early stopping: the model with the lowest validation RMSE is returned; training stops
when it has not improved for ``patience`` epochs (or the LM damping blows up, i.e.
no step decreases the error any more).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from .clustering import radius_for_rules, subclust, unit_scaling
from .model import KINDS, Model, logit_clipped, features, forward, log_firing, rule_outputs


@dataclass
class History:
    """What happened during training (RMSE in target units, all outputs pooled)."""

    train_rmse: list = field(default_factory=list)
    val_rmse: list = field(default_factory=list)
    best_epoch: int = 0
    epochs: int = 0
    seconds: float = 0.0
    radius: float = float("nan")
    initial: Model | None = None  # the model right after clustering + least squares
    stop_reason: str = ""


# ----------------------------------------------------------------------------- checks
def _as_2d(a, name):
    try:
        arr = np.asarray(a, dtype=float)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be an array of numbers") from err
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"{name} must be a non-empty 1-D or 2-D array (samples first), got shape {arr.shape}")
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr)).any(axis=1).sum())
        raise ValueError(f"{name} contains NaN or infinite values ({bad} rows)")
    return arr


def check_data(X, Y, name_x="X", name_y="Y"):
    """(X (P, d), Y (P, m), scalar_output) as float arrays, or ValueError."""
    Yarr = np.asarray(Y)
    scalar = Yarr.ndim == 1
    X2 = _as_2d(X, name_x)
    Y2 = _as_2d(Y, name_y)
    if X2.shape[0] != Y2.shape[0]:
        raise ValueError(f"{name_x} and {name_y} have different numbers of samples: "
                         f"{X2.shape[0]} and {Y2.shape[0]}")
    return X2, Y2, scalar


# ----------------------------------------------------------------------------- LS
def _solve_ls(phi, V, ridge):
    """theta (c, m) minimising ||phi theta - V||^2 + lam ||theta||^2 (lam relative)."""
    G = phi.T @ phi
    ncol = G.shape[0]
    eps = jnp.finfo(phi.dtype).eps
    lam = jnp.maximum(ridge, 10 * eps) * (jnp.trace(G) / ncol) + eps
    L = jnp.linalg.cholesky(G + lam * jnp.eye(ncol, dtype=G.dtype))
    rhs = phi.T @ V
    z = jax.scipy.linalg.solve_triangular(L, rhs, lower=True)
    return jax.scipy.linalg.solve_triangular(L.T, z, lower=False)


def consequents(c, s, U, V, kind, order, ridge):
    """Least-squares consequents theta (R, k, m) for premises (c, s)."""
    phi = features(c, s, U, kind, order)
    B, R, k = phi.shape
    th = _solve_ls(phi.reshape(B, R * k), V, ridge)
    return th.reshape(R, k, V.shape[1])


def premise_jacobian(c, s, th, U, kind, order):
    """Jacobian of the outputs v (B, m) with respect to (c, s), at fixed consequents,
    as a (B m, 2 R d) matrix (columns: c row-major, then s row-major).

    With ``l_r = log w_r`` and ``beta = softmax(l)``:
    ``dv_k / dl_r = beta_r (f_rk - v_k + df_rk / dl_r)``,
    ``dl_r / dc_ri = (u_i - c_ri) / s_ri^2``, ``dl_r / ds_ri = (u_i - c_ri)^2 / s_ri^3``;
    ``df / dl`` is 0 for Sugeno and ``a_rk / (1 - w_r)`` for Tsukamoto (inside the clip).
    """
    lw = log_firing(c, s, U)
    beta = jax.nn.softmax(lw, axis=-1)
    f = rule_outputs(lw, U, th, kind, order)  # (B, R, m)
    v = jnp.einsum("br,brm->bm", beta, f)
    g = f - v[:, None, :]
    if kind == "tsukamoto":
        _, inside = logit_clipped(lw)
        dlogit = jnp.where(inside, 1.0 / (-jnp.expm1(jnp.minimum(lw, -1e-300))), 0.0)
        g = g + dlogit[:, :, None] * th[None, :, 0, :]
    dv_dl = beta[:, :, None] * g  # (B, R, m)
    diff = U[:, None, :] - c[None, :, :]  # (B, R, d)
    dl_dc = diff / s[None] ** 2
    dl_ds = diff**2 / s[None] ** 3
    B, R, m = dv_dl.shape
    d = c.shape[1]
    Jc = jnp.einsum("brm,bri->bmri", dv_dl, dl_dc).reshape(B * m, R * d)
    Js = jnp.einsum("brm,bri->bmri", dv_dl, dl_ds).reshape(B * m, R * d)
    return jnp.concatenate([Jc, Js], axis=1)


def _mse(c, s, th, U, V, kind, order):
    r = forward(c, s, th, U, kind, order) - V
    return jnp.mean(r * r)


def _evaluate(c, s, U, V, Uv, Vv, y_span, ridge, kind, order):
    """Least-squares consequents for premises (c, s), the training MSE (normalised
    units) and the train / validation RMSE in target units."""
    th = consequents(c, s, U, V, kind, order, ridge)
    r = forward(c, s, th, U, kind, order) - V
    rv = (forward(c, s, th, Uv, kind, order) - Vv) * y_span[None]
    mse = jnp.mean(r * r)
    return th, mse, jnp.sqrt(jnp.mean((r * y_span[None]) ** 2)), jnp.sqrt(jnp.mean(rv * rv))


@partial(jax.jit, static_argnames=("kind", "order"))
def _lm_system(c, s, th, U, V, kind, order):
    """Gauss-Newton system (J^T J, J^T r) of the premises at fixed consequents, and the
    Marquardt scaling (diagonal of J^T J, bounded away from 0)."""
    r = (forward(c, s, th, U, kind, order) - V).ravel()
    J = premise_jacobian(c, s, th, U, kind, order)
    H = J.T @ J
    dH = jnp.diag(H)
    return H, J.T @ r, jnp.maximum(dH, 1e-12 * (jnp.max(dH) + 1e-300))


@partial(jax.jit, static_argnames=("kind", "order"))
def _lm_trial(c, s, H, g, scale, mu, floor, U, V, Uv, Vv, y_span, ridge, kind, order):
    """Premises after the damped step ``(H + mu diag(scale)) step = g`` (widths floored)
    and their evaluation (see :func:`_evaluate`). With g = 0 this evaluates (c, s)."""
    step = jnp.linalg.solve(H + mu * jnp.diag(scale), g)
    n_c = c.size
    c2 = c - step[:n_c].reshape(c.shape)
    s2 = jnp.maximum(s - step[n_c:].reshape(s.shape), floor)
    return (c2, s2) + _evaluate(c2, s2, U, V, Uv, Vv, y_span, ridge, kind, order)


@partial(jax.jit, static_argnames=("kind", "order"))
def _grad_trial(c, s, th, ss, floor, U, V, Uv, Vv, y_span, ridge, kind, order):
    """MATLAB-style step of length ``ss`` along the normalised negative gradient."""
    gc, gs = jax.grad(lambda p: _mse(p[0], p[1], th, U, V, kind, order))((c, s))
    norm = jnp.sqrt(jnp.sum(gc**2) + jnp.sum(gs**2)) + 1e-300
    c2 = c - ss * gc / norm
    s2 = jnp.maximum(s - ss * gs / norm, floor)
    return (c2, s2) + _evaluate(c2, s2, U, V, Uv, Vv, y_span, ridge, kind, order)


# ----------------------------------------------------------------------------- fit
@dataclass
class _Premises:
    """Given premises in the shape clustering returns them (unit-hypercube coordinates)."""

    centers: np.ndarray  # (R, d + m): the inputs' part is used
    lo: np.ndarray
    span: np.ndarray
    widths: np.ndarray  # (R, d) Gaussian widths, unit-hypercube units


def _given_premises(premises, XY, d: int) -> _Premises:
    """``premises = (centers (R, d), sigmas (R, d) or (d,))`` in input units, scaled as
    clustering scales its centres (the training data's range onto [0, 1])."""
    try:
        centers, sigmas = (np.asarray(a, dtype=float) for a in premises)
    except (TypeError, ValueError) as err:
        raise ValueError("premises must be a pair (centers (R, d), sigmas (R, d))") from err
    if centers.ndim != 2 or centers.shape[1] != d or centers.shape[0] < 1:
        raise ValueError(f"premises' centers must have shape (R, {d}), got {centers.shape}")
    try:
        sigmas = np.broadcast_to(sigmas, centers.shape)
    except ValueError as err:
        raise ValueError(f"premises' sigmas must broadcast to {centers.shape}, got {sigmas.shape}") from err
    if not (np.isfinite(centers).all() and np.isfinite(sigmas).all() and (sigmas > 0).all()):
        raise ValueError("premises must be finite, with positive sigmas")
    lo, span = unit_scaling(XY)
    full = np.concatenate([centers, np.broadcast_to(lo[d:], (centers.shape[0], XY.shape[1] - d))], axis=1)
    return _Premises(centers=full, lo=lo, span=span, widths=sigmas / span[:d])


def train(X, Y, *, n_rules: int | None = None, radius=0.5, squash: float = 1.25, accept: float = 0.5,
          reject: float = 0.15, kind: str = "tsk", order: int = 1, epochs: int = 100,
          validation=0.1, seed: int = 0, method: str = "lm", ridge: float = 1e-10,
          sigma_floor: float = 0.4, patience: int = 20, step_size: float = 0.01,
          metadata: dict | None = None, progress=False, clip_outputs: bool = False,
          premises=None) -> tuple[Model, History]:
    """Fit an ANFIS and return ``(model, history)``; see :func:`fit` for arguments."""
    t0 = time.perf_counter()
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    if order not in (0, 1):
        raise ValueError(f"order must be 0 or 1, got {order!r}")
    if method not in ("lm", "gradient"):
        raise ValueError(f"method must be 'lm' or 'gradient', got {method!r}")
    if int(epochs) < 0:
        raise ValueError(f"epochs must be >= 0, got {epochs!r}")
    X2, Y2, scalar = check_data(X, Y)

    # --- split
    if isinstance(validation, tuple):
        Xv, Yv, _ = check_data(validation[0], validation[1], "validation X", "validation Y")
        if Xv.shape[1] != X2.shape[1] or Yv.shape[1] != Y2.shape[1]:
            raise ValueError("validation data must have the same columns as X and Y")
        Xt, Yt = X2, Y2
    else:
        frac = float(validation)
        if not 0.0 <= frac < 1.0:
            raise ValueError(f"validation must be a fraction in [0, 1) or an (X, Y) pair, got {validation!r}")
        P = X2.shape[0]
        n_val = int(round(frac * P))
        if n_val > 0 and P - n_val >= 1:
            perm = np.random.default_rng(seed).permutation(P)
            vi, ti = np.sort(perm[:n_val]), np.sort(perm[n_val:])
            Xt, Yt, Xv, Yv = X2[ti], Y2[ti], X2[vi], Y2[vi]
        else:
            Xt, Yt, Xv, Yv = X2, Y2, None, None
    if n_rules is not None and int(n_rules) > Xt.shape[0]:
        raise ValueError(f"fewer training samples ({Xt.shape[0]}) than rules (n_rules = {int(n_rules)})")

    # --- clustering (genfis2: joint input-output space), or the given premises
    d = Xt.shape[1]
    XY = np.concatenate([Xt, Yt], axis=1)
    if premises is not None:
        cl, used_radius = _given_premises(premises, XY, d), float("nan")
    elif n_rules is None:
        cl = subclust(XY, radius, squash=squash, accept=accept, reject=reject)
        used_radius = radius
        if cl.centers.shape[0] == 0:
            raise ValueError(f"radius {radius!r} (squash {squash}, accept {accept}, reject {reject}) yields no "
                             "rule: lower reject below 1 or change the radius")
    else:
        used_radius, cl = radius_for_rules(XY, int(n_rules), squash=squash, accept=accept, reject=reject)
    R = cl.centers.shape[0]
    if R > Xt.shape[0]:
        raise ValueError(f"fewer training samples ({Xt.shape[0]}) than rules ({R})")
    x_lo, x_span = cl.lo[:d], cl.span[:d]
    y_lo, y_span = cl.lo[d:], cl.span[d:]
    dtype = jnp.asarray(0.0).dtype
    A = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    U, V = A((Xt - x_lo) / x_span), A((Yt - y_lo) / y_span)
    if Xv is None:
        Uv, Vv = U, V
    else:
        Uv, Vv = A((Xv - x_lo) / x_span), A((Yv - y_lo) / y_span)
    c = A((cl.centers[:, :d] - x_lo) / x_span)
    if not 0.0 <= sigma_floor <= 1.0:
        raise ValueError(f"sigma_floor must be a fraction in [0, 1] of the initial width, got {sigma_floor!r}")
    s0 = cl.widths if isinstance(cl, _Premises) else np.broadcast_to(cl.radius[:d] / math.sqrt(8.0), (R, d))
    s = A(s0)
    floor = A(np.maximum(sigma_floor * s0, 1e-6))
    ridge_a, ysp = A(ridge), A(y_span)
    data = (U, V, Uv, Vv, ysp, ridge_a)
    P_prem = 2 * c.size
    c, s, th, mse, tr0, va0 = _lm_trial(c, s, jnp.eye(P_prem, dtype=dtype), jnp.zeros(P_prem, dtype),
                                        jnp.ones(P_prem, dtype), A(1.0), floor, *data, kind=kind, order=order)

    info = dict(format="jtraj.anfis", kind=kind, order=order, n_rules=R,
                radius=None if premises is not None else float(np.mean(used_radius)),
                squash=squash, accept=accept, reject=reject, method=method, ridge=ridge, sigma_floor=sigma_floor,
                n_train=int(Xt.shape[0]), n_validation=0 if Xv is None else int(Xv.shape[0]), seed=seed)
    if metadata:
        info.update(metadata)

    def make(c, s, th, extra=None):
        meta = dict(info, **(extra or {}))
        return Model(c, s, th, A(x_lo), A(x_span), A(y_lo), A(y_span), kind=kind, order=order,
                     scalar_output=scalar, info=json.dumps(meta, sort_keys=True), clip_outputs=bool(clip_outputs))

    hist = History(radius=float(np.mean(used_radius)))
    hist.initial = make(c, s, th, {"epochs": 0})
    tr0, va0 = float(tr0), float(va0)
    hist.train_rmse.append(tr0)
    hist.val_rmse.append(va0)
    best = (va0, 0, (c, s), th)

    bar = None
    if progress:
        from tqdm.auto import tqdm

        every = 0.1 if progress is True else float(progress)
        bar = tqdm(total=int(epochs), desc="anfis", unit="epoch", leave=False, mininterval=every)
    mu = 1e-3
    ss = float(step_size)
    moves: list[int] = []  # +1 error went down, -1 up (gradient step-size rule)
    mse = float(mse)
    hist.stop_reason = "epochs"
    for ep in range(1, int(epochs) + 1):
        if method == "lm":
            H, g, scale = _lm_system(c, s, th, U, V, kind=kind, order=order)
            accepted = False
            for _ in range(10):  # Marquardt trials: damping x4 on each rejection
                c2, s2, th2, mse2, tr, va = _lm_trial(c, s, H, g, scale, A(mu), floor, *data, kind=kind,
                                                      order=order)
                mse2 = float(mse2)
                if math.isfinite(mse2) and mse2 < mse:
                    accepted = True
                    break
                mu *= 4.0
            if not accepted:
                hist.stop_reason = "converged (no decreasing step)"
                break
            mu = max(mu / 3.0, 1e-12)
        else:
            c2, s2, th2, mse2, tr, va = _grad_trial(c, s, th, A(ss), floor, *data, kind=kind, order=order)
            mse2 = float(mse2)
            if not math.isfinite(mse2):
                hist.stop_reason = "non-finite error"
                break
            moves.append(1 if mse2 < mse else -1)
            if len(moves) >= 4 and moves[-4:] == [1, 1, 1, 1]:
                ss *= 1.1
                moves.clear()
            elif len(moves) >= 4 and moves[-4:] in ([1, -1, 1, -1], [-1, 1, -1, 1]):
                ss *= 0.9
                moves.clear()
        c, s, th, mse = c2, s2, th2, mse2
        tr, va = float(tr), float(va)
        hist.train_rmse.append(tr)
        hist.val_rmse.append(va)
        if bar is not None:
            bar.set_postfix(train=f"{tr:.3g}", val=f"{va:.3g}", refresh=False)
            bar.update(1)  # (redraws at most every mininterval)
        if va < best[0]:
            best = (va, ep, (c, s), th)
        if ep - best[1] >= patience:
            hist.stop_reason = "early stopping"
            break
    if bar is not None:
        bar.close()
    hist.epochs = len(hist.train_rmse) - 1
    hist.best_epoch = best[1]
    hist.seconds = time.perf_counter() - t0
    (c, s), th = best[2], best[3]
    model = make(c, s, th, {"epochs": hist.epochs, "best_epoch": hist.best_epoch,
                            "train_seconds": round(hist.seconds, 3)})
    return model, hist


def fit(X, Y, *, n_rules: int | None = None, radius=0.5, squash: float = 1.25, accept: float = 0.5,
        reject: float = 0.15, kind: str = "tsk", epochs: int = 100, validation=0.1, seed: int = 0,
        **options) -> Model:
    """Fit an ANFIS to samples ``X (P, d)`` -> ``Y (P, m)`` (or ``Y (P,)``).

    Structure from subtractive clustering of ``[X, Y]`` (MATLAB ``genfis2``:
    ``radius`` r_a in unit-hypercube units, ``squash``, ``accept`` and ``reject``
    ratios; see :mod:`jtraj.anfis.clustering`). With ``n_rules`` given, the radius is
    instead chosen by bisection so that clustering yields that many rules (when the
    count jumps past ``n_rules``, the first ``n_rules`` centres of the largest radius
    giving more are kept); ``radius`` is then ignored.

    ``kind``: ``"tsk"`` (first-order Sugeno; ``order=0`` for zero-order) or
    ``"tsukamoto"`` (monotone logistic consequents). Training: ``epochs`` of the hybrid
    rule (least squares + ``method="lm"`` or ``"gradient"`` on the premises), early
    stopping on a random ``validation`` fraction of the samples (seeded by ``seed``;
    pass an ``(X_val, Y_val)`` pair to choose it yourself, 0 to disable). Other
    options: ``order``, ``method``, ``ridge`` (relative ridge of the least squares,
    1e-10), ``sigma_floor`` (0.4, relative to the initial width), ``patience`` (20), ``step_size`` (0.01, gradient
    method), ``metadata`` (dict stored in the model), ``progress`` (a tqdm bar: ``True``,
    or the least seconds between its redraws), ``clip_outputs`` (False; predictions
    clipped into the training targets' range, see :class:`Model`; training itself is
    unaffected), ``premises`` (None; a pair
    ``(centers (R, d), sigmas (R, d) or (d,))`` in input units replaces the clustering:
    a grid partition as in Jang's ANFIS, or a model's premises to train further; the
    radius options are then ignored).

    Raises ValueError for mismatched lengths, NaN/inf in the data, fewer samples than
    rules, or a radius that yields no rule.

    >>> import numpy as np, jtraj.anfis as anfis
    >>> X = np.linspace(-1, 1, 200)[:, None]
    >>> model = anfis.fit(X, np.sin(3 * X[:, 0]), n_rules=5)
    >>> y = model.predict(X)            # (200,)
    """
    model, _ = train(X, Y, n_rules=n_rules, radius=radius, squash=squash, accept=accept, reject=reject,
                     kind=kind, epochs=epochs, validation=validation, seed=seed, **options)
    return model
