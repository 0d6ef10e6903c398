"""Standalone run of the IPOPT peer on the serial3 benchmark family.

    python benchmarks/bench_ipopt_peer.py [--pairs 64] [--seed 0] [--N 20] [--processes P]
                                          [--formulation lifted|condensed]

Solves ``--pairs`` random pairs (q_start ~ U(-1.2, 1.2)^3, q_goal = q_start +
U(-0.8, 0.8)^3, seeded) on all cores with :func:`jtraj_peers.ipopt_peer.solve_many`, checks
every solution with the independent verifier and prints success rates, solve times,
iterations, throughput, T and cost.
"""

from __future__ import annotations

import argparse
import collections
import os
import sys

import numpy as np

sys.path.append(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root: jtraj_peers

from jtraj_peers.ipopt_peer import benchmark_pairs, solve_many  # noqa: E402
from jtraj_peers.verify import verify  # noqa: E402


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--N", type=int, default=20)
    ap.add_argument("--processes", type=int, default=None, help="default os.cpu_count()")
    ap.add_argument("--tol", type=float, default=1e-6, help="verifier tolerance")
    ap.add_argument("--formulation", choices=("lifted", "condensed"), default="lifted",
                    help="CasADi form of the NLP (see jtraj_peers/ipopt_peer.py)")
    args = ap.parse_args(argv)

    q0, q1 = benchmark_pairs(args.pairs, args.seed)
    res = solve_many(q0, q1, processes=args.processes, N=args.N, formulation=args.formulation)
    checks = [verify(a, b, r["v"], r["h"], tol=args.tol) for a, b, r in zip(q0, q1, res)]

    ok_ipopt = np.array([r["success"] for r in res])
    ok_strict = np.array([r["strict_success"] for r in res])
    ok_ver = np.array([c["ok"] for c in checks])
    both = ok_ipopt & ok_ver
    sec = np.array([r["seconds"] for r in res])
    it = np.array([r["iterations"] for r in res])
    n = len(res)
    print(f"IPOPT peer, serial3, N={args.N}, weights (1, 0.1, 0), {n} pairs (seed {args.seed}), "
          f"{res.processes} processes (os.cpu_count() = {os.cpu_count()})")
    print(f"  success (IPOPT: Solve_Succeeded or Solved_To_Acceptable_Level): {ok_ipopt.sum()}/{n}"
          f"  (Solve_Succeeded only: {ok_strict.sum()}/{n})")
    print(f"  success (verifier, tol {args.tol:g}): {ok_ver.sum()}/{n};  both: {both.sum()}/{n}")
    print("  statuses:", dict(collections.Counter(r["status"] for r in res)))
    print(f"  solve time [s] (wall, per solve): median {np.median(sec):.3f}  min {sec.min():.3f}  "
          f"max {sec.max():.3f}  (successful only: median {np.median(sec[ok_ipopt]) if ok_ipopt.any() else np.nan:.3f})")
    print(f"  iterations: median {np.median(it):.0f}  min {it.min()}  max {it.max()}")
    print(f"  throughput: {n / res.wall_seconds:.2f} pairs/s on {res.processes} processes "
          f"(set of {n} in {res.wall_seconds:.1f} s; pool start + NLP builds {res.setup_seconds:.1f} s)")
    if both.any():
        T = np.array([r["T"] for r in res])[both]
        J = np.array([c["cost"] for c in checks])[both]
        print(f"  successful pairs: median T {np.median(T):.4f} s (min {T.min():.4f}, max {T.max():.4f}); "
              f"median cost {np.median(J):.4f}")
    for i, (r, c) in enumerate(zip(res, checks)):
        if not (r["success"] and c["ok"]):
            viol = {k: f"{x:.1e}" for k, x in c["max_rel_violation"].items()}
            print(f"  pair {i}: {r['status']}, {r['iterations']} it, T {r['T']:.4f}, goal error "
                  f"{c['goal_error']:.1e}, rel. violations {viol}, |dq| {np.round(np.abs(q1[i] - q0[i]), 3)}")
    return dict(results=res, checks=checks)


if __name__ == "__main__":
    main()
