"""Time to the first solution in a new process: jtraj against CasADi + IPOPT.

    python benchmarks/bench_first_solution.py [--N 20] [--new-N 24] [--repeats 1] [--json out.json]

The README quick-start problem (serial3, start (0, 30, 30) deg, goal tip at (1.35, 1.30)
m, weights time = 1, energy = 1, N = 20), each case in a fresh Python process, timed
inside it from its first import to a returned solution:

* ``ipopt``: ``import casadi`` (and the peer, ``jtraj_peers/ipopt_peer.py``: the same
  transcription written in CasADi) to IPOPT's first solution, building the NLP included;
* ``jtraj cold``: ``import jax, jtraj`` to a converged ``jtraj.solve`` Solution, with an
  empty private compilation cache and an empty native-kernel directory (a new machine:
  the C++ kernel of :mod:`jtraj._kkt_native` is built too);
* ``jtraj cold, kernel built``: the same with the kernel already built (a machine that
  has run jtraj once, caches since cleared); once more with ``JTRAJ_QUICK_FIRST=0`` (the
  first call's program compiled optimised rather than quickly, see
  :func:`jtraj._tracecache.tiered`);
* ``jtraj warm``: a new process with the compilation cache the cold run left;
* ``jtraj new N``: a new process solving the problem with ``--new-N`` stages, everything
  else (kernel, other programs) cached.

The caches are private temporary folders (``JTRAJ_CACHE_DIR``, JAX's
``jax_compilation_cache_dir``, ``JTRAJ_NATIVE_DIR``), set explicitly in every jtraj
process, so the user's caches are never read or written. Printed: seconds per case and
the ratio to IPOPT's (the best of ``--repeats`` for each). On a shared machine the
timings are noisy; both sides are measured in the same run on the same cores.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

_JTRAJ = r"""
import os, sys, time, json
t0 = time.perf_counter()
import jax
jax.config.update("jax_compilation_cache_dir", os.environ["JTRAJ_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_enable_x64", True)
import numpy as np
import jtraj
from jtraj.problem import ik_or_raise
robot = jtraj.robots.get("serial3")
q_start = np.deg2rad([0.0, 30.0, 30.0])
q_goal = np.asarray(ik_or_raise(robot, np.array([1.35, 1.30]), q_start, "goal"))
sol = jtraj.solve(jtraj.Problem(robot, q_start, q_goal, N=int(sys.argv[1]), weights=jtraj.Weights.parse("time=1,energy=1")))
ok = bool(sol.converged)
print(json.dumps({"seconds": time.perf_counter() - t0, "converged": ok, "cost": float(sol.cost),
                  "iterations": int(sol.iterations)}))
"""

_IPOPT = r"""
import os, sys, time, json
t0 = time.perf_counter()
import casadi
import numpy as np
sys.path.insert(0, sys.argv[2])
from jtraj_peers import ipopt_peer
from jtraj_peers.ipopt_peer import solve_pair
q_start = np.deg2rad([0.0, 30.0, 30.0])
q_goal = np.asarray(json.loads(sys.argv[3]))
r = solve_pair(q_start, q_goal, N=int(sys.argv[1]), weights=(1.0, 1.0, 0.0))
print(json.dumps({"seconds": time.perf_counter() - t0, "converged": bool(r["success"]), "cost": float(r["cost"]),
                  "iterations": int(r["iterations"])}))
"""


def _run(code: str, args: list[str], env: dict) -> dict:
    proc = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, cwd=ROOT)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"case failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
    return json.loads(lines[-1])


def _goal() -> list[float]:
    """The quick-start goal configuration (IK of the goal tip), computed once here so that
    the IPOPT process imports nothing from jtraj."""
    code = ("import json, numpy as np, jax; jax.config.update('jax_enable_x64', True); import jtraj; "
            "from jtraj.problem import ik_or_raise; r = jtraj.robots.get('serial3'); "
            "qs = np.deg2rad([0.0, 30.0, 30.0]); "
            "print(json.dumps(np.asarray(ik_or_raise(r, np.array([1.35, 1.30]), qs, 'goal')).tolist()))")
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--N", type=int, default=20)
    ap.add_argument("--new-N", type=int, default=24)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    base = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    goal = json.dumps(_goal())
    results: dict[str, list[dict]] = {}

    def record(name, r):
        results.setdefault(name, []).append(r)
        print(f"  {name:28s} {r['seconds']:8.2f} s  converged {r['converged']}  iterations {r['iterations']}  "
              f"cost {r['cost']:.6f}", flush=True)

    for rep in range(args.repeats):
        print(f"repeat {rep + 1} of {args.repeats}", flush=True)
        record("ipopt", _run(_IPOPT, [str(args.N), ROOT, goal], base))
        for kernel_built, quick in ((False, True), (True, True), (True, False)):
            cache = tempfile.mkdtemp(prefix="jtraj-first-cache-")
            native = tempfile.mkdtemp(prefix="jtraj-first-native-")
            try:
                env = dict(base, JTRAJ_CACHE_DIR=cache, JTRAJ_NATIVE_DIR=native)
                if not quick:
                    env["JTRAJ_QUICK_FIRST"] = "0"
                if kernel_built:  # build the kernel in a process of its own first
                    subprocess.run([sys.executable, "-c", "from jtraj import _kkt_native; _kkt_native.available(3)"],
                                   env=env, cwd=ROOT, check=True, capture_output=True)
                    record("jtraj cold, kernel built" + ("" if quick else ", JTRAJ_QUICK_FIRST=0"),
                           _run(_JTRAJ, [str(args.N)], env))
                    continue
                record("jtraj cold", _run(_JTRAJ, [str(args.N)], env))
                record("jtraj warm", _run(_JTRAJ, [str(args.N)], env))
                record(f"jtraj new N = {args.new_N}", _run(_JTRAJ, [str(args.new_N)], env))
            finally:
                shutil.rmtree(cache, ignore_errors=True)
                shutil.rmtree(native, ignore_errors=True)
    best = {k: min(r["seconds"] for r in v) for k, v in results.items()}
    print("\ncase                          seconds   x IPOPT")
    for k, s in best.items():
        print(f"{k:28s} {s:8.2f}  {s / best['ipopt']:8.1f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"best_seconds": best, "runs": results}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
