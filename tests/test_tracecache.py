"""The cross-process trace cache (jtraj._tracecache): a program exported once, later
deserialised instead of traced, must compute exactly what the traced program computes."""

import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jtraj
from jtraj import _tracecache


def _newton_sqrt(x, iters):
    # a bounded while loop, autodiff inside and a vmap: the constructs the solver uses
    def body(c):
        y, k = c
        f = lambda t: t * t - x  # noqa: E731
        return y - f(y) / jax.grad(f)(y), k + 1

    y, _ = jax.lax.while_loop(lambda c: c[1] < iters, body, (x, 0))
    return jax.vmap(lambda a: jnp.sin(a) * y)(jnp.arange(3.0)), {"k": iters}


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("JTRAJ_TRACE_CACHE", "1")
    old = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    yield tmp_path
    jax.config.update("jax_compilation_cache_dir", old)


def test_a_kept_program_is_loaded_without_tracing_and_computes_what_the_traced_one_does(cache_dir):
    traces = []

    def fn(x, iters):
        traces.append(1)
        return _newton_sqrt(x, iters)

    args = (jnp.asarray(2.0), jnp.asarray(7))
    first = _tracecache.cached("sqrt", fn, "test")(*args)
    assert len(traces) == 1
    files = os.listdir(cache_dir / _tracecache.FOLDER)
    assert len(files) == 1 and files[0].startswith("sqrt-") and files[0].endswith(".jaxexport")
    # a new wrapper (as in a new process) reads the file: no trace
    again = _tracecache.cached("sqrt", fn, "test")(*args)
    assert len(traces) == 1
    reference = jax.jit(_newton_sqrt)(*args)
    for a, b, c in zip(jax.tree.leaves(first), jax.tree.leaves(again), jax.tree.leaves(reference)):
        np.testing.assert_array_equal(a, c)
        np.testing.assert_array_equal(b, c)
    # another shape is another program; another static key too
    _tracecache.cached("sqrt", fn, "test")(jnp.asarray(3.0), jnp.asarray(3))
    assert len(traces) == 1  # same shapes, dtypes and weak types: the same program
    _tracecache.cached("sqrt", fn, "test")(jnp.ones((), jnp.float32), jnp.asarray(3))
    assert len(traces) == 2
    _tracecache.cached("sqrt", fn, "other")(*args)  # (JAX's in-process cache has its trace)
    assert len(os.listdir(cache_dir / _tracecache.FOLDER)) == 3


class _Scaled(eqx.Module):  # a jtraj-like module: a static field, an array and a float leaf
    kind: str = eqx.field(static=True)
    a: jax.Array
    factor: float


def test_pytrees_with_static_parts_and_plain_values(cache_dir, monkeypatch):
    # this test module's class counts as jtraj's own here (a user's class is foreign)
    monkeypatch.setattr(_tracecache, "_OWN_MODULES", ("jtraj", _Scaled.__module__))
    traces = []

    def fn(m, b):
        traces.append(1)
        y = m.a * m.factor + b["x"]
        return {"y": y, "kind": m.kind, "m": _Scaled(m.kind, y, m.factor)}

    args = (_Scaled("s", jnp.arange(3.0), 2.0), {"x": jnp.ones(3)})
    out = _tracecache.cached("mod", fn, "test")(*args)
    again = _tracecache.cached("mod", fn, "test")(*args)  # from the file
    assert len(traces) == 1
    for o in (out, again):
        np.testing.assert_array_equal(o["y"], [1.0, 3.0, 5.0])
        assert o["kind"] == "s" and isinstance(o["m"], _Scaled) and o["m"].factor == 2.0
        np.testing.assert_array_equal(o["m"].a, o["y"])
    # a plain value is part of the program: another value, another program
    other = _tracecache.cached("mod", fn, "test")(_Scaled("s", jnp.arange(3.0), 3.0), {"x": jnp.ones(3)})
    np.testing.assert_array_equal(other["y"], [1.0, 4.0, 7.0])
    assert len(os.listdir(_tracecache.directory())) == 2
    # a class from outside jtraj: no program kept, traced as eqx.filter_jit would
    monkeypatch.setattr(_tracecache, "_OWN_MODULES", ("jtraj",))
    out = _tracecache.cached("mod", fn, "test")(_Scaled("s", jnp.arange(3.0), 4.0), {"x": jnp.ones(3)})
    np.testing.assert_array_equal(out["y"], [1.0, 5.0, 9.0])
    assert len(os.listdir(_tracecache.directory())) == 2


def test_no_key_without_a_stable_text_or_for_foreign_pytree_nodes(cache_dir):
    args = (jnp.ones(3),)
    assert _tracecache.key("f", "static", args, None) is not None
    assert _tracecache.key("f", repr(lambda x: x), args, None) is None  # "<function ... at 0x...>"

    @jax.tree_util.register_pytree_node_class
    class Foreign:  # a user's pytree node: its code is not in jtraj's source hash
        def __init__(self, a):
            self.a = a

        def tree_flatten(self):
            return (self.a,), None

        @classmethod
        def tree_unflatten(cls, aux, children):
            return cls(*children)

    Foreign.__module__ = "users_module"
    assert _tracecache.key("f", "static", (Foreign(jnp.ones(3)),), None) is None
    # the key follows the source, the shapes and the compiler options
    k = _tracecache.key("f", "static", args, None)
    assert k != _tracecache.key("f", "static", (jnp.ones(4),), None)
    assert k != _tracecache.key("f", "static", args, {"xla_cpu_use_fusion_emitters": False})


def test_off_without_a_compilation_cache_or_when_asked(tmp_path, monkeypatch):
    old = jax.config.jax_compilation_cache_dir
    try:
        jax.config.update("jax_compilation_cache_dir", None)
        assert _tracecache.directory() is None
        assert _tracecache.program("f", lambda x: x, (jnp.ones(2),), "s") is None
        jax.config.update("jax_compilation_cache_dir", str(tmp_path))
        monkeypatch.setenv("JTRAJ_TRACE_CACHE", "0")
        assert _tracecache.directory() is None
    finally:
        jax.config.update("jax_compilation_cache_dir", old)


@pytest.mark.slow
def test_solve_batch_is_the_same_with_and_without_kept_programs(monkeypatch):
    """Datasets must not depend on whether a worker traced or loaded its programs."""
    from jtraj import _testing

    robot = jtraj.robots.get("serial3")
    q0 = np.array([[0.2, -0.3, 0.4], [-0.5, 0.6, 0.1]])
    q1 = q0 + np.array([[0.4, 0.1, -0.5], [-0.3, -0.6, 0.5]])
    w = jtraj.Weights(time=1.0, energy=0.1)
    assert _tracecache.directory() is not None  # the tests run with a compilation cache
    kept = jtraj.solve_batch(robot, q0, q1, N=20, weights=w)
    # every program of the batch is kept (one whose output cannot be kept is traced again
    # by every worker process: a few seconds per chunk)
    names = {f.split("-")[0] for f in os.listdir(_tracecache.directory())
             if f.endswith(".jaxexport")}
    assert {"_guess_batch_jit", "_prepare_batch_jit", "_ip_init_batch_jit", "pool", "_finish_batch_jit"} <= names
    monkeypatch.setenv("JTRAJ_TRACE_CACHE", "0")
    _testing.lane_programs.cache_clear()
    try:
        traced = jtraj.solve_batch(robot, q0, q1, N=20, weights=w)
    finally:
        _testing.lane_programs.cache_clear()
    assert np.all(np.asarray(kept.converged))
    for name in ("v", "h", "cost", "iterations", "status"):
        np.testing.assert_array_equal(np.asarray(getattr(kept, name)), np.asarray(getattr(traced, name)), err_msg=name)


@pytest.mark.parametrize("name", jtraj.transcription.TRANSCRIPTIONS)
def test_a_transcription_in_a_skeleton_is_kept_and_rebuilt(name):
    """The solver's NLP carries its transcription object: a skeleton holding it must be
    kept (else the program is exported again by every process) and come back equal."""
    import json

    tr = jtraj.transcription.Transcription(name)
    skeleton = {"nlp": (tr, _tracecache._Slot())}
    back = _tracecache.decode(json.loads(json.dumps(_tracecache.encode(skeleton))))
    assert back["nlp"][0] == tr and type(back["nlp"][0]) is type(tr)
    assert isinstance(back["nlp"][1], _tracecache._Slot)


def test_a_skeleton_keeps_no_object_that_holds_data():
    tr = jtraj.transcription.Transcription("decoupled")
    tr.extra = 1  # a jtraj class, but this instance holds data its constructor does not give
    with pytest.raises(TypeError, match="cannot keep"):
        _tracecache.encode(tr)


def test_without_flatbuffers_the_program_is_traced(cache_dir, monkeypatch):
    """jax.export serialises with the flatbuffers package (a dependency); without it the
    program is traced as usual, not an error."""
    def no_flatbuffers(self, *a, **k):
        raise ImportError("Please install 'flatbuffers'")

    monkeypatch.setattr(jax.export.Exported, "serialize", no_flatbuffers)
    assert _tracecache.program("f", lambda x: 2 * x, (jnp.ones(2),), "s") is None
    np.testing.assert_array_equal(_tracecache.cached("f", lambda x: 2 * x, "s")(jnp.ones(2)), [2.0, 2.0])


def test_with_the_cache_off_a_program_runs_from_memory_as_eqx_filter_jit_would(monkeypatch):
    """Where the cache is off (or has no key), ``cached(..., lean=True)`` (the solver's
    entry points) runs an in-memory program of the array leaves
    (:func:`_tracecache.in_memory`): traced once per signature, the non-array leaves of
    arguments and output passed through, the same numbers as ``eqx.filter_jit``. Without
    ``lean``, or inside another trace, the fallback runs instead."""
    monkeypatch.setenv("JTRAJ_TRACE_CACHE", "0")
    traces = []

    def fn(x, iters, label):
        traces.append(label)
        y, aux = _newton_sqrt(x, iters)
        return y, {**aux, "label": label}

    wrapped = _tracecache.cached("sqrt", fn, "test", lean=True)
    args = (jnp.asarray(2.0), jnp.asarray(7), "a")
    out = wrapped(*args)
    again = wrapped(jnp.asarray(5.0), jnp.asarray(7), "a")
    assert traces == ["a"]  # one trace for the signature
    assert out[1]["label"] == "a" and isinstance(out[1]["label"], str)
    ref = eqx.filter_jit(fn)(*args)
    for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(ref)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(again[0], jax.jit(_newton_sqrt)(jnp.asarray(5.0), 7)[0])
    wrapped(jnp.asarray(2.0), jnp.asarray(7), "b")  # another static value: another program
    assert traces[-1] == "b"
    calls = []
    with_fallback = _tracecache.cached("sqrt", fn, "test", fallback=lambda *a: calls.append(a) or "fallback")
    assert with_fallback(*args) == "fallback" and len(calls) == 1
    # inside another trace: the default fallback (eqx.filter_jit), which traces into it
    inner = jax.jit(lambda x: wrapped(x, jnp.asarray(7), "a")[0])(jnp.asarray(2.0))
    np.testing.assert_array_equal(inner, out[0])


def test_a_quick_first_program_runs_its_quick_compilation_once_then_the_optimised_one(cache_dir, monkeypatch):
    # the tests' XLA_FLAGS fix an optimisation level, which switches the tiers off
    monkeypatch.setattr(_tracecache, "_level_in_xla_flags", lambda: False)
    if not _tracecache.quick_first_enabled({}):
        pytest.skip("this XLA does not take xla_backend_optimization_level per program")
    args = (jnp.asarray(2.0), jnp.asarray(7))
    reference = jax.jit(_newton_sqrt)(*args)
    wrapper = _tracecache.cached("sqrt", _newton_sqrt, "tiers", quick_first=True)
    outs = [wrapper(*args)]
    (run,) = [r for r in _quick_runs(wrapper)]
    assert run.quick.compiled._cache_size() == 1 and run.full.compiled._cache_size() == 0
    outs += [wrapper(*args), wrapper(*args)]
    assert run.quick.compiled._cache_size() == 1 and run.full.compiled._cache_size() == 1
    for out in outs:
        for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(reference)):
            np.testing.assert_allclose(a, b, rtol=1e-14)
    markers = [f for f in os.listdir(cache_dir / _tracecache.FOLDER) if f.endswith(".optimised")]
    assert len(markers) == 1
    # a later process (a new wrapper) finds the marker and starts with the optimised program
    again = _tracecache.cached("sqrt", _newton_sqrt, "tiers", quick_first=True)
    again(*args)
    assert _quick_runs(again) == []
    # kept quick (the CLI's one-shot commands): the quick program for every call
    monkeypatch.setenv("JTRAJ_QUICK_FIRST", "keep")
    def markers():
        return sorted(f for f in os.listdir(cache_dir / _tracecache.FOLDER) if f.endswith(".optimised"))

    before = markers()
    kept = _tracecache.cached("sqrt", _newton_sqrt, "tiers-kept", quick_first=True)
    for _ in range(3):
        kept(*args)
    assert markers() == before  # never compiled optimised
    monkeypatch.setenv("JTRAJ_QUICK_FIRST", "1")
    for _ in range(2):
        _tracecache.cached("sqrt", _newton_sqrt, "tiers-first", quick_first=True)(*args)
    assert len(markers()) == len(before)  # (a new wrapper each time: first calls only)
    tiers = _tracecache.cached("sqrt", _newton_sqrt, "tiers-first", quick_first=True)
    tiers(*args)
    tiers(*args)
    assert len(markers()) == len(before) + 1
    # switched off: one program
    monkeypatch.setenv("JTRAJ_QUICK_FIRST", "0")
    assert not _tracecache.quick_first_enabled({})
    monkeypatch.delenv("JTRAJ_QUICK_FIRST")
    assert not _tracecache.quick_first_enabled({"xla_backend_optimization_level": 3})


def _quick_runs(wrapper):
    """The tiered programs a cached() wrapper holds (through its closure)."""
    loaded = next(c.cell_contents for c in wrapper.__closure__ if isinstance(c.cell_contents, dict))
    found = []
    for run in loaded.values():
        if hasattr(run, "quick"):
            found.append(run)
            continue
        compiled = next((c.cell_contents for c in run.__closure__ if callable(c.cell_contents)
                         and hasattr(c.cell_contents, "quick")), None)
        if compiled is not None:
            found.append(compiled)
    return found


def _kernel_or_xla(x):
    # a stand-in for the solver: its trace takes the native kernel where
    # jtraj._kkt_native.active says so (x 2 here), else the XLA version (x 3)
    from jtraj import _kkt_native

    return x * (2.0 if _kkt_native.active(jnp.float64, 3, 6) else 3.0)


def test_while_the_kernel_is_built_a_first_call_runs_the_xla_version(cache_dir, monkeypatch):
    """A machine's first solve does not wait for the native kernel's compiler: the quick
    first call runs the XLA version (kept as .xla), the second exports the native one."""
    from jtraj import _kkt_native

    monkeypatch.setattr(_tracecache, "_level_in_xla_flags", lambda: False)
    if not _tracecache.quick_first_enabled({}):
        pytest.skip("this XLA does not take xla_backend_optimization_level per program")
    monkeypatch.setattr(_kkt_native, "_usable", lambda n: True)  # the kernel "built or being built"
    monkeypatch.setattr(_kkt_native, "available", lambda n: True)
    monkeypatch.setattr(_kkt_native, "building", lambda: True)
    x = jnp.asarray(1.5)

    def files():
        return sorted(f.split("-")[0] + f[f.index("."):] for f in os.listdir(cache_dir / _tracecache.FOLDER))

    wrapper = _tracecache.cached("kern", _kernel_or_xla, "v1", quick_first=True)
    assert float(wrapper(x)) == 4.5  # the XLA version, quickly compiled
    assert files() == ["kern.xla.jaxexport"]
    assert float(wrapper(x)) == 3.0  # the second call: the native version, exported and kept
    assert files() == ["kern.jaxexport", "kern.jaxexport.optimised", "kern.xla.jaxexport"]
    # a later process: the native version at once (marker), kernel built or not
    monkeypatch.setattr(_kkt_native, "building", lambda: False)
    assert float(_tracecache.cached("kern", _kernel_or_xla, "v1", quick_first=True)(x)) == 3.0
    # a later process that finds only the XLA version starts from it without tracing
    for f in os.listdir(cache_dir / _tracecache.FOLDER):
        if not f.endswith(".xla.jaxexport"):
            os.remove(cache_dir / _tracecache.FOLDER / f)

    def no_trace(*args):
        raise AssertionError("traced again")

    monkeypatch.setattr(_tracecache, "_flat", no_trace)
    assert float(_tracecache.cached("kern", _kernel_or_xla, "v1", quick_first=True)(x)) == 4.5
