"""The interior-point method's KKT solve as a native CPU kernel (an XLA FFI call).

:func:`jtraj.lq.kkt_directions` for the shift ladder (:func:`jtraj.solver.ipm._ladder_directions`)
is the largest piece of an interior-point iteration: 45 % of its instructions on the
canonical problem (serial3, N = 20, 8 lanes; ``benchmarks/iteration_cost.py --method
ip``). XLA compiles its per-stage 4x4 to 7x7 operations into many small loops, each
scalar over a few elements. ``_native/kkt.cc`` computes the same recursion (the same
operations in the same order, up to the summation order within a product: results
agree to about 1e-12 relative) with the lanes (problem x shift) innermost in blocks of
16 (8 or 4 for a small call), the dimensions fixed at compile time (1 to 7 joints), so that each operation is
a few vector instructions over the lanes. The solver calls it in its ``ladder`` mode: the
unshifted system for every problem first, the shifted ones only where that is not
positive definite (about 40 % of the iterations on the benchmark family).

On serial3 at N = 20 an interior-point iteration runs about 1.4x faster with it than with
XLA's Riccati recursion, with the same iterations (``benchmarks/iteration_cost.py
--method ip`` measures the pieces).

The kernel is compiled with the machine's C++ compiler (``$CXX``, else ``g++`` or
``c++``: ``-O3 -march=native``; ``JTRAJ_NATIVE_MARCH`` sets another ``-march``,
``JTRAJ_NATIVE_OPT`` another level: at ``2`` a build takes about a third of the time
and the kernel runs about 1.6x slower), one library per joint count
(``-DJTRAJ_KKT_N=n``: a third of the compile time of all seven), once per machine, into
``$JTRAJ_NATIVE_DIR`` (default ``$XDG_CACHE_HOME/jtraj/native`` or
``~/.cache/jtraj/native``; used only where no other user can write to it, see
:func:`jtraj._setup.untrusted`), under a name that hashes the source, the flags, the
compiler's and jaxlib's versions and the CPU's model and flags, so that a cache shared
between machines never hands one a build for another. :func:`prefetch` starts a build
in a background thread when a :class:`~jtraj.Problem` is made or a solve begins, so that
the compiler runs while JAX traces the solver. A trace exported into the kept traces
(:mod:`jtraj._tracecache`) runs inside :func:`deferred`: it calls the kernel without
waiting for its build, and the export waits only before the program is compiled (XLA
needs the FFI target registered to compile it); where the build then fails, the
program is exported again with the XLA version. Other traces wait where they reach the
KKT solve.

The kernel is used where all of these hold: the backend is the CPU, the arrays are
float64, the robot has 1 to 7 joints, and the build succeeded; elsewhere (no compiler,
an accelerator, float32, more joints, or ``JTRAJ_NATIVE=0``) the solver runs
:func:`jtraj.lq.kkt_directions` in XLA, with the same iterates up to rounding.
:func:`status` says which and why. Programs calling the kernel stay in JAX's persistent
compilation cache (an FFI call is named, not a Python callback); the kept traces
(:mod:`jtraj._tracecache`) include :func:`identity` in their key and name the
kernels they call, which a process registers before running one.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import ctypes
import hashlib
import os
import platform
import shlex
import shutil
import subprocess
import tempfile
import threading
import warnings

import jax
import jax.numpy as jnp

#: the FFI targets' names: TARGET + the joint count (1 to 7)
TARGET = "jtraj_kkt_n"
JOINTS = range(1, 8)
_SOURCE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "_native", "kkt.cc")


def target(n: int) -> str:
    """The FFI target of the kernel for ``n`` joints."""
    return f"{TARGET}{n}"


def _flags(n: int) -> tuple[str, ...]:
    # JTRAJ_NATIVE_MARCH: another -march (valgrind, for one, knows no AVX-512: x86-64-v3);
    # JTRAJ_NATIVE_OPT: another optimisation level (RuntimeError, caught by _family, if bad)
    level = os.environ.get("JTRAJ_NATIVE_OPT", "3").strip()
    if level not in ("0", "1", "2", "3"):
        raise RuntimeError(f"JTRAJ_NATIVE_OPT must be 0, 1, 2 or 3 (the compiler's -O level), got {level!r}")
    return (f"-O{level}", f"-march={os.environ.get('JTRAJ_NATIVE_MARCH', 'native')}", "-std=c++17", "-shared", "-fPIC",
            f"-DJTRAJ_KKT_N={n}")


def _compiler() -> str | None:
    found = (shutil.which(c) for c in (os.environ.get("CXX"), "g++", "c++") if c)
    return next((f for f in found if f), None)


def _cpu_text() -> str:
    """The CPU's model and feature flags (what -march=native compiles for)."""
    try:
        with open("/proc/cpuinfo") as fh:
            lines = [ln for ln in fh if ln.startswith(("model name", "flags", "Features", "CPU part"))]
        return "".join(sorted(set(lines)))
    except OSError:
        return platform.processor() or platform.machine()


def _directory() -> str:
    base = os.environ.get("JTRAJ_NATIVE_DIR")
    if not base:
        cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        base = os.path.join(cache, "jtraj", "native")
    return base


_state: dict = {"libs": {}, "futures": {}, "failed": {}, "compiling": set()}
#: per thread: ``on`` inside :func:`deferred`, ``off`` inside :func:`without`
_deferring = threading.local()
_lock = threading.Lock()


def _family() -> tuple[str | None, str]:
    """The builds' common identity (a hash of source, flags, compiler, jaxlib and CPU)
    and why there is none (off, no compiler, an unsafe folder)."""
    if "family" not in _state:
        ident, why = None, "off (JTRAJ_NATIVE=0)"
        if os.environ.get("JTRAJ_NATIVE", "1") != "0":
            try:
                ident, why = _hash(), "available"
            except (RuntimeError, OSError, subprocess.SubprocessError) as err:
                why = f"unavailable: {err}"
                if _compiler() is not None:  # a compiler that cannot be used is worth a word; none is documented
                    warnings.warn(f"jtraj: the native KKT kernel cannot be used ({err}); the solver runs the XLA "
                                  "version (slower, same results up to rounding)", stacklevel=3)
        _state["family"] = (ident, why)
    return _state["family"]


def _hash() -> str:
    import jaxlib

    cxx = _compiler()
    if cxx is None:
        raise RuntimeError("no C++ compiler found ($CXX, g++ or c++)")
    version = subprocess.run([cxx, "--version"], capture_output=True, text=True, check=True).stdout
    folder = _directory()
    from ._setup import trusted_dir, untrusted

    if not trusted_dir(folder, "native kernel's folder"):  # a library loaded from it runs as this user
        raise RuntimeError(f"{folder} is not safe to load a library from ({untrusted(folder)})")
    with open(_SOURCE, "rb") as fh:
        source = fh.read()
    h = hashlib.sha256()
    for part in (source, repr(_flags(0)).encode(), version.encode(), jaxlib.__version__.encode(),
                 _cpu_text().encode()):
        h.update(part)
        h.update(b"\0")
    return h.hexdigest()[:16]


def _library(n: int) -> str:
    """The path of the library for ``n`` joints (the kernel can be used: see :func:`_family`)."""
    return os.path.join(_directory(), f"jtraj_kkt-{_family()[0]}-n{n}.so")


def building() -> bool:
    """Whether the compiler is building a kernel for this process now (started by
    :func:`prefetch`; loading a library built before does not count)."""
    return bool(_state["compiling"])


def _build(n: int) -> None:
    """Compile (unless already built) and register the kernel for ``n`` joints."""
    ident, why = _family()
    if ident is None:
        raise RuntimeError(why)
    path = _library(n)
    folder = os.path.dirname(path)
    if not os.path.exists(path):
        fd, tmp = tempfile.mkstemp(dir=folder, suffix=".so.tmp")
        os.close(fd)
        # the compiler, the chmod and the atomic rename run detached (setsid), so that
        # a build outlives a process that ends first (a one-shot solve that ran the XLA
        # version meanwhile): the next process finds the library; concurrent builders
        # (dataset workers) each rename a whole file
        # (at a lower priority: where cores are short, the solve the user waits for goes first)
        nice = ("nice", "-n", "10") if shutil.which("nice") else ()
        command = " ".join(shlex.quote(x) for x in (*nice, _compiler(), *_flags(n), "-I", jax.ffi.include_dir(),
                                                      _SOURCE, "-o", tmp))
        q = {k: shlex.quote(v) for k, v in (("tmp", tmp), ("log", tmp + ".log"), ("path", path))}
        script = (f"{command} >/dev/null 2>{q['log']} && chmod 755 {q['tmp']} && mv -f {q['tmp']} {q['path']}; "
                  f"status=$?; rm -f {q['tmp']}; [ $status -eq 0 ] && rm -f {q['log']}; exit $status")
        proc = subprocess.run(["/bin/sh", "-c", script], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, start_new_session=True)
        if proc.returncode != 0 or not os.path.exists(path):
            try:
                with open(tmp + ".log") as fh:
                    errors = fh.read()[-2000:]
                os.remove(tmp + ".log")
            except OSError:
                errors = ""
            raise RuntimeError(f"{os.path.basename(_compiler())} failed on {_SOURCE}:\n{errors}")
    lib = ctypes.CDLL(path)
    jax.ffi.register_ffi_target(target(n), jax.ffi.pycapsule(lib.JtrajKkt), platform="cpu")
    _state["libs"][n] = lib  # kept alive with the process


def prefetch(n: int) -> None:
    """Start building the kernel for ``n`` joints in a background thread (if it is not
    built or being built, and the kernel applies: 1 to 7 joints, a CPU backend)."""
    n = int(n)
    if n not in JOINTS or jax.default_backend() != "cpu" or _family()[0] is None:
        return
    with _lock:
        if n in _state["libs"] or n in _state["futures"] or n in _state["failed"]:
            return
        fut = concurrent.futures.Future()
        _state["futures"][n] = fut

    if not os.path.exists(_library(n)):
        _state["compiling"].add(n)  # (set before the thread starts: building() sees it at once)

    def work():
        try:
            _build(n)
            fut.set_result(True)
        except BaseException as err:  # reported by available(), in the caller's thread
            fut.set_exception(err)
        finally:
            _state["compiling"].discard(n)

    threading.Thread(target=work, name=f"jtraj-kkt-build-{n}", daemon=True).start()


@contextlib.contextmanager
def _flag(name: str):
    before = getattr(_deferring, name, False)
    setattr(_deferring, name, True)
    try:
        yield
    finally:
        setattr(_deferring, name, before)


def deferred():
    """Within this context :func:`active` does not wait for a build in progress: it
    answers whether the kernel is built or being built (and has not failed). The caller
    must call :func:`available` for the kernels its program names before compiling it,
    and trace again where one is not available."""
    return _flag("on")


def without():
    """Within this context :func:`active` is False: a trace uses the XLA version."""
    return _flag("off")


def _kernel(n: int):
    """True where the kernel for ``n`` joints is built, False where it cannot be (or is
    not for this backend), else its build's future (started by :func:`prefetch` if need
    be)."""
    if n in _state["libs"]:
        return True
    if n not in JOINTS or n in _state["failed"] or _family()[0] is None:
        return False
    prefetch(n)
    return _state["futures"].get(n, False)


def _pending_or_built(n: int) -> bool:
    fut = _kernel(int(n))
    if isinstance(fut, bool):
        return fut
    return available(n) if fut.done() else True


def _usable(n: int) -> bool:
    """:func:`available`, or inside :func:`deferred` whether it is built or being built."""
    return _pending_or_built(n) if getattr(_deferring, "on", False) else available(n)


def available(n: int) -> bool:
    """Whether the kernel for ``n`` joints is built and registered: builds it (or waits
    for :func:`prefetch`'s build) on the first call."""
    n = int(n)
    fut = _kernel(n)
    if isinstance(fut, bool):
        return fut
    try:
        fut.result()
        return True
    except (RuntimeError, OSError, subprocess.SubprocessError, AttributeError) as err:
        _state["failed"][n] = f"unavailable: {err}"
        warnings.warn(f"jtraj: the native KKT kernel could not be built ({err}); the solver runs the XLA "
                      "version (slower, same results up to rounding)", stacklevel=2)
        return False


def identity() -> str | None:
    """The kernel builds' identity (a hash of source, flags, compiler, jaxlib and CPU)
    where the kernel can be used, else None (``JTRAJ_NATIVE=0``, no compiler, an unsafe
    folder). Builds nothing."""
    return _family()[0]


def status(n: int | None = None) -> str:
    """A line saying whether the kernel (for ``n`` joints) is in use in this process, and why not."""
    ident, why = _family()
    if ident is None:
        return f"native KKT kernel: {why}"
    if n is not None:
        if not available(n):
            return f"native KKT kernel for {n} joints: {_state['failed'].get(n, 'not for this joint count')}"
        return f"native KKT kernel: in use on the CPU in float64 ({n} joints, build {ident}, {_directory()})"
    built = sorted(_state["libs"])
    return (f"native KKT kernel: available on the CPU in float64 (build {ident}, {_directory()}; "
            f"built in this process for joint counts {built or 'none yet'})")


def active(dtype, n: int, r: int) -> bool:
    """Whether :func:`kkt_directions` is used for arrays of ``dtype``, ``n`` joints and
    ``r`` terminal rows (decided at trace time; the kernel is compiled for 1 to 7 joints
    and the 2n rows of a goal state)."""
    if not (jnp.dtype(dtype) == jnp.float64 and 1 <= n <= 7 and r == 2 * n and jax.default_backend() == "cpu"):
        return False
    return not getattr(_deferring, "off", False) and _usable(n)


def kkt_directions(model, shifts, terminal, ladder: bool = False):
    """:func:`jtraj.lq.kkt_directions` (all shifts at once) by the native kernel: the same
    arguments and results. Vmaps (a batch is one call), does not differentiate.

    ``ladder``: the first shift for every problem, the others only where it is not
    positive definite (elsewhere their slots are zeros and not positive definite, as in
    :func:`jtraj.solver.ipm._ladder_directions_xla` for one problem): the least shifted positive
    definite direction is the same, at about half the work (on the benchmark family
    shift 0 is positive definite in about 60 % of the iterations)."""
    N, nx, m = model.B.shape[-3:]
    if not _usable(m - 1):
        raise RuntimeError(status(m - 1))
    r = terminal.shape[-1]
    L = shifts.shape[-1]
    f64 = jnp.float64
    out = (jax.ShapeDtypeStruct((N * m, 1 + r, L), f64), jax.ShapeDtypeStruct((N + 1, nx, 1 + r, L), f64),
           jax.ShapeDtypeStruct((L,), jnp.bool_))
    call = jax.ffi.ffi_call(target(m - 1), out, vmap_method="broadcast_all")
    return call(model.A, model.B, model.Q, model.S, model.R, model.cx, model.cu, model.PN, shifts, terminal,
                ladder=bool(ladder))
