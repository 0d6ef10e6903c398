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

The kernel is compiled on first use with the machine's C++ compiler (``$CXX``, else
``g++`` or ``c++``: ``-O3 -march=native``, about 12 s, once per machine;
``JTRAJ_NATIVE_MARCH`` sets another ``-march``) into
``$JTRAJ_NATIVE_DIR`` (default ``$XDG_CACHE_HOME/jtraj/native`` or ``~/.cache/jtraj/native``;
used only where no other user can write to it, see :func:`jtraj._setup.untrusted`), under a name that hashes the
source, the flags, the compiler's and jaxlib's versions and the CPU's model and flags,
so that a cache shared between machines never hands one a build for another. It is
used where all of these hold: the backend is the CPU, the arrays are float64, the robot
has 1 to 7 joints, and the build succeeded; elsewhere (no compiler, an accelerator,
float32, more joints, or ``JTRAJ_NATIVE=0``) the solver runs :func:`jtraj.lq.kkt_directions` in XLA, with the
same iterates up to rounding. :func:`status` says which and why. Programs calling the
kernel stay in JAX's persistent compilation cache (an FFI call is named, not a Python
callback); the kept traces (:mod:`jtraj._tracecache`) include :func:`identity` in
their key.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import warnings

import jax
import jax.numpy as jnp

#: the FFI target's name
TARGET = "jtraj_kkt"
_SOURCE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "_native", "kkt.cc")


def _flags() -> tuple[str, ...]:
    # JTRAJ_NATIVE_MARCH: another -march (valgrind, for one, knows no AVX-512: x86-64-v3)
    return ("-O3", f"-march={os.environ.get('JTRAJ_NATIVE_MARCH', 'native')}", "-std=c++17", "-shared", "-fPIC")

_state: dict = {}


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


def _build() -> str:
    """Compile (unless already built) and register the kernel; returns its identity."""
    import jaxlib

    cxx = _compiler()
    if cxx is None:
        raise RuntimeError("no C++ compiler found ($CXX, g++ or c++)")
    version = subprocess.run([cxx, "--version"], capture_output=True, text=True, check=True).stdout
    with open(_SOURCE, "rb") as fh:
        source = fh.read()
    h = hashlib.sha256()
    for part in (source, repr(_flags()).encode(), version.encode(), jaxlib.__version__.encode(), _cpu_text().encode()):
        h.update(part)
        h.update(b"\0")
    ident = h.hexdigest()[:16]
    folder = _directory()
    from ._setup import trusted_dir, untrusted

    if not trusted_dir(folder, "native kernel's folder"):  # a library loaded from it runs as this user
        raise RuntimeError(f"{folder} is not safe to load a library from ({untrusted(folder)})")
    path = os.path.join(folder, f"jtraj_kkt-{ident}.so")
    if not os.path.exists(path):
        fd, tmp = tempfile.mkstemp(dir=folder, suffix=".so.tmp")
        os.close(fd)
        try:
            proc = subprocess.run([cxx, *_flags(), "-I", jax.ffi.include_dir(), _SOURCE, "-o", tmp],
                                  capture_output=True, text=True)
            if proc.returncode != 0:
                raise RuntimeError(f"{os.path.basename(cxx)} failed on {_SOURCE}:\n{proc.stderr[-2000:]}")
            os.chmod(tmp, 0o755)
            os.replace(tmp, path)  # atomic: concurrent builders (dataset workers) each write whole files
        finally:
            if os.path.exists(tmp):
                os.remove(tmp)
    lib = ctypes.CDLL(path)
    jax.ffi.register_ffi_target(TARGET, jax.ffi.pycapsule(lib.JtrajKkt), platform="cpu")
    _state["lib"] = lib  # kept alive with the process
    return ident


def identity() -> str | None:
    """The kernel's identity (a hash of its build) where it is available, else None.
    Builds and registers it on the first call (``JTRAJ_NATIVE=0``: never)."""
    if "identity" not in _state:
        ident, why = None, "off (JTRAJ_NATIVE=0)"
        if os.environ.get("JTRAJ_NATIVE", "1") != "0":
            try:
                ident, why = _build(), "built"
            except (RuntimeError, OSError, subprocess.SubprocessError, AttributeError) as err:
                why = f"unavailable: {err}"
                if _compiler() is not None:  # a compiler that failed is worth a word; none is documented
                    warnings.warn(f"jtraj: the native KKT kernel could not be built ({err}); the solver "
                                  "runs the XLA version (slower, same results up to rounding)", stacklevel=2)
        _state["identity"], _state["why"] = ident, why
    return _state["identity"]


def status() -> str:
    """A line saying whether the kernel is in use in this process, and why not."""
    ident = identity()
    if ident is None:
        return f"native KKT kernel: {_state['why']}"
    return f"native KKT kernel: in use on the CPU in float64 (build {ident}, {_directory()})"


def active(dtype, n: int, r: int) -> bool:
    """Whether :func:`kkt_directions` is used for arrays of ``dtype``, ``n`` joints and
    ``r`` terminal rows (decided at trace time; the kernel is compiled for 1 to 7 joints
    and the 2n rows of a goal state)."""
    return (jnp.dtype(dtype) == jnp.float64 and 1 <= n <= 7 and r == 2 * n and jax.default_backend() == "cpu"
            and identity() is not None)


def kkt_directions(model, shifts, terminal, ladder: bool = False):
    """:func:`jtraj.lq.kkt_directions` (all shifts at once) by the native kernel: the same
    arguments and results. Vmaps (a batch is one call), does not differentiate.

    ``ladder``: the first shift for every problem, the others only where it is not
    positive definite (elsewhere their slots are zeros and not positive definite, as in
    :func:`jtraj.solver.ipm._ladder_directions_xla` for one problem): the least shifted positive
    definite direction is the same, at about half the work (on the benchmark family
    shift 0 is positive definite in about 60 % of the iterations)."""
    N, nx, m = model.B.shape[-3:]
    r = terminal.shape[-1]
    L = shifts.shape[-1]
    f64 = jnp.float64
    out = (jax.ShapeDtypeStruct((N * m, 1 + r, L), f64), jax.ShapeDtypeStruct((N + 1, nx, 1 + r, L), f64),
           jax.ShapeDtypeStruct((L,), jnp.bool_))
    call = jax.ffi.ffi_call(TARGET, out, vmap_method="broadcast_all")
    return call(model.A, model.B, model.Q, model.S, model.R, model.cx, model.cu, model.PN, shifts, terminal,
                ladder=bool(ladder))
