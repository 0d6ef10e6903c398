"""Coverage of a learned planner: how far a query lies from its training data.

A query is a start/goal pair ``x = (q_start, q_goal)`` (2n numbers), the input of a
``plan`` model. The training pairs are stored in the model's metadata
(``train_pairs``, written by :func:`jtraj.mappings.train_mapping`).

Coverage is measured on the features ``(q_start, q_goal - q_start)``, a linear change of
the model's inputs in which the datasets' sampling laws are boxes (a start in a box, a
step in a box: ``jtraj dataset``), each scaled by the training features' range (1 is the
width of the training data along a feature). Two tests, either of which flags a query
out of distribution:

* the **box**: a feature beyond the training features' range (e.g. a step longer than
  any training step), measured by the scaled distance outside the box;
* the **hole**: the Euclidean distance to the nearest training pair beyond the radius of
  the training data (``coverage_radius`` in the metadata), the largest distance from a
  training pair to its nearest other training pair.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def features(pairs):
    """``(q_start, q_goal - q_start)`` of pairs ``(..., 2n)``."""
    pairs = np.asarray(pairs, float) if not isinstance(pairs, jnp.ndarray) else pairs
    n = pairs.shape[-1] // 2
    lib = jnp if isinstance(pairs, jnp.ndarray) else np
    return lib.concatenate([pairs[..., :n], pairs[..., n:] - pairs[..., :n]], axis=-1)


def normaliser(pairs):
    """``(lo, span)`` of the training pairs' features (P, 2n); span 1 where a feature is
    constant."""
    f = features(pairs)
    lo, span = f.min(0), np.ptp(f, axis=0)
    return lo, np.where(span > 0, span, 1.0)


def radius(pairs, chunk: int = 1024) -> float:
    """The largest distance from a training pair to its nearest other one (module doc);
    0 with fewer than two pairs."""
    pairs = np.asarray(pairs, float)
    if len(pairs) < 2:
        return 0.0
    lo, span = normaliser(pairs)
    A = (features(pairs) - lo) / span
    sq = np.sum(A**2, 1)
    worst = 0.0
    for s in range(0, len(A), chunk):
        d2 = sq[s:s + chunk, None] + sq[None, :] - 2 * A[s:s + chunk] @ A.T
        np.fill_diagonal(d2[:, s:s + chunk], np.inf)
        worst = max(worst, float(np.sqrt(np.maximum(d2.min(1), 0.0)).max()))
    return worst


#: the training pairs are searched in blocks of this many (:func:`distance_fn`)
BLOCK = 32


def distance_fn(pairs):
    """A jit-, vmap-able ``x (2n,) -> (distance to the nearest training pair, distance
    outside the training box)`` (module doc)."""
    lo, span = normaliser(pairs)
    A = (features(pairs) - lo) / span
    # the pairs in blocks of BLOCK (the last one padded with pairs at infinite distance),
    # one feature at a time: |u - a|^2 - |u|^2 = |a|^2 - 2 a.u as a sum of broadcast
    # products over contiguous rows of pairs, then the nearest of each block and of the
    # blocks (XLA fuses products and the first minimum into one loop; one minimum over
    # hundreds of pairs becomes a windowed reduction, several times slower on a CPU)
    P, d = A.shape
    nb = -(-P // BLOCK)
    sq = np.full(nb * BLOCK, np.inf)
    sq[:P] = np.sum(A**2, axis=1)
    At = np.zeros((d, nb * BLOCK))
    At[:, :P] = A.T
    sq, At = jnp.asarray(sq.reshape(nb, BLOCK)), jnp.asarray(At.reshape(d, nb, BLOCK))
    lo, span = jnp.asarray(lo), jnp.asarray(span)

    def distance(x):
        u = (features(x) - lo) / span
        d2 = sq - 2 * sum(At[j] * u[j] for j in range(d))
        nearest = jnp.sqrt(jnp.maximum(jnp.min(jnp.min(d2, axis=1)) + jnp.sum(u * u), 0.0))
        return nearest, jnp.linalg.norm(jnp.maximum(jnp.maximum(-u, u - 1.0), 0.0))
    return distance


def box_distance_fn(lo, span):
    """``x -> (0, distance outside the box [lo, lo + span] scaled by span)``: the coverage
    of a model without stored training pairs (its input box)."""
    lo, span = jnp.asarray(lo, float), jnp.asarray(span, float)

    def distance(x):
        u = (x - lo) / span
        return jnp.zeros((), x.dtype), jnp.linalg.norm(jnp.maximum(jnp.maximum(-u, u - 1.0), 0.0))
    return distance
