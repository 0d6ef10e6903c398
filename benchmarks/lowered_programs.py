"""The lowered StableHLO text of the solver's compiled programs, one file per program, so
that a refactor can show it leaves the programs unchanged (``diff -r`` of two runs).

The programs: the staged single solve's interior-point and augmented-Lagrangian
programs (:mod:`jtraj.solver.staged`), the single traced program
(``jtraj.solver.core.solve_jit``), the vmapped batch program, and the lane driver's
segment, restart and interior-point pool programs (:mod:`jtraj.solver.lanes`), each for
serial3 at the given N with the decoupled transcription and with ``--transcription``
(whose problems take the AL method: no interior-point programs there). Only tracing and
lowering, no XLA compilation; run from the tree whose programs to dump::

    PYTHONPATH=$PWD python benchmarks/lowered_programs.py --out /tmp/hlo-after
    diff -r /tmp/hlo-before /tmp/hlo-after && echo identical
"""

from __future__ import annotations

import argparse
import os
import sys

import jax

jax.config.update("jax_enable_x64", True)


def problems(N: int, B: int):
    """The quick-start problem and a batch of B problems (serial3, fixed seed)."""
    import numpy as np

    from jtraj import Problem, Weights, robots
    from jtraj.problem import ik_or_raise

    robot = robots.get("serial3")
    q_start = np.deg2rad([0.0, 30.0, 30.0])
    q_goal = np.asarray(ik_or_raise(robot, np.array([1.35, 1.30]), q_start, "goal"))
    one = Problem(robot, q_start, q_goal, N=N, weights=Weights.parse("time=1,energy=1"))
    rng = np.random.default_rng(0)
    qs = q_start + 0.3 * rng.standard_normal((B, 3))
    qg = q_goal + 0.3 * rng.standard_normal((B, 3))
    return one, robot, qs, qg


def dump(out: str, N: int, transcription: str, B: int = 4) -> None:
    import numpy as np

    from jtraj import _packing, _tracecache
    from jtraj import _testing as S
    from jtraj.solver import lanes
    from jtraj.transcription import Transcription

    # the lane programs' plain jit (with .lower), not the process cache's loaded programs
    _tracecache.cached = lambda name, fn, static, options=None, fallback=None, lean=False: fallback
    lanes._lane_programs.cache_clear()
    one, robot, qs, qg = problems(N, B)
    opts = S.resolve_method(None, transcription, robot)
    split = S.split_options(opts)
    tr = Transcription(transcription)
    init = S.placeholder_init(N, tr.control_dim(one))
    yes, no = np.bool_(True), np.bool_(False)
    tag = f"{transcription}-N{N}"

    def write(name, text):
        with open(os.path.join(out, f"{tag}-{name}.mlir"), "w") as f:
            f.write(text)
        print(f"{tag}-{name}: {len(text.splitlines())} lines", flush=True)

    def lower(fn, *args):
        return jax.jit(fn).lower(*args).as_text()

    if opts.method == "ip":
        write("staged-ip", lower(lambda p, s, i: S.staged_ip_jit.__wrapped__(
            p, S.TracedOptions(s), transcription, i, no, yes), one, split, init))
    write("staged-al", lower(lambda p, s, i: S.staged_al_jit.__wrapped__(
        p, S.TracedOptions(s), transcription, i, no, yes, None), one, split, init))
    write("solve-jit", lower(lambda p, s, i: S.solve_jit.__wrapped__(
        p, S.TracedOptions(s), transcription, i, no, yes), one, split, init))

    batch = jax.jit(lambda qs, qg: jax.vmap(lambda a, b: type(one)(
        robot, a, b, N=N, weights=one.weights, validate=False))(qs, qg))(qs, qg)
    binit = S.guess_batch_jit(batch, opts, transcription)
    write("batch-jit", lower(lambda p, s, i: S.solve_batch_jit.__wrapped__(
        p, S.TracedOptions(s), transcription, i, no), batch, split, binit))

    nlps, states, valid = S.prepare_batch_jit(batch, opts, transcription, binit, no)
    progs = S.lane_programs(_packing.packing(nlps), _packing.packing(states), 10, jax.default_backend())
    all_nlps, all_states = progs.pack(_packing.arrays(nlps), _packing.arrays(states), None)
    lanes_ = np.arange(2)
    sub_nlps, sub_states = progs.take(all_nlps, all_states, lanes_)
    write("lane-segment", progs.segment.lower(sub_nlps, sub_states, split).as_text())
    write("lane-restart", progs.restart.lower(sub_nlps, sub_states, np.array([True, False]), split).as_text())
    if opts.method == "ip":
        ips = S.ip_init_batch_jit(nlps, states, opts)
        pp = S.lane_programs(_packing.packing(nlps), _packing.packing(ips), 0, jax.default_backend())
        size = 64
        all_nlps, all_ips = pp.pack(_packing.arrays(nlps), _packing.arrays(ips), size)
        q = np.zeros(size, np.int64)
        q[:B] = np.arange(B)
        write("lane-pool", pp.pool.lower(all_nlps, all_ips, q, np.asarray(B), np.arange(2), np.ones(2, bool),
                                         np.asarray(0), split).as_text())


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--N", type=int, default=10)
    ap.add_argument("--transcription", default="spline", help="the second transcription (default spline)")
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    for transcription in ("decoupled", args.transcription):
        dump(args.out, args.N, transcription)
    return 0


if __name__ == "__main__":
    sys.exit(main())
