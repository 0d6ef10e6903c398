"""Efforts between the samples: the thesis' bound at the samples against efforts="intervals".

    python benchmarks/bench_efforts.py [--pairs 64] [--seed 5] [--h-max 0.1] [--per-interval 64]

The canonical serial3 family (N = 20, time = 1, energy = 0.1, float64, ``jtraj_peers.pairs``),
solved by ``jtraj.solve_batch`` with ``efforts="samples"`` (default) and ``"intervals"``
in one process pinned to one core (warm: each is compiled first on two pairs and on the
batch, then timed, in alternating order). Prints, per setting, the converged count, the
largest ``|tau(t)| / tau_max`` along the executed motion (``jtraj.resample``, median and
max over the converged pairs, share above 1), the Newton iterations and the warm time;
then the cost change on pairs both converge, and the largest effort at the interval ends
re-computed by Pinocchio's RNEA (``jtraj_peers.verify``, independent of jtraj) for the
"intervals" optima. ``--h-max 0.2`` is the datasets' period bound.
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
    ap.add_argument("--pairs", type=int, default=64)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--h-max", type=float, default=None, help="period bound [s] (default: the robot's, 0.1)")
    ap.add_argument("--per-interval", type=int, default=64, help="points per interval for the effort ratio")
    args = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    import jtraj

    jtraj.pin_to_one_cpu()
    from jtraj.resample import intersample_effort
    from jtraj_peers.pairs import benchmark_pairs
    from jtraj_peers.verify import rnea

    robot = jtraj.robots.get("serial3", **({} if args.h_max is None else {"h_max": args.h_max}))
    w = jtraj.Weights(time=1.0, energy=0.1)
    q0, q1 = benchmark_pairs(args.pairs, seed=args.seed)
    modes = ("samples", "intervals")
    for mode in modes:  # compile every lane count once
        jax.block_until_ready(jtraj.solve_batch(robot, q0[:2], q1[:2], N=20, weights=w, efforts=mode).q)
        jax.block_until_ready(jtraj.solve_batch(robot, q0, q1, N=20, weights=w, efforts=mode).q)
    times, sols = {m: [] for m in modes}, {}
    for order in (modes, modes[::-1]):
        for mode in order:
            t = time.perf_counter()
            sols[mode] = jtraj.solve_batch(robot, q0, q1, N=20, weights=w, efforts=mode)
            jax.block_until_ready(sols[mode].q)
            times[mode].append(time.perf_counter() - t)
    tau_max = np.asarray(robot.limits.tau_max)
    print(f"serial3, {args.pairs} pairs of seed {args.seed}, h_max {float(robot.limits.h_max)} s, one core, warm")
    conv = {}
    for mode in modes:
        s = sols[mode]
        c = np.asarray(s.converged)
        conv[mode] = c
        e = np.asarray(intersample_effort(s, robot, per_interval=args.per_interval))[c]
        it = np.asarray(s.iterations)
        print(f"  {mode:9s}: converged {c.sum()}/{args.pairs}; max |tau(t)|/tau_max along the motion: median "
              f"{np.median(e):.5f}, max {e.max():.5f}, {np.mean(e > 1 + 1e-9) * 100:.0f} % above 1; iterations "
              f"mean {it[c].mean():.0f}; time {min(times[mode]):.2f} s (best of {len(times[mode])})")
    both = conv["samples"] & conv["intervals"]
    cost = {m: np.asarray(sols[m].cost) for m in modes}
    gap = (cost["intervals"] - cost["samples"])[both] / cost["samples"][both] * 100
    print(f"  cost of 'intervals' against 'samples' on {both.sum()} pairs: median {np.median(gap):+.3f} %, "
          f"max {gap.max():+.3f} %; time ratio {min(times['intervals']) / min(times['samples']):.2f}x")
    s = sols["intervals"]
    q, qd, v = (np.asarray(x) for x in (s.q, s.qd, s.v))
    ends = max(np.max(np.abs(rnea(q[i, k + 1], qd[i, k + 1], v[i, k])) / tau_max)
               for i in np.flatnonzero(conv["intervals"]) for k in range(v.shape[1]))
    print(f"  'intervals' optima, Pinocchio at the interval ends: max |tau|/tau_max {ends:.8f}")


if __name__ == "__main__":
    main()
