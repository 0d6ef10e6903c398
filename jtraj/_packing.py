"""Batched pytrees packed into one ``(B, width)`` array per dtype.

The batched solver's driver moves problems and loop states between the whole batch and a
few vmapped lanes: the AL loop's after every segment of Newton iterations
(:func:`jtraj.solver.lanes._run_lanes`), the interior-point method's inside its compiled loop
whenever a lane's problem finishes (:func:`jtraj.solver.lanes._run_pool`). As pytrees they are about 50 array leaves, and every compiled call pays for
each leaf on the way in and out (Python flattening in ``eqx.filter_jit``, then one
buffer, one gather or scatter kernel each): a gather of 8 lanes cost about 0.9 ms and a
scatter 0.8 ms, next to a 16 ms segment (serial3, N = 20, 128 pairs, one core). Packed,
a batch is a handful of arrays (float64, int, bool), and the compiled programs unpack it
inside, where slicing is free.

A :class:`Packing` (how a tree is packed) is hashable, so it keys the compiled programs.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


class Packing(NamedTuple):
    """How a batched pytree is packed: its tree structure, per leaf either
    ``(dtype name, shape without the batch axis, start in its group)`` for an array or
    ``(None, value)`` for a static leaf (kept out of the arrays), and the groups' dtypes
    and widths."""

    treedef: Any
    leaves: tuple
    groups: tuple  # ((dtype name, width), ...)


def packing(tree) -> Packing:
    """The :class:`Packing` of ``tree``, whose array leaves all have the same leading
    batch axis. Static leaves must be hashable."""
    leaves, treedef = jax.tree.flatten(tree)
    widths: dict[str, int] = {}
    spec = []
    batch = {int(np.shape(x)[0]) for x in leaves if eqx.is_array(x) and np.ndim(x)}
    if len(batch) > 1 or any(eqx.is_array(x) and not np.ndim(x) for x in leaves):
        raise ValueError(f"every array leaf needs the same leading batch axis, got sizes {sorted(batch)}")
    for x in leaves:
        if eqx.is_array(x):
            name = jnp.dtype(x.dtype).name
            start = widths.get(name, 0)
            widths[name] = start + int(np.prod(np.shape(x)[1:], dtype=int))
            spec.append((name, tuple(np.shape(x)[1:]), start))
        else:
            spec.append((None, x))
    return Packing(treedef, tuple(spec), tuple(sorted(widths.items())))


def arrays(tree) -> list:
    """The array leaves of ``tree`` in order: what :func:`pack` takes (a compiled program
    cannot take the static leaves as arguments)."""
    return [x for x in jax.tree.leaves(tree) if eqx.is_array(x)]


def pack(leaves: list, how: Packing) -> tuple:
    """The array leaves of a tree (:func:`arrays`) packed as ``how`` says, one
    ``(B, width)`` array per group."""
    parts: dict[str, list] = {name: [] for name, _ in how.groups}
    for x, (name, *_) in zip(leaves, [s for s in how.leaves if s[0] is not None]):
        parts[name].append(jnp.reshape(x, (x.shape[0], -1)))
    return tuple(jnp.concatenate(parts[name], axis=1) for name, _ in how.groups)


def unpack(packed: tuple, how: Packing):
    """The tree that :func:`pack` packed into ``packed``."""
    group = {name: a for (name, _), a in zip(how.groups, packed)}
    leaves = []
    for name, shape, start in (s for s in how.leaves if s[0] is not None):
        a = group[name]
        size = int(np.prod(shape, dtype=int))
        leaves.append(a[:, start:start + size].reshape((a.shape[0],) + shape))
    return from_arrays(leaves, how)


def from_arrays(leaves: list, how: Packing):
    """The tree whose array leaves (:func:`arrays`) are ``leaves``, its static leaves
    restored (what a compiled program that returns :func:`arrays` hands back)."""
    it = iter(leaves)
    return jax.tree.unflatten(how.treedef, [s[1] if s[0] is None else next(it) for s in how.leaves])
