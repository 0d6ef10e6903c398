"""Traced programs kept across processes (:mod:`jax.export`).

JAX's persistent compilation cache keeps XLA's work between processes, but not JAX's own:
every new process traces and lowers the solver again before the cache can even be
looked up. For a batch that was about 12 s on a 2-core machine (each dataset worker and
each ``jtraj solve`` pays it), against a few seconds of actual solving.

Where the persistent compilation cache is on (``jax_compilation_cache_dir`` set: the CLI,
``jtraj dataset``'s workers, the tests), :func:`program` keeps a program's traced and
lowered form (a serialised :class:`jax.export.Exported` of the program on its arguments'
array leaves, with a JSON skeleton of its output's structure) next to it, keyed by
everything its trace depends on: jtraj's source (a hash of its ``.py`` files), the JAX
and jaxlib versions, the backend, the native KKT kernel's build or its absence
(:mod:`jtraj._kkt_native`), the JAX settings that change a trace (x64, precision,
promotion), the caller's static key, the arguments' tree structure and plain values, and
their arrays' shapes, dtypes and weak types. A later process deserialises it instead of tracing (a
fraction of a second). The program is always run from its deserialised form, also right
after it was exported, so a result does not depend on whether the file existed; the
tests check that it equals the traced program's bit for bit.

The caller's static key must name everything else the traced function closes over.
It refuses (returns None, the caller then traces as usual) when that key shows a value
that has no stable text (``<... at 0x...>``, e.g. a function) or a pytree node class
defined outside jtraj (a user's robot: its code is not in the source hash).
``JTRAJ_TRACE_CACHE=0`` turns the cache off.

Reading a kept file runs no code: the skeleton is JSON naming only plain values,
containers and classes defined in jtraj (rebuilt field by field, as ``jax.tree.unflatten``
does, without calling their constructors), and the program is ``jax.export``'s
serialised form (a flatbuffer). No pickle: a file that someone else could write would
otherwise run their code on loading. An output holding anything else is not kept (the
program is traced as usual). The folder is used only where :func:`jtraj._setup.untrusted`
finds no other user able to write to it.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import importlib
import json
import os
import re
import tempfile
from typing import Any, Callable

import equinox as eqx
import jax
import numpy as np

from . import _kkt_native
from ._source import source_hash_cached

#: the folder, inside the compilation cache directory, holding the exported programs
FOLDER = "jtraj-traces"




def directory() -> str | None:
    """Where exported programs are kept, or None when the cache is off."""
    if os.environ.get("JTRAJ_TRACE_CACHE", "1") == "0":
        return None
    base = jax.config.jax_compilation_cache_dir
    if not base:
        return None
    from ._setup import trusted_dir

    folder = os.path.join(base, FOLDER)
    return folder if trusted_dir(folder, "folder of kept traces") else None


#: the modules whose pytree node classes the source hash covers
_OWN_MODULES = ("jtraj",)


def _foreign_node(tree) -> bool:
    """Whether a pytree node of ``tree``'s structure is a class defined outside jtraj
    (JAX's and Python's own containers aside)."""
    def walk(treedef):
        data = treedef.node_data()
        if data is not None:
            kind = data[0]
            module = getattr(kind, "__module__", "") or ""
            if kind not in (tuple, list, dict) and not module.startswith(_OWN_MODULES + ("builtins", "collections")):
                return True
        return any(walk(c) for c in treedef.children())
    return walk(jax.tree.structure(tree))


_NATIVE_CALLS = [jax.export.DisabledSafetyCheck.custom_call(_kkt_native.target(n)) for n in _kkt_native.JOINTS]

#: JAX settings that change what a trace produces
_FLAGS = ("jax_enable_x64", "jax_default_matmul_precision", "jax_numpy_dtype_promotion",
          "jax_numpy_rank_promotion", "jax_default_prng_impl", "jax_enable_checks", "jax_debug_nans")


def _sig(x):
    """What a trace depends on in one leaf: an array's shape, dtype and weak type, or a
    plain value itself."""
    if eqx.is_array(x):  # (the leaves program() passes as arrays)
        return (np.shape(x), np.dtype(x.dtype), bool(getattr(x, "weak_type", False)))
    return ("value", x)


class _Slot:
    """Marks an array's place in a kept program's output skeleton."""


#: the first bytes of a kept program's file (then the skeleton's JSON length, 8 bytes
#: big-endian, the JSON and jax.export's bytes)
MAGIC = b"jtraj-trace 2\n"


def _class_name(cls) -> str:
    name = f"{cls.__module__}:{cls.__qualname__}"
    if not cls.__module__.startswith(_OWN_MODULES) or "<" in cls.__qualname__:
        raise TypeError(f"{name} is not a class of jtraj")
    return name


def _resolve(name: str):
    """The class ``module:qualname``, of jtraj only (a skeleton names nothing else)."""
    module, _, qualname = name.partition(":")
    if not module.startswith(_OWN_MODULES):
        raise ValueError(f"a kept trace names the class {name!r}, outside jtraj")
    obj = importlib.import_module(module)
    for part in qualname.split("."):
        obj = getattr(obj, part)
    if not isinstance(obj, type):
        raise ValueError(f"{name!r} is not a class")
    return obj


def encode(x):
    """A JSON-able form of a skeleton (see :func:`decode`); TypeError where it holds
    something else than plain values, NumPy scalars, tuples, lists, dicts, and
    dataclasses (equinox modules), named tuples, enums and instances holding no data (the
    transcriptions) of classes defined in jtraj."""
    if isinstance(x, _Slot):
        return {"$": "slot"}
    if x is None or type(x) in (bool, int, str):
        return {"$": "v", "v": x}
    if type(x) is float:
        return {"$": "f", "v": repr(x)}
    if isinstance(x, enum.Enum):
        return {"$": "enum", "cls": _class_name(type(x)), "v": encode(x.value)}
    if isinstance(x, np.generic) and x.dtype.kind in "biuf":
        return {"$": "np", "dtype": x.dtype.str, "v": repr(x.item())}
    if type(x) in (tuple, list):
        return {"$": type(x).__name__, "v": [encode(v) for v in x]}
    if type(x) is dict:
        return {"$": "dict", "k": [encode(k) for k in x], "v": [encode(v) for v in x.values()]}
    if isinstance(x, tuple) and hasattr(type(x), "_fields"):
        return {"$": "nt", "cls": _class_name(type(x)), "v": [encode(v) for v in x]}
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {"$": "dc", "cls": _class_name(type(x)),
                "f": {f.name: encode(getattr(x, f.name)) for f in dataclasses.fields(x)}}
    if getattr(x, "__dict__", None) == {} and not hasattr(type(x), "__slots__"):
        # an instance that holds no data (a transcription): rebuilt by its constructor
        return {"$": "obj", "cls": _class_name(type(x))}
    raise TypeError(f"cannot keep a {type(x).__name__} in a trace's skeleton")


def decode(d):
    """The skeleton :func:`encode` described (ValueError on anything else)."""
    if not isinstance(d, dict):
        raise ValueError("malformed skeleton")
    tag = d.get("$")
    if tag == "slot":
        return _Slot()
    if tag == "v":
        if d["v"] is not None and type(d["v"]) not in (bool, int, str):
            raise ValueError("malformed skeleton value")
        return d["v"]
    if tag == "f":
        return float(d["v"])
    if tag == "np":
        dtype = np.dtype(d["dtype"])
        if dtype.kind not in "biuf":
            raise ValueError("malformed skeleton scalar")
        return dtype.type(float(d["v"]) if dtype.kind == "f" else int(d["v"]) if dtype.kind in "iu"
                          else d["v"] == "True")
    if tag in ("tuple", "list"):
        items = [decode(v) for v in d["v"]]
        return tuple(items) if tag == "tuple" else items
    if tag == "dict":
        return {decode(k): decode(v) for k, v in zip(d["k"], d["v"])}
    cls = _resolve(d["cls"])
    if tag == "enum" and issubclass(cls, enum.Enum):
        return cls(decode(d["v"]))
    if tag == "nt" and issubclass(cls, tuple) and hasattr(cls, "_fields"):
        return cls(*[decode(v) for v in d["v"]])
    if tag == "obj" and not dataclasses.is_dataclass(cls):
        obj = cls()
        if getattr(obj, "__dict__", None) != {}:
            raise ValueError(f"{d['cls']} holds data: it cannot be kept as a bare instance")
        return obj
    if tag == "dc" and dataclasses.is_dataclass(cls):
        names = {f.name for f in dataclasses.fields(cls)}
        if set(d["f"]) != names:
            raise ValueError(f"the kept fields of {d['cls']} are not its fields")
        obj = object.__new__(cls)  # as jax.tree.unflatten rebuilds an equinox module: no constructor
        for name, value in d["f"].items():
            object.__setattr__(obj, name, decode(value))
        return obj
    raise ValueError(f"malformed skeleton entry {tag!r}")


def _read(path: str):
    """(skeleton, jax.export bytes, the native kernels' joint counts it calls) of a kept
    file; ValueError where it is not one."""
    with open(path, "rb") as fh:
        data = fh.read()
    if not data.startswith(MAGIC) or len(data) < len(MAGIC) + 8:
        raise ValueError("not a kept trace of this format")
    at = len(MAGIC)
    size = int.from_bytes(data[at:at + 8], "big")
    text = data[at + 8:at + 8 + size]
    if len(text) != size:
        raise ValueError("truncated")
    head = json.loads(text)
    natives = head["natives"]
    if not (isinstance(natives, list) and all(isinstance(n, int) and n in _kkt_native.JOINTS for n in natives)):
        raise ValueError("bad native kernel list")
    return decode(head["skeleton"]), data[at + 8 + size:], natives


def _payload(skeleton, blob: bytes, natives: list[int]) -> bytes:
    text = json.dumps({"skeleton": encode(skeleton), "natives": natives}, separators=(",", ":")).encode()
    return MAGIC + len(text).to_bytes(8, "big") + text + bytes(blob)


def key(name: str, static: str, args: tuple, compiler_options: dict | None) -> str | None:
    """The cache key of program ``name`` for these arguments, or None where no stable key
    exists (see the module's docstring)."""
    if _foreign_node(args):
        return None
    import jaxlib

    leaves, tree = jax.tree.flatten(args)
    text = "\n".join([
        name, static, repr(tree), repr(tuple(map(_sig, leaves))),
        repr(sorted((compiler_options or {}).items())), source_hash_cached(), jax.__version__,
        jaxlib.__version__, jax.default_backend(), repr([getattr(jax.config, f) for f in _FLAGS]),
        f"native KKT kernel {_kkt_native.identity()}",
    ])
    if re.search(r" at 0x[0-9a-fA-F]+", text):
        return None
    return f"{name}-{hashlib.sha256(text.encode()).hexdigest()[:32]}"


#: XLA CPU options of a quick compilation (see :func:`tiered`)
QUICK = {"xla_backend_optimization_level": 0}


def _level_in_xla_flags() -> bool:
    return "xla_backend_optimization_level" in os.environ.get("XLA_FLAGS", "")


def quick_first_mode() -> str:
    """``JTRAJ_QUICK_FIRST``: ``"first"`` (default) quick programs for a process's first
    call and optimised ones from its second, ``"keep"`` quick programs for every call
    (the CLI's one-shot ``solve`` and ``query``: a process that solves one problem),
    ``"off"`` (``0``, ``off``, ``false``, ``no``) optimised programs at once."""
    value = os.environ.get("JTRAJ_QUICK_FIRST", "1").strip().lower()
    if value in ("0", "off", "false", "no"):
        return "off"
    return "keep" if value == "keep" else "first"


def quick_first_enabled(compiler_options: dict | None) -> bool:
    """Whether :func:`tiered` compiles a program quickly first: not where
    :func:`quick_first_mode` is ``"off"``, where the process or the caller already chose
    an LLVM optimisation level (``XLA_FLAGS``, ``compiler_options``), or where this XLA
    refuses the option."""
    if quick_first_mode() == "off":
        return False
    if _level_in_xla_flags() or "xla_backend_optimization_level" in (compiler_options or {}):
        return False
    from ._compile import supported_options

    return supported_options(QUICK) == QUICK


def tiered(make: Callable[[dict], Callable], compiler_options: dict | None, marker: str | None,
           what: str, make_quick: Callable[[dict], Callable] | None = None) -> Callable:
    """A program that compiles quickly for its first call and optimised from its second.

    ``make(options)`` returns the program (a ``jax.jit`` callable) compiled with XLA
    ``options``. The first call runs it compiled at LLVM optimisation level 0
    (:data:`QUICK`): for the solver's single-problem programs that compiles in about
    0.4x the time and runs about 2.4x slower, with the same iterations and statuses
    and results equal to rounding (``benchmarks/bench_opt_level.py``). The second call
    compiles the optimised program and every later call runs it. ``marker``, a file
    written once the optimised program is compiled (and so in the persistent cache),
    makes later processes start with the optimised program at once. Without
    :func:`quick_first_enabled`, simply ``make(compiler_options)``; in the ``"keep"`` mode
    (:func:`quick_first_mode`) the quick program for every call unless the marker is there.
    ``make_quick``: the quick program, where it is another program computing the same
    (the solver's XLA version while the native kernel is built); ``make`` is then called
    only when the second call needs it."""
    options = dict(compiler_options or {})
    if not quick_first_enabled(options) or (marker is not None and os.path.exists(marker)):
        return make(options)
    quick = (make if make_quick is None else make_quick)({**options, **QUICK})
    if quick_first_mode() == "keep":
        return quick
    calls = [0]
    full = [] if make_quick is not None else [make(options)]

    def call(*arrays):
        calls[0] += 1
        if calls[0] == 1:
            return quick(*arrays)
        if calls[0] == 2:
            from ._setup import logger

            logger.info("jtraj: compiling the optimised %s (the first call ran a quickly compiled one)", what)
            if not full:
                full.append(make(options))
            out = full[0](*arrays)
            if marker is not None:
                try:
                    with open(marker, "w"):
                        pass
                except OSError:
                    pass
            return out
        return full[0](*arrays)

    call.quick = quick  # (for the tests)
    if full:
        call.full = full[0]
    return call


#: what a kept program's file may fail with when read (then it is exported again)
_UNREADABLE = (OSError, ValueError, KeyError, ImportError, TypeError, AttributeError, RecursionError)


def _load(path: str):
    """``(exported, skeleton)`` of the kept program at ``path``, its native kernels
    registered (a missing or unreadable file raises one of :data:`_UNREADABLE`)."""
    skeleton, blob, natives = _read(path)
    for n in natives:  # the native kernels it calls, registered before it runs
        _kkt_native.available(n)
    return jax.export.deserialize(bytearray(blob)), skeleton


def _export(path: str, flat: Callable, kept: dict, arrays: list, native: bool):
    """Export ``flat`` on ``arrays`` and keep it at ``path``: ``(exported, skeleton)``, or
    None where it cannot be kept. ``native``: with the native KKT kernel where it is
    built or being built (the trace does not wait for the build, the compilation will:
    the compiler runs while JAX traces; where the build fails, the XLA version), else
    the XLA version."""
    if native:
        with _kkt_native.deferred():
            exported = jax.export.export(jax.jit(flat), disabled_checks=_NATIVE_CALLS)(*arrays)
    else:
        with _kkt_native.without():
            exported = jax.export.export(jax.jit(flat), disabled_checks=_NATIVE_CALLS)(*arrays)
    # the native kernel's FFI call is registered by every process whose file names it
    natives = sorted({int(n) for n in re.findall(rf"{_kkt_native.TARGET}([1-7])", exported.mlir_module())})
    if not all([_kkt_native.available(n) for n in natives]):  # a build failed: the XLA version
        exported = jax.export.export(jax.jit(flat), disabled_checks=_NATIVE_CALLS)(*arrays)
        natives = []
    try:
        blob = exported.serialize()
    except ImportError:  # jax.export's serialisation needs the flatbuffers package
        return None
    skeleton = kept["skeleton"]
    try:
        payload = _payload(skeleton, blob, natives)
    except (TypeError, ValueError):
        return None  # an output that cannot be kept: trace as usual
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path), suffix=".tmp")
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)  # atomic: a concurrent reader sees no file or the whole file
    except OSError:
        pass  # an unwritable cache: run it from memory
    return jax.export.deserialize(blob), skeleton


def program(name: str, fn: Callable, args: tuple, static: str,
            compiler_options: dict | None = None, quick_first: bool = False) -> Callable | None:
    """``fn(*args)`` as a callable of the arguments' leaves (``jax.tree.leaves(args)``
    of arguments with the same signature) returning ``fn``'s output, compiled from the program
    kept on disk, exported now if missing; None when the cache is off or no stable key
    exists (then trace ``fn`` as usual). ``static`` names what ``fn`` closes over (see
    the module's docstring); the arguments' non-array leaves are part of the key.

    ``quick_first``: compile it quickly for its first call (:func:`tiered`). Where the
    native KKT kernel is still being built when the program is exported (a machine's
    first solve), the first call runs the program's XLA version (kept beside it, with
    ``.xla`` in its name) instead of waiting for the compiler; the second call exports
    the native version. A later process without the native version starts from the
    kept XLA version likewise."""
    folder = directory()
    leaves, tree = jax.tree.flatten(args)
    is_array = [eqx.is_array(x) for x in leaves]
    fixed = [None if a else x for x, a in zip(leaves, is_array)]
    k = None if folder is None else key(name, f"{static}\n{fixed!r}", args, compiler_options)
    if k is None:
        return None
    path = os.path.join(folder, k + ".jaxexport")
    arrays = [x for x, a in zip(leaves, is_array) if a]
    marker = path + ".optimised"

    def native_version():
        try:
            return _load(path)
        except _UNREADABLE:  # missing (or written by another version or format): export it now
            kept = {}
            return _export(path, _flat(fn, tree, is_array, fixed, kept), kept, arrays, native=True)

    def runner(made):
        exported, skeleton = made
        return lambda options: _runner(jax.jit(exported.call, compiler_options=options), is_array,
                                       lambda: skeleton)

    quick_xla = None
    if quick_first and quick_first_enabled(compiler_options) and not os.path.exists(marker) \
            and not os.path.exists(path):
        xla_path = os.path.join(folder, k + ".xla.jaxexport")
        if os.path.exists(xla_path) or _kkt_native.building():
            try:
                quick_xla = _load(xla_path)
            except _UNREADABLE:
                kept = {}
                quick_xla = _export(xla_path, _flat(fn, tree, is_array, fixed, kept), kept, arrays, native=False)
    if quick_xla is not None:
        def full(options):  # the native version, exported when the second call needs it
            made = native_version()
            return runner(quick_xla if made is None else made)(options)

        return tiered(full, compiler_options, marker, f"program {name}", make_quick=runner(quick_xla))
    made = native_version()
    if made is None:
        return None
    if quick_first:
        return tiered(runner(made), compiler_options, marker, f"program {name}")
    return runner(made)(compiler_options)


def _flat(fn, tree, is_array, fixed, kept):
    """``fn`` as a function of its arguments' array leaves (the other leaves ``fixed``)
    returning its output's array leaves; ``kept["skeleton"]``: the output with a
    :class:`_Slot` for each array, set when it is traced."""
    def flat(*arrays):
        it = iter(arrays)
        out = fn(*jax.tree.unflatten(tree, [next(it) if a else x for a, x in zip(is_array, fixed)]))
        out_leaves, out_tree = jax.tree.flatten(out)
        kept["skeleton"] = jax.tree.unflatten(out_tree, [_Slot() if eqx.is_array(x) else x for x in out_leaves])
        return [x for x in out_leaves if eqx.is_array(x)]

    return flat


def _runner(compiled, is_array, skeleton):
    """A callable of the arguments' leaves (as ``jax.tree.leaves(args)`` gives them)
    running ``compiled`` on their arrays and returning the output rebuilt from
    ``skeleton()`` (read at the first call, after ``compiled`` has traced)."""
    layout = []

    def run(leaves):
        arrays = compiled(*[x for x, a in zip(leaves, is_array) if a])
        if not layout:
            out_leaves, out_tree = jax.tree.flatten(skeleton())
            layout.append((out_tree, out_leaves, [isinstance(x, _Slot) for x in out_leaves]))
        out_tree, out_leaves, slots = layout[0]
        it = iter(arrays)
        return jax.tree.unflatten(out_tree, [next(it) if s else x for s, x in zip(slots, out_leaves)])

    run.compiled = compiled  # (for the tests)
    return run


def in_memory(fn: Callable, args: tuple, compiler_options: dict | None = None) -> Callable:
    """``fn(*args)`` as :func:`program` gives it, traced and compiled in this process
    only (a plain ``jax.jit`` of the array leaves, the other leaves fixed): for the
    solver's entry points where the cache is off, one flattening and JAX's own dispatch
    per call instead of ``eqx.filter_jit``'s partitioning of the arguments and the
    output (one warm ``jtraj.solve`` of serial3 at N = 20, pinned to one core: about
    0.2 of 3-5 ms)."""
    leaves, tree = jax.tree.flatten(args)
    is_array = [eqx.is_array(x) for x in leaves]
    fixed = [None if a else x for x, a in zip(leaves, is_array)]
    kept = {}
    compiled = jax.jit(_flat(fn, tree, is_array, fixed, kept), compiler_options=compiler_options)
    return _runner(compiled, is_array, lambda: kept["skeleton"])


def cached(name: str, fn: Callable, static: str, compiler_options: dict | None = None,
           fallback: Callable | None = None, lean: bool = False, quick_first: bool = False) -> Callable:
    """``fn`` as a callable that takes each argument signature's program from
    :func:`program` (after the first call: one flattening and one dictionary lookup), or
    where the cache is off or has no key calls ``fallback`` (default
    ``eqx.filter_jit(fn)``: the same treatment of non-array leaves, as static values);
    with ``lean``, :func:`in_memory`'s program there instead. Called inside another
    trace it always calls ``fallback``. ``quick_first``: a kept program compiles quickly
    for its first call (:func:`tiered`)."""
    if fallback is None:
        fallback = eqx.filter_jit(fn, compiler_options=compiler_options)
    loaded: dict[Any, Callable | None] = {}

    def call(*args):
        leaves, tree = jax.tree.flatten(args)
        # (called inside another trace: that trace's own jit, not a kept program)
        traced = any(isinstance(x, jax.core.Tracer) for x in leaves)
        sig = (tree, tuple(map(_sig, leaves)), traced)
        if sig not in loaded:
            run = None if traced else program(name, fn, args, static, compiler_options, quick_first)
            if run is None and lean and not traced:
                run = in_memory(fn, args, compiler_options)
            loaded[sig] = run
        run = loaded[sig]
        if run is None:
            return fallback(*args)
        return run(leaves)

    return call
