"""On-disk layout of a dataset: a directory of independent, atomically written HDF5 chunks.

::

    PATH/
      manifest.json          written first (atomically): format, identity, metadata
      .lock                  advisory lock (fcntl) held by the process building the dataset
      chunks/
        chunk-000000.h5      pairs [0, B)          one self-describing HDF5 file per chunk
        chunk-000001.h5      pairs [B, 2B)
        ...
        chunk-000007.h5.tmp-<pid>   a chunk being written (ignored; removed on resume)

Durability. A chunk is written to ``chunk-XXXXXX.h5.tmp-<pid>``, flushed, ``fsync``-ed
and only then renamed to its final name with :func:`os.replace` (atomic on POSIX); the
directory is ``fsync``-ed after the rename. A ``kill -9`` at any moment therefore
leaves either no file for a chunk or a complete one; finished chunks are never opened for
writing again. Each chunk file repeats the dataset's identity (JSON), its hash and its
pair range in its attributes, so it cannot be mixed into another dataset.

Integrity. A file damaged after it was written (a disk fault, a bad copy) is detected and
named: every HDF5 dataset (field) carries a Fletcher-32 checksum of its stored bytes
(checked by HDF5 on every read) and a SHA-256 of its array (dtype, shape and values) in
its attribute ``sha256``; the file's attribute ``digest`` is a SHA-256 over its header
attributes (format, identity, chunk, pair range) and the fields' names and SHA-256s, so a
flipped bit in a field, in an attribute or in the list of fields shows, as does a file
HDF5 cannot open. :func:`verify_chunk` checks one file completely; ``jtraj dataset info``
and ``jtraj dataset verify`` check every chunk and name the corrupt files; a resumed
build solves corrupt chunks again instead of counting them done; :func:`read_chunk`
(hence :func:`jtraj.dataset.load`) checks the SHA-256 of every field it reads and the
header digest, and raises ``ValueError`` naming the file and saying "corrupt". Chunks
written before these checksums existed (no ``digest`` attribute) stay readable; for them
only Fletcher-32 is checked, and ``verify`` says so.

Resuming. The manifest's ``identity`` holds every parameter that determines the values
(robot and its parameters, N, weights, solver settings, seed, pairs, batch, sampling
distribution, solver function). A second run into the same path with an identical
identity computes only the missing chunks; any difference is refused with a message
naming the differing parameters.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
from typing import Iterator

import numpy as np

FORMAT = "jtraj-dataset"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
LOCK = ".lock"
CHUNKS = "chunks"
_CHUNK_RE = re.compile(r"^chunk-(\d{6})\.h5$")
_TMP_RE = re.compile(r"^chunk-(\d{6})\.h5\.tmp-\d+$")
_MAN_TMP_RE = re.compile(r"^manifest\.json\.tmp-\d+$")


def identity_hash(identity: dict) -> str:
    text = json.dumps(identity, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def chunk_name(c: int) -> str:
    return f"chunk-{c:06d}.h5"


def _fsync_dir(path: str) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _write_atomic(path: str, data: bytes) -> None:
    tmp = f"{path}.tmp-{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(os.path.dirname(os.path.abspath(path)))


def read_manifest(path: str) -> dict:
    try:
        with open(os.path.join(path, MANIFEST)) as f:
            man = json.load(f)
    except FileNotFoundError:
        raise ValueError(f"{path!r} is not a jtraj dataset (no {MANIFEST})") from None
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path!r}: unreadable {MANIFEST} ({err})") from None
    if not isinstance(man, dict) or man.get("format") != FORMAT:
        raise ValueError(f"{path!r} is not a jtraj dataset ({MANIFEST} of another format)")
    if man.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{path!r}: dataset format version {man.get('format_version')} is not supported "
                         f"(this jtraj reads version {FORMAT_VERSION})")
    return man


def _describe_diff(old: dict, new: dict, prefix: str = "") -> list[str]:
    out = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k, "<absent>"), new.get(k, "<absent>")
        if isinstance(a, dict) and isinstance(b, dict):
            out += _describe_diff(a, b, f"{prefix}{k}.")
        elif a != b:
            sa, sb = json.dumps(a), json.dumps(b)
            if len(sa) > 60:
                sa = sa[:57] + "..."
            if len(sb) > 60:
                sb = sb[:57] + "..."
            out.append(f"{prefix}{k}: {sa} in the dataset, {sb} requested")
    return out


def inspect(path: str, identity: dict) -> bool:
    """Read-only check of ``path`` for a run with ``identity``: True when it holds the same
    dataset (resume), False when it is absent or empty; ``ValueError`` otherwise."""
    apath = os.path.abspath(path)
    ident_hash = identity_hash(identity)
    resumed = False
    if os.path.lexists(apath):
        if not os.path.isdir(apath):
            raise ValueError(f"{path!r} exists and is not a directory; refusing to overwrite it "
                             f"(choose a new --out)")
        if os.path.exists(os.path.join(apath, MANIFEST)):
            man = read_manifest(apath)
            if man.get("identity_hash") != ident_hash:
                diff = _describe_diff(man.get("identity", {}), identity)
                raise ValueError(
                    f"{path!r} holds a dataset made with different parameters; refusing to resume "
                    f"into it (" + "; ".join(diff[:6] or ["identity differs"]) + "). "
                    "Use the original parameters to resume, or a new --out.")
            resumed = True
        else:
            # a run killed while writing its manifest leaves only the lock and a temp manifest
            extra = [e for e in os.listdir(apath) if e not in (LOCK, CHUNKS) and not _MAN_TMP_RE.match(e)]
            chunk_dir = os.path.join(apath, CHUNKS)
            if os.path.isdir(chunk_dir) and os.listdir(chunk_dir):
                extra.append(CHUNKS + "/...")
            if extra:
                raise ValueError(f"{path!r} is not empty and is not a jtraj dataset "
                                 f"(contains {sorted(extra)[:5]}); refusing to write into it")
    else:
        parent = os.path.dirname(apath)
        if not os.path.isdir(parent):
            raise ValueError(f"cannot create {path!r}: the parent directory {parent!r} does not exist")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise ValueError(f"cannot create {path!r}: the parent directory {parent!r} is not writable")
    if os.path.lexists(apath) and not os.access(apath, os.W_OK | os.X_OK):
        raise ValueError(f"cannot write to {path!r}: permission denied")
    return resumed


class Writer:
    """Creates or reopens the directory store at ``path`` for a run with ``identity``.

    Checks everything before compute starts: an existing path must be either empty or a
    dataset with the same identity; the path must be writable; no other process may be
    building it (advisory lock). Nothing that exists is overwritten.
    """

    def __init__(self, path: str, identity: dict, metadata: dict):
        self.path = os.path.abspath(path)
        self.identity = identity
        self.hash = identity_hash(identity)
        self._identity_json = json.dumps(identity, sort_keys=True)
        self._lock_fd = None
        self.resumed = inspect(path, identity)
        try:
            os.makedirs(self.path, exist_ok=True)
            self._lock()
            if not self.resumed:
                man = {"format": FORMAT, "format_version": FORMAT_VERSION, "identity_hash": self.hash,
                       "identity": identity, "metadata": metadata}
                _write_atomic(os.path.join(self.path, MANIFEST),
                              json.dumps(man, indent=1, sort_keys=True).encode())
            os.makedirs(os.path.join(self.path, CHUNKS), exist_ok=True)
            probe = os.path.join(self.path, CHUNKS, f".probe-{os.getpid()}")
            with open(probe, "wb"):
                pass
            os.remove(probe)
        except OSError as err:
            self.close()
            raise ValueError(f"cannot write to {path!r}: {err.strerror or err}") from None
        self._clean_tmp()

    def _lock(self):
        import fcntl

        fd = os.open(os.path.join(self.path, LOCK), os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise ValueError(f"{self.path!r} is being built by another process (locked); "
                             f"wait for it or kill it first") from None
        self._lock_fd = fd

    def close(self):
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # releases the flock
            self._lock_fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _clean_tmp(self):
        for e in os.listdir(self.path):
            if _MAN_TMP_RE.match(e):
                with contextlib.suppress(OSError):
                    os.remove(os.path.join(self.path, e))
        d = os.path.join(self.path, CHUNKS)
        for e in os.listdir(d):
            if _TMP_RE.match(e):  # a chunk that was in flight when a previous run died
                with contextlib.suppress(OSError):
                    os.remove(os.path.join(d, e))

    def finished(self, n_chunks: int) -> list[int]:
        """Indices of the chunks already on disk and intact (every checksum verified, see
        :func:`verify_chunk`); ``self.rejected`` maps the others (corrupt, of another
        dataset) to why: they are solved again."""
        done = []
        self.rejected = {}
        for c in finished_chunks(self.path):
            if c < n_chunks:
                why = chunk_problem(os.path.join(self.path, CHUNKS, chunk_name(c)), self.hash)
                if why is None:
                    done.append(c)
                else:
                    self.rejected[c] = why
        return done

    def write_chunk(self, c: int, start: int, arrays: dict) -> None:
        """Write chunk ``c`` (pairs ``start .. start+len-1``) atomically."""
        import h5py

        final = os.path.join(self.path, CHUNKS, chunk_name(c))
        tmp = f"{final}.tmp-{os.getpid()}"
        count = len(arrays["status"])
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = FORMAT
            f.attrs["identity_hash"] = self.hash
            f.attrs["chunk"] = c
            f.attrs["start"] = start
            f.attrs["count"] = count
            f.attrs["identity"] = self._identity_json  # each chunk file is readable on its own
            for k, v in arrays.items():
                v = np.asarray(v)
                d = f.create_dataset(k, data=v, fletcher32=v.size > 0, chunks=v.shape if v.size else None)
                d.attrs["sha256"] = array_digest(v)
            f.attrs["complete"] = True
            f.attrs["integrity"] = INTEGRITY
            f.attrs["digest"] = header_digest(f)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, final)
        _fsync_dir(os.path.dirname(final))


#: version of the chunk checksums (a chunk file's ``integrity`` attribute; absent: none)
INTEGRITY = 1
#: the attributes a chunk's ``digest`` covers, besides its fields' names and SHA-256s
_HEADER = ("format", "identity_hash", "chunk", "start", "count", "identity", "complete")


def array_digest(v) -> str:
    """SHA-256 of an array's dtype, shape and values (C order)."""
    v = np.ascontiguousarray(np.asarray(v))
    h = hashlib.sha256()
    h.update(v.dtype.str.encode())
    h.update(repr(v.shape).encode())
    h.update(v.tobytes())
    return h.hexdigest()


def _attr(x):
    """An HDF5 attribute's value as plain JSON-able Python."""
    if isinstance(x, bytes):
        return x.decode("utf-8", "replace")
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return x


def header_digest(f) -> str:
    """SHA-256 of an open chunk file's header attributes and its fields' SHA-256s."""
    fields = sorted((k, _attr(f[k].attrs.get("sha256"))) for k in f.keys())
    text = json.dumps({"attrs": {k: _attr(f.attrs.get(k)) for k in _HEADER}, "fields": fields}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


class CorruptChunk(ValueError):
    """A chunk file whose contents do not match its checksums (or that HDF5 cannot read)."""


def corrupt_chunk(file: str, why: str) -> CorruptChunk:
    return CorruptChunk(f"{file}: corrupt chunk ({why}); 'jtraj dataset verify' lists the corrupt chunks, and "
                        f"re-running the build command solves them again")


def check_header(f, file: str) -> bool:
    """``CorruptChunk`` where the header digest does not match; False for a chunk written
    without checksums (older format), True otherwise."""
    if "digest" not in f.attrs:
        return False
    if _attr(f.attrs["digest"]) != header_digest(f):
        raise corrupt_chunk(file, "its header attributes or list of fields do not match their checksum")
    return True


def _read_field(f, k: str, file: str, checked: bool):
    try:
        v = f[k][()]
    except OSError as err:  # HDF5's Fletcher-32 check ("filter returned failure during read")
        raise corrupt_chunk(file, f"field {k!r} fails its Fletcher-32 checksum: {err}") from None
    if checked and array_digest(v) != _attr(f[k].attrs.get("sha256")):
        raise corrupt_chunk(file, f"field {k!r} does not match its SHA-256")
    return v


def verify_chunk(file: str, ident: str | None = None) -> str | None:
    """Check chunk file ``file`` completely (every field read, every checksum compared):
    None when intact with SHA-256 checksums, ``"older format"`` when intact by Fletcher-32
    but written without SHA-256 checksums, else ``CorruptChunk`` (a ``ValueError``)
    naming the file. ``ident``: also refuse a chunk of another dataset (``ValueError``)."""
    import h5py

    try:
        with h5py.File(file, "r") as f:
            checked = check_header(f, file)
            if not bool(f.attrs.get("complete")):
                raise corrupt_chunk(file, "not marked complete")
            if ident is not None and f.attrs.get("identity_hash") != ident:
                raise ValueError(f"{file}: chunk belongs to another dataset")
            for k in f.keys():
                _read_field(f, k, file, checked)
    except CorruptChunk:
        raise
    except (OSError, KeyError, RuntimeError) as err:  # HDF5 cannot read its structure
        raise corrupt_chunk(file, f"HDF5 cannot read it: {err}") from None
    return None if checked else "older format"


def finished_chunks(path: str) -> list[int]:
    d = os.path.join(path, CHUNKS)
    if not os.path.isdir(d):
        return []
    return sorted(int(m.group(1)) for m in map(_CHUNK_RE.match, os.listdir(d)) if m)


def chunk_problem(file: str, ident: str) -> str | None:
    """Why chunk file ``file`` does not count as a finished chunk of the dataset
    ``ident`` (corrupt: :func:`verify_chunk`; of another dataset; unfinished), or None."""
    try:
        verify_chunk(file, ident)
    except ValueError as err:
        return str(err)
    return None


def read_chunk(path: str, c: int, keys=None, ident: str | None = None) -> dict:
    """Arrays of chunk ``c`` (all fields, or ``keys``), each checked against its
    checksums (``CorruptChunk``, a ``ValueError`` naming the file, where one fails)."""
    import h5py

    file = os.path.join(path, CHUNKS, chunk_name(c))
    try:
        with h5py.File(file, "r") as f:
            checked = check_header(f, file)
            if ident is not None and f.attrs.get("identity_hash") != ident:
                raise ValueError(f"{file}: chunk belongs to another dataset")
            names = list(f.keys()) if keys is None else keys
            return {k: _read_field(f, k, file, checked) for k in names}
    except (CorruptChunk, KeyError):
        raise
    except (OSError, RuntimeError) as err:
        if not os.path.exists(file):
            raise
        raise corrupt_chunk(file, f"HDF5 cannot read it: {err}") from None


def iter_chunk_files(path: str) -> Iterator[int]:
    yield from finished_chunks(path)
