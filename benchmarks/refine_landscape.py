"""Why a warm start from a learned plan saves few Newton iterations: where the
interior-point runs from the cold start and from the plan end, and whether they end at
one optimum.

    python benchmarks/refine_landscape.py --data ds300 --model plan.anfis [--pairs 16] [--json out.json]

Held-out pairs as ``bench_online.py`` takes them (the dataset's test split, in order).
For each pair, on the dataset's problem (robot, N, weights, default options), the
interior-point method (:mod:`jtraj.solver.ipm`, the solver's default) runs

* from the cycloidal guess with the default settings (the cold start), and
* from the ``Planner``'s plan with ``jtraj.online.WARM_IPM`` (what
  ``Planner.query(refine=True)`` runs),

each to the solver's default stopping test, then each continued from its final state
to a tight one (IPOPT's overall scaled error at most 1e-9, at most 400 more iterations).
Printed per pair: the iterations of both runs and of both continuations; for each run,
the iteration from which its cost stays within 1e-3 (relative, the criterion of
``bench_online.py``'s "same optimum") of the cost it ends at; the iterations of a third
run with ``WARM_IPM``, from an oracle plan: the cold start's tight optimum's own motion
sampled on N equal periods of its duration (its accelerations from the motion's
velocities at the new samples), which tells what a model that predicted the optimal
motion exactly, but not its periods, would save; the relative
cost difference of the two tight optima and their distance in the scaled unknowns
(accelerations and periods apart; the same optimum where every component agrees within
1e-5); the distances of the cycloidal guess and of the plan to the cold start's tight
optimum; and the constraints active there (stage inequalities whose multiplier exceeds
their slack, box bounds whose multiplier exceeds their distance). The summary counts the
pairs whose two runs reach one optimum and gives the ranges of the others.

The scaled unknowns are those the solver iterates on (``Transcription.layout``:
accelerations divided by their scale, periods by ``h_max / 4``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

#: every scaled component within this: the two tight runs reached the same optimum
SAME = 1e-5


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--model", required=True)
    ap.add_argument("--pairs", type=int, default=16)
    ap.add_argument("--json")
    args = ap.parse_args(argv)

    import equinox as eqx
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jtraj
    from jtraj import anfis, dataset, mappings
    from jtraj.online import WARM_IPM, Planner
    from jtraj.solver import core, ipm, loop
    from jtraj.solver.api import solver_options
    from jtraj.transcription import Transcription

    data = dataset.load(args.data)
    meta = data["metadata"]
    robot = jtraj.robots.from_metadata(meta)  # with the dataset's period bound; a URDF arm from its text
    N, n = int(meta["N"]), robot.n
    weights = jtraj.Weights.parse(meta.get("weights_text", "time=1,energy=0.1"))
    planner = Planner(anfis.load(args.model, mapping="plan"), robot, weights=weights)
    _, _, traj, _, _ = mappings.view(data, "plan")
    _, te = mappings.split(traj)
    ids = np.unique(traj[te])[: args.pairs]
    QS, QG = np.asarray(data["q_start"], float)[ids], np.asarray(data["q_goal"], float)[ids]

    tr = Transcription("decoupled")
    opts = core.resolve_method(solver_options(jtraj.Auto(), None), "decoupled", robot, False)
    default_tol, tight_tol = core.ip_tolerances(opts), ipm.Tolerances(1e-9)

    step = eqx.filter_jit(lambda nlp, st: ipm.step(nlp, st, default_tol))
    start_state = eqx.filter_jit(ipm.init)

    def run(nlp, z, mu0, push, shift0):
        """The run (the solver's iterations, one jitted step at a time) and the iteration
        from which its cost stays within 1e-3 of its final cost."""
        st = start_state(nlp, z, mu0, push, shift0)
        costs = [float(cost(nlp, st.z))]
        while not bool(ipm.finished(st, opts.ip_max_iter)):
            st = step(nlp, st)
            costs.append(float(cost(nlp, st.z)))
        final = costs[-1]
        settled = [abs(c - final) <= 1e-3 * abs(final) for c in costs]
        return st, next(k for k in range(len(costs)) if all(settled[k:]))

    @eqx.filter_jit
    def tighten(nlp, st):
        st = st._replace(done=jnp.asarray(False), it=jnp.asarray(0))
        return loop.iterate(ipm.InteriorPoint(max_iter=400, tol=tight_tol), nlp, st)

    @eqx.filter_jit
    def cost(nlp, z):
        return ipm._parts(nlp, z).f

    def on_equal_periods(v, h, qd0):
        """The motion of (v, h) from the velocity qd0, sampled on N equal periods of its
        duration: (v, h) of the constant accelerations between its velocities there."""
        v, h = np.asarray(v), np.asarray(h)
        t = np.concatenate([[0.0], np.cumsum(h)])
        qd = np.asarray(qd0)[None] + np.concatenate([np.zeros((1, n)), np.cumsum(h[:, None] * v, axis=0)])
        tn = np.linspace(0.0, t[-1], N + 1)
        k = np.clip(np.searchsorted(t, tn, side="right") - 1, 0, N - 1)
        qd_new = qd[k] + v[k] * (tn - t[k])[:, None]
        h_new = np.full(N, t[-1] / N)
        return jnp.asarray((qd_new[1:] - qd_new[:-1]) / h_new[:, None]), jnp.asarray(h_new)

    rows, t0 = [], time.perf_counter()
    nv = N * n
    for i in range(len(ids)):
        prob = jtraj.Problem(robot, QS[i], QG[i], N=N, weights=weights)
        start = core.prepare(prob, opts, tr, core.initial_guess(prob, opts, tr), False)
        nlp, z_cyc = start.nlp, start.state.z
        p = planner.plan(QS[i], QG[i])
        z_plan = nlp.layout.pack(jnp.asarray(p.v), jnp.asarray(p.h))
        cold, cold_settled = run(nlp, z_cyc, opts.ip_mu_init, opts.ip_bound_push, opts.ip_first_shift)
        warm, warm_settled = run(nlp, z_plan, WARM_IPM["mu_init"], WARM_IPM["bound_push"], WARM_IPM["first_shift"])
        ct, wt = tighten(nlp, cold), tighten(nlp, warm)
        oracle, _ = run(nlp, nlp.layout.pack(*on_equal_periods(*nlp.layout.unpack(ct.z), prob.qd_start)),
                        WARM_IPM["mu_init"], WARM_IPM["bound_push"], WARM_IPM["first_shift"])

        def dist(a, b):
            d = np.asarray(a - b)
            return [float(np.linalg.norm(d[:nv])), float(np.linalg.norm(d[nv:]))]

        lo, hi = nlp.layout.z_lo, nlp.layout.z_hi
        fc, fw = float(cost(nlp, ct.z)), float(cost(nlp, wt.z))
        r = dict(pair=int(ids[i]), cold_iterations=int(cold.it), warm_iterations=int(warm.it),
                 cost_settled=[cold_settled, warm_settled], oracle_iterations=int(oracle.it),
                 oracle_solved=bool(oracle.done & ~oracle.failed),
                 oracle_cost_difference=(float(cost(nlp, oracle.z)) - fc) / abs(fc),
                 tight_iterations=[int(ct.it), int(wt.it)], tight_solved=[bool(ct.done), bool(wt.done)],
                 same_optimum=bool(np.max(np.abs(np.asarray(ct.z - wt.z))) <= SAME),
                 cost_difference=(fw - fc) / abs(fc), optima_distance=dist(wt.z, ct.z),
                 cycloid_distance=dist(z_cyc, ct.z), plan_distance=dist(z_plan, ct.z),
                 default_end_distance=[dist(cold.z, ct.z), dist(warm.z, wt.z)],
                 active_inequalities=int(jnp.sum(ct.y > ct.s)), inequalities=int(ct.y.size),
                 active_bounds=int(jnp.sum((ct.zu > hi - ct.z) & jnp.isfinite(hi))
                                   + jnp.sum((ct.zl > ct.z - lo) & jnp.isfinite(lo))))
        rows.append(r)
        print(f"pair {r['pair']:4d}: iterations cold {r['cold_iterations']:3d}, plan {r['warm_iterations']:3d} "
              f"(costs settled from {cold_settled} and {warm_settled}), oracle plan {r['oracle_iterations']}; "
              f"tight +{r['tight_iterations'][0]}/+{r['tight_iterations'][1]}; "
              + ("one optimum" if r["same_optimum"] else
                 f"two optima, cost {r['cost_difference']:+.1e}, apart {r['optima_distance'][0]:.2f} (acc.) / "
                 f"{r['optima_distance'][1]:.2f} (periods)")
              + f"; to the cold optimum: cycloid {r['cycloid_distance'][0]:.2f} / {r['cycloid_distance'][1]:.2f}, "
              f"plan {r['plan_distance'][0]:.2f} / {r['plan_distance'][1]:.2f}; active {r['active_inequalities']} of "
              f"{r['inequalities']} inequalities, {r['active_bounds']} bounds", flush=True)

    solved = [r for r in rows if all(r["tight_solved"])]
    two = [r for r in solved if not r["same_optimum"]]
    ratio = np.array([np.linalg.norm(r["plan_distance"]) / np.linalg.norm(r["cycloid_distance"]) for r in rows])
    summary = dict(
        pairs=len(rows), tight_solved=len(solved), one_optimum=len(solved) - len(two), two_optima=len(two),
        two_optima_cost_difference_abs=[float(min(abs(r["cost_difference"]) for r in two)),
                                        float(max(abs(r["cost_difference"]) for r in two))] if two else None,
        two_optima_period_distance=[float(min(r["optima_distance"][1] for r in two)),
                                    float(max(r["optima_distance"][1] for r in two))] if two else None,
        plan_over_cycloid_distance_median=float(np.median(ratio)),
        warm_over_cold_iterations_median=float(np.median([r["warm_iterations"] / r["cold_iterations"] for r in rows])),
        # where the runs' costs settle (within 1e-3 of their final costs), over the cold run's iterations
        cold_settled_over_cold_iterations_median=float(np.median([r["cost_settled"][0] / r["cold_iterations"]
                                                                  for r in rows])),
        warm_settled_over_cold_iterations_median=float(np.median([r["cost_settled"][1] / r["cold_iterations"]
                                                                  for r in rows])),
        oracle_over_cold_iterations_median=float(np.median([r["oracle_iterations"] / r["cold_iterations"]
                                                            for r in rows])),
        oracle_same_cost=int(sum(r["oracle_solved"] and abs(r["oracle_cost_difference"]) <= 1e-3 for r in rows)),
        warm_settled_over_cold_settled_median=float(np.median([r["cost_settled"][1] / max(r["cost_settled"][0], 1)
                                                               for r in rows])),
        active_inequalities=[int(min(r["active_inequalities"] for r in rows)),
                             int(max(r["active_inequalities"] for r in rows))],
        active_bounds=[int(min(r["active_bounds"] for r in rows)), int(max(r["active_bounds"] for r in rows))],
        seconds=time.perf_counter() - t0, load_average_1min=os.getloadavg()[0])
    print(f"{summary['pairs']} pairs, both tight runs solved on {summary['tight_solved']}: one optimum on "
          f"{summary['one_optimum']}, two on {summary['two_optima']}"
          + (f" (costs {summary['two_optima_cost_difference_abs'][0]:.1e} to "
             f"{summary['two_optima_cost_difference_abs'][1]:.1e} apart, periods "
             f"{summary['two_optima_period_distance'][0]:.1f} to {summary['two_optima_period_distance'][1]:.1f})"
             if two else "")
          + f"; the plan's distance to the cold optimum / the cycloid's: median "
          f"{summary['plan_over_cycloid_distance_median']:.2f}; iterations from the plan / cold: median "
          f"{summary['warm_over_cold_iterations_median']:.2f}; costs settled within 1e-3 (over the cold run's "
          f"iterations, medians): cold {summary['cold_settled_over_cold_iterations_median']:.2f}, from the plan "
          f"{summary['warm_settled_over_cold_iterations_median']:.2f} (over the cold run's settling: "
          f"{summary['warm_settled_over_cold_settled_median']:.2f}); from the oracle plan / cold: median "
          f"{summary['oracle_over_cold_iterations_median']:.2f} ({summary['oracle_same_cost']} at the cold "
          f"optimum's cost within 1e-3); active at the optimum: "
          f"{summary['active_inequalities'][0]}-{summary['active_inequalities'][1]} inequalities, "
          f"{summary['active_bounds'][0]}-{summary['active_bounds'][1]} bounds")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(summary=summary, rows=rows, data=args.data, model=args.model), f, indent=1)
    return summary


if __name__ == "__main__":
    main()
