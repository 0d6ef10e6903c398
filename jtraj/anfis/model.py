"""The ANFIS model: Gaussian premises, product t-norm, Sugeno or Tsukamoto consequents.

Notation (shapes): ``d`` inputs, ``m`` outputs, ``R`` rules, ``B`` a batch.

Inputs and outputs are scaled to the unit hypercube of the training data
(``u = (x - x_lo) / x_span``, ``v = (y - y_lo) / y_span``); every parameter lives in
those units, so the premise widths start at ``sigma = r_a / sqrt(8)`` as in MATLAB's
``genfis2`` (``r_a (max - min) / sqrt(8)`` in data units) and the ridge regularisation
is scale-free. :meth:`Model.memberships` converts back to data units.

Layer by layer, for one sample ``u``:

1. memberships ``mu_ri = exp(-(u_i - c_ri)^2 / (2 s_ri^2))``;
2. firing strengths (product t-norm) kept in log space,
   ``log w_r = -1/2 sum_i ((u_i - c_ri) / s_ri)^2``, so that many inputs far from a
   centre never underflow to 0/0;
3. normalised strengths ``beta = softmax(log w)`` (exact, stable);
4. consequents, per output ``k``:

   * ``"tsk"`` order 1 (first-order Sugeno): ``f_rk = theta_rk . [clip(u, 0, 1), 1]``
     (the consequents' inputs are clipped to the training box, so that a query
     outside it is not extrapolated linearly by a rule fitted far away; inside the box,
     where all training data lie, this is the plain TSK model);
   * ``"tsk"`` order 0 (zero-order Sugeno): ``f_rk = theta_rk``;
   * ``"tsukamoto"``: monotone logistic consequent ``F(z) = 1 / (1 + exp(-(rho z - s)))``
     read backwards at the rule's firing strength, ``f_rk = F^{-1}(w_r)
     = (logit(w_r) + s_rk) / rho_rk = a_rk logit(w_r) + b_rk`` with
     ``a = 1 / rho``, ``b = s / rho``: linear in ``(a, b)``, so least squares stays
     exact. ``w_r`` is clipped to ``[w_eps, 1 - w_eps]`` (``w_eps = 1e-9``) because
     ``logit(1)`` is infinite at a rule's centre.
5. output ``v_k = sum_r beta_r f_rk``.

dtype: ``predict`` computes in the dtype of the stored parameters, float64 when the
model was trained with ``jax_enable_x64`` on (the CLI and the tests do so);
``model.astype(jnp.float32)`` gives a float32 copy for faster queries.
"""

from __future__ import annotations

import dataclasses
import json
from functools import lru_cache, partial, update_wrapper

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._file import save

KINDS = ("tsk", "tsukamoto")
W_EPS = 1e-9


def n_coef(kind: str, order: int, d: int) -> int:
    """Consequent coefficients per rule and output."""
    if kind == "tsukamoto":
        return 2
    return d + 1 if order == 1 else 1


def log_firing(c: Float[Array, "R d"], s: Float[Array, "R d"], u: Float[Array, "B d"]) -> Float[Array, "B R"]:
    """log w (B, R): product of Gaussian memberships, in log space."""
    z = (u[:, None, :] - c[None, :, :]) / s[None, :, :]
    return -0.5 * jnp.sum(z * z, axis=-1)


def features(c, s, u, kind: str, order: int) -> Float[Array, "B R k"]:
    """Consequent regressors phi (B, R, k) with output ``v = sum_r phi_r . theta_r``."""
    lw = log_firing(c, s, u)
    beta = jax.nn.softmax(lw, axis=-1)
    if kind == "tsukamoto":
        logit, _ = logit_clipped(lw)
        reg = jnp.stack([logit, jnp.ones_like(logit)], axis=-1)
        return beta[..., None] * reg
    if order == 1:
        uc = jnp.clip(u, 0.0, 1.0)
        ua = jnp.concatenate([uc, jnp.ones(u.shape[:-1] + (1,), u.dtype)], axis=-1)
        return beta[:, :, None] * ua[:, None, :]
    return beta[:, :, None]


def logit_clipped(lw):
    """logit(w) from log w, with w clipped to [W_EPS, 1 - W_EPS]; and the clip mask."""
    lo, hi = jnp.log(W_EPS), jnp.log1p(-W_EPS)
    lw_c = jnp.clip(lw, lo, hi)
    return lw_c - jnp.log1p(-jnp.exp(lw_c)), (lw > lo) & (lw < hi)


def rule_outputs(lw, u, theta, kind: str, order: int) -> Float[Array, "B R m"]:
    """Per-rule consequent values f (B, R, m)."""
    if kind == "tsukamoto":
        logit, _ = logit_clipped(lw)
        return logit[:, :, None] * theta[None, :, 0, :] + theta[None, :, 1, :]
    if order == 1:
        R, k, m = theta.shape
        W = jnp.transpose(theta[:, :-1, :], (1, 0, 2)).reshape(k - 1, R * m)
        uc = jnp.clip(u, 0.0, 1.0)  # no linear extrapolation outside the training box
        return (uc @ W).reshape(u.shape[0], R, m) + theta[None, :, -1, :]
    return jnp.broadcast_to(theta[None, :, 0, :], (u.shape[0],) + theta[:, 0, :].shape)


def forward(c, s, theta, u, kind: str, order: int) -> Float[Array, "B m"]:
    """Normalised outputs v (B, m) for normalised inputs u (B, d)."""
    lw = log_firing(c, s, u)
    beta = jax.nn.softmax(lw, axis=-1)
    f = rule_outputs(lw, u, theta, kind, order)
    return jnp.einsum("br,brm->bm", beta, f)


ARRAYS = ("centers", "sigmas", "theta", "x_lo", "x_span", "y_lo", "y_span")


@lru_cache(maxsize=256)
def compiled_query(fn, *static):
    """``jax.jit`` of ``fn`` with its trailing (hashable) arguments ``static`` bound: a
    jitted function of arrays only, one per configuration. With the fields read through
    ``vars`` (see :meth:`Model.predict`), a single query became about 1.3x faster than
    handing the static arguments to a jitted function at each call (2-core CPU, float64,
    three alternating runs, medians of 500-call blocks: seven-member ensemble of 52 rules
    132 / 105 / 115 -> 99 / 109 / 82 us, its best member of 11 rules 58 / 44 / 58 -> 35 /
    41 / 29 us)."""
    return jax.jit(lambda *arrays: fn(*arrays, *static))


def _predict(c, s, theta, x_lo, x_span, y_lo, y_span, X, kind, order, single, squeeze, clip):
    X = jnp.asarray(X, c.dtype)
    if single:
        X = X[None, :]
    u = (X - x_lo[None]) / x_span[None]
    v = forward(c, s, theta, u, kind, order)
    if clip:
        v = jnp.clip(v, 0.0, 1.0)
    Y = v * y_span[None] + y_lo[None]
    if single:
        Y = Y[0]
    return Y[..., 0] if squeeze else Y


class query_method:
    """Decorator for the query methods of the model classes: accessed on an instance it
    returns a plain ``functools.partial``. Equinox turns every bound method of a Module
    into a ``BoundMethod`` module, built (and the model's leaves flattened and checked)
    at each attribute access: a single query of a 20-rule model took 149 us that way and
    35 us this way (2-core CPU, float64, interleaved)."""

    def __init__(self, f):
        self.f = f
        update_wrapper(self, f)

    def __get__(self, obj, objtype=None):
        return self.f if obj is None else partial(self.f, obj)


class RuleSystem(eqx.Module):
    """The rule arrays and accessors shared by :class:`Model` and
    :class:`~jtraj.anfis.Ensemble` (both also have a JSON ``info`` field)."""

    centers: Array
    sigmas: Array
    theta: Array
    x_lo: Array
    x_span: Array
    y_lo: Array
    y_span: Array

    @property
    def n_rules(self) -> int:
        return int(self.centers.shape[0])

    @property
    def n_inputs(self) -> int:
        return int(self.centers.shape[1])

    @property
    def n_outputs(self) -> int:
        return int(self.theta.shape[2])

    @property
    def metadata(self) -> dict:
        """Hyperparameters and user metadata (a fresh dict)."""
        return json.loads(self.info)

    def with_metadata(self, **kv):
        """Copy with ``kv`` merged into :attr:`metadata` (values must be JSON-able)."""
        meta = self.metadata
        meta.update(kv)
        return dataclasses.replace(self, info=json.dumps(meta, sort_keys=True))

    def astype(self, dtype):
        """Copy with every array cast to ``dtype`` (e.g. float32 for faster queries)."""
        return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), self)

    def save(self, path) -> None:
        """Write the model to ``path`` (see :func:`jtraj.anfis.load`)."""
        save(path, self)


class Model(RuleSystem):
    """A trained ANFIS (see the module docstring for the structure).

    Fields (unit-hypercube units): ``centers (R, d)``, ``sigmas (R, d)``,
    ``theta (R, k, m)`` consequent coefficients, scalings ``x_lo, x_span (d,)`` and
    ``y_lo, y_span (m,)``; static ``kind``, ``order``, ``scalar_output`` (Y was 1-D),
    ``info`` (a JSON string: hyperparameters, training figures, user metadata such as
    the trajectory mapping) and ``clip_outputs``: predictions clipped into the range of
    the training targets (``[y_lo, y_lo + y_span]``; off by default, as in MATLAB; the
    trajectory models turn it on: their targets are bounded by the robot's limits, and
    a first-order rule can swing far outside them where its normalised weight is small
    but not negligible).
    """

    kind: str = eqx.field(static=True, default="tsk")
    order: int = eqx.field(static=True, default=1)
    scalar_output: bool = eqx.field(static=True, default=False)
    info: str = eqx.field(static=True, default="{}")
    clip_outputs: bool = eqx.field(static=True, default=False)

    def with_clip(self, clip: bool = True) -> "Model":
        """Copy with :attr:`clip_outputs` set to ``clip``."""
        return dataclasses.replace(self, clip_outputs=bool(clip))

    # ----- evaluation -----------------------------------------------------------------
    @query_method
    def predict(self, X) -> Array:
        """Outputs for inputs X: ``(d,)`` -> ``(m,)`` or ``(B, d)`` -> ``(B, m)``
        (without the last axis when the model was fitted on 1-D targets).

        Jitted (one compilation per batch shape); computes in the parameters' dtype.
        """
        f = vars(self)  # the fields, without equinox's attribute hook (~2 us an access)
        if not isinstance(X, jax.Array):
            X = np.asarray(X)
        shape = X.shape
        if len(shape) not in (1, 2) or shape[-1] != f["centers"].shape[1]:
            raise ValueError(f"X must have shape ({self.n_inputs},) or (B, {self.n_inputs}), got {shape}")
        query = compiled_query(_predict, f["kind"], f["order"], len(shape) == 1, f["scalar_output"], f["clip_outputs"])
        return query(*(f[k] for k in ARRAYS), X)

    __call__ = predict

    def predict_fn(self):
        """A pure function ``X (B, d) -> Y (B, m)`` closing over the parameters, for use
        inside other jitted code (e.g. the online planner)."""
        c, s, th, xl, xs, yl, ys = (self.centers, self.sigmas, self.theta, self.x_lo, self.x_span,
                                    self.y_lo, self.y_span)
        kind, order, clip = self.kind, self.order, self.clip_outputs

        def f(X):
            u = (X - xl[None]) / xs[None]
            v = forward(c, s, th, u, kind, order)
            return (jnp.clip(v, 0.0, 1.0) if clip else v) * ys[None] + yl[None]
        return f

    def firing(self, X) -> Array:
        """Normalised firing strengths beta (B, R) for inputs X (B, d) in data units."""
        X = jnp.atleast_2d(jnp.asarray(X, dtype=self.centers.dtype))
        return jax.nn.softmax(log_firing(self.centers, self.sigmas, (X - self.x_lo[None]) / self.x_span[None]), axis=-1)

    def memberships(self) -> tuple[np.ndarray, np.ndarray]:
        """(centres, sigmas) of the Gaussian memberships in data units, each (R, d)."""
        span = np.asarray(self.x_span)
        return (np.asarray(self.centers) * span + np.asarray(self.x_lo), np.asarray(self.sigmas) * span)

    def tsukamoto_parameters(self) -> tuple[np.ndarray, np.ndarray]:
        """(rho, s) of the logistic consequents (R, m), in normalised units; ``inf``
        where a rule's slope coefficient is 0 (a constant consequent)."""
        if self.kind != "tsukamoto":
            raise ValueError("tsukamoto_parameters: the model is of kind " + repr(self.kind))
        a = np.asarray(self.theta[:, 0, :])
        b = np.asarray(self.theta[:, 1, :])
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = 1.0 / a
            return rho, b * rho
