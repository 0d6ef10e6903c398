"""Derivatives through ``jtraj.solve`` on arms loaded from URDF files, against central
differences of re-solves (float64).

    python benchmarks/check_grad_arms.py [--arms ur5,panda] [--pairs 2] [--N 10] [--step 1e-4] [--json PATH]

For each arm (``bench_urdf_arms.ARMS``: ``jtraj.robots.from_urdf`` of an
example-robot-data file with its defaults) and the first ``--pairs`` pairs of
``bench_urdf_arms.arm_pairs`` (seed 0), ``jax.jacobian`` (reverse mode) of the optimal
time T and of the optimal cost through ``jtraj.solve`` with the default solver, with
respect to the goal (n joints), the weights (time, energy) and the link masses
(``jtraj.robots.with_params(robot, masses=...)``, the n bodies of the chain), against
central differences of re-solves (steps ``--step`` rad for the goal, ``--step`` relative
for the others). Each re-solve is a ``jtraj.solve`` of a concrete problem warm-started
at the solve's optimum with :data:`jtraj.implicit.REFINE_IP` (the interior-point method
at a barrier parameter of 1e-8 to tolerance 1e-9; where that does not converge,
:data:`jtraj.implicit.REFINE`, the AL method at 1e-10, from the same start), so that it
follows that optimum:
an arm's optima are not unique (cold re-solves at tight tolerances of the Panda's pair
land in a neighbouring optimum, cost 1.4e-4 lower, and one of its differences hops
between the two).

Errors are in the units of the output's relative change: ``|d - fd| * s / |y|`` with
``s`` = 1 rad for the goal and the input's own value otherwise, the largest over each
block, printed with the block's size (``|fd| * s / |y|``, 0 where the output does not
depend on the input). Also timed: three solves (the first of the process compiles quickly compiled programs,
the second the optimised ones, the third runs compiled) and three jacobians at the same
point (the first compiles the reverse program).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np

sys.path.append(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root

def check_arm(label: str, N: int, step: float, pair: int) -> dict:
    import jax
    import jax.numpy as jnp

    import jtraj
    from benchmarks.bench_urdf_arms import arm_pairs, jtraj_arm
    from jtraj.implicit import REFINE, REFINE_IP, valid_derivatives

    robot0 = jtraj_arm(label)
    n = robot0.n
    qs, qg = arm_pairs(robot0, pair + 1, 0)
    start, goal = np.asarray(qs[pair]), np.asarray(qg[pair])
    theta0 = np.r_[goal, 1.0, 0.1, np.asarray(robot0.masses)]
    groups = {"q_goal": slice(0, n), "weights": slice(n, n + 2), "masses": slice(n + 2, 2 * n + 2)}

    def problem(theta):
        robot = jtraj.robots.with_params(robot0, masses=theta[n + 2:])
        return jtraj.Problem(robot, start, theta[:n], N=N,
                             weights=jtraj.Weights(time=theta[n], energy=theta[n + 1]))

    out = {"arm": label, "pair": pair, "n": n, "N": N, "step": step, "q_start": start.tolist(), "q_goal": goal.tolist()}
    times = []
    for _ in range(3):  # the first compiles quick programs, the second the optimised ones
        t0 = time.perf_counter()
        sol = jax.block_until_ready(jtraj.solve(problem(theta0)))
        times.append(time.perf_counter() - t0)
    out["solve_s"] = times
    out["status"], out["T"], out["cost"] = sol.status_message, float(sol.T), float(sol.cost)
    at = (sol.v, sol.h)

    def outputs(theta):
        s = jtraj.solve(problem(theta))
        return {"T": s.T, "cost": s.cost, "valid": valid_derivatives(s)}

    jac_fn = jax.jacobian(lambda th: {k: v for k, v in outputs(th).items() if k != "valid"})
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        jac = jax.block_until_ready(jac_fn(jnp.asarray(theta0)))
        times.append(time.perf_counter() - t0)
    out["jacobian_s"] = times
    out["valid_derivatives"] = bool(outputs(jnp.asarray(theta0))["valid"])

    hs = np.where(np.arange(theta0.size) < n, step, step * np.abs(theta0))
    fd = {"T": [], "cost": []}
    iterations, fallbacks, uncertified = [], 0, 0
    t0 = time.perf_counter()
    for i in range(theta0.size):
        vals = []
        for sign in (1.0, -1.0):
            th = theta0.copy()
            th[i] += sign * hs[i]
            s = jtraj.solve(problem(th), init=at, solver=REFINE_IP, warm="primal")
            if not bool(s.converged):  # the AL method at 1e-10 from the same start
                fallbacks += 1
                s = jtraj.solve(problem(th), init=at, solver=REFINE, warm="full")
            uncertified += not bool(s.converged)
            iterations.append(int(s.iterations))
            vals.append((float(s.T), float(s.cost)))
        for j, o in enumerate(("T", "cost")):
            fd[o].append((vals[0][j] - vals[1][j]) / (2 * hs[i]))
    out["differences_s"] = time.perf_counter() - t0
    out["resolve_iterations_median"] = float(np.median(iterations))
    out["resolve_fallbacks"], out["resolve_uncertified"] = fallbacks, uncertified
    out["errors"], out["sizes"] = {}, {}
    scale = np.where(np.arange(theta0.size) < n, 1.0, np.abs(theta0))
    for o in ("T", "cost"):
        a, b = np.asarray(jac[o]), np.asarray(fd[o])
        y = abs(out[o])
        for g, sl in groups.items():
            out["errors"][f"d{o}/d{g}"] = float(np.max(np.abs(a[sl] - b[sl]) * scale[sl]) / y)
            out["sizes"][f"d{o}/d{g}"] = float(np.max(np.abs(b[sl]) * scale[sl]) / y)
        out[f"d{o}"] = a.tolist()
        out[f"fd_d{o}"] = b.tolist()
    return out


def main(argv=None):
    from benchmarks.bench_urdf_arms import ARMS

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--arms", default="ur5,panda", help=f"comma-separated, of {', '.join(ARMS)}")
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--N", type=int, default=10)
    ap.add_argument("--step", type=float, default=1e-4)
    ap.add_argument("--json", default="")
    args = ap.parse_args(argv)
    labels = [a for a in args.arms.split(",") if a]
    unknown = [a for a in labels if a not in ARMS]
    if unknown:
        ap.error(f"--arms: unknown {unknown}; known: {', '.join(ARMS)}")
    if args.pairs < 1 or args.N < 2 or not args.step > 0:
        ap.error("--pairs must be >= 1, --N >= 2 and --step > 0")

    from jtraj.cli import setup_jax

    setup_jax(x64=True)
    import jax

    command = " ".join(["python", *sys.argv])
    machine = f"{platform.node() or 'host'}, {os.cpu_count()} CPUs, jax {jax.__version__}"
    print(f"# {command}\n# {time.strftime('%Y-%m-%d')}, {machine}", flush=True)
    results = []
    for label, pair in ((a, i) for a in labels for i in range(args.pairs)):
        r = check_arm(label, args.N, args.step, pair)
        results.append(r)
        e = r["errors"]
        print(f"{label} pair {pair} (n = {r['n']}, N = {r['N']}): {r['status']}, T = {r['T']:.6g} s; derivatives "
              f"valid {r['valid_derivatives']}", flush=True)
        if r["resolve_uncertified"]:
            print(f"   no reference: {r['resolve_uncertified']} re-solves not certified at these tolerances")
        else:
            print("   error (block size): " + ", ".join(f"{k} {v:.1e} ({r['sizes'][k]:.2g})" for k, v in e.items()))
        print(f"   solve {r['solve_s'][0]:.1f} s (first), {r['solve_s'][2]:.3f} s (third); jacobian "
              f"{r['jacobian_s'][0]:.1f} s (first), {r['jacobian_s'][2]:.2f} s (third); {2 * (2 * r['n'] + 2)} "
              f"re-solves {r['differences_s']:.1f} s (median {r['resolve_iterations_median']:.0f} iterations, "
              f"{r['resolve_fallbacks']} by the AL method)",
              flush=True)
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump({"command": command, "machine": machine, "arms": results}, f, indent=1)
        print(f"figures written to {args.json}")


if __name__ == "__main__":
    main()
