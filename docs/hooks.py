"""mkdocs hook: serve the figures that live beside the code they come from.

``examples/figures/*.png`` (the reproduced experiments) and ``benchmarks/figures/*.png``
are added to the site as ``figures/<name>.png``, so that the pages (and
``examples/RESULTS.md``, included in ``experiments.md``) refer to them without copies in
``docs/``. Nothing here runs the solver.
"""

from __future__ import annotations

import os

from mkdocs.structure.files import File

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_SOURCES = ("examples", "benchmarks")


def on_files(files, config):
    for top in _SOURCES:
        src_dir = os.path.join(_ROOT, top)
        folder = os.path.join(src_dir, "figures")
        if not os.path.isdir(folder):
            continue
        for name in sorted(os.listdir(folder)):
            if name.endswith(".png"):
                files.append(File(f"figures/{name}", src_dir, config["site_dir"], config["use_directory_urls"]))
    return files
