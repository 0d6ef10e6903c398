"""XLA's CPU backend optimisation level against compile and run time of the solver's
interior-point program (:func:`jtraj.solver.staged._solve_ip_jit`, what a default
``jtraj.solve`` runs).

    python benchmarks/bench_opt_level.py [--levels 0,0c,1,2,3] [--pairs 16] [--N 20]

One process: the program is traced and lowered once, then compiled at each level
(``xla_backend_optimization_level`` with the solver's other options; ``0c``: level 0
with ``xla_llvm_disable_expensive_passes``); each compiled
program solves the same benchmark pairs (serial3, weights time = 1, energy = 0.1),
interleaved, best of ``--repeats`` per pair; printed: compile seconds, median solve
milliseconds, and whether iterations and statuses match level 3's.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.append(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root: jtraj_peers


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--levels", default="0,1,2,3")
    ap.add_argument("--pairs", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--N", type=int, default=20)
    args = ap.parse_args(argv)
    import equinox as eqx

    import jtraj
    from jtraj import _kkt_native
    from jtraj import _testing as solver
    from jtraj._compile import SOLVER_XLA_OPTIONS, supported_options
    from jtraj._testing import staged_start as _start
    from jtraj_peers.pairs import benchmark_pairs

    _kkt_native.available(3)
    robot = jtraj.robots.get("serial3")
    weights = jtraj.Weights(time=1.0, energy=0.1)
    q0, q1 = benchmark_pairs(args.pairs)
    problems = [jtraj.Problem(robot, q0[i], q1[i], N=args.N, weights=weights) for i in range(args.pairs)]
    opts = solver.resolve_method(None, "decoupled", robot)
    split = solver.split_options(opts)
    init = solver.placeholder_init(args.N, 3)

    def program(problem, split, init):
        o = solver.TracedOptions(split)
        nlp, state, valid = _start(problem, o, "decoupled", init, np.bool_(False), np.bool_(True))
        ip = solver.ip_run(nlp, state, o)
        sol = solver.finish(nlp, solver.ipm.InteriorPoint().postprocess(nlp, ip, state), o, valid, light=True)
        return sol.status, sol.iterations, sol.cost, solver.ipm.decided(state, ip)

    flat = [jax.tree.leaves(eqx.filter((p, split, init), eqx.is_array)) for p in problems]
    t0 = time.perf_counter()
    lowered = eqx.filter_jit(program).lower(problems[0], split, init)
    print(f"trace+lower {time.perf_counter() - t0:.1f} s", flush=True)
    compiled = {}
    for level in args.levels.split(","):
        # "0c": level 0 with LLVM's expensive passes off as well
        options = supported_options({**SOLVER_XLA_OPTIONS, "xla_backend_optimization_level": int(level.rstrip("c")),
                                     **({"xla_llvm_disable_expensive_passes": True} if level.endswith("c") else {})})
        t0 = time.perf_counter()
        compiled[level] = lowered.compile(options)
        print(f"level {level}: compile {time.perf_counter() - t0:6.1f} s", flush=True)
    times = {lv: [[] for _ in problems] for lv in compiled}
    outs = {}
    for _ in range(args.repeats):
        for lv, c in compiled.items():
            for i, p in enumerate(problems):
                t0 = time.perf_counter()
                out = jax.block_until_ready(c(p, split, init))
                times[lv][i].append(time.perf_counter() - t0)
                outs[lv, i] = out
    ref = max(compiled, key=lambda lv: (int(lv.rstrip("c")), not lv.endswith("c")))
    for lv in compiled:
        med = np.median([min(t) for t in times[lv]]) * 1e3
        same = all(int(outs[lv, i][1]) == int(outs[ref, i][1]) and int(outs[lv, i][0]) == int(outs[ref, i][0])
                   for i in range(len(problems)))
        dc = max(abs(float(outs[lv, i][2]) - float(outs[ref, i][2])) for i in range(len(problems)))
        print(f"level {lv}: median solve {med:7.2f} ms  same iterations/statuses as level {ref}: {same}  "
              f"max |cost diff| {dc:.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
