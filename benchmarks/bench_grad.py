"""Derivatives through the solve (jtraj.implicit): accuracy, cost and failures.

    python benchmarks/bench_grad.py [--fd-pairs 64] [--time-pairs 64] [--pairs 1024] [--N 20]
                                    [--seed 1] [--step 1e-3] [--sweep 3] [--json PATH]

Measurements on the serial3 benchmark family (time = 1, energy = 0.1, float64):

1. **Agreement with finite differences of re-solves** on ``--fd-pairs`` pairs: for each
   input kind a random unit direction per pair (``--kinds``, default all):

   - ``q_goal``, ``q_start``; ``qd_boundary``: start and goal velocities (0.2 and 0.1 of
     qd_max along the move);
   - ``weights``: time and energy; ``weights_UQ``: explicit diagonal U (the default
     energy term's) and Q (a kinetic term of 0.05);
   - ``masses``: link masses and inertias; ``lengths``: link lengths and centres of mass;
   - ``tau_max``; ``limits``: qd_max (0.8 of the free optimum's peak speed, so that it
     binds), qdd_max and h_max; ``T_max``: a binding bound (0.99 of the free optimum's T);
   - ``via``: the position and tolerance of a via point near the path's middle;
   - ``path``: pkm2 (path constraints: the legs' closure and the distance to its
     singularities) on its own pairs drawn in the middle of its joint box: its q_start,
     q_goal and tau_max.

   Steps are absolute for configurations, velocities and positions, relative to the
   value otherwise. The forward-mode
   derivative (``jax.jvp`` through ``jtraj.solve``, warm-started at the base optimum so
   that it is that optimum's derivative, not another local optimum's) of T and of the cost against central
   differences of warm re-solves (AL method, tolerances 1e-10). Two estimates: the
   central difference with step ``--step / 2`` and its Richardson extrapolation from
   steps ``--step`` and ``--step / 2`` (truncation O(step^4), so a longer step that keeps
   the re-solves' noise, about 1e-9 in T, small against it). Prints the distribution
   (median, 90th percentile, max) of the relative errors per kind and output over the
   pairs whose solves all converged. Where the active set (:func:`jtraj.implicit.active_set`)
   of a shifted re-solve differs from the base optimum's, the differences straddle a
   change of active set and are no reference for the derivative (of the base's active
   set): such pairs are counted per kind, and the errors on the other pairs reported on
   their own. For the ``--sweep`` worst cases among those other pairs, the error against
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

KINDS = ("q_goal", "q_start", "qd_boundary", "weights", "weights_UQ", "masses", "lengths", "tau_max", "limits",
         "T_max", "via", "path")
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


def _setup(kind, jtraj, robot, q0, q1, free, free_sol, N, w, solver, pkm2_pair):
    """The problem of input kind ``kind`` on pair (q0, q1), its converged solution, the
    getter of the differentiated leaves (a tuple of arrays) and, per leaf, whether its
    step is absolute (True) or relative to its value; None where the pair does not give
    a valid, converged problem of that kind."""
    import jax.numpy as jnp

    init = (free_sol.v, free_sol.h)
    p, base = free, free_sol
    if kind == "T_max":  # a binding total-time bound
        p = jtraj.Problem(robot, q0, q1, N=N, weights=w, T_max=0.99 * float(free_sol.T))
    elif kind == "via":  # a passage near the path's middle, off the free path
        mid = np.asarray(free_sol.q)[N // 2]
        p_mid = np.asarray(robot.forward_kinematics(jnp.asarray(mid))) + np.array([0.02, -0.01])
        p = jtraj.Problem(robot, q0, q1, N=N, weights=w,
                          via_points=[jtraj.ViaPoint(point=jnp.asarray(p_mid), tol=jnp.asarray(1e-3))])
    elif kind == "qd_boundary":  # moving start and goal: 0.2 of qd_max along the motion
        d = np.sign(np.asarray(q1) - np.asarray(q0)) * 0.2 * np.asarray(robot.limits.qd_max)
        p = jtraj.Problem(robot, q0, q1, N=N, weights=w, qd_start=d, qd_goal=0.5 * d)
    elif kind == "weights_UQ":  # explicit U (the default energy term's) and Q (a kinetic term)
        U = 0.1 / np.asarray(robot.limits.tau_max) ** 2
        p = jtraj.Problem(robot, q0, q1, N=N, weights=jtraj.Weights(time=1.0, energy=0.1, U=jnp.asarray(U),
                                                                   Q=jnp.asarray(np.full(robot.n, 0.05))))
    elif kind == "limits":  # a velocity bound that binds on the fastest joint; qdd_max, h_max as they are
        qd_peak = float(np.max(np.abs(np.asarray(free_sol.qd))))
        r = jtraj.robots.get("serial3", qd_max=np.full(robot.n, 0.8 * qd_peak))
        p = jtraj.Problem(r, q0, q1, N=N, weights=w)
    elif kind == "path":  # pkm2: path constraints (the legs' closure and the singularity distance)
        r = jtraj.robots.get("pkm2")
        try:
            p = jtraj.Problem(r, pkm2_pair[0], pkm2_pair[1], N=N, weights=w)
        except ValueError:
            return None
        init = None
    if p is not free:
        base = jtraj.solve(p, solver=solver, init=init)
    if not bool(base.converged):
        return None
    get, absolute = {
        "q_goal": (lambda d: (d.q_goal,), (True,)),
        "q_start": (lambda d: (d.q_start,), (True,)),
        "qd_boundary": (lambda d: (d.qd_start, d.qd_goal), (True, True)),
        "weights": (lambda d: (d.weights.time, d.weights.energy), (False, False)),
        "weights_UQ": (lambda d: (d.weights.U, d.weights.Q), (False, False)),
        "masses": (lambda d: (d.robot.masses, d.robot.inertias), (False, False)),
        "lengths": (lambda d: (d.robot.lengths, d.robot.com), (False, False)),
        "tau_max": (lambda d: (d.robot.limits.tau_max,), (False,)),
        "limits": (lambda d: (d.robot.limits.qd_max, d.robot.limits.qdd_max, d.robot.limits.h_max),
                   (False, False, False)),
        "T_max": (lambda d: (d.T_max,), (False,)),
        "via": (lambda d: (d.via_points[0].point, d.via_points[0].tol), (True, False)),
        "path": (lambda d: (d.q_start, d.q_goal, d.robot.limits.tau_max), (True, True, False)),
    }[kind]
    return p, base, get, absolute


def _active_signature(problem, sol):
    """The active set at a solution (:func:`jtraj.implicit.active_set`) as host arrays:
    (active constraint rows, variables held at their lower bound, at their upper bound)."""
    import equinox as eqx

    global _SIGNATURE
    if _SIGNATURE is None:
        import jax.numpy as jnp

        from jtraj import implicit
        from jtraj.transcription import Transcription

        @eqx.filter_jit
        def sig(p, s):
            tr = Transcription("decoupled")
            z = implicit.z_of(p, tr, s)
            act = implicit.active_set(p, tr, z)
            nc = implicit._rows(implicit._nlp(p, tr), z)[0].shape[0]
            rows = jnp.zeros(nc, jnp.int32).at[act.idx].max(act.on.astype(jnp.int32))
            return rows, act.at_lo, act.at_hi

        _SIGNATURE = sig
    return tuple(np.asarray(x) for x in _SIGNATURE(problem, sol))


_SIGNATURE = None


def _table(fd_fig, kinds):
    """The markdown table of part 1 (docs/benchmarks.md) from its figures."""
    lines = ["", "| input kind | pairs | dT*: median / p90 / max | dJ*: median / p90 / max | "
             "central differences alone, max (dT* / dJ*) | active set changes within the step | "
             "max on the other pairs (dT* / dJ*) |", "|---|---|---|---|---|---|---|"]
    for kind in kinds:
        r = [fd_fig[f"{kind}/d{o}"]["richardson"] for o in ("T", "cost")]
        c = [fd_fig[f"{kind}/d{o}"]["central"] for o in ("T", "cost")]
        if r[0] is None:
            lines.append(f"| {kind} | 0 | | | | | |")
            continue
        cells = [" / ".join(f"{st[q]:.1e}" for q in ("median", "p90", "max")) for st in r]
        same = [fd_fig[f"{kind}/d{o}"].get("richardson_same_active") for o in ("T", "cost")]
        n_changed = fd_fig[f"{kind}/dT"].get("active_set_changed")
        ch = "" if n_changed is None else f"{n_changed} of {r[0]['n']}"
        other = " / ".join("n/a" if st is None else f"{st['max']:.1e}" for st in same) if n_changed is not None else ""
        lines.append(f"| {kind} | {r[0]['n']} | {cells[0]} | {cells[1]} | {c[0]['max']:.1e} / {c[1]['max']:.1e} "
                     f"| {ch} | {other} |")
    return "\n".join(lines) + "\n"


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
    ap.add_argument("--table", metavar="JSON", help="print part 1's table from the figures of an earlier run and exit")
    args = ap.parse_args(argv)
    if args.table:
        with open(args.table) as f:
            fig = json.load(f)
        if "fd" in fig:
            fd_fig = fig["fd"]["errors"]
        else:  # a run cut short: the pairs done
            part = fig["fd_partial"]["errors"]
            print(f"(a run cut short: {fig['fd_partial']['pairs_done']} pairs done)")
            fd_fig = {f"{k}/d{o}": {e: part[f"{k}/d{o}/{e}"] for e in ("central", "richardson")}
                      for k in KINDS for o in ("T", "cost") if f"{k}/d{o}/central" in part}
        print(_table(fd_fig, [k for k in KINDS if f"{k}/dT" in fd_fig]))
        return

    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from jtraj.cli import setup_jax

    setup_jax(x64=True)  # float64 and the persistent compilation cache (a rerun loads its programs)
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
    tight = jtraj.AugmentedLagrangian(tol_feasibility=1e-10, tol_optimality=1e-10, max_iter=2000)
    tighter = jtraj.AugmentedLagrangian(tol_feasibility=1e-12, tol_optimality=1e-12, max_iter=4000)
    rng = np.random.default_rng(args.seed)

    # ---- 1. agreement with finite differences -----------------------------------------
    if args.fd_pairs:
        q0s, q1s = benchmark_pairs(args.fd_pairs, seed=args.seed)
        pk = jtraj.robots.get("pkm2").limits
        pk_lo, pk_hi = np.asarray(pk.q_min), np.asarray(pk.q_max)

        def pkm2_pair(i):  # start and goal drawn in the middle 60 % of pkm2's joint box
            u = np.random.default_rng([args.seed, i]).uniform(0.2, 0.8, (2, 2))
            return pk_lo + u[0] * (pk_hi - pk_lo), pk_lo + u[1] * (pk_hi - pk_lo)
        errs = {(k, o, e): [] for k in kinds for o in ("T", "cost") for e in ("central", "richardson")}
        changed = {k: [] for k in kinds}  # per kind and pair: the active set changes within the step
        cases = []  # (error, kind, output, pair index, closure) for the sweep
        skipped, t0 = 0, time.perf_counter()
        failed, unconverged, nan_jvp = {}, {}, {}  # per kind: pairs whose problem raised / did not converge /
        # whose converged optimum has a NaN derivative (left out of the error statistics, counted)
        for ip, (q0, q1) in enumerate(zip(q0s, q1s)):
            try:
                free = jtraj.Problem(robot, q0, q1, N=args.N, weights=w)
            except ValueError:
                skipped += 1
                continue
            free_sol = jtraj.solve(free, solver=tight)
            if not bool(free_sol.converged):
                skipped += 1
                continue
            for kind in kinds:
                try:
                    setup = _setup(kind, jtraj, robot, q0, q1, free, free_sol, args.N, w, tight, pkm2_pair(ip))
                except Exception as err:  # counted and printed: a kind that fails is a finding, not a crash
                    failed[kind] = failed.get(kind, 0) + 1
                    print(f"   pair {ip} {kind}: {type(err).__name__}: {err}"[:400], flush=True)
                    continue
                if setup is None:
                    unconverged[kind] = unconverged.get(kind, 0) + 1
                    continue
                try:
                    p, base, get, absolute = setup
                    dyn, static = eqx.partition(p, eqx.is_inexact_array)
                    zero = jax.tree.map(jnp.zeros_like, dyn)
                    x = get(p)
                    leaves, tdef = jax.tree.flatten(x)
                    flat = np.concatenate([np.ravel(np.asarray(v, float)) for v in leaves])
                    u = rng.standard_normal(flat.size)
                    u /= np.linalg.norm(u)
                    # an absolute step (rad, rad/s, m) for configurations, velocities and positions,
                    # a relative one otherwise
                    scale = np.concatenate([np.ones(np.size(v)) if a else np.abs(np.ravel(np.asarray(v, float)))
                                            for v, a in zip(leaves, absolute)])
                    direction = u * scale
                    pieces, pos = [], 0
                    for v in leaves:
                        pieces.append(jnp.asarray(direction[pos:pos + np.size(v)]).reshape(np.shape(v)))
                        pos += np.size(v)

                    def along(t, leaves=leaves, tdef=tdef, pieces=pieces):
                        return jax.tree.unflatten(tdef, [jnp.asarray(v) + t * d for v, d in zip(leaves, pieces)])

                    tangent = eqx.tree_at(get, zero, jax.tree.unflatten(tdef, pieces))

                    def out_of(d, static=static, base=base):  # at the base optimum: warm from it
                        s = jtraj.solve(eqx.combine(d, static), solver=tight, init=(base.v, base.h))
                        return jnp.stack([s.T, s.cost])

                    _, jvp = jax.jvp(out_of, (dyn,), (tangent,))
                    jvp = np.asarray(jvp)
                    if not np.all(np.isfinite(jvp)):  # a converged base with an invalid derivative
                        nan_jvp[kind] = nan_jvp.get(kind, 0) + 1
                        print(f"   pair {ip} {kind}: NaN derivative at a converged optimum", flush=True)
                        continue

                    def central(step, solver=tight, dyn=dyn, static=static, get=get, along=along, base=base,
                                acts=None):
                        vals = []
                        for sign in (1.0, -1.0):
                            d_ = eqx.tree_at(get, dyn, along(sign * step))
                            s = jtraj.solve(eqx.combine(d_, static), solver=solver, init=(base.v, base.h))
                            if not bool(s.converged):
                                return None
                            vals.append(np.array([float(s.T), float(s.cost)]))
                            if acts is not None:
                                acts.append(_active_signature(eqx.combine(d_, static), s))
                        return (vals[0] - vals[1]) / (2 * step)

                    acts = []
                    d1, d2 = central(args.step, acts=acts), central(args.step / 2, acts=acts)
                    if d1 is None or d2 is None:
                        unconverged[kind] = unconverged.get(kind, 0) + 1
                        continue
                    rich = (4 * d2 - d1) / 3
                    # does the active set of a shifted re-solve differ from the base optimum's?
                    # (then the differences straddle a change of active set: not a reference)
                    sig0 = _active_signature(p, base)
                    moved = any(not all(np.array_equal(a, b) for a, b in zip(sig, sig0)) for sig in acts)
                    changed[kind].append(moved)
                    for i, o in enumerate(("T", "cost")):
                        for name, fd in (("central", d2), ("richardson", rich)):
                            e = abs(jvp[i] - fd[i]) / max(abs(fd[i]), 1e-6)
                            errs[(kind, o, name)].append(e)
                        e = abs(jvp[i] - rich[i]) / max(abs(rich[i]), 1e-6)
                        cases.append((e, kind, o, ip, i, jvp[i], central, moved))
                except Exception as err:  # counted and printed, as above
                    failed[kind] = failed.get(kind, 0) + 1
                    print(f"   pair {ip} {kind}: {type(err).__name__}: {err}"[:400], flush=True)
            print(f"   pair {ip}: {time.perf_counter() - t0:.0f} s", flush=True)
            figures["fd_partial"] = {"pairs_done": ip + 1, "seconds": time.perf_counter() - t0,
                                     "failed": failed, "unconverged": unconverged, "nan_derivative": nan_jvp,
                                     "errors": {f"{k}/d{o}/{e}": _stats(v) for (k, o, e), v in errs.items()},
                                     "active_set_changed": {k: int(np.sum(v)) for k, v in changed.items()}}
            dump()
        elapsed = time.perf_counter() - t0
        print(f"1. finite differences of re-solves, {args.fd_pairs} pairs ({skipped} skipped: invalid or "
              f"not converged), {elapsed:.0f} s; relative errors (central with step {args.step / 2:g}; "
              f"Richardson from {args.step:g} and {args.step / 2:g}):")
        fd_fig = {}
        for kind in kinds:
            for o in ("T", "cost"):
                c, r = _stats(errs[(kind, o, "central")]), _stats(errs[(kind, o, "richardson")])
                moved = np.asarray(changed[kind], bool)
                same = _stats(np.asarray(errs[(kind, o, "richardson")])[~moved]) if moved.size else None
                fd_fig[f"{kind}/d{o}"] = {"central": c, "richardson": r, "active_set_changed": int(moved.sum()),
                                          "richardson_same_active": same}
                print(f"   {kind:8s} d{o:4s} central:    {_fmt(c)}")
                print(f"   {'':8s} {'':5s} Richardson: {_fmt(r)}")
                print(f"   {'':8s} {'':5s} active set changes within the step on {int(moved.sum())} pairs; "
                      f"Richardson on the others: {_fmt(same)}")
        print(_table(fd_fig, kinds))  # the benchmarks page's table (docs/benchmarks.md)
        allr = [e for (k, o, n), v in errs.items() if n == "richardson" for e in v]
        print(f"   all kinds, Richardson: {_fmt(_stats(allr))}; above 1e-5: {int(np.sum(np.asarray(allr) > 1e-5))}")
        figures.pop("fd_partial", None)
        figures["fd"] = {"pairs": args.fd_pairs, "skipped": skipped, "step": args.step, "seconds": elapsed,
                         "errors": fd_fig, "all_richardson": _stats(allr), "failed": failed,
                         "unconverged": unconverged, "nan_derivative": nan_jvp,
                         "above_1e-5": int(np.sum(np.asarray(allr) > 1e-5))}
        # the worst cases: error against the step, and with tighter re-solves
        sweep = []
        # (the worst cases among the pairs whose active set stays: the others' differences are no reference)
        for e, kind, o, ip, i, jv, central, _ in sorted([c for c in cases if not c[-1]],
                                                        key=lambda c: -c[0])[:args.sweep]:
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
