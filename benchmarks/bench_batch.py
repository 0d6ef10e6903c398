"""Batched solver throughput on whatever device JAX uses (CPU or GPU), no peer.

    python benchmarks/bench_batch.py [--batches 1024,4096] [--slots 1024] [--segment 25] [--seed 1]
    JAX_PLATFORMS=cpu python benchmarks/bench_batch.py --batches 256 --slots 32

The canonical serial3 benchmark family (N = 20, time = 1, energy = 0.1, float64), solved by
``jtraj.solve_batch`` with ``slots`` vmapped lanes refilled every ``segment`` iterations.
Each batch size is solved twice: the first call includes compilation, the second is warm.
Prints pairs/s, the converged fraction, the status counts and the iterations. Use it on a
GPU machine (the CasADi peer is not needed); ratios against IPOPT come from
``bench_solver.py`` and ``bench_dataset.py`` on the CPU.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.append(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root: jtraj_peers


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batches", default="1024,4096", help="comma-separated batch sizes")
    ap.add_argument("--slots", type=int, default=1024)
    ap.add_argument("--segment", type=int, default=25)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    import jtraj
    from jtraj_peers.pairs import benchmark_pairs

    print(f"jax {jax.__version__} on {jax.devices()[0].device_kind} ({jax.default_backend()})", flush=True)
    robot = jtraj.robots.get("serial3")
    w = jtraj.Weights(time=1.0, energy=0.1)
    for B in (int(b) for b in args.batches.split(",")):
        q0, q1 = benchmark_pairs(B, seed=args.seed)
        for run in ("cold", "warm"):
            t = time.perf_counter()
            s = jtraj.solve_batch(robot, q0, q1, N=20, weights=w, slots=args.slots, segment=args.segment)
            jax.block_until_ready(s.cost)
            dt = time.perf_counter() - t
            st, it = np.asarray(s.status), np.asarray(s.iterations)
            print(f"B {B:6d} slots {args.slots} {run}: {dt:7.1f} s  {B / dt:8.1f} pairs/s  converged "
                  f"{np.mean(st == 0) * 100:5.1f} %  statuses {np.bincount(st, minlength=7).tolist()}  "
                  f"iterations median {np.median(it):.0f} max {it.max()}", flush=True)


if __name__ == "__main__":
    main()
