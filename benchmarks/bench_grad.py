"""Derivatives through the solve (jtraj.implicit): accuracy, cost and failures.

    python benchmarks/bench_grad.py [--fd-pairs 64] [--time-pairs 64] [--pairs 1024] [--N 20]
                                    [--seed 1] [--step 1e-3] [--sweep 3] [--json PATH]

Measurements on the serial3 benchmark family (time = 1, energy = 0.1, float64):

1. **Agreement with finite differences of re-solves** on ``--fd-pairs`` pairs: for each
   input kind (q_goal, q_start, the weights time and energy, the link masses, tau_max,
   a binding T_max (0.99 of the free optimum's T), the position and tolerance of a via
   point near the path's middle) a random unit direction per pair, the forward-mode
   derivative (``jax.jvp`` through ``jtraj.solve``) of T and of the cost against central
   differences of warm re-solves (AL method, tolerances 1e-10). Two estimates: the
   central difference with step ``--step / 2`` and its Richardson extrapolation from
   steps ``--step`` and ``--step / 2`` (truncation O(step^4), so a longer step that keeps
   the re-solves' noise, about 1e-9 in T, small against it). Prints the distribution
   (median, 90th percentile, max) of the relative errors per kind and output over the
   pairs whose solves all converged. For the ``--sweep`` worst cases, the error against
   the step (1e-2 ... 1e-6) and against a re-solve tolerance of 1e-12: the evidence on
   whether a miss is the derivative's or the differences' (noise grows as the step
   shrinks, truncation as it grows).
2. **The backward pass of grad(sum of T over a batch)** on ``--time-pairs`` pairs against
   the batched forward solve (``jtraj.solve_batch``, warm): ``jax.vjp`` splits the work
   into the forward part (the solve plus the linearisation: active sets, stage models)
   and the backward part (the transposed tangent: one stage-wise KKT solve per problem);
   both are printed as ratios to the solve.
3. **NaN count** over ``--pairs`` pairs: per-sample gradients of T through
   ``solve_batch`` with the default options; NaN entries on converged samples (the goal
   is 0), and how many samples converged (the others get zero derivatives).

The figures go to ``--json`` (default ``benchmarks/figures/grad.json``). Timings on a
shared CPU are noisy: rerun where a ratio matters.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np

sys.path.append(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root: jtraj_peers

KINDS = ("q_goal", "q_start", "weights", "masses", "tau_max", "T_max", "via")
HERE = os.path.dirname(os.path.abspath(__file__))


def _stats(x):
    x = np.asarray(x, float)
    if x.size == 0:
        return None
    return {"median": float(np.median(x)), "p90": float(np.percentile(x, 90)), "max": float(np.max(x)),
            "n": int(x.size)}


def _fmt(st):
    if st is None:
        return "n/a"
    return f"median {st['median']:.2e}  p90 {st['p90']:.2e}  max {st['max']:.2e}  (n = {st['n']})"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fd-pairs", type=int, default=64)
    ap.add_argument("--time-pairs", type=int, default=64)
    ap.add_argument("--pairs", type=int, default=1024, help="pairs of the NaN count")
    ap.add_argument("--N", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--step", type=float, default=1e-3, help="longer step of the differences (relative)")
    ap.add_argument("--sweep", type=int, default=3, help="worst cases whose error is swept over the step")
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--json", default=os.path.join(HERE, "figures", "grad.json"))
    args = ap.parse_args(argv)

    import equinox as eqx
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import jtraj
    from jtraj.implicit import valid_derivatives
    from jtraj_peers.pairs import benchmark_pairs

    kinds = tuple(k for k in args.kinds.split(",") if k)

    def dump():  # after every part (and every pair of part 1): a cut-short run keeps its figures
        if args.json:
            os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
            with open(args.json, "w") as f:
                json.dump(figures, f, indent=1)

    device = f"{jax.devices()[0].device_kind} ({jax.default_backend()})"
    print(f"jax {jax.__version__} on {device}, N = {args.N}", flush=True)
    figures = {"N": args.N, "seed": args.seed, "device": device, "host": platform.node(),
               "cpu_count": os.cpu_count()}
    robot = jtraj.robots.get("serial3")
    w = jtraj.Weights(time=1.0, energy=0.1)
    tight = jtraj.SolverOptions(tol_feasibility=1e-10, tol_optimality=1e-10, max_iter=2000, method="al")
    tighter = jtraj.SolverOptions(tol_feasibility=1e-12, tol_optimality=1e-12, max_iter=4000, method="al")
    rng = np.random.default_rng(args.seed)

    # ---- 1. agreement with finite differences -----------------------------------------
    if args.fd_pairs:
        q0s, q1s = benchmark_pairs(args.fd_pairs, seed=args.seed)
        errs = {(k, o, e): [] for k in kinds for o in ("T", "cost") for e in ("central", "richardson")}
        cases = []  # (error, kind, output, pair index, closure) for the sweep
        skipped, t0 = 0, time.perf_counter()
        for ip, (q0, q1) in enumerate(zip(q0s, q1s)):
            try:
                free = jtraj.Problem(robot, q0, q1, N=args.N, weights=w)
            except ValueError:
                skipped += 1
                continue
            free_sol = jtraj.solve(free, options=tight)
            if not bool(free_sol.converged):
                skipped += 1
                continue
            for kind in kinds:
                kw = {}
                if kind == "T_max":
                    kw["T_max"] = 0.99 * float(free_sol.T)
                if kind == "via":
                    mid = np.asarray(free_sol.q)[args.N // 2]
                    p_mid = np.asarray(robot.forward_kinematics(jnp.asarray(mid))) + np.array([0.02, -0.01])
                    kw["via_points"] = [jtraj.ViaPoint(point=jnp.asarray(p_mid), tol=jnp.asarray(1e-3))]
                p = jtraj.Problem(robot, q0, q1, N=args.N, weights=w, **kw) if kw else free
                base = jtraj.solve(p, options=tight, init=(free_sol.v, free_sol.h)) if kw else free_sol
                if not bool(base.converged):
                    continue
                dyn, static = eqx.partition(p, eqx.is_inexact_array)
                zero = jax.tree.map(jnp.zeros_like, dyn)
                get = {"q_goal": lambda d: d.q_goal, "q_start": lambda d: d.q_start,
                       "weights": lambda d: (d.weights.time, d.weights.energy),
                       "masses": lambda d: d.robot.masses, "tau_max": lambda d: d.robot.limits.tau_max,
                       "T_max": lambda d: d.T_max,
                       "via": lambda d: (d.via_points[0].point, d.via_points[0].tol)}[kind]
                x = get(p)
                leaves, tdef = jax.tree.flatten(x)
                flat = np.concatenate([np.ravel(np.asarray(v, float)) for v in leaves])
                u = rng.standard_normal(flat.size)
                u /= np.linalg.norm(u)
                # an absolute step (rad, m) for configurations and positions, a relative one otherwise
                absolute = kind in ("q_goal", "q_start")
                scale = np.ones_like(flat) if absolute else np.abs(flat)
                if kind == "via":
                    scale = np.r_[np.ones(flat.size - 1), abs(flat[-1])]
                direction = u * scale
                pieces, pos = [], 0
                for v in leaves:
                    pieces.append(jnp.asarray(direction[pos:pos + np.size(v)]).reshape(np.shape(v)))
                    pos += np.size(v)

                def along(t, leaves=leaves, tdef=tdef, pieces=pieces):
                    return jax.tree.unflatten(tdef, [jnp.asarray(v) + t * d for v, d in zip(leaves, pieces)])

                tangent = eqx.tree_at(get, zero, jax.tree.unflatten(tdef, pieces))

                def out_of(d, static=static):
                    s = jtraj.solve(eqx.combine(d, static), options=tight)
                    return jnp.stack([s.T, s.cost])

                _, jvp = jax.jvp(out_of, (dyn,), (tangent,))
                jvp = np.asarray(jvp)

                def central(step, options=tight, dyn=dyn, static=static, get=get, along=along, base=base):
                    vals = []
                    for sign in (1.0, -1.0):
                        d_ = eqx.tree_at(get, dyn, along(sign * step))
                        s = jtraj.solve(eqx.combine(d_, static), options=options, init=(base.v, base.h))
                        if not bool(s.converged):
                            return None
                        vals.append(np.array([float(s.T), float(s.cost)]))
                    return (vals[0] - vals[1]) / (2 * step)

                d1, d2 = central(args.step), central(args.step / 2)
                if d1 is None or d2 is None:
                    continue
                rich = (4 * d2 - d1) / 3
                for i, o in enumerate(("T", "cost")):
                    for name, fd in (("central", d2), ("richardson", rich)):
                        e = abs(jvp[i] - fd[i]) / max(abs(fd[i]), 1e-6)
                        errs[(kind, o, name)].append(e)
                    e = abs(jvp[i] - rich[i]) / max(abs(rich[i]), 1e-6)
                    cases.append((e, kind, o, ip, i, jvp[i], central))
            figures["fd_partial"] = {"pairs_done": ip + 1, "seconds": time.perf_counter() - t0,
                                     "errors": {f"{k}/d{o}/{e}": _stats(v) for (k, o, e), v in errs.items()}}
            dump()
            if (ip + 1) % 8 == 0:
                print(f"   ... {ip + 1} pairs, {time.perf_counter() - t0:.0f} s", flush=True)
        elapsed = time.perf_counter() - t0
        print(f"1. finite differences of re-solves, {args.fd_pairs} pairs ({skipped} skipped: invalid or "
              f"not converged), {elapsed:.0f} s; relative errors (central with step {args.step / 2:g}; "
              f"Richardson from {args.step:g} and {args.step / 2:g}):")
        fd_fig = {}
        for kind in kinds:
            for o in ("T", "cost"):
                c, r = _stats(errs[(kind, o, "central")]), _stats(errs[(kind, o, "richardson")])
                fd_fig[f"{kind}/d{o}"] = {"central": c, "richardson": r}
                print(f"   {kind:8s} d{o:4s} central:    {_fmt(c)}")
                print(f"   {'':8s} {'':5s} Richardson: {_fmt(r)}")
        allr = [e for (k, o, n), v in errs.items() if n == "richardson" for e in v]
        print(f"   all kinds, Richardson: {_fmt(_stats(allr))}; above 1e-5: {int(np.sum(np.asarray(allr) > 1e-5))}")
        figures.pop("fd_partial", None)
        figures["fd"] = {"pairs": args.fd_pairs, "skipped": skipped, "step": args.step, "seconds": elapsed,
                         "errors": fd_fig, "all_richardson": _stats(allr),
                         "above_1e-5": int(np.sum(np.asarray(allr) > 1e-5))}
        # the worst cases: error against the step, and with tighter re-solves
        sweep = []
        for e, kind, o, ip, i, jv, central in sorted(cases, key=lambda c: -c[0])[:args.sweep]:
            rows = []
            for step in (1e-2, 1e-3, 1e-4, 1e-5, 1e-6):
                fd = central(step)
                rows.append({"step": step, "error": None if fd is None else abs(jv - fd[i]) / max(abs(fd[i]), 1e-6)})
            tight_fd = [central(s, tighter) for s in (args.step, args.step / 2)]
            rt = None
            if all(f is not None for f in tight_fd):
                r_ = (4 * tight_fd[1][i] - tight_fd[0][i]) / 3
                rt = abs(jv - r_) / max(abs(r_), 1e-6)
            sweep.append({"kind": kind, "output": o, "pair": ip, "richardson_error": e, "by_step": rows,
                          "richardson_error_tol_1e-12": rt})
            print(f"   worst: {kind} d{o} pair {ip}: Richardson {e:.2e}; central by step "
                  + ", ".join(f"{r['step']:g}: " + ("n/a" if r["error"] is None else f"{r['error']:.1e}")
                              for r in rows)
                  + "; Richardson with re-solves at 1e-12: " + ("n/a" if rt is None else f"{rt:.1e}"), flush=True)
        figures["fd"]["worst"] = sweep
        dump()

    # ---- 2. backward pass against the batched forward solve -----------------------------
    if args.time_pairs:
        q0, q1 = benchmark_pairs(args.time_pairs, seed=args.seed + 100)

        def total_T(g):
            s = jtraj.solve_batch(robot, q0, g, N=args.N, weights=w)
            return jnp.sum(jnp.where(valid_derivatives(s), s.T, 0.0))

        runs = {}
        for run in ("cold", "warm", "warm2"):
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
            runs[run] = {"forward_solve_s": t_fwd, "vjp_forward_s": t_lin, "backward_s": t_bwd,
                         "backward_ratio": t_bwd / t_fwd, "linearisation_and_backward_ratio":
                         (t_lin - t_fwd + t_bwd) / t_fwd}
            print(f"2. {run}: B = {args.time_pairs}: forward solve {t_fwd:.2f} s; vjp's forward (solve + "
                  f"linearisation) {t_lin:.2f} s = {t_lin / t_fwd:.2f}x; backward pass {t_bwd:.3f} s = "
                  f"{t_bwd / t_fwd:.3f}x; linearisation + backward beyond the solve "
                  f"{(t_lin - t_fwd + t_bwd) / t_fwd:.2f}x", flush=True)
        figures["backward"] = {"batch": args.time_pairs, "runs": runs}
        dump()

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
        nan_other = int(np.isnan(g[~conv]).sum())
        zero_other = bool(np.all(g[~conv] == 0))
        elapsed = time.perf_counter() - t
        print(f"3. {args.pairs} pairs, {elapsed:.0f} s: converged {conv.sum()}; NaN gradient "
              f"entries on converged samples {nan_conv}; on the others {nan_other} (all zero: {zero_other})",
              flush=True)
        figures["nan"] = {"pairs": args.pairs, "converged": int(conv.sum()), "nan_on_converged": nan_conv,
                          "nan_on_others": nan_other, "others_all_zero": zero_other, "seconds": elapsed}

    dump()
    if args.json:
        print(f"figures written to {args.json}")


if __name__ == "__main__":
    main()
