"""Elementary functions for the solver's hot loop.

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
