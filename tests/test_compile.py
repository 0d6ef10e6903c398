"""jtraj._compile.cpu_jit: XLA options on the CPU backend, none elsewhere."""

import jax
import jax.numpy as jnp
import pytest

from jtraj import _compile
from jtraj._compile import cpu_jit


def test_cpu_jit_passes_its_options_on_cpu_only(monkeypatch):
    # an option XLA does not know makes the compilation fail: with the filter of unknown
    # options bypassed, proof that the options reach XLA on the CPU
    if jax.default_backend() != "cpu":
        pytest.skip("needs the CPU as JAX's default backend")
    monkeypatch.setattr(_compile, "supported_options", lambda options: dict(options))
    f = cpu_jit({"xla_no_such_option": True})(lambda x: 2.0 * x)
    with pytest.raises(Exception, match="xla_no_such_option"):
        f(jnp.ones(3))
    # on another backend the same function compiles without the options
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert jnp.array_equal(f(jnp.ones(3)), jnp.full(3, 2.0))


def test_options_unknown_to_xla_are_dropped():
    # experimental XLA options come and go between jaxlib releases: an unknown one (or a
    # value XLA refuses) is left out instead of failing every compilation
    options = {"xla_no_such_option": True, "xla_cpu_use_fusion_emitters": False,
               "xla_cpu_experimental_ynn_fusion_type": "NO_SUCH_FUSION_TYPE"}
    assert _compile.supported_options(options) == {"xla_cpu_use_fusion_emitters": False}
    f = cpu_jit(options)(lambda x: 2.0 * x)
    assert jnp.array_equal(f(jnp.ones(3)), jnp.full(3, 2.0))


def test_cpu_jit_keeps_filter_jit_semantics():
    # non-array arguments are static, as with eqx.filter_jit
    g = cpu_jit({"xla_cpu_use_fusion_emitters": False})(lambda x, k: x * k if k > 1 else -x)
    assert jnp.array_equal(g(jnp.arange(3.0), 3), jnp.arange(3.0) * 3)
    assert jnp.array_equal(g(jnp.arange(3.0), 1), -jnp.arange(3.0))
