"""Saving and loading :class:`~jtraj.anfis.Model` and :class:`~jtraj.anfis.Ensemble`.

File layout: one line of JSON (the header: format name and version, kind, order,
shapes, dtype, and the model's metadata; for an ensemble, the rules per member), a
newline, then the array leaves written by ``equinox.tree_serialise_leaves``.
:func:`load` rebuilds a skeleton of the right shapes from the header and reads the
leaves into it: no retraining, no pickle.
"""

from __future__ import annotations

import json

import equinox as eqx
import jax.numpy as jnp

from ._file import FORMAT, FORMAT_VERSION, READS, save
from .ensemble import Ensemble
from .model import KINDS, Model, n_coef

__all__ = ["FORMAT", "FORMAT_VERSION", "READS", "load", "read_header", "save"]

def read_header(path) -> dict:
    """The JSON header of a model file (ValueError if it is not one)."""
    try:
        with open(path, "rb") as f:
            line = f.readline()
        header = json.loads(line)
    except OSError:
        raise
    except (ValueError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: not a jtraj ANFIS model file") from err
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise ValueError(f"{path}: not a jtraj ANFIS model file")
    return header


def _skeleton(path, header):
    """A model (an ensemble where the header has ``sizes``) of the shapes in ``header``,
    zeros for its arrays."""
    kind, order = header["kind"], int(header["order"])
    if kind not in KINDS:
        raise ValueError(f"{path}: unknown model kind {kind!r}")
    R, d, m = int(header["n_rules"]), int(header["n_inputs"]), int(header["n_outputs"])
    dt = jnp.dtype(header["dtype"])
    z = lambda *shape: jnp.zeros(shape, dt)  # noqa: E731
    arrays = (z(R, d), z(R, d), z(R, n_coef(kind, order, d), m), z(d), z(d), z(m), z(m))
    static = dict(kind=kind, order=order, scalar_output=bool(header["scalar_output"]),
                  info=json.dumps(header.get("metadata", {}), sort_keys=True),
                  clip_outputs=bool(header.get("clip_outputs", False)))  # absent before clipping existed
    if "sizes" in header:
        sizes = tuple(int(r) for r in header["sizes"])
        if sum(sizes) != R:
            raise ValueError(f"{path}: corrupted model file (ensemble sizes {sizes} do not add up to {R} rules)")
        return Ensemble(*arrays, z(len(sizes)), sizes, **static)
    return Model(*arrays, **static)


def load(path, *, mapping: str | None = None):
    """Read a model (or an ensemble) written by :meth:`Model.save` (:meth:`Ensemble.save`).

    Raises ValueError when the file is not a model, was written by another format
    version, or (with ``mapping`` given) was trained for another trajectory mapping.
    """
    header = read_header(path)
    if header.get("version") not in READS:
        raise ValueError(f"{path}: model file format version {header.get('version')!r}, this jtraj reads "
                         f"versions {READS}; retrain or convert the model")
    meta = header.get("metadata", {})
    if mapping is not None and meta.get("mapping") != mapping:
        raise ValueError(f"{path}: model was trained for mapping {meta.get('mapping')!r}, not {mapping!r}")
    skeleton = _skeleton(path, header)
    with open(path, "rb") as f:
        f.readline()
        try:
            return eqx.tree_deserialise_leaves(f, skeleton)
        except Exception as err:  # truncated or corrupted leaves
            raise ValueError(f"{path}: corrupted model file ({err})") from err
