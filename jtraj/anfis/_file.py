"""Writing a model file: the format's name and version, and :func:`save` (read back by
:func:`jtraj.anfis.io.load`). A module of its own, below :mod:`.model`, so that
``Model.save`` needs no import of the reader."""

from __future__ import annotations

import json
import os

import equinox as eqx

FORMAT = "jtraj.anfis"
FORMAT_VERSION = 2  # 2: ensembles (version 1 files, single models, are still read)
READS = (1, 2)


def _model_header(model) -> dict:
    return dict(kind=model.kind, order=model.order, scalar_output=model.scalar_output, n_rules=model.n_rules,
                n_inputs=model.n_inputs, n_outputs=model.n_outputs, dtype=str(model.centers.dtype),
                metadata=model.metadata, clip_outputs=bool(model.clip_outputs))


def save(path, model) -> None:
    """Write ``model`` (a :class:`Model` or an :class:`Ensemble`) to ``path`` (parent
    directories must exist); an ensemble's header adds the rules per member."""
    header = _model_header(model)
    if hasattr(model, "sizes"):  # an ensemble
        header["sizes"] = list(model.sizes)
    header.update(format=FORMAT, version=FORMAT_VERSION)
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(json.dumps(header, sort_keys=True).encode() + b"\n")
        eqx.tree_serialise_leaves(f, model)
    os.replace(tmp, path)
