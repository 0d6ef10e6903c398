"""JAX set-up of the library (jtraj._setup): the compilation cache turned on by import
jtraj in a trusted directory only, its switches, processes sharing it, the float64
policy, the log line of a first compilation, and the lazy subpackages."""

import logging
import os
import stat
import subprocess
import sys
import textwrap

import jax
import pytest

from jtraj import _setup, _tracecache

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _run(code: str, env: dict | None = None, timeout: int = 300) -> subprocess.CompletedProcess:
    """``code`` in a fresh Python process (this checkout's jtraj, no conftest set-up)."""
    e = {k: v for k, v in os.environ.items() if k not in ("JTRAJ_CACHE_DIR", "JTRAJ_CACHE", "JAX_ENABLE_X64",
                                                          "JAX_COMPILATION_CACHE_DIR", "JTRAJ_CACHE_MAX_GB")}
    e["PYTHONPATH"] = ROOT + os.pathsep + e.get("PYTHONPATH", "")
    if "JTRAJ_CACHE_DIR" not in (env or {}):
        e["JTRAJ_CACHE"] = "0"  # never the user's ~/.cache/jtraj
    e.update(env or {})
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, env=e,
                          timeout=timeout, cwd=ROOT)


def test_cache_dir_default_and_switches(monkeypatch, tmp_path):
    monkeypatch.delenv("JTRAJ_CACHE_DIR", raising=False)
    monkeypatch.delenv("JTRAJ_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert _setup.cache_dir() == str(tmp_path / "xdg" / "jtraj" / "jax")
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert _setup.cache_dir() == str(tmp_path / "home" / ".cache" / "jtraj" / "jax")
    monkeypatch.setenv("JTRAJ_CACHE_DIR", str(tmp_path / "mine"))
    assert _setup.cache_dir() == str(tmp_path / "mine")
    for off in ("0", "off", "false", "no"):
        monkeypatch.setenv("JTRAJ_CACHE", off)
        assert _setup.cache_dir() is None


@pytest.mark.skipif(not hasattr(os, "getuid"), reason="POSIX ownership")
def test_a_directory_others_can_write_to_is_refused(tmp_path, caplog):
    own = tmp_path / "own"
    own.mkdir(mode=0o700)
    assert _setup.untrusted(str(own)) is None
    for mode, needle in ((0o777, "other users can write to it"), (0o770, "other users can write to it")):
        d = tmp_path / f"d{mode:o}"
        d.mkdir()
        os.chmod(d, mode)
        assert needle in _setup.untrusted(str(d))
        before = jax.config.jax_compilation_cache_dir
        with caplog.at_level(logging.WARNING, logger="jtraj"):
            assert _setup.enable_cache(str(d)) is None
        assert jax.config.jax_compilation_cache_dir == before  # left as it was
        assert any(str(d) in r.getMessage() and "running without it" in r.getMessage() for r in caplog.records)
    # a folder above it that others may write to (without the sticky bit): they could swap ours
    open_parent = tmp_path / "open"
    open_parent.mkdir()
    os.chmod(open_parent, 0o777)
    (open_parent / "cache").mkdir(mode=0o700)
    assert "above it" in _setup.untrusted(str(open_parent / "cache"))
    os.chmod(open_parent, 0o777 | stat.S_ISVTX)  # as /tmp: others cannot rename what is ours
    assert _setup.untrusted(str(open_parent / "cache")) is None
    # created where missing, private
    new = tmp_path / "new" / "cache"
    assert _setup.trusted_dir(str(new))
    assert stat.S_IMODE(os.stat(new).st_mode) & 0o077 == 0


def test_cache_cap_from_the_environment(monkeypatch):
    monkeypatch.delenv("JTRAJ_CACHE_MAX_GB", raising=False)
    assert _setup.cache_max_bytes() == _setup.CACHE_MAX_BYTES == 2 * 2**30
    for text, expected in (("0.5", 2**29), ("8", 8 * 2**30), ("0", None), (" ", _setup.CACHE_MAX_BYTES)):
        monkeypatch.setenv("JTRAJ_CACHE_MAX_GB", text)
        assert _setup.cache_max_bytes() == expected, text
    for text in ("two", "-1", "nan", "inf"):
        monkeypatch.setenv("JTRAJ_CACHE_MAX_GB", text)
        with pytest.raises(ValueError, match="JTRAJ_CACHE_MAX_GB must be"):
            _setup.cache_max_bytes()


def test_import_turns_the_cache_on_unless_switched_off_or_set(tmp_path):
    code = """
        import jax
        assert jax.config.jax_compilation_cache_dir is None
        import jtraj
        print(jax.config.jax_compilation_cache_dir)
        print(jax.config.jax_compilation_cache_max_size)
        print(jax.config.jax_enable_x64)  # left as it was
    """
    own = tmp_path / "c"
    r = _run(code, {"JTRAJ_CACHE_DIR": str(own)})
    assert r.returncode == 0, r.stderr
    # capped: JAX then locks each entry's read and write (it writes them in place)
    assert r.stdout.split() == [str(own), str(_setup.CACHE_MAX_BYTES), "False"] and own.is_dir()
    # JTRAJ_CACHE_MAX_GB=0: no cap (-1: JAX neither evicts nor locks)
    r = _run(code, {"JTRAJ_CACHE_DIR": str(own), "JTRAJ_CACHE_MAX_GB": "0"})
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == [str(own), "-1", "False"]
    # a bad value: a warning naming it, and the default cap
    r = _run(code, {"JTRAJ_CACHE_DIR": str(own), "JTRAJ_CACHE_MAX_GB": "two"})
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == [str(own), str(_setup.CACHE_MAX_BYTES), "False"]
    assert "JTRAJ_CACHE_MAX_GB must be a number of GiB" in r.stderr
    r = _run(code, {"JTRAJ_CACHE_DIR": str(own), "JTRAJ_CACHE": "0"})
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[0] == "None"
    # a directory the program set itself is kept
    r = _run("""
        import jax
        jax.config.update("jax_compilation_cache_dir", %r)
        import jtraj
        print(jax.config.jax_compilation_cache_dir)
    """ % str(tmp_path / "theirs"), {"JTRAJ_CACHE_DIR": str(own)})
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(tmp_path / "theirs")
    # a world-writable one: a warning on stderr (logging's last resort), no cache, no failure
    bad = tmp_path / "bad"
    bad.mkdir()
    os.chmod(bad, 0o777)
    r = _run(code, {"JTRAJ_CACHE_DIR": str(bad)})
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[0] == "None" and "other users can write to it" in r.stderr


_SHARED = """
    import os, sys
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    from jtraj import _setup, _tracecache
    assert _setup.enable_cache() is not None
    traced = []
    def fn(x):
        traced.append(1)
        return {"y": jnp.cumsum(jnp.sin(x) * 3.0), "n": 7}
    out = _tracecache.cached("shared", fn, "test_setup")(jnp.arange(5.0))
    np.testing.assert_allclose(out["y"], np.cumsum(np.sin(np.arange(5.0)) * 3.0), rtol=1e-15)
    assert out["n"] == 7
    print(len(traced))
"""


def test_processes_share_one_cache(tmp_path):
    cache = tmp_path / "shared"
    env = {"JTRAJ_CACHE_DIR": str(cache), "JTRAJ_TRACE_CACHE": "1"}
    e = {k: v for k, v in os.environ.items() if k not in ("JTRAJ_CACHE_DIR", "JTRAJ_CACHE")}
    e["PYTHONPATH"] = ROOT + os.pathsep + e.get("PYTHONPATH", "")
    e.update(env)
    # two at once, writing the same entries
    procs = [subprocess.Popen([sys.executable, "-c", textwrap.dedent(_SHARED)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=e, cwd=ROOT) for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err
    kept = os.listdir(cache / "jtraj-traces")
    assert len(kept) == 1 and not any(f.endswith(".tmp") for f in kept)
    with open(cache / "jtraj-traces" / kept[0], "rb") as fh:
        assert fh.read(len(_tracecache.MAGIC)) == _tracecache.MAGIC  # JSON + jax.export bytes, no pickle
    # a third process loads the kept program: no trace
    r = _run(_SHARED, env)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "0"


def test_a_skeleton_cannot_name_a_class_outside_jtraj():
    from jtraj import _tracecache

    assert _tracecache.decode(_tracecache.encode({"a": (1, 2.5, None, "x")})) == {"a": (1, 2.5, None, "x")}
    with pytest.raises(ValueError, match="outside jtraj"):
        _tracecache.decode({"$": "dc", "cls": "os:_wrap_close", "f": {}})
    with pytest.raises(TypeError):
        _tracecache.encode(object())


def test_no_silent_float32(tmp_path):
    # x64 off: refused before anything is traced, the message says how to switch it on
    r = _run("""
        import jtraj
        robot = jtraj.robots.get("serial3")
        p = jtraj.Problem(robot, [0.0, 0.5, 0.5], [0.2, 0.4, 0.5], N=10)
        try:
            jtraj.solve(p)
        except ValueError as err:
            print("ERR", err)
        try:
            jtraj.solve_batch(robot, [[0.0, 0.5, 0.5]], [[0.2, 0.4, 0.5]], N=10)
        except ValueError as err:
            print("ERR", err)
    """, {"JTRAJ_CACHE": "0"})
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("ERR")]
    assert len(lines) == 2
    for ln in lines:
        assert "jax_enable_x64 is off" in ln and "jax.config.update('jax_enable_x64', True)" in ln
    # a problem built while x64 was off holds float32 arrays: refused, naming the array
    r = _run("""
        import jax, jtraj
        robot = jtraj.robots.get("serial3")
        p = jtraj.Problem(robot, [0.0, 0.5, 0.5], [0.2, 0.4, 0.5], N=10)
        jax.config.update("jax_enable_x64", True)
        try:
            jtraj.solve(p)
        except ValueError as err:
            print("ERR", err)
    """, {"JTRAJ_CACHE": "0"})
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("ERR problem.") and "is float32, not float64" in r.stdout
    assert "before building robots and problems" in r.stdout


def test_a_first_compilation_is_logged_once_then_loaded_from_the_cache(tmp_path, monkeypatch, caplog):
    state = {"cache": True, "seen": set(), "refused": set()}
    monkeypatch.setattr(_setup, "_state", state)
    old = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    try:
        key = ("Serial", "serial3", 3, 20, False, "decoupled", "ip", "samples")
        with caplog.at_level(logging.INFO, logger="jtraj"):
            _setup.announce(key, "serial3 (n = 3), N = 20")
            _setup.announce(key, "serial3 (n = 3), N = 20")  # once per process
            _setup.compiled(key)
        msgs = [r.getMessage() for r in caplog.records if r.name == "jtraj"]
        assert len(msgs) == 1 and msgs[0].startswith("jtraj: compiling the solver for serial3 (n = 3), N = 20")
        assert str(tmp_path) in msgs[0]
        caplog.clear()
        state["seen"].clear()  # as a new process
        with caplog.at_level(logging.INFO, logger="jtraj"):
            _setup.announce(key, "serial3 (n = 3), N = 20")
            _setup.announce(key[:3] + (40,) + key[4:], "serial3 (n = 3), N = 40")  # another N compiles
        msgs = [r.getMessage() for r in caplog.records if r.name == "jtraj"]
        assert msgs[0].startswith("jtraj: loading the compiled solver for serial3 (n = 3), N = 20 from the cache")
        assert msgs[1].startswith("jtraj: compiling the solver for serial3 (n = 3), N = 40")
    finally:
        jax.config.update("jax_compilation_cache_dir", old)


@pytest.mark.parametrize("attr", ["dataset.load", "anfis.load", "online.Planner", "gradcheck", "plotting",
                                  "resample.resample"])
def test_subpackages_resolve_on_first_access(attr):
    r = _run(f"""
        import sys, jtraj
        name = {attr!r}.split(".")[0]
        assert "jtraj." + name not in sys.modules, name  # not imported by import jtraj
        assert name in dir(jtraj) and name in jtraj.__all__
        jtraj.{attr}
        assert "jtraj." + name in sys.modules
    """)
    assert r.returncode == 0, r.stderr


def test_import_jtraj_loads_no_subpackage_and_is_quick():
    r = _run("""
        import sys, time
        t0 = time.perf_counter()
        import jax
        t1 = time.perf_counter()
        import jtraj
        t2 = time.perf_counter()
        heavy = [m for m in ("jtraj.dataset", "jtraj.anfis", "h5py", "matplotlib", "tqdm") if m in sys.modules]
        print(heavy, t1 - t0, t2 - t1)
    """)
    assert r.returncode == 0, r.stderr
    heavy, _, jtraj_s = r.stdout.rsplit(" ", 2)
    assert heavy == "[]", heavy
    assert float(jtraj_s) < 10.0  # loose: a loaded 2-core machine; about 0.5-1 s after jax


def test_orphan_cache_entries_are_removed(tmp_path):
    """An entry of JAX's size-capped cache without its access-time file (a process killed
    while writing it) breaks JAX's eviction for every later write: enabling the cache
    removes such entries, and only those."""
    (tmp_path / "jit_a-1-cache").write_bytes(b"partial")
    (tmp_path / "jit_b-2-cache").write_bytes(b"whole")
    (tmp_path / "jit_b-2-atime").write_bytes((1).to_bytes(8, "little"))
    (tmp_path / "jit_c-3-atime").write_bytes((1).to_bytes(8, "little"))  # an atime alone is harmless
    assert _setup.remove_orphans(str(tmp_path)) == ["jit_a-1-cache"]
    left = sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith("."))
    assert left == ["jit_b-2-atime", "jit_b-2-cache", "jit_c-3-atime"]
