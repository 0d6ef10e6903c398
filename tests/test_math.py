"""jtraj._math.sincos and log1p against NumPy's sin, cos and log1p (glibc), and their derivatives."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtraj._math import log1p, sincos


def _ulps(a, ref):
    return np.abs(np.asarray(a) - ref) / np.spacing(np.abs(ref))


def test_sincos_within_one_ulp_of_numpy():
    """At most 1 ulp from NumPy on 2e5 uniform angles in [-30, 30] rad, the multiples of
    pi/2 up to 9 pi (where the reduction matters most), tiny angles and zero."""
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.uniform(-30, 30, 200_000), np.pi / 2 * np.arange(-18, 19),
                        [0.0, -0.0, 1e-300, -1e-20, 1e-8, np.pi / 4, -np.pi / 4, 1e5, -1e5]])
    s, c = jax.jit(sincos)(jnp.asarray(x))
    ref_s, ref_c = np.sin(x), np.cos(x)
    nz_s, nz_c = ref_s != 0, ref_c != 0
    assert _ulps(s, ref_s)[nz_s].max() <= 1.0
    assert _ulps(c, ref_c)[nz_c].max() <= 1.0
    np.testing.assert_array_equal(np.asarray(s)[~nz_s], 0.0)


def test_sincos_nonfinite_gives_nan():
    s, c = sincos(jnp.asarray([np.inf, -np.inf, np.nan]))
    assert np.all(np.isnan(s)) and np.all(np.isnan(c))


def test_sincos_derivatives_and_transforms():
    """First and second derivatives are the exact cos / -sin (custom JVP), under jit and
    vmap, and float32 falls back to jnp.sin / jnp.cos."""
    x = jnp.linspace(-4.0, 4.0, 17)
    ds = jax.vmap(jax.grad(lambda t: sincos(t)[0]))(x)
    d2c = jax.vmap(jax.grad(jax.grad(lambda t: sincos(t)[1])))(x)
    s, c = sincos(x)
    np.testing.assert_array_equal(ds, c)
    np.testing.assert_array_equal(d2c, -c)
    np.testing.assert_allclose(ds, np.cos(np.asarray(x)), rtol=0, atol=2e-16)
    x32 = x.astype(jnp.float32)
    s32, c32 = jax.jit(sincos)(x32)
    assert s32.dtype == jnp.float32
    np.testing.assert_array_equal(s32, jnp.sin(x32))
    np.testing.assert_array_equal(c32, jnp.cos(x32))


@pytest.mark.parametrize("x", [0.3, -2.5])
def test_sincos_scalar(x):
    s, c = sincos(x)
    assert abs(float(s) - np.sin(x)) <= 2e-16 and abs(float(c) - np.cos(x)) <= 2e-16


def test_log1p_within_one_ulp_of_numpy():
    """At most 1 ulp from NumPy under jit on 2.5e5 arguments: uniform in (-1, 3) (the PBM
    barrier's range is [-1/2, inf)), near -1, log-uniform from 1e-300 to 1e300 of both
    signs, and the edges where the correction for 1 + x matters (tiny |x|, where XLA's own
    log1p is up to 128 ulp off)."""
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.uniform(-0.999, 3.0, 200_000), -1.0 + rng.uniform(0, 1, 10_000) ** 8,
                        10.0 ** rng.uniform(-300, 300, 20_000), -(10.0 ** rng.uniform(-300, -1e-4, 20_000)),
                        [1e-300, -1e-20, 2.0**-53, -(2.0**-53), 1e-8, -0.5, 1.0, np.sqrt(2) - 1, 1.7e308]])
    y = np.asarray(jax.jit(log1p)(jnp.asarray(x)))
    with np.errstate(divide="ignore"):
        ref = np.log1p(x)
    finite = np.isfinite(ref)  # x = -1 exactly (near -1 in the draw): -inf on both sides
    assert _ulps(y[finite], ref[finite]).max() <= 1.0
    np.testing.assert_array_equal(y[~finite], ref[~finite])
    z = np.asarray(jax.jit(log1p)(jnp.asarray([0.0, -0.0])))
    np.testing.assert_array_equal(z, 0.0)


def test_log1p_edges_derivatives_and_float32():
    y = np.asarray(jax.jit(log1p)(jnp.asarray([-1.0, -2.0, np.inf, np.nan, -np.inf])))
    assert y[0] == -np.inf and np.isnan(y[1]) and y[2] == np.inf and np.isnan(y[3]) and np.isnan(y[4])
    x = jnp.linspace(-0.9, 4.0, 23)
    d1 = jax.vmap(jax.grad(log1p))(x)
    d2 = jax.vmap(jax.grad(jax.grad(log1p)))(x)
    np.testing.assert_allclose(d1, 1.0 / (1.0 + np.asarray(x)), rtol=1e-15)
    np.testing.assert_allclose(d2, -1.0 / (1.0 + np.asarray(x)) ** 2, rtol=1e-15)
    x32 = x.astype(jnp.float32)
    y32 = jax.jit(log1p)(x32)
    assert y32.dtype == jnp.float32
    np.testing.assert_array_equal(y32, jnp.log1p(x32))
