"""Exact refinement warm-started by the ANFIS planner vs the default cycloidal start.

    .venv/bin/python benchmarks/bench_refine.py --data DATASET [--model PLAN.anfis]
        [--rules R] [--order 0|1] [--pairs 100] [--fresh-seed S] [--knn] [--primal] [--closed]
        [--json out.json]

Figures in docs/benchmarks.md (warm starts from a plan): ``--order 0 --pairs 100 --knn --primal`` on
``jtraj dataset --robot serial3 --pairs 300 --seed 2``.

Issue #6 item 5. The planner model (mapping ``plan``) is trained here on the dataset's
training split (``jtraj.mappings.train_mapping``; ``--rules``, ``--epochs``,
``--order``, ``--ridge``)
unless ``--model`` is given. Held-out pairs: the test split of the dataset (the last
10 % of its converged trajectories, never seen in training), topped up to ``--pairs``
with fresh pairs drawn from the dataset's own sampling law with seed ``--fresh-seed``
(default: the dataset's seed + 1000; also never seen) when the test split is smaller.

For every pair ``jtraj.solve`` runs on the dataset's problem (robot, N, weights,
default ``SolverOptions``) twice, in alternating order: warm-started from the planner's
``(v, h)`` (``init=``) and from the default cycloidal guess; with ``--knn`` also from
the ``(v, h)`` of the training trajectory whose (q_start, q_goal) is nearest (a
lookup baseline for the warm start); with ``--closed`` also from the closed-loop
planner (a nefotc controller and a nefumop period model, ``jtraj train`` defaults,
trained here on the same split: ``closed``); with ``--primal`` each warm start also once with
its primal point only (``*_primal``: multipliers zero and ``penalty_init`` as in a cold
start, whereas ``jtraj.solve(init=...)`` also estimates multipliers and starts the
penalty at ``penalty_max / 100``, which assumes the guess is near an optimum).
Compilation is excluded (one untimed solve of
each kind first). Printed: success rates (strict ``converged``; and ``converged or
FEASIBLE_NOT_OPTIMAL``), Newton iterations and wall time (mean, median; ratios
warm / cold), and the final cost difference where both converged.
"""

from __future__ import annotations

import argparse
import json
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402


def _solve(prob, init, solver, primal_only=False):
    import jtraj

    t0 = time.perf_counter()
    # primal_only: the warm start's primal point with cold multipliers and penalty
    sol = jtraj.solve(prob, init=init, solver=solver, warm="primal" if primal_only else "full")
    jax.block_until_ready(sol.status)
    dt = time.perf_counter() - t0
    st = int(np.asarray(sol.status))
    return dict(status=st, converged=bool(np.asarray(sol.converged)), feasible=st in (0, 2),
                iterations=int(np.asarray(sol.iterations)), seconds=dt, cost=float(np.asarray(sol.cost)),
                T=float(np.asarray(sol.T)))


def _stats(rows, key):
    a = np.array([r[key] for r in rows], float)
    return dict(mean=float(a.mean()), median=float(np.median(a)), sum=float(a.sum()))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="dataset directory (jtraj dataset --out ...)")
    ap.add_argument("--model", help="planner model (jtraj train --mapping plan); default: train one here")
    ap.add_argument("--rules", type=int, default=None, help="rules of the planner trained here")
    ap.add_argument("--epochs", type=int, default=100)
    ap.add_argument("--order", type=int, default=1, choices=[0, 1], help="Sugeno order of the planner trained here")
    ap.add_argument("--ridge", type=float, default=1e-6, help="relative ridge of the planner trained here")
    ap.add_argument("--pairs", type=int, default=100, help="held-out pairs to solve (at most)")
    ap.add_argument("--fresh-seed", type=int, default=None)
    ap.add_argument("--knn", action="store_true", help="also warm-start from the nearest training trajectory")
    ap.add_argument("--primal", action="store_true",
                    help="also warm-start with the primal point only (multipliers and penalty as for a cold "
                         "start: jtraj.solve(..., warm='primal'))")
    ap.add_argument("--closed", action="store_true",
                    help="also warm-start from the closed-loop planner (nefotc + nefumop models trained here)")
    ap.add_argument("--json", help="write per-pair results and the summary")
    args = ap.parse_args(argv)

    import jtraj
    from jtraj import anfis, dataset
    from jtraj import mappings
    from jtraj.dataset import sampling
    from jtraj.online import Planner

    data = dataset.load(args.data)
    meta = data["metadata"]
    robot = jtraj.robots.from_metadata(meta)  # with the dataset's period bound; a URDF arm from its text
    N = int(meta["N"])
    weights = jtraj.Weights.parse(meta.get("weights_text", "time=1,energy=0.1"))
    solver = jtraj.Auto()

    X, Y, traj, _, _ = mappings.view(data, "plan")
    tr, te = mappings.split(traj)
    if args.model:
        model = anfis.load(args.model, mapping="plan")
        print(f"planner: {args.model} ({model.n_rules} rules)")
    else:
        t0 = time.perf_counter()
        model, rep, _ = mappings.train_mapping(data, "plan", n_rules=args.rules, epochs=args.epochs,
                                                      order=args.order, ridge=args.ridge)
        print(f"planner trained here: {rep['n_rules']} rules, {rep['epochs']} epochs, {time.perf_counter() - t0:.1f} s;"
              f" test RMSE {rep['test_rmse']:.4g} (linear {rep['linear_test_rmse']:.4g}, "
              f"5-NN {rep['knn_test_rmse']:.4g})")
    planner = Planner(model, robot)
    closed = None
    if args.closed:
        t0 = time.perf_counter()
        ctl, rc, _ = mappings.train_mapping(data, "nefotc")
        per, rp, _ = mappings.train_mapping(data, "nefumop")
        closed = Planner(ctl, robot, periods=per)
        print(f"closed-loop planner trained here: nefotc {rc['n_rules']} rules (ratio to linear "
              f"{rc['ratio_to_linear']:.3f}), nefumop {rp['n_rules']} rules ({rp['ratio_to_linear']:.3f}), "
              f"{time.perf_counter() - t0:.1f} s")

    qs_all, qg_all = np.asarray(data["q_start"], float), np.asarray(data["q_goal"], float)
    test_ids = np.unique(traj[te])[: args.pairs]
    pairs = [("test", qs_all[i], qg_all[i]) for i in test_ids]
    if len(pairs) < args.pairs:
        ident = meta["identity"]["distribution"]
        dist = sampling.Distribution.from_record(ident)
        seed = args.fresh_seed if args.fresh_seed is not None else int(meta["identity"]["seed"]) + 1000
        fq0, fq1 = sampling.sample_pairs(robot, dist, seed, 0, args.pairs - len(pairs))
        pairs += [("fresh", a, b) for a, b in zip(fq0, fq1)]
    n_test = sum(p[0] == "test" for p in pairs)
    print(f"held-out pairs: {len(pairs)} ({n_test} from the dataset's test split, {len(pairs) - n_test} fresh); "
          f"robot {meta['robot']}, N = {N}, weights {meta.get('weights_text')}")

    Xtr_traj = X[tr]
    Ytr_traj = Y[tr]
    mu, sd = Xtr_traj.mean(0), np.where(Xtr_traj.std(0) > 0, Xtr_traj.std(0), 1.0)
    n = robot.n

    def knn_init(qs, qg):
        x = (np.r_[qs, qg] - mu) / sd
        j = int(np.argmin(np.sum(((Xtr_traj - mu) / sd - x) ** 2, 1)))
        y = Ytr_traj[j]
        return y[: N * n].reshape(N, n), y[N * n:]

    labels = ["planner", "cycloidal"] + (["knn"] if args.knn else []) + (["closed"] if args.closed else [])
    if args.primal:
        labels += [lab + "_primal" for lab in labels if lab != "cycloidal"]

    def inits(qs, qg):
        p = planner.plan(qs, qg)
        out = {"planner": (np.asarray(p.v), np.asarray(p.h)), "cycloidal": None}
        if args.knn:
            out["knn"] = knn_init(qs, qg)
        pc = None
        if closed is not None:
            pc = closed.plan(qs, qg)
            out["closed"] = (np.asarray(pc.v), np.asarray(pc.h))
        for lab in list(out):
            if out[lab] is not None:
                out[lab + "_primal"] = out[lab]
        return out, p, pc

    # compilation (untimed)
    t0 = time.perf_counter()
    _, qs0, qg0 = pairs[0]
    ini, _, _ = inits(qs0, qg0)
    for lab in labels:
        _solve(jtraj.Problem(robot, qs0, qg0, N=N, weights=weights), ini[lab], solver, lab.endswith("_primal"))
    print(f"compilation + first solves: {time.perf_counter() - t0:.1f} s")

    rows = []
    t_plan = []
    for i, (src, qs, qg) in enumerate(pairs):
        t1 = time.perf_counter()
        ini, p, pc = inits(qs, qg)
        jax.block_until_ready(p)
        t_plan.append(time.perf_counter() - t1)
        prob = jtraj.Problem(robot, qs, qg, N=N, weights=weights)
        order = labels if i % 2 == 0 else labels[::-1]
        row = dict(source=src, q_start=qs.tolist(), q_goal=qg.tolist(), plan_feasible=planner.feasible(p),
                   plan_goal_error=float(p.goal_error), plan_T=float(p.T))
        if closed is not None:
            row["closed_goal_error"] = float(pc.goal_error)
        for lab in order:
            row[lab] = _solve(prob, ini[lab], solver, lab.endswith("_primal"))
        rows.append(row)
        print(f"  {i + 1:3d}/{len(pairs)} {src:5s} " + "  ".join(
            f"{lab}: st {row[lab]['status']} it {row[lab]['iterations']:4d} {row[lab]['seconds']:.2f} s"
            for lab in labels), flush=True)

    P = len(rows)
    summary = dict(pairs=P, pairs_test_split=n_test, pairs_fresh=P - n_test, n_rules=model.n_rules,
                   plan_seconds_median=float(np.median(t_plan)),
                   plan_feasible=int(sum(r["plan_feasible"] for r in rows)),
                   plan_goal_error_median=float(np.median([r["plan_goal_error"] for r in rows])))
    print(f"\nplanner alone: feasible (limits and goal within {planner.goal_tol} rad) "
          f"{summary['plan_feasible']}/{P}; median goal error {summary['plan_goal_error_median']:.3g} rad; "
          f"plan call median {summary['plan_seconds_median'] * 1e3:.2f} ms (incl. Python overhead)")
    if closed is not None:
        ge = np.array([r["closed_goal_error"] for r in rows])
        summary["closed_goal_error_median"] = float(np.median(ge))
        print(f"closed-loop planner alone: goal error median {np.median(ge):.3g} rad, max {ge.max():.3g}")
    for lab in labels:
        rs = [r[lab] for r in rows]
        s = dict(converged=int(sum(r["converged"] for r in rs)), feasible=int(sum(r["feasible"] for r in rs)),
                 iterations=_stats(rs, "iterations"), seconds=_stats(rs, "seconds"))
        summary[lab] = s
        print(f"{lab:14s}: converged {s['converged']}/{P}, converged or feasible-not-optimal {s['feasible']}/{P}; "
              f"iterations mean {s['iterations']['mean']:.1f} median {s['iterations']['median']:.0f}; "
              f"seconds mean {s['seconds']['mean']:.3f} median {s['seconds']['median']:.3f} "
              f"total {s['seconds']['sum']:.1f}")
    c = summary["cycloidal"]
    for lab in labels:
        if lab == "cycloidal":
            continue
        s = summary[lab]
        both = [r for r in rows if r[lab]["converged"] and r["cycloidal"]["converged"]]
        rel = np.array([(r[lab]["cost"] - r["cycloidal"]["cost"]) / abs(r["cycloidal"]["cost"]) for r in both])
        it_ratio = s["iterations"]["mean"] / c["iterations"]["mean"]
        t_ratio = s["seconds"]["sum"] / c["seconds"]["sum"]
        per_pair = np.array([r[lab]["iterations"] / max(r["cycloidal"]["iterations"], 1) for r in rows])
        cmp = dict(iterations_ratio_mean=it_ratio, seconds_ratio_total=t_ratio,
                   iterations_ratio_per_pair_median=float(np.median(per_pair)),
                   fewer_iterations_pairs=int(sum(r[lab]["iterations"] < r["cycloidal"]["iterations"] for r in rows)),
                   both_converged=len(both))
        if len(both):
            cmp.update(cost_rel_diff_mean=float(rel.mean()), cost_rel_diff_median=float(np.median(rel)),
                       cost_rel_diff_max_abs=float(np.abs(rel).max()),
                       lower_cost_pairs=int((rel < -1e-6).sum()), higher_cost_pairs=int((rel > 1e-6).sum()))
        summary[f"{lab}_vs_cycloidal"] = cmp
        line = (f"{lab} / cycloidal: iterations {it_ratio:.3f}x (mean), "
                f"per-pair median {cmp['iterations_ratio_per_pair_median']:.3f}x, "
                f"fewer iterations on {cmp['fewer_iterations_pairs']}/{P}; wall time {t_ratio:.3f}x (total); "
                f"success {s['converged']}/{P} vs {c['converged']}/{P}")
        if len(both):
            line += (f"; cost (warm - cold)/cold where both converged ({len(both)}): mean {rel.mean():+.2e}, "
                     f"median {np.median(rel):+.2e}, max |.| {np.abs(rel).max():.2e} "
                     f"(lower {cmp['lower_cost_pairs']}, higher {cmp['higher_cost_pairs']})")
        print(line)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(summary=summary, rows=rows), f, indent=2)


if __name__ == "__main__":
    main()
