"""Online planner benchmark: latency, feasibility, cost gap, coverage, batches, and exact
refinement from the plan against cold and nearest-neighbour starts.

    .venv/bin/python benchmarks/bench_online.py --data DATASET [--model PLAN.anfis]
        [--pairs 40] [--repeat 2000] [--batch 4096] [--batch-rounds 1] [--batch-only]
        [--variants cold,plan_primal,...] [--json benchmarks/figures/online.json]

Figures in docs/guides/anfis.md ("What it reaches"), from
``--data ds300 --model plan.anfis --pairs 40 --json benchmarks/figures/online.json`` with the
dataset and model of that guide's commands. Issue #60 item 5. The planner model (mapping ``plan``, Sugeno order 0, as the anfis guide
trains it) is trained here on the dataset's training split unless ``--model`` is given.
Held-out pairs: the dataset's test split (last 10 % of its converged trajectories), topped
up to ``--pairs`` with fresh pairs of the dataset's own sampling law (seed + 1000).

Printed and written (``--json``):

* latency of one jitted plan (the repair and the coverage included; median and p99 over
  ``--repeat`` calls cycling through the pairs): ``Planner._flat``, the program
  ``Planner.plan`` runs (start and goal in one device array, the plan out as one), and
  ``Planner._plan`` (two device arrays in, the Plan's fields out); of the Python call
  ``Planner.plan`` (input checks, NumPy in and out) and of the model alone. The same
  again in a child process with JAX's asynchronous CPU dispatch off
  (``jax_cpu_enable_async_dispatch=False``, set before JAX's first computation): with it
  on, XLA's CPU client hands every program of more than about a thousand flops to a
  worker thread and the caller waits for it, and each of the program's kernels passes
  through its thread pool (the anfis guide)
  (``--sync-dispatch`` runs the whole benchmark so; ``--latency-only`` stops after the
  latencies; ``--batch-only`` runs the batch measurement alone);
* feasibility (each plan re-verified independently, NumPy recursion and Pinocchio's
  RNEA: serial3 by ``jtraj_peers/verify.py``, the panda by ``jtraj_peers/verify_arm.py``
  on example-robot-data's URDF, parallel3 by ``jtraj_peers/verify_parallel3.py``; bounds
  within 1e-6 relative, goal within 1e-6; other robots by the planner's own report), the
  goal error, the raw model's goal error;
* the cost gap ``(plan - optimum) / optimum`` to the exact solve from the cycloidal
  guess, where it converged; the same for the nearest training trajectory (inputs
  scaled as the coverage scales them) put through the same repair (a lookup baseline);
* coverage: the share of held-out pairs flagged out of distribution, and of pairs drawn
  with twice the dataset's step range (those with a step beyond the training range, and
  the others);
* batch: plans per second of ``Planner.plan`` on ``--batch`` fresh pairs (NumPy in and
  out; calls of ``Planner.chunk`` pairs on ``Planner.threads`` threads; best of 5 calls,
  the median over ``--batch-rounds`` rounds of the three planners interleaved), the
  process's CPU time per plan (the least of the 5 calls; on a machine shared with other
  jobs a steadier measure of the work than the wall time) and the
  share of them feasible (the default planner's re-verified as above), with the default repair, with its least-effort candidates too
  (``effort=True``) and without the projected prediction (``projection=False``), the
  latter two's held-out plans re-verified and their cost gaps reported;
* refinement, one compiled solve per pair and variant, compilation excluded (one untimed
  solve of each variant first): ``cold`` (default options from the cycloidal guess, the
  exact warm solve's latency of the reference), ``plan_primal`` / ``plan_full``
  (``jtraj.solve(init=plan, warm=...)``), ``nn_primal`` (from the nearest training
  trajectory), ``plan_mu3`` (interior point with a shortened barrier schedule,
  ``ip_mu_init=1e-3``, from the plan), ``plan_warm`` (from the plan with
  ``jtraj.online.WARM_IPM``, what ``Planner.query(refine=True)`` runs), ``al_cold`` /
  ``al_plan_full`` (the augmented-Lagrangian method alone, cold and from the plan with
  multipliers estimated there):
  Newton iterations, wall time, convergence, and the final cost against ``cold``'s
  (the same optimum where within 1e-3 relative: the solver's optimality tolerance is 3e-4).

Timings are of this machine's CPU, under whatever else runs on it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

# the exact solves' optimised programs from their first (untimed) call: with a quick
# program first (jtraj's default), a variant's first timed solve would compile them
os.environ.setdefault("JTRAJ_QUICK_FIRST", "0")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.append(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root: jtraj_peers

VARIANTS = ("cold", "plan_primal", "plan_full", "nn_primal", "plan_mu3", "plan_warm", "al_cold", "al_plan_full")


def _lat(f, args_list, repeat, block=True):
    """Wall times of ``f`` over ``repeat`` calls; ``block=False`` for a function returning
    NumPy arrays (already there: no ``block_until_ready`` walking its outputs)."""
    wait = jax.block_until_ready if block else (lambda x: x)
    wait(f(*args_list[0]))
    ts = np.empty(repeat)
    for i in range(repeat):
        a = args_list[i % len(args_list)]
        t0 = time.perf_counter()
        wait(f(*a))
        ts[i] = time.perf_counter() - t0
    return dict(median_us=float(np.median(ts) * 1e6), p99_us=float(np.percentile(ts, 99) * 1e6),
                min_us=float(ts.min() * 1e6), p10_us=float(np.percentile(ts, 10) * 1e6))


def _child_latency(args, model):
    """The latencies measured again in a child process with asynchronous dispatch off."""
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = args.model
        if path is None:
            path = os.path.join(tmp, "plan.anfis")
            model.save(path)
        cmd = [sys.executable, os.path.abspath(__file__), "--data", args.data, "--model", path, "--pairs",
               str(args.pairs), "--repeat", str(args.repeat), "--sync-dispatch", "--latency-only"]
        res = subprocess.run(cmd, capture_output=True, text=True, check=True)
    lines = res.stdout.strip().splitlines()
    print(lines[-2], flush=True)
    return json.loads(lines[-1])


def _verifier(robot, name, weights, tol):
    """``(check, label)``: ``check(q_start, q_goal, v, h)`` -> dict(ok, goal_error, violation,
    cost) of an independent re-verification of a plan, or ``(None, None)`` where the robot has
    none. serial3: :mod:`jtraj_peers.verify` (NumPy recursion, Pinocchio's RNEA of its own
    model); the panda: :mod:`jtraj_peers.verify_arm` (the same recursion, Pinocchio's RNEA of
    example-robot-data's URDF), with jtraj's limits of the robot, its jerk bound included;
    parallel3: :mod:`jtraj_peers.verify_parallel3` (NumPy leg kinematics, Pinocchio's RNEA of
    each leg, the legs' singularity margins), with the robot's limits."""
    w = (float(weights.time), float(weights.energy), float(weights.kinetic))
    lim = robot.limits
    if name == "serial3":
        from jtraj_peers import verify

        def run(qs, qg, v, h):
            return verify.verify(qs, qg, np.asarray(v), np.asarray(h), h_max=float(lim.h_max), weights=w, tol=tol)
        label = "jtraj_peers.verify (NumPy + Pinocchio)"
    elif name == "panda":
        from jtraj_peers import casadi_rnea, verify_arm

        model = casadi_rnea.panda_model()
        kw = {k: np.asarray(getattr(lim, k), float) for k in ("tau_max", "qd_max", "qdd_max", "q_min", "q_max")}
        kw.update(h_min=float(lim.h_min), h_max=float(lim.h_max), weights=w, tol=tol,
                  jerk_max=None if lim.qddd_max is None else np.asarray(lim.qddd_max, float))

        def run(qs, qg, v, h):
            return verify_arm.verify(model, qs, qg, np.asarray(v), np.asarray(h), **kw)
        label = "jtraj_peers.verify_arm (NumPy + Pinocchio, example-robot-data's URDF)"
    elif name == "parallel3":
        from jtraj_peers import verify_parallel3

        kw = {k: np.asarray(getattr(lim, k), float) for k in ("tau_max", "qd_max", "qdd_max", "q_min", "q_max")}
        kw.update(rho_min=float(robot.rho_min), rho_max=float(robot.rho_max), h_min=float(lim.h_min),
                  h_max=float(lim.h_max), weights=w, tol=tol)

        def run(qs, qg, v, h):
            return verify_parallel3.verify(qs, qg, np.asarray(v), np.asarray(h), **kw)
        label = "jtraj_peers.verify_parallel3 (NumPy leg kinematics + Pinocchio)"
    else:
        return None, None

    def check(qs, qg, v, h):
        c = run(qs, qg, v, h)
        return dict(ok=c["ok"], goal_error=c["goal_error"], violation=max(c["max_rel_violation"].values()),
                    cost=c["cost"])
    return check, label


def _q(a, qs):
    a = np.asarray(a, float)
    return {f"p{q}": float(np.percentile(a, q)) for q in qs} | {"max": float(a.max()), "mean": float(a.mean())}


def _chosen(planner, plans) -> dict:
    """How many of a batch's plans took each of the repair's candidates."""
    counts = np.bincount(np.asarray(plans.candidate).ravel(), minlength=len(planner.candidates))
    return {name: int(c) for name, c in zip(planner.candidates, counts)}


def _batch(args, planner, model, robot, weights, dist, seed, out, verify=None):
    """Batch throughput: ``Planner.plan`` (NumPy in and out, chunked over threads) with the
    default repair, the one with the least-effort candidates too (``effort=True``) and the
    one without the projected prediction (``projection=False``), ``--batch-rounds``
    rounds of the three interleaved, the best of each round's five calls; fills
    ``out["batch"]`` and returns the two other planners."""
    from jtraj.dataset import sampling
    from jtraj.online import Planner

    b0, b1 = sampling.sample_pairs(robot, dist, seed + 2, 0, args.batch)
    others = {"effort_true": Planner(model, robot, weights=weights, effort=True),
              "projection_false": Planner(model, robot, weights=weights, projection=False)}
    out["batch"] = dict(size=args.batch, chunk=planner.chunk, threads=planner.threads)
    planners = (("default", planner), *others.items())
    for _, pl in planners:
        pl.plan(b0[: planner.chunk], b1[: planner.chunk])  # compiles
    rates = {label: [] for label, _ in planners}
    cpus = {label: [] for label, _ in planners}
    loads = []
    for _ in range(args.batch_rounds):
        for label, pl in planners:
            best = cpu = np.inf
            for _ in range(5):
                t0, c0 = time.perf_counter(), time.process_time()
                pbb = pl.plan(b0, b1)
                best, cpu = min(best, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
            rates[label].append(args.batch / best)
            cpus[label].append(cpu / args.batch * 1e6)
            bf = pl.feasible(pbb)
            out["batch"][label] = dict(seconds=args.batch / np.median(rates[label]),
                                       plans_per_second=float(np.median(rates[label])),
                                       plans_per_second_rounds=rates[label],
                                       cpu_us_per_plan=float(np.median(cpus[label])), feasible=int(bf.sum()),
                                       ood=int(np.asarray(pbb.ood).sum()), bent=int(np.asarray(pbb.bent).sum()),
                                       candidates=_chosen(pl, pbb))
        loads.append(os.getloadavg()[0])
    for label, pl in planners:
        b = out["batch"][label]
        print(f"batch of {args.batch} ({label}, Planner.plan in calls of {pl.chunk} on {pl.threads} threads): "
              f"{b['plans_per_second']:,.0f} plans/s (median of {args.batch_rounds} rounds; "
              f"{min(rates[label]):,.0f} to {max(rates[label]):,.0f}), {b['cpu_us_per_plan']:.2f} CPU us per plan, "
              f"feasible {b['feasible']}/{args.batch} (own report), flagged out of distribution {b['ood']}, "
              f"bent by the position step {b['bent']}; "
              f"the repair's choices {b['candidates']}", flush=True)
    out["batch"]["load_average_1min"] = os.getloadavg()[0]
    out["batch"]["load_average_1min_rounds"] = loads
    if verify is not None:  # the default planner's batch, re-verified
        pb = planner.plan(b0, b1)
        ok = np.array([verify(b0[i], b1[i], pb.v[i], pb.h[i])["ok"] for i in range(args.batch)])
        out["batch"]["default"]["verified_feasible"] = int(ok.sum())
        print(f"batch of {args.batch} (default): re-verified feasible {ok.sum()}/{args.batch}; the planner's own "
              f"report and the verifier disagree on {int(np.sum(ok != planner.feasible(pb)))}", flush=True)
    return others


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--model")
    ap.add_argument("--pairs", type=int, default=40)
    ap.add_argument("--repeat", type=int, default=2000)
    ap.add_argument("--batch", type=int, default=4096)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--json")
    ap.add_argument("--sync-dispatch", action="store_true")
    ap.add_argument("--latency-only", action="store_true")
    ap.add_argument("--batch-only", action="store_true")
    ap.add_argument("--batch-rounds", type=int, default=1)
    args = ap.parse_args(argv)
    if args.sync_dispatch:
        jax.config.update("jax_cpu_enable_async_dispatch", False)
    variants = [v for v in args.variants.split(",") if v]
    bad = set(variants) - set(VARIANTS)
    if bad:
        raise SystemExit(f"unknown variants {sorted(bad)}; choose from {VARIANTS}")

    import jtraj
    from jtraj import anfis, dataset
    from jtraj import mappings
    from jtraj.dataset import sampling
    from jtraj.online import WARM_IPM, Planner
    from jtraj.repair import make_repair

    data = dataset.load(args.data)
    meta = data["metadata"]
    robot = jtraj.robots.from_metadata(meta)  # with the dataset's period bound; a URDF arm from its text
    N, n = int(meta["N"]), robot.n
    wtext = meta.get("weights_text", "time=1,energy=0.1")
    weights = jtraj.Weights.parse(wtext)
    tol = 1e-6
    verify, verifier = _verifier(robot, meta["robot"], weights, tol)
    out = dict(robot=meta["robot"], N=N, weights=wtext, h_max=float(robot.limits.h_max))

    X, Y, traj, _, _ = mappings.view(data, "plan")
    tr, te = mappings.split(traj)
    if args.model:
        model = anfis.load(args.model, mapping="plan")
    else:
        t0 = time.perf_counter()
        model, rep, _ = mappings.train_mapping(data, "plan", order=0)
        out["training"] = dict(seconds=time.perf_counter() - t0, test_rmse=rep["test_rmse"],
                               linear_test_rmse=rep["linear_test_rmse"], knn_test_rmse=rep["knn_test_rmse"])
    planner = Planner(model, robot, weights=weights)
    out.update(model_rules=int(model.n_rules), coverage_kind=planner.coverage_kind,
               coverage_radius=planner.coverage_radius)

    qs_all, qg_all = np.asarray(data["q_start"], float), np.asarray(data["q_goal"], float)
    test_ids = np.unique(traj[te])[: args.pairs]
    pairs = [("test", qs_all[i], qg_all[i]) for i in test_ids]
    ident = meta["identity"]["distribution"]
    dist = sampling.Distribution.from_record(ident)
    seed = int(meta["identity"]["seed"]) + 1000
    if len(pairs) < args.pairs:
        fq0, fq1 = sampling.sample_pairs(robot, dist, seed, 0, args.pairs - len(pairs))
        pairs += [("fresh", a, b) for a, b in zip(fq0, fq1)]
    P = len(pairs)
    QS = np.array([p[1] for p in pairs])
    QG = np.array([p[2] for p in pairs])
    out["pairs"] = dict(total=P, test_split=int(sum(p[0] == "test" for p in pairs)))
    print(f"{meta['robot']}, N = {N}, weights {wtext}; model {model.n_rules} rules; {P} held-out pairs "
          f"({out['pairs']['test_split']} of the test split)")
    if args.batch_only:
        _batch(args, planner, model, robot, weights, dist, seed, out)
        print(json.dumps(out))
        return out

    # --- latency
    dev = [(jnp.asarray(a), jnp.asarray(b)) for a, b in zip(QS, QG)]
    lat = dict(plan_jitted=_lat(planner._flat, [(jnp.concatenate(d),) for d in dev], args.repeat),
               plan_jitted_fields=_lat(planner._plan, dev, args.repeat))
    f_model = jax.jit(lambda x: model.predict_fn()(x[None])[0])
    lat["model_only"] = _lat(f_model, [(jnp.concatenate(d),) for d in dev], args.repeat)
    lat["plan_python_call"] = _lat(planner.plan, list(zip(QS, QG)), max(args.repeat // 4, 50), block=False)
    lat["load_average_1min"] = os.getloadavg()[0]
    lat["cpus"] = os.cpu_count()
    lat["async_dispatch"] = not args.sync_dispatch
    out["latency"] = lat
    print(f"latency (us, median / p99; {'synchronous' if args.sync_dispatch else 'asynchronous'} dispatch): plan "
          f"jitted {lat['plan_jitted']['median_us']:.1f} / {lat['plan_jitted']['p99_us']:.1f} (min "
          f"{lat['plan_jitted']['min_us']:.1f}; with the Plan's outputs "
          f"{lat['plan_jitted_fields']['median_us']:.1f}); model alone {lat['model_only']['median_us']:.1f}; "
          f"Planner.plan (checks included) {lat['plan_python_call']['median_us']:.1f}; load average "
          f"{lat['load_average_1min']:.1f} on {lat['cpus']} CPUs", flush=True)
    if args.latency_only:
        print(json.dumps(out))
        return out
    if not args.sync_dispatch:
        out["latency_sync_dispatch"] = _child_latency(args, model)["latency"]

    # --- feasibility, goal, coverage of the held-out plans
    pb = planner.plan(QS, QG)
    rows = []
    for i in range(P):
        r = dict(source=pairs[i][0], q_start=QS[i].tolist(), q_goal=QG[i].tolist(),
                 cost=float(pb.cost[i]), T=float(pb.T[i]), violation=float(pb.violation[i]),
                 goal_error=float(pb.goal_error[i]), predicted_goal_error=float(pb.predicted_goal_error[i]),
                 scale=float(pb.scale[i]), coverage_distance=float(pb.coverage_distance[i]), ood=bool(pb.ood[i]))
        if verify is not None:
            chk = verify(QS[i], QG[i], pb.v[i], pb.h[i])
            r.update(verified=chk["ok"], verified_goal_error=chk["goal_error"], verified_violation=chk["violation"],
                     verified_cost=chk["cost"])
        rows.append(r)
    feas = np.array([r.get("verified", planner.feasible(jax.tree.map(lambda a, i=i: a[i], pb))) for i, r in
                     enumerate(rows)])
    out["plans"] = dict(feasible=int(feas.sum()), of=P, verifier=verifier or "the planner's own report",
                        goal_error=_q([r["goal_error"] for r in rows], (50, 90)),
                        predicted_goal_error=_q([r["predicted_goal_error"] for r in rows], (50, 90)),
                        ood=int(sum(r["ood"] for r in rows)), candidates=_chosen(planner, pb))
    print(f"plans: feasible {feas.sum()}/{P} (re-verified: {out['plans']['verifier']}, tol {tol}); goal error "
          f"max {out['plans']['goal_error']['max']:.2e}; raw model's goal error median "
          f"{out['plans']['predicted_goal_error']['p50']:.3g} rad; flagged out of distribution {out['plans']['ood']}/{P}; "
          f"the repair's choices {out['plans']['candidates']}")

    # coverage on pairs twice as far apart as the dataset's
    wide = dataclasses.replace(dist, step_range=2 * dist.step_range)
    w0, w1 = sampling.sample_pairs(robot, wide, seed + 1, 0, 200)
    # pairs with a step beyond the training law's range on some joint
    far = np.max(np.abs(w1 - w0), axis=1) > dist.step_range
    pw = planner.plan(w0, w1)
    ood_w = np.asarray(pw.ood)
    out["coverage"] = dict(wide_pairs=int(len(w0)), beyond_range=int(far.sum()),
                           beyond_range_flagged=int(ood_w[far].sum()), within_range=int((~far).sum()),
                           within_range_flagged=int(ood_w[~far].sum()))
    print(f"coverage: of {len(w0)} pairs drawn with twice the step range, those with a step beyond the training "
          f"range flagged {ood_w[far].sum()}/{far.sum()}, the others {ood_w[~far].sum()}/{(~far).sum()}")

    others = _batch(args, planner, model, robot, weights, dist, seed, out, verify)
    if verify is not None:  # feasibility of the other plans on the held-out pairs, re-verified
        for label, pl in others.items():
            pf = pl.plan(QS, QG)
            ok = [verify(QS[i], QG[i], pf.v[i], pf.h[i])["ok"] for i in range(P)]
            for i, r in enumerate(rows):
                r[f"{label}_cost"] = float(pf.cost[i])
            out["plans"][f"{label}_feasible"] = int(sum(ok))

    # --- nearest training trajectory, repaired (lookup baseline), and its raw (v, h)
    from jtraj import coverage

    Xtr = X[tr]  # one row per training trajectory
    Ytr = Y[tr]
    lo, span = coverage.normaliser(Xtr)
    A = (Xtr - lo) / span
    nn = [int(np.argmin(np.sum(((np.r_[a, b] - lo) / span - A) ** 2, 1))) for a, b in zip(QS, QG)]
    nn_v = np.array([Ytr[j][: N * n].reshape(N, n) for j in nn])
    nn_h = np.array([Ytr[j][N * n:] for j in nn])
    rep = jax.jit(jax.vmap(make_repair(robot, weights, effort=planner.effort, switch=planner.switch),
                           in_axes=(0, None, 0, None, 0, 0)))
    z = jnp.zeros(n)
    nr = rep(jnp.asarray(QS), z, jnp.asarray(QG), z, jnp.asarray(nn_v), jnp.asarray(nn_h))
    for i, r in enumerate(rows):
        r["nn_repaired_cost"] = float(nr.cost[i])

    # --- exact solves
    solvers = {"cold": jtraj.Auto(), "plan_primal": jtraj.Auto(), "plan_full": jtraj.Auto(), "nn_primal": jtraj.Auto(),
               "plan_mu3": jtraj.Auto(ipm=jtraj.IPM(mu_init=1e-3)),
               "plan_warm": jtraj.Auto(ipm=jtraj.IPM(**WARM_IPM)), "al_cold": jtraj.AugmentedLagrangian(),
               "al_plan_full": jtraj.AugmentedLagrangian()}

    def run(label, i):
        prob = jtraj.Problem(robot, QS[i], QG[i], N=N, weights=weights)
        if label in ("cold", "al_cold"):
            init, warm = None, "full"
        elif label == "nn_primal":
            init, warm = (jnp.asarray(nn_v[i]), jnp.asarray(nn_h[i])), "primal"
        else:
            init, warm = (pb.v[i], pb.h[i]), ("primal" if label in ("plan_primal", "plan_warm") else "full")
        t0 = time.perf_counter()
        sol = jtraj.solve(prob, init=init, solver=solvers[label], warm=warm)
        jax.block_until_ready(sol.status)
        dt = time.perf_counter() - t0
        return dict(converged=bool(sol.converged), status=int(sol.status), iterations=int(sol.iterations),
                    seconds=dt, cost=float(sol.cost))

    t0 = time.perf_counter()
    for lab in variants:
        run(lab, 0)
    out["compile_seconds"] = time.perf_counter() - t0
    print(f"exact solves compiled ({', '.join(variants)}): {out['compile_seconds']:.0f} s", flush=True)
    for i, r in enumerate(rows):
        order = variants if i % 2 == 0 else variants[::-1]
        for lab in order:
            r[lab] = run(lab, i)
        print(f"  {i + 1:3d}/{P} " + "  ".join(f"{lab} {r[lab]['iterations']:3d} it {r[lab]['seconds'] * 1e3:6.1f} ms"
                                              + ("" if r[lab]["converged"] else " (not converged)")
                                              for lab in variants), flush=True)

    ref = "cold" if "cold" in variants else None
    if ref:
        ok = [r for r in rows if r[ref]["converged"]]
        gap = np.array([(r["cost"] - r[ref]["cost"]) / abs(r[ref]["cost"]) for r in ok])
        gnn = np.array([(r["nn_repaired_cost"] - r[ref]["cost"]) / abs(r[ref]["cost"]) for r in ok])
        for r in ok:
            r["gap"] = (r["cost"] - r[ref]["cost"]) / abs(r[ref]["cost"])
        alt = {label: np.array([(r[f"{label}_cost"] - r[ref]["cost"]) / abs(r[ref]["cost"]) for r in ok
                                if f"{label}_cost" in r]) for label in ("effort_true", "projection_false")}
        out["gap"] = dict(pairs=len(ok), plan=_q(gap, (50, 90)), nn_repaired=_q(gnn, (50, 90)),
                          **{label: _q(g, (50, 90)) if len(g) else None for label, g in alt.items()},
                          within_3pct_median=bool(np.median(gap) <= 0.03),
                          within_10pct_p90=bool(np.percentile(gap, 90) <= 0.10))
        print(f"cost gap to the exact optimum ({len(ok)} pairs where it converged): plan median "
              f"{100 * np.median(gap):.2f} %, p90 {100 * np.percentile(gap, 90):.2f} %, max {100 * gap.max():.2f} %; "
              f"nearest training trajectory repaired: median {100 * np.median(gnn):.2f} %, "
              f"p90 {100 * np.percentile(gnn, 90):.2f} %" + "".join(
                  f"; {label}: median {100 * np.median(g):.2f} %, p90 {100 * np.percentile(g, 90):.2f} %, max "
                  f"{100 * g.max():.2f} %" for label, g in alt.items() if len(g)))
    ref_it = np.array([r[ref]["iterations"] for r in rows]) if ref else None
    out["refine"] = {}
    for lab in variants:
        it = np.array([r[lab]["iterations"] for r in rows])
        sec = np.array([r[lab]["seconds"] for r in rows])
        conv = np.array([r[lab]["converged"] for r in rows])
        s = dict(converged=int(conv.sum()), iterations=_q(it, (50, 90)), seconds=_q(sec, (50, 90)))
        if ref and lab != ref:
            both = [r for r in rows if r[lab]["converged"] and r[ref]["converged"]]
            dc = np.array([(r[lab]["cost"] - r[ref]["cost"]) / abs(r[ref]["cost"]) for r in both])
            s.update(iterations_ratio_median=float(np.median(it / np.maximum(ref_it, 1))),
                     same_optimum=int(np.sum(np.abs(dc) <= 1e-3)) if len(both) else 0, both_converged=len(both),
                     cost_rel_diff_max_abs=float(np.abs(dc).max()) if len(both) else None)
        out["refine"][lab] = s
        line = (f"{lab:13s}: converged {conv.sum()}/{P}, iterations median {np.median(it):.0f} (p90 "
                f"{np.percentile(it, 90):.0f}), wall median {np.median(sec) * 1e3:.1f} ms")
        if "iterations_ratio_median" in s:
            line += (f"; per-pair iterations / cold median {s['iterations_ratio_median']:.2f}; same optimum "
                     f"(cost within 1e-3, the solver's optimality tolerance 3e-4) {s['same_optimum']}/"
                     f"{s['both_converged']}")
        print(line)
    if ref:
        ratio = lat["plan_jitted"]["median_us"] / (out["refine"][ref]["seconds"]["p50"] * 1e6)
        out["plan_latency_over_exact_solve"] = ratio
        print(f"plan latency / exact compiled solve (median): {ratio:.4f}")
    out["rows"] = rows
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
