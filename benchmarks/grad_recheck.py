"""Re-examine the cases of ``bench_grad.py`` part 1 where dT* misses its reference.

    python benchmarks/grad_recheck.py [--json benchmarks/figures/grad_1e-10.json] [--cases weights:34,via:37]
                                      [--tols 1e-10,1e-12] [--out benchmarks/figures/grad_recheck.json]

For each (kind, pair) case (by default: every pair of the run in ``--json`` whose dT*
error exceeds 1e-5, with the same active set within the steps, and three times the
reference's uncertainty) the problem and the direction of that run are rebuilt, and:

- the base optimum is re-solved at tolerances 1e-12 (AL method, warm, 8,000 iterations):
  its status, KKT error and violation are recorded;
- the forward-mode derivative of T and of the cost is taken at the run's base optimum
  (tolerances 1e-10) and at the 1e-12 one, by the stage-wise KKT solve and by the dense
  LU of the same system (``jtraj.implicit.KKT_SOLVE = "dense"``);
- the +-h re-solves (the run's steps) are repeated at each tolerance of ``--tols``,
  warm-started at the 1e-12 base, one problem at a time; for each, its status, KKT error
  and whether its active set (:func:`jtraj.implicit.active_set`, constraint rows and
  bound-held variables) differs from the base's, and how many entries differ;
- the central differences and their Richardson extrapolations (steps h and h / 4) are
  compared with the derivative at the 1e-12 base.

The directions: a kind whose figures carry ``direction_seeding`` drew each pair's
direction from a generator seeded by (seed, kind, pair); a run without it drew them in
sequence from one generator seeded by ``seed``, kind by kind (of the kinds without
``direction_seeding``) and pair by pair (pairs with
a finite derivative at a converged base, recorded in the rows, and pairs with a NaN
derivative, counted), restarted for the path kind, which ran on its own: they are
replayed in that order. The replay is checked: the derivative at the run's base optimum
must equal the recorded one.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.append(os.path.dirname(HERE))
sys.path.append(HERE)


def _default_cases(fd):
    cases = []
    for kind, res in fd["kinds"].items():
        for r in res.get("rows", []):
            t = r.get("T")
            if t and not t["moved"] and t["error"] > 1e-5 and t["error"] > 3 * t["uncertainty"]:
                cases.append((kind, r["pair"]))
    return cases


def _directions(fd, seed, kinds, sizes):
    """{(kind, pair): unit direction} of the run (see the module doc)."""
    dirs, rng = {}, np.random.default_rng(seed)
    for kind in kinds:
        res = fd["kinds"].get(kind)
        if res is None or res.get("direction_seeding"):  # (those are drawn per pair, on demand)
            continue
        if kind == "path":
            rng = np.random.default_rng(seed)
        drawn = {r["pair"] for r in res.get("rows", [])}
        if res["counts"].get("nan_derivative"):
            drawn |= set(res.get("nan_pairs", [32]))
        for ip in sorted(drawn):
            u = rng.standard_normal(sizes[kind])
            dirs[(kind, ip)] = u / np.linalg.norm(u)
    return dirs


def _reference(r):
    """bench_grad's choice of the reference among the Richardson estimates ``r["richardson"]``
    (T): where two successive ones agree best; returns (estimate, uncertainty) or None."""
    R = np.asarray(r["richardson"], float)[:, 0]
    usable = [j for j in range(len(R) - 1) if np.isfinite(R[j]) and np.isfinite(R[j + 1])]
    if not usable:
        return None
    spread = [abs(R[j] - R[j + 1]) for j in usable]
    j = usable[int(np.argmin(spread))]
    return R[j], min(spread)


def table(out, tols):
    """The markdown table of the cases (docs/benchmarks.md)."""
    lines = ["", "| case (kind: pair) | run's error / uncertainty | dT*: stage-wise vs dense LU | base at 1e-12: "
             "KKT error | " + " | ".join(f"re-solves at {t:g}: error / uncertainty" for t in tols)
             + " | active set differs |", "|---" * (5 + len(tols)) + "|"]
    for name, row in out["cases"].items():
        jT, jd = row["jvp"][0], row["jvp_dense"][0]
        cells = []
        moved = False
        for t in tols:
            r = row[f"resolves_{t:g}"]
            moved |= any(any(i["active_set_differs"]) for i in r["resolves"])
            ref = _reference(r)
            cells.append("n/a" if ref is None else f"{abs(ref[0] - jT) / max(abs(ref[0]), 1e-6):.1e} / "
                         f"{ref[1] / max(abs(ref[0]), 1e-6):.1e}")
        rec = row["recorded_T"]
        lines.append(f"| {name.replace(':', ': ')} | {rec['error']:.1e} / {rec['uncertainty']:.1e} | "
                     f"{abs(jT - jd) / abs(jd):.0e} | {row['base_1e-12']['kkt_error']:.0e} | " + " | ".join(cells)
                     + f" | {'yes' if moved else 'no'} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", default=os.path.join(HERE, "figures", "grad_1e-10.json"))
    ap.add_argument("--cases", default="", help="kind:pair,... (default: the misses, see above)")
    ap.add_argument("--tols", default="1e-10,1e-12")
    ap.add_argument("--out", default=os.path.join(HERE, "figures", "grad_recheck.json"))
    ap.add_argument("--table", action="store_true", help="print the table of the figures in --out and exit")
    args = ap.parse_args(argv)
    if args.table:
        print(table(json.load(open(args.out)), [float(t) for t in args.tols.split(",")]))
        return

    import jax

    from jtraj.cli import setup_jax

    setup_jax(x64=True)
    import equinox as eqx
    import jax.numpy as jnp

    import bench_grad as bg
    import jtraj
    from jtraj import implicit
    from jtraj_peers.pairs import benchmark_pairs

    figures = json.load(open(args.json))
    fd, N, seed = figures["fd"], figures["N"], figures["seed"]
    cases = ([(c.split(":")[0], int(c.split(":")[1])) for c in args.cases.split(",") if c]
             or _default_cases(fd))
    tols = [float(t) for t in args.tols.split(",")]
    robot = jtraj.robots.get("serial3")
    w = jtraj.Weights(time=1.0, energy=0.1)

    def al(tol, it=8000):
        return jtraj.AugmentedLagrangian(tol_feasibility=tol, tol_optimality=tol, max_iter=it)

    q0s, q1s = benchmark_pairs(fd["pairs"], seed=seed)
    pk = jtraj.robots.get("pkm2").limits
    pk_lo, pk_hi = np.asarray(pk.q_min), np.asarray(pk.q_max)
    steps = np.asarray(fd["steps"])
    r2 = (steps[0] / steps[1]) ** 2

    def pkm2_pair(i):
        u = np.random.default_rng([seed, i]).uniform(0.2, 0.8, (2, 2))
        return pk_lo + u[0] * (pk_hi - pk_lo), pk_lo + u[1] * (pk_hi - pk_lo)

    def setup(kind, ip):
        free = jtraj.Problem(robot, q0s[ip], q1s[ip], N=N, weights=w)
        free_sol = jtraj.solve(free, solver=al(fd["tol"], 4000))
        return bg._setup(kind, jtraj, robot, q0s[ip], q1s[ip], free, free_sol, N, w, al(fd["tol"], 4000),
                         pkm2_pair(ip))

    out = json.load(open(args.out)) if os.path.exists(args.out) else {}
    out["source"] = os.path.relpath(args.json, os.path.dirname(HERE))
    results = out.setdefault("cases", {})
    recorded = {(k, r["pair"]): r for k, v in fd["kinds"].items() for r in v.get("rows", [])}
    dirs = None
    for kind, ip in cases:
        t0 = time.perf_counter()
        p, base, get, absolute = setup(kind, ip)
        dyn, static = eqx.partition(p, eqx.is_inexact_array)
        leaves, tdef = jax.tree.flatten(get(p))
        n_entries = sum(np.size(v) for v in leaves)
        if fd["kinds"][kind].get("direction_seeding"):
            u = np.random.default_rng([seed, bg.KINDS.index(kind), ip]).standard_normal(n_entries)
            u /= np.linalg.norm(u)
        else:
            if dirs is None:
                dirs = _directions(fd, seed, bg.KINDS, _SIZES)
            u = dirs[(kind, ip)]
        pieces, along = bg.direction_along(leaves, tdef, absolute, u)
        tangent = eqx.tree_at(get, jax.tree.map(jnp.zeros_like, dyn), jax.tree.unflatten(tdef, pieces))

        def jvp_at(b, solver, method=None, static=static, dyn=dyn, tangent=tangent):
            old = implicit.KKT_SOLVE
            implicit.KKT_SOLVE = method
            try:
                def f(d):
                    s = jtraj.solve(eqx.combine(d, static), solver=solver, init=(b.v, b.h))
                    return jnp.stack([s.T, s.cost])
                return np.asarray(jax.jvp(f, (dyn,), (tangent,))[1])
            finally:
                implicit.KKT_SOLVE = old

        row = {"recorded_jvp": recorded[(kind, ip)]["jvp"], "recorded_T": recorded[(kind, ip)]["T"]}
        row["jvp_run_base"] = jvp_at(base, al(fd["tol"], 4000)).tolist()
        row["jvp_run_base_dense"] = jvp_at(base, al(fd["tol"], 4000), "dense").tolist()
        replayed = bool(np.allclose(row["jvp_run_base"], row["recorded_jvp"], rtol=1e-7, atol=0))
        base12 = jtraj.solve(p, solver=al(1e-12), init=(base.v, base.h))
        row["base_1e-12"] = {"status": int(base12.status), "kkt_error": float(base12.kkt_error),
                             "violation": float(base12.max_violation["overall"]),
                             "T_shift": float(base12.T - base.T)}
        row["jvp"] = jvp_at(base12, al(1e-12)).tolist()
        row["jvp_dense"] = jvp_at(base12, al(1e-12), "dense").tolist()
        sig0 = bg._active_signature(p, base12)
        jT = row["jvp"][0]
        for tol in tols:
            vals, info = np.full((len(steps), 2, 2), np.nan), []
            for j, hh in enumerate(steps):
                for k, sgn in enumerate((1.0, -1.0)):
                    ps = eqx.combine(eqx.tree_at(get, dyn, along(sgn * hh)), static)
                    s = jtraj.solve(ps, solver=al(tol), init=(base12.v, base12.h))
                    sig = bg._active_signature(ps, s)
                    diff = [int(np.sum(a != b)) for a, b in zip(sig, sig0)]
                    if int(s.status) == 0:
                        vals[j, k] = [float(s.T), float(s.cost)]
                    info.append({"step": float(hh), "sign": sgn, "status": int(s.status),
                                 "kkt_error": float(s.kkt_error), "active_set_differs": diff})
            D = (vals[:, 0] - vals[:, 1]) / (2 * steps[:, None])
            R = (r2 * D[1:] - D[:-1]) / (r2 - 1)
            row[f"resolves_{tol:g}"] = {"central": D.tolist(), "richardson": R.tolist(), "resolves": info,
                                        "T_error_richardson": (np.abs(R[:, 0] - jT) / abs(jT)).tolist(),
                                        "T_error_central": (np.abs(D[:, 0] - jT) / abs(jT)).tolist()}
        row["replayed"] = replayed
        row["seconds"] = time.perf_counter() - t0
        results[f"{kind}:{ip}"] = row
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)
        print(f"{kind} {ip} ({row['seconds']:.0f} s; direction replayed: {replayed}): base at 1e-12 "
              f"{row['base_1e-12']}", flush=True)
        print(f"   dT*: run's base {row['jvp_run_base'][0]:.10e} (dense {row['jvp_run_base_dense'][0]:.10e}); "
              f"1e-12 base {jT:.10e} (dense {row['jvp_dense'][0]:.10e})", flush=True)
        for tol in tols:
            r = row[f"resolves_{tol:g}"]
            moved = [(i["step"], i["sign"], i["active_set_differs"]) for i in r["resolves"]
                     if any(i["active_set_differs"])]
            bad = [(i["step"], i["sign"], i["status"]) for i in r["resolves"] if i["status"] != 0]
            print(f"   re-solves at {tol:g}: Richardson error " +
                  " ".join(f"{e:.1e}" for e in r["T_error_richardson"]) + "; central " +
                  " ".join(f"{e:.1e}" for e in r["T_error_central"]) +
                  f"; KKT max {max(i['kkt_error'] for i in r['resolves']):.1e}; active set differs {moved}; "
                  f"not converged {bad}", flush=True)
    print(f"figures written to {args.out}")


# the number of differentiated entries of each kind (serial3; pkm2 for the path kind)
_SIZES = dict(q_goal=3, q_start=3, qd_boundary=6, weights=2, weights_UQ=6, masses=6, lengths=6, tau_max=3,
              limits=7, T_max=1, via=3, path=6)

if __name__ == "__main__":
    main()
