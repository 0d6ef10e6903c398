"""Where the solver's first compilation goes: trace+lower and XLA compile seconds and
HLO sizes of the single-problem solve and of its pieces (serial3 quick-start problem).

Run in a fresh process with private caches, e.g.::

    JTRAJ_NATIVE_DIR=$(mktemp -d) python benchmarks/profile_compile.py --full --staged --pieces

``--full``: the single traced program (``jtraj.solver.core.solve_jit``, what a solve under
an outer jit runs); ``--staged``: the two programs of a concrete single solve
(:mod:`jtraj.solver.staged`), and the interior-point one again at XLA's LLVM optimisation
levels 1 and 0 (see ``bench_opt_level.py``; level 0 is a process's quick first call, also
with the XLA version of the KKT solve that a machine's first solve runs while the native
kernel is built); ``--pieces``: the parts of the single program
compiled apart. Each program is traced and lowered by ``jax.jit`` in this process (the
first trace of a process also pays JAX's one-time set-up), then compiled; HLO ops
counts the instructions of the optimised module.
"""

from __future__ import annotations

import argparse
import re
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)


def quick_start_problem(N=20):
    """The README quick-start problem (serial3, start (0, 30, 30) deg, goal tip at
    (1.35, 1.30) m, weights time=1, energy=1)."""
    import numpy as np

    from jtraj import Problem, Weights, robots
    from jtraj.problem import ik_or_raise

    robot = robots.get("serial3")
    q_start = np.deg2rad([0.0, 30.0, 30.0])
    q_goal = np.asarray(ik_or_raise(robot, np.array([1.35, 1.30]), q_start, "goal"))
    return Problem(robot, q_start, q_goal, N=N, weights=Weights.parse("time=1,energy=1"))


def hlo_ops(text: str) -> int:
    """Instructions of an HLO module's text (lines defining a value)."""
    return sum(1 for line in text.splitlines() if re.match(r"\s*(ROOT )?%?[\w.\-]+ = ", line))


def measure(name, fn, *args, options=None):
    t0 = time.perf_counter()
    lowered = jax.jit(fn).lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile(options or {})
    t2 = time.perf_counter()
    ops = hlo_ops(compiled.as_text())
    print(f"{name:28s} trace+lower {t1 - t0:7.2f} s  compile {t2 - t1:7.2f} s  HLO ops {ops:7d}", flush=True)
    return compiled


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--N", type=int, default=20)
    ap.add_argument("--pieces", action="store_true")
    ap.add_argument("--full", action="store_true")
    ap.add_argument("--staged", action="store_true", help="the staged single solve's two programs")
    args = ap.parse_args()
    t0 = time.perf_counter()
    import numpy as np

    from jtraj import _kkt_native
    from jtraj import _testing as solver
    from jtraj._compile import SOLVER_XLA_OPTIONS, supported_options
    from jtraj.transcription import Transcription
    print(f"import {time.perf_counter() - t0:.2f} s")
    t0 = time.perf_counter()
    ok = _kkt_native.available(3)
    print(f"native kernel build/load {time.perf_counter() - t0:.2f} s ({ok})")
    t0 = time.perf_counter()
    problem = quick_start_problem(args.N)
    print(f"problem (IK) {time.perf_counter() - t0:.2f} s")
    opts = solver.resolve_method(None, "decoupled", problem.robot)
    split = solver.split_options(opts)
    xla = supported_options(SOLVER_XLA_OPTIONS)
    init = solver.placeholder_init(problem.N, 3)
    tr = Transcription("decoupled")

    if args.full:
        def full(problem, split, init):
            o = solver.TracedOptions(split)
            return solver.solve_jit.__wrapped__(problem, o, "decoupled", init, np.bool_(False), np.bool_(True))
        measure("full _solve_jit", full, problem, split, init, options=xla)

    if args.staged:
        staged = supported_options({**SOLVER_XLA_OPTIONS, "xla_backend_optimization_level": 1})
        yes, no = np.bool_(True), np.bool_(False)

        def ip_program(problem, split, init):
            return solver.staged_ip_jit.__wrapped__(problem, solver.TracedOptions(split), "decoupled", init, no, yes)

        def al_program(problem, split, init):
            return solver.staged_al_jit.__wrapped__(problem, solver.TracedOptions(split), "decoupled", init, no, yes,
                                                    None)
        measure("staged: interior point", ip_program, problem, split, init, options=xla)
        measure("staged: AL fallback", al_program, problem, split, init, options=xla)
        if "xla_backend_optimization_level" in staged:
            measure("staged: interior point, O1", ip_program, problem, split, init, options=staged)
        quick = supported_options({**SOLVER_XLA_OPTIONS, "xla_backend_optimization_level": 0})
        if "xla_backend_optimization_level" in quick:
            # the quick first call (jtraj._tracecache.tiered), and on a machine whose native
            # kernel is still being built, its XLA version
            measure("staged: interior point, O0 (quick first call)", ip_program, problem, split, init,
                    options=quick)
            def ip_program_xla(problem, split, init):  # (another function: traced anew)
                return ip_program(problem, split, init)

            with _kkt_native.without():
                measure("staged: interior point, O0, XLA KKT (kernel being built)", ip_program_xla, problem, split,
                        init, options=quick)

    if args.pieces:
        def prep(problem, split):
            o = solver.TracedOptions(split)
            init = solver.initial_guess(problem, o, tr)
            nlp, state, valid = solver.prepare(problem, o, tr, init, False)
            return nlp, state, valid

        c = measure("guess+prepare", prep, problem, split, options=xla)
        nlp, state, valid = c(problem, split)

        def ip(nlp, state, split):
            return solver.ip_run(nlp, state, solver.TracedOptions(split))
        c = measure("interior point run", ip, nlp, state, split, options=xla)
        ipr = c(nlp, state, split)

        def light(nlp, state, ipr, split):
            o = solver.TracedOptions(split)
            s = solver.ipm.InteriorPoint().postprocess(nlp, ipr, state)
            return solver.finish(nlp, s, o, valid, light=True)
        measure("ip postprocess+finish(light)", light, nlp, state, ipr, split, options=xla)

        def finish_light_static(nlp, state, ipr, split):
            o = solver.TracedOptions(split)
            s = solver.ipm.InteriorPoint().postprocess(nlp, ipr, state)
            return solver.finish(nlp, s, o, valid, light=True)

        def al(nlp, state, split):
            return solver.run_with_restart(nlp, state, solver.TracedOptions(split))
        c = measure("AL _run_with_restart", al, nlp, state, split, options=xla)
        s_al = c(nlp, state, split)

        def heavy(nlp, s, split):
            return solver.finish(nlp, s, solver.TracedOptions(split), valid, light=False)
        measure("finish(polish+LS kkt)", heavy, nlp, s_al, split, options=xla)

        def polish(nlp, s, split):
            return solver.final_polish(nlp, s.z, solver.TracedOptions(split))
        measure("  _final_polish", polish, nlp, s_al, split, options=xla)

        def kls(nlp, s):
            return solver.kkt_error(nlp, s.z)
        measure("  _kkt_error (LS)", kls, nlp, s_al, options=xla)

        def kal(nlp, s):
            return solver.al_kkt_error(nlp, s.z, s.mult, s.mu)
        measure("  _al_kkt_error", kal, nlp, s_al, options=xla)


if __name__ == "__main__":
    sys.exit(main())
