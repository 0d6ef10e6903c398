"""The staged single solve (:mod:`jtraj.solver.staged`, what ``jtraj.solve`` runs on concrete
arrays) against the single traced program (``jtraj.solver.core.solve_jit``, what it runs
under an outer jit): the same statuses, iterations and costs on benchmark pairs,
including pairs the interior-point method leaves to the augmented-Lagrangian loop.

    python benchmarks/check_staged.py [--pairs 32] [--scan 256] [--seed 0] [--N 20]

Of the first ``--scan`` pairs, those the interior-point method leaves undecided are
taken first (at most half), the rest of the ``--pairs`` from the start of the family.
With ``--ip-max-iter K`` every pair runs with ``SolverOptions(ip_max_iter=K)`` too:
a budget the interior-point method often exhausts, so that those pairs go through the
augmented-Lagrangian fallback (both programs compiled again for these options).
Exit status 1 on a mismatch (iterations or status differ, or |cost difference| > 1e-10
relative).
"""

from __future__ import annotations

import argparse
import os
import sys

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.append(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root: jtraj_peers


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pairs", type=int, default=32)
    ap.add_argument("--scan", type=int, default=256)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--N", type=int, default=20)
    ap.add_argument("--ip-max-iter", type=int, default=0)
    args = ap.parse_args(argv)

    import jtraj
    from jtraj import _testing as solver
    from jtraj_peers.pairs import benchmark_pairs

    robot = jtraj.robots.get("serial3")
    weights = jtraj.Weights(time=1.0, energy=0.1)
    q0, q1 = benchmark_pairs(args.scan, seed=args.seed)
    opts = solver.resolve_method(None, "decoupled", robot)
    short = solver.resolve_method(jtraj.SolverOptions(ip_max_iter=args.ip_max_iter), "decoupled", robot)
    init = solver.placeholder_init(args.N, 3)
    yes, no = np.bool_(True), np.bool_(False)

    def problem(i):
        return jtraj.Problem(robot, q0[i], q1[i], N=args.N, weights=weights)

    undecided = []
    for i in range(args.scan):
        _, decided, _ = solver.staged_ip_jit(problem(i), opts, "decoupled", init, no, yes)
        if not bool(decided):
            undecided.append(i)
    chosen = undecided[: args.pairs // 2]
    chosen += [i for i in range(args.scan) if i not in chosen][: args.pairs - len(chosen)]
    print(f"{len(undecided)} of {args.scan} pairs left to the AL loop by the interior-point method; "
          f"checking {len(chosen)} pairs, {min(len(undecided), args.pairs // 2)} of them left to it")
    bad = 0
    worst = 0.0
    fallback = 0
    runs = [(i, opts, "IP" if i not in undecided else "AL") for i in chosen]
    if args.ip_max_iter:
        runs += [(i, short, f"ip_max_iter={args.ip_max_iter}") for i in chosen]
    for i, o, label in runs:
        p = problem(i)
        if o is short:
            fallback += not bool(solver.staged_ip_jit(p, o, "decoupled", init, no, yes)[1])
        new = jtraj.solve(p, solver=jtraj.solver.from_options(o))
        old = solver.solve_jit(p, o, "decoupled", init, no, yes)
        rel = abs(float(new.cost) - float(old.cost)) / max(1.0, abs(float(old.cost)))
        worst = max(worst, rel if np.isfinite(rel) else 0.0)
        same = (int(new.iterations) == int(old.iterations) and int(new.status) == int(old.status)
                and (rel <= 1e-10 or not np.isfinite(float(old.cost))))
        bad += not same
        print(f"pair {i:3d} {label}  status {int(old.status)} / {int(new.status)}  "
              f"iterations {int(old.iterations)} / {int(new.iterations)}  cost {float(old.cost):.12f} / "
              f"{float(new.cost):.12f}  kkt {float(old.kkt_error):.3g} / {float(new.kkt_error):.3g}"
              f"{'' if same else '  MISMATCH'}", flush=True)
    if args.ip_max_iter:
        print(f"with ip_max_iter={args.ip_max_iter}: {fallback} of {len(chosen)} pairs went to the AL fallback")
    chosen = runs
    print(f"{len(chosen) - bad} of {len(chosen)} identical (statuses, iterations); largest relative cost "
          f"difference {worst:.3g}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
