"""Sub-commands of the ``jtraj`` CLI; see :mod:`jtraj.cli` for the protocol."""

from __future__ import annotations

import os


def check_input_file(path, option: str) -> None:
    """ValueError naming ``option`` unless ``path`` is an existing, readable file."""
    if path is None:
        return
    if not os.path.exists(path):
        raise ValueError(f"{option} {path!r} does not exist")
    if os.path.isdir(path):
        raise ValueError(f"{option} {path!r} is a directory, not a file")
    if not os.access(path, os.R_OK):
        raise ValueError(f"{option} {path!r} is not readable")


def check_output_file(path, option: str) -> None:
    """ValueError naming ``option`` unless a file can be written at ``path``: checked
    before any compute, so that a typo in an output path does not throw a finished
    solve or training away."""
    if path is None:
        return
    path = os.fspath(path)
    if not path or os.path.isdir(path):
        raise ValueError(f"{option} {path!r} is a directory, not a file name")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise ValueError(f"{option} {path!r}: the folder {folder!r} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK) or (os.path.exists(path) and not os.access(path, os.W_OK)):
        raise ValueError(f"{option} {path!r} is not writable")
