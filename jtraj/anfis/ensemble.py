"""A weighted average of ANFIS models trained on the same data.

:func:`jtraj.anfis.trajectory.train_mapping` with ``radius="auto"`` trains one model per
candidate clustering radius and, by default, keeps all of them, weighted by
1 / (validation mean squared error)^2. On small trajectory datasets the validation split
is a handful of trajectories, so picking the single best radius on it is noisy;
averaging the candidates removes much of that noise (README, ANFIS: 18 slices of 96
pairs, test RMSE / linear baseline mean 0.469 -> 0.425).

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

from .model import Model


class Ensemble(eqx.Module):
    """``sum_k weights[k] * members[k].predict(X)``; the weights are positive and sum to 1.

    Fields: ``members`` (a tuple of :class:`Model` with the same inputs and outputs),
    ``weights (K,)`` and static ``info`` (a JSON string: the metadata, as for a model).
    """

    members: tuple
    weights: Array
    info: str = eqx.field(static=True, default="{}")

    def __check_init__(self):
        if not self.members or not all(isinstance(m, Model) for m in self.members):
            raise ValueError("an Ensemble needs one or more jtraj.anfis.Model members")
        shapes = {(m.n_inputs, m.n_outputs, m.scalar_output) for m in self.members}
        if len(shapes) != 1:
            raise ValueError(f"ensemble members differ in (inputs, outputs, scalar output): {sorted(shapes)}")
        if np.shape(self.weights) != (len(self.members),):
            raise ValueError(f"weights must have shape ({len(self.members)},), got {np.shape(self.weights)}")

    @classmethod
    def from_models(cls, members, weights, metadata: dict | None = None) -> "Ensemble":
        """The ensemble of ``members`` with ``weights`` (positive, finite) normalised to sum
        1 and ``metadata`` (JSON-able)."""
        w = np.asarray(weights, float)
        if w.shape != (len(members),) or not np.all(np.isfinite(w)) or not np.all(w > 0):
            raise ValueError(f"weights must be {len(members)} positive finite numbers, got {weights!r}")
        dt = members[0].centers.dtype
        return cls(tuple(members), jnp.asarray(w / w.sum(), dt), json.dumps(metadata or {}, sort_keys=True))

    # ----- sizes and metadata, as for a Model -------------------------------------------
    @property
    def n_rules(self) -> int:
        """Rules of all members together."""
        return sum(m.n_rules for m in self.members)

    @property
    def n_inputs(self) -> int:
        return self.members[0].n_inputs

    @property
    def n_outputs(self) -> int:
        return self.members[0].n_outputs

    @property
    def leading(self) -> Model:
        """The member with the largest weight (e.g. for a membership plot)."""
        return self.members[int(np.argmax(np.asarray(self.weights)))]

    @property
    def metadata(self) -> dict:
        return json.loads(self.info)

    def with_metadata(self, **kv) -> "Ensemble":
        meta = self.metadata
        meta.update(kv)
        return Ensemble(self.members, self.weights, json.dumps(meta, sort_keys=True))

    def astype(self, dtype) -> "Ensemble":
        """Copy with every array cast to ``dtype``."""
        return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), self)

    # ----- evaluation -------------------------------------------------------------------
    def predict_fn(self):
        """A pure function ``X (B, d) -> Y (B, m)`` (see :meth:`Model.predict_fn`)."""
        fs = [m.predict_fn() for m in self.members]
        w = self.weights

        def f(X):
            return sum(w[k] * fk(X) for k, fk in enumerate(fs))
        return f

    def predict(self, X) -> Array:
        """As :meth:`Model.predict`: ``(d,)`` -> ``(m,)`` or ``(B, d)`` -> ``(B, m)``, jitted."""
        if not isinstance(X, jax.Array):
            X = np.asarray(X)
        d = self.n_inputs
        if X.ndim not in (1, 2) or X.shape[-1] != d:
            raise ValueError(f"X must have shape ({d},) or (B, {d}), got {X.shape}")
        return _predict(self, X)

    __call__ = predict

    def save(self, path) -> None:
        """Write the ensemble to ``path`` (see :func:`jtraj.anfis.load`)."""
        from .io import save

        save(path, self)


@eqx.filter_jit
def _predict(ens: Ensemble, X):
    single = X.ndim == 1
    X2 = jnp.asarray(X, ens.weights.dtype)
    Y = ens.predict_fn()(X2[None, :] if single else X2)
    if single:
        Y = Y[0]
    return Y[..., 0] if ens.members[0].scalar_output else Y
