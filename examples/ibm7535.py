"""ibm7535 (Chettibi 7.1): minimum time from (0, 0) to (0, pi/4) rad, |tau| <= (25, 9) N m,
with every transcription jtraj implements (the thesis' decoupled and coupled ones and
Chettibi's collocation, shooting and spline).

Three parts:

* N = 40 intervals for every transcription: T, parameter count, CPU time, the
  time-optimal signature (fraction of samples with an actuator >= 90 % of its bound) and
  the largest torque between samples. A solve that ends uncertified is continued by
  warm-started runs of ``CHUNK`` Newton iterations, recording the KKT error after each
  (``figures/ibm7535_kkt.png``): either a run certifies it (CONVERGED) or the history
  shows where the error stalls.
* Chettibi's coarse parameterisations (Table 1): collocation on 20 intervals (21 nodes),
  shooting with 14 piecewise-constant torque intervals, a spline with 2 interior knots,
  compared through T / T_ref, the same footing as the published T / 0.99 s.
* The decoupled transcription with the torque bound at both ends of every interval
  (``efforts="intervals"``).

The robot is horizontal and frictionless, so slowing a motion uniformly by c divides
its torques by c^2: ``T sqrt(max(1, r))``, with r the largest |tau|/tau_max anywhere
along the motion, is the duration of the same path that meets the bound everywhere.
T_ref is the shortest such duration among the N = 40 solutions.

Writes examples/figures/ibm7535_*.png, examples/status/ibm7535.json and the "ibm7535"
section of examples/RESULTS.md.
Run: python examples/ibm7535.py [--skip=shooting,...] (leave transcriptions out: the
shooting programs take minutes of CPU to compile) [--resume] (keep the parts a run cut
short cached, solve the rest) | --report (redraw from the cached solves)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_all import FIGURES, SolveCache, setup, table, timed_solve, write_section, write_status  # noqa: E402

setup()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jtraj  # noqa: E402
from jtraj import plotting  # noqa: E402
from jtraj.resample import intersample_effort  # noqa: E402
from jtraj.transcription import TRANSCRIPTIONS, Transcription  # noqa: E402

NAME = "ibm7535"
N = 40
WEIGHTS = jtraj.Weights(time=1.0, energy=0.0)
Q_START, Q_GOAL = (0.0, 0.0), (0.0, np.pi / 4)
#: warm-started continuation of an uncertified solve: runs of CHUNK Newton iterations
#: (no automatic restart inside a run), at most CHUNKS of them
CHUNK, CHUNKS = 100, 10
#: Chettibi Table 1: method -> (jtraj transcription, N reproducing the parameter count,
#: published parameters, T [s], CPU [s], how the published count decomposes)
COARSE = {
    "collocation": (20, 127, 1.02, 20, "21 nodes x (4 states + 2 torques) + T = 127"),
    "shooting": (14, 29, 1.14, 525, "14 intervals x 2 torques + T = 29"),
    "spline": (3, 5, 1.05, 4, "2 interior knots x 2 joints + T = 5"),
}
PONTRYAGIN = 0.99  # Chen & Desrochers' optimum for the real IBM 7535 [s]
#: the coarse problems need N h_max above T (3 intervals of at most 0.1 s cannot take 0.9 s)
H_MAX_COARSE = 0.5
DISCRETE = {
    "decoupled": "Khoukhi's recursion, accelerations as controls, torque bound at the N samples",
    "coupled": "the same recursion with torques as controls (forward dynamics): the same discrete "
               "problem as the decoupled one, reparametrised",
    "collocation": "states and torques as unknowns, midpoint-rule defects as equalities",
    "shooting": "piecewise-constant torques, one RK4 step per interval",
    "spline": "clamped cubic spline through free knots, torque bound at the knots only",
}


def dense_effort(name, robot, sol, per_interval=16):
    """max_t |tau_i(t)| / tau_max_i along the motion the transcription describes: the
    piecewise-constant torques of shooting; the cubic Hermite pieces of the spline; the
    constant-acceleration intervals of the others (exact for the recursion, and the
    midpoint rule's q_{k+1} = q_k + h (qd_k + qd_{k+1}) / 2 is that motion too)."""
    tau_max = np.asarray(robot.limits.tau_max)
    if name == "shooting":
        return float(np.max(np.abs(np.asarray(sol.tau)) / tau_max))
    if name != "spline":
        return float(intersample_effort(sol, robot, per_interval=per_interval))
    q, qd, h = jnp.asarray(sol.q), jnp.asarray(sol.qd), jnp.asarray(sol.h)
    s = jnp.linspace(0.0, 1.0, per_interval)[None, :, None]
    q0, q1, m0, m1, hk = q[:-1, None], q[1:, None], qd[:-1, None], qd[1:, None], h[:, None, None]
    pos = ((2 * s**3 - 3 * s**2 + 1) * q0 + (s**3 - 2 * s**2 + s) * hk * m0 + (-2 * s**3 + 3 * s**2) * q1
           + (s**3 - s**2) * hk * m1)
    vel = ((6 * s**2 - 6 * s) * q0 + (3 * s**2 - 4 * s + 1) * hk * m0 + (-6 * s**2 + 6 * s) * q1
           + (3 * s**2 - 2 * s) * hk * m1) / hk
    acc = ((12 * s - 6) * q0 + (6 * s - 4) * hk * m0 + (-12 * s + 6) * q1 + (6 * s - 2) * hk * m1) / hk**2
    n = q.shape[1]
    tau = jax.vmap(robot.inverse_dynamics)(pos.reshape(-1, n), vel.reshape(-1, n), acc.reshape(-1, n))
    return float(jnp.max(jnp.abs(tau) / robot.limits.tau_max))


def continue_until_certified(problem, name, sol):
    """Warm-started runs of CHUNK Newton iterations from ``sol`` while it is not certified,
    each from the previous run's end: (the best solution (certified, else the latest
    feasible one, else the smallest violation), history rows (cumulative Newton it., KKT
    error, T, violation, status))."""
    tr = Transcription(name)
    # traced values: the same compiled program as the default solver's
    solver = jtraj.Auto(ipm=jtraj.IPM(fallback=jtraj.AugmentedLagrangian(max_iter=CHUNK, restart_iter=0)))

    def row(s, total):
        return (total, float(s.kkt_error), float(s.T), float(s.max_violation["overall"]),
                jtraj.Status(int(s.status)).name)

    def rank(s):
        return 0 if bool(s.converged) else 1 if int(s.status) == jtraj.Status.FEASIBLE_NOT_OPTIMAL else 2

    total = int(sol.iterations)
    hist, best, cur = [row(sol, total)], sol, sol
    for _ in range(CHUNKS):
        if bool(cur.converged):
            break
        cur = jtraj.solve(problem, transcription=name, solver=solver, init=(tr.controls_of(cur), cur.h))
        total += int(cur.iterations)
        hist.append(row(cur, total))
        if rank(cur) < rank(best) or (rank(cur) == rank(best) < 2) or (
                rank(cur) == rank(best) == 2
                and float(cur.max_violation["overall"]) <= float(best.max_violation["overall"])):
            best = cur
    return best, hist


#: the activity thresholds of :func:`best_stationarity` (scaled units): the certification's
#: own, and one wide enough for the interior-point method, which leaves a weakly active
#: bound about mu / multiplier inside it
ACT_TOLS = (1e-3, 3e-2)


def best_stationarity(problem, name, sol, act_tol):
    """(stationarity, complementarity) of ``sol`` with the best multipliers there are:
    the bounded least-squares problem (SciPy's ``bvls``) min ||grad f + J^T lam|| over the
    multipliers of the equalities (free), of the inequalities within ``act_tol`` of active
    (>= 0) and of the variable bounds within ``act_tol`` (>= 0), in the scaled variables
    z; then the largest entry of that residual and the largest lam_i |g_i|. It separates a
    point that is not stationary from a multiplier estimate that fails: the solver's
    least-squares estimate clips negative inequality multipliers after the fact, which
    fails where nearly-active rows are nearly parallel."""
    from scipy.optimize import lsq_linear

    from jtraj.solver.certify import ls_multipliers
    from jtraj.solver.nlp import NLP

    tr = Transcription(name)
    nlp = NLP(problem=problem, tr=tr, layout=tr.layout(problem), sd=tr.stage_data(problem))
    z = tr.layout(problem).pack(tr.controls_of(sol), sol.h)
    _, J, gf, n_eq = ls_multipliers(nlp, z, act_tol)
    J, gf = np.asarray(J), np.asarray(gf)
    _, ineq, glob = nlp.constraints(z)
    g = np.concatenate([np.ravel(x) for x in jax.tree.leaves(ineq)] + [np.ravel(glob)])
    near = g > -act_tol
    rows = np.concatenate([np.ones(n_eq, bool), near])  # the rows of J: equalities, then inequalities
    zz, lo, hi = np.asarray(z), np.asarray(nlp.layout.z_lo), np.asarray(nlp.layout.z_hi)
    band = act_tol * np.maximum(1.0, hi - lo)
    eye = np.eye(zz.size)
    M = np.concatenate([J[rows].T, -eye[:, zz <= lo + band], eye[:, zz >= hi - band]], axis=1)
    lower = np.concatenate([np.full(n_eq, -np.inf), np.zeros(M.shape[1] - n_eq)])
    lam = lsq_linear(M, -gf, bounds=(lower, np.full(M.shape[1], np.inf)), method="bvls", tol=1e-14,
                     max_iter=20000).x
    comp = np.abs(lam[n_eq:n_eq + near.sum()] * g[near])
    return float(np.max(np.abs(gf + M @ lam))), float(comp.max(initial=0.0))


#: bisection steps on the common period of :func:`tied_periods` (the bracket shrinks 2^steps-fold)
TIED_STEPS = 10


def _feasible(sol) -> bool:
    return int(sol.status) in (jtraj.Status.CONVERGED, jtraj.Status.FEASIBLE_NOT_OPTIMAL)


def tied_periods(name, Nc, free_sol):
    """Chettibi's own family for a coarse parameterisation: every period equal (one T).

    jtraj's coarse problems keep a free period per interval; tying them leaves the common
    period h as the only time variable, and the minimum time is the smallest h for which
    the problem with ``h_k = h`` (``h_min = h``, ``h_max = h (1 + 1e-7)``) has a solution
    that meets every constraint (CONVERGED or FEASIBLE_NOT_OPTIMAL: re-simulated). It is
    found by bisection from ``free_sol`` (the free-period optimum, a lower bound on it),
    each solve warm-started from the last feasible one. Returns (N h of the last period
    without a feasible solve, N h of the feasible one, its solution, the number of
    solves). A solve that ends infeasible counts as infeasible, so the upper value is a
    feasible (re-simulated) duration and the lower one is not proven infeasible."""
    def attempt(h, init):
        robot = jtraj.robots.get(NAME, h_min=h, h_max=h * (1 + 1e-7))
        pc = jtraj.Problem(robot, Q_START, Q_GOAL, N=Nc, weights=WEIGHTS)
        return jtraj.solve(pc, transcription=name, init=init)

    tr = Transcription(name)
    lo, best, solves = float(free_sol.T) / Nc, None, 0
    hi, init = lo, (tr.controls_of(free_sol), free_sol.h)
    while best is None:
        hi *= 1.05
        sol = attempt(hi, (init[0], jnp.full(Nc, hi)))
        solves += 1
        if _feasible(sol):
            best = sol
        elif hi > 2.0 * lo:
            raise RuntimeError(f"{name}: no feasible tied-period solve up to twice the free optimum's period")
        else:
            lo = hi
    for _ in range(TIED_STEPS):
        mid = 0.5 * (lo + hi)
        sol = attempt(mid, (tr.controls_of(best), jnp.full(Nc, mid)))
        solves += 1
        if _feasible(sol):
            hi, best = mid, sol
        else:
            lo = mid
    return Nc * lo, Nc * hi, best, solves


def near_active(sol, tau_max, rel=1e-3):
    """Number of (sample, actuator) torque bounds within ``rel`` of active."""
    return int(np.sum(np.abs(np.asarray(sol.tau)) / tau_max >= 1 - rel))


def slowed(T, effort):
    """Duration of the same path slowed uniformly until its largest torque ratio is 1."""
    return T * np.sqrt(max(1.0, effort))


def n_params(problem, name):
    return Transcription(name).layout(problem).nz - (problem.robot.n if name == "spline" else 0)


def kkt_figure(histories, tol, path):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4), layout="constrained")
    a, b = fig.subplots(1, 2)
    for i, (name, hist) in enumerate(histories.items()):
        it = np.array([r[0] for r in hist])
        a.semilogy(it, [r[1] for r in hist], "o-", color=f"C{i}", ms=3, label=name)
        T = np.array([r[2] for r in hist])
        b.semilogy(it, np.maximum(np.abs(T - T[-1]) / T[-1], 1e-16), "o-", color=f"C{i}", ms=3, label=name)
    a.axhline(tol, color="k", ls=":", lw=1.0, label=f"tol_optimality = {tol:g}")
    a.set_xlabel("cumulative Newton iterations")
    a.set_ylabel("KKT error (scaled variables)")
    a.set_title(f"KKT error: cold solve, then warm runs of {CHUNK} iterations")
    a.legend(fontsize=7)
    b.set_xlabel("cumulative Newton iterations")
    b.set_ylabel("|T - T_last| / T_last")
    b.set_title("duration against its last value")
    b.legend(fontsize=7)
    plotting.save(fig, str(path))


def ratio_figure(points, path):
    """T / reference against the number of parameters: jtraj's N = 40 and coarse solves,
    Chettibi's Table 1 (T / 0.99 s)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4.2), layout="constrained")
    ax = fig.add_subplot()
    for i, name in enumerate(COARSE):
        if name in points:
            fine, coarse = points[name]
            ax.plot(*fine, "o", color=f"C{i}", ms=7, label=f"{name}, jtraj N = {N}")
            ax.errorbar([coarse[0]], [coarse[1]], yerr=[[0.0], [coarse[2] - coarse[1]]], fmt="s", color=f"C{i}",
                        ms=7, mfc="none", capsize=3, label=f"{name}, jtraj coarse (bar: slowed to meet the bound)")
        _, p, T_pub, _, _ = COARSE[name]
        ax.plot([p], [T_pub / PONTRYAGIN], "^", color=f"C{i}", mec="k", ms=9,
                label=f"{name}, Chettibi Table 1 ({T_pub} / {PONTRYAGIN} s)")
    ax.axhline(1.0, color="0.4", ls=":", lw=1.0)
    ax.set_xscale("log")
    ax.set_xlabel("number of parameters")
    ax.set_ylabel("T / reference optimum")
    ax.set_title("ibm7535: transcription against parameter count")
    ax.legend(fontsize=6.5)
    plotting.save(fig, str(path))


def main(skip=(), resume=False):
    """Solve everything (the transcriptions in ``skip`` left out), cache the solves after
    each part (:class:`run_all.SolveCache`), report. ``resume``: keep the parts already
    cached (a run cut short goes on where it stopped; ``seconds`` adds up the solving time
    of every run)."""
    robot = jtraj.robots.get(NAME)
    tau_max = np.asarray(robot.limits.tau_max)
    problem = jtraj.Problem(robot, Q_START, Q_GOAL, N=N, weights=WEIGHTS)
    cache = SolveCache(NAME, resume=resume)
    data = cache.data
    if cache.resumed:
        data["skipped"] = tuple(t for t in skip if t not in data["fine"])
        print("resumed:", list(data["fine"]), "intervals" if "s_int" in data else "", list(data["coarse"]), flush=True)
    else:
        data.update(fine={}, histories={}, coarse={}, skipped=tuple(skip))
    fine, histories, coarse = data["fine"], data["histories"], data["coarse"]
    checkpoint = cache.save

    for name in (t for t in TRANSCRIPTIONS if t not in skip and t not in fine):
        first, t_first = timed_solve(problem, transcription=name)
        sol, t_solve = timed_solve(problem, transcription=name)
        cold = jtraj.Status(int(sol.status)).name
        sol, hist = continue_until_certified(problem, name, sol)
        if len(hist) > 1:
            histories[name] = hist
        ratio = np.abs(np.asarray(sol.tau)) / tau_max
        status = jtraj.Status(int(sol.status)).name
        fine[name] = dict(sol=sol, t_first=t_first, t_solve=t_solve, cold=cold, hist=hist,
                          sat=float(np.mean(np.max(ratio, axis=1) >= 0.9)), peak=ratio.max(axis=0),
                          effort=dense_effort(name, robot, sol), params=n_params(problem, name))
        fine[name]["record"] = {"run": f"{name}, N = {N}", "status": status,
                                "max_violation": float(sol.max_violation["overall"]),
                                "effort_between_samples": fine[name]["effort"]}
        fig = plotting.plot_solution(problem, sol, title=f"ibm7535, {name}, N = {N}: T = {float(sol.T):.4f} s "
                                                         f"({status})")
        plotting.save(fig, str(FIGURES / f"{NAME}_{name}.png"))
        print(name, cold, status, float(sol.T), t_solve, fine[name]["effort"], flush=True)
        checkpoint()

    # the decoupled transcription with the bound at both ends of every interval
    p_int = jtraj.Problem(robot, Q_START, Q_GOAL, N=N, weights=WEIGHTS, efforts="intervals")
    if "s_int" not in data:
        s_int, t_int_first = timed_solve(p_int)
        s_int, t_int = timed_solve(p_int)
        e_int = dense_effort("decoupled", robot, s_int)
        data.update(s_int=s_int, t_int=t_int, t_int_first=t_int_first, e_int=e_int,
                    int_record={"run": f"decoupled, N = {N}, efforts=intervals",
                                "status": jtraj.Status(int(s_int.status)).name,
                                "max_violation": float(s_int.max_violation["overall"]),
                                "effort_between_samples": e_int})
        fig = plotting.plot_solution(p_int, s_int, title=f"ibm7535, decoupled, bound at both ends of every "
                                                         f"interval: T = {float(s_int.T):.4f} s "
                                                         f"({jtraj.Status(int(s_int.status)).name})")
        plotting.save(fig, str(FIGURES / f"{NAME}_decoupled_intervals.png"))
        print("intervals", float(s_int.T), e_int, flush=True)
        checkpoint()

    # Chettibi's coarse parameterisations
    robot_c = jtraj.robots.get(NAME, h_max=H_MAX_COARSE)
    for name, (Nc, p_pub, T_pub, cpu_pub, how) in COARSE.items():
        if name in skip or name in coarse:
            continue
        pc = jtraj.Problem(robot_c, Q_START, Q_GOAL, N=Nc, weights=WEIGHTS)
        sol, t_first = timed_solve(pc, transcription=name)
        cold = jtraj.Status(int(sol.status)).name
        sol, hist = continue_until_certified(pc, name, sol)
        if len(hist) > 1:
            histories[f"{name}, N = {Nc}"] = hist
        eff = dense_effort(name, robot_c, sol)
        coarse[name] = dict(sol=sol, t_first=t_first, cold=cold, effort=eff, params=n_params(pc, name), N=Nc,
                            record={"run": f"{name}, N = {Nc} (coarse)", "status": jtraj.Status(int(sol.status)).name,
                                    "max_violation": float(sol.max_violation["overall"]),
                                    "effort_between_samples": eff})
        fig = plotting.plot_solution(pc, sol, title=f"ibm7535, {name}, N = {Nc} (Chettibi's {p_pub} parameters): "
                                                    f"T = {float(sol.T):.4f} s ({jtraj.Status(int(sol.status)).name})")
        plotting.save(fig, str(FIGURES / f"{NAME}_{name}_coarse.png"))
        print("coarse", name, cold, jtraj.Status(int(sol.status)).name, float(sol.T), eff, flush=True)
        checkpoint()
    # the same with the periods tied equal: Chettibi's own families
    tied = data.setdefault("tied", {})
    for name, (Nc, *_) in COARSE.items():
        if name in skip or name in tied or name not in coarse:
            continue
        t0 = time.perf_counter()
        T_lo, T_hi, sol, solves = tied_periods(name, Nc, coarse[name]["sol"])
        tied[name] = dict(T_lo=T_lo, T_hi=T_hi, sol=sol, solves=solves, seconds=time.perf_counter() - t0,
                          effort=dense_effort(name, robot_c, sol),
                          record={"run": f"{name}, N = {Nc} (coarse, tied periods)",
                                  "status": jtraj.Status(int(sol.status)).name,
                                  "max_violation": float(sol.max_violation["overall"]),
                                  "effort_between_samples": None})
        tied[name]["record"]["effort_between_samples"] = tied[name]["effort"]
        print("tied", name, T_lo, T_hi, solves, tied[name]["effort"], flush=True)
        checkpoint()
    data["records"] = ([r["record"] for r in fine.values()] + [data["int_record"]]
                       + [r["record"] for r in data.get("tied", {}).values()]
                       + [r["record"] for r in coarse.values()])
    checkpoint()
    report(data)


def tied_cell(t, T_ref) -> str:
    """The coarse table's cell for a tied-period solve (:func:`tied_periods`)."""
    if t is None:
        return "not run"
    return (f"{t['T_hi'] / T_ref:.3f} - {slowed(t['T_hi'], t['effort']) / T_ref:.3f} (no feasible solve at "
            f"{t['T_lo'] / T_ref:.3f}; {jtraj.Status(int(t['sol'].status)).name}, {t['solves']} solves, "
            f"{t['seconds']:.0f} s)")


def coarse_verdict(coarse, T_ref, tied=None) -> str:
    """The comparison of the coarse solves with Table 1's ratios, from the numbers."""
    if not coarse:
        return "Chettibi's coarse parameterisations were not run by this invocation."
    pub = {k: COARSE[k][2] / PONTRYAGIN for k in coarse}
    ours = {k: float(r["sol"].T) / T_ref for k, r in coarse.items()}
    slow = {k: slowed(float(r["sol"].T), r["effort"]) / T_ref for k, r in coarse.items()}
    certified = [k for k, r in coarse.items() if int(r["sol"].status) == jtraj.Status.CONVERGED]
    order_pub = " < ".join(sorted(pub, key=pub.get))
    order_ours = " < ".join(sorted(slow, key=slow.get))
    return ("**Against Table 1.** Chettibi's coarse optima lie "
            + ", ".join(f"{100 * (pub[k] - 1):.1f} %" for k in coarse) + " above the Pontryagin optimum ("
            + " / ".join(coarse) + "); jtraj's at the same parameter counts (plus one period per interval) lie "
            + ", ".join(f"{100 * (ours[k] - 1):+.1f} to {100 * (slow[k] - 1):+.1f} %" for k in coarse)
            + " from T_ref (bound at the knots, then the path slowed to meet it everywhere), "
            + (f"all {len(certified)} certified (CONVERGED)" if len(certified) == len(coarse) else
               f"{len(certified)} of {len(coarse)} certified")
            + f". Verdict: not reproduced. The published order is {order_pub}, jtraj's (slowed paths) "
            f"{order_ours}, and every jtraj coarse solve is within {100 * (max(slow.values()) - 1):.1f} % of the "
            f"N = {N} reference. jtraj's families are larger than Chettibi's (a free period per interval instead "
            f"of one T), so they can only do as well or better. " + tied_verdict(tied or {}, T_ref, pub))


def tied_verdict(tied, T_ref, pub) -> str:
    """The sentence on Chettibi's own families (the periods tied equal)."""
    if not tied:
        return ("Whether Chettibi's own families reach his ratios is not tested by this invocation (the "
                "tied-period solves did not run).")
    ratio = {k: slowed(t["T_hi"], t["effort"]) / T_ref for k, t in tied.items()}
    order = " < ".join(sorted(ratio, key=ratio.get))
    return ("With the periods tied equal, his families themselves, jtraj's optima lie "
            + ", ".join(f"{100 * (t['T_hi'] / T_ref - 1):+.1f} to {100 * (ratio[k] - 1):+.1f} %"
                        for k, t in tied.items())
            + f" from T_ref ({' / '.join(tied)}; order {order}) against the published "
            + ", ".join(f"{100 * (pub[k] - 1):+.1f} %" for k in tied if k in pub) + ". "
            + ("Every published ratio lies above its own family's optimum here, by "
               + ", ".join(f"{100 * (pub[k] - ratio[k]):.1f}" for k in tied) + " points: on this model of the "
               "robot his families reach shorter times than Table 1 reports. Whether his solver stopped short or "
               "the IBM 7535's own data (not published) make the difference cannot be told from the sources."
               if all(pub[k] > ratio[k] for k in tied) else
               "Families whose published ratio lies above their optimum here: "
               + (", ".join(k for k in tied if pub[k] > ratio[k]) or "none") + "."))


def report(data):
    """Figures, status record and RESULTS.md section from the solves of :func:`main`."""
    fine, histories, records, coarse = data["fine"], data["histories"], data["records"], data["coarse"]
    # in the order of TRANSCRIPTIONS and COARSE (the cache's dicts come back sorted by name)
    fine = {k: fine[k] for k in TRANSCRIPTIONS if k in fine}
    coarse = {k: coarse[k] for k in COARSE if k in coarse}
    tied = {k: data.get("tied", {})[k] for k in COARSE if k in data.get("tied", {})}
    order = [f"{k}, N = {N}" for k in fine] + [f"decoupled, N = {N}, efforts=intervals"] + [
        f"{k}, N = {r['N']}{sfx}" for k, r in coarse.items() for sfx in (" (coarse)", " (coarse, tied periods)")]
    records = sorted(records, key=lambda r: order.index(r["run"]) if r["run"] in order else len(order))
    s_int, t_int, t_int_first, e_int = data["s_int"], data["t_int"], data["t_int_first"], data["e_int"]
    robot = jtraj.robots.get(NAME)
    tau_max = np.asarray(robot.limits.tau_max)
    p_int = jtraj.Problem(robot, Q_START, Q_GOAL, N=N, weights=WEIGHTS, efforts="intervals")
    tol = jtraj.AugmentedLagrangian().tol_optimality
    feasible_T = {k: slowed(float(r["sol"].T), r["effort"]) for k, r in fine.items()
                  if int(r["sol"].status) in (jtraj.Status.CONVERGED, jtraj.Status.FEASIBLE_NOT_OPTIMAL)}
    feasible_T["decoupled, intervals"] = slowed(float(s_int.T), e_int)
    ref_name = min(feasible_T, key=feasible_T.get)
    T_ref = feasible_T[ref_name]

    write_status(NAME, records)

    if histories:
        kkt_figure(histories, tol, FIGURES / f"{NAME}_kkt.png")
    elif (FIGURES / f"{NAME}_kkt.png").exists():  # no continuation: no history to draw
        (FIGURES / f"{NAME}_kkt.png").unlink()
    ratio_figure({name: ((fine[name]["params"], feasible_T.get(name, np.nan) / T_ref),
                         (coarse[name]["params"], float(coarse[name]["sol"].T) / T_ref,
                          slowed(float(coarse[name]["sol"].T), coarse[name]["effort"]) / T_ref))
                  for name in COARSE if name in fine and name in coarse}, FIGURES / f"{NAME}_ratios.png")

    # ---- tables
    problem = jtraj.Problem(robot, Q_START, Q_GOAL, N=N, weights=WEIGHTS)
    best = {k: [best_stationarity(problem, k, r["sol"], t) for t in ACT_TOLS] for k, r in fine.items()}
    rows = []
    for name, r in fine.items():
        sol = r["sol"]
        st = jtraj.Status(int(sol.status)).name
        cont = "" if len(r["hist"]) == 1 else (f"; cold solve {r['cold']} after {r['hist'][0][0]} Newton it., then "
                                               f"{len(r['hist']) - 1} warm run(s) of <= {CHUNK}")
        rows.append((name, f"{float(sol.T):.4f}", f"{st} ({int(sol.iterations)} Newton it. in the last run{cont})",
                     f"{float(sol.kkt_error):.1e}", " / ".join(f"{x:.1e}" for x, _ in best[name]),
                     f"{float(sol.max_violation['overall']):.0e}", f"{r['effort']:.3f}", f"{feasible_T.get(name, float('nan')) / T_ref:.4f}", str(r["params"]),
                     f"{r['t_solve']:.2f} ({r['t_first']:.0f})", f"{100 * r['sat']:.0f} %", DISCRETE[name]))
    skipped = data.get("skipped", ())
    rows += [(name, "not run by this invocation (`--skip`)", *["-"] * 10) for name in skipped]
    rows.append(("decoupled, efforts=intervals", f"{float(s_int.T):.4f}",
                 f"{jtraj.Status(int(s_int.status)).name} ({int(s_int.iterations)} Newton it.)",
                 f"{float(s_int.kkt_error):.1e}", "-", f"{float(s_int.max_violation['overall']):.0e}", f"{e_int:.3f}",
                 f"{feasible_T['decoupled, intervals'] / T_ref:.4f}", str(n_params(p_int, "decoupled")),
                 f"{t_int:.2f} ({t_int_first:.0f})", "-", "the torque bound also at each interval's end"))
    header = ("transcription (N = 40)", "T [s]", "status", "KKT error",
              "stationarity, best multipliers (rows within " + " / ".join(f"{t:g}" for t in ACT_TOLS) + " of active)",
              "worst violation",
              "largest |tau|/tau_max along the motion", "T sqrt(max(1, that)) / T_ref", "parameters",
              "wall s per solve (first call, compile incl.; shared, loaded 2-core machine)", "samples with an actuator >= 90 %", "discrete model")
    crow = []
    for name, r in coarse.items():
        Nc, p_pub, T_pub, cpu_pub, how = COARSE[name]
        sol = r["sol"]
        T = float(sol.T)
        crow.append((name, f"{Nc} intervals: {r['params']} ({how} in Chettibi; jtraj adds one period per interval)",
                     f"{T:.4f}", f"{jtraj.Status(int(sol.status)).name} (cold: {r['cold']})",
                     f"{r['effort']:.3f}", f"{T / T_ref:.3f} - {slowed(T, r['effort']) / T_ref:.3f}",
                     tied_cell(tied.get(name), T_ref),
                     f"{T_pub} / {PONTRYAGIN} = {T_pub / PONTRYAGIN:.3f}", f"{r['t_first']:.0f} (compile incl.)",
                     f"{cpu_pub}"))
    cheader = ("Chettibi method", "jtraj N: parameters", "T [s]", "status", "largest |tau|/tau_max along the motion",
               "T / T_ref (bound at the samples - slowed to meet it everywhere)",
               "periods tied equal (Chettibi's family): T / T_ref (bound at the samples - slowed)",
               "published T / 0.99 s",
               "jtraj wall s", "published CPU s")
    for name in skipped:
        Nc, p_pub, T_pub, cpu_pub, how = COARSE.get(name, (None,) * 5)
        if Nc is not None:
            crow.append((name, f"not run by this invocation (`--skip`); {how} in Chettibi", "-", "-", "-", "-", "-",
                         f"{T_pub} / {PONTRYAGIN} = {T_pub / PONTRYAGIN:.3f}", "-", f"{cpu_pub}"))
    uncert = [k for k, r in fine.items() if not bool(r["sol"].converged)]
    ran = ", ".join(fine)
    kkt_text = (f"Every N = {N} transcription run here ({ran}) ends CONVERGED"
                + (": certified by the cold solve, with KKT errors "
                   + ", ".join(f"{float(r['sol'].kkt_error):.1e}" for r in fine.values())
                   + f" against the target {tol:g}." if not histories else
                   "; those that did not at once were certified by the warm-started continuation "
                   "(`figures/ibm7535_kkt.png`: their KKT error against the Newton iterations).")
                if not uncert else
                f"Not certified at N = {N}: {', '.join(uncert)}. `figures/ibm7535_kkt.png` shows the KKT error after "
                f"the cold solve and after each warm run of {CHUNK} Newton iterations: "
                + "; ".join(f"{k}: {fine[k]['hist'][0][1]:.1e} -> {fine[k]['hist'][-1][1]:.1e}, T "
                            f"{fine[k]['hist'][0][2]:.5f} -> {fine[k]['hist'][-1][2]:.5f} s "
                            f"({(fine[k]['hist'][-1][2] - fine[k]['hist'][0][2]) / fine[k]['hist'][-1][2]:+.1e} "
                            f"relative)" for k in uncert)
                + f", against the target {tol:g}. At the returned points "
                + "; ".join(f"{k}: {near_active(fine[k]['sol'], tau_max)} of {2 * N} torque bounds within 0.1 % of active "
                            f"({fine[k]['params']} parameters)" for k in uncert)
                + f". Over {CHUNKS * CHUNK} further Newton iterations the KKT error does not fall towards the "
                  "target while the duration still moves by the amount above, so these rows are feasible "
                  "(re-simulated) but their optimality is not certified.\n\n"
                  "**Why: the multiplier estimate, and a point near stationarity.** At a bang-bang optimum many "
                  "torque bounds are active or nearly so along consecutive samples and their gradients are nearly "
                  "parallel; the solver's least-squares multipliers, clipped to >= 0 after the fact, are then "
                  "ill-determined. The column \"stationarity, best multipliers\" measures each point with the best "
                  "multipliers there are (`best_stationarity`: bounded least squares, the inequalities' "
                  "multipliers >= 0, rows within "
                + " and ".join(f"{t:g}" for t in ACT_TOLS)
                + " of active): "
                + "; ".join(f"{k}: {float(fine[k]['sol'].kkt_error):.1e} reported, "
                            + " / ".join(f"{x:.1e}" for x, _ in best[k]) + " with the best multipliers "
                            f"(complementarity {max(c for _, c in best[k]):.0e})" for k in uncert)
                + ". The same measure reproduces the certified rows' errors ("
                + ", ".join(f"{k} {min(x for x, _ in best[k]):.1e}" for k in fine if k not in uncert)
                + f") once the rows the interior-point method leaves up to {ACT_TOLS[-1]:g} inside their bound are "
                  "counted. So the reported error is the estimate failing, and the point itself is "
                + ", ".join(f"{min(x for x, _ in best[k]) / tol:.1f}x" for k in uncert)
                + " the target away from stationarity: near-optimal, not certified.")
    text = (f"## ibm7535: minimum time (0, 0) -> (0, pi/4) rad (Chettibi Table 1)\n\n"
            f"Robot `ibm7535`: assumed SCARA-like parameters in a horizontal plane, lengths (0.4, 0.25) m, "
            f"masses (15, 6) kg, inertias about the centres of mass (1.6, 2.4) kg m^2 (rotor inertia lumped "
            f"in), |tau| <= (25, 9) N m, |qd| <= 10 rad/s, |qdd| <= 50 rad/s^2 (loose), h in [0.005, 0.1] s; "
            f"no friction. The IBM 7535 data are not in the sources, so absolute times differ from the "
            f"published 0.99 s and only ratios are compared. Weights time = 1, energy = 0; default solver "
            f"options; a solve that ends uncertified is continued by warm-started runs of {CHUNK} Newton "
            f"iterations (at most {CHUNKS}). Chettibi's methods map to `collocation` (Table 1 row 1), "
            f"`shooting` (row 2) and `spline` (row 3). Figures: `figures/ibm7535_<transcription>.png` (N = {N}), "
            f"`figures/ibm7535_<transcription>_coarse.png`, `figures/ibm7535_decoupled_intervals.png`, "
            + ("`figures/ibm7535_kkt.png`, " if histories else "") + "`figures/ibm7535_ratios.png`.\n\n"
            f"**Reference.** The robot has no gravity and no friction, so a motion slowed uniformly by c needs "
            f"its torques divided by c^2: T sqrt(max(1, r)), r the largest |tau|/tau_max along the motion (dense "
            f"evaluation: 16 points per interval of the motion the transcription describes), is the duration of "
            f"the same path meeting the bound everywhere. T_ref = {T_ref:.4f} s is the shortest of these among "
            f"the N = {N} solutions ({ref_name}); Chettibi's reference is the Pontryagin optimum 0.99 s.\n\n"
            f"### N = {N}, every transcription\n\n" + table(rows, header=header)
            + f"\n\n{kkt_text}\n\n"
            f"### Chettibi's coarse parameterisations\n\n"
            f"The same task with Chettibi's parameter counts: collocation on 20 intervals, shooting on 14, a "
            f"spline with 2 interior knots (h_max raised to {H_MAX_COARSE} s so that 3 intervals can span the "
            f"motion). jtraj keeps one free period per interval where Chettibi has one T, so each jtraj family "
            f"contains Chettibi's; the column \"periods tied equal\" solves Chettibi's own families, one period "
            f"for all intervals, by bisection on that period ({TIED_STEPS} halvings after a bracket, each solve "
            f"warm-started; `tied_periods`). The spline and the collocation bound the torque at their knots or nodes only; "
            f"the last-but-two column brackets their optimum with the bound imposed everywhere: between the "
            f"knot-only T (a relaxation) and the same path slowed until it meets the bound everywhere (a "
            f"feasible point).\n\n" + table(crow, header=cheader)
            + "\n\n" + coarse_verdict(coarse, T_ref, tied)
            + "\n\nFigure `figures/ibm7535_ratios.png` draws these ratios against the parameter count beside "
              "Table 1's.")
    text += (f"\n\nScript wall time {data['seconds']:.0f} s (solving, summed over the runs that filled the cache"
             + (f"; process CPU {data['cpu']:.0f} s" if "cpu" in data else "") + ").")
    write_status(NAME, records, wall_s=data["seconds"])
    write_section(NAME, text)
    print(text)


if __name__ == "__main__":
    if sys.argv[1:] == ["--report"]:
        report(SolveCache(NAME, must_exist=True).data)
    else:
        skip = [a.split("=", 1)[1] for a in sys.argv[1:] if a.startswith("--skip=")]
        main(skip=tuple(x for a in skip for x in a.split(",")), resume="--resume" in sys.argv[1:])
