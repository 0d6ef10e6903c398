"""Solver correctness tests run in float64.

One run's processes (the xdist workers and the CLI subprocesses) share a persistent
compilation cache in a fresh folder, removed at the end: a program that two test files
compile is compiled once. Since the numeric solver options and the period bounds are
traced (see :class:`jtraj.SolverOptions`), most files' serial3 solvers are the same
programs.

Every process of the run leaves that cache uncapped (``JTRAJ_CACHE_MAX_GB=0`` reaches the
CLI's subprocesses): a capped process would remove the others' entries as orphans when
it starts and fail to write beside them, and a cap's eviction reads the whole folder on
every write, which the run's thousands of entries make slow."""

import os
import shutil
import tempfile

os.environ.setdefault("MPLBACKEND", "Agg")
if "JTRAJ_TEST_CACHE" not in os.environ:  # the controlling process; its workers inherit it
    os.environ["JTRAJ_TEST_CACHE"] = tempfile.mkdtemp(prefix="jtraj-test-cache-")
    _OWN_CACHE = True
else:
    _OWN_CACHE = False
# the CLI's cache too (in-process and in subprocesses): never the user's ~/.cache/jtraj
os.environ["JTRAJ_CACHE_DIR"] = os.environ["JTRAJ_TEST_CACHE"]
os.environ["JTRAJ_CACHE_MAX_GB"] = "0"

# XLA's CPU backend compiles the tests' programs at LLVM optimisation level 0
# (JTRAJ_TEST_XLA_OPT sets another; 3 is what users' programs get; a level already in
# XLA_FLAGS is left alone). The suite's time is mostly compilation: tests/test_tracecache.py
# + tests/test_ipm.py in one process took 123 s at level 0 against 176 s at the default
# level and 166 s at level 1 (2 cores). Without fast-math (XLA's default) the
# level changes no result beyond rounding. The workers and the CLI's subprocesses inherit it.
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    _level = os.environ.get("JTRAJ_TEST_XLA_OPT", "0")
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_backend_optimization_level={_level}".strip()

# the native KKT kernel (jtraj._kkt_native) is built at -O2 (JTRAJ_NATIVE_OPT): on a machine
# without the builds (CI), the four joint counts the suite solves take 25 s of CPU against
# 69 s at -O3; the kernel then runs about 1.6x slower, which the tests do not measure
os.environ.setdefault("JTRAJ_NATIVE_OPT", "2")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
# implicit rank promotion (adding an (n,) array to an (N, n) one, say) is an error in the
# tests: broadcasts are written out (JTRAJ_TEST_RANK_PROMOTION=allow or warn to relax)
jax.config.update("jax_numpy_rank_promotion", os.environ.get("JTRAJ_TEST_RANK_PROMOTION", "raise"))
jax.config.update("jax_compilation_cache_dir", os.environ["JTRAJ_TEST_CACHE"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # as the CLI


def pytest_unconfigure(config):
    if _OWN_CACHE and not hasattr(config, "workerinput"):
        shutil.rmtree(os.environ["JTRAJ_TEST_CACHE"], ignore_errors=True)
