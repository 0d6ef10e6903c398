"""Where a spatial arm's interior-point solve spends its compile and run time, for one
curvature of the dynamics (``SolverOptions.ip_curvature``, :mod:`jtraj.solver.curvature`).

    python benchmarks/profile_spatial.py [--robot panda] [--N 40] [--curvature exact|gauss_newton]
                                         [--pieces] [--iteration] [--no-program] [--tight]
                                         [--opt-level L] [--repeats 3] [--cache DIR] [--json F]
    taskset -c 0 python benchmarks/profile_spatial.py --dataset-chunks 4 [--dataset-batch 64] [--N 40]

One problem of ``bench_spatial``'s family (pair 0 of seed 0 for the panda; for other arms
the same rule on their joint ranges). ``--pieces``: the per-sample functions over the
N + 1 samples, compiled apart (trace+lower s, compile s, HLO instructions, warm run ms):
the stage value, the efforts' Jacobian, and the stage Hessian of the interior-point
model with the chosen curvature. ``--iteration``: the pieces of one interior-point
iteration at the starting point, compiled apart (the Newton model, the KKT solve of the
shift ladder, one trial point of the line search, the whole step). Without ``--no-program``: the interior-point program
of a concrete solve (``jtraj.T.staged_ip_jit``: guess, interior point, light
finish), its compile s and HLO size, then warm solves (best of ``--repeats``) and the
run's iterations, status and cost. ``--dataset-chunks K``: instead, a dataset worker's
pieces: ``jtraj dataset``'s spec for the robot (1,000 pairs, seed 0, chunks of
``--dataset-batch`` pairs) and :func:`jtraj.dataset.build.compute_chunk` on its first K
chunks in this process, each timed (the first includes loading or compiling the
programs), with its sampling time and Newton iterations; run it under ``taskset -c 0``
(one CPU, as the workers). ``--opt-level`` sets XLA's LLVM optimisation level
(default: XLA's own). Run each curvature in its own fresh process.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--robot", default="panda")
    ap.add_argument("--N", type=int, default=40)
    ap.add_argument("--curvature", default="auto", choices=("auto", "exact", "gauss_newton"))
    ap.add_argument("--pieces", action="store_true")
    ap.add_argument("--no-program", action="store_true")
    ap.add_argument("--iteration", action="store_true", help="the pieces of one interior-point iteration")
    ap.add_argument("--tight", action="store_true", help="also solve to tol_optimality 1e-8 (same program)")
    ap.add_argument("--cache", default=None, help="JAX's persistent compilation cache folder")
    ap.add_argument("--opt-level", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--dataset-chunks", type=int, default=0, help="time a dataset worker's first K chunks instead")
    ap.add_argument("--dataset-batch", type=int, default=64)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    if args.dataset_chunks:
        return dataset_chunks(args)
    if args.opt_level is not None:
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_backend_optimization_level={args.opt_level}"

    import jax

    jax.config.update("jax_enable_x64", True)
    if args.cache:
        jax.config.update("jax_compilation_cache_dir", args.cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    import jax.numpy as jnp
    import numpy as np

    import jtraj
    from bench_spatial import WEIGHTS, panda_pairs
    from jtraj import _testing as T
    from jtraj.solver import curvature
    from jtraj._compile import SOLVER_XLA_OPTIONS, supported_options
    from jtraj.transcription import Transcription
    from profile_compile import hlo_ops

    xla = supported_options(SOLVER_XLA_OPTIONS)
    robot = jtraj.robots.get(args.robot)
    q0, q1 = panda_pairs(1, 0, robot.limits.q_min, robot.limits.q_max)
    problem = jtraj.Problem(robot, q0[0], q1[0], N=args.N, weights=jtraj.Weights(**WEIGHTS))
    opts = T.resolve_method(jtraj.SolverOptions(ip_curvature=args.curvature), "decoupled", robot)
    split = T.split_options(opts)
    tr = Transcription("decoupled")
    report = {"robot": args.robot, "N": args.N, "curvature": curvature.resolve(args.curvature, robot),
              "opt_level": args.opt_level}
    print(f"{args.robot}, N = {args.N}, curvature {report['curvature']}, opt level "
          f"{'default' if args.opt_level is None else args.opt_level}", flush=True)

    def measure(name, fn, *a):
        t0 = time.perf_counter()
        lowered = jax.jit(fn).lower(*a)
        t1 = time.perf_counter()
        compiled = lowered.compile(xla)
        t2 = time.perf_counter()
        ops = hlo_ops(compiled.as_text())
        report[name] = {"trace_lower_s": t1 - t0, "compile_s": t2 - t1, "hlo_ops": ops}
        print(f"  {name:24s} trace+lower {t1 - t0:7.2f} s  compile {t2 - t1:7.2f} s  HLO ops {ops:7d}", flush=True)
        return compiled

    def warm(name, compiled, *a, repeats=None):
        best = np.inf
        for _ in range(repeats or args.repeats):
            t0 = time.perf_counter()
            out = jax.block_until_ready(compiled(*a))
            best = min(best, time.perf_counter() - t0)
        report[name]["warm_s"] = best
        print(f"  {name:24s} warm {best * 1e3:9.2f} ms", flush=True)
        return out

    if args.pieces:
        from jtraj.solver import ipm

        def prep(problem, split):
            o = T.TracedOptions(split)
            nlp, state, _ = T.prepare(problem, o, tr, T.initial_guess(problem, o, tr), False)
            st = ipm.init(nlp, state.z)
            return nlp, nlp.W(st.z), ipm.multipliers(nlp, st)

        nlp, W, mult = jax.jit(prep)(problem, split)
        import dataclasses
        lag = dataclasses.replace(nlp, ineq_penalty="lagrangian")
        n = robot.n

        def value(lag, W, mult):
            return jax.vmap(lambda w, sdk, mk: lag._stage_al_parts(w, sdk, mk, 0.0)[0], in_axes=(0, 0, T.stage_axes(mult)))(
                W, lag.sd, T.stage_mult(mult))

        def effort_jac(lag, W):
            def one(w):
                def tau_of(s, acc):
                    return tr.accel_and_tau(problem, s[:n], s[n:], acc)[1]
                return curvature.effort_jacobian(tau_of, w[:2 * n], w[2 * n:3 * n])
            return jax.vmap(one)(W)

        def hessian(lag, W, mult):
            return lag.stage_derivatives(W, mult, jnp.asarray(0.0, W.dtype), efforts=True)

        warm("stage value", measure("stage value", value, lag, W, mult), lag, W, mult, repeats=20)
        warm("effort Jacobian", measure("effort Jacobian", effort_jac, lag, W), lag, W, repeats=20)
        warm("stage Hessian", measure("stage Hessian", hessian, lag, W, mult), lag, W, mult, repeats=20)

    if args.iteration:
        from jtraj.solver import ipm

        def start(problem, split):
            o = T.TracedOptions(split)
            nlp, state, _ = T.prepare(problem, o, tr, T.initial_guess(problem, o, tr), False)
            return nlp, ipm.init(nlp, state.z)

        nlp, st = jax.jit(start)(problem, split)

        def model(nlp, st):
            m, Jg, dgT, p, Ex = T.ipm_model(nlp, st)
            return T.ipm_with_rhs(nlp, st, m, Jg, dgT, p, st.mu), Ex

        m, Ex = warm("ip model", measure("ip model", model, nlp, st), nlp, st, repeats=10)
        shifts = jnp.asarray([0.0, 0.25, 2.0, 16.0])

        def kkt(m, Ex):
            return T.ipm_ladder_directions(m, shifts, Ex.T)

        d, _, _ = warm("ip KKT ladder", measure("ip KKT ladder", kkt, m, Ex), m, Ex, repeats=10)
        dz = d[:, 0, 0]

        def trial(nlp, st, dz):
            return T.ipm_trial(nlp, (st.z, st.s, st.sT, dz, jnp.zeros_like(st.s), jnp.zeros_like(st.sT), st.mu), 0.5)

        warm("ip trial point", measure("ip trial point", trial, nlp, st, dz), nlp, st, dz, repeats=10)

        def whole(nlp, st):
            return ipm.step(nlp, st, ipm.Tolerances(1e-6))

        warm("ip step (whole)", measure("ip step (whole)", whole, nlp, st), nlp, st, repeats=10)

    if not args.no_program:

        yes, no = np.bool_(True), np.bool_(False)
        init = T.placeholder_init(problem.N, robot.n)

        def ip_program(problem, split, init):
            return T.staged_ip_jit.__wrapped__(problem, T.TracedOptions(split), "decoupled", init, no, yes)

        compiled = measure("interior-point program", ip_program, problem, split, init)
        sol, decided, it = warm("interior-point program", compiled, problem, split, init)
        report["solve"] = {"decided": bool(decided), "ip_iterations": int(it), "converged": bool(sol.converged),
                           "status": int(sol.status), "cost": float(sol.cost), "T": float(np.sum(sol.h))}
        print(f"  solve: decided {bool(decided)}, converged {bool(sol.converged)}, interior-point iterations "
              f"{int(it)}, cost {float(sol.cost):.8f}, T {float(np.sum(sol.h)):.6f} s", flush=True)
        if args.tight:
            tight = T.split_options(T.resolve_method(jtraj.SolverOptions(
                ip_curvature=args.curvature, tol_optimality=1e-8, ip_compl_tol=1e-8), "decoupled", robot))
            sol_t, decided_t, it_t = compiled(problem, tight, init)
            report["tight"] = {"decided": bool(decided_t), "ip_iterations": int(it_t), "converged": bool(sol_t.converged),
                               "cost": float(sol_t.cost), "T": float(np.sum(sol_t.h))}
            print(f"  tight (tol_optimality 1e-8): decided {bool(decided_t)}, iterations {int(it_t)}, cost "
                  f"{float(sol_t.cost):.8f}, T {float(np.sum(sol_t.h)):.6f} s", flush=True)
        if not bool(decided):
            t0 = time.perf_counter()
            full = jtraj.solve(problem, solver=jtraj.Auto(ipm=jtraj.IPM(curvature=args.curvature)))
            print(f"  undecided: jtraj.solve with the AL fallback {time.perf_counter() - t0:.1f} s, converged "
                  f"{bool(full.converged)}, iterations {int(full.iterations)}, cost {float(full.cost):.8f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=2)
    return report


def dataset_chunks(args):
    """``--dataset-chunks``: see the module docstring."""
    import importlib

    t0 = time.perf_counter()

    from jtraj._setup import setup_jax

    setup_jax()
    from jtraj import dataset
    from jtraj.dataset import sampling

    build = importlib.import_module("jtraj.dataset.build")
    spec = dataset.make_spec(args.robot, 1000, 0, N=args.N, batch=args.dataset_batch)
    robot = spec.robot_model()
    print(f"{args.robot}, N = {args.N}, chunks of {spec.batch} pairs, h_max {float(robot.limits.h_max):g} s; "
          f"import and spec {time.perf_counter() - t0:.2f} s", flush=True)
    report = {"robot": args.robot, "N": args.N, "batch": spec.batch, "chunks": []}
    for c in range(args.dataset_chunks):
        start, stop = spec.chunk_range(c)
        t1 = time.perf_counter()
        sampling.sample_pairs(robot, spec.distribution, spec.seed, start, stop)
        t2 = time.perf_counter()
        out = build.compute_chunk(spec, c)
        t3 = time.perf_counter()
        it = out["iterations"]
        report["chunks"].append({"sample_s": t2 - t1, "chunk_s": t3 - t2, "pairs_per_s": (stop - start) / (t3 - t2),
                                 "iterations_mean": float(it.mean()), "iterations_max": int(it.max()),
                                 "converged": int(out["converged"].sum())})
        print(f"  chunk {c}: sampling {t2 - t1:.3f} s, compute_chunk {t3 - t2:.2f} s ({(stop - start) / (t3 - t2):.2f} "
              f"pairs/s), Newton iterations mean {it.mean():.1f} max {it.max()}, converged "
              f"{int(out['converged'].sum())}/{stop - start}", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=2)
    return report


if __name__ == "__main__":
    main()
