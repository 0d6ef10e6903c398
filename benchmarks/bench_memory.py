"""Peak resident memory of one ``jtraj.solve`` against the number of stages N.

    python benchmarks/bench_memory.py [--N 20,40,80,160,320,640,1000] [--limit-gb 8]
                                      [--json memory.json] [--plot memory_vs_N.png]
                                      [--method auto|al] [--compare before.json ...]

Each N runs in a fresh process (private, empty compilation caches; the native kernel's
build directory shared) that builds the README quick-start problem (serial3, start
(0, 30, 30) deg, goal tip at (1.35, 1.30) m, weights time = 1, energy = 1, the robot's
default period bounds) with N stages and solves it with the default options; it reports
``resource.getrusage(RUSAGE_SELF).ru_maxrss`` (the peak resident set, compilation
included), the wall time and the status. The address space of each process is capped
at ``--limit-gb`` (RLIMIT_AS), so that a solve that grows without bound fails in its
own process instead of exhausting a shared machine; such a run is reported with its
error. ``--method al`` measures the
augmented-Lagrangian programs (what a problem the interior-point method leaves
undecided also compiles and runs: the dense constraint Jacobians of the polish and the
least-squares multipliers). ``--compare`` adds earlier ``--json`` files (e.g. of another checkout, run with
its own PYTHONPATH) to the plot.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time

sys.path.append(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root: jtraj_peers


def child(N: int, limit_gb: float, method: str = "auto") -> dict:
    if limit_gb > 0:
        cap = int(limit_gb * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    t0 = time.perf_counter()
    out = {"N": N}
    try:
        import jax

        jax.config.update("jax_enable_x64", True)
        import jtraj
        from jtraj.solver.options import from_overrides
        from profile_compile import quick_start_problem

        problem = quick_start_problem(N)
        sol = jtraj.solve(problem, solver=from_overrides({"method": method}))
        out.update(status=int(sol.status), converged=bool(sol.converged), iterations=int(sol.iterations),
                   cost=float(sol.cost))
    except Exception as exc:  # noqa: BLE001 - reported, not raised: the point of the run
        out.update(error=f"{type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else ''}")
    out["seconds"] = time.perf_counter() - t0
    out["maxrss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return out


def run(N: int, limit_gb: float, timeout: float, method: str = "auto") -> dict:
    env = dict(os.environ)
    cache = tempfile.mkdtemp(prefix="jtraj-mem-cache-")
    env["JTRAJ_CACHE_DIR"] = cache
    env.setdefault("JTRAJ_NATIVE_DIR", os.path.join(tempfile.gettempdir(), "jtraj-native-bench"))
    try:
        proc = subprocess.run([sys.executable, __file__, "--child", str(N), "--limit-gb", str(limit_gb),
                               "--method", method],
                              capture_output=True, text=True, env=env, timeout=timeout)
        lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
        if lines:
            return json.loads(lines[-1])
        tail = (proc.stderr.strip().splitlines() or ["?"])[-1]
        return {"N": N, "error": f"exit {proc.returncode}: {tail[:200]}"}
    except subprocess.TimeoutExpired:
        return {"N": N, "error": f"timeout after {timeout:.0f} s"}
    finally:
        import shutil

        shutil.rmtree(cache, ignore_errors=True)


def plot(series: dict, path: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for label, rows in series.items():
        ok = [r for r in rows if "error" not in r]
        bad = [r for r in rows if "error" in r]
        line, = ax.plot([r["N"] for r in ok], [r["maxrss_mb"] / 1024 for r in ok], "o-", label=label)
        if bad:
            ax.plot([r["N"] for r in bad], [r["maxrss_mb"] / 1024 if "maxrss_mb" in r else float("nan") for r in bad],
                    "x", color=line.get_color(), markersize=10, label=f"{label}: failed")
            for r in bad:
                m = re.search(r"allocating (\d+) bytes", r["error"])
                note = f"asked XLA for {int(m.group(1)) / 2**30:.0f} GiB" if m else r["error"][:40]
                ax.annotate(note, (r["N"], r.get("maxrss_mb", 1024) / 1024), textcoords="offset points",
                            xytext=(-150, -4), fontsize=8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("N (stages)")
    ax.set_ylabel("peak resident memory of a solve [GiB]")
    ax.set_title("serial3 quick-start problem, one jtraj.solve, fresh process")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--child", type=int)
    ap.add_argument("--N", default="20,40,80,160,320,640,1000")
    ap.add_argument("--limit-gb", type=float, default=8.0)
    ap.add_argument("--timeout", type=float, default=900.0)
    ap.add_argument("--label", default="jtraj")
    ap.add_argument("--method", default="auto", help="SolverOptions.method (al: the fallback's programs)")
    ap.add_argument("--json")
    ap.add_argument("--plot")
    ap.add_argument("--compare", nargs="*", default=[])
    args = ap.parse_args(argv)
    if args.child is not None:
        print(json.dumps(child(args.child, args.limit_gb, args.method)), flush=True)
        return 0
    series = {}
    for path in args.compare:
        with open(path) as fh:
            d = json.load(fh)
        series[d["label"]] = d["rows"]
    rows = []
    if args.N:
        for N in map(int, args.N.split(",")):
            r = run(N, args.limit_gb, args.timeout, args.method)
            rows.append(r)
            print(f"N = {N:5d}  peak RSS {r.get('maxrss_mb', float('nan')):8.0f} MB  {r.get('seconds', float('nan')):7.1f} s  "
                  + (f"status {r['status']} iterations {r['iterations']}" if "status" in r else r.get("error", "")),
                  flush=True)
        series[args.label] = rows
        if args.json:
            with open(args.json, "w") as fh:
                json.dump({"label": args.label, "rows": rows}, fh, indent=1)
    if args.plot:
        plot(series, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
