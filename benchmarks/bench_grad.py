"""Derivatives through the solve (jtraj.implicit): accuracy, cost and failures.

    python benchmarks/bench_grad.py [--fd-pairs 64] [--time-pairs 64] [--pairs 1024] [--N 20]
                                    [--seed 1] [--step 4e-3] [--steps 4] [--ratio 4] [--tol 1e-12]
                                    [--kinds ...] [--pairs-list 3,17,...] [--json PATH] [--table JSON]

Measurements on the serial3 benchmark family (time = 1, energy = 0.1, float64):

1. **Agreement with finite differences of re-solves** on ``--fd-pairs`` pairs (or the
   pairs of ``--pairs-list`` among them): for each input kind (``--kinds``, default all)
   a random unit direction per pair, drawn from a generator seeded by (``--seed``, the
   kind, the pair), so that a run of some kinds or pairs repeats those of a full run:

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
   value otherwise. The forward-mode derivative (``jax.jvp`` through ``jtraj.solve``,
   warm-started at the base optimum so that it is that optimum's derivative, not another
   local optimum's) of T and of the cost against central differences of re-solves
   warm-started at the base optimum (AL method, tolerances ``--tol``, 1e-12 by default:
   T is not stationary in the parameters, so the re-solves' error enters its differences
   to first order; at tolerances 1e-10 it is systematic, common to neighbouring steps,
   and reaches 1e-4 relative on derivatives of T of 1e-4 while the successive
   Richardson estimates still agree; the largest KKT error of the re-solves used is
   reported per kind). All pairs' shifted
   problems of a kind (``--steps`` steps from ``--step`` down, each ``--ratio`` times
   shorter, both signs) are solved in ONE batch (a batched ``Problem`` whose every leaf,
   the robot's and the weights' included, carries the batch axis, by the lane driver of
   :func:`jtraj.solver.lanes.solve_problems`); a re-solve that stops short of the
   tolerance there is solved again on its own, from the base at 1e-10 and then at
   ``--tol`` (counted: ``resolved_alone``, ``resolve_not_converged``). The reference is a Richardson
   extrapolation: from steps h and h / ratio, ``(ratio^2 D(h / ratio) - D(h)) /
   (ratio^2 - 1)`` (truncation O(h^4)); its step is chosen per pair and output where two
   successive Richardson estimates agree best (noise grows as the step shrinks,
   truncation as it grows; the choice never looks at the derivative under test), and the
   disagreement of the two is reported as the reference's uncertainty. Where the active
   set (:func:`jtraj.implicit.active_set`) of a shifted re-solve used by the reference
   differs from the base optimum's, the differences straddle a change of active set and
   are no reference for the derivative (of the base's active set): such pairs are
   counted per kind and reported apart. Prints the distribution (median, 90th
   percentile, max) of the relative errors per kind and output.
2. **The backward pass of grad(sum of T over a batch)** on ``--time-pairs`` pairs against
   the batched forward solve (``jtraj.solve_batch``, warm): ``jax.vjp`` splits the work
   into the forward part (the solve plus the linearisation: active sets, stage models)
   and the backward part (the transposed tangent: one stage-wise KKT solve per problem);
   both are printed as ratios to the solve.
3. **NaN count** over ``--pairs`` pairs: per-sample gradients of T through
   ``solve_batch`` with the default options; NaN entries on converged samples (the goal
   is 0), how many samples converged, and how many of those report
   ``Status.CONVERGED_NO_DERIVATIVE`` (a derivative not valid after refinement); the
   samples without a valid derivative get zero derivatives.

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


def _signature(p, s):
    """The active set at a solution (:func:`jtraj.implicit.active_set`): (active
    constraint rows, variables held at their lower bound, at their upper bound)."""
    import jax.numpy as jnp

    from jtraj import implicit
    from jtraj.transcription import Transcription

    tr = Transcription("decoupled")
    z = implicit.z_of(p, tr, s)
    act = implicit.active_set(p, tr, z)
    nc = implicit._rows(implicit._nlp(p, tr), z)[0].shape[0]
    rows = jnp.zeros(nc, jnp.int32).at[act.idx].max(act.on.astype(jnp.int32))
    return rows, act.at_lo, act.at_hi


_PROGRAMS = {}


def _active_signature(problem, sol):
    """:func:`_signature` as host arrays."""
    import equinox as eqx

    run = _PROGRAMS.setdefault("one", eqx.filter_jit(_signature))
    return tuple(np.asarray(x) for x in run(problem, sol))


def _signatures(batch, sols):
    """:func:`_signature` of every problem of a batch (one vmapped program)."""
    import equinox as eqx

    run = _PROGRAMS.setdefault("batch", eqx.filter_jit(eqx.filter_vmap(_signature)))
    return tuple(np.asarray(x) for x in run(batch, sols))


def _table(fig, kinds):
    """The markdown table of part 1 (docs/benchmarks.md) from its figures."""
    lines = ["", "| input kind | tolerances | pairs | active set changes within the steps | dT*: median / p90 / max | "
             "dJ*: median / p90 / max | reference uncertainty, max (dT* / dJ*) | above 1e-5 (dT* / dJ*) | "
             "all pairs, max (dT* / dJ*) |", "|---|---|---|---|---|---|---|---|---|"]
    for kind in kinds:
        res = fig["kinds"].get(kind)
        if res is None or "dT" not in res:
            lines.append(f"| {kind} | | 0 | | | | | | |")
            continue
        T, C = res["dT"], res["dcost"]
        n = max(T["pairs"], C["pairs"])
        moved = max(T["moved"], C["moved"])
        cell = lambda st: "n/a" if st is None else " / ".join(f"{st[q]:.1e}" for q in ("median", "p90", "max"))  # noqa: E731
        mx = lambda st: "n/a" if st is None else f"{st['max']:.1e}"  # noqa: E731
        lines.append(f"| {kind} | {res.get('tol', fig.get('tol')):g} | {n} | {moved} of {n} ({100 * moved / max(n, 1):.0f} %) | {cell(T['same_active'])} | "
                     f"{cell(C['same_active'])} | {mx(T['uncertainty_same_active'])} / "
                     f"{mx(C['uncertainty_same_active'])} | {T['above_1e-5_same_active']} / "
                     f"{C['above_1e-5_same_active']} | {mx(T['all'])} / {mx(C['all'])} |")
    return "\n".join(lines) + "\n"


def _fd_part(args, jtraj, robot, w, tight, kinds, figures, dump):
    """Part 1: the derivatives against finite differences of batched re-solves (see the
    module doc); fills ``figures["fd"]``."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from jtraj.solver.core import resolve_method
    from jtraj.solver.lanes import solve_problems
    from jtraj.solver.options import to_options
    from jtraj_peers.pairs import benchmark_pairs

    q0s, q1s = benchmark_pairs(args.fd_pairs, seed=args.seed)
    pk = jtraj.robots.get("pkm2").limits
    pk_lo, pk_hi = np.asarray(pk.q_min), np.asarray(pk.q_max)
    steps = args.step * args.ratio ** -np.arange(args.steps, dtype=float)  # h_0 > h_1 > ...
    r2 = args.ratio**2

    def pkm2_pair(i):  # start and goal drawn in the middle 60 % of pkm2's joint box
        u = np.random.default_rng([args.seed, i]).uniform(0.2, 0.8, (2, 2))
        return pk_lo + u[0] * (pk_hi - pk_lo), pk_lo + u[1] * (pk_hi - pk_lo)

    t0 = time.perf_counter()
    # the free optima of every pair: one batched solve (pairs refused on their face: INVALID_INPUT)
    free_all = jtraj.solve_batch(robot, q0s, q1s, N=args.N, weights=w, solver=tight)
    chosen = {int(x) for x in args.pairs_list.split(",") if x.strip()} or set(range(args.fd_pairs))
    # (the kinds not run keep their figures of an earlier run: each kind records its own tolerance)
    fig = {"pairs": args.fd_pairs, "pairs_list": sorted(chosen), "steps": steps.tolist(), "tol": args.tol,
           "direction_seeding": "per (seed, kind, pair)",
           "kinds": dict(figures.get("fd", {}).get("kinds", {})),
           "load_average": os.getloadavg()[0]}  # (the date goes beside the table on docs/benchmarks.md)
    for kind in kinds:
        tk = time.perf_counter()
        counts = {"setup_failed": 0, "not_converged": 0, "nan_derivative": 0, "resolve_failed": 0}
        entries = []  # per pair: (pair, problem, base, dyn, static, get, along, jvp)
        for ip, (q0, q1) in enumerate(zip(q0s, q1s)):
            if ip not in chosen:
                continue
            free_sol = jax.tree.map(lambda x, ip=ip: x[ip], free_all)
            if int(free_sol.status) != 0:
                counts["not_converged"] += 1
                continue
            try:
                free = jtraj.Problem(robot, q0, q1, N=args.N, weights=w)
                setup = _setup(kind, jtraj, robot, q0, q1, free, free_sol, args.N, w, tight, pkm2_pair(ip))
            except Exception as err:  # counted and printed: a kind that fails is a finding, not a crash
                counts["setup_failed"] += 1
                print(f"   pair {ip} {kind}: {type(err).__name__}: {err}"[:300], flush=True)
                continue
            if setup is None:
                counts["not_converged"] += 1
                continue
            p, base, get, absolute = setup
            dyn, static = eqx.partition(p, eqx.is_inexact_array)
            leaves, tdef = jax.tree.flatten(get(p))
            flat = np.concatenate([np.ravel(np.asarray(v, float)) for v in leaves])
            u = np.random.default_rng([args.seed, KINDS.index(kind), ip]).standard_normal(flat.size)
            u /= np.linalg.norm(u)
            # an absolute step (rad, rad/s, m) for configurations, velocities and positions,
            # a relative one otherwise
            pieces, along = direction_along(leaves, tdef, absolute, u)
            tangent = eqx.tree_at(get, jax.tree.map(jnp.zeros_like, dyn), jax.tree.unflatten(tdef, pieces))

            def out_of(d, static=static, base=base):  # warm at the base optimum: its derivative
                s = jtraj.solve(eqx.combine(d, static), solver=tight, init=(base.v, base.h))
                return jnp.stack([s.T, s.cost]), s.status

            _, jvp, status = jax.jvp(out_of, (dyn,), (tangent,), has_aux=True)
            jvp = np.asarray(jvp)
            if int(status) not in (0, 7):  # the solve warm at the base stops short of --tol
                counts["warm_base_not_converged"] = counts.get("warm_base_not_converged", 0) + 1
                print(f"   pair {ip} {kind}: the solve warm at the base optimum ends with status {int(status)}",
                      flush=True)
                continue
            if not np.all(np.isfinite(jvp)):  # a converged base with an invalid derivative
                counts["nan_derivative"] += 1
                print(f"   pair {ip} {kind}: NaN derivative at a converged optimum", flush=True)
                continue
            entries.append((ip, p, base, dyn, static, get, along, jvp))
        if not entries:
            fig["kinds"][kind] = {"counts": counts}
            continue
        # every pair's shifted problems (steps x signs) in one batched solve, warm at the base
        shifted, inits = [], []
        for ip, p, base, dyn, static, get, along, jvp in entries:
            for h in steps:
                for sign in (1.0, -1.0):
                    shifted.append(eqx.combine(eqx.tree_at(get, dyn, along(sign * h)), static))
                    inits.append((base.v, base.h))
        stack = lambda *xs: jnp.stack(xs)  # noqa: E731
        batch = jax.tree.map(stack, *shifted)
        init = jax.tree.map(stack, *inits)
        opts = resolve_method(to_options(tight), "decoupled", entries[0][1].robot)
        ts = time.perf_counter()
        sols = solve_problems(batch, opts, "decoupled", init, True, args.slots, 10)
        t_solve = time.perf_counter() - ts
        sig = [np.array(x) for x in _signatures(batch, sols)]
        T_, C_ = np.array(sols.T), np.array(sols.cost)
        status, kkt_ = np.array(sols.status), np.array(sols.kkt_error)
        # a re-solve that stops short of the tolerance in the batch is solved again on its
        # own, in two stages from the base (tolerances 1e-10, then --tol): the same
        # problem, a longer path to the tolerance
        loose = jtraj.AugmentedLagrangian(tol_feasibility=max(args.tol, 1e-10), tol_optimality=max(args.tol, 1e-10),
                                          max_iter=args.max_iter)
        retried = np.flatnonzero(status != 0)
        for i in retried:
            b0 = entries[i // (2 * len(steps))][2]
            s1 = jtraj.solve(shifted[i], solver=loose, init=(b0.v, b0.h))
            s2 = jtraj.solve(shifted[i], solver=tight, init=(s1.v, s1.h))
            T_[i], C_[i], status[i], kkt_[i] = float(s2.T), float(s2.cost), int(s2.status), float(s2.kkt_error)
            for a, b in zip(sig, _active_signature(shifted[i], s2)):
                a[i] = b
        counts["resolved_alone"] = int(np.sum(status[retried] == 0))
        counts["resolve_not_converged"] = int(np.sum(status != 0))
        out = np.stack([T_, C_], axis=1).reshape(len(entries), len(steps), 2, 2)
        ok = (status == 0).reshape(len(entries), len(steps), 2)
        kkt = kkt_.reshape(len(entries), len(steps), 2)
        rows = []
        for e, (ip, p, base, dyn, static, get, along, jvp) in enumerate(entries):
            sig0 = _active_signature(p, base)
            moved = np.array([[not all(np.array_equal(a[(e * len(steps) + j) * 2 + k], b) for a, b in zip(sig, sig0))
                               for k in range(2)] for j in range(len(steps))])
            D = (out[e, :, 0] - out[e, :, 1]) / (2 * steps[:, None])  # (steps, outputs) central differences
            R = (r2 * D[1:] - D[:-1]) / (r2 - 1)  # Richardson from steps j and j+1
            good = ok[e].all(axis=1)
            row = {"pair": ip, "jvp": jvp.tolist(), "kkt_max": float(np.max(np.where(ok[e], kkt[e], 0.0)))}
            for i, o in enumerate(("T", "cost")):
                # the step: where two successive Richardson estimates (from converged re-solves)
                # agree best; the reference is the first of the two, the disagreement its
                # uncertainty (chosen without looking at the derivative under test)
                usable = [j for j in range(len(steps) - 2) if good[j:j + 3].all()]
                if not usable:
                    row[o] = None
                    continue
                spread = np.array([abs(R[j, i] - R[j + 1, i]) for j in usable])
                j = usable[int(np.argmin(spread))]
                ref = R[j, i]
                denom = max(abs(ref), 1e-6)
                row[o] = {"error": abs(jvp[i] - ref) / denom, "uncertainty": float(spread.min()) / denom,
                          "step": float(steps[j]), "moved": bool(moved[j:j + 3].any()),
                          "central": abs(jvp[i] - D[1, i]) / max(abs(D[1, i]), 1e-6) if good[1] else None}
            if row["T"] is None and row["cost"] is None:
                counts["resolve_failed"] += 1
            rows.append(row)
        res = {"counts": counts, "seconds": time.perf_counter() - tk, "resolve_seconds": t_solve,
               "resolves": len(shifted), "tol": args.tol, "direction_seeding": fig["direction_seeding"],
               "resolves_kkt_max": float(np.max(np.where(ok, kkt, 0.0))), "rows": rows}
        for o in ("T", "cost"):
            rs = [r[o] for r in rows if r[o] is not None]
            same = [r for r in rs if not r["moved"]]
            res[f"d{o}"] = {"all": _stats([r["error"] for r in rs]), "same_active": _stats([r["error"] for r in same]),
                            "uncertainty_same_active": _stats([r["uncertainty"] for r in same]),
                            "central_all": _stats([r["central"] for r in rs if r["central"] is not None]),
                            "pairs": len(rs), "moved": len(rs) - len(same),
                            "above_1e-5_same_active": int(sum(r["error"] > 1e-5 for r in same))}
        fig["kinds"][kind] = res
        print(f"   {kind}: {len(entries)} pairs, {len(shifted)} re-solves in {t_solve:.0f} s "
              f"({time.perf_counter() - tk:.0f} s in all), largest KKT error of the converged re-solves "
              f"{res['resolves_kkt_max']:.1e}; {counts}", flush=True)
        for o in ("T", "cost"):
            r = res[f"d{o}"]
            print(f"      d{o}: same active set ({r['pairs'] - r['moved']} pairs): {_fmt(r['same_active'])}; "
                  f"reference uncertainty {_fmt(r['uncertainty_same_active'])}; active set changes on "
                  f"{r['moved']} of {r['pairs']}; all pairs {_fmt(r['all'])}", flush=True)
        fig["seconds"] = time.perf_counter() - t0
        figures["fd"] = fig
        dump()
    print(_table(fig, kinds))
    fig["seconds"] = time.perf_counter() - t0
    figures["fd"] = fig
    dump()


def direction_along(leaves, tdef, absolute, u):
    """The direction of unit vector ``u`` over the input's ``leaves`` (an absolute step for
    configurations, velocities and positions, ``absolute``; a relative one otherwise), as
    arrays shaped like the leaves, and ``along(t)``: the input moved by ``t`` along it."""
    import jax
    import jax.numpy as jnp

    scale = np.concatenate([np.ones(np.size(v)) if a else np.abs(np.ravel(np.asarray(v, float)))
                            for v, a in zip(leaves, absolute)])
    direction, pieces, pos = u * scale, [], 0
    for v in leaves:
        pieces.append(jnp.asarray(direction[pos:pos + np.size(v)]).reshape(np.shape(v)))
        pos += np.size(v)

    def along(t):
        return jax.tree.unflatten(tdef, [jnp.asarray(v) + t * d for v, d in zip(leaves, pieces)])
    return pieces, along


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fd-pairs", type=int, default=64)
    ap.add_argument("--time-pairs", type=int, default=64)
    ap.add_argument("--pairs", type=int, default=1024, help="pairs of the NaN count")
    ap.add_argument("--N", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--step", type=float, default=4e-3, help="the longest step of the differences")
    ap.add_argument("--steps", type=int, default=4, help="steps of the differences, each --ratio times shorter")
    ap.add_argument("--ratio", type=float, default=4.0)
    ap.add_argument("--tol", type=float, default=1e-12, help="the re-solves' (and base solves') AL tolerances")
    ap.add_argument("--max-iter", type=int, default=8000, help="the re-solves' (and base solves') iteration limit")
    ap.add_argument("--pairs-list", default="", help="part 1 on these pairs only (comma-separated indices)")
    ap.add_argument("--slots", type=int, default=16, help="lanes of the batched re-solves")
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--json", default=os.path.join(HERE, "figures", "grad.json"))
    ap.add_argument("--table", metavar="JSON", help="print part 1's table from the figures of an earlier run and exit")
    args = ap.parse_args(argv)
    if args.table:
        with open(args.table) as f:
            fig = json.load(f)["fd"]
        print(_table(fig, [k for k in KINDS if k in fig["kinds"]]))
        return

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
    figures = {}
    if args.json and os.path.exists(args.json):  # the parts not run keep their figures
        with open(args.json) as f:
            figures = json.load(f)
    figures.update({"N": args.N, "seed": args.seed, "device": device, "host": platform.node(),
                    "cpu_count": os.cpu_count()})
    robot = jtraj.robots.get("serial3")
    w = jtraj.Weights(time=1.0, energy=0.1)
    tight = jtraj.AugmentedLagrangian(tol_feasibility=args.tol, tol_optimality=args.tol, max_iter=args.max_iter)

    # ---- 1. agreement with finite differences -----------------------------------------
    if args.fd_pairs:
        _fd_part(args, jtraj, robot, w, tight, kinds, figures, dump)

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
        conv = np.asarray(s.converged)  # CONVERGED or CONVERGED_NO_DERIVATIVE
        valid = np.asarray(valid_derivatives(s))
        no_derivative = conv & ~valid  # converged, derivative not valid after refinement: zero
        g = np.asarray(g)
        nan_conv = int(np.isnan(g[conv]).sum())
        nan_other = int(np.isnan(g[~valid]).sum())
        zero_other = bool(np.all(g[~valid] == 0))
        elapsed = time.perf_counter() - t
        print(f"3. {args.pairs} pairs, {elapsed:.0f} s: converged {conv.sum()}, of which "
              f"{no_derivative.sum()} without a valid derivative (CONVERGED_NO_DERIVATIVE); NaN gradient entries "
              f"on converged samples {nan_conv}; on the samples without a valid derivative {nan_other} "
              f"(all zero: {zero_other})", flush=True)
        figures["nan"] = {"pairs": args.pairs, "converged": int(conv.sum()), "valid": int(valid.sum()),
                          "converged_no_derivative": int(no_derivative.sum()), "nan_on_converged": nan_conv,
                          "nan_on_invalid": nan_other, "invalid_all_zero": zero_other, "seconds": elapsed}

    dump()
    if args.json:
        print(f"figures written to {args.json}")


if __name__ == "__main__":
    main()
