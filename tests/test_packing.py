"""jtraj._packing: batched pytrees packed into one array per dtype and back."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtraj import _packing


def _tree(B):
    rng = np.random.default_rng(0)
    return {"z": jnp.asarray(rng.normal(size=(B, 5, 2))), "it": jnp.arange(B), "done": jnp.arange(B) % 2 == 0,
            "mu": jnp.asarray(rng.normal(size=(B,))), "label": "serial3", "flag": True,
            "nested": (jnp.asarray(rng.normal(size=(B, 3))), jnp.ones((B, 2, 2), jnp.int32))}


def test_pack_unpack_round_trip_under_jit():
    """Every array comes back bit for bit with its shape and dtype, static leaves as they
    were; one packed array per dtype, (B, total width)."""
    tree = _tree(6)
    how = _packing.packing(tree)
    packed = jax.jit(lambda t: _packing.pack(t, how))(_packing.arrays(tree))
    widths = dict(how.groups)
    assert {a.dtype.name for a in packed} == set(widths)
    for (name, width), a in zip(how.groups, packed):
        assert a.shape == (6, width) and a.dtype.name == name
    back = _packing.from_arrays(jax.jit(lambda p: _packing.arrays(_packing.unpack(p, how)))(packed), how)
    assert jax.tree.structure(back) == jax.tree.structure(tree)
    for x, y in zip(jax.tree.leaves(tree), jax.tree.leaves(back)):
        if isinstance(x, jax.Array):
            assert x.dtype == y.dtype and x.shape == y.shape
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        else:
            assert x == y


def test_packing_is_hashable_and_rows_are_problems():
    """A Packing keys compiled programs (equal trees, equal packings); a row of the packed
    arrays is one problem, so gathering rows gathers problems."""
    how = _packing.packing(_tree(4))
    assert how == _packing.packing(_tree(4)) and hash(how) == hash(_packing.packing(_tree(4)))
    tree = _tree(4)
    rows = jnp.asarray([3, 1])
    sub = _packing.unpack(tuple(a[rows] for a in _packing.pack(_packing.arrays(tree), how)), how)
    for x, y in zip(jax.tree.leaves(tree), jax.tree.leaves(sub)):
        if isinstance(x, jax.Array):
            np.testing.assert_array_equal(np.asarray(x)[np.asarray(rows)], np.asarray(y))


def test_packing_rejects_leaves_without_a_common_batch_axis():
    with pytest.raises(ValueError, match="batch axis"):
        _packing.packing({"a": jnp.zeros((3, 2)), "b": jnp.zeros((4,))})
    with pytest.raises(ValueError, match="batch axis"):
        _packing.packing({"a": jnp.zeros((3, 2)), "b": jnp.zeros(())})
