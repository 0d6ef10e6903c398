"""Elementary functions for the solver's hot loop: :func:`sincos` and :func:`log1p`.

:func:`sincos`: sine and cosine of the same float64 angles in one pass. XLA's CPU
``sin`` and ``cos`` of float64 are scalar library calls (about 25 ns for the pair per
element on the 2-core machine of the benchmarks, against 3 ns here), and the RNEA of the
planar serial arms evaluates them at every sample of every trial point of every Newton
iteration (serial3, N = 20: 13 x 21 x 3 pairs per problem and iteration).

The method is the textbook one: Cody and Waite's reduction by multiples of pi/2, with
pi/2 split in three parts (the first two of 33 significant bits, so that ``k * P1`` and
``k * P2`` are exact for ``|k| < 2^20``), then the Taylor series of sin and cos to
r^17 / r^16 on ``|r| <= pi/4`` (truncation below 5e-17 relative) by Horner's rule, and
the quadrant's signs. Measured against NumPy (glibc) on 10^6 uniform angles in
[-30, 30] rad and the multiples of pi/2 up to 9 pi: at most 1 ulp from the reference
(``tests/test_math.py``). Accurate for ``|x| <= 1e5`` rad (joint angles); beyond, the
reduction loses about ``|x| * 1e-22`` absolute; non-finite angles give NaN, as ``sin``
does. Other dtypes (float32) use ``jnp.sin`` and ``jnp.cos``.

:func:`log1p`: ``log(1 + x)`` of float64, for the PBM inequality term (its barrier
``-log(1 - t)`` is evaluated for every inequality at every trial point). XLA's CPU
``log1p`` of float64 is up to 128 ulp from NumPy's and about 10 ns per element on that
machine; this one is at most 1 ulp (``tests/test_math.py``: 2.5e5 arguments from -1 to
1e300) and about 7 ns. Method: ``u = 1 + x`` with its rounding error ``c`` carried as a
correction ``c / u`` (fdlibm's device), ``u = 2^e m`` with ``m`` in ``[sqrt(1/2), sqrt(2)]``
read off the bits, ``log m = 2 atanh(f / (2 + f))`` (``f = m - 1``) by its series to 11
terms, and ``e ln 2`` with ln 2 split in two so that ``e ln2_hi`` is exact.
``log1p(-1) = -inf``, below -1 NaN; float32 uses ``jnp.log1p``.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

# pi/2 = _P1 + _P2 + _P3 (_P1, _P2: 33 significant bits; _P3 the rest, rounded), computed
# from 60 digits of pi with exact rational arithmetic
_P1 = 1.5707963267341256
_P2 = 6.077100506303966e-11
_P3 = 2.0222662487959506e-21
_SIN = tuple((-1) ** k / math.factorial(2 * k + 1) for k in range(1, 9))  # r^3 .. r^17
_COS = tuple((-1) ** k / math.factorial(2 * k) for k in range(1, 9))  # r^2 .. r^16


def _horner(coefs, x):
    acc = coefs[-1]
    for a in reversed(coefs[:-1]):
        acc = acc * x + a
    return acc


def _sincos64(x):
    k = jnp.round(x * (2.0 / np.pi))
    r = ((x - k * _P1) - k * _P2) - k * _P3  # |r| <= pi/4 (+ rounding)
    r2 = r * r
    s = r + r * r2 * _horner(_SIN, r2)
    c = 1.0 + r2 * _horner(_COS, r2)
    q = k - 4.0 * jnp.floor(0.25 * k)  # the quadrant, 0..3, exact in floating point
    sin = jnp.where(q == 0, s, jnp.where(q == 1, c, jnp.where(q == 2, -s, -c)))
    cos = jnp.where(q == 0, c, jnp.where(q == 1, -s, jnp.where(q == 2, -c, s)))
    return sin, cos


@jax.custom_jvp
def sincos(x):
    """(sin x, cos x), elementwise; see the module's docstring for accuracy and range."""
    x = jnp.asarray(x)
    if x.dtype != jnp.float64:
        return jnp.sin(x), jnp.cos(x)
    return _sincos64(x)


@sincos.defjvp
def _sincos_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    s, c = sincos(x)
    return (s, c), (c * dx, -s * dx)


# log1p ----------------------------------------------------------------------------------
# ln 2 = _LN2_HI + _LN2_LO, _LN2_HI with its low 32 bits zero, so that e * _LN2_HI is exact
# for every binary exponent e of a float64 (the split of fdlibm's e_log.c)
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
# log(1 + f) = f - f^2/2 + s (f^2/2 + R(s^2)) with s = f / (2 + f) and R(z) = sum_k 2 z^k / (2k+1)
# (the series of 2 atanh(s), rearranged); |f| <= sqrt(2) - 1 gives z <= 0.0295, and 11 terms
# leave a truncation below 1e-18 relative
_ATANH = tuple(2.0 / (2 * k + 1) for k in range(1, 12))
_MANTISSA = 0x000FFFFFFFFFFFFF
_ONE_BITS = 0x3FF0000000000000


def _log1p64(x):
    # a one hidden behind a barrier: with the literal 1, XLA's algebraic simplifier folds
    # (1 + x) - 1 into x and the correction c below into 0 (up to 128 ulp off; a barrier
    # on u instead costs a materialised array, about 10 % slower)
    one = jax.lax.optimization_barrier(jnp.ones((), x.dtype))
    u = one + x
    # the rounding error of u = 1 + x, which log(u) cannot see: log1p(x) = log(u) + c / u
    c = jnp.where(u > 2.0, one - (u - x), x - (u - one)) / u
    bits = jax.lax.bitcast_convert_type(u, jnp.int64)
    e = ((bits >> 52) & 0x7FF) - 1023
    m = jax.lax.bitcast_convert_type((bits & _MANTISSA) | _ONE_BITS, jnp.float64)  # [1, 2)
    big = m > math.sqrt(2.0)
    m = jnp.where(big, 0.5 * m, m)  # [sqrt(1/2), sqrt(2)], exact
    e = (e + big.astype(e.dtype)).astype(jnp.float64)
    f = m - 1.0  # exact (Sterbenz)
    s = f / (2.0 + f)
    z = s * s
    hfsq = 0.5 * f * f
    R = z * _horner(_ATANH, z)
    out = e * _LN2_HI - ((hfsq - (s * (hfsq + R) + (e * _LN2_LO + c))) - f)
    # the edges: log1p(-1) = -inf, below -1 NaN, +inf and NaN pass through
    out = jnp.where(u == 0.0, -jnp.inf, out)
    out = jnp.where((x < -1.0) | jnp.isnan(x), jnp.nan, out)
    return jnp.where(x == jnp.inf, jnp.inf, out)


@jax.custom_jvp
def log1p(x):
    """log(1 + x), elementwise; see the module's docstring for accuracy and range."""
    x = jnp.asarray(x)
    if x.dtype != jnp.float64:
        return jnp.log1p(x)
    return _log1p64(x)


@log1p.defjvp
def _log1p_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    return log1p(x), dx / (1.0 + x)


def small_matmul(a, b):
    """``a @ b`` for small matrices (trailing two axes, leading axes broadcast) as an
    elementwise product summed. XLA on a CPU turns a dot, batched or not, into an Eigen
    contraction that packs its operands into freshly allocated buffers, a fixed cost far
    above the arithmetic at these sizes (a few rows per stage); the product fuses with its
    neighbours into one loop instead (for the interior-point Newton model's two per-stage
    products, about 7 % fewer instructions in a serial3 solve at N = 20)."""
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)
