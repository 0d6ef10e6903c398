"""jtraj's ALD solver against CasADi + IPOPT on the canonical serial3 benchmark.

    python benchmarks/bench_solver.py [--pairs 64] [--batch 64] [--seed 0] [--N 20]
                                      [--peer-formulation lifted|condensed] [--peer-init same|cycloidal]
                                      [--linear-solver auto|riccati|dense]
                                      [--option KEY=VALUE ...]
                                      [--scaling] [--plot bench_solver.png] [--json out.json]

Problem family (issue #3): serial3, N = 20, weights time = 1, energy = 0.1, q_start ~
U(-1.2, 1.2)^3, q_goal = q_start + U(-0.8, 0.8)^3 (``jtraj_peers.ipopt_peer.benchmark_pairs``).
Both solvers see the same pairs in the same run. Every trajectory either side calls a
success is re-simulated from its own (v, h) by the independent NumPy + Pinocchio
verifier (tolerance 1e-6). Printed: verified success rates, false "converged" counts,
cost gaps where both succeed, warm single-solve latency (median over pairs, best of 3
per pair, both solvers in one process pinned to one core, alternating), batch
throughput on all cores (IPOPT: one process per core, one pass over the pairs; jtraj:
vmapped batches, one process pinned to each core, ``--workers``, the median of three
timed passes after an untimed one), compile time, and, with ``--scaling``,
time per problem against N = 10..80 for both solvers on all cores (T <= 2 s throughout)
and against the batch size B = 64..4096 for jtraj on one core (``_scaling``; ``--plot``
draws both). ``--json`` also holds every pair's
statuses, costs and iterations (``per_pair``).
Ratios are jtraj / IPOPT or IPOPT / jtraj as labelled; > 1 means jtraj is ahead.
Both solvers start from jtraj's starting point (``--peer-init same``, the default:
jtraj's torque-scaled cycloid, from which IPOPT too needs fewer iterations, median 30
instead of 54 on 256 pairs of seed 1); ``--peer-init cycloidal`` gives IPOPT Khoukhi's
kinematic cycloid.
The peer is the "lifted" CasADi form by default (states as variables, sparse; the fast
one); "condensed" (states eliminated) is 4-6x slower per IPOPT iteration.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.append(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root: jtraj_peers


KEYS = ("v", "h", "cost", "converged", "status", "iterations")
WEIGHTS = dict(time=1.0, energy=0.1)  # the benchmark's cost (plain values: sent to workers)


def _robot(h_max=None):
    import jtraj

    return jtraj.robots.get("serial3", **({} if h_max is None else {"h_max": h_max}))


def _solve_chunk(q0, q1, N, weights, options=None, h_max=None):
    """One solve_batch call (runs in a worker process or here); numpy arrays. ``h_max``:
    the robot's period bound unless given (the scaling study keeps N h_max at 2 s)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jtraj
    from jtraj.solver.options import from_overrides

    sol = jtraj.solve_batch(_robot(h_max), q0, q1, N=N, weights=jtraj.Weights(**weights),
                            solver=from_overrides(options or {}))
    return {k: np.asarray(getattr(sol, k)) for k in KEYS}


def peer_starts(q0, q1, N, which, options=None, h_max=None):
    """IPOPT's starting points for the pairs: None for "cycloidal" (the peer's own,
    Khoukhi's kinematic cycloid, ``jtraj_peers.ipopt_peer.cycloidal_init``), or for "same"
    jtraj's starting point under ``options`` (its ``guess``, default the torque-scaled
    cycloid), so that both solvers start from the same point. IPOPT's clock does not
    include them (nor its own guess)."""
    if which == "cycloidal":
        return None
    import equinox as eqx
    import jax

    jax.config.update("jax_enable_x64", True)
    import jtraj
    from jtraj.initial_guess import GUESSES

    robot = _robot(h_max)
    guess = GUESSES[jtraj.SolverOptions(**(options or {})).guess]
    v, h = eqx.filter_jit(eqx.filter_vmap(lambda a, b: guess(jtraj.Problem(robot, a, b, N=N, validate=False))))(
        np.asarray(q0, float), np.asarray(q1, float))
    return [(np.asarray(a), np.asarray(b)) for a, b in zip(v, h)]


def _option(text):
    """'key=value' -> (key, value) with value as int, float or str."""
    key, sep, value = text.partition("=")
    if not sep:
        raise SystemExit(f"--option wants KEY=VALUE, got {text!r}")
    for kind in (int, float):
        try:
            return key, kind(value)
        except ValueError:
            pass
    return key, value


def _jtraj_batch(q0, q1, N, B, weights, workers=1, options=None, h_max=None):
    """Throughput of solve_batch on chunks of B pairs: in this process (workers = 1) or in
    ``workers`` processes pinned one per core (jtraj.dataset's local
    backend; one JAX process does not use several cores well). The first chunk per worker
    (compilation, or loading it from the persistent cache) is timed apart; with workers,
    every worker first solves every chunk untimed (see below)."""
    P = len(q0)
    pad = (-P) % B
    q0p = np.concatenate([q0, np.repeat(q0[-1:], pad, 0)])
    q1p = np.concatenate([q1, np.repeat(q1[-1:], pad, 0)])
    chunks = [(q0p[s:s + B], q1p[s:s + B], N, weights, options, h_max) for s in range(0, len(q0p), B)]
    if workers == 1:
        t0 = time.perf_counter()
        _solve_chunk(*chunks[0])
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        parts = [_solve_chunk(*c) for c in chunks]
        wall = time.perf_counter() - t0
    else:
        from jtraj.dataset._local import worker_pool

        with worker_pool(workers) as pool:
            # every worker solves every chunk once untimed: a chunk compiles the paths its
            # problems take (the restart of an uncertified run, the narrower lanes of the
            # stragglers), and warming up on the first chunk alone left a compilation
            # inside the timed pass where only a later chunk needed a restart (seed 11:
            # 15.2 instead of ~28 pairs/s)
            t0 = time.perf_counter()
            for c in chunks:
                list(pool.map(_solve_chunk, *zip(*[c] * workers)))
            first = time.perf_counter() - t0
            # the timed pass three times, its median: one pass of two chunks of 256 takes
            # about a second, and a shared machine's speed swings within seconds (two
            # single-pass runs a few minutes apart can differ by 15 %)
            walls = []
            for _ in range(3):
                t0 = time.perf_counter()
                parts = list(pool.map(_solve_chunk, *zip(*chunks)))
                walls.append(time.perf_counter() - t0)
            wall = float(np.median(walls))
    res = {k: np.concatenate([p[k] for p in parts])[:P] for k in KEYS}
    res["wall"] = wall
    res["compile_and_first_batch"] = first
    return res


def _single_latencies(q0, q1, N, weights, repeats=3, options=None, formulation="lifted", starts=None):
    """Warm single-solve times of both solvers (best of ``repeats`` per pair, each) and
    jtraj's first call's time: (jtraj (L,), IPOPT (L,), compile s). Run by
    :func:`_pinned_single_latency` in one process pinned to one core, like an IPOPT solve
    (one problem runs faster there, see ``jtraj._cpu``), the two solvers alternating pair
    by pair: measured apart (IPOPT in the unpinned main process afterwards), a core's
    noise of the minute fell on one side only (the same jtraj solves can take 4.0 and
    7.6 ms in two processes pinned to one core a minute apart)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jtraj
    from jtraj.solver.options import from_overrides
    from jtraj_peers.ipopt_peer import solve_pair

    robot = jtraj.robots.get("serial3")
    weights = jtraj.Weights(**weights)
    solver = from_overrides(options or {})
    problems = [jtraj.Problem(robot, a, b, N=N, weights=weights, validate=False) for a, b in zip(q0, q1)]
    t0 = time.perf_counter()
    jax.block_until_ready(jtraj.solve(problems[0], solver=solver).status)
    compile_s = time.perf_counter() - t0

    def peer_seconds(i):
        return solve_pair(q0[i], q1[i], N=N, formulation=formulation,
                          init=None if starts is None else starts[i])["seconds"]

    peer_seconds(0)  # the peer's NLP build
    ours, peer = [], []
    for i, p in enumerate(problems):
        best = np.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(jtraj.solve(p, solver=solver).status)
            best = min(best, time.perf_counter() - t0)
        ours.append(best)
        peer.append(min(peer_seconds(i) for _ in range(repeats)))
    return np.array(ours), np.array(peer), compile_s


def _pinned_single_latency(q0, q1, N, weights, options=None, formulation="lifted", starts=None):
    from jtraj.dataset._local import worker_pool

    with worker_pool(1) as pool:  # a spawned process pinned to one core before JAX starts
        return pool.submit(_single_latencies, q0, q1, N, weights, 3, options, formulation, starts).result()


#: the scaling study (``--scaling``): numbers of samples, and batch sizes in one process
SCALING_N = (10, 20, 40, 80)
SCALING_B = (64, 256, 1024, 4096)
SCALING_T = 2.0  # s: N h_max, held fixed over N (the canonical 20 x 0.1 s)


def _batch_scan(Bs, seed, N, weights, options=None):
    """jtraj's time per problem against the batch size, in this (pinned) process: for each
    B one ``solve_batch`` of B fresh benchmark pairs, after a call on B non-finite pairs
    that compiles the B-wide kernels (preparation, guess, gather and scatter) without
    iterating (those samples are ``INVALID_INPUT`` at once); the solver's loop, restart
    and finish kernels do not depend on B (fixed lanes, see ``jtraj.solve_batch``) and are
    compiled by the first small batches."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from jtraj_peers.pairs import benchmark_pairs

    from jtraj import SolverOptions

    h_max = SCALING_T / N  # as in the N scan
    # the loop's and the restart's kernels (they do not depend on B): warm-up batches until
    # one of them had a restart (iterations beyond max_iter), at most four
    max_iter = SolverOptions(**(options or {})).max_iter
    for k in range(4):
        if np.any(_solve_chunk(*benchmark_pairs(Bs[0], seed + 100 + k), N, weights, options, h_max)["iterations"]
                  > max_iter):
            break
    rows = []
    for B in Bs:
        q0, q1 = benchmark_pairs(B, seed)
        _solve_chunk(np.full_like(q0, np.nan), q1, N, weights, options, h_max)
        t0 = time.perf_counter()
        res = _solve_chunk(q0, q1, N, weights, options, h_max)
        wall = time.perf_counter() - t0
        rows.append({"axis": "B", "value": B, "N": N, "jtraj_ms": 1e3 * wall / B,
                     "jtraj_converged": int(res["converged"].sum()), "pairs": B,
                     "jtraj_iterations_median": float(np.median(res["iterations"]))})
    return rows


def _scaling(args, opts):
    """``--scaling``: (1) time per problem against N, both solvers on all cores on the same
    ``--scaling-pairs`` pairs, with the bound on T held at ``SCALING_T`` (h_max = 2 s / N,
    so that only the discretisation changes: with the robot's 0.1 s, N = 10 would cap T
    at 1 s, which most pairs need more than); every success of either side verified
    (1e-6); (2) jtraj's time per problem against the batch size B, in one process pinned
    to one core (IPOPT's time per problem on one core is its all-core time times its
    processes, from the row of the same N, if the N scan has one)."""
    from jtraj_peers.ipopt_peer import benchmark_pairs, solve_many
    from jtraj_peers.verify import verify

    from jtraj.dataset._local import worker_pool

    P = args.scaling_pairs
    q0, q1 = benchmark_pairs(P, args.seed + 1)
    rows = []
    for N in SCALING_N:
        h_max = SCALING_T / N
        ip = solve_many(q0, q1, N=N, h_max=h_max, formulation=args.peer_formulation,
                        inits=peer_starts(q0, q1, N, args.peer_init, opts, h_max))
        ip_ok = np.array([r["success"] and verify(a, b, r["v"], r["h"], h_max=h_max, tol=1e-6)["ok"]
                          for a, b, r in zip(q0, q1, ip)])
        jt = _jtraj_batch(q0, q1, N, -(-P // args.workers), WEIGHTS, args.workers, opts, h_max)
        jt_ok = jt["converged"].astype(bool) & np.array(
            [verify(a, b, v, h, h_max=h_max, tol=1e-6)["ok"] for a, b, v, h in zip(q0, q1, jt["v"], jt["h"])])
        row = {"axis": "N", "value": N, "h_max": h_max, "pairs": P,
               "ipopt_ms": 1e3 * ip.wall_seconds / P, "jtraj_ms": 1e3 * jt["wall"] / P,
               "ipopt_processes": ip.processes, "ipopt_verified": int(ip_ok.sum()), "jtraj_converged": int(jt_ok.sum()),
               "jtraj_false_converged": int(np.sum(jt["converged"].astype(bool) & ~jt_ok)),
               "ipopt_iterations_median": float(np.median([r["iterations"] for r in ip])),
               "jtraj_iterations_median": float(np.median(jt["iterations"])),
               "jtraj_compile_and_first_pass_s": jt["compile_and_first_batch"]}
        row["throughput_ratio"] = row["ipopt_ms"] / row["jtraj_ms"]
        rows.append(row)
        print(f"  N = {N:2d} (h_max {h_max:.4g} s, {P} pairs, all cores): IPOPT {row['ipopt_ms']:.1f} ms per problem "
              f"({row['ipopt_verified']} verified, median {row['ipopt_iterations_median']:.0f} it), jtraj "
              f"{row['jtraj_ms']:.1f} ms ({row['jtraj_converged']} converged, {row['jtraj_false_converged']} false, "
              f"median {row['jtraj_iterations_median']:.0f} it) -> {row['throughput_ratio']:.2f}x")
    with worker_pool(1) as pool:  # a spawned process pinned to one core before JAX starts
        b_rows = pool.submit(_batch_scan, SCALING_B, args.seed + 2, args.N, WEIGHTS, opts).result()
    ip_core_ms = next((r["ipopt_ms"] * r["ipopt_processes"] for r in rows if r["value"] == args.N), None)
    for r in b_rows:
        r["ipopt_one_core_ms"] = ip_core_ms
        print(f"  B = {r['value']:4d} (N = {args.N}, one process on one core): "
              f"jtraj {r['jtraj_ms']:.1f} ms per problem ({r['jtraj_converged']}/{r['pairs']} converged)"
              + ("" if ip_core_ms is None else f"; IPOPT on one core {ip_core_ms:.1f} ms"))
    return rows + b_rows


def _plot_scaling(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    n_rows = [r for r in rows if r["axis"] == "N"]
    b_rows = [r for r in rows if r["axis"] == "B"]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    Ns = [r["value"] for r in n_rows]
    ax[0].loglog(Ns, [r["jtraj_ms"] for r in n_rows], "o-", label="jtraj (vmapped, all cores)")
    ax[0].loglog(Ns, [r["ipopt_ms"] for r in n_rows], "s--", c="k", label="CasADi + IPOPT (all cores)")
    for r in n_rows:
        ax[0].annotate(f"{r['jtraj_converged']}/{r['ipopt_verified']}", (r["value"], r["jtraj_ms"]),
                       textcoords="offset points", xytext=(4, -12), fontsize=7)
    ax[0].set_xticks(Ns, [str(n) for n in Ns], minor=False)
    ax[0].xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
    ax[0].set_xlabel(f"N (T <= {SCALING_T:g} s: h_max = {SCALING_T:g} s / N)")
    ax[0].set_ylabel("wall ms per problem")
    ax[0].set_title("against N (labels: converged jtraj / IPOPT)", fontsize=9)
    ax[0].legend(fontsize=8)
    Bs = [r["value"] for r in b_rows]
    ax[1].semilogx(Bs, [r["jtraj_ms"] for r in b_rows], "o-", label="jtraj, one core")
    if b_rows[0]["ipopt_one_core_ms"] is not None:
        ax[1].axhline(b_rows[0]["ipopt_one_core_ms"], ls="--", c="k", label="IPOPT, one core")
    ax[1].set_xticks(Bs, [str(b) for b in Bs])
    ax[1].xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
    ax[1].set_ylim(bottom=0)
    ax[1].set_xlabel(f"batch size B (N = {b_rows[0]['N']})")
    ax[1].set_ylabel("wall ms per problem")
    ax[1].set_title("against the batch size", fontsize=9)
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=64)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--N", type=int, default=20)
    ap.add_argument("--latency-pairs", type=int, default=8)
    ap.add_argument("--workers", type=int, default=None,
                    help="jtraj batch processes, one pinned to each core (default: all cores, as IPOPT)")
    ap.add_argument("--scaling", action="store_true",
                    help="also time N = 10..80 against IPOPT and B = 64..4096 (see _scaling; --plot draws it)")
    ap.add_argument("--scaling-pairs", type=int, default=64, help="pairs per N in the scaling study")
    ap.add_argument("--peer-init", choices=("same", "cycloidal"), default="same",
                    help="IPOPT's starting point: jtraj's (default: both solvers start from the same point) "
                         "or the peer's own kinematic cycloid (see peer_starts)")
    ap.add_argument("--peer-formulation", choices=("lifted", "condensed"), default="lifted",
                    help="CasADi form of the IPOPT peer (default lifted, the fast one; see jtraj_peers/ipopt_peer.py)")
    ap.add_argument("--linear-solver", choices=("auto", "riccati", "dense"), default="auto",
                    help="jtraj.SolverOptions.linear_solver (the Newton systems: stage-wise or dense)")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="another jtraj.SolverOptions field, e.g. --option inner_tol_ratio=0 (repeatable)")
    ap.add_argument("--plot", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    if args.workers is None:
        from jtraj.dataset._local import available_cpus

        args.workers = available_cpus()

    import jax

    jax.config.update("jax_enable_x64", True)
    from jtraj_peers.ipopt_peer import benchmark_pairs, solve_many
    from jtraj_peers.verify import verify

    q0, q1 = benchmark_pairs(args.pairs, args.seed)
    print(f"serial3, N = {args.N}, weights time=1 energy=0.1, {args.pairs} pairs (seed {args.seed}), "
          f"os.cpu_count() = {os.cpu_count()}")
    from jtraj import _kkt_native

    print(f"  {_kkt_native.status(3)}")

    opts = {"linear_solver": args.linear_solver, **dict(_option(o) for o in args.option)}
    starts = peer_starts(q0, q1, args.N, args.peer_init, opts)
    ip = solve_many(q0, q1, N=args.N, formulation=args.peer_formulation, inits=starts)
    ip_thr = len(ip) / ip.wall_seconds
    ip_ok = np.array([r["success"] for r in ip])
    ip_ver = np.array([r["success"] and verify(a, b, r["v"], r["h"], tol=1e-6)["ok"] for a, b, r in zip(q0, q1, ip)])
    ip_cost = np.array([r["cost"] for r in ip])

    chunks = -(-args.pairs // args.batch)
    if chunks < args.workers:
        print(f"  note: {chunks} chunk(s) of {args.batch} pairs for {args.workers} jtraj workers: only {chunks} "
              f"core(s) solve, IPOPT uses {args.workers} (use --pairs >= {args.workers} x --batch)")
    jt = _jtraj_batch(q0, q1, args.N, args.batch, WEIGHTS, args.workers, opts)
    jt_thr = args.pairs / jt["wall"]
    checks = [verify(a, b, v, h, tol=1e-6) for a, b, v, h in zip(q0, q1, jt["v"], jt["h"])]
    jt_conv = jt["converged"].astype(bool)
    jt_ver = np.array([c["ok"] for c in checks])
    false_conv = int(np.sum(jt_conv & ~jt_ver))
    both = jt_conv & ip_ver
    gap = (jt["cost"] - ip_cost) / ip_cost

    L = min(args.latency_pairs, args.pairs)
    lat, ip_lat, compile_single = _pinned_single_latency(q0[:L], q1[:L], args.N, WEIGHTS, opts,
                                                         args.peer_formulation, None if starts is None else starts[:L])

    report = {
        "pairs": args.pairs, "N": args.N, "batch": args.batch, "jtraj_workers": args.workers,
        "peer_formulation": args.peer_formulation, "peer_init": args.peer_init, "solver_options": opts,
        "ipopt_success": int(ip_ok.sum()), "ipopt_verified": int(ip_ver.sum()),
        "jtraj_converged": int(jt_conv.sum()), "jtraj_verified_converged": int((jt_conv & jt_ver).sum()),
        "jtraj_feasible_verified": int(jt_ver.sum()), "jtraj_false_converged": false_conv,
        "cost_gap_pct_max_both": float(100 * gap[both].max()) if both.any() else None,
        "cost_gap_pct_median_both": float(100 * np.median(gap[both])) if both.any() else None,
        "ipopt_throughput_all_cores": ip_thr, "jtraj_throughput": jt_thr,
        "throughput_ratio": jt_thr / ip_thr,
        "ipopt_single_median_s": float(np.median(ip_lat)), "jtraj_single_median_s": float(np.median(lat)),
        "latency_ratio": float(np.median(ip_lat) / np.median(lat)),
        "jtraj_compile_single_s": compile_single, "jtraj_compile_and_first_batch_s": jt["compile_and_first_batch"],
        "jtraj_iterations_median": float(np.median(jt["iterations"])),
        "ipopt_iterations_median": float(np.median([r["iterations"] for r in ip])),
        "jtraj_status_counts": {int(k): int(v) for k, v in zip(*np.unique(jt["status"], return_counts=True))},
        # where jtraj's work goes: the share of all Newton iterations spent per status
        "jtraj_iteration_share_by_status": {
            int(k): float(jt["iterations"][jt["status"] == k].sum() / max(jt["iterations"].sum(), 1))
            for k in np.unique(jt["status"])},
        # per pair, in the order of benchmark_pairs(pairs, seed): which pairs either side lost
        "per_pair": {
            "ipopt_verified": ip_ver.tolist(), "ipopt_cost": ip_cost.tolist(),
            "ipopt_iterations": [int(r["iterations"]) for r in ip],
            "jtraj_status": jt["status"].astype(int).tolist(), "jtraj_verified": jt_ver.tolist(),
            "jtraj_cost": jt["cost"].tolist(), "jtraj_iterations": jt["iterations"].astype(int).tolist(),
        },
    }
    print(f"  success: IPOPT {report['ipopt_verified']}/{args.pairs} verified; jtraj converged "
          f"{report['jtraj_converged']}/{args.pairs} (verified {report['jtraj_verified_converged']}), "
          f"feasible (verified) {report['jtraj_feasible_verified']}; false converged: {false_conv}")
    if both.any():
        print(f"  cost gap where both succeed ({both.sum()} pairs): median {report['cost_gap_pct_median_both']:+.4f} %, "
              f"max {report['cost_gap_pct_max_both']:+.4f} % (pair {int(np.argmax(np.where(both, gap, -np.inf)))})")
    lost = np.where(ip_ver & ~jt_conv)[0]
    if lost.size:
        print(f"  pairs IPOPT solves and jtraj does not: {lost.tolist()} (statuses {jt['status'][lost].tolist()})")
    print(f"  throughput: IPOPT {ip_thr:.2f} pairs/s on {ip.processes} processes; jtraj {jt_thr:.2f} pairs/s "
          f"(batch {args.batch}, {args.workers} processes) -> ratio {report['throughput_ratio']:.2f}x")
    print(f"  warm single solve (median of {L}): IPOPT {report['ipopt_single_median_s'] * 1e3:.0f} ms, jtraj "
          f"{report['jtraj_single_median_s'] * 1e3:.0f} ms -> ratio {report['latency_ratio']:.2f}x")
    print(f"  compile: single {compile_single:.1f} s, batch {jt['compile_and_first_batch']:.1f} s "
          "(incl. the untimed warm-up pass)")
    print(f"  iterations median: jtraj {report['jtraj_iterations_median']:.0f}, IPOPT {report['ipopt_iterations_median']:.0f}; "
          f"jtraj statuses {report['jtraj_status_counts']}")
    print("  share of jtraj's iterations by status: " + ", ".join(
        f"{k}: {100 * v:.0f} %" for k, v in report["jtraj_iteration_share_by_status"].items()))

    if args.scaling:
        report["scaling"] = _scaling(args, opts)
        if args.plot:
            _plot_scaling(report["scaling"], args.plot)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=2)
    return report


if __name__ == "__main__":
    main()
