"""A hash of jtraj's own source files: the key part that changes when the code does
(kept traces, the compiled-solver markers, datasets' provenance). Imports nothing of
jtraj, so that every low-level module may use it."""

from __future__ import annotations

import functools
import hashlib
import os


def source_hash() -> str:
    """sha256 of jtraj's Python sources (16 hex digits; a solver edited between two runs
    changes it)."""
    root = os.path.dirname(os.path.abspath(__file__))
    h = hashlib.sha256()
    for dirpath, dirnames, files in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
        for f in sorted(files):
            if f.endswith(".py"):
                full = os.path.join(dirpath, f)
                h.update(os.path.relpath(full, root).encode())
                with open(full, "rb") as fh:
                    h.update(fh.read())
    return h.hexdigest()[:16]


source_hash_cached = functools.lru_cache(maxsize=1)(source_hash)
