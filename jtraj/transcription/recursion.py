"""Khoukhi's state recursion and the sums over samples it is made of, and the jerk rows
shared by the transcriptions whose accelerations are piecewise constant."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def recursion_step(q, qd, a, h):
    """One step of Khoukhi's recursion: ``(q + h qd + h^2/2 a, qd + h a)``
    (:func:`integrate` is its closed form over all steps)."""
    return q + h * qd + 0.5 * h**2 * a, qd + h * a


def integrate(q0, qd0, v, h):
    """Closed form of the decoupled recursion: (q, qd), each (N+1, n), by prefix sums
    (:func:`prefix_sums`; under ``jacfwd``/``vmap`` on a CPU about 3x faster than
    ``cumsum``, measured)."""
    qd = qd0[None] + prefix_sums(h[:, None] * v)
    dq = h[:, None] * qd[:-1] + 0.5 * (h**2)[:, None] * v
    return q0[None] + prefix_sums(dq), qd


def sample_times(h):
    """t_k = sum_{i<k} h_i, (N+1,), from the periods h (N,)."""
    return prefix_sums(h)


def time_differences(h):
    """(t (N+1,), low (N+1, N): k > j, dt (N+1, N): t_k - t_j where k > j, else 0)."""
    N = h.shape[0]
    t = sample_times(h)
    low = jnp.arange(N + 1)[:, None] > jnp.arange(N)[None, :]
    return t, low, jnp.where(low, t[:, None] - t[None, :N], 0.0)


# Prefix and suffix sums over the samples are products with a triangular matrix of ones,
# not ``cumsum``: XLA's CPU lowering of a cumsum is a blocked reduce-window (pads,
# transposes and copies, several kernels each), and these arrays are short (N + 1 rows).
# The products are elementwise and summed, not a dot: XLA fuses them into one loop, where
# a dot of these small shapes is an Eigen contraction that packs its operands into freshly
# allocated buffers (about 3-4 % fewer instructions for a serial3 solve at N = 20).
def tri_product(tri, X):
    """``tensordot(tri, X, axes=1)`` for a constant 0/1 matrix ``tri``, elementwise."""
    tri = jnp.asarray(tri, X.dtype)
    return jnp.sum(tri.reshape(tri.shape + (1,) * (X.ndim - 1)) * X[None], axis=1)


#: Beyond this many stages the prefix and suffix sums are ``cumsum``: the triangular
#: product's (N + 1, N, ...) intermediate grows as N^2, and under ``jacfwd`` (the
#: polish's and the least-squares multipliers' Jacobians: one tangent per variable) as
#: N^3 (serial3 at N = 1,000: about 100 GB).
TRI_MAX = 64


def prefix_sums(X):
    """sum_{j < k} X_j for k = 0..N, from X (N, ...) over the stages."""
    N = X.shape[0]
    if N > TRI_MAX:
        return jnp.concatenate([jnp.zeros_like(X[:1]), jnp.cumsum(X, axis=0)])
    return tri_product(np.tri(N + 1, N, -1), X)


def suffix_sums(X):
    """sum_{k > j} X_k for j = 0..N-1, from X (N+1, ...) over the samples."""
    N = X.shape[0] - 1
    if N > TRI_MAX:
        return jnp.cumsum(X[::-1], axis=0)[::-1][1:]
    return tri_product(np.triu(np.ones((N, N + 1)), 1), X)


def jerk_inequalities(v, h, limits):
    """The jerk bound between consecutive intervals, normalised, (2 (N-1) n,)::

        |v_{k+1} - v_k| <= qddd_max (h_k + h_{k+1}) / 2,   k = 0..N-2, per joint

    The accelerations are constant over each interval, so the motion's jerk is a train
    of impulses at the inner samples; the bound limits each impulse's weight, the jump
    of acceleration, to what a jerk of ``qddd_max`` achieves over the time between the
    two intervals' midpoints (the finite-difference jerk at sample k+1 is then within
    ``qddd_max``). Written this way, and not as ``|v_{k+1} - v_k| / dt <= qddd_max``, the
    rows are *linear* in (v, h): a polyhedron in z, with a constant Jacobian and no
    curvature of its own. Each row is divided by ``qddd_max h_max`` (the bound at the
    longest periods), so ``g <= tol`` lets the jump exceed its bound by at most
    ``tol qddd_max h_max``. The jumps from rest into the first interval and out of the
    last are not bounded (the boundary accelerations are not part of the problem).

    ``v`` (N, n) accelerations, ``h`` (N,) periods; rows ordered (k, joint, sign)."""
    return jump_rows(v[1:] - v[:-1], 0.5 * (h[1:] + h[:-1]), limits)


def jump_rows(dv, dt, limits):
    """``|dv| <= qddd_max dt`` row by row as ``(+-dv - qddd_max dt) / (qddd_max h_max) <= 0``:
    dv (K, n) jumps of acceleration, dt (K,) the times they may take; (2 K n,)."""
    J = jnp.asarray(limits.qddd_max, dv.dtype)
    J = jnp.broadcast_to(J, dv.shape[-1:])[None]  # (1, n)
    reach = dt[:, None] * J
    scale = J * limits.h_max
    return jnp.stack([(dv - reach) / scale, (-dv - reach) / scale], axis=-1).ravel()
