"""JAX set-up shared by the library and the CLI: float64, the persistent compilation
cache, and a line saying when the solver compiles.

Precision. jtraj solves in float64 only. ``import jtraj`` changes no global JAX setting;
:func:`before_solve` (called by :func:`jtraj.solve` and :func:`jtraj.solve_batch`)
raises ``ValueError`` where ``jax_enable_x64`` is off, or where the problem's or the
robot's arrays are float32 (built while it was off): with x64 off JAX makes every array
float32, and the solver's tolerances (KKT error 3e-4 and below, feasibility 1e-6) are
then out of reach or met by rounding noise. The fix is one line at the start of the
program, before robots and problems are built::

    jax.config.update("jax_enable_x64", True)

The CLI (:func:`setup_jax`) switches it on itself.

Compilation cache. Compiling the solver takes tens of seconds; JAX's persistent
compilation cache keeps the compiled programs (and :mod:`jtraj._tracecache` the traced
ones) between processes. ``import jtraj`` turns it on (:func:`ensure_cache`; the first
solve would be too late for the small programs that building robots and problems
compiles: about 20 of them, 0.5-3 s of every new process), in :func:`cache_dir`:
``$JTRAJ_CACHE_DIR``, else ``$XDG_CACHE_HOME/jtraj/jax``, else ``~/.cache/jtraj/jax``;
``JTRAJ_CACHE=0`` leaves it off. A cache directory the program already set
(``jax.config.update("jax_compilation_cache_dir", ...)`` before ``import jtraj``, or
``JAX_COMPILATION_CACHE_DIR``) is kept as it is; where jtraj sets it, it also keeps
programs that compile in under a second (JAX's default keeps only longer ones), for the
whole process. Several processes may share the cache:
jtraj writes its own files (kept traces, the native kernel) to a temporary name and renames
them (atomic on POSIX); JAX writes its entries in place, so where jtraj sets the cache up
it caps it at :data:`CACHE_MAX_BYTES` (2 GiB, least recently used programs evicted;
``JTRAJ_CACHE_MAX_GB`` sets another cap, 0 none), which makes JAX hold a file lock (the
``filelock`` package) around each entry's read and write. The cap has a price: each
write reads the access times of every entry (about 40 us an entry), so a cache of
thousands of programs spends a tenth of a second per program written.

A cache holds programs that every process loads and runs, so whoever may write to it may
run code as its users. jtraj uses a cache directory (its own, and the native kernel's of
:mod:`jtraj._kkt_native`) only where it is owned by this user and neither group- nor
world-writable, and no folder above it (up to the root) is writable by another user
without the sticky bit; otherwise it logs why and runs without it (:func:`untrusted`).
The files jtraj itself writes there are read without running code
(:mod:`jtraj._tracecache` stores JSON and ``jax.export``'s serialised bytes, no pickle).

Logging. The library logs through the ``logging`` logger ``"jtraj"``; the line that a
solver will be compiled is at INFO (``logging.basicConfig()`` with
``logging.getLogger("jtraj").setLevel(logging.INFO)`` shows it). The CLI shows the
logger's INFO lines on stderr.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import stat
import threading
import weakref

logger = logging.getLogger("jtraj")

#: how long a first compilation of the solver usually takes (told in the log line)
TYPICAL_COMPILE = "usually tens of seconds to a minute or two on a 2-core machine"

#: the compilation cache's size cap where jtraj sets the cache up (JAX evicts the least
#: recently used programs beyond it); one serial3 solver's programs take about 5 MB
CACHE_MAX_BYTES = 2 << 30


def cache_max_bytes() -> int | None:
    """The size cap jtraj gives the cache it sets up: ``$JTRAJ_CACHE_MAX_GB`` GiB (0: no
    cap, no eviction and no locks), else :data:`CACHE_MAX_BYTES`."""
    text = os.environ.get("JTRAJ_CACHE_MAX_GB")
    if text is None or not text.strip():
        return CACHE_MAX_BYTES
    try:
        gb = float(text)
    except ValueError:
        raise ValueError(f"JTRAJ_CACHE_MAX_GB must be a number of GiB (0: no cap), got {text!r}") from None
    if not math.isfinite(gb) or gb < 0:
        raise ValueError(f"JTRAJ_CACHE_MAX_GB must be a finite number of GiB >= 0 (0: no cap), got {text!r}")
    return None if gb == 0 else int(gb * 2**30)


_lock = threading.Lock()
#: id -> weak reference of the problems, robots and weights found float64 (before_solve)
_checked: dict = {}
#: id -> (weak reference, (class, name, n)) of the robots solved (before_solve)
_robots: dict = {}
_state: dict = {"cache": False, "seen": set(), "refused": set()}


def cache_dir() -> str | None:
    """The compilation cache jtraj uses: ``$JTRAJ_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/jtraj/jax``, else ``~/.cache/jtraj/jax``; None where ``JTRAJ_CACHE=0``
    (or ``off``, ``false``, ``no``) switches it off."""
    if os.environ.get("JTRAJ_CACHE", "1").strip().lower() in ("0", "off", "false", "no"):
        return None
    path = os.environ.get("JTRAJ_CACHE_DIR")
    if path:
        return os.path.abspath(os.path.expanduser(path))
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(os.path.abspath(base), "jtraj", "jax")


def untrusted(path: str) -> str | None:
    """Why ``path`` (an existing directory) is not safe to load programs from, or None:
    it must be owned by this user and not writable by group or others, and every folder
    above it must be owned by this user or root and not writable by another user unless
    its sticky bit is set (``/tmp``: others cannot rename what is ours there)."""
    if not hasattr(os, "getuid"):  # not POSIX: no ownership to check
        return None
    uid = os.getuid()
    path = os.path.realpath(path)
    try:
        st = os.stat(path)
    except OSError as err:
        return f"cannot inspect it ({err.strerror or err})"
    if not stat.S_ISDIR(st.st_mode):
        return "it is not a directory"
    if st.st_uid != uid:
        return f"it is owned by another user (uid {st.st_uid})"
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return f"other users can write to it (mode {stat.S_IMODE(st.st_mode):o}; chmod go-w fixes it)"
    parent = os.path.dirname(path)
    while True:
        try:
            pst = os.stat(parent)
        except OSError as err:
            return f"cannot inspect {parent} ({err.strerror or err})"
        if pst.st_uid not in (uid, 0):
            return f"the folder {parent} above it is owned by another user (uid {pst.st_uid})"
        if pst.st_mode & (stat.S_IWGRP | stat.S_IWOTH) and not pst.st_mode & stat.S_ISVTX:
            return f"other users can write to the folder {parent} above it (mode {stat.S_IMODE(pst.st_mode):o})"
        up = os.path.dirname(parent)
        if up == parent:
            return None
        parent = up


def trusted_dir(path: str, what: str = "compilation cache") -> bool:
    """Create ``path`` (mode 0700) if missing and say whether it may be used
    (:func:`untrusted`); a refusal is logged once per path, as a warning."""
    try:
        os.makedirs(path, mode=0o700, exist_ok=True)
    except OSError as err:
        reason = f"cannot create it ({err.strerror or err})"
    else:
        reason = untrusted(path)
    if reason is None:
        return True
    with _lock:
        first = (what, path) not in _state["refused"]
        _state["refused"].add((what, path))
    if first:
        logger.warning("jtraj: not using %s as the %s: %s; running without it", path, what, reason)
    return False


def enable_cache(path: str | None = None, *, small: bool = True) -> str | None:
    """Point JAX's persistent compilation cache at ``path`` (default :func:`cache_dir`)
    where it may be trusted, and return it (None: left off). ``small``: keep every
    program, also those that compile in under a second (JAX's default keeps only
    those over one second; the solver's batch driver has about 30 small ones that a
    fresh process reads in a fraction of the time it spends compiling them)."""
    import jax

    path = cache_dir() if path is None else path
    if path is None or not trusted_dir(path):
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    if small:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    try:
        cap = cache_max_bytes()
    except ValueError as err:  # a setting of the cache never stops a program: the default cap
        cap = CACHE_MAX_BYTES
        with _lock:  # (one warning per process, as a refused folder's: keys (what, value))
            first = ("cache cap", str(err)) not in _state["refused"]
            _state["refused"].add(("cache cap", str(err)))
        if first:
            logger.warning("jtraj: %s; capping the cache at %d GiB", err, CACHE_MAX_BYTES >> 30)
    if cap is not None and jax.config.jax_compilation_cache_max_size == -1:
        try:
            import filelock  # noqa: F401  (JAX's size cap needs it)
        except ImportError:
            pass
        else:
            # a size cap makes JAX take a file lock around every read and write of an entry,
            # which it otherwise writes in place: a process could read another's half-written
            # entry (JAX then warns and compiles). Least recently used entries go first.
            jax.config.update("jax_compilation_cache_max_size", cap)
            remove_orphans(path)
    return path


def remove_orphans(path: str) -> list[str]:
    """Remove the entries of JAX's size-capped cache at ``path`` that have no access-time
    file (``<key>-cache`` without ``<key>-atime``): a process killed while writing one
    leaves it, possibly truncated, and JAX's eviction then fails on every later write.
    Done under JAX's own lock of the folder (skipped if another process holds it for
    more than a second). Returns the removed files' names."""
    import filelock

    removed = []
    try:
        with filelock.FileLock(os.path.join(path, ".lockfile"), timeout=1.0):
            names = set(os.listdir(path))
            for name in names:
                if name.endswith("-cache") and name[:-len("-cache")] + "-atime" not in names:
                    try:
                        os.remove(os.path.join(path, name))
                        removed.append(name)
                    except OSError:
                        pass
    except (filelock.Timeout, OSError):
        pass
    return removed


def ensure_cache() -> None:
    """Turn the compilation cache on once per process, unless the program configured
    one itself or ``JTRAJ_CACHE=0`` (called by ``import jtraj``, and again, a no-op then,
    at each solve)."""
    if _state["cache"]:
        return
    with _lock:
        if _state["cache"]:
            return
        _state["cache"] = True
    import jax

    if jax.config.jax_compilation_cache_dir:  # the program's own choice
        return
    enable_cache()


def setup_jax(x64: bool = True) -> None:
    """float64 and the persistent compilation cache (the CLI and dataset workers)."""
    import jax

    jax.config.update("jax_enable_x64", x64)
    with _lock:
        _state["cache"] = True
    if cache_dir() is not None:
        enable_cache()


class PrecisionError(ValueError):
    """jtraj was asked to solve in float32 (see the module's docstring)."""


_FIX = ("call jax.config.update('jax_enable_x64', True) at the start of the program, before building "
        "robots and problems")


#: floating dtypes jtraj refuses (what JAX makes with x64 off, and narrower)
_NARROW = None


def _narrow():
    global _NARROW
    if _NARROW is None:
        import jax.numpy as jnp
        import numpy as np

        _NARROW = frozenset(np.dtype(d) for d in (np.float32, np.float16, jnp.bfloat16, np.complex64))
    return _NARROW


def check_float64(**trees) -> None:
    """Raise :class:`PrecisionError` (a ``ValueError``) naming the argument where x64 is
    off or a floating array of ``trees`` (name -> pytree) is narrower than float64."""
    import jax

    if not jax.config.jax_enable_x64:
        raise PrecisionError(f"jtraj solves in float64 but jax_enable_x64 is off (JAX would make every array "
                             f"float32): {_FIX}")
    narrow = _narrow()
    for name, tree in trees.items():
        if not any(getattr(x, "dtype", None) in narrow for x in jax.tree.leaves(tree)):
            continue
        for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
            if getattr(leaf, "dtype", None) in narrow:
                where = name + jax.tree_util.keystr(path)
                raise PrecisionError(f"{where} is {leaf.dtype}, not float64 (built while jax_enable_x64 was off?): "
                                     f"jtraj solves in float64; {_FIX}")


def _marker(key: tuple) -> str | None:
    """The file that says a solver of ``key`` was compiled into the cache (None: no cache)."""
    import jax

    base = jax.config.jax_compilation_cache_dir
    if not base:
        return None
    from ._source import source_hash_cached

    text = json.dumps([repr(k) for k in key] + [source_hash_cached(), jax.__version__, jax.default_backend()])
    return os.path.join(base, "jtraj-seen", hashlib.sha256(text.encode()).hexdigest()[:32])


def announce(key: tuple, what) -> None:
    """Log once per process and ``key`` (robot type, sizes, options: what selects the
    solver's programs) that the solver is compiled now, or loaded from the cache where a
    process before this one compiled it there (a marker file, see :func:`compiled`).
    ``what``: the text naming it, or a function returning it."""
    if key in _state["seen"]:
        return
    with _lock:
        if key in _state["seen"]:
            return
        _state["seen"].add(key)
    what = what() if callable(what) else what
    marker = _marker(key)
    if marker is not None and os.path.exists(marker):
        logger.info("jtraj: loading the compiled solver for %s from the cache %s (first use in this process)",
                    what, os.path.dirname(os.path.dirname(marker)))
        return
    where = ("kept in the cache " + os.path.dirname(os.path.dirname(marker)) + " for later processes"
             if marker else "not cached: the compilation cache is off")
    logger.info("jtraj: compiling the solver for %s (first use; %s; %s)", what, TYPICAL_COMPILE, where)
    _state.setdefault("pending", set()).add(key)


def compiled(key: tuple) -> None:
    """Record that the solver of ``key`` finished compiling into the cache (a marker
    file for :func:`announce` in later processes)."""
    pending = _state.get("pending", set())
    if key not in pending:
        return
    pending.discard(key)
    marker = _marker(key)
    if marker is None:
        return
    try:
        os.makedirs(os.path.dirname(marker), mode=0o700, exist_ok=True)
        with open(marker, "w") as fh:
            fh.write("")
    except OSError:
        pass


def before_solve(robot, N: int, *, batch: bool, problem=None, weights=None, options=None,
                 transcription: str = "decoupled", efforts: str = "samples") -> tuple:
    """What :func:`jtraj.solve` and :func:`jtraj.solve_batch` do before solving: the
    float64 check (``ValueError``), the compilation cache on (once per process) and the
    log line of a first compilation. Returns the key to pass to :func:`compiled` after
    the solve."""
    import jax

    if not jax.config.jax_enable_x64:
        check_float64()  # raises
    for name, tree in (("problem", problem), ("robot", None if problem is not None else robot),
                       ("weights", weights)):
        # each (immutable) problem, robot and weights checked once (a warm solve takes
        # milliseconds; flattening a problem about 0.05 ms)
        if tree is None:
            continue
        ref = _checked.get(id(tree))
        if ref is None or ref() is not tree:
            check_float64(**{name: tree})
            if len(_checked) > 1024:
                _checked.clear()
            try:
                _checked[id(tree)] = weakref.ref(tree)
            except TypeError:  # (no weak references: checked every time)
                pass
    if not _state["cache"]:
        ensure_cache()
    entry = _robots.get(id(robot))
    if entry is None or entry[0]() is not robot:  # (a robot's attributes take microseconds each)
        entry = (weakref.ref(robot), (type(robot).__qualname__, getattr(robot, "name", type(robot).__name__),
                                      int(robot.n)))
        if len(_robots) > 1024:
            _robots.clear()
        _robots[id(robot)] = entry
    kind, name, n = entry[1]
    key = (kind, name, n, N, batch, transcription, getattr(options, "method", None), efforts)
    announce(key, lambda: (f"{name} (n = {n}), N = {N}" + (", batches" if batch else "")
                           + ("" if transcription == "decoupled" else f", {transcription}")))
    return key
