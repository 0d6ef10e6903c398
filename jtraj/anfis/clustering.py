"""Chiu's subtractive clustering, as MATLAB's ``subclust`` (and ``genfis2``) does it.

Algorithm (S. Chiu, 1994; MATLAB Fuzzy Logic Toolbox ``subclust``):

1. Scale every column of the data to the unit hypercube with its min and max (a
   constant column keeps span 1 instead of dividing by zero).
2. Potential of each point ``P_i = sum_j exp(-4 ||(z_i - z_j) / r_a||^2)``.
3. Repeatedly take the point of highest potential ``P*``, with ``ratio = P* / P_1``
   (``P_1`` the first maximum):

   * ``ratio > accept``: accept it as a centre;
   * ``ratio <= reject``: stop;
   * otherwise accept it when ``ratio + d_min >= 1`` (``d_min`` its distance to the
     nearest centre, in units of ``r_a``), else set its potential to 0 and try the
     next-highest point.

   After accepting ``c`` every potential is revised,
   ``P_i -= P* exp(-4 ||(z_i - c) / (squash r_a)||^2)`` (clipped at 0).
4. Gaussian widths ``sigma = r_a (max - min) / sqrt(8)`` per input dimension.

**The first-centre quirk.** MATLAB computes ``d_min`` as ``sqrt(minDistSq)`` with
``minDistSq = -1`` while there is no centre; ``sqrt(-1)`` is ``i`` and MATLAB's ``>=``
compares real parts only, so the first point (ratio 1) is always accepted when
``reject < 1``. A literal port to real arithmetic gets NaN, rejects every candidate and
finds no centre with settings such as the thesis' (radius 0.9, squash 0.5, accept 1.0,
reject 0.8). We treat "no centre yet" as ``d_min = 0``, which reproduces MATLAB.

Memory: the potentials are computed in row chunks (``chunk_bytes``, 256 MB by default)
from squared norms, never as a full (P, P) or (P, P, d) array, so 50,000 samples in a
dozen dimensions need well under 2 GB. The greedy selection runs in NumPy (one O(P d)
revision per accepted centre).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class Clusters(NamedTuple):
    """Result of :func:`subclust`, in the units of the data.

    centers: (R, D) cluster centres, in order of acceptance (decreasing potential).
    sigmas: (D,) Gaussian widths ``r_a (max - min) / sqrt(8)``.
    lo, span: (D,) the unit-hypercube scaling used (``z = (x - lo) / span``).
    radius: (D,) the radii of influence ``r_a`` (in unit-hypercube units).
    """

    centers: np.ndarray
    sigmas: np.ndarray
    lo: np.ndarray
    span: np.ndarray
    radius: np.ndarray


def unit_scaling(X: np.ndarray, bounds=None) -> tuple[np.ndarray, np.ndarray]:
    """(lo, span) mapping X column-wise onto [0, 1]; constant columns keep span 1."""
    X = np.asarray(X, dtype=float)
    if bounds is None:
        lo, hi = X.min(axis=0), X.max(axis=0)
    else:
        lo, hi = (np.asarray(b, dtype=float) for b in bounds)
    span = hi - lo
    span = np.where(span > 0, span, 1.0)
    return lo, span


@jax.jit
def _potential_chunk(rows, Z, sqZ):
    d2 = jnp.sum(rows**2, axis=1)[:, None] + sqZ[None, :] - 2.0 * rows @ Z.T
    return jnp.sum(jnp.exp(-4.0 * jnp.maximum(d2, 0.0)), axis=1)


def potentials(Z: np.ndarray, radius, *, chunk_bytes: int = 256 * 2**20) -> np.ndarray:
    """``P_i = sum_j exp(-4 ||(z_i - z_j) / r_a||^2)`` for unit-scaled data Z (P, D)."""
    Z = np.asarray(Z, dtype=float)
    P = Z.shape[0]
    Zs_np = Z / np.asarray(radius, dtype=float)
    Zs, sqZ = jnp.asarray(Zs_np), jnp.asarray(np.sum(Zs_np**2, axis=1))
    rows = max(1, min(P, chunk_bytes // (8 * P * 3)))  # d2, exp and a temporary
    out = np.empty(P)
    for s in range(0, P, rows):
        block = Zs_np[s:s + rows]
        if block.shape[0] < rows:  # keep one compiled shape: pad the last chunk
            block = np.concatenate([block, np.zeros((rows - block.shape[0], Z.shape[1]))])
        out[s:s + rows] = np.asarray(_potential_chunk(block, Zs, sqZ))[: min(rows, P - s)]
    return out


def subclust(X, radius=0.5, *, squash: float = 1.25, accept: float = 0.5, reject: float = 0.15,
             bounds=None, max_centers: int | None = None, chunk_bytes: int = 256 * 2**20) -> Clusters:
    """Subtractive clustering of X (P, D) as MATLAB ``subclust(X, radius, bounds,
    [squash accept reject 0])``.

    ``radius`` is a scalar or one radius per column (unit-hypercube units, typically
    0.2-0.5). ``bounds = (lo, hi)`` overrides the data's min and max. ``max_centers``
    stops after that many centres (used by the rule-count search). Returns
    :class:`Clusters` (possibly with zero centres: the caller decides whether that is
    an error).
    """
    X = np.asarray(X, dtype=float)
    if X.ndim != 2 or X.shape[0] == 0:
        raise ValueError(f"X must be a non-empty 2-D array (samples, dims), got shape {X.shape}")
    if not np.isfinite(X).all():
        raise ValueError("X contains NaN or infinite values")
    P, D = X.shape
    r = np.broadcast_to(np.asarray(radius, dtype=float), (D,)).copy()
    if not (np.isfinite(r).all() and (r > 0).all()):
        raise ValueError(f"radius must be finite and > 0, got {radius!r}")
    if not squash > 0:
        raise ValueError(f"squash must be > 0, got {squash!r}")
    lo, span = unit_scaling(X, bounds)
    Z = (X - lo) / span

    pot = potentials(Z, r, chunk_bytes=chunk_bytes)
    idx = int(np.argmax(pot))
    best = float(pot[idx])
    ref = best
    inv_r = 1.0 / r
    inv_sq = 1.0 / (squash * r)
    centers: list[np.ndarray] = []
    limit = P if max_centers is None else int(max_centers)
    while best > 0 and len(centers) < limit:
        cand = Z[idx]
        ratio = best / ref
        if ratio > accept:
            take = True
        elif ratio > reject:
            if centers:
                d2 = np.sum(((np.asarray(centers) - cand) * inv_r) ** 2, axis=1)
                d_min = math.sqrt(float(d2.min()))
            else:
                d_min = 0.0  # MATLAB: sqrt(-1) = i, compared by real part (see module doc)
            take = ratio + d_min >= 1.0
        else:
            break
        if take:
            centers.append(cand.copy())
            pot = pot - best * np.exp(-4.0 * np.sum(((Z - cand) * inv_sq) ** 2, axis=1))
            pot[pot < 0] = 0.0
        else:
            pot[idx] = 0.0
        idx = int(np.argmax(pot))
        best = float(pot[idx])
    C = np.asarray(centers).reshape(-1, D) * span + lo
    sigmas = r * span / math.sqrt(8.0)
    return Clusters(C, sigmas, lo, span, r)


def radius_for_rules(X, n_rules: int, *, squash: float = 1.25, accept: float = 0.5, reject: float = 0.15,
                     r_min: float = 0.01, r_max: float = 2.0, iters: int = 30,
                     chunk_bytes: int = 256 * 2**20) -> tuple[float, Clusters]:
    """Radius whose clustering yields ``n_rules`` centres, by bisection.

    The number of centres falls (not always strictly monotonically) as the radius
    grows. Bisection on ``log r`` in ``[r_min, r_max]`` keeps the invariant
    ``count(lo) >= n_rules > count(hi)``; after ``iters`` halvings (or on an exact hit)
    the largest radius with at least ``n_rules`` centres is used and, when counts jump
    past ``n_rules``, its first ``n_rules`` centres (highest potential first) are kept.
    Returns ``(radius, clusters)``.
    """
    X = np.asarray(X, dtype=float)
    n_rules = int(n_rules)
    if n_rules < 1:
        raise ValueError(f"n_rules must be >= 1, got {n_rules}")
    if n_rules > X.shape[0]:
        raise ValueError(f"n_rules = {n_rules} exceeds the number of samples ({X.shape[0]})")

    def count(rad):
        cl = subclust(X, rad, squash=squash, accept=accept, reject=reject, max_centers=n_rules + 1,
                      chunk_bytes=chunk_bytes)
        return cl.centers.shape[0], cl

    lo, hi = r_min, r_max
    n_lo, cl_lo = count(lo)
    if n_lo < n_rules:
        raise ValueError(f"no radius >= {r_min} yields {n_rules} rules (radius {r_min} gives {n_lo}); "
                         "lower accept/reject or supply more distinct samples")
    n_hi, cl_hi = count(hi)
    if n_hi >= n_rules:
        lo, cl_lo, n_lo = hi, cl_hi, n_hi
    else:
        for _ in range(iters):
            mid = math.sqrt(lo * hi)
            n_mid, cl_mid = count(mid)
            if n_mid >= n_rules:
                lo, cl_lo, n_lo = mid, cl_mid, n_mid
                if n_mid == n_rules:
                    break
            else:
                hi = mid
    cl = cl_lo
    if cl.centers.shape[0] > n_rules:
        cl = cl._replace(centers=cl.centers[:n_rules])
    return lo, cl
