"""Batched generation of optimal-trajectory datasets: sampling, chunked solving, durable
storage, resume, scale-out on Ray, and learning views.

Build (or resume) from Python::

    from jtraj import dataset
    spec = dataset.make_spec("serial3", pairs=1000, seed=0, N=20)
    dataset.build(spec, "runs/serial3-1k")

or from the shell: ``jtraj dataset --robot serial3 --pairs 1000 --seed 0 --out runs/serial3-1k``.

Read::

    data = dataset.load("runs/serial3-1k")
    data["q"].shape          # (P, N+1, n)
    data["converged"].mean() # fraction of strictly converged pairs
    data["metadata"]         # robot, limits, weights, N, solver settings, seed, sampling, versions

The store layout and its durability guarantees are described in
:mod:`jtraj.dataset.store`, the sampling distributions in :mod:`jtraj.dataset.sampling`.

Memory. :func:`load` reads lazily: a field is read from the chunk files (and
concatenated) the first time it is accessed, then kept. All fields of a serial3, N = 20
dataset take about 2.3 kB per pair (about 230 MB for 100,000 pairs); :func:`iter_chunks`
streams chunk by chunk in constant memory for larger ones. Building holds only the
chunks in flight.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import numpy as np

from . import sampling, store
from .build import Spec, build, compute_chunk, make_spec

__all__ = ["Dataset", "Spec", "build", "compute_chunk", "iter_chunks", "load", "make_spec", "sampling", "store",
           "summary", "verify", "views"]


class Dataset(Mapping):
    """Read-only mapping ``field -> numpy array`` over a dataset directory, plus ``"metadata"``.

    Arrays have the pair axis first, in pair order. Fields are read on first access.
    Attributes: ``path``, ``metadata``, ``identity``, ``chunks`` (indices present),
    ``complete``, ``pairs`` (pairs present).
    """

    def __init__(self, path: str, partial: bool = False, exclude=()):
        self.path = os.path.abspath(path)
        man = store.read_manifest(self.path)
        self.identity = man["identity"]
        self.metadata = dict(man["metadata"], identity=man["identity"])
        self._hash = man["identity_hash"]
        n_chunks = int(self.metadata["chunks"])
        self.chunks = [c for c in store.finished_chunks(self.path) if c < n_chunks and c not in exclude]
        self.complete = len(self.chunks) == n_chunks
        if not self.complete and not partial:
            raise ValueError(f"dataset {path!r} is incomplete ({len(self.chunks)}/{n_chunks} chunks); re-run the "
                             f"same command to resume it, or load(path, partial=True) for the finished chunks")
        import h5py

        # the fields of every chunk: a dataset resumed with a newer jtraj may hold chunks
        # with a field that older chunks lack (see __getitem__)
        self._keys, self._chunk_keys = [], {}
        for c in self.chunks:
            file = os.path.join(self.path, store.CHUNKS, store.chunk_name(c))
            try:  # the header's checksum here; each field's when it is read (store.read_chunk)
                with h5py.File(file, "r") as f:
                    store.check_header(f, file)
                    self._chunk_keys[c] = set(f.keys())
            except (OSError, RuntimeError) as err:
                raise store.corrupt_chunk(file, f"HDF5 cannot read it: {err}") from None
            self._keys += [k for k in sorted(self._chunk_keys[c]) if k not in self._keys]
        self._cache: dict = {}

    @property
    def pairs(self) -> int:
        return len(self["status"]) if self.chunks else 0

    def __getitem__(self, key):
        if key == "metadata":
            return self.metadata
        if key not in self._cache:
            if key not in self._keys:
                raise KeyError(key)
            parts = [store.read_chunk(self.path, c, [key], self._hash)[key] if key in self._chunk_keys[c] else None
                     for c in self.chunks]
            if any(p is None for p in parts):  # chunks written before the field existed: NaN rows
                like = next(p for p in parts if p is not None)
                counts = [len(store.read_chunk(self.path, c, ["index"], self._hash)["index"]) for c in self.chunks]
                parts = [p if p is not None else np.full((n,) + like.shape[1:], np.nan) for p, n in zip(parts, counts)]
            self._cache[key] = np.concatenate(parts) if parts else np.zeros(0)
        return self._cache[key]

    def __iter__(self):
        yield from self._keys
        yield "metadata"

    def __len__(self):
        return len(self._keys) + 1

    def __repr__(self):
        return (f"Dataset({self.path!r}, robot={self.metadata['robot']!r}, pairs={self.metadata['pairs']}, "
                f"N={self.metadata['N']}, chunks={len(self.chunks)}/{self.metadata['chunks']})")


def load(path: str, *, partial: bool = False) -> Dataset:
    """Open the dataset at ``path`` (see :class:`Dataset`). ``partial=True`` accepts an
    unfinished dataset and exposes the finished chunks only (``data["index"]`` gives
    their pair indices). A chunk file that fails its checksums raises ``ValueError``
    naming the file ("corrupt chunk"), here for its header and when a field is read for
    the field (see :mod:`jtraj.dataset.store`; :func:`verify` checks every chunk)."""
    return Dataset(path, partial=partial)


def verify(path: str) -> dict:
    """Check every chunk file of the dataset at ``path`` completely (all fields read, all
    checksums compared, see :func:`jtraj.dataset.store.verify_chunk`). Returns
    ``{"chunks": expected count, "intact": [...], "older": [...] (intact by Fletcher-32,
    written without SHA-256 checksums), "corrupt": {chunk: message naming the file},
    "missing": [...]}``."""
    man = store.read_manifest(path)
    n_chunks = int(man["metadata"]["chunks"])
    out = {"chunks": n_chunks, "intact": [], "older": [], "corrupt": {}, "missing": []}
    present = [c for c in store.finished_chunks(path) if c < n_chunks]
    for c in present:
        try:
            note = store.verify_chunk(os.path.join(os.path.abspath(path), store.CHUNKS, store.chunk_name(c)),
                                      man["identity_hash"])
        except ValueError as err:
            out["corrupt"][c] = str(err)
        else:
            out["older" if note else "intact"].append(c)
    out["missing"] = sorted(set(range(n_chunks)) - set(present))
    return out


def verify_report(path: str) -> tuple[str, bool]:
    """``jtraj dataset verify``'s text and whether every present chunk is intact."""
    r = verify(path)
    lines = [f"dataset {os.path.abspath(path)}: {r['chunks']} chunks, {len(r['intact'])} intact"
             + (f", {len(r['older'])} intact by Fletcher-32 only (written without SHA-256 checksums by an older "
                f"jtraj)" if r["older"] else "")
             + (f", {len(r['missing'])} not yet built" if r["missing"] else "")
             + (f", {len(r['corrupt'])} CORRUPT" if r["corrupt"] else "")]
    lines += [f"  corrupt: {msg}" for msg in r["corrupt"].values()]
    return "\n".join(lines), not r["corrupt"]


def iter_chunks(path: str, keys=None):
    """Yield ``(chunk index, {field: array})`` chunk by chunk (constant memory)."""
    man = store.read_manifest(path)
    for c in store.finished_chunks(path):
        yield c, store.read_chunk(path, c, keys, man["identity_hash"])


_EFFORTS_TEXT = {"samples": "samples", "intervals": "samples and interval ends"}


def summary(path: str) -> str:
    """Human-readable summary (``jtraj dataset info``): every chunk is verified first
    (:func:`verify`); corrupt chunk files are named and left out of the figures."""
    return summary_and_check(path)[0]


def _robot_note(md) -> str:
    """The URDF arm and the parameters replaced, for the summary's robot line."""
    urdf, params = md.get("urdf"), md.get("robot_params")
    note = "" if not urdf else "; a URDF arm" + (f", tip link {urdf['tip_link']}" if urdf.get("tip_link") else "")
    return note + ("; " + ", ".join(f"{k} = {v}" for k, v in params.items()) if params else "")


def summary_and_check(path: str) -> tuple[str, dict]:
    """:func:`summary`'s text and :func:`verify`'s result."""
    from jtraj.solver import Status

    check = verify(path)
    data = Dataset(path, partial=True, exclude=set(check["corrupt"]))
    md = data.metadata
    lines = [f"dataset {data.path}",
             f"  robot {md['robot']} (n = {md['n']}{_robot_note(md)}), N = {md['N']}, weights {md['weights_text']}, "
             f"seed {md['seed']}, batch {md['batch']}",
             f"  h in [{md['limits']['h_min']:g}, {md['limits']['h_max']:g}] s (T <= {md['N'] * md['limits']['h_max']:g} s)"
             f"; torque bound at the {_EFFORTS_TEXT[md.get('efforts', 'samples')]}",
             f"  sampling: {md['sampling']['space']} space, {md['sampling']['law']}",
             f"  created {md['created']} with jtraj {md['versions'].get('jtraj')}, jax {md['versions'].get('jax')}",
             f"  chunks {len(data.chunks)}/{md['chunks']}" + ("" if data.complete else " (incomplete: re-run to resume)")]
    if check["corrupt"]:
        lines.append(f"  CORRUPT chunks: {len(check['corrupt'])} (left out below; re-running the build command "
                     f"solves them again)")
        lines += [f"    {msg}" for msg in check["corrupt"].values()]
    if check["older"]:
        lines.append(f"  {len(check['older'])} chunks written without SHA-256 checksums (older jtraj): "
                     f"checked by Fletcher-32 only")
    if not data.chunks:
        return "\n".join(lines + ["  no intact chunk" if check["corrupt"] else "  no finished chunk yet"]), check
    P = data.pairs
    conv = data["converged"]
    status = data["status"]
    lines.append(f"  pairs {P}/{md['pairs']}, converged {int(conv.sum())} ({100 * conv.mean():.1f} %)")
    for code, count in zip(*np.unique(status, return_counts=True)):
        try:
            msg = Status(int(code)).name
        except ValueError:
            msg = "?"
        lines.append(f"    status {int(code)} {msg:22s} {int(count):8d}")

    def stats(name, x, unit=""):
        x = x[np.isfinite(x)]
        if not len(x):
            return f"  {name}: -"
        return (f"  {name}{unit}: median {np.median(x):.4g}, min {x.min():.4g}, max {x.max():.4g}"
                f" (converged pairs)")

    sel = conv if conv.any() else np.ones_like(conv)
    lines.append(stats("T", data["T"][sel], " [s]"))
    lines.append(stats("cost", data["cost"][sel]))
    lines.append(stats("energy", data["energy"][sel]))
    lines.append(stats("iterations", data["iterations"][sel].astype(float)))
    if "kkt_error" in data:  # datasets written before it was recorded lack it
        lines.append(stats("KKT error", data["kkt_error"][sel]))
    lines.append(f"  max violation (all pairs): median {np.median(data['max_violation']):.3g}, "
                 f"max {np.max(data['max_violation']):.3g}")
    return "\n".join(lines), check


from . import views  # noqa: E402
