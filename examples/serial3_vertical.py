"""serial3_vertical (Khoukhi ch. 5-6 / annex A, with gravity behind gearboxes): the straight
line from q = (0, 30, 30) deg to the tip point (1.35, 1.30) m, the same move through the
three published passages, a closed circle (centre (-0.045, 0.75) m, radius 0.14 m) as via
points, and the third link +1.5 kg (open-loop replay and re-solve);
cycloid versus optimum in T and energy. The line is also solved with the torque bound at
both ends of every interval (``efforts="intervals"``); every solve reports its largest
torque between samples (``intersample_effort``) in examples/status/serial3_vertical.json.

Every solve is saved as it ends (:class:`run_all.SolveCache`), so a run cut short resumes
where it stopped.

Writes examples/figures/serial3_vertical_*.png and the "serial3_vertical" section of
examples/RESULTS.md. Run: python examples/serial3_vertical.py [--resume] (keep the solves a
run cut short saved) [--only=circle,...] (solve and print some parts, leaving RESULTS.md
and the status record as they are)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_all import (publish, FIGURES, SolveCache, setup, solve_with_restart, status_record, status_text,  # noqa: E402
                     table, timed_solve)

setup()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jtraj  # noqa: E402
from jtraj import plotting  # noqa: E402
from jtraj.initial_guess import cycloidal_time  # noqa: E402
from jtraj.robots.ik import ik  # noqa: E402
from jtraj.transcription import Transcription  # noqa: E402

# shared with the horizontal experiment: scenario constants, the cycloid sampled like the
# transcription, the normalised energy, the task-space problem constructor
from serial3 import EXTRA, N, P_GOAL, T_MAX, WEIGHTS, cycloid, energy_of, fmt, make_problem  # noqa: E402

NAME = "serial3_vertical"
PASSAGES = ((1.7, 0.9), (1.5, 1.0), (1.4, 1.2))
VIA_TOL = 1e-6  # m; the thesis does not print its passage tolerance
CIRCLE_C, CIRCLE_R = np.array([-0.045, 0.75]), 0.14
CIRCLE_VIA = 11  # via points every 30 deg, start = goal at angle 0
N_CIRCLE = 36  # three intervals per 30-degree arc
T_CIRCLE = 3.0  # s, initial guess duration of the circle


def status_of(sol):
    return jtraj.Status(int(sol.status))


def tip_error(robot, q, p):
    return float(np.linalg.norm(np.asarray(robot.forward_kinematics(q)) - np.asarray(p)))


def via_errors(problem, sol):
    """Distance of the tip from each via point at its assigned sample [m]."""
    robot = problem.robot
    return np.array([tip_error(robot, sol.q[k], vp.point) for vp, k in zip(problem.via_points, problem.via_samples())])


def dense_tip(robot, sol, per_interval=10):
    """Tip positions along the continuous trajectory (constant acceleration v_k on each
    interval, exactly the transcription's state recursion), (N * per_interval + 1, 2)."""
    q, qd, v, h = (np.asarray(a) for a in (sol.q, sol.qd, sol.v, sol.h))
    s = np.linspace(0.0, 1.0, per_interval, endpoint=False)
    pts = [q[k] + (s * h[k])[:, None] * qd[k] + 0.5 * ((s * h[k]) ** 2)[:, None] * v[k] for k in range(len(h))]
    qq = np.concatenate(pts + [q[-1:]], axis=0)
    return np.asarray(jax.vmap(robot.forward_kinematics)(jnp.asarray(qq)))


def torque_feasible_cycloid(problem, tau_max):
    """Smallest cycloid duration (on a 1 ms grid above the kinematic time) whose torques fit:
    with gravity and viscous damping the torques do not scale as 1/T^2, so search."""
    T_kin = float(cycloidal_time(problem))
    for T in np.arange(T_kin, N * float(problem.robot.limits.h_max) + 1e-9, 0.001):
        tau, h = cycloid(problem, T)
        peak = float(np.max(np.abs(tau) / tau_max))
        if peak <= 1.0:
            return T_kin, T, tau, h, peak
    return T_kin, None, None, None, None


def circle_guess(robot, q0, T, n_samples):
    """(v, h) of a cycloidal-in-angle traversal of the circle: IK at fine time steps (warm-
    chained from q0), accelerations by central differences at the interval midpoints."""
    fine = 20 * n_samples
    t = np.linspace(0.0, T, fine + 1)
    s = t / T - np.sin(2 * np.pi * t / T) / (2 * np.pi)
    ang = 2 * np.pi * s
    q, qs = np.asarray(q0), []
    for a in ang:
        res = ik(robot, CIRCLE_C + CIRCLE_R * np.array([np.cos(a), np.sin(a)]), q)
        q = np.asarray(res.q)
        qs.append(q)
    qs = np.array(qs)
    dt = T / fine
    qdd = np.gradient(np.gradient(qs, dt, axis=0), dt, axis=0)
    mid = (np.arange(n_samples) + 0.5) * T / n_samples
    v = np.stack([np.interp(mid, t, qdd[:, j]) for j in range(qs.shape[1])], axis=1)
    # committed to the device like a solver output, so that a warm re-solve from the result
    # hits the same compiled solver
    dev = jax.devices()[0]
    return jax.device_put(jnp.asarray(v), dev), jax.device_put(jnp.full((n_samples,), T / n_samples), dev)


#: the parts of the experiment (``--only`` runs some of them): the straight line with its
#: intervals solve and the +1.5 kg re-solve, the three passages, the circle
PARTS = ("line", "passages", "circle")


def main(resume=False, parts=PARTS):
    """Solve the ``parts`` (every try saved as it ends: ``resume`` keeps those a run cut
    short saved) and, when all parts ran, write the section, figures and status record;
    a run of some parts prints their rows and draws their figures only."""
    t_start = time.perf_counter()
    cache = SolveCache(NAME, resume=resume)
    if cache.resumed:
        print("resumed:", [k for k in cache.data if k not in ("seconds", "cpu")], flush=True)

    def cached(key, solve):
        if key not in cache:
            cache.put(key, solve())
        return cache[key]

    robot = jtraj.robots.get(NAME)
    tau_max = np.asarray(robot.limits.tau_max)
    rows, records = [], []

    # ---------------------------------------------------------------- straight line
    # The line carries the three passages as inactive via points (tolerance 100 m): the
    # number of via points is a static shape, so the line and the passage problem then
    # share one compilation of the solver (an inactive via point changes nothing else).
    task = make_problem(robot, WEIGHTS)
    inactive = [jtraj.ViaPoint(jnp.asarray(p), tol=100.0) for p in PASSAGES]
    line = jtraj.Problem(robot, task.q_start, task.q_goal, N=N, weights=WEIGHTS, T_max=T_MAX, via_points=inactive)
    p0 = np.asarray(robot.forward_kinematics(line.q_start))
    q_goal_deg = np.rad2deg(np.asarray(line.q_goal))
    T_kin, T_cyc, tau_c, h_c, peak_c = torque_feasible_cycloid(line, tau_max)
    tau_k, _ = cycloid(line, T_kin)
    peak_kin = float(np.max(np.abs(tau_k) / tau_max))
    E_cyc = energy_of(tau_c, h_c, tau_max)
    g_hold = np.abs(np.asarray(robot.inverse_dynamics(line.q_start, jnp.zeros(3), jnp.zeros(3)))) / tau_max

    if "line" in parts:
        (_, t_first), (sol, t_solve) = cached("line", lambda: (timed_solve(line), timed_solve(line)))
        T, E = float(sol.T), float(sol.energy)
        n_hmin = int(np.sum(np.asarray(sol.h) <= robot.limits.h_min + 1e-9))
        n_hmax = int(np.sum(np.asarray(sol.h) >= robot.limits.h_max - 1e-9))
        qd_sat = float(np.max(np.abs(np.asarray(sol.qd)) / np.asarray(robot.limits.qd_max)))
        v_sat = np.mean(np.max(np.abs(np.asarray(sol.v)) / np.asarray(robot.limits.qdd_max), axis=1) >= 0.99)
        tau_peak = np.max(np.abs(np.asarray(sol.tau)) / tau_max, axis=0)
        fig = plotting.plot_solution(task, sol, title=f"{NAME}, straight line: T = {T:.3f} s ({status_of(sol).name})")
        plotting.save(fig, str(FIGURES / f"{NAME}_line.png"))
        rows += [
            ("start tip [m]; goal configuration [deg]",
             f"({p0[0]:.3f}, {p0[1]:.3f}); ({', '.join(f'{x:.1f}' for x in q_goal_deg)})",
             "(1.95, 0.82) text, (1.92, 0.79) from Table 6.1; goal q not published",
             "forward kinematics of (0, 30, 30) deg; goal by the inertia-weighted pseudo-inverse IK, whose weighting "
             "includes the reflected rotor inertia here, so the goal configuration differs slightly from serial3's"),
            ("static holding torque at the start / tau_max (motor side)", ", ".join(f"{x:.2f}" for x in g_hold), "-",
             "gravity through a 1:20 gear: the published limits become consistent with a vertical plane "
             "(joint-side holding torques would be 6x the limits, see SCIENCE.md)"),
            ("line: cycloid T, kinematic limits only [s]", fmt(T_kin), "-",
             f"Khoukhi's formula T = max_j max(2|dq_j|/qd_max, sqrt(2 pi |dq_j|/qdd_max)); peak |tau|/tau_max = "
             f"{peak_kin:.2f}" + (", already admissible" if peak_kin <= 1 else ", not admissible")),
            ("line: cycloid T, torque-feasible [s]", "none" if T_cyc is None else fmt(T_cyc), "2",
             "smallest admissible cycloid (1 ms search; the gear makes the motor torques small, so the "
             "kinematic limits bind, not the torques); the thesis' 2 s cycloid is not reproducible from the text"),
            ("line: cycloid energy [s]", fmt(E_cyc), "not comparable",
             "sum_k h_k tau_k^T diag(1/tau_max^2) tau_k of motor-side torques"),
            ("line: optimum T [s] (all weights 1)", fmt(T), "1.175 (ch. 6) / 1.237 (annex A)",
             f"with motor-side normalised torques the energy term is small, so the optimum is nearly minimum-time "
             f"and kinematically limited (bang-bang in acceleration: h at h_min on {n_hmin}/{N}, at h_max on "
             f"{n_hmax}/{N} samples; peak |qd|/qd_max = {qd_sat:.2f}, {100 * v_sat:.0f} % of intervals with a "
             f"joint at |qdd| = qdd_max); the thesis' faster-than-2 s result holds, its exact T depends on unpublished U, Q"),
            ("line: optimum energy [s]", fmt(E), "not comparable",
             f"peak |tau|/tau_max per motor = {', '.join(f'{x:.2f}' for x in tau_peak)} (no torque bound active)"),
            ("line: T optimum / cycloid; energy optimum / cycloid", f"{T / T_cyc:.3f}; {E / E_cyc:.3f}",
             f"{1.175 / 2:.3f} / {1.237 / 2:.3f}; -",
             "the kinematic limits bound both: the bang-bang optimum is faster than the smooth cycloid and "
             "spends more acceleration energy"),
            ("line: solver status", status_text(sol, t_solve), "4 outer x 4 inner (annex A); 9-13 min Matlab",
             f"projected Newton on exact Hessians vs L-BFGS; first call {t_first:.0f} s including compilation"),
            ("line: max violation (relative), tip goal error [m]",
             f"{float(sol.max_violation['overall']):.1e}, {tip_error(robot, sol.q[-1], P_GOAL):.1e}", "-",
             "re-simulated from (v, h); goal imposed in joint space at the IK configuration"),
        ]

        records.append(status_record("line", sol, robot))
        line_i = jtraj.Problem(robot, task.q_start, task.q_goal, N=N, weights=WEIGHTS, T_max=T_MAX,
                               via_points=inactive, efforts="intervals")
        si, ti_first, ti_last, tries_i = solve_with_restart(line_i, init=(sol.v, sol.h), cache=cache,
                                                            key="line, intervals")
        records.append(status_record("line, efforts=intervals", si, robot))
        rows += [
            ("line: largest |tau|/tau_max between samples (bound at the samples / efforts=intervals)",
             f"{records[0]['effort_between_samples']:.3f} / {records[1]['effort_between_samples']:.3f}", "-",
             f"intersample_effort of the constant-acceleration motion; with the bound at both ends of every interval "
             f"T = {float(si.T):.4f} s ({status_text(si, ti_last)}, tries {' -> '.join(tries_i)}, warm-started; first "
             f"call {ti_first:.0f} s incl. compilation)"),
        ]

        # ------------------------------------------------------------ +1.5 kg on link 3
        heavy = jtraj.robots.get(NAME, masses=np.asarray(robot.masses) + np.array([0.0, 0.0, EXTRA]))
        # same start and goal configurations (make_problem would redo the inertia-weighted IK,
        # whose result depends on the masses, and so move the goal configuration)
        heavy_line = jtraj.Problem(heavy, line.q_start, line.q_goal, N=N, weights=WEIGHTS, T_max=T_MAX,
                                   via_points=inactive)
        q_ol, _ = Transcription("coupled").states(heavy_line, sol.tau, sol.h)
        ol_err = tip_error(heavy, q_ol[-1], P_GOAL)
        hs, _, t_heavy, htries = solve_with_restart(heavy_line, init=(sol.v, sol.h), cache=cache, key="+1.5 kg")
        records.append(status_record("+1.5 kg re-solve", hs, heavy))
        rows += [
            ("+1.5 kg on link 3: open-loop tip error [m]", f"{ol_err:.2e}", "< 1e-3",
             "nominal optimal motor torques replayed on the heavier arm without feedback; the gravity load of the "
             "extra mass is not compensated, so the tip drifts (the thesis' 1e-3 m is for its re-planned motion)"),
            ("+1.5 kg: re-solved T [s], status, tip error [m]",
             f"{float(hs.T):.4f}, {status_text(hs, t_heavy)}, {tip_error(heavy, hs.q[-1], P_GOAL):.1e}",
             "goal within 1e-3 m", "warm-started from the nominal optimum (tries: " + " -> ".join(htries) + "); goal met "
             "to round-off"),
        ]
        rows.append(("+1.5 kg: T change, cost change (re-solve)",
                     f"{float(hs.T) - T:+.4f} s, {float(hs.cost) - float(sol.cost):+.5f}", "-",
                     "the kinematically limited optimum does not depend on the mass (only the small energy term "
                     "does); derivatives by implicit differentiation are in the serial3 section (here dT*/dm = 0 "
                     "and the extra compilation is not worth it)"))

    # ---------------------------------------------------------------- three passages
    if "passages" in parts:
        passages = jtraj.Problem(robot, line.q_start, line.q_goal, N=N, weights=WEIGHTS, T_max=T_MAX,
                                 via_points=[jtraj.ViaPoint(jnp.asarray(p), tol=VIA_TOL) for p in PASSAGES])
        ps, t_pfirst, t_psolve, ptries = solve_with_restart(passages, cache=cache, key="passages")
        verr = via_errors(passages, ps)
        records.append(status_record("passages", ps, robot))
        fig = plotting.plot_solution(passages, ps, title=f"{NAME}, three passages: T = {float(ps.T):.3f} s "
                                                         f"({status_of(ps).name})")
        plotting.save(fig, str(FIGURES / f"{NAME}_passages.png"))
        rows += [
            ("passages (1.7, 0.9), (1.5, 1.0), (1.4, 1.2): T [s], energy [s]",
             f"{float(ps.T):.4f}, {float(ps.energy):.4g}", "not published",
             f"via points at samples {passages.via_samples()} (evenly split; the periods stay free), "
             f"tolerance {VIA_TOL:g} m; T grows by {100 * (float(ps.T) / T - 1):.0f} % over the free straight line"),
            ("passages: status", status_text(ps, t_psolve) + "; tries: " + " -> ".join(ptries), "-",
             f"default settings from the cycloidal guess, then (if not certified) one re-solve warm-started from "
             f"the result; first call {t_pfirst:.0f} s (shares the line's compilation)"),
            ("passages: distance to each via point [m]", ", ".join(f"{e:.1e}" for e in verr), "not published",
             "met within the imposed tolerance (re-simulated)"),
        ]

    # ---------------------------------------------------------------- circle
    if "circle" in parts:
        q_c0 = jnp.asarray(ik(robot, CIRCLE_C + np.array([CIRCLE_R, 0.0]), line.q_start).q)
        angles = np.deg2rad(np.arange(1, CIRCLE_VIA + 1) * 360.0 / (CIRCLE_VIA + 1))
        via = [jtraj.ViaPoint(jnp.asarray(CIRCLE_C + CIRCLE_R * np.array([np.cos(a), np.sin(a)])), tol=VIA_TOL)
               for a in angles]
        circle = jtraj.Problem(robot, q_c0, q_c0, N=N_CIRCLE, weights=WEIGHTS, T_max=None, via_points=via)
        guess = circle_guess(robot, q_c0, T_CIRCLE, N_CIRCLE)
        # the default solver from the guess: its interior-point method stops after a few
        # iterations, its Newton matrix positive definite at no shift, and reports the problem
        # likely infeasible; the AL method alone finds a feasible point, from which the
        # default solver certifies the optimum
        cold, t_cold = cached("circle, default solver from the guess", lambda: timed_solve(circle, init=guess))
        records.append(status_record("circle, default solver from the guess", cold, robot))
        al, t_cfirst = cached("circle, AL method from the guess",
                              lambda: timed_solve(circle, init=guess, solver=jtraj.AugmentedLagrangian()))
        records.append(status_record("circle, AL method from the guess", al, robot))
        cs, _, t_csolve, ctries = solve_with_restart(circle, init=(al.v, al.h), cache=cache, key="circle")
        cerr = via_errors(circle, cs)
        records.append(status_record("circle, default solver from the AL point", cs, robot))
        p_dense = dense_tip(robot, cs)
        radial = np.abs(np.linalg.norm(p_dense - CIRCLE_C, axis=1) - CIRCLE_R)
        fig = plotting.plot_solution(circle, cs, guess=False,
                                     title=f"{NAME}, circle by {CIRCLE_VIA} via points: T = {float(cs.T):.3f} s "
                                           f"({status_of(cs).name})")
        ax = fig.axes[0]
        th = np.linspace(0, 2 * np.pi, 200)
        ax.plot(CIRCLE_C[0] + CIRCLE_R * np.cos(th), CIRCLE_C[1] + CIRCLE_R * np.sin(th), ":", color="C2", lw=1,
                label="circle")
        ax.plot(p_dense[:, 0], p_dense[:, 1], "-", color="C1", lw=0.8, label="tip between samples")
        ax.legend(fontsize=7)
        plotting.save(fig, str(FIGURES / f"{NAME}_circle.png"))
        rows += [
            ("circle (-0.045, 0.75), r = 0.14: T [s], energy [s]", f"{float(cs.T):.4f}, {float(cs.energy):.4g}",
             "not published",
             f"closed circle from and back to (0.095, 0.75) m at rest, imposed as {CIRCLE_VIA} via points every "
             f"30 deg (N = {N_CIRCLE}, {N_CIRCLE // (CIRCLE_VIA + 1)} intervals per arc, tolerance {VIA_TOL:g} m), not as a continuous path "
             "constraint; no T_max"),
            ("circle: status", status_text(cs, t_csolve) + "; tries: " + " -> ".join(ctries), "-",
             f"the default cycloidal guess is degenerate for start = goal (zero motion), so the solve starts from "
             f"a cycloidal-in-angle traversal of {T_CIRCLE:g} s obtained by IK. From it the default solver ends "
             f"{status_text(cold, t_cold)} with via points missed by up to "
             f"{np.max(via_errors(circle, cold)):.1e} m: its interior-point method finds its Newton matrix positive "
             f"definite at no shift and stops at its first barrier parameter, a verdict about the method, not the "
             f"problem. The AL method alone from the same guess ends {status_text(al, t_cfirst)} with every via point "
             f"within {np.max(via_errors(circle, al)):.1e} m (worst violation "
             f"{float(al.max_violation['overall']):.1e}, T = {float(al.T):.4f} s); the default solver warm-started "
             f"from that point gives this row (then one warm re-solve if not certified)"),
            ("circle: via point errors (max) [m]; radial deviation at samples / between samples (max) [m]",
             f"{np.max(cerr):.1e}; {np.max(radial[::10]):.1e} / {np.max(radial):.1e}", "not published",
             ("via points met; between them the tip is free (the other samples and the continuous motion cut the "
              "arcs slightly), so the circle is approximated by a closed curve through the 12 points"
              if np.max(cerr) <= VIA_TOL + 1e-6 else
              f"via points missed by up to {np.max(cerr):.1e} m: the solve ended {status_of(cs).name}, so this is not "
              f"a trajectory through the circle's points")),
        ]

    header = ("quantity", "jtraj", "published", "explanation")
    if tuple(parts) != PARTS:
        print(table(rows, header=header), flush=True)
        print(f"parts {', '.join(parts)} only: RESULTS.md and the status record are left as they were; "
              f"{cache.time_text()}", flush=True)
        return
    text = (f"## serial3_vertical: serial3 in a vertical plane behind 1:20 gears\n\n"
            f"Robot `serial3_vertical` (Table 6.1 arm, g = 9.81 m/s^2, rotary gears of ratio 20 on every joint "
            f"with rotor inertia 1e-3 kg m^2 and damping 1e-3 N m s/rad; |tau| <= 40, 25, 20 N m read as "
            f"motor-side limits; |qd| <= 2 rad/s, |qdd| <= 3 rad/s^2, h in [0.005, 0.1] s), all weights 1 "
            f"(time = energy = kinetic = 1, energy on motor torques normalised by tau_max), decoupled "
            f"transcription, default solver options unless stated. Line and passages: N = {N}, T_max = {T_MAX} s. "
            f"Figures: `figures/{NAME}_line.png`, `figures/{NAME}_passages.png`, `figures/{NAME}_circle.png`."
            f"\n\n" + table(rows, header=header))
    publish(NAME, text, records, t_start, cache=cache)


if __name__ == "__main__":
    only = [a.split("=", 1)[1].split(",") for a in sys.argv[1:] if a.startswith("--only=")]
    chosen = tuple(p for p in PARTS if not only or p in only[0])
    if only and set(only[0]) - set(PARTS):
        raise SystemExit(f"--only takes some of {', '.join(PARTS)}, got {','.join(only[0])}")
    main(resume="--resume" in sys.argv[1:], parts=chosen)
