"""Coverage of a learned planner: how far a query lies from its training data.

A query is a start/goal pair ``x = (q_start, q_goal)`` (2n numbers), the input of a
``plan`` model. The training pairs are stored in the model's metadata
(``train_pairs``, written by :func:`jtraj.anfis.trajectory.train_mapping`). Distances are
Euclidean after scaling every coordinate by the training pairs' range
(``(x - lo) / span``, the normalisation of the model's own inputs), so 1 is the width of
the training data along a coordinate.

The radius of the training data (``coverage_radius`` in the metadata) is the largest
distance from a training pair to its nearest other training pair: a query farther from
every training pair than that lies in a hole or outside of the data no training pair
lies in, and is flagged out of distribution.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def normaliser(pairs):
    """``(lo, span)`` of the training pairs (P, d); span 1 where a coordinate is constant."""
    pairs = np.asarray(pairs, float)
    lo, span = pairs.min(0), np.ptp(pairs, axis=0)
    return lo, np.where(span > 0, span, 1.0)


def radius(pairs, chunk: int = 1024) -> float:
    """The largest distance from a training pair to its nearest other one (module doc);
    0 with fewer than two pairs."""
    pairs = np.asarray(pairs, float)
    if len(pairs) < 2:
        return 0.0
    lo, span = normaliser(pairs)
    A = (pairs - lo) / span
    sq = np.sum(A**2, 1)
    worst = 0.0
    for s in range(0, len(A), chunk):
        d2 = sq[s:s + chunk, None] + sq[None, :] - 2 * A[s:s + chunk] @ A.T
        np.fill_diagonal(d2[:, s:s + chunk], np.inf)
        worst = max(worst, float(np.sqrt(np.maximum(d2.min(1), 0.0)).max()))
    return worst


def distance_fn(pairs):
    """A jit-, vmap-able ``x (d,) -> distance`` to the nearest training pair (module doc)."""
    lo, span = normaliser(pairs)
    A = jnp.asarray((np.asarray(pairs, float) - lo) / span)
    lo, span = jnp.asarray(lo), jnp.asarray(span)

    sq = jnp.sum(A**2, axis=1)

    def distance(x):
        u = (x - lo) / span
        return jnp.sqrt(jnp.maximum(jnp.min(sq - 2 * (A @ u)) + u @ u, 0.0))
    return distance


def box_distance_fn(lo, span):
    """``x -> distance`` outside the box ``[lo, lo + span]`` (scaled by span): the
    coverage of a model without stored training pairs (its input box)."""
    lo, span = jnp.asarray(lo, float), jnp.asarray(span, float)

    def distance(x):
        u = (x - lo) / span
        return jnp.linalg.norm(jnp.maximum(jnp.maximum(-u, u - 1.0), 0.0))
    return distance
