"""Input validation shared by the public API.

Every public entry point validates its concrete (non-traced) inputs here and raises a
``ValueError`` that names the argument and the expected form *before* anything is
traced. Inside ``jit``/``vmap`` the values are tracers: only static properties (shape,
dtype) can be checked then, and batched paths report per-sample status codes instead.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def is_concrete(x: Any) -> bool:
    """True when ``x`` holds values we can inspect (not a JAX tracer)."""
    return not isinstance(x, jax.core.Tracer)


def as_vector(x: Any, name: str, n: int | None = None, *, positive: bool = False,
              nonnegative: bool = False, allow_inf: bool = False) -> jax.Array:
    """Convert ``x`` to a float vector, checking shape and values when concrete.

    Scalars are broadcast to length ``n`` when ``n`` is given.
    """
    if is_concrete(x):
        try:
            arr = np.asarray(x, dtype=float)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{name} must be a sequence of numbers, got {x!r}") from err
        if arr.ndim == 0 and n is not None:
            arr = np.full((n,), float(arr))
        if arr.ndim != 1:
            raise ValueError(f"{name} must be a 1-D vector, got shape {arr.shape}")
        if n is not None and arr.shape[0] != n:
            raise ValueError(f"{name} must have shape ({n},), got shape {arr.shape}")
        bad = np.isnan(arr) if allow_inf else ~np.isfinite(arr)
        if bad.any():
            raise ValueError(f"{name} must be finite, got {arr.tolist()}")
        if positive and (arr <= 0).any():
            raise ValueError(f"{name} must be > 0 element-wise, got {arr.tolist()}")
        if nonnegative and (arr < 0).any():
            raise ValueError(f"{name} must be >= 0 element-wise, got {arr.tolist()}")
        return jnp.asarray(arr)
    x = jnp.asarray(x)
    if x.ndim == 0 and n is not None:
        x = jnp.broadcast_to(x, (n,))
    if x.ndim != 1 or (n is not None and x.shape[0] != n):
        raise ValueError(f"{name} must have shape ({n},), got shape {x.shape}")
    return x


def as_array(x: Any, name: str, shape: tuple[int, ...]) -> np.ndarray:
    """A concrete ``x`` as a finite float NumPy array of ``shape`` (``ValueError`` naming
    ``name`` otherwise)."""
    try:
        arr = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be an array of numbers with shape {shape}, got {x!r}") from err
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite (no NaN or inf), got {arr.tolist()}")
    return arr


def check_state(x: Any, name: str, n: int) -> jax.Array:
    """Validate a joint-space vector of length ``n`` (or a batch ``(..., n)``)."""
    if is_concrete(x):
        try:
            arr = np.asarray(x, dtype=float)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{name} must be an array of numbers, got {x!r}") from err
        if arr.ndim == 0 or arr.shape[-1] != n:
            raise ValueError(f"{name} must have shape ({n},) (or (..., {n})), got shape {arr.shape}")
        if not np.isfinite(arr).all():
            raise ValueError(f"{name} must be finite (no NaN or inf)")
        return jnp.asarray(x, dtype=jnp.result_type(float))
    x = jnp.asarray(x)
    if x.ndim == 0 or x.shape[-1] != n:
        raise ValueError(f"{name} must have shape ({n},) (or (..., {n})), got shape {x.shape}")
    return x
