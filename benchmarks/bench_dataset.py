"""End-to-end dataset throughput (sampling + solve_batch + atomic HDF5 storage) against the
IPOPT peer on all cores, measured in the same run.

    python benchmarks/bench_dataset.py --quick            # batch 64, 64 timed pairs, 16 IPOPT pairs
    python benchmarks/bench_dataset.py                    # batch sizes 64, 256, 1024, 4096
    python benchmarks/bench_dataset.py --batches 64 128 --chunks 2 --ipopt-pairs 64
    python benchmarks/bench_dataset.py --batches 256 --chunks 8 --ipopt-pairs 64 --inequalities pbm

For each batch size B the benchmark builds a serial3, N = 20, weights time=1,energy=0.1
joint-space dataset through :func:`jtraj.dataset.build` into a temporary directory,
twice. The first build, untimed (reported as ``cold_build_s``), compiles every program
any of its chunks needs into the persistent compilation cache: a chunk compiles the
paths its problems take (the AL loop for the few the interior-point method leaves, its
restart, the narrower lanes of the stragglers), and with one warm-up chunk per worker a
later chunk's compilation (the AL loop's programs, about 17 s on one core) would fall
inside the timed part. The second build: first one chunk per
worker process (worker start-up, programs loaded from the cache: ``first_chunk_s``),
then the remaining ``--chunks`` chunks by *resuming* the same dataset (new worker
processes: their start-up included; by default about 2048 pairs, so that it weighs
little); the resumed part gives the steady-state pairs/s, end to end including sampling
and storage. jtraj runs ``--workers`` pinned worker processes (default one per core, as
``jtraj dataset``). The IPOPT peer (:func:`jtraj_peers.ipopt_peer.solve_many`, one
process per core, NLP built once per process) solves the first ``--ipopt-pairs`` pairs
of the same dataset; its pairs/s is the solve phase (pool start and NLP builds excluded,
which favours IPOPT).

Projected CPU-hours for a million pairs = 1e6 / (pairs/s) / 3600 x cores used (JAX uses
all cores, one worker process per core; the peer one process per core).

Writes ``bench_dataset.json`` and ``bench_dataset.png`` into ``--out-dir``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))


def measure_jtraj(B, chunks, seed, N, solver, workers, options=None):
    from jtraj import dataset

    # an untimed build of the whole spec first (every program any chunk needs compiled and
    # cached); then the first `workers` chunks of a second build (timed apart), the rest timed
    pairs = B * (workers + chunks)
    spec = dataset.make_spec("serial3", pairs, seed, N=N, batch=B, solver=solver, options=options)
    with tempfile.TemporaryDirectory(prefix="bench_dataset_") as tmp:
        out = os.path.join(tmp, "d")
        t0 = time.perf_counter()
        dataset.build(spec, os.path.join(tmp, "cold"), progress=False, workers=workers)
        cold = time.perf_counter() - t0
        t0 = time.perf_counter()
        dataset.build(spec, out, progress=False, max_chunks=workers, workers=workers)
        first = time.perf_counter() - t0
        s = dataset.build(spec, out, progress=True, workers=workers)
        data = dataset.load(out)
        conv = float(np.mean(data["converged"]))
        q0, q1 = data["q_start"].copy(), data["q_goal"].copy()
        size = sum(os.path.getsize(os.path.join(out, "chunks", f)) for f in os.listdir(os.path.join(out, "chunks")))
    return {"batch": B, "pairs": pairs, "timed_pairs": s["new_pairs"], "seconds": s["seconds"],
            "pairs_per_s": s["pairs_per_s"], "first_chunk_s": first, "cold_build_s": cold,
            "converged_fraction": conv,
            "bytes_per_pair": size / pairs, "h_max": float(spec.robot_model().limits.h_max), "workers": workers}, (q0, q1)


def measure_ipopt(q0, q1, processes, N, h_max, formulation="lifted", init="same", options=None):
    """IPOPT on the pairs (``init``: see ``bench_solver.peer_starts``; "same" starts it
    where jtraj's ``options`` start)."""
    from bench_solver import peer_starts
    from jtraj_peers.ipopt_peer import solve_many

    res = solve_many(q0, q1, processes=processes, N=N, h_max=h_max, formulation=formulation,
                     inits=peer_starts(q0, q1, N, init, options, h_max))
    ok = np.array([r["success"] for r in res])
    return {"pairs": len(res), "processes": res.processes, "formulation": formulation, "seconds": res.wall_seconds,
            "setup_seconds": res.setup_seconds, "pairs_per_s": len(res) / res.wall_seconds,
            "success_fraction": float(ok.mean())}


def plot(results, ipopt, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    B = [r["batch"] for r in results]
    rate = [r["pairs_per_s"] for r in results]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].plot(B, rate, "o-", label="jtraj dataset (end to end)")
    if ipopt:
        ax[0].axhline(ipopt["pairs_per_s"], color="tab:red", ls="--",
                      label=f"IPOPT peer, {ipopt['processes']} processes")
        ax[0].axhline(30 * ipopt["pairs_per_s"], color="tab:green", ls=":", label="goal: 30x IPOPT")
    ax[0].set_xscale("log", base=2)
    ax[0].set_yscale("log")
    ax[0].set_xlabel("batch size")
    ax[0].set_ylabel("pairs / s")
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"serial3, N = {results[0].get('N', 20)}, {os.cpu_count()} cores")
    ax[1].bar([str(b) for b in B], [100 * r["converged_fraction"] for r in results])
    ax[1].set_xlabel("batch size")
    ax[1].set_ylabel("converged [%]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="batch 64 only, 1 timed chunk, 16 IPOPT pairs")
    ap.add_argument("--batches", type=int, nargs="+", default=None, help="batch sizes (default 64 256 1024 4096)")
    ap.add_argument("--chunks", type=int, default=None,
                    help="timed chunks per batch size (default: 2048 / B, at least 2; quick 1)")
    ap.add_argument("--ipopt-pairs", type=int, default=None, help="pairs for the IPOPT peer (default 64; quick 16)")
    ap.add_argument("--processes", type=int, default=None, help="IPOPT processes (default all cores)")
    ap.add_argument("--workers", type=int, default=None,
                    help="jtraj worker processes, one pinned to each core (default all cores)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--N", type=int, default=20)
    ap.add_argument("--no-ipopt", action="store_true")
    ap.add_argument("--peer-formulation", choices=("lifted", "condensed"), default="lifted",
                    help="CasADi form of the IPOPT peer (default lifted, the fast one; see jtraj_peers/ipopt_peer.py)")
    ap.add_argument("--peer-init", choices=("same", "cycloidal"), default="same",
                    help="IPOPT's starting point: jtraj's (default) or the peer's own kinematic cycloid")
    ap.add_argument("--solver", default="jtraj:solve_batch", help=argparse.SUPPRESS)
    ap.add_argument("--out-dir", default=".", help="where bench_dataset.json/.png go")
    ap.add_argument("--method", choices=("auto", "al", "ip"), default="auto",
                    help="jtraj's inner method (as jtraj dataset --method)")
    ap.add_argument("--inequalities", choices=("phr", "pbm"), default="phr",
                    help="jtraj's inequality term (as jtraj dataset --inequalities)")
    args = ap.parse_args(argv)
    batches = args.batches or ([64] if args.quick else [64, 256, 1024, 4096])
    # by default about 2048 timed pairs per batch size: the timed resume starts (and
    # loads programs in) fresh workers, which two chunks of 256 cannot amortise
    n_ipopt = args.ipopt_pairs or (16 if args.quick else 64)

    from jtraj.cli import setup_jax

    setup_jax()
    import jax

    cores = os.cpu_count() or 1
    from jtraj.dataset._local import available_cpus

    workers = args.workers or available_cpus()
    from jtraj.solver import PBM_SETTINGS

    options = dict(PBM_SETTINGS) if args.inequalities == "pbm" else {}
    options["method"] = args.method
    from jtraj import _kkt_native

    print(_kkt_native.status(3), flush=True)  # (the workers' own, on this machine)
    results, pairs = [], None
    for B in batches:
        chunks = args.chunks or (1 if args.quick else max(2, 2048 // B))
        r, qq = measure_jtraj(B, chunks, args.seed, args.N, args.solver, workers, options)
        r["N"] = args.N
        results.append(r)
        if pairs is None or len(qq[0]) > len(pairs[0]):
            pairs = qq
        print(f"batch {B:5d}: {r['pairs_per_s']:8.2f} pairs/s ({r['timed_pairs']} pairs in {r['seconds']:.1f} s; "
              f"first chunk {r['first_chunk_s']:.1f} s; the untimed first build, compilation included, "
              f"{r['cold_build_s']:.1f} s), converged {100 * r['converged_fraction']:.1f} %"
              f", {r['bytes_per_pair']:.0f} B/pair on disk", flush=True)
    ipopt = None
    if not args.no_ipopt:
        m = min(n_ipopt, len(pairs[0]))
        # the same problems: the dataset's period bound (twice the robot's by default)
        ipopt = measure_ipopt(pairs[0][:m], pairs[1][:m], args.processes, args.N, results[0]["h_max"],
                              args.peer_formulation, args.peer_init, options)
        print(f"IPOPT peer: {ipopt['pairs_per_s']:.2f} pairs/s on {ipopt['processes']} processes "
              f"({ipopt['pairs']} pairs in {ipopt['seconds']:.1f} s, setup {ipopt['setup_seconds']:.1f} s), "
              f"success {100 * ipopt['success_fraction']:.1f} %")
    best = max(results, key=lambda r: r["pairs_per_s"])
    summary = {"cores": cores, "jax": jax.__version__, "N": args.N, "inequalities": args.inequalities, "method": args.method,
               "peer_init": args.peer_init,
               "results": results, "ipopt": ipopt,
               "best_batch": best["batch"], "best_pairs_per_s": best["pairs_per_s"],
               "cpu_hours_per_million": 1e6 / best["pairs_per_s"] / 3600 * cores}
    if ipopt:
        summary["ratio_vs_ipopt"] = best["pairs_per_s"] / ipopt["pairs_per_s"]
        summary["ipopt_cpu_hours_per_million"] = 1e6 / ipopt["pairs_per_s"] / 3600 * ipopt["processes"]
        for r in results:
            r["ratio_vs_ipopt"] = r["pairs_per_s"] / ipopt["pairs_per_s"]
    print(f"best: batch {best['batch']}, {best['pairs_per_s']:.2f} pairs/s"
          + (f" = {summary['ratio_vs_ipopt']:.2f}x IPOPT" if ipopt else "")
          + f"; projected {summary['cpu_hours_per_million']:.1f} CPU-hours per million pairs"
          + (f" (IPOPT {summary['ipopt_cpu_hours_per_million']:.1f})" if ipopt else "")
          + f"; 10,000 pairs in {1e4 / best['pairs_per_s'] / 60:.1f} min on {cores} cores")
    os.makedirs(args.out_dir, exist_ok=True)
    with open(os.path.join(args.out_dir, "bench_dataset.json"), "w") as f:
        json.dump(summary, f, indent=1)
    plot(results, ipopt, os.path.join(args.out_dir, "bench_dataset.png"))
    print(f"wrote {os.path.join(args.out_dir, 'bench_dataset.json')} and bench_dataset.png")
    return summary


if __name__ == "__main__":
    main()
