"""Derivatives through the solve (jtraj.implicit): accuracy, cost and failures.

    python benchmarks/bench_grad.py [--fd-pairs 64] [--pairs 1024] [--N 20] [--seed 1]

Three measurements on the serial3 benchmark family (time = 1, energy = 0.1, float64):

1. **Agreement with finite differences of re-solves** on ``--fd-pairs`` pairs: for each
   input kind (q_goal, q_start, the weights time and energy, the link masses, tau_max)
   a random unit direction per pair, the forward-mode derivative (``jax.jvp`` through
   ``jtraj.solve``) of T and of the cost against central differences of warm re-solves
   (AL method, tolerances 1e-10, relative step ``--step``). Prints the distribution
   (median, 90th percentile, max) of the relative errors per kind and output, over the
   pairs whose solves all converged.
2. **The backward pass of grad(sum of T over a batch)** on ``--time-pairs`` pairs against
   the batched forward solve (``jtraj.solve_batch``, warm): ``jax.vjp`` splits the work
   into the forward part (the solve plus the linearisation: active sets, KKT matrices
   and their factorisations) and the backward part (the transposed tangent: one solve
   with each factorisation per problem); both are printed as ratios to the solve.
3. **NaN count** over ``--pairs`` pairs: per-sample gradients of T through
   ``solve_batch`` with the default options; NaN entries on converged samples (the goal
   is 0), and how many samples converged (the others get zero derivatives).

Timings on a shared CPU are noisy: rerun where a ratio matters.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.append(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root: jtraj_peers

KINDS = ("q_goal", "q_start", "weights", "masses", "tau_max")


def _pct(x):
    x = np.asarray(x)
    if x.size == 0:
        return "n/a"
    return f"median {np.median(x):.2e}  p90 {np.percentile(x, 90):.2e}  max {np.max(x):.2e}  (n = {x.size})"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fd-pairs", type=int, default=64)
    ap.add_argument("--time-pairs", type=int, default=64)
    ap.add_argument("--pairs", type=int, default=1024, help="pairs of the NaN count")
    ap.add_argument("--N", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--step", type=float, default=1e-5, help="relative step of the central differences")
    args = ap.parse_args(argv)

    import equinox as eqx
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import jtraj
    from jtraj.implicit import valid_derivatives
    from jtraj_peers.pairs import benchmark_pairs

    print(f"jax {jax.__version__} on {jax.devices()[0].device_kind} ({jax.default_backend()}), N = {args.N}",
          flush=True)
    robot = jtraj.robots.get("serial3")
    w = jtraj.Weights(time=1.0, energy=0.1)
    tight = jtraj.SolverOptions(tol_feasibility=1e-10, tol_optimality=1e-10, max_iter=2000, method="al")
    rng = np.random.default_rng(args.seed)

    # ---- 1. agreement with finite differences -----------------------------------------
    if args.fd_pairs:
        q0s, q1s = benchmark_pairs(args.fd_pairs, seed=args.seed)
        errs = {(k, o): [] for k in KINDS for o in ("T", "cost")}
        skipped = 0
        t0 = time.perf_counter()
        for q0, q1 in zip(q0s, q1s):
            try:
                p = jtraj.Problem(robot, q0, q1, N=args.N, weights=w)
            except ValueError:
                skipped += 1
                continue
            base = jtraj.solve(p, options=tight)
            if not bool(base.converged):
                skipped += 1
                continue
            dyn, static = eqx.partition(p, eqx.is_inexact_array)
            zero = jax.tree.map(jnp.zeros_like, dyn)
            for kind in KINDS:
                if kind == "weights":
                    get = lambda d: (d.weights.time, d.weights.energy)  # noqa: E731
                    x = (p.weights.time, p.weights.energy)
                else:
                    get = {"q_goal": lambda d: d.q_goal, "q_start": lambda d: d.q_start,
                           "masses": lambda d: d.robot.masses, "tau_max": lambda d: d.robot.limits.tau_max}[kind]
                    x = get(p)
                flat = np.concatenate([np.ravel(np.asarray(v)) for v in jax.tree.leaves(x)])
                u = rng.standard_normal(flat.size)
                u /= np.linalg.norm(u)
                # a relative step for parameters, an absolute one (rad) for configurations
                scale = np.ones_like(flat) if kind in ("q_goal", "q_start") else np.abs(flat)
                direction = u * scale
                leaves, tdef = jax.tree.flatten(x)
                pieces, pos = [], 0
                for v in leaves:
                    pieces.append(jnp.asarray(direction[pos:pos + np.size(v)]).reshape(np.shape(v)))
                    pos += np.size(v)

                def along(t, leaves=leaves, tdef=tdef, pieces=pieces):
                    return jax.tree.unflatten(tdef, [jnp.asarray(v) + t * d for v, d in zip(leaves, pieces)])

                tangent = eqx.tree_at(get, zero, jax.tree.unflatten(tdef, pieces))

                def out_of(d):
                    s = jtraj.solve(eqx.combine(d, static), options=tight)
                    return jnp.stack([s.T, s.cost])

                _, jvp = jax.jvp(out_of, (dyn,), (tangent,))
                vals, ok = [], True
                for sign in (1.0, -1.0):
                    d_ = eqx.tree_at(get, dyn, along(sign * args.step))
                    s = jtraj.solve(eqx.combine(d_, static), options=tight, init=(base.v, base.h))
                    ok &= bool(s.converged)
                    vals.append(np.array([float(s.T), float(s.cost)]))
                if not ok:
                    continue
                fd = (vals[0] - vals[1]) / (2 * args.step)
                for i, o in enumerate(("T", "cost")):
                    errs[(kind, o)].append(abs(float(jvp[i]) - fd[i]) / max(abs(fd[i]), 1e-6))
        print(f"1. finite differences of re-solves, {args.fd_pairs} pairs ({skipped} skipped: invalid or "
              f"not converged), {time.perf_counter() - t0:.0f} s; relative errors:")
        for (kind, o), e in errs.items():
            print(f"   {kind:8s} d{o:4s}: {_pct(e)}")

    # ---- 2. backward pass against the batched forward solve -----------------------------
    if args.time_pairs:
        q0, q1 = benchmark_pairs(args.time_pairs, seed=args.seed + 100)

        def total_T(g):
            s = jtraj.solve_batch(robot, q0, g, N=args.N, weights=w)
            return jnp.sum(jnp.where(valid_derivatives(s), s.T, 0.0))

        for run in ("cold", "warm"):
            t = time.perf_counter()
            s = jtraj.solve_batch(robot, q0, q1, N=args.N, weights=w)
            jax.block_until_ready(s.T)
            t_fwd = time.perf_counter() - t
            t = time.perf_counter()
            _, vjp = jax.vjp(total_T, jnp.asarray(q1))
            t_lin = time.perf_counter() - t
            t = time.perf_counter()
            (g,) = vjp(jnp.ones(()))
            jax.block_until_ready(g)
            t_bwd = time.perf_counter() - t
            print(f"2. {run}: B = {args.time_pairs}: forward solve {t_fwd:.2f} s; vjp's forward (solve + "
                  f"linearisation) {t_lin:.2f} s = {t_lin / t_fwd:.2f}x; backward pass {t_bwd:.3f} s = "
                  f"{t_bwd / t_fwd:.3f}x; linearisation + backward beyond the solve "
                  f"{(t_lin - t_fwd + t_bwd) / t_fwd:.2f}x", flush=True)

    # ---- 3. NaN count -------------------------------------------------------------------
    if args.pairs:
        q0, q1 = benchmark_pairs(args.pairs, seed=args.seed + 200)
        t = time.perf_counter()

        def total(g):
            s = jtraj.solve_batch(robot, q0, g, N=args.N, weights=w)
            return jnp.sum(s.T), s

        g, s = jax.grad(total, has_aux=True)(jnp.asarray(q1))
        conv = np.asarray(valid_derivatives(s))
        g = np.asarray(g)
        nan_conv = int(np.isnan(g[conv]).sum())
        print(f"3. {args.pairs} pairs, {time.perf_counter() - t:.0f} s: converged {conv.sum()}; NaN gradient "
              f"entries on converged samples {nan_conv}; on the others {int(np.isnan(g[~conv]).sum())} (zero: "
              f"{int(np.all(g[~conv] == 0))})", flush=True)


if __name__ == "__main__":
    main()
