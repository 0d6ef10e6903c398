"""jtraj against CasADi + IPOPT on a 7-DOF spatial arm (the Franka Panda).

    python benchmarks/bench_spatial.py [--pairs 64] [--batch 32] [--seed 0] [--N 40]
                                       [--latency-pairs 4] [--workers W] [--peer-jerk off|auto]
                                       [--first-solution] [--json out.json]
    python benchmarks/bench_spatial.py --dataset [--pairs 64] [--batch B] [--ipopt-pairs 8] [--json out.json]

Problem family: ``jtraj.robots.get("panda")``, N = 40, weights time 1 / energy 0.1,
q_start uniform in the middle 60 % of each joint range, q_goal = q_start + U(-0.5, 0.5)
rad per joint, clipped to the range (:func:`panda_pairs`, seeded). The peer solves the
same decoupled NLP (``jtraj_peers.ipopt_arm``) with the dynamics of a CasADi RNEA built from
Pinocchio's model of the same URDF (``jtraj_peers.casadi_rnea``, checked against
``pinocchio.rnea`` by tests/test_casadi_rnea.py; the installed ``pin`` has no
``pinocchio.casadi``) and the limits of jtraj's robot, so that both sides see one
problem. Both start from jtraj's starting point. Every trajectory either side calls a
success is re-simulated from its own (v, h) and checked with Pinocchio
(``jtraj_peers.verify_arm``, tolerance 1e-6). Printed: verified successes, false
"converged", cost gaps where both succeed, batch throughput on all cores (IPOPT one
process per core; jtraj vmapped batches, one process pinned per core), warm single
solve (both in one pinned process, alternating pair by pair), and with
``--first-solution`` the time from a fresh interpreter to the first solution of each.
Ratios > 1 mean jtraj is ahead. ``--dataset``: ``jtraj dataset --robot panda`` end to end
against the IPOPT loop on a subset of the same pairs instead (:func:`dataset_run`).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

sys.path.append(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root: jtraj_peers

KEYS = ("v", "h", "cost", "converged", "status", "iterations")
WEIGHTS = dict(time=1.0, energy=0.1)
PEER_WEIGHTS = (1.0, 0.1, 0.0)


def jtraj_panda():
    """``jtraj.robots.get("panda")``, or a clear exit when this jtraj has no Panda."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jtraj

    try:
        return jtraj.robots.get("panda")
    except (ImportError, ValueError, FileNotFoundError) as err:
        raise SystemExit(f"bench_spatial needs jtraj.robots.get('panda') (issue 55: URDF robots, "
                         f"pip install 'jtraj[robots]'); it failed with: {err}") from err


def _limits(robot) -> dict:
    lim = robot.limits
    out = {}
    for k in ("q_min", "q_max", "qd_max", "qdd_max", "tau_max", "qddd_max"):
        x = getattr(lim, k)
        out[k] = None if x is None else np.asarray(x, float)
    out["h_min"], out["h_max"] = float(lim.h_min), float(lim.h_max)
    return out


def panda_pairs(n: int, seed: int, q_min, q_max) -> tuple[np.ndarray, np.ndarray]:
    """The family: q_start ~ U(middle 60 % of [q_min, q_max]) per joint, q_goal =
    clip(q_start + U(-0.5, 0.5), q_min, q_max). Pair i does not depend on n."""
    q_min, q_max = np.asarray(q_min, float), np.asarray(q_max, float)
    u = np.random.default_rng(seed).random((n, 2, q_min.size))
    mid, half = (q_min + q_max) / 2, (q_max - q_min) / 2
    q0 = mid + 0.6 * half * (2 * u[:, 0] - 1)
    return q0, np.clip(q0 + (u[:, 1] - 0.5), q_min, q_max)


def peer_spec(lim: dict, jerk: bool):
    """The peer's arm: the CasADi RNEA of Pinocchio's Panda with jtraj's limits."""
    from jtraj_peers import casadi_rnea as CR
    from jtraj_peers.ipopt_arm import ArmSpec

    model = CR.panda_model()
    urdf = CR.model_limits(model)
    for k in ("q_min", "q_max", "qd_max", "tau_max"):
        if lim[k] is not None and not np.allclose(lim[k], urdf[k]):
            print(f"  note: jtraj's panda {k} {lim[k].tolist()} differs from the URDF's {urdf[k].tolist()}; "
                  "the peer uses jtraj's")
    spec = ArmSpec.make(CR.rnea_function(model), q_min=lim["q_min"], q_max=lim["q_max"], qd_max=lim["qd_max"],
                        qdd_max=lim["qdd_max"], tau_max=lim["tau_max"], h_min=lim["h_min"], h_max=lim["h_max"],
                        jerk_max=lim["qddd_max"] if jerk else None)
    return model, spec


def jtraj_starts(q0, q1, N, robot=None):
    """jtraj's starting points (its default guess) for the pairs, as (v, h) arrays
    (``robot``: default ``jtraj_panda()``)."""
    import equinox as eqx

    import jtraj
    from jtraj.initial_guess import GUESSES

    robot = jtraj_panda() if robot is None else robot
    guess = GUESSES[jtraj.SolverOptions().guess]
    v, h = eqx.filter_jit(eqx.filter_vmap(lambda a, b: guess(jtraj.Problem(robot, a, b, N=N, validate=False))))(
        np.asarray(q0, float), np.asarray(q1, float))
    return [(np.asarray(a), np.asarray(b)) for a, b in zip(v, h)]


def _solve_chunk(q0, q1, N):
    import jtraj

    sol = jtraj.solve_batch(jtraj_panda(), q0, q1, N=N, weights=jtraj.Weights(**WEIGHTS))
    return {k: np.asarray(getattr(sol, k)) for k in KEYS}


def _jtraj_batch(q0, q1, N, B, workers):
    """Throughput of solve_batch in chunks of B pairs on ``workers`` pinned processes:
    every chunk once untimed (compilation), then the median of three timed passes."""
    from jtraj.dataset._local import worker_pool

    P = len(q0)
    pad = (-P) % B
    q0p, q1p = (np.concatenate([x, np.repeat(x[-1:], pad, 0)]) for x in (q0, q1))
    chunks = [(q0p[s:s + B], q1p[s:s + B], N) for s in range(0, len(q0p), B)]
    with worker_pool(workers) as pool:
        t0 = time.perf_counter()
        for c in chunks:
            list(pool.map(_solve_chunk, *zip(*[c] * workers)))
        first = time.perf_counter() - t0
        walls = []
        for _ in range(3):
            t0 = time.perf_counter()
            parts = list(pool.map(_solve_chunk, *zip(*chunks)))
            walls.append(time.perf_counter() - t0)
    res = {k: np.concatenate([p[k] for p in parts])[:P] for k in KEYS}
    res["wall"], res["compile_and_first_pass"] = float(np.median(walls)), first
    return res


def _single_latencies(q0, q1, N, starts, jerk, repeats=3):
    """Warm single solves, best of ``repeats`` per pair, both solvers alternating in this
    (pinned) process: (jtraj (L,), IPOPT (L,), jtraj's first call s)."""
    import jax

    import jtraj
    from jtraj_peers.ipopt_arm import get_peer

    robot = jtraj_panda()
    _, spec = peer_spec(_limits(robot), jerk)
    peer = get_peer(spec, N, PEER_WEIGHTS)
    problems = [jtraj.Problem(robot, a, b, N=N, weights=jtraj.Weights(**WEIGHTS), validate=False)
                for a, b in zip(q0, q1)]
    t0 = time.perf_counter()
    jax.block_until_ready(jtraj.solve(problems[0]).status)
    compile_s = time.perf_counter() - t0
    ours, theirs = [], []
    for i, p in enumerate(problems):
        best = np.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(jtraj.solve(p).status)
            best = min(best, time.perf_counter() - t0)
        ours.append(best)
        theirs.append(min(peer.solve(q0[i], q1[i], starts[i])["seconds"] for _ in range(repeats)))
    return np.array(ours), np.array(theirs), compile_s


_FIRST_JTRAJ = """
import time; t0 = time.perf_counter()
import sys; sys.path.insert({i}, {bench!r})
import bench_spatial as B, numpy as np, jtraj
r = B.jtraj_panda(); lim = B._limits(r)
q0, q1 = B.panda_pairs(1, {seed}, lim["q_min"], lim["q_max"])
s = jtraj.solve(jtraj.Problem(r, q0[0], q1[0], N={N}, weights=jtraj.Weights(**B.WEIGHTS)))
s.status.block_until_ready(); print(time.perf_counter() - t0, bool(s.converged))
"""
_FIRST_PEER = """
import time; t0 = time.perf_counter()
import sys; sys.path.insert(0, {bench!r})
import casadi, numpy as np, bench_spatial as B
from jtraj_peers import ipopt_arm as A
lim = {lim!r}; lim = {{k: None if v is None else (np.array(v) if isinstance(v, list) else v) for k, v in lim.items()}}
_, spec = B.peer_spec(lim, {jerk})
q0, q1 = B.panda_pairs(1, {seed}, lim["q_min"], lim["q_max"])
r = A.solve_pair(spec, q0[0], q1[0], N={N}, weights=B.PEER_WEIGHTS); print(time.perf_counter() - t0, r["success"])
"""


def first_solution(N, seed, lim, jerk):
    """Seconds from a fresh interpreter to each side's first solution (jtraj: ``import``,
    compilation with JAX's caches as the library leaves them, one solve; IPOPT: import,
    NLP build, one solve)."""
    bench = os.path.dirname(os.path.abspath(__file__))
    out = {}
    for name, code in (("jtraj", _FIRST_JTRAJ.format(i=0, bench=bench, seed=seed, N=N)),
                       ("ipopt", _FIRST_PEER.format(bench=bench, seed=seed, N=N, jerk=jerk,
                                                    lim={k: (v.tolist() if isinstance(v, np.ndarray) else v)
                                                         for k, v in lim.items()}))):
        t0 = time.perf_counter()
        res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=dict(os.environ))
        wall = time.perf_counter() - t0
        if res.returncode != 0:
            raise RuntimeError(f"first solution of {name} failed:\n{res.stderr[-2000:]}")
        inside, ok = res.stdout.split()[-2:]
        out[name] = {"wall_s": wall, "in_process_s": float(inside), "success": ok == "True"}
    return out


def dataset_run(pairs, batch, seed, N, workers, ipopt_pairs, jerk):
    """``jtraj dataset --robot panda`` end to end against the IPOPT loop on the same pairs.

    The dataset (:func:`jtraj.dataset.make_spec`: joint-space sampling, weights time 1 /
    energy 0.1, the dataset's period bound ``h_max="auto"``; ``batch=None``: the default
    chunk size) is first built untimed for its first ``workers`` chunks into a
    temporary folder by ``workers`` pinned processes (every program its chunks need
    compiled into the persistent cache: ``warmup_s``), then built whole into another
    folder, timed end to end (worker start-up, loading the compiled programs, sampling,
    solving and writing included: ``build_s``). The chunks both builds solved must be
    equal. The IPOPT loop (:func:`jtraj_peers.ipopt_arm.solve_many`, one process per
    core, NLP built once per process, not timed) solves the first ``ipopt_pairs`` pairs
    of the same dataset with the same limits from jtraj's starting points; both sides'
    solutions of those pairs are re-simulated and checked with Pinocchio."""
    import tempfile

    from jtraj import dataset
    from jtraj_peers.ipopt_arm import solve_many
    from jtraj_peers.verify_arm import verify

    spec = dataset.make_spec("panda", pairs, seed, N=N, batch=batch)
    robot = spec.robot_model()
    lim = _limits(robot)
    keys = ("q_start", "q_goal", "v", "h", "cost", "converged", "status", "iterations")
    with tempfile.TemporaryDirectory(prefix="bench_spatial_dataset_") as tmp:
        warm_dir, out = os.path.join(tmp, "warmup"), os.path.join(tmp, "d")
        t0 = time.perf_counter()
        dataset.build(spec, warm_dir, progress=False, max_chunks=workers, workers=workers)
        warmup = time.perf_counter() - t0
        t0 = time.perf_counter()
        stats = dataset.build(spec, out, progress=False, workers=workers)
        wall = time.perf_counter() - t0
        data, ref = dataset.load(out), dataset.load(warm_dir, partial=True)
        d = {k: np.asarray(data[k]).copy() for k in keys}
        both_built = np.asarray(ref["index"])
        same = bool(both_built.size) and all(
            np.array_equal(d[k][both_built], np.asarray(ref[k])) for k in keys)
    jt_thr = pairs / wall
    M = min(ipopt_pairs, pairs)
    q0, q1 = d["q_start"][:M], d["q_goal"][:M]
    model, pspec = peer_spec(lim, jerk)
    ip = solve_many(pspec, q0, q1, N=N, weights=PEER_WEIGHTS, inits=jtraj_starts(q0, q1, N, robot))
    ip_thr = len(ip) / ip.wall_seconds
    kw = dict(tau_max=lim["tau_max"], qd_max=lim["qd_max"], qdd_max=lim["qdd_max"], q_min=lim["q_min"],
              q_max=lim["q_max"], h_min=lim["h_min"], h_max=lim["h_max"], weights=PEER_WEIGHTS, tol=1e-6)
    ip_ver = np.array([r["success"] and verify(model, a, b, r["v"], r["h"], **kw)["ok"] for a, b, r in zip(q0, q1, ip)])
    jt_conv = d["converged"][:M].astype(bool)
    jt_ver = np.array([verify(model, a, b, v, h, **kw)["ok"] for a, b, v, h in zip(q0, q1, d["v"][:M], d["h"][:M])])
    ip_cost = np.array([r["cost"] for r in ip])
    both = jt_conv & jt_ver & ip_ver
    gap = (d["cost"][:M] - ip_cost) / ip_cost
    report = {
        "pairs": pairs, "N": N, "batch": spec.batch, "chunks": spec.n_chunks, "workers": workers,
        "h_max": lim["h_max"], "distribution": spec.distribution.describe(),
        "warmup_s": warmup, "warmup_pairs": int(both_built.size), "build_s": wall, "complete": bool(stats["complete"]),
        "jtraj_pairs_per_s": jt_thr, "warmup_chunks_equal": same,
        "converged": int(d["converged"].sum()), "iterations_median": float(np.median(d["iterations"])),
        "ipopt_pairs": M, "ipopt_processes": ip.processes, "ipopt_pairs_per_s": ip_thr,
        "ipopt_build_s_per_worker": ip.setup_seconds, "ratio": jt_thr / ip_thr,
        "ipopt_verified": int(ip_ver.sum()), "jtraj_verified_converged_subset": int((jt_conv & jt_ver).sum()),
        "jtraj_false_converged_subset": int(np.sum(jt_conv & ~jt_ver)),
        "cost_gap_pct_median_both": float(100 * np.median(gap[both])) if both.any() else None,
        "cost_gap_pct_max_both": float(100 * gap[both].max()) if both.any() else None,
        "projected_1000_pairs_s": 1000 / jt_thr, "ipopt_projected_1000_pairs_s": 1000 / ip_thr,
    }
    print(f"  dataset, {pairs} pairs (batch {spec.batch}, {workers} workers, N = {N}, h_max {lim['h_max']:g} s): "
          f"converged {report['converged']}/{pairs}, Newton iterations median {report['iterations_median']:g}; "
          f"untimed warm-up build of {both_built.size} pairs {warmup:.1f} s (compilation included); timed build "
          f"{wall:.1f} s -> {jt_thr:.3f} pairs/s end to end; the pairs both built equal: {same}")
    print(f"  IPOPT loop on the first {M} pairs: {ip_thr:.3f} pairs/s on {ip.processes} processes "
          f"(verified {report['ipopt_verified']}/{M}; jtraj verified {report['jtraj_verified_converged_subset']}/{M}, "
          f"false converged {report['jtraj_false_converged_subset']}) -> ratio {report['ratio']:.2f}x")
    if both.any():
        print(f"  cost gap where both succeed ({both.sum()} pairs): median {report['cost_gap_pct_median_both']:+.4f} %, "
              f"max {report['cost_gap_pct_max_both']:+.4f} %")
    print(f"  projected 1,000 pairs: jtraj {1000 / jt_thr / 60:.1f} min, IPOPT loop {1000 / ip_thr / 60:.1f} min")
    return report


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=64)
    ap.add_argument("--batch", type=int, default=None,
                    help="jtraj's batch (default 32), with --dataset its chunk size (default: jtraj dataset's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--N", type=int, default=40)
    ap.add_argument("--latency-pairs", type=int, default=4)
    ap.add_argument("--workers", type=int, default=None, help="jtraj batch processes (default: all cores)")
    ap.add_argument("--peer-jerk", choices=("auto", "off"), default="off",
                    help="auto: the peer bounds |v_k+1 - v_k| <= qddd_max (h_k + h_k+1)/2 when jtraj's panda "
                         "has jerk limits; use it only where jtraj's transcription bounds the jerk in that same "
                         "form, otherwise the two NLPs differ (default off)")
    ap.add_argument("--first-solution", action="store_true", help="also time a fresh process to a first solution")
    ap.add_argument("--dataset", action="store_true",
                    help="instead: a panda dataset of --pairs pairs (jtraj dataset) against the IPOPT loop on its first "
                         "--ipopt-pairs pairs (dataset_run)")
    ap.add_argument("--ipopt-pairs", type=int, default=8, help="with --dataset: pairs the IPOPT loop solves")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)

    robot = jtraj_panda()  # exits with a clear message when unavailable
    from jtraj.dataset._local import available_cpus, worker_pool
    from jtraj_peers.ipopt_arm import solve_many
    from jtraj_peers.verify_arm import verify

    workers = args.workers or available_cpus()
    lim = _limits(robot)
    jerk = args.peer_jerk == "auto" and lim["qddd_max"] is not None
    if args.dataset:
        print(f"panda dataset, N = {args.N}, weights time=1 energy=0.1, seed {args.seed}, "
              f"os.cpu_count() = {os.cpu_count()}, peer jerk bound: {'on' if jerk else 'off'}")
        report = {"robot": "panda", "dataset": dataset_run(args.pairs, args.batch, args.seed, args.N, workers,
                                                           args.ipopt_pairs, jerk)}
        if args.json:
            with open(args.json, "w") as f:
                json.dump(report, f, indent=2)
        return report
    args.batch = args.batch or 32
    model, spec = peer_spec(lim, jerk)
    q0, q1 = panda_pairs(args.pairs, args.seed, lim["q_min"], lim["q_max"])
    print(f"panda, N = {args.N}, weights time=1 energy=0.1, {args.pairs} pairs (seed {args.seed}), "
          f"os.cpu_count() = {os.cpu_count()}, peer jerk bound: {'on' if jerk else 'off'}")
    kw = dict(tau_max=lim["tau_max"], qd_max=lim["qd_max"], qdd_max=lim["qdd_max"], q_min=lim["q_min"],
              q_max=lim["q_max"], h_min=lim["h_min"], h_max=lim["h_max"], weights=PEER_WEIGHTS, tol=1e-6)

    starts = jtraj_starts(q0, q1, args.N)
    ip = solve_many(spec, q0, q1, N=args.N, weights=PEER_WEIGHTS, inits=starts)
    ip_thr = len(ip) / ip.wall_seconds
    ip_ver = np.array([r["success"] and verify(model, a, b, r["v"], r["h"], **kw)["ok"] for a, b, r in zip(q0, q1, ip)])
    ip_cost = np.array([r["cost"] for r in ip])

    jt = _jtraj_batch(q0, q1, args.N, args.batch, workers)
    jt_thr = args.pairs / jt["wall"]
    jt_conv = jt["converged"].astype(bool)
    jt_ver = np.array([verify(model, a, b, v, h, **kw)["ok"] for a, b, v, h in zip(q0, q1, jt["v"], jt["h"])])
    both = jt_conv & jt_ver & ip_ver
    gap = (jt["cost"] - ip_cost) / ip_cost

    L = min(args.latency_pairs, args.pairs)
    with worker_pool(1) as pool:
        lat, ip_lat, compile_single = pool.submit(_single_latencies, q0[:L], q1[:L], args.N, starts[:L], jerk).result()

    report = {
        "robot": "panda", "pairs": args.pairs, "N": args.N, "batch": args.batch, "jtraj_workers": workers,
        "ipopt_processes": ip.processes, "peer_jerk": jerk,
        "ipopt_success": int(sum(r["success"] for r in ip)), "ipopt_verified": int(ip_ver.sum()),
        "jtraj_converged": int(jt_conv.sum()), "jtraj_verified_converged": int((jt_conv & jt_ver).sum()),
        "jtraj_false_converged": int(np.sum(jt_conv & ~jt_ver)),
        "cost_gap_pct_median_both": float(100 * np.median(gap[both])) if both.any() else None,
        "cost_gap_pct_max_both": float(100 * gap[both].max()) if both.any() else None,
        "ipopt_throughput_all_cores": ip_thr, "jtraj_throughput": jt_thr, "throughput_ratio": jt_thr / ip_thr,
        "ipopt_single_median_s": float(np.median(ip_lat)), "jtraj_single_median_s": float(np.median(lat)),
        "latency_ratio": float(np.median(ip_lat) / np.median(lat)),
        "jtraj_compile_single_s": compile_single, "jtraj_compile_and_first_pass_s": jt["compile_and_first_pass"],
        "ipopt_build_s_per_worker": ip.setup_seconds,
        "jtraj_iterations_median": float(np.median(jt["iterations"])),
        "ipopt_iterations_median": float(np.median([r["iterations"] for r in ip])),
        "per_pair": {"ipopt_verified": ip_ver.tolist(), "ipopt_cost": ip_cost.tolist(),
                     "jtraj_status": jt["status"].astype(int).tolist(), "jtraj_verified": jt_ver.tolist(),
                     "jtraj_cost": jt["cost"].tolist()},
    }
    print(f"  success: IPOPT {report['ipopt_verified']}/{args.pairs} verified; jtraj converged "
          f"{report['jtraj_converged']}/{args.pairs} (verified {report['jtraj_verified_converged']}); "
          f"false converged: {report['jtraj_false_converged']}")
    if both.any():
        print(f"  cost gap where both succeed ({both.sum()} pairs): median {report['cost_gap_pct_median_both']:+.4f} %, "
              f"max {report['cost_gap_pct_max_both']:+.4f} %")
    print(f"  throughput: IPOPT {ip_thr:.3f} pairs/s on {ip.processes} processes; jtraj {jt_thr:.3f} pairs/s "
          f"(batch {args.batch}, {workers} processes) -> ratio {report['throughput_ratio']:.2f}x")
    print(f"  warm single solve (median of {L}): IPOPT {report['ipopt_single_median_s'] * 1e3:.0f} ms, jtraj "
          f"{report['jtraj_single_median_s'] * 1e3:.0f} ms -> ratio {report['latency_ratio']:.2f}x")
    print(f"  compile: jtraj single {compile_single:.1f} s, batch {jt['compile_and_first_pass']:.1f} s (incl. the "
          f"untimed pass); IPOPT NLP build {ip.setup_seconds:.1f} s")
    if args.first_solution:
        report["first_solution"] = fs = first_solution(args.N, args.seed, lim, jerk)
        print(f"  time to first solution (fresh process): jtraj {fs['jtraj']['wall_s']:.1f} s, IPOPT "
              f"{fs['ipopt']['wall_s']:.1f} s -> ratio {fs['ipopt']['wall_s'] / fs['jtraj']['wall_s']:.2f}x")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=2)
    return report


if __name__ == "__main__":
    main()
