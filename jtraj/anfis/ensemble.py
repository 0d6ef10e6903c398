"""A weighted average of ANFIS models trained on the same data.

:func:`jtraj.mappings.train_mapping` with ``radius="auto"`` trains one model per
candidate clustering radius and, by default, keeps all of them, weighted by
1 / (validation mean squared error)^2. On small trajectory datasets the validation split
is a handful of trajectories, so picking the single best radius on it is noisy;
averaging the candidates removes much of that noise (18 slices of 96 pairs: test RMSE
/ linear baseline mean 0.444 -> 0.403; docs/guides/anfis.md).

An :class:`Ensemble` answers like a :class:`~jtraj.anfis.Model` (``predict``,
``predict_fn``, ``metadata``, ``astype``, ``save``; :func:`jtraj.anfis.load` reads it
back). It is not a single fuzzy system: each member normalises its own firing strengths.
"""

from __future__ import annotations

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .model import ARRAYS, Model, query_method, RuleSystem, compiled_query, log_firing, rule_outputs

_SCALING = ("x_lo", "x_span", "y_lo", "y_span")


class Ensemble(RuleSystem):
    """``sum_k weights[k] * members[k].predict(X)``; the weights are positive and sum to 1.

    The members share the kind, order, output clipping and the data scaling (they were
    trained on the same data), so their rules are stored together and evaluated in one
    pass: ``centers``, ``sigmas`` ``(R, d)`` and ``theta (R, k, m)`` hold all members'
    rules in order, ``sizes`` (static) the rules per member; the scalings as in
    :class:`Model`; ``weights (K,)``; static ``info`` (JSON metadata). Build one with
    :meth:`from_models`; :attr:`members` gives the models back.
    """

    weights: Array
    sizes: tuple = eqx.field(static=True)
    kind: str = eqx.field(static=True, default="tsk")
    order: int = eqx.field(static=True, default=1)
    scalar_output: bool = eqx.field(static=True, default=False)
    info: str = eqx.field(static=True, default="{}")
    clip_outputs: bool = eqx.field(static=True, default=False)

    @classmethod
    def from_models(cls, members, weights, metadata: dict | None = None) -> "Ensemble":
        """The ensemble of ``members`` (models trained on the same data) with ``weights``
        (positive, finite) normalised to sum 1 and ``metadata`` (JSON-able)."""
        members = list(members)
        if not members or not all(isinstance(m, Model) for m in members):
            raise ValueError("an Ensemble needs one or more jtraj.anfis.Model members")
        first = members[0]
        for m in members[1:]:
            same = (m.kind, m.order, m.clip_outputs, m.scalar_output, m.n_inputs, m.n_outputs) == (
                first.kind, first.order, first.clip_outputs, first.scalar_output, first.n_inputs, first.n_outputs)
            if not same or not all(np.array_equal(getattr(m, k), getattr(first, k)) for k in _SCALING):
                raise ValueError("ensemble members must share kind, order, output clipping, inputs, outputs and "
                                 "the data scaling (models trained on the same data)")
        w = np.asarray(weights, float)
        if w.shape != (len(members),) or not np.all(np.isfinite(w)) or not np.all(w > 0):
            raise ValueError(f"weights must be {len(members)} positive finite numbers, got {weights!r}")
        cat = [jnp.concatenate([getattr(m, k) for m in members]) for k in ("centers", "sigmas", "theta")]
        return cls(*cat, first.x_lo, first.x_span, first.y_lo, first.y_span,
                   jnp.asarray(w / w.sum(), first.centers.dtype), tuple(m.n_rules for m in members),
                   kind=first.kind, order=first.order, scalar_output=first.scalar_output,
                   info=json.dumps(metadata or {}, sort_keys=True), clip_outputs=first.clip_outputs)

    # n_rules (all members' rules), n_inputs, n_outputs, metadata, with_metadata, astype
    # and save as for a Model
    @property
    def members(self) -> tuple[Model, ...]:
        """The member models (copies of their arrays, in order)."""
        ends = np.cumsum(self.sizes)
        return tuple(Model(self.centers[e - r:e], self.sigmas[e - r:e], self.theta[e - r:e], self.x_lo,
                           self.x_span, self.y_lo, self.y_span, kind=self.kind, order=self.order,
                           scalar_output=self.scalar_output, info=self.info, clip_outputs=self.clip_outputs)
                     for r, e in zip(self.sizes, ends))

    @property
    def leading(self) -> Model:
        """The member with the largest weight (e.g. for a membership plot)."""
        return self.members[int(np.argmax(np.asarray(self.weights)))]

    # ----- evaluation -------------------------------------------------------------------
    def predict_fn(self):
        """A pure function ``X (B, d) -> Y (B, m)`` (see :meth:`Model.predict_fn`)."""
        arrays, static = _arrays(self), (self.kind, self.order, self.clip_outputs, self.sizes)
        return lambda X: _forward(*arrays, X, *static)

    @query_method
    def predict(self, X) -> Array:
        """As :meth:`Model.predict`: ``(d,)`` -> ``(m,)`` or ``(B, d)`` -> ``(B, m)``, jitted."""
        f = vars(self)  # the fields, without equinox's attribute hook (see Model.predict)
        if not isinstance(X, jax.Array):
            X = np.asarray(X)
        d = f["centers"].shape[1]
        if X.ndim not in (1, 2) or X.shape[-1] != d:
            raise ValueError(f"X must have shape ({d},) or (B, {d}), got {X.shape}")
        query = compiled_query(_predict, f["kind"], f["order"], f["clip_outputs"], f["sizes"], X.ndim == 1,
                               f["scalar_output"])
        return query(*_arrays(self), X)

    __call__ = predict


def _arrays(e: Ensemble):
    f = vars(e)
    return tuple(f[k] for k in ARRAYS) + (f["weights"],)


def _forward(c, s, theta, x_lo, x_span, y_lo, y_span, weights, X, kind, order, clip, sizes):
    """Outputs (B, m) for inputs X (B, d) in data units: the firing strengths of all rules
    at once, normalised within each member (a static mask per member), each member's
    output clipped as its own, then weighted. (A loop over the members cost about their
    number times one model's query: the XLA CPU runtime's per-operation cost dominates
    such small queries.)"""
    u = (jnp.asarray(X, weights.dtype) - x_lo[None]) / x_span[None]
    lw = log_firing(c, s, u)  # (B, R)
    member = np.repeat(np.arange(len(sizes)), sizes)
    mask = member[None, :] == np.arange(len(sizes))[:, None]  # (K, R)
    beta = jax.nn.softmax(jnp.where(mask[None], lw[:, None, :], -jnp.inf), axis=-1)  # (B, K, R)
    v = jnp.einsum("bkr,brm->bkm", beta, rule_outputs(lw, u, theta, kind, order))
    if clip:
        v = jnp.clip(v, 0.0, 1.0)
    return jnp.einsum("k,bkm->bm", weights, v) * y_span[None] + y_lo[None]


def _predict(c, s, theta, x_lo, x_span, y_lo, y_span, weights, X, kind, order, clip, sizes, single, squeeze):
    Y = _forward(c, s, theta, x_lo, x_span, y_lo, y_span, weights, X[None, :] if single else X, kind, order, clip,
                 sizes)
    if single:
        Y = Y[0]
    return Y[..., 0] if squeeze else Y
