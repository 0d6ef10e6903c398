"""jtraj: differentiable robot trajectory optimisation in JAX."""

__version__ = "0.1.0"
