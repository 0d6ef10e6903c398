"""What one Newton iteration of the batched solver costs, piece by piece.

The canonical benchmark problem (serial3, N = 20, weights time = 1, energy = 0.1): a
batch of ``--pairs`` problems (8, the default lane count on a CPU) is run for ``--warm``
iterations to a mid-run state, then each piece of an iteration is called on that state
as its own compiled, vmapped program:

* ``model``: the AL's value and the stage-wise Newton model (stage derivatives, the
  recursion's Jacobians, co-states and curvature; ``_NLP.stage_newton_model``);
* ``stage_derivs``: the per-stage values, gradients and Hessians alone (part of ``model``);
* ``bounds``: diag(H) and the Gershgorin row bounds of the free rows;
* ``dirs``: the Riccati directions for the four shifts of the ladder;
* ``trials``: the AL at the 13 trial points;
* ``grad``: the gradient and constraints after the step (the loop's test);
* ``iter``: one whole loop iteration (``solver.segment_jit`` with one step).

With ``--method ip`` the pieces are those of the interior-point method (:mod:`jtraj.solver.ipm`,
the default method), from a batch run ``--warm`` interior-point iterations in:

* ``ip_model``: the primal-dual Newton model (``S.ipm_model``: stage derivatives with the
  efforts' Jacobians, the inequalities' Jacobians by the chain rule, the stage model);
* ``ip_stage_derivs``: the per-stage values, gradients and Hessians alone (part of it);
* ``ip_kkt``: the barrier right-hand side and the Riccati KKT solves for the shift ladder
  (``S.ipm_ladder_directions``, all shifts at once under vmap: the native kernel of
  :mod:`jtraj._kkt_native` where it is in use, as in the solver);
* ``ip_kkt_xla``: the same in XLA (``S.ipm_ladder_directions_xla``, the fallback);
* ``ip_kkt1``: one shift's KKT solve alone in XLA (``jtraj.lq.kkt_directions``);
* ``ip_trials``: the cost and constraints at the line search's step lengths;
* ``ip_iter``: one whole interior-point iteration (``ipm.step``).

Each piece includes one program call's overhead, so the pieces add up to more than
``iter``: a no-op program on the same arguments takes about 90 us per call through
``eqx.filter_jit`` (the pieces) and about 210 us through the solver's ``_options_jit``
(``iter``), i.e. 11 and 26 us per problem at 8 lanes. With one lane that
overhead dominates: a segment of 10 iterations on packed arrays, as the batch driver
runs it, costs 0.21 ms per iteration on one lane and 0.15 ms per lane-iteration on 8.

Two measures:

* wall clock (default): the median over ``--rounds`` of ``--calls`` calls, in us per
  problem, in a process pinned to one core (as the batch workers run);
* ``--instructions``: the instructions executed, counted by valgrind's callgrind (the
  script re-runs itself under valgrind with instrumentation off, switches it on only
  around the timed calls and dumps the counts after each piece; Debian's ``valgrind``
  package). Instruction counts repeat to the unit for the same program and inputs, so
  they compare two versions of the code on a machine whose timings swing by 20 %
  (one iteration 470-780 us per problem in repeated wall-clock runs, the same
  instruction count to 0.1 % in every run). They do not see cache misses or
  vectorisation width: confirm a gain in time too. valgrind runs pinned to one CPU, so
  that the counts leave out the spinning of XLA's idle pool threads.

    python benchmarks/iteration_cost.py                  # wall clock
    python benchmarks/iteration_cost.py --instructions   # callgrind counts (~6 min)
    python benchmarks/iteration_cost.py --pbm --option penalty_init=30   # other options
    python benchmarks/iteration_cost.py --method ip --warm 8   # the interior-point method's pieces

The pieces at one mid-run state are not the cost of a whole batch: the PBM
term's iteration counts 1.21x PHR's instructions here (the logarithm at every trial
point), but whole batches of dataset-family pairs took 1.3-1.5x PHR's time per Newton
iteration; its fallback's restarts (a feasibility polish and multiplier estimate on all
8 lanes, about 30 ms a call) were about 10 % of such a batch's time.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PIECES = ("model", "stage_derivs", "bounds", "dirs", "trials", "grad", "iter")
IP_PIECES = ("ip_model", "ip_stage_derivs", "ip_kkt", "ip_kkt_xla", "ip_kkt1", "ip_trials", "ip_iter")


def _programs(pairs: int, seed: int, warm: int, pbm: bool = False, options=(), method: str = "al"):
    """{piece name: a thunk calling it on the mid-run state}, each compiled and run once."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import jtraj
    from jtraj import lq
    from jtraj import _testing as S
    from jtraj._compile import SOLVER_XLA_OPTIONS, cpu_jit

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_solver import _option  # bench_solver's own --option parser
    from jtraj_peers.pairs import benchmark_pairs

    robot = jtraj.robots.get("serial3")
    q0, q1 = benchmark_pairs(pairs, seed)
    extra = dict(_option(o) for o in options)
    opts = S.SolverOptions.pbm(**extra) if pbm else S.SolverOptions(**extra)
    weights = jtraj.Weights(time=1.0, energy=0.1)
    problems = eqx.filter_vmap(lambda a, b: jtraj.Problem(robot, a, b, N=20, weights=weights, validate=False))(
        jnp.asarray(q0), jnp.asarray(q1))
    init = S.guess_batch_jit(problems, opts, "decoupled")
    nlps, states, _ = S.prepare_batch_jit(problems, opts, "decoupled", init, jnp.asarray(False))
    jit, vmap = cpu_jit(SOLVER_XLA_OPTIONS), eqx.filter_vmap
    if method == "ip":
        return _ip_programs(nlps, states, opts, warm, jit, vmap)
    mid = jax.block_until_ready(S.segment_jit(nlps, states, opts, warm))
    kink = jnp.zeros(pairs)  # the kink margin as traced, at zero (its value does not change the cost)

    model_f = jit(lambda n, s, k: vmap(lambda n, s, k: n.stage_newton_model(s.z, s.mult, s.mu, k))(n, s, k))
    _, model, pieces = model_f(nlps, mid, kink)

    def stage_derivs(n, s, k):
        return n.stage_derivatives(n.W(s.z), s.mult, s.mu, k)

    def bounds(n, p):
        hdiag, rows = n.hessian_bounds(p)
        return hdiag, rows(jnp.ones(hdiag.shape, bool))

    shifts = jnp.asarray([1e-3, 1e-2, 1e-1, 1.0])

    def dirs(m):
        return lq.newton_directions(m, jnp.ones(m.g.shape, bool), shifts)

    def trials(n, s, d):
        steps = jnp.asarray(S.TRIAL_STEP)[:, None]
        cand = jnp.clip(s.z[None] + steps * d[S.TRIAL_SHIFT], n.layout.z_lo, n.layout.z_hi)
        return jax.vmap(n.al_value, in_axes=(0, None, None))(cand, s.mult, s.mu)

    stage_f = jit(lambda n, s, k: vmap(stage_derivs)(n, s, k))
    bounds_f = jit(lambda n, p: vmap(bounds)(n, p))
    dirs_f = jit(lambda m: vmap(dirs)(m))
    d, _ = dirs_f(model)
    trials_f = jit(lambda n, s, d: vmap(trials)(n, s, d))
    grad_f = jit(lambda n, s: vmap(lambda n, s: n.al_grad_and_parts(s.z, s.mult, s.mu))(n, s))
    calls = {
        "model": lambda: model_f(nlps, mid, kink),
        "stage_derivs": lambda: stage_f(nlps, mid, kink),
        "bounds": lambda: bounds_f(nlps, pieces),
        "dirs": lambda: dirs_f(model),
        "trials": lambda: trials_f(nlps, mid, d),
        "grad": lambda: grad_f(nlps, mid),
        "iter": lambda: S.segment_jit(nlps, mid, opts, 1),
    }
    for f in calls.values():  # compile every piece before anything is measured
        jax.block_until_ready(f())
    return calls


def _ip_programs(nlps, states, opts, warm, jit, vmap):
    """The interior-point method's pieces (see the module doc) at a state ``warm``
    iterations into a batch run from ``states``' starting points."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from jtraj import lq
    from jtraj import _testing as S
    from jtraj.solver import ipm

    tol = S.ip_tolerances(opts)
    max_iter = S.static_options(opts).ip_max_iter
    ips = S.ip_init_batch_jit(nlps, states, opts)
    method = ipm.InteriorPoint(max_iter=max_iter, tol=tol)
    mid = jax.block_until_ready(jit(lambda n, s: vmap(lambda n, s: S.loop.iterate(method, n, s, warm))(n, s))(nlps, ips))
    if bool(jnp.any(ipm.finished(mid, max_iter))):
        print(f"note: some lanes finished within {warm} iterations (their pieces still run)")

    def stage_derivs(n, s):
        lag = dataclasses.replace(n, ineq_penalty="lagrangian")
        return lag.stage_derivatives(n.W(s.z), ipm.multipliers(n, s), jnp.zeros((), s.z.dtype), efforts=True)

    def kkt(n, s, m, ladder=S.ipm_ladder_directions):
        model, Jg, dgT, p, Ex = m
        model = S.ipm_with_rhs(n, s, model, Jg, dgT, p, s.mu)
        return ladder(model, s.delta * jnp.asarray(S.IPM_SHIFT_LADDER, s.z.dtype), Ex.T)

    def kkt1(s, m):
        model, _, _, _, Ex = m
        return lq.kkt_directions(model, s.delta[None], Ex.T)

    def trials(n, s):
        g = jax.grad(lambda z: S.ipm_parts(n, z).f)(s.z)  # a direction of the right scale
        d = -g / jnp.maximum(1.0, jnp.max(jnp.abs(g)))
        return jax.vmap(lambda a: S.ipm_parts(n, s.z + 1e-3 * a * d))(jnp.asarray(S.IPM_ALPHAS, s.z.dtype))

    model_f = jit(lambda n, s: vmap(S.ipm_model)(n, s))
    m = model_f(nlps, mid)
    stage_f = jit(lambda n, s: vmap(stage_derivs)(n, s))
    kkt_f = jit(lambda n, s, m: vmap(kkt)(n, s, m))
    kkt_xla_f = jit(lambda n, s, m: vmap(lambda *a: kkt(*a, ladder=S.ipm_ladder_directions_xla))(n, s, m))
    kkt1_f = jit(lambda s, m: vmap(kkt1)(s, m))
    trials_f = jit(lambda n, s: vmap(trials)(n, s))
    step_f = jit(lambda n, s: vmap(lambda n, s: ipm.step(n, s, tol))(n, s))
    calls = {
        "ip_model": lambda: model_f(nlps, mid),
        "ip_stage_derivs": lambda: stage_f(nlps, mid),
        "ip_kkt": lambda: kkt_f(nlps, mid, m),
        "ip_kkt_xla": lambda: kkt_xla_f(nlps, mid, m),
        "ip_kkt1": lambda: kkt1_f(mid, m),
        "ip_trials": lambda: trials_f(nlps, mid),
        "ip_iter": lambda: step_f(nlps, mid),
    }
    for f in calls.values():
        jax.block_until_ready(f())
    return calls


def _wall(args) -> None:
    import jax
    import numpy as np

    calls = _programs(args.pairs, args.seed, args.warm, args.pbm, args.option, args.method)
    from jtraj import _kkt_native

    print(f"serial3, N = 20, {args.pairs} lanes, {args.warm} iterations in; us per problem "
          f"(median / min of {args.rounds} x {args.calls} calls); {_kkt_native.status(3)}")
    for name in calls:
        f = calls[name]
        per = []
        for _ in range(args.rounds):
            t = time.perf_counter()
            for _ in range(args.calls):
                out = f()
            jax.block_until_ready(out)
            per.append((time.perf_counter() - t) / args.calls / args.pairs * 1e6)
        print(f"  {name:13s} {np.median(per):8.1f} / {min(per):8.1f}")


def _counted_child(args) -> None:
    """Runs under valgrind: asks callgrind_control (a native child process, polled so
    that valgrind's scheduler keeps running) to switch the counting on, then dumps the
    counts after each piece."""
    import jax

    calls = _programs(args.pairs, args.seed, args.warm, args.pbm, args.option, args.method)
    pid = str(os.getpid())

    def control(*flags):
        proc = subprocess.Popen(["callgrind_control", *flags, pid], stdout=subprocess.DEVNULL)
        while proc.poll() is None:
            time.sleep(0.02)

    control("-z")
    control("-i", "on")
    for name, f in calls.items():
        for _ in range(args.calls):
            out = f()
        jax.block_until_ready(out)
        control("-d", name)
    control("-i", "off")


def _one_cpu() -> None:
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})


def _instructions(args) -> None:
    if shutil.which("valgrind") is None or shutil.which("callgrind_control") is None:
        sys.exit("--instructions needs valgrind (Debian: apt install valgrind)")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "callgrind.out"
        cmd = ["valgrind", "--tool=callgrind", "--instr-atstart=no", f"--callgrind-out-file={out}",
               sys.executable, __file__, "--counted-child", "--pairs", str(args.pairs), "--seed", str(args.seed),
               "--warm", str(args.warm), "--calls", str(args.calls), "--method", args.method,
               *(["--pbm"] if args.pbm else []), *(f"--option={o}" for o in args.option)]
        # on one CPU, as the batch workers run (unpinned, XLA's idle pool threads spin and
        # are counted too; see the module doc)
        pin = _one_cpu if hasattr(os, "sched_setaffinity") else None
        # valgrind knows no AVX-512: the native KKT kernel built for AVX2 under it
        env = {**os.environ, "JTRAJ_NATIVE_MARCH": os.environ.get("JTRAJ_NATIVE_MARCH", "x86-64-v3")}
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, preexec_fn=pin,
                       env=env)
        counts = {}
        for f in Path(tmp).glob("callgrind.out.*"):
            text = f.read_text(errors="replace")
            trigger = next((ln.split("dump ", 1)[1].strip() for ln in text.splitlines()
                            if ln.startswith("desc: Trigger:") and "dump " in ln), None)
            total = next((int(ln.split()[1]) for ln in text.splitlines()
                          if ln.startswith(("summary:", "totals:"))), None)
            if trigger in PIECES + IP_PIECES and total is not None:
                counts[trigger] = total
    from jtraj import _kkt_native

    print(f"serial3, N = 20, {args.pairs} lanes, {args.warm} iterations in; instructions per problem "
          f"and call (callgrind, {args.calls} calls); {_kkt_native.status(3)}, built for "
          f"-march={env['JTRAJ_NATIVE_MARCH']} under valgrind")
    for name in IP_PIECES if args.method == "ip" else PIECES:
        if name in counts:
            print(f"  {name:13s} {counts[name] / args.calls / args.pairs:12,.0f}")
        else:
            print(f"  {name:13s} (no dump)")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=8, help="lanes (benchmark pairs); default 8")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--warm", type=int, default=30, help="iterations run before measuring (a mid-run state)")
    ap.add_argument("--calls", type=int, default=10, help="calls of each piece per round")
    ap.add_argument("--rounds", type=int, default=9, help="wall clock: rounds per piece")
    ap.add_argument("--pbm", action="store_true", help="the PBM inequality term (SolverOptions.pbm())")
    ap.add_argument("--method", choices=("al", "ip"), default="al",
                    help="the AL loop's pieces (default) or the interior-point method's (see the module doc)")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="another jtraj.SolverOptions field, as in bench_solver.py, e.g. --option penalty_init=30 (repeatable)")
    ap.add_argument("--instructions", action="store_true", help="count instructions with callgrind instead")
    ap.add_argument("--counted-child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    for name in ("pairs", "warm", "calls", "rounds"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be at least 1")
    import jax

    jax.config.update("jax_enable_x64", True)
    if args.counted_child:
        _counted_child(args)
    elif args.instructions:
        _instructions(args)
    else:
        import jtraj

        jtraj.pin_to_one_cpu()  # one core, as the batch workers run
        _wall(args)


if __name__ == "__main__":
    main()
